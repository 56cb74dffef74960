"""Synthetic scenes with known answers, at the measurement level (pure NumPy).

Scenes are expressed in the first camera's frame (pose 0 is the identity), which is the
filter's world frame, so estimates compare with the truth directly once the scale prior
is set to the true distance between the first two poses.

* :func:`corridor_scene`: a camera moving forward along a corridor, features on its walls
  entering and leaving view (no loop) — the back-end benchmark's exploration.
* :func:`orbit_scene`: a camera circling a cloud of points, looking inward (sideways
  motion, the case where the paper's ``ZT`` is singular).
* :func:`simulate`: ``Zm`` with pixel noise and ``ZR``/``ZT`` with a known joint covariance.
* Algorithm 1 on these measurements is the system's own: :class:`eifslam.system.slam.Slam`
  fed by :class:`eifslam.sim.frontend.SyntheticFrontEnd`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from ..geometry.rotations import (
    quat_conjugate,
    quat_exp,
    quat_multiply,
    quat_normalize,
    quat_to_rotmat,
    rotmat_to_quat,
    tangent_basis,
)
from ..estimation.measurements import FeatureObservations, RelativePose

Array = NDArray[np.float64]


@dataclass
class SyntheticScene:
    """Ground truth of a synthetic scene (first camera = world frame).

    Attributes
    ----------
    camera : PinholeCamera
    positions : (K, 3) camera centres.
    quats : (K, 4) orientations ``q_wc``.
    points : (M, 3) world points.
    """

    camera: PinholeCamera
    positions: Array
    quats: Array
    points: Array

    def visible(self, k: int, max_range: float = np.inf, margin: float = 2.0) -> NDArray[np.bool_]:
        """Mask ``(M,)`` of points in view of camera *k*."""
        Xc = (self.points - self.positions[k]) @ quat_to_rotmat(self.quats[k])
        z = Xc[:, 2]
        uv = self.camera.project(np.where(z[:, None] > 1e-9, Xc, 1.0))
        return (z > 0.1) & (np.linalg.norm(Xc, axis=1) < max_range) & self.camera.in_image(uv, margin)

    def project(self, k: int, idx: NDArray[np.int64]) -> Array:
        """Noise-free pixels ``(N, 2)`` of points ``idx`` in camera *k*."""
        Xc = (self.points[idx] - self.positions[k]) @ quat_to_rotmat(self.quats[k])
        return self.camera.project(Xc)


def _to_first_frame(P: Array, Q: Array, X: Array) -> tuple[Array, Array, Array]:
    R0 = quat_to_rotmat(Q[0])
    q0c = quat_conjugate(Q[0])
    return (P - P[0]) @ R0, quat_normalize(quat_multiply(q0c, Q)), (X - P[0]) @ R0


def default_camera() -> PinholeCamera:
    """A 640x480 camera with a 60 degree horizontal field of view."""
    f = 320.0 / np.tan(np.radians(30.0))
    return PinholeCamera(f, f, 319.5, 239.5, 640, 480)


def corridor_scene(
    n_frames: int, rng: np.random.Generator, step: float = 0.5, points_per_metre: float = 40.0,
    width: float = 4.0, height: float = 3.0, camera: PinholeCamera | None = None,
) -> SyntheticScene:
    """A camera walking down a corridor along +z with a gentle weave.

    Points lie on the four walls, ``points_per_metre`` per metre of corridor.
    """
    camera = camera or default_camera()
    k = np.arange(n_frames)
    z = k * step
    P = np.stack([0.3 * np.sin(0.2 * k), 0.1 * np.sin(0.13 * k), z], 1)
    yaw = 0.15 * np.sin(0.1 * k + 0.5)
    Q = np.stack([np.cos(yaw / 2), 0 * yaw, np.sin(yaw / 2), 0 * yaw], 1)
    length = z[-1] + 15.0
    n = int(points_per_metre * length)
    s = rng.uniform(-2.0, length, n)
    wall = rng.integers(0, 4, n)
    a = rng.uniform(-0.5, 0.5, n)
    X = np.zeros((n, 3))
    X[:, 2] = s
    X[:, 0] = np.where(wall < 2, np.where(wall == 0, -1, 1) * width / 2, a * width)
    X[:, 1] = np.where(wall >= 2, np.where(wall == 2, -1, 1) * height / 2, a * height)
    return SyntheticScene(camera, *_to_first_frame(P, Q, X))


def orbit_scene(
    n_frames: int, rng: np.random.Generator, radius: float = 4.0, arc_deg: float = 120.0,
    n_points: int = 400, camera: PinholeCamera | None = None,
) -> SyntheticScene:
    """A camera moving on a circle round a point cloud, looking at its centre."""
    camera = camera or default_camera()
    ang = np.radians(np.linspace(0.0, arc_deg, n_frames))
    P = np.stack([radius * np.sin(ang), -0.5 * np.ones_like(ang), -radius * np.cos(ang)], 1)
    Rs = []
    for p in P:
        zc = -p / np.linalg.norm(p)
        xc = np.cross([0.0, 1.0, 0.0], zc)
        xc /= np.linalg.norm(xc)
        Rs.append(np.stack([xc, np.cross(zc, xc), zc], 1))
    Q = rotmat_to_quat(np.stack(Rs))
    X = rng.uniform(-1.2, 1.2, (n_points, 3))
    return SyntheticScene(camera, *_to_first_frame(P, Q, X))


@dataclass
class SyntheticMeasurements:
    """Simulated measurements.

    Attributes
    ----------
    frames : list of FeatureObservations, one per frame (``Zm`` of visible map points).
    relative : list of RelativePose, ``relative[k-1]`` from frame ``k-1`` to ``k``.
    rel_cov : (5, 5) covariance the relative-pose noise was drawn from.
    """

    frames: list[FeatureObservations]
    relative: list[RelativePose]
    rel_cov: Array = field(default_factory=lambda: np.eye(5))


def true_relative(scene: SyntheticScene, i: int, j: int) -> tuple[Array, Array]:
    """True ``(q_ij, t_ij unit)`` between frames *i* and *j*."""
    q = quat_normalize(quat_multiply(quat_conjugate(scene.quats[i]), scene.quats[j]))
    t = quat_to_rotmat(scene.quats[i]).T @ (scene.positions[j] - scene.positions[i])
    return q, t / np.linalg.norm(t)


def relative_covariance(sigma_rot: float = 1e-3, sigma_dir: float = 2e-3) -> Array:
    """The ``(5, 5)`` covariance of simulated ``[dtheta, dt]`` relative-pose errors.

    Standard deviations ``sigma_rot`` (radians, rotation vector of ``ZR``) and
    ``sigma_dir`` (unit-vector tangent of ``ZT``), with correlation between rotation and
    direction: rotation about y couples with the sideways direction error (0.5), rotation
    about x with the vertical one (-0.4), as a five-point solution's errors do.
    """
    sd = np.array([sigma_rot] * 3 + [sigma_dir] * 2)
    C = np.eye(5)
    C[1, 3] = C[3, 1] = 0.5
    C[0, 4] = C[4, 0] = -0.4
    return C * np.outer(sd, sd)


def _rng(seed: int, tag: int, *index: int) -> np.random.Generator:
    """A generator for one draw of the noise model, keyed by ``(seed, tag, *index)``.

    The key ends in a non-zero sentinel: ``SeedSequence`` ignores trailing zeros, so
    ``(seed, 0)`` would otherwise draw what ``default_rng(seed)`` (often the scene's own
    generator) draws.
    """
    return np.random.default_rng([int(seed), int(tag), *(int(i) for i in index), 0x5EED])


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise of a synthetic scene, a deterministic function of its seed.

    The pixel noise of point ``m`` in frame ``k`` is row ``m`` of an ``(M, 2)`` standard
    normal draw keyed by ``(seed, 1, k)``, times ``sigma_px``; the error of the relative
    pose from frame ``i`` to frame ``j`` is ``L e`` with ``L L^T = rel_cov`` and ``e`` a
    standard normal 5-vector keyed by ``(seed, 2, i, j)``. Every measurement is therefore
    the same however often, and in whatever order, it is asked for; :func:`simulate` and
    :class:`eifslam.sim.frontend.SyntheticFrontEnd` built with the same seed measure the
    same values.

    Attributes
    ----------
    seed : int
    sigma_px : float
        Pixel noise standard deviation of ``Zm``, pixels (also the ``sigma_px`` the
        measurements carry when ``noise`` is False).
    rel_cov : (5, 5) covariance of ``[dtheta, dt]`` (see :func:`relative_covariance`).
    noise : bool
        False: every measurement is exact (the covariances stay as above).
    """

    seed: int
    sigma_px: float = 1.0
    rel_cov: Array = field(default_factory=relative_covariance)
    noise: bool = True

    def pixels(self, scene: SyntheticScene, k: int, idx: NDArray[np.int64]) -> Array:
        """Measured pixels ``(N, 2)`` of scene points ``idx`` (N,) in frame *k*."""
        uv = scene.project(k, idx)
        if self.noise:
            e = _rng(self.seed, 1, k).standard_normal((len(scene.points), 2))
            uv = uv + self.sigma_px * e[idx]
        return uv

    def relative(self, scene: SyntheticScene, i: int, j: int) -> RelativePose:
        """Measured ``ZR``/``ZT`` from frame *i* to frame *j* (i != j), with ``rel_cov``."""
        q, t = true_relative(scene, i, j)
        if self.noise:
            e = np.linalg.cholesky(self.rel_cov) @ _rng(self.seed, 2, i, j).standard_normal(5)
            q = quat_multiply(q, quat_exp(-e[:3]))
            t = t - tangent_basis(t) @ e[3:]
        return RelativePose(int(i), int(j), q, t, self.rel_cov)


def simulate(
    scene: SyntheticScene, rng: np.random.Generator | int, sigma_px: float = 1.0,
    rel_sigma_rot: float = 1e-3, rel_sigma_dir: float = 2e-3, max_range: float = 12.0,
    noise: bool = True,
) -> SyntheticMeasurements:
    """Simulate ``Zm`` for every visible point and ``ZR``/``ZT`` between consecutive frames.

    The noise is :class:`NoiseModel`'s, seeded by ``rng`` (an int, or one integer drawn
    from a generator); with ``noise=False`` everything is exact.
    """
    seed = rng if isinstance(rng, (int, np.integer)) else int(rng.integers(2**63))
    model = NoiseModel(int(seed), sigma_px, relative_covariance(rel_sigma_rot, rel_sigma_dir), noise)
    K = len(scene.positions)
    frames = []
    for k in range(K):
        idx = np.flatnonzero(scene.visible(k, max_range))
        frames.append(FeatureObservations.make(np.full(len(idx), k), idx, model.pixels(scene, k, idx), sigma_px))
    rel = [model.relative(scene, k - 1, k) for k in range(1, K)]
    return SyntheticMeasurements(frames, rel, model.rel_cov)
