"""Synthetic two-view scenes with known relative pose, for tests and validation (no OpenCV).

Randomness only through an explicit :class:`numpy.random.Generator`.

>>> import numpy as np
>>> s = make_two_view_scene(np.random.default_rng(0), motion="sideways", n_points=50)
>>> s.uv_i.shape, s.uv_j.shape
((50, 2), (50, 2))
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from ..geometry.rotations import rotvec_exp

Array = NDArray[np.float64]

__all__ = ["TwoViewScene", "make_two_view_scene", "MOTIONS"]

MOTIONS = ("sideways", "forward", "general", "rotation", "planar")


@dataclass(frozen=True)
class TwoViewScene:
    """Two calibrated views of a random point cloud.

    Attributes
    ----------
    camera : PinholeCamera
    R_ij : (3, 3) orientation of camera *j* in frame *i* (``R_wi.T @ R_wj``).
    t_ij : (3,) unit direction of camera *j*'s centre in frame *i* (arbitrary unit vector
        when ``baseline == 0``).
    baseline : float
        Distance between the centres, scene units.
    X_i : (N, 3) points in frame *i*.
    uv_i, uv_j : (N, 2) noise-free pixels in images *i* and *j* (inside both images).
    """

    camera: PinholeCamera
    R_ij: Array
    t_ij: Array
    baseline: float
    X_i: Array
    uv_i: Array
    uv_j: Array

    def noisy(self, rng: np.random.Generator, sigma_px: float) -> tuple[Array, Array]:
        """Pixels with independent Gaussian noise of ``sigma_px`` per coordinate."""
        return (
            self.uv_i + sigma_px * rng.standard_normal(self.uv_i.shape),
            self.uv_j + sigma_px * rng.standard_normal(self.uv_j.shape),
        )


def make_two_view_scene(
    rng: np.random.Generator,
    motion: str = "general",
    n_points: int = 100,
    camera: PinholeCamera | None = None,
    depth: tuple[float, float] = (4.0, 12.0),
    baseline: float = 1.0,
    rotation_deg: float = 5.0,
) -> TwoViewScene:
    """Random scene seen from two cameras.

    Parameters
    ----------
    rng : numpy.random.Generator
    motion : {"sideways", "forward", "general", "rotation", "planar"}
        Direction of the baseline in frame *i*: along ``x``, along ``z``, random; zero
        baseline (pure rotation); or a general motion looking at a tilted plane.
    n_points : int
        Number of points returned (all visible in both views, in front of both cameras).
    camera : PinholeCamera, optional
        Default 640x480 with a 500 px focal length.
    depth : (float, float)
        Depth range of the points in frame *i*, scene units.
    baseline : float
        Distance between the camera centres (ignored for ``"rotation"``).
    rotation_deg : float
        Magnitude of the random relative rotation, degrees.

    Returns
    -------
    TwoViewScene
    """
    if motion not in MOTIONS:
        raise ValueError(f"motion must be one of {MOTIONS}, got {motion!r}")
    cam = camera or PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)
    axis = rng.standard_normal(3)
    R = rotvec_exp(np.radians(rotation_deg) * axis / np.linalg.norm(axis))
    direction = {
        "sideways": np.array([1.0, 0.0, 0.0]),
        "forward": np.array([0.0, 0.0, 1.0]),
    }.get(motion)
    if direction is None:
        direction = rng.standard_normal(3)
    t = direction / np.linalg.norm(direction)
    b = 0.0 if motion == "rotation" else float(baseline)
    c_j = b * t
    pts_i, pts_j, X = [], [], []
    count = 0
    while count < n_points:
        m = 4 * n_points
        uv = rng.uniform([0, 0], [cam.width - 1, cam.height - 1], (m, 2))
        ray = np.concatenate([cam.normalized(uv), np.ones((m, 1))], 1)
        if motion == "planar":
            # plane through (0, 0, mean depth) with a 30 degree tilt about the x axis
            n = np.array([0.0, np.sin(np.radians(30)), np.cos(np.radians(30))])
            z = np.mean(depth) * n[2] / (ray @ n)
        else:
            z = rng.uniform(depth[0], depth[1], m)
        Xi = ray * z[:, None]
        Xj = (Xi - c_j) @ R  # R.T @ (X - c) for each row
        ok = (z > 0) & (Xj[:, 2] > 0.1)
        uvj = cam.project(Xj)
        ok &= cam.in_image(uvj, margin=1.0)
        X.append(Xi[ok])
        pts_i.append(uv[ok])
        pts_j.append(uvj[ok])
        count += int(ok.sum())
    X_i = np.concatenate(X)[:n_points]
    return TwoViewScene(
        camera=cam,
        R_ij=R,
        t_ij=t,
        baseline=b,
        X_i=X_i,
        uv_i=np.concatenate(pts_i)[:n_points],
        uv_j=np.concatenate(pts_j)[:n_points],
    )
