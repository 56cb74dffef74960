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


def refine_points(
    X: Array, feature: NDArray[np.int64], p: Array, q: Array, uv: Array, camera: PinholeCamera,
    iterations: int = 5,
) -> tuple[Array, NDArray[np.bool_]]:
    """Refine points on every view of them, the poses held fixed (Gauss-Newton on pixels).

    A new feature enters the filter with every observation it has, and the filter keeps
    the Jacobians of all of them at its first estimate, so that estimate should be the
    best the observations give for the current poses, not a two-view midpoint.

    Parameters
    ----------
    X : (F, 3) initial points (e.g. :func:`triangulate`).
    feature : (N,) index into ``X`` of each observation.
    p, q : (N, 3), (N, 4) the observing poses (centres, ``q_wc``).
    uv : (N, 2) measured pixels.
    camera : PinholeCamera
    iterations : int
        Gauss-Newton iterations (each one damped to keep the cost from rising).

    Returns
    -------
    X : (F, 3) refined points (the initial one where refinement did not lower the cost).
    ok : (F,) bool, every view sees the refined point in front of it.
    """
    from ..geometry.models import feature_model

    X = np.array(X, float).reshape(-1, 3)
    F = len(X)
    feature = np.asarray(feature, np.int64)

    def residual(Xs: Array) -> tuple[Array, Array, Array]:
        h, _, Jf, z = feature_model(p, q, Xs[feature], camera.fx, camera.fy, camera.cx, camera.cy)
        r = uv - h
        cost = np.zeros(F)
        np.add.at(cost, feature, np.where(z > 0, np.sum(r**2, 1), 1e12))
        return r, Jf, cost

    r, Jf, cost = residual(X)
    for _ in range(iterations):
        A = np.zeros((F, 3, 3))
        b = np.zeros((F, 3))
        np.add.at(A, feature, np.einsum("nki,nkj->nij", Jf, Jf))
        np.add.at(b, feature, np.einsum("nki,nk->ni", Jf, r))
        A += 1e-9 * np.trace(A, axis1=1, axis2=2)[:, None, None] * np.eye(3) + 1e-12 * np.eye(3)
        step = np.linalg.solve(A, b[..., None])[..., 0]
        Xn = X + step
        rn, Jn, cn = residual(Xn)
        better = np.all(np.isfinite(Xn), 1) & (cn < cost)
        X = np.where(better[:, None], Xn, X)
        cost = np.where(better, cn, cost)
        if not better.any():
            break
        r, Jf, _ = residual(X)
    _, _, _, z = feature_model(p, q, X[feature], camera.fx, camera.fy, camera.cx, camera.cy)
    front = np.ones(F, bool)
    np.logical_and.at(front, feature, z > 0)
    return X, front
