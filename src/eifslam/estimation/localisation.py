"""Pose of one image from known map features (pure NumPy).

Used when an image has no relative pose with enough baseline to a known pose (a camera
that only rotates, or a 30 Hz camera that has barely moved): the pose is then determined by
the ``Zm`` of known map features alone, which the EIF fuses as usual. This module only
provides the initial guess (a few robust Gauss-Newton steps on the reprojection error of
the pose alone), so that the EIF linearises at a good point.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray

from ..geometry import models
from ..geometry.camera import PinholeCamera
from ..geometry.rotations import quat_normalize

Array = NDArray[np.float64]

#: χ²₂ 99.9% bound, ``-2 ln 0.001``: a 2-D residual beyond ``sqrt`` of this many standard
#: deviations is taken for a wrong correspondence.
_CHI2_2_999 = float(-2.0 * np.log(1e-3))
#: A residual beyond this many times the median residual is beyond that bound at the
#: residuals' robust scale: for ``|r|² ~ σ² χ²₂`` the median of ``|r|²`` is ``2 ln 2 σ²``
#: (about 3.16).
_CUT_PER_MEDIAN = float(np.sqrt(_CHI2_2_999 / (2.0 * np.log(2.0))))


def localise_pose(
    camera: PinholeCamera, p0: Array, q0: Array, X: Array, uv: Array, iterations: int = 8,
    huber_px: float = 2.0, min_inliers: int = 12, inlier_px: float = 4.0, tol_px2: float = 1e-4,
    X_cov: Array | Callable[[NDArray[np.int64]], Array] | None = None,
) -> tuple[Array, Array, NDArray[np.bool_]] | None:
    """Refine a pose guess from 2D-3D correspondences.

    Parameters
    ----------
    camera : PinholeCamera
    p0, q0 : (3,), (4,) initial camera centre and ``q_wc``.
    X : (N, 3) world points; uv : (N, 2) their undistorted pixels.
    iterations : at most this many Gauss-Newton steps with Huber weights.
    huber_px, inlier_px : robust-weight threshold and final inlier threshold, pixels.
    min_inliers : fewer inliers than this is a failure.
    tol_px2 : stop once a step's predicted decrease of the weighted squared reprojection
        error, ``b . d`` (px²), is below this: at 1 px noise the step is then a hundredth
        of a standard deviation of the pose (its Mahalanobis length is ``sqrt(b . d) / sigma``).
    X_cov : (N, 3, 3) array or callable, optional
        Covariances of ``X`` (state units squared; NaN where unknown), for the cut in the
        notes; or ``X_cov(idx (m,)) -> (m, 3, 3)``, asked only for the points that the
        other bounds would cut (the filter's marginals cost a few milliseconds a frame).

    Returns
    -------
    (p, q, inliers) or None when the pose is not determined.

    Notes
    -----
    At each step a correspondence gets no weight when its residual exceeds the largest of
    ``inlier_px``, the χ²₂ 99.9% bound at the residuals' robust scale (3.16 × their
    median) and the same bound for the point's own uncertainty projected into the image
    (``3.72 sqrt(λ_max(J_X P_X J_Xᵀ))``, with ``X_cov``). Huber's weight alone bounds a wrong
    correspondence's pull only to ``huber_px`` times its Jacobian, and wrong matches on
    a repeated facade pull the same way: on strecha-castle-p30 a few dozen of them, 40 to
    1,400 px off, dragged the pose from a start the map fitted well (median residual
    0.43 px) to one it fitted badly (1.34 px). A correct observation of a point the map
    has not fixed yet may be far off too; the third bound keeps it.
    """
    if len(X) < min_inliers:
        return None
    p, q = np.asarray(p0, float).copy(), quat_normalize(np.asarray(q0, float))
    c = camera
    cov = _LazyCovariances(X_cov, len(X))
    for _ in range(iterations):
        h, Jp, Jf, z = models.feature_model_one_pose(p, q, X, c.fx, c.fy, c.cx, c.cy)
        r = uv - h
        e = np.linalg.norm(r, axis=1)
        front = z > 0
        cut = max(inlier_px, _CUT_PER_MEDIAN * float(np.median(e[front]))) if front.any() else inlier_px
        keep = e <= cut
        if X_cov is not None and not keep.all():  # beyond the pixel bounds: within the point's own?
            far = np.flatnonzero(~keep)
            S = np.einsum("nij,njk,nlk->nil", Jf[far], cov.get(far), Jf[far])
            keep[far] = e[far] <= np.sqrt(_CHI2_2_999 * np.maximum(np.linalg.eigvalsh(S)[:, 1], 0.0))
        w = np.where(e <= huber_px, 1.0, huber_px / np.maximum(e, 1e-12)) * front * keep
        Jw = (Jp * w[:, None, None]).reshape(-1, 7)
        A = Jw.T @ Jp.reshape(-1, 7)
        b = Jw.T @ r.ravel()
        A[3:, 3:] += 1e6 * np.outer(q, q)  # fix the quaternion's norm direction
        A += 1e-9 * np.trace(A) * np.eye(7)
        try:
            d = np.linalg.solve(A, b)
        except np.linalg.LinAlgError:
            return None
        if not np.all(np.isfinite(d)):
            return None
        p, q = p + d[:3], quat_normalize(q + d[3:])
        if float(b @ d) < tol_px2:
            break
    h, _, _, z = models.feature_model_one_pose(p, q, X, c.fx, c.fy, c.cx, c.cy)
    inl = (z > 0) & (np.linalg.norm(uv - h, axis=1) < inlier_px)
    if inl.sum() < min_inliers:
        return None
    return p, q, inl


class _LazyCovariances:
    """``X_cov`` of :func:`localise_pose`, asked once per point and only where needed; NaN
    (unknown) counts as zero."""

    def __init__(self, X_cov: Array | Callable[[NDArray[np.int64]], Array] | None, n: int) -> None:
        self._source = X_cov
        self._P = np.zeros((n, 3, 3)) if callable(X_cov) or X_cov is None else np.nan_to_num(np.asarray(X_cov, float))
        self._asked = np.zeros(n, bool)

    def get(self, idx: NDArray[np.int64]) -> Array:
        """``(m, 3, 3)`` covariances of the points ``idx``."""
        if callable(self._source):
            new = idx[~self._asked[idx]]
            if len(new):
                self._P[new] = np.nan_to_num(np.asarray(self._source(new), float))
                self._asked[new] = True
        return self._P[idx]


def map_pose_sensitivity(camera: PinholeCamera, p: Array, q: Array, X: Array, sigma_px: float
                         ) -> tuple[Array, Array] | None:
    """A pose localised on known map features: its covariance given the map, and how it
    moves with the map's error.

    The pose minimising the reprojection errors of the ``Zm`` of ``X`` has the covariance
    ``C = (sum_n J_n^T J_n / sigma_px^2)^-1`` given the map (``J_n`` with respect to ``[p,
    dtheta]``, ``dtheta`` the right-multiplied rotation error in the camera frame) and
    moves by ``A dX`` when the points move by ``dX``, ``A = -C sum_n J_n^T Jf_n /
    sigma_px^2`` (the residuals' first-order change ``J_n dpose + Jf_n dX`` stays
    orthogonal to the pose's directions).

    Parameters
    ----------
    camera : PinholeCamera
    p, q : (3,), (4,) camera centre (world frame) and ``q_wc``.
    X : (N, 3) world points used (the inliers).
    sigma_px : float
        Standard deviation of a pixel measurement.

    Returns
    -------
    C : (6, 6) covariance of ``[p, dtheta]`` given the map.
    A : (6, 3 N) sensitivity to the points (a point behind the camera: zero columns).
    None when there are fewer than 3 points or the information is singular.
    """
    from ..geometry.rotations import quat_left_matrix

    q = quat_normalize(np.asarray(q, float))
    N = len(X)
    if N < 3:
        return None
    c = camera
    _, Jp, Jf, z = models.feature_model_one_pose(p, q, X, c.fx, c.fy, c.cx, c.cy)
    front = z > 0
    E = np.zeros((7, 6))  # [dp, dtheta] -> [dp, dq], dq = q ⊗ [0, dtheta / 2]
    E[:3, :3] = np.eye(3)
    E[3:, 3:] = 0.5 * quat_left_matrix(q)[:, 1:]
    J = Jp[front] @ E
    try:
        J2 = J.reshape(-1, 6)
        C = np.linalg.inv(J2.T @ J2 / sigma_px**2)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(C)) or np.min(np.linalg.eigvalsh(0.5 * (C + C.T))) <= 0:
        return None
    G = np.zeros((6, 3 * N))  # sum_n J_n^T Jf_n / sigma^2, one 6x3 block per point
    G.reshape(6, N, 3)[:, front] = np.einsum("nij,nik->njk", J, Jf[front]).transpose(1, 0, 2) / sigma_px**2
    return 0.5 * (C + C.T), -C @ G


def map_pose_covariance(camera: PinholeCamera, p: Array, q: Array, X: Array, sigma_px: float,
                        map_cov: Callable[[Array], Array] | None = None) -> Array | None:
    """Covariance of a pose localised on known map features.

    The inverse of the Gauss-Newton information ``sum J^T J / sigma_px^2`` of the ``Zm``
    of ``X`` with respect to ``[p, dtheta]`` (``dtheta``, rad, the right-multiplied rotation
    error in the camera frame, ``R_true = R_est @ Exp(dtheta)``, as in
    :func:`~eifslam.estimation.state.pose_tangent_covariance`). Without ``map_cov`` it is
    conditional on the map (the map's own uncertainty left out); with it, the map's error
    is propagated too: the pose minimising the reprojection errors moves by
    ``A dX`` (:func:`map_pose_sensitivity`), so the covariance is
    ``C + A P_X A^T`` (``C`` the conditional one, ``P_X`` the points' joint covariance;
    the frame's own pixels are not in the map, so the two errors are independent).

    Parameters
    ----------
    camera, p, q, X, sigma_px
        As :func:`map_pose_sensitivity`.
    map_cov : callable, optional
        ``G (k, 3 N) -> G P_X G^T (k, k)`` for the joint covariance ``P_X`` of the points
        ``X`` (state units squared), e.g. ``lambda G: filt.feature_propagate(ids, G)``
        (:meth:`InformationFilter.feature_propagate`).

    Returns
    -------
    (6, 6) covariance of ``[p, dtheta]``, or None when the information is singular.
    """
    out = map_pose_sensitivity(camera, p, q, X, sigma_px)
    if out is None:
        return None
    C, A = out
    if map_cov is not None:
        M = C + np.asarray(map_cov(A), float)
        if np.all(np.isfinite(M)):
            C = M
    return 0.5 * (C + C.T)
