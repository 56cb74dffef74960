"""A dense EKF in covariance form over the EIF's state: the cost reference (MonoSLAM-style).

:class:`DenseEKF` keeps the mean ``x`` and the full dense covariance ``P`` of every pose
and map feature, augmented exactly as in the EIF (poses ``[p, q]``, features ``X``). It is
fed the *same* measurements linearised the *same* way: every ``Zm``, ``ZR``/``ZT``, gauge
prior, scale prior and quaternion-norm pseudo-measurement is linearised at the current
``x`` by :mod:`eifslam.estimation.factors` (the functions the EIF uses) into
``(idx, J, W, innov)``. The EKF buffers them and applies them in one covariance update at
:meth:`DenseEKF.recover` (so, like the EIF, all the measurements of a frame are
linearised at the same point):

    ``S = H P H^T + R``,  ``K = P H^T S^-1``,  ``x <- x + K innov``,  ``P <- (I - K H) P``

with ``H`` non-zero only in the columns of the states involved, so an update costs
``O(m n^2)`` for ``m`` scalar measurements and state dimension ``n`` (MonoSLAM's cost).

New states enter with the EIF's weak prior as their covariance (positions,
``weak_prior_sigma^2``) and a broad variance on quaternion entries (``quat_init_var``;
the EIF has zero information there before the first measurement). Pure NumPy.

The EKF shares no code path with the EIF by inheritance: both satisfy
:class:`eifslam.estimation.backend.Backend`, so either is a back end of
:class:`eifslam.system.slam.Slam`.
"""

from __future__ import annotations

import copy

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve

from ..errors import EstimatorError
from ..estimation import factors
from ..estimation.factors import Linearised
from ..estimation.filter import InformationFilter
from ..estimation.measurements import FeatureObservations, MeasurementStore, PriorStore, RelativePose
from ..estimation.options import FilterConfig
from ..estimation.state import StateKind, StateLayout, pose_tangent_covariance, read_features, read_pose, read_poses
from ..geometry.camera import PinholeCamera
from ..geometry.rotations import quat_normalize

Array = NDArray[np.float64]


