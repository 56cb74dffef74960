"""A dense EKF in covariance form over the EIF's state: the cost reference (MonoSLAM-style).

:class:`DenseEKF` keeps the mean ``x`` and the full dense covariance ``P`` of every pose
and map feature, augmented exactly as in the EIF (poses ``[p, q]``, features ``X``). It is
fed the *same* measurements linearised the *same* way: it subclasses
:class:`~eifslam.filter.InformationFilter` and replaces only where a linearised
measurement goes. Every ``Zm``, ``ZR``/``ZT``, gauge prior and quaternion-norm
pseudo-measurement reaches :meth:`_add_linearised` as ``(idx, J, W, innov)`` computed by
:mod:`eifslam.models` at the current ``x``; the EKF buffers them and applies them in one
covariance update at :meth:`recover` (so, like the EIF, all the measurements of a frame
are linearised at the same point):

    ``S = H P H^T + R``,  ``K = P H^T S^-1``,  ``x <- x + K innov``,  ``P <- (I - K H) P``

with ``H`` non-zero only in the columns of the states involved, so an update costs
``O(m n^2)`` for ``m`` scalar measurements and state dimension ``n`` (MonoSLAM's cost).

New states enter with the EIF's weak prior as their covariance (positions,
``weak_prior_sigma^2``) and a broad variance on quaternion entries (``quat_init_var``;
the EIF has zero information there before the first measurement). Pure NumPy.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve

from ..geometry.camera import PinholeCamera
from ..errors import EstimatorError
from ..estimation.filter import FilterConfig, InformationFilter

Array = NDArray[np.float64]


class DenseEKF(InformationFilter):
    """Extended Kalman filter with a full dense covariance.

    Parameters
    ----------
    camera : PinholeCamera
    config : FilterConfig
        The EIF's settings (priors, gating, ``ZT`` form, weak prior).
    quat_init_var : float
        Initial variance of each quaternion entry of a new pose.

    Notes
    -----
    :meth:`recover` is the covariance update (the EKF's per-frame back-end cost);
    :meth:`fuse_features` and :meth:`fuse_relative` only linearise.
    """

    def __init__(self, camera: PinholeCamera, config: FilterConfig | None = None, quat_init_var: float = 1.0) -> None:
        super().__init__(camera, config, recovery="full")
        self.quat_init_var = float(quat_init_var)
        self.P = np.zeros((0, 0))
        self._pending: list[tuple[NDArray[np.int64], Array, Array, Array]] = []

    # -- state augmentation -------------------------------------------------------------
    def _grow(self) -> None:
        n_old = self.P.shape[0]
        n = self.dim
        if n > len(self._x):
            new = np.zeros(max(n, 2 * len(self._x)))
            new[: len(self._x)] = self._x
            self._x = new
        if n > n_old:
            P = np.zeros((n, n))
            P[:n_old, :n_old] = self.P
            pos = self.layout.position_mask()[n_old:n]
            var = np.where(pos, self.config.weak_prior_sigma**2, self.quat_init_var)
            P[np.arange(n_old, n), np.arange(n_old, n)] = var
            self.P = P

    def _fuse_weak(self, cols, X: Array) -> None:
        """The weak prior is the initial covariance of a new state (set in :meth:`_grow`)."""

    def _fuse_pose_prior(self, fid: int, p: Array, q: Array) -> None:
        cols = self.layout.pose_columns([fid])
        z = np.concatenate([p, q])
        W = np.eye(7)[None] / self.config.prior_sigma**2
        self._add_linearised(cols, np.eye(7)[None], W, (z - self.x[cols[0]])[None])

    # -- measurements -------------------------------------------------------------------
    def _add_linearised(self, idx, J: Array, W: Array, innov: Array) -> None:
        """Buffer ``N`` linearised measurements (applied by :meth:`recover`)."""
        if len(idx):
            self._pending.append((np.asarray(idx, np.int64), np.asarray(J, float), np.asarray(W, float),
                                  np.asarray(innov, float)))

    def recover(self) -> Array:
        """Apply every buffered measurement in one EKF update; return ``x``."""
        if not self._pending:
            return self.x
        idx = [b[0] for b in self._pending]
        cols = np.unique(np.concatenate([i.ravel() for i in idx]))
        m = sum(b[1].shape[0] * b[1].shape[1] for b in self._pending)
        H = np.zeros((m, len(cols)))
        R = np.zeros((m, m))
        y = np.zeros(m)
        r0 = 0
        for ii, J, W, e in self._pending:
            N, d, _ = J.shape
            loc = np.searchsorted(cols, ii)  # (N, k)
            rows = r0 + np.arange(N * d).reshape(N, d)
            H[rows[:, :, None], loc[:, None, :]] = J
            Rb = np.linalg.inv(W)
            R[rows[:, :, None], rows[:, None, :]] = Rb
            y[rows] = e
            r0 += N * d
        self._pending = []
        PHt = self.P[:, cols] @ H.T  # (n, m)
        S = H @ PHt[cols] + R
        try:
            c = cho_factor(0.5 * (S + S.T))
        except np.linalg.LinAlgError as exc:
            raise EstimatorError(f"EKF innovation covariance is not positive definite: {exc}") from exc
        K = cho_solve(c, PHt.T).T  # (n, m)
        self._x[: self.dim] += K @ y
        self.P -= K @ PHt.T
        self.P = 0.5 * (self.P + self.P.T)
        if not np.all(np.isfinite(self.x)):
            raise EstimatorError("EKF update produced non-finite values")
        return self.x

    def recover_active(self) -> Array:
        return self.recover()

    def complete_estimate(self) -> Array:
        return self.x

    # -- uncertainty --------------------------------------------------------------------
    def covariance(self, idx) -> Array:
        """Marginal covariance of state entries ``idx`` (k,), read from ``P``."""
        idx = np.asarray(idx, np.int64)
        return self.P[np.ix_(idx, idx)].copy()


__all__ = ["DenseEKF"]
