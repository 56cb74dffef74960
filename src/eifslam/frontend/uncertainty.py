"""Covariance of a relative pose ``[dtheta, dt]`` from image-point noise (no OpenCV).

Two methods, both with the inlier set fixed and the refinement of
:func:`eifslam.frontend.twoview.refine_pose` as the deterministic solver:

* :func:`unscented_covariance` -- the unscented transform (paper ref. [15]) of the
  ``4N`` independent pixel coordinates through the whole refinement. With
  ``n + kappa = 3`` every sigma point moves one coordinate by ``+-sqrt(3) sigma``; the
  covariance is centred on the output of the central point, so the (negative) central
  weight drops out and the result is positive semi-definite.
* :func:`first_order_covariance` -- ``sigma**2 (J^T J)^-1`` with ``J`` the Jacobian of
  the Sampson residuals at the estimate (each residual has variance ``sigma**2`` to first
  order). Essentially free once the refinement has run.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from .twoview import pose_error, refine_pose

Array = NDArray[np.float64]

__all__ = ["first_order_covariance", "unscented_covariance", "is_valid_covariance"]


def first_order_covariance(J: Array, sigma_px: float) -> Array:
    """First-order covariance ``sigma**2 (J^T J)^-1``.

    Parameters
    ----------
    J : (..., N, 5) Jacobian of the Sampson residuals (pixels) w.r.t. ``[dtheta, dt]``.
    sigma_px : float
        Pixel noise standard deviation per coordinate.

    Returns
    -------
    (..., 5, 5) covariance (rad^2 for the rotation block); NaN-free only if ``J`` has full
    column rank -- check with :func:`is_valid_covariance`.
    """
    J = np.asarray(J, float)
    H = np.swapaxes(J, -1, -2) @ J
    with np.errstate(all="ignore"):
        P = sigma_px**2 * np.linalg.pinv(H, hermitian=True)
    return 0.5 * (P + np.swapaxes(P, -1, -2))


def unscented_covariance(
    R: Array,
    t: Array,
    uv_i: Array,
    uv_j: Array,
    K: Array,
    sigma_px: float,
    iterations: int = 2,
    chunk: int = 512,
) -> Array:
    """Unscented transform of isotropic pixel noise through the pose refinement.

    Parameters
    ----------
    R : (3, 3), t : (3,)
        The refined estimate ``R_ij, t_ij`` (output of the central sigma point).
    uv_i, uv_j : (N, 2)
        Inlier correspondences, undistorted pixels.
    K : (3, 3)
    sigma_px : float
        Noise standard deviation per pixel coordinate.
    iterations : int
        Gauss-Newton iterations per sigma point, started from ``(R, t)``.
    chunk : int
        Sigma points refined per batch (bounds memory at ``chunk * N``).

    Returns
    -------
    (5, 5) covariance of ``[dtheta (rad), dt]`` in the tangent basis of ``t``.
    """
    uv_i = np.asarray(uv_i, float)
    uv_j = np.asarray(uv_j, float)
    z0 = np.concatenate([uv_i, uv_j], 1)  # (N, 4): u_i, v_i, u_j, v_j
    n = z0.size
    spread = np.sqrt(3.0) * sigma_px  # n + kappa = 3
    weight = 1.0 / (2.0 * 3.0)
    P = np.zeros((5, 5))
    idx = np.arange(2 * n)
    for s in range(0, 2 * n, chunk):
        k = idx[s : s + chunk]
        coord = k % n
        sign = np.where(k < n, 1.0, -1.0)
        Z = np.broadcast_to(z0, (len(k),) + z0.shape).copy()
        Z.reshape(len(k), -1)[np.arange(len(k)), coord] += sign * spread
        Rk, tk, _ = refine_pose(
            np.broadcast_to(R, (len(k), 3, 3)),
            np.broadcast_to(t, (len(k), 3)),
            Z[..., :2],
            Z[..., 2:],
            K,
            iterations,
        )
        d = pose_error(R, t, Rk, tk)  # (chunk, 5)
        P += weight * d.T @ d
    return 0.5 * (P + P.T)


def is_valid_covariance(P: Array, max_std: float = 1.0) -> bool:
    """True when ``P`` is a finite, symmetric positive-definite 5x5 matrix whose standard
    deviations are all below ``max_std`` (rad / tangent units)."""
    P = np.asarray(P, float)
    if P.shape != (5, 5) or not np.all(np.isfinite(P)):
        return False
    w = np.linalg.eigvalsh(0.5 * (P + P.T))
    return bool(w[0] > 0 and np.sqrt(w[-1]) < max_std)

