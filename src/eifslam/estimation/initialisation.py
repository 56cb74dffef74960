"""Initial guesses for new poses and features (paper III-C, Algorithm 1 steps 2-3; pure NumPy).

* A new pose comes from one relative pose (rotation and translation direction) to a known
  pose and measurements of known map features, which fix the length of the step.
* A new feature comes from two poses by linear triangulation (midpoint of the closest
  points of the two rays), with a parallax check.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from ..geometry.rotations import quat_multiply, quat_normalize, quat_to_rotmat
from .measurements import RelativePose

Array = NDArray[np.float64]


def pose_from_relative(
    p_i: Array,
    q_i: Array,
    rp: RelativePose,
    camera: PinholeCamera,
    X_known: Array,
    uv_known: Array,
    default_step: float | None = None,
) -> tuple[Array, Array, float] | None:
    """Initial guess of pose *j* from a relative pose to known pose *i*.

    The orientation is ``q_j = q_i ⊗ q_ij``; the centre is ``p_i + s R_wi t_ij``. The step
    ``s`` is the median over known features of the least-squares solution of
    ``p_i + s R_wi t_ij + lam R_wj b = X`` (``b`` the feature's bearing in camera *j*).

    Parameters
    ----------
    p_i, q_i : (3,), (4,) known pose *i*.
    rp : RelativePose from *i* to *j*.
    camera : PinholeCamera
    X_known : (M, 3) known map features seen from *j*, world frame.
    uv_known : (M, 2) their undistorted pixels in image *j*.
    default_step : float or None
        Step to use when no known feature gives a usable answer; ``None`` returns None.

    Returns
    -------
    (p_j, q_j, s) or None when the step cannot be determined.
    """
    q_j = quat_normalize(quat_multiply(q_i, rp.q_ij))
    R_i, R_j = quat_to_rotmat(q_i), quat_to_rotmat(q_j)
    d = R_i @ rp.t_ij
    s = None
    if len(X_known):
        b = (R_j @ camera.bearing(uv_known).T).T  # (M, 3) world-frame bearings from j
        # per feature: [d, b] [s, lam]^T = X - p_i, 2 unknowns, 3 equations
        r = X_known - p_i
        dd = d @ d
        db = b @ d
        bb = np.sum(b * b, 1)
        dr = r @ d
        br = np.sum(b * r, 1)
        det = dd * bb - db**2
        ok = det > 1e-6  # rays not parallel to the step
        s_all = (bb * dr - db * br)[ok] / det[ok]
        lam = (dd * br - db * dr)[ok] / det[ok]
        s_all = s_all[(lam > 0) & np.isfinite(s_all) & (s_all > 0)]
        if len(s_all):
            s = float(np.median(s_all))
    if s is None:
        if default_step is None:
            return None
        s = float(default_step)
    return p_i + s * d, q_j, s


def triangulate(
    p_a: Array, q_a: Array, uv_a: Array, p_b: Array, q_b: Array, uv_b: Array, camera: PinholeCamera
) -> tuple[Array, Array, Array]:
    """Triangulate points seen from two poses (midpoint of the closest ray points).

    Parameters
    ----------
    p_a, q_a, p_b, q_b : pose centres (3,) and orientations ``q_wc`` (4,).
    uv_a, uv_b : (N, 2) undistorted pixels in the two images.

    Returns
    -------
    X : (N, 3) world points.
    parallax_deg : (N,) angle between the two rays at the point.
    ok : (N,) bool, point in front of both cameras with non-degenerate rays.
    """
    ba = (quat_to_rotmat(q_a) @ camera.bearing(uv_a).T).T
    bb = (quat_to_rotmat(q_b) @ camera.bearing(uv_b).T).T
    w = p_a - p_b
    c = np.sum(ba * bb, 1)
    d = ba @ w
    e = bb @ w
    den = 1.0 - c**2
    safe = np.where(den > 1e-12, den, 1.0)
    la = (c * e - d) / safe
    lb = (e - c * d) / safe
    X = 0.5 * ((p_a + la[:, None] * ba) + (p_b + lb[:, None] * bb))
    parallax = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    ok = (den > 1e-12) & (la > 0) & (lb > 0) & np.all(np.isfinite(X), 1)
    return X, parallax, ok