class DenseEKF:
    """Extended Kalman filter with a full dense covariance.

    Satisfies :class:`~eifslam.estimation.backend.Backend`, like
    :class:`~eifslam.estimation.filter.InformationFilter`.

    Parameters
    ----------
    camera : PinholeCamera
    config : FilterConfig
        The EIF's settings (priors, gating, ``ZT`` form, weak prior).
    quat_init_var : float
        Initial variance of each quaternion entry of a new pose.

    Attributes
    ----------
    P : (dim, dim) float64
        The covariance of ``x``.
    priors : PriorStore
        Gauge and scale priors set so far (as the EIF keeps them).
    store : MeasurementStore
        Every measurement fused so far.
    incremental : None
        No incremental recovery (the EIF's attribute, for callers that check it).

    Notes
    -----
    :meth:`recover` is the covariance update (the EKF's per-frame back-end cost);
    :meth:`fuse_features` and :meth:`fuse_relative` only linearise.
    """

    incremental = None

    def __init__(self, camera: PinholeCamera, config: FilterConfig | None = None, quat_init_var: float = 1.0) -> None:
        self.camera = camera
        self.config = config or FilterConfig()
        self.quat_init_var = float(quat_init_var)
        self.layout = StateLayout()
        self.priors = PriorStore()
        self.store = MeasurementStore()
        self.P = np.zeros((0, 0))
        self._x = np.zeros(64)
        self._pending: list[Linearised] = []

    # -- state --------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return self.layout.dim

    @property
    def x(self) -> Array:
        """Current mean ``(dim,)`` (a view; linearisation point)."""
        return self._x[: self.dim]

    def _grow(self) -> None:
        """Make room for new states; they enter with their initial (weak prior) variance."""
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

    def add_pose(self, frame_id: int, p: Array, q: Array) -> None:
        """Augment the state with a pose and buffer its quaternion-norm pseudo-measurement."""
        p, q = np.asarray(p, float), quat_normalize(np.asarray(q, float))
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise EstimatorError(f"initial guess of pose {frame_id} is not finite")
        off = self.layout.add_pose(frame_id)
        self._grow()
        self._x[off : off + 3], self._x[off + 3 : off + 7] = p, q
        self.priors.weak[(StateKind.POSE, int(frame_id))] = np.concatenate([p, q])
        self._buffer(factors.quat_norm(self.layout, self.x, [frame_id], self.config.quat_norm_sigma))

    def add_features(self, track_ids, X: Array) -> None:
        """Augment the state with features ``X`` (N, 3), world frame."""
        X = np.asarray(X, float).reshape(-1, 3)
        if not np.all(np.isfinite(X)):
            raise EstimatorError("initial guesses of features are not finite")
        for tid, xyz in zip(track_ids, X):
            off = self.layout.add_feature(tid)
            self._grow()
            self._x[off : off + 3] = xyz
            self.priors.weak[(StateKind.FEATURE, int(tid))] = xyz.copy()

    def pose(self, frame_id: int) -> tuple[Array, Array]:
        """Estimated ``(p (3,), q_wc (4,) unit)`` of a pose."""
        return read_pose(self.layout, self.x, frame_id)

    def poses(self) -> tuple[list[int], Array, Array]:
        """Frame ids, positions ``(P, 3)`` and unit quaternions ``(P, 4)`` of every pose."""
        return read_poses(self.layout, self.x)

    def features(self) -> tuple[list[int], Array]:
        """Track ids and positions ``(F, 3)`` of every map feature."""
        return read_features(self.layout, self.x)

    # -- priors -------------------------------------------------------------------------
    def fix_pose(self, frame_id: int) -> None:
        """Strong prior on a pose at its current estimate (the gauge)."""
        p, q = self.pose(frame_id)
        self.priors.pose[int(frame_id)] = (p, q)
        self._buffer(factors.pose_prior(self.layout, self.x, int(frame_id), p, q, self.config.prior_sigma))

    def set_scale(self, frame_a: int, frame_b: int, distance: float | None = None) -> None:
        """Scale prior ``|p_b - p_a| = distance`` (default: the current distance)."""
        pa, _ = self.pose(frame_a)
        pb, _ = self.pose(frame_b)
        d = float(np.linalg.norm(pb - pa)) if distance is None else float(distance)
        if not (np.isfinite(d) and d > 0):
            raise EstimatorError(f"scale prior distance must be positive, got {d}")
        self.priors.scale = (int(frame_a), int(frame_b), d)
        self._buffer(factors.scale_prior(self.layout, self.x, *self.priors.scale, self.config.scale_prior_sigma))

    # -- measurements -------------------------------------------------------------------
    def _buffer(self, lin: Linearised) -> None:
        """Buffer ``N`` linearised measurements (applied by :meth:`recover`)."""
        if len(lin):
            self._pending.append(lin)

    def linearise_features(self, obs: FeatureObservations, gate: bool = True):
        """Linearise ``Zm`` at the current mean (:func:`eifslam.estimation.factors.features`)."""
        return factors.features(self.layout, self.x, self.camera, self.config, obs, gate)

    def fuse_features(self, obs: FeatureObservations, store: bool = True, gate: bool = True,
                      recent: bool = True) -> FeatureObservations:
        """Linearise a batch of ``Zm`` (gated as in the EIF) and buffer it; return the
        measurements kept (``recent`` is the EIF's recovery's business: no effect here)."""
        if len(obs) == 0:
            return obs
        ok, idx, J, W, innov, _ = self.linearise_features(obs, gate)
        if not np.all(ok):
            obs, idx, J, W, innov = obs.subset(ok), idx[ok], J[ok], W[ok], innov[ok]
        self._buffer(Linearised(idx, J, W, innov))
        if store and len(obs):
            self.store.features.append(obs)
        return obs

    def linearise_relative(self, rps: list[RelativePose]):
        """Linearise ``ZR``/``ZT`` at the current mean (:func:`eifslam.estimation.factors.relative`)."""
        return factors.relative(self.layout, self.x, self.config, rps)

    def fuse_relative(self, rps: list[RelativePose], store: bool = True) -> None:
        """Linearise ``ZR`` and ``ZT`` of each relative pose jointly and buffer them."""
        if not rps:
            return
        self._buffer(Linearised(*self.linearise_relative(rps)))
        if store:
            self.store.relative.extend(rps)

    def recover(self) -> Array:
        """Apply every buffered measurement in one EKF update; return ``x``."""
        if not self._pending:
            return self.x
        cols = np.unique(np.concatenate([b.idx.ravel() for b in self._pending]))
        m = sum(b.J.shape[0] * b.J.shape[1] for b in self._pending)
        H = np.zeros((m, len(cols)))
        R = np.zeros((m, m))
        y = np.zeros(m)
        r0 = 0
        for b in self._pending:
            N, d, _ = b.J.shape
            loc = np.searchsorted(cols, b.idx)  # (N, k)
            rows = r0 + np.arange(N * d).reshape(N, d)
            H[rows[:, :, None], loc[:, None, :]] = b.J
            R[rows[:, :, None], rows[:, None, :]] = np.linalg.inv(b.W)
            y[rows] = b.innov
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
        """The per-frame recovery: :meth:`recover`."""
        return self.recover()

    def complete_estimate(self) -> Array:
        """Nothing is marginalised: ``x``."""
        return self.x

    def recent_estimate(self, steps: int) -> Array:
        """Nothing is marginalised: ``x``."""
        return self.x

    def affordable_features(self, track_ids) -> bool:
        """Every measurement costs the same: True."""
        return True

    def local_map(self, steps: int) -> tuple[NDArray[np.int64], Array]:
        """Every feature is current: all of them, ids ``(F,)`` and positions ``(F, 3)``."""
        ids, X = self.features()
        return np.asarray(ids, np.int64), X

    def recent_features(self, track_ids, steps: int | None = None) -> NDArray[np.bool_]:
        """Every feature is current: all True ``(N,)``."""
        return np.ones(len(np.asarray(track_ids).reshape(-1)), bool)

    def set_estimate(self, x: Array) -> None:
        """Replace the mean by ``x`` ``(dim,)`` (e.g. a bundle adjustment's); ``P`` is kept."""
        x = np.asarray(x, float)
        if x.shape != (self.dim,):
            raise EstimatorError(f"set_estimate: expected shape ({self.dim},), got {x.shape}")
        self._x[: self.dim] = x

    # -- batch steps in information form ------------------------------------------------
    def information_form(self) -> InformationFilter:
        """The same problem as an :class:`~eifslam.estimation.filter.InformationFilter` (full
        recovery) linearised at the current mean: every state, prior and stored measurement.

        Smoothing, loop correction and scale recovery run on it; :meth:`set_from_information_form`
        takes their result back. The buffered measurements are among the stored ones.
        """
        filt = InformationFilter(self.camera, self.config, recovery="full")
        for key in self.layout.order:
            if key.kind == StateKind.POSE:
                filt.add_pose(key.id, *self.pose(key.id))
            else:
                filt.add_features([key.id], self.x[self.layout.feature_slice(key.id)][None])
        filt.set_estimate(self.x)  # the mean as it is (add_pose normalises quaternions)
        filt.priors = copy.deepcopy(self.priors)
        filt.store = copy.deepcopy(self.store)
        filt.relinearise()
        return filt

    def set_from_information_form(self, filt: InformationFilter) -> None:
        """Take the estimate, priors and stored measurements of ``filt`` (made by
        :meth:`information_form` and changed by a batch step); ``P`` becomes the inverse of
        its information matrix (dense, ``O(n^3)``). Buffered measurements are dropped: the
        information holds them."""
        if filt.layout.order != self.layout.order:
            raise EstimatorError("set_from_information_form: the information form holds other states")
        self._x[: self.dim] = filt.x
        self.priors = copy.deepcopy(filt.priors)
        self.store = copy.deepcopy(filt.store)
        self._pending = []
        if self.dim:
            I = filt.information_matrix().toarray()
            try:
                c = cho_factor(0.5 * (I + I.T))
            except np.linalg.LinAlgError as exc:
                raise EstimatorError(f"information matrix is not positive definite: {exc}") from exc
            P = cho_solve(c, np.eye(self.dim))
            self.P = 0.5 * (P + P.T)

    # -- uncertainty --------------------------------------------------------------------
    def covariance(self, idx) -> Array:
        """Marginal covariance of state entries ``idx`` (k,), read from ``P``."""
        idx = np.asarray(idx, np.int64)
        return self.P[np.ix_(idx, idx)].copy()

    def pose_covariance(self, frame_id: int) -> Array:
        """6x6 covariance of ``[p, dtheta]`` of a pose (as the EIF's)."""
        cols = self.layout.pose_columns([frame_id])[0]
        return pose_tangent_covariance(self.covariance(cols), self.x[cols[3:]])

    def feature_covariance(self, track_id: int) -> Array:
        """3x3 covariance of a map feature."""
        return self.covariance(self.layout.feature_columns([track_id])[0])

    def propagate(self, frame_ids, track_ids, G: Array) -> Array:
        """``G P G^T`` for the joint covariance ``P`` of poses and map features, read from the
        dense ``P``; features not in the state count as exact (as the EIF's).

        Parameters
        ----------
        frame_ids : (Np,) int, distinct pose ids.
        track_ids : (F,) int, distinct feature ids.
        G : (k, 7 Np + 3 F) float, 7 columns per pose, then 3 per feature, in the order given.

        Returns
        -------
        (k, k) float
        """
        fr = [int(f) for f in np.asarray(frame_ids, np.int64).reshape(-1)]
        ids, G = np.asarray(track_ids, np.int64).reshape(-1), np.asarray(G, float)
        k, n_p = G.shape[0], 7 * len(fr)
        have = self.layout.has_features(ids) if len(ids) else np.zeros(0, bool)
        pcols = self.layout.pose_columns(fr).ravel() if fr else np.zeros(0, np.int64)
        fcols = self.layout.feature_columns(ids[have]).ravel() if have.any() else np.zeros(0, np.int64)
        Gh = np.concatenate([G[:, :n_p], G[:, n_p:].reshape(k, len(ids), 3)[:, have].reshape(k, -1)], 1)
        return Gh @ self.covariance(np.concatenate([pcols, fcols])) @ Gh.T

    def feature_propagate(self, track_ids, G: Array) -> Array:
        """``G P G^T`` for the joint covariance ``P`` of map features (:meth:`propagate`
        without poses)."""
        return self.propagate([], track_ids, G)

    def feature_covariances(self, track_ids) -> Array:
        """``(N, 3, 3)`` covariances of map features (repeats allowed), read from ``P``;
        NaN for an id not in the state (as :meth:`InformationFilter.feature_covariances`)."""
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        out = np.full((len(ids), 3, 3), np.nan)
        known = self.layout.has_features(ids) if len(ids) else np.zeros(0, bool)
        if known.any():
            cols = self.layout.feature_columns(ids[known])
            out[known] = self.P[cols[:, :, None], cols[:, None, :]]
        return out

    def information_matrix(self) -> sp.csc_matrix:
        """``P^-1`` as a sparse matrix ``(dim, dim)`` (dense inverse, ``O(n^3)``; for outputs)."""
        if not self.dim:
            return sp.csc_matrix((0, 0))
        return sp.csc_matrix(np.linalg.inv(self.P))


__all__ = ["DenseEKF"]
