"""Covariance of a relative pose ``[dtheta, dt]`` from image-point noise (no OpenCV).

With the inlier set fixed, :func:`first_order_covariance` is ``sigma**2 (J^T J)^-1`` with
``J`` the Jacobian of the Sampson residuals at the refined estimate
(:func:`eifslam.frontend.twoview.refine_pose`; each residual has variance ``sigma**2`` to
first order). It is essentially free once the refinement has run, and agrees with a Monte
Carlo covariance on the synthetic two-view scenes (the second-order terms it drops are
small except for forward motion).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


Array = NDArray[np.float64]

__all__ = ["first_order_covariance", "is_valid_covariance"]


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


def is_valid_covariance(P: Array, max_std: float = 1.0) -> bool:
    """True when ``P`` is a finite, symmetric positive-definite 5x5 matrix whose standard
    deviations are all below ``max_std`` (rad / tangent units)."""
    P = np.asarray(P, float)
    if P.shape != (5, 5) or not np.all(np.isfinite(P)):
        return False
    w = np.linalg.eigvalsh(0.5 * (P + P.T))
    return bool(w[0] > 0 and np.sqrt(w[-1]) < max_std)

