"""Two-view geometry without OpenCV: Sampson residuals, Gauss-Newton refinement, parallax.

Conventions follow :mod:`eifslam.geometry` and :class:`eifslam.estimation.measurements.RelativePose`:
``R = R_ij = R_wi.T @ R_wj`` and ``t = t_ij``, the unit direction of camera *j*'s centre in
frame *i*. A point ``X_i`` (frame *i*) is ``X_j = R.T @ (X_i - s t)`` in frame *j*, so the
epipolar constraint on normalised homogeneous points is ``x_i.T @ [t]x @ R @ x_j = 0``.

Everything is vectorised over leading (batch) dimensions so that Monte Carlo draws and
unscented-transform sigma points are refined in one call.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..geometry.rotations import quat_log, rotmat_to_quat, rotvec_exp, skew, tangent_basis

Array = NDArray[np.float64]

__all__ = [
    "essential",
    "fundamental",
    "sampson_residuals",
    "retract",
    "pose_error",
    "refine_pose",
    "sampson_jacobian",
    "median_parallax_deg",
    "cheirality_mask",
    "rotation_only_parallax_deg",
]

_EPS = 1e-300
_GENERATORS = skew(np.eye(3))  # (3, 3, 3): [e_k]x, the rotation error's generators


def essential(R: Array, t: Array) -> Array:
    """Essential matrix ``E = [t]x R`` with ``x_i.T @ E @ x_j = 0``.

    Parameters
    ----------
    R : (..., 3, 3) ``R_ij``.
    t : (..., 3) direction of ``t_ij``.

    Returns
    -------
    (..., 3, 3) array.
    """
    return skew(np.asarray(t, float)) @ np.asarray(R, float)


def fundamental(R: Array, t: Array, K: Array) -> Array:
    """Fundamental matrix ``F = K^-T E K^-1`` with ``p_i.T @ F @ p_j = 0`` (pixels)."""
    Kinv = np.linalg.inv(np.asarray(K, float))
    return Kinv.T @ essential(R, t) @ Kinv


def _homog(uv: Array) -> Array:
    uv = np.asarray(uv, float)
    return np.concatenate([uv, np.ones(uv.shape[:-1] + (1,))], -1)


def sampson_residuals(R: Array, t: Array, uv_i: Array, uv_j: Array, K: Array) -> Array:
    """Signed Sampson residuals of correspondences, in pixels.

    For isotropic pixel noise ``sigma`` on both points, each residual has standard
    deviation ``sigma`` to first order.

    Parameters
    ----------
    R : (..., 3, 3) ``R_ij``.
    t : (..., 3) ``t_ij`` (any scale).
    uv_i, uv_j : (..., N, 2) undistorted pixels in images *i* and *j*.
    K : (3, 3) intrinsics.

    Returns
    -------
    (..., N) residuals, pixels.
    """
    F = fundamental(R, t, K)
    pi, pj = _homog(uv_i), _homog(uv_j)
    Fpj = np.einsum("...ab,...nb->...na", F, pj)
    Ftpi = np.einsum("...ba,...nb->...na", F, pi)
    e = np.sum(pi * Fpj, -1)
    den = Fpj[..., 0] ** 2 + Fpj[..., 1] ** 2 + Ftpi[..., 0] ** 2 + Ftpi[..., 1] ** 2
    return e / np.sqrt(np.maximum(den, _EPS))


def retract(R: Array, t: Array, dx: Array) -> tuple[Array, Array]:
    """Apply a 5-vector error ``[dtheta, dt]`` to a relative pose.

    ``R' = R @ Exp(dtheta)``, ``t' = normalize(t + tangent_basis(t) @ dt)``: the error
    definition of :class:`~eifslam.estimation.measurements.RelativePose`.

    Parameters
    ----------
    R : (..., 3, 3); t : (..., 3) unit; dx : (..., 5).

    Returns
    -------
    (R', t') with the broadcast shapes.
    """
    dx = np.asarray(dx, float)
    R2 = np.asarray(R, float) @ rotvec_exp(dx[..., :3])
    t = np.asarray(t, float)
    t2 = t + np.einsum("...ab,...b->...a", tangent_basis(t), dx[..., 3:])
    return R2, t2 / np.linalg.norm(t2, axis=-1, keepdims=True)


def pose_error(R_est: Array, t_est: Array, R_true: Array, t_true: Array) -> Array:
    """The 5-vector ``[dtheta, dt]`` taking the estimate to the truth (``retract`` inverse).

    Returns
    -------
    (..., 5) array: ``dtheta = Log(R_est.T R_true)`` (rad) and
    ``dt = B(t_est).T t_true / (t_est . t_true)``.
    """
    R_est, R_true = np.asarray(R_est, float), np.asarray(R_true, float)
    dth = quat_log(rotmat_to_quat(np.swapaxes(R_est, -1, -2) @ R_true))
    te = np.asarray(t_est, float)
    te = te / np.linalg.norm(te, axis=-1, keepdims=True)
    tt = np.asarray(t_true, float)
    tt = tt / np.linalg.norm(tt, axis=-1, keepdims=True)
    B = tangent_basis(te)
    dt = np.einsum("...ab,...a->...b", B, tt) / np.sum(te * tt, -1, keepdims=True)
    return np.concatenate([dth, dt], -1)


def sampson_jacobian(R: Array, t: Array, uv_i: Array, uv_j: Array, K: Array) -> tuple[Array, Array]:
    """Residuals and their analytic Jacobian w.r.t. the 5-vector error of :func:`retract`.

    With ``F = K^-T [t]x R K^-1``, ``e = p_iᵀ F p_j`` and ``r = e / sqrt(den)``: a rotation
    error ``dθ_k`` changes ``R`` by ``R [e_k]x`` and a direction error ``dt_m`` changes ``t``
    by the tangent vector ``B(t)[:, m]`` (the normalisation is second order), so
    ``dr = de / sqrt(den) - e d(den) / (2 den^1.5)``.

    Parameters
    ----------
    R : (..., 3, 3); t : (..., 3) unit; uv_i, uv_j : (..., N, 2); K : (3, 3).

    Returns
    -------
    r : (..., N) residuals, pixels.
    J : (..., N, 5) derivative of ``r`` w.r.t. ``[dtheta (rad), dt]``.
    """
    R, t = np.asarray(R, float), np.asarray(t, float)
    Kinv = np.linalg.inv(np.asarray(K, float))
    tx = skew(t)
    E = tx @ R
    dE = np.concatenate([(E[..., None, :, :] @ _GENERATORS),  # (..., 3, 3, 3): [t]x R [e_k]x
                         skew(np.swapaxes(tangent_basis(t), -1, -2)) @ R[..., None, :, :]], -3)  # (..., 5, 3, 3)
    F = Kinv.T @ E @ Kinv
    dF = Kinv.T @ dE @ Kinv
    pi, pj = _homog(uv_i), _homog(uv_j)
    Fpj = np.einsum("...ab,...nb->...na", F, pj)
    Ftpi = np.einsum("...ba,...nb->...na", F, pi)
    e = np.sum(pi * Fpj, -1)
    den = np.maximum(Fpj[..., 0] ** 2 + Fpj[..., 1] ** 2 + Ftpi[..., 0] ** 2 + Ftpi[..., 1] ** 2, _EPS)
    dFpj = np.einsum("...kab,...nb->...kna", dF, pj)  # (..., 5, N, 3)
    dFtpi = np.einsum("...kba,...nb->...kna", dF, pi)
    de = np.sum(pi[..., None, :, :] * dFpj, -1)  # (..., 5, N)
    dden = 2.0 * (Fpj[..., None, :, 0] * dFpj[..., 0] + Fpj[..., None, :, 1] * dFpj[..., 1]
                  + Ftpi[..., None, :, 0] * dFtpi[..., 0] + Ftpi[..., None, :, 1] * dFtpi[..., 1])
    sq = np.sqrt(den)
    r = e / sq
    J = de / sq[..., None, :] - 0.5 * (r / den)[..., None, :] * dden
    return r, np.swapaxes(J, -1, -2)


def refine_pose(
    R0: Array, t0: Array, uv_i: Array, uv_j: Array, K: Array, iterations: int = 3, damping: float = 0.0
) -> tuple[Array, Array, Array]:
    """Gauss-Newton (``damping`` 0) or Levenberg-Marquardt refinement of ``(R_ij, t_ij)`` on
    the Sampson error, batched.

    Each iteration tries one step per batch element, damped by ``lam * diag(JᵀJ)`` with
    ``lam`` starting at ``damping``, divided by 10 after a step that lowers the element's
    cost and multiplied by 10 after one that does not, which is then not taken; until every
    element has converged (a step lowering its cost by less than 1e-10 of it, or ``lam``
    above 1e8) or ``iterations`` steps. Undamped, a rejected step is tried again unchanged:
    near a dominant plane ``JᵀJ`` is ill-conditioned (condition numbers of 1e5 on
    strecha-castle-p30) and Gauss-Newton can stay where it started.

    Parameters
    ----------
    R0 : (..., 3, 3), t0 : (..., 3)
        Initial estimate (e.g. from RANSAC).
    uv_i, uv_j : (..., N, 2)
        Inlier correspondences (undistorted pixels), fixed.
    K : (3, 3)
    iterations : int
    damping : float
        Initial ``lam``; 0: undamped Gauss-Newton.

    Returns
    -------
    R : (..., 3, 3); t : (..., 3) unit; J : (..., N, 5) Jacobian at the result.
    """
    R = np.asarray(R0, float)
    t = np.asarray(t0, float)
    t = t / np.linalg.norm(t, axis=-1, keepdims=True)
    r, J = sampson_jacobian(R, t, uv_i, uv_j, K)
    cost = np.sum(r * r, -1)
    lam = np.full(cost.shape, float(damping))
    for _ in range(iterations):
        H = np.swapaxes(J, -1, -2) @ J
        g = np.einsum("...na,...n->...a", J, r)
        d = np.diagonal(H, axis1=-2, axis2=-1)
        H = H + (lam[..., None] * d + 1e-12 * d.sum(-1, keepdims=True))[..., None] * np.eye(5)
        dx = -np.linalg.solve(H, g[..., None])[..., 0]
        R2, t2 = retract(R, t, dx)
        r2, J2 = sampson_jacobian(R2, t2, uv_i, uv_j, K)
        cost2 = np.sum(r2 * r2, -1)
        better = np.isfinite(cost2) & (cost2 <= cost)
        R = np.where(better[..., None, None], R2, R)
        t = np.where(better[..., None], t2, t)
        r = np.where(better[..., None], r2, r)
        J = np.where(better[..., None, None], J2, J)
        tiny = better & (cost - cost2 <= 1e-10 * cost)
        cost = np.where(better, cost2, cost)
        lam = np.where(better, lam / 10.0, lam * 10.0)
        if np.all(tiny | (lam > 1e8)):
            break  # every element converged (a negligible step) or stuck (no step lowers it)
    return R, t, J


def median_parallax_deg(R: Array, bearing_i: Array, bearing_j: Array) -> float:
    """Median angle between bearings of frame *i* and rotation-compensated bearings of *j*.

    Parameters
    ----------
    R : (3, 3) ``R_ij``.
    bearing_i, bearing_j : (N, 3) unit bearings in frames *i* and *j*.

    Returns
    -------
    Median angle in degrees (0 for empty input): the typical triangulation angle.
    """
    if len(bearing_i) == 0:
        return 0.0
    bj = np.asarray(bearing_j, float) @ np.asarray(R, float).T
    c = np.clip(np.sum(np.asarray(bearing_i, float) * bj, -1), -1.0, 1.0)
    return float(np.degrees(np.median(np.arccos(c))))


def rotation_only_parallax_deg(bearing_i: Array, bearing_j: Array) -> float:
    """Median angle left after the best pure-rotation fit (Wahba / Kabsch) of the bearings.

    Close to the noise level for a pure rotation or a repeated frame, whatever the
    essential-matrix solver returned for such degenerate input.

    Parameters
    ----------
    bearing_i, bearing_j : (N, 3) unit bearings.

    Returns
    -------
    Median residual angle in degrees (0 for fewer than 2 bearings).
    """
    bi, bj = np.asarray(bearing_i, float), np.asarray(bearing_j, float)
    if len(bi) < 2:
        return 0.0
    U, _, Vt = np.linalg.svd(bi.T @ bj)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])
    return median_parallax_deg(U @ D @ Vt, bi, bj)


def cheirality_mask(R: Array, t: Array, bearing_i: Array, bearing_j: Array) -> NDArray[np.bool_]:
    """Points triangulated in front of both cameras (mid-point method).

    Solves ``l_i b_i - l_j R b_j = t`` in the least-squares sense for each point.

    Parameters
    ----------
    R : (3, 3) ``R_ij``; t : (3,) ``t_ij``; bearing_i, bearing_j : (N, 3).

    Returns
    -------
    (N,) bool, True where both depths are positive (False for parallel rays).
    """
    bi = np.asarray(bearing_i, float)
    bj = np.asarray(bearing_j, float) @ np.asarray(R, float).T
    t = np.asarray(t, float)
    a, b, c = np.sum(bi * bi, -1), np.sum(bi * bj, -1), np.sum(bj * bj, -1)
    d, e = bi @ t, bj @ t
    det = a * c - b * b
    ok = det > 1e-12
    det = np.where(ok, det, 1.0)
    li = (c * d - b * e) / det
    lj = (b * d - a * e) / det
    return ok & (li > 0) & (lj > 0)
