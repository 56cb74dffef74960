"""The exactly sparse Extended Information Filter (paper III-D, III-G, III-H; pure NumPy/SciPy).

The filter keeps the information matrix ``I`` and vector ``i`` of every pose and map
feature, and the current estimate ``x`` used for linearisation. Fusing a measurement
(paper eq. 8) touches only the blocks of the states it involves, so ``I`` stays exactly
sparse. The gauge and the quaternions are handled as follows:

* the first pose gets a strong prior (position and quaternion) at its initial value;
* one scale prior fixes the distance between two poses (by default the first two);
* every pose gets a pseudo-measurement ``|q|^2 = 1`` (the models are invariant to the
  quaternion's norm, so this is the only information in that direction).

Priors and pseudo-measurements are stored with the measurements, so smoothing
(:mod:`eifslam.estimation.smoothing`) relinearises them too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from ..errors import EstimatorError, SessionError
from ..geometry.camera import PinholeCamera
from ..geometry.rotations import quat_normalize
from . import factors
from .factors import Linearised
from .incremental import IncrementalRecovery
from .measurements import (FeatureObservations, MeasurementStore, PriorStore, RelativePose, pack_features,
                           pack_relative, unpack_features, unpack_relative)
from .options import WINDOW, FilterConfig, Recovery
from .recovery import SchurFactor, factorize
from .recovery_modes import FullRecovery, RecoveryMode, WindowRecovery
from .relinearisation import OnlineRelinearisation
from .statedict import check_index, sub, take, take_float, take_ids, take_int
from .state import FEATURE_DIM, POSE_DIM, StateKind, StateLayout, pose_tangent_covariance, read_features, read_pose, read_poses  # noqa: F401

Array = NDArray[np.float64]


@dataclass
class GateCount:
    """How many ``Zm`` the gate (``FilterConfig.gate_chi2``) was offered and refused.

    Offered: those that could be linearised (in front of the camera, finite). On data
    without wrong matches (a simulation) every refusal is a false alarm, and the rate
    would be the test's (``1 - chi2.cdf(gate_chi2, 2)``, 1% at 9.21) if the estimate
    were exact; features whose estimate is off raise it (``docs/estimator.md``,
    Consistency)."""

    offered: int = 0
    refused: int = 0

    @property
    def rate(self) -> float | None:
        """The fraction refused (None before any was offered)."""
        return self.refused / self.offered if self.offered else None


class InformationFilter:
    """Exactly sparse EIF over camera poses and map features.

    Satisfies :class:`~eifslam.estimation.backend.Backend` (as does the dense EKF
    baseline, :class:`~eifslam.baselines.ekf.DenseEKF`).

    Parameters
    ----------
    camera : PinholeCamera
        Intrinsics used by ``Zm`` (pixels are undistorted).
    config : FilterConfig
    recovery : RecoveryMode or Recovery or {"incremental", "full"}
        What :meth:`recover_active` (the per-keyframe recovery) does, as an object
        (:mod:`~eifslam.estimation.recovery_modes`): ``"incremental"``
        (:class:`~eifslam.estimation.recovery_modes.WindowRecovery`, the default) solves an
        active window of recent states exactly and marginalises the rest, at a cost bounded
        by the window; ``"full"`` (:class:`~eifslam.estimation.recovery_modes.FullRecovery`)
        solves the whole system. :meth:`recover` is always the full solve;
        :meth:`complete_estimate` back-substitutes the marginalised states.
    window : int
        With ``"incremental"``: steps without a measurement before a state leaves the
        active window (:data:`~eifslam.estimation.options.WINDOW` by default).
    """

    def __init__(
        self, camera: PinholeCamera, config: FilterConfig | None = None,
        recovery: RecoveryMode | Recovery | str = Recovery.INCREMENTAL, window: int = WINDOW,
    ) -> None:
        self.camera = camera
        self.config = config or FilterConfig()
        self.layout = StateLayout()
        self.store = MeasurementStore()
        self.priors = PriorStore()
        self._x = np.zeros(64)
        self._factor: SchurFactor | None = None
        self.zm_gate = GateCount()
        if not isinstance(recovery, RecoveryMode):
            online = None if self.config.relinearise_threshold is None else \
                OnlineRelinearisation(self.config.relinearise_threshold)
            recovery = WindowRecovery(window, online) if Recovery.parse(recovery, "recovery") == Recovery.INCREMENTAL \
                else FullRecovery()
        self.recovery: RecoveryMode = recovery
        self.info = recovery.information_store()

    def restart(self) -> None:
        """Forget every state, measurement and prior: the filter as it was constructed (the
        same configuration, a recovery of the same kind and settings that has seen nothing).
        What :class:`~eifslam.system.slam.Slam` does when the world frame moves on before
        the map exists."""
        self.layout = StateLayout()
        self.store = MeasurementStore()
        self.priors = PriorStore()
        self._x = np.zeros(64)
        self._factor = None
        self.recovery = self.recovery.fresh()
        self.info = self.recovery.information_store()
        self.zm_gate = GateCount()

    @property
    def incremental(self) -> IncrementalRecovery | None:
        """The incremental recovery's window (its statistics, for inspection), or None."""
        return self.recovery.incremental

    @property
    def online(self) -> OnlineRelinearisation | None:
        """The online relinearisation (``config.relinearise_threshold``), or None."""
        return self.recovery.online

    # -- pickling -----------------------------------------------------------------------
    def __getstate__(self) -> dict:
        """Pickle without the cached factorisation (SuperLU objects do not pickle; it is
        rebuilt on demand). In incremental mode the pickled ``x`` is the complete
        estimate (marginalised states back-substituted); this filter is not changed."""
        state = self.__dict__.copy()
        state["_factor"] = None
        x = self._x.copy()
        self.recovery.complete(self, x[: self.dim])
        state["_x"] = x
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._factor = None

    def _check_states(self, kind: StateKind, ids, what: str) -> None:
        ids = np.asarray(ids, np.int64).reshape(-1)
        known = np.array(self.layout.pose_ids if kind == StateKind.POSE else self.layout.feature_ids, np.int64)
        if not np.all(np.isin(ids, known)):
            raise SessionError(f"{what} names a {kind.value} that is not in the state")

    # -- state ------------------------------------------------------------------------
    @property
    def dim(self) -> int:
        return self.layout.dim

    @property
    def x(self) -> Array:
        """Current estimate ``(dim,)`` (a view; linearisation point)."""
        return self._x[: self.dim]

    def _grow(self) -> None:
        n = self.dim
        if n > len(self._x):
            size = max(n, 2 * len(self._x))
            new = np.zeros(size)
            new[: len(self._x)] = self._x
            self._x = new
        self.info.grow(n)

    def add_pose(self, frame_id: int, p: Array, q: Array) -> None:
        """Augment the state with a pose (zeros in ``I``, ``i``; Algorithm 1 step 4) and
        fuse its quaternion-norm pseudo-measurement at the initial guess."""
        p, q = np.asarray(p, float), quat_normalize(np.asarray(q, float))
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise EstimatorError(f"initial guess of pose {frame_id} is not finite")
        off = self.layout.add_pose(frame_id)
        self._grow()
        self._x[off : off + 3], self._x[off + 3 : off + 7] = p, q
        self._factor = None
        self._fuse(factors.quat_norm(self.layout, self.x, [frame_id], self.config.quat_norm_sigma))
        self.priors.weak[(StateKind.POSE, int(frame_id))] = np.concatenate([p, q])
        self._fuse_weak(self.layout.pose_columns([frame_id]), np.concatenate([p, q])[None])

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
        self._factor = None
        if len(X):
            self._fuse_weak(self.layout.feature_columns(list(track_ids)), X)

    def _fuse_weak(self, cols, X: Array) -> None:
        """Weak prior ``X ~ N(X0, weak_prior_sigma^2 I)`` on state entries ``cols`` (N, k)."""
        self._fuse(factors.weak_prior(cols, X, self.x, self.config.weak_prior_sigma))

    def prior_terms(self) -> list[Linearised]:
        """What :meth:`relinearise` fuses besides the stored measurements, linearised at ``x``:
        the gauge and scale priors, every weak prior and the ``|q|^2 = 1``
        pseudo-measurements (their ``innov`` also gives their part of the cost)."""
        x, lay, cfg = self.x, self.layout, self.config
        terms = [factors.pose_prior(lay, x, fid, p, q, cfg.prior_sigma) for fid, (p, q) in self.priors.pose.items()]
        if self.priors.scale is not None:
            terms.append(factors.scale_prior(lay, x, *self.priors.scale, cfg.scale_prior_sigma))
        for kind, columns in ((StateKind.POSE, lay.pose_columns), (StateKind.FEATURE, lay.feature_columns)):
            keys = [i for (kd, i) in self.priors.weak if kd == kind]
            if keys:
                X = np.stack([self.priors.weak[(kind, i)] for i in keys])
                terms.append(factors.weak_prior(columns(keys), X, x, cfg.weak_prior_sigma))
        if lay.pose_ids:
            terms.append(factors.quat_norm(lay, x, np.array(lay.pose_ids), cfg.quat_norm_sigma))
        return terms

    def pose(self, frame_id: int) -> tuple[Array, Array]:
        """Estimated ``(p (3,), q_wc (4,) unit)`` of a pose."""
        return read_pose(self.layout, self.x, frame_id)

    def poses(self) -> tuple[list[int], Array, Array]:
        """Frame ids, positions ``(P, 3)`` and unit quaternions ``(P, 4)`` of every pose."""
        return read_poses(self.layout, self.x)

    def features(self) -> tuple[list[int], Array]:
        """Track ids and positions ``(F, 3)`` of every map feature."""
        return read_features(self.layout, self.x)

    # -- priors -----------------------------------------------------------------------
    def fix_pose(self, frame_id: int) -> None:
        """Strong prior on a pose at its current estimate (the gauge; METHOD §6.1)."""
        p, q = self.pose(frame_id)
        self.priors.pose[int(frame_id)] = (p, q)
        self._fuse_pose_prior(int(frame_id), p, q)

    def set_scale(self, frame_a: int, frame_b: int, distance: float | None = None) -> None:
        """Scale prior ``|p_b - p_a| = distance`` (default: the current distance)."""
        pa, _ = self.pose(frame_a)
        pb, _ = self.pose(frame_b)
        d = float(np.linalg.norm(pb - pa)) if distance is None else float(distance)
        if not (np.isfinite(d) and d > 0):
            raise EstimatorError(f"scale prior distance must be positive, got {d}")
        self.priors.scale = (int(frame_a), int(frame_b), d)
        self._fuse_scale(*self.priors.scale)

    def _fuse_pose_prior(self, fid: int, p: Array, q: Array) -> None:
        self._fuse(factors.pose_prior(self.layout, self.x, fid, p, q, self.config.prior_sigma))

    def _fuse_scale(self, fa: int, fb: int, d: float) -> None:
        self._fuse(factors.scale_prior(self.layout, self.x, fa, fb, d, self.config.scale_prior_sigma))

    # -- fusion (paper eq. 8) -----------------------------------------------------------
    def _fuse(self, lin: Linearised, measurement: bool = True) -> None:
        """``I += J^T W J``, ``i += J^T W (innov + J x)`` for a linearised batch
        (``measurement`` as in :meth:`add_information`)."""
        self.add_information(lin.idx, *lin.information(self.x), measurement=measurement)

    def add_information(self, idx, Lam: Array, eta: Array, measurement: bool = True) -> None:
        """Add blocks ``Lam (N, k, k)`` to ``I`` and ``eta (N, k)`` to ``i`` at ``idx (N, k)``;
        ``measurement=False``: a correction (relinearisation) or measurements fused late, the
        states age as untouched."""
        if measurement:
            self.info.add(idx, Lam, eta)
        else:
            with self.recovery.corrections():
                self.info.add(idx, Lam, eta)
        self._factor = None

    def subtract_information(self, idx, Lam: Array, eta: Array) -> None:
        """Take back blocks that :meth:`add_information` added: ``I -= Lam``, ``i -= eta`` at
        ``idx (N, k)``. ``I`` and ``i`` are sums over measurements, so this is exact when
        ``I`` was not rebuilt since (``info.generation`` unchanged). The recovery window
        (which eliminated with the old ``I``) is rebuilt at the next recovery."""
        self.add_information(idx, -np.asarray(Lam, float), -np.asarray(eta, float), measurement=False)
        self.recovery.invalidate()

    def linearise_features(self, obs: FeatureObservations, gate: bool = True):
        """Linearise ``Zm`` at the current estimate.

        Returns
        -------
        ok : (N,) bool, usable (predicted depth above ``min_depth``, finite, inside the gate).
        idx : (N, 10) state indices ``[pose 7, feature 3]``; J : (N, 2, 10);
        W : (N, 2, 2) information; innov : (N, 2) ``z - h(x)``; chi2 : (N,) normalised
        innovation squared against ``R`` (``inf`` where not finite or behind the camera).
        """
        return factors.features(self.layout, self.x, self.camera, self.config, obs, gate)

    def fuse_features(self, obs: FeatureObservations, store: bool = True, gate: bool = True,
                      recent: bool = True) -> FeatureObservations:
        """Fuse a batch of ``Zm``; return the measurements actually fused.

        Measurements whose predicted depth is below ``min_depth`` or whose innovation
        fails the ``gate_chi2`` test are skipped (never fused as NaN/inf). ``recent=False``:
        measurements made earlier and fused late, which leave the states they touch as old
        as they were (the recovery does not take them back into its window for them).
        """
        if len(obs) == 0:
            return obs
        ok, idx, J, W, innov, chi2 = self.linearise_features(obs, gate)
        if gate and self.config.gate_chi2 is not None:
            usable = np.isfinite(chi2)
            self.zm_gate.offered += int(usable.sum())
            self.zm_gate.refused += int(np.sum(usable & ~ok))
        if not np.all(ok):
            obs, idx, J, W, innov = obs.subset(ok), idx[ok], J[ok], W[ok], innov[ok]
        self._fuse(Linearised(idx, J, W, innov), measurement=recent)
        if store and len(obs):
            self.store.features.append(obs)
            if self.online is not None:
                self.online.record_features(obs, idx, J, W, innov, self.x)
        return obs

    def linearise_relative(self, rps: list[RelativePose]):
        """Linearise ``ZR`` and ``ZT`` jointly at the current estimate.

        Returns
        -------
        idx : (N, 14) state indices ``[pose i, pose j]``; J : (N, 5, 14);
        W : (N, 5, 5) information of the joint measurement; innov : (N, 5).
        """
        return factors.relative(self.layout, self.x, self.config, rps)

    def fuse_relative(self, rps: list[RelativePose], store: bool = True) -> None:
        """Fuse ``ZR`` and ``ZT`` of each relative pose jointly (5x5 covariance)."""
        if not rps:
            return
        lin = Linearised(*self.linearise_relative(rps))
        self._fuse(lin)
        if store:
            self.store.relative.extend(rps)
            if self.online is not None:
                self.online.record_relative(rps, lin.idx, lin.J, lin.W, lin.innov, self.x)

    # -- recovery (paper eq. 9) -------------------------------------------------------
    def information_matrix(self) -> sp.csc_matrix:
        """``I`` as a sparse matrix ``(dim, dim)``."""
        return self.info.matrix()

    def information_blocks(self) -> Iterator[sp.csc_matrix]:
        """``I`` as consecutive blocks of whole columns (CSC), for a writer that streams it
        (:meth:`~eifslam.estimation.information.InformationStore.column_blocks`)."""
        return self.info.column_blocks()

    def information_nnz(self) -> int:
        """Stored entries of ``I`` (counted without summing it into one matrix)."""
        return self.info.nnz

    def information_vector(self) -> Array:
        """``i`` as a vector ``(dim,)`` (a copy)."""
        return self.info.vector.copy()

    def index_sets(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """State indices of every pose entry ``(7 P,)`` and every feature entry ``(3 F,)``,
        in state order (what :func:`~eifslam.estimation.recovery.factorize` needs)."""
        pids, fids = self.layout.pose_ids, self.layout.feature_ids
        pose_idx = self.layout.pose_columns(pids).ravel() if pids else np.zeros(0, np.int64)
        feat_idx = self.layout.feature_columns(fids).ravel() if fids else np.zeros(0, np.int64)
        return pose_idx, feat_idx

    def factorize(self, matrix: sp.spmatrix) -> SchurFactor:
        """Factorise a ``(dim, dim)`` matrix with the structure of ``I`` (features
        eliminated first), e.g. a damped ``I``; not cached."""
        return factorize(matrix, *self.index_sets())

    def factor(self) -> SchurFactor:
        """The (cached) factorisation of ``I``."""
        if self._factor is None:
            self._factor = self.factorize(self.info.matrix_csr())
        return self._factor

    def cached_factor(self) -> SchurFactor | None:
        """The factorisation of ``I`` if one is cached (None: none since ``I`` changed)."""
        return self._factor

    def invalidate(self) -> None:
        """Drop the cached factorisation: ``I`` or ``i`` were changed from outside
        (e.g. through ``info.set``) or the caller wants covariances refactorised."""
        self._factor = None

    def relinearise(self) -> NDArray[np.bool_]:
        """Rebuild ``I`` and ``i`` from zero at the current ``x``: the gauge and scale
        priors, the weak priors, the quaternion-norm pseudo-measurements
        (:meth:`prior_terms`) and every stored measurement (smoothing, paper III-E). Stored
        ``Zm`` are not gated again: the set the filter accepted is a fixed problem, except
        that a ``Zm`` behind its camera, and those of a feature whose usable views no longer
        constrain it (fewer than two in front of their cameras, or a singular block:
        :func:`~eifslam.estimation.factors.constrained_features`), are left out (the
        feature keeps its weak prior only).

        Returns
        -------
        (N,) bool
            Which ``Zm`` of ``store.all_features()`` were fused: with the stored
            ``ZR``/``ZT`` and :meth:`prior_terms`, the terms of the cost the new
            information's solution minimises to first order.
        """
        self.info.reset()
        self._factor = None
        with self.recovery.corrections():
            return self._refuse_all()

    def _refuse_all(self) -> NDArray[np.bool_]:
        for lin in self.prior_terms():
            self._fuse(lin)
        obs = self.store.all_features()
        ok = np.zeros(len(obs), bool)
        if len(obs):  # a feature whose views no longer constrain it keeps its weak prior only
            ok, idx, J, W, innov, _ = self.linearise_features(obs, gate=False)
            ok = factors.constrained_features(obs.feature, ok, J[:, :, 7:], W, self.config.weak_prior_sigma**-2)
            lin = Linearised(idx[ok], J[ok], W[ok], innov[ok])
            self.info.add_split(lin.idx, *lin.information(self.x), POSE_DIM)  # [pose 7, feature 3]
            self._factor = None
        self.fuse_relative(self.store.relative, store=False)
        return ok

    def recover(self) -> Array:
        """Solve ``I x = i`` and make the result the new linearisation point."""
        x = self.factor().solve(self.info.vector)
        if not np.all(np.isfinite(x)):
            raise EstimatorError("state recovery produced non-finite values")
        self._x[: self.dim] = x
        return self.x

    # -- set from outside (the system layer's bundle adjustment) ---------------------------
    def set_estimate(self, x: Array) -> None:
        """Replace the estimate (the linearisation point) by ``x`` ``(dim,)``, e.g. a
        bundle adjustment's. The information is unchanged; in incremental mode the
        recovery window is rebuilt at the next step (its back-substitution would put the
        previous answer back)."""
        x = np.asarray(x, float)
        if x.shape != (self.dim,):
            raise EstimatorError(f"set_estimate: expected shape ({self.dim},), got {x.shape}")
        self._x[: self.dim] = x
        self.recovery.invalidate()

    def information_form(self) -> "InformationFilter":
        """The problem in information form, on which smoothing, loop correction and scale
        recovery run: this filter itself (see :meth:`set_from_information_form`)."""
        return self

    def set_from_information_form(self, filt: "InformationFilter") -> None:
        """Take back the result of a batch step run on :meth:`information_form`: nothing
        to do, the step changed this filter."""
        if filt is not self:
            raise EstimatorError("set_from_information_form: expected this filter's own information form")

    # -- per-keyframe recovery (the recovery object's) ------------------------------------
    def recover_active(self) -> Array:
        """Per-keyframe recovery by the recovery object (:mod:`.recovery_modes`): exact over
        the active window, other states keeping their last estimate (``"incremental"``), or
        :meth:`recover` (``"full"``)."""
        return self.recovery.recover(self)

    def recover_rebuilt(self) -> Array:
        """:meth:`recover`; in incremental mode by rebuilding the recovery window (about one
        full solve) and back-substituting, so that the window is valid afterwards and the
        next :meth:`recover_active` needs no second rebuild (after :meth:`relinearise`)."""
        return self.recovery.recover_rebuilt(self)

    def recent_estimate(self, steps: int) -> Array:
        """Back-substitute the states marginalised in about the last ``steps`` recoveries
        (exact for those, at a cost bounded by ``steps``; older ones keep their values until
        :meth:`complete_estimate`). Full recovery: nothing to do."""
        return self.recovery.recent(self, steps)

    def recent_features(self, track_ids, steps: int | None = None) -> NDArray[np.bool_]:
        """Which of the map features ``track_ids (N,)`` were measured in the last ``steps``
        recoveries; by default (None) recently enough to be in the recovery's active
        window, the local map whose new measurements the recovery takes in at a cost
        bounded by the window (all of them with the full recovery)."""
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        if not len(ids):
            return np.zeros(0, bool)
        return self.recovery.measured_within(self.layout.feature_columns(ids)[:, 0], steps)

    def local_map(self, steps: int) -> tuple[NDArray[np.int64], Array]:
        """Track ids ``(F,)`` and positions ``(F, 3)`` of the map features measured in the
        last ``steps`` recoveries (every feature with the full recovery), found from the
        recovery's bookkeeping rather than by a pass over every feature."""
        entries = self.recovery.recent_entries(int(steps), self.dim)
        if entries is None:
            ids, X = self.features()
            return np.asarray(ids, np.int64), X
        ids = self.layout.features_starting_at(entries)
        ids = ids[ids >= 0]
        return ids, self.x[self.layout.feature_columns(ids)].reshape(-1, 3) if len(ids) else np.zeros((0, 3))

    def affordable_features(self, track_ids) -> bool:
        """Whether new measurements of the map features ``track_ids`` cost the next
        recovery no solve of the whole state (re-activating those marginalised is cheaper
        than rebuilding the window; always with the full recovery)."""
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        if not len(ids):
            return True
        return self.recovery.affordable(self.layout.feature_columns(ids)[:, 0])

    def complete_estimate(self) -> Array:
        """Back-substitute every marginalised state (``O(n)``), so that ``x`` equals the full
        solve of the information as of the last :meth:`recover_active`. Full recovery:
        nothing to do."""
        return self.recovery.complete(self, self.x)

    # -- sessions -----------------------------------------------------------------------
    def state_dict(self) -> dict:
        """What a session keeps, as arrays and JSON values (:mod:`.statedict`): the layout,
        the complete estimate, ``I`` (CSC arrays) and ``i``, the priors, every stored
        measurement and the incremental recovery's bookkeeping. The filter is not changed."""
        order = self.layout.order
        x = self.recovery.complete(self, self.x.copy())
        I = sp.csc_matrix(self.information_matrix(), copy=True)
        I.sum_duplicates()
        weak = {kind: [(i, v) for (kd, i), v in self.priors.weak.items() if kd == kind] for kind in StateKind}
        batches = self.store.features
        return {
            "is_feature": np.array([k.kind == StateKind.FEATURE for k in order], bool),
            "id": np.array([k.id for k in order], np.int64),
            "x": x,
            "I": {"data": I.data.astype(float), "indices": I.indices.astype(np.int64),
                  "indptr": I.indptr.astype(np.int64)},
            "i": self.information_vector(),
            "prior_pose": {"ids": np.array(list(self.priors.pose), np.int64),
                           "p": np.array([p for p, _ in self.priors.pose.values()], float).reshape(-1, 3),
                           "q": np.array([q for _, q in self.priors.pose.values()], float).reshape(-1, 4)},
            "scale": None if self.priors.scale is None else list(self.priors.scale),
            **{f"weak_{kind.value}": {"ids": np.array([i for i, _ in weak[kind]], np.int64),
                                      "x": np.array([v for _, v in weak[kind]], float).reshape(-1, n)}
               for kind, n in ((StateKind.POSE, POSE_DIM), (StateKind.FEATURE, FEATURE_DIM))},
            "zm": pack_features(self.store.all_features()),
            "zm_batches": np.array([len(b) for b in batches], np.int64),
            "relative": pack_relative(self.store.relative),
            "incremental": self.recovery.state_dict(),
            "online": None if self.recovery.online is None else self.recovery.online.state_dict(),
            "zm_gate": [self.zm_gate.offered, self.zm_gate.refused],
        }

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict` into this (new, empty) filter. The incremental
        recovery's window starts invalid and is rebuilt from ``I`` at the next step.

        Raises
        ------
        SessionError
            On a missing, malformed or inconsistent entry (nothing is trusted).
        """
        if self.layout.n_states:
            raise SessionError("a session loads into a new filter only")
        isf = take(d, "is_feature", bool, (None,))
        ids = take_ids(d, "id", len(isf))
        try:
            for f, i in zip(isf.tolist(), ids.tolist()):
                (self.layout.add_feature if f else self.layout.add_pose)(i)
        except EstimatorError as exc:
            raise SessionError(f"bad state layout: {exc}") from None
        n = self.dim
        self._grow()
        Id = sub(d, "I")
        indptr = take_ids(Id, "indptr", n + 1)
        data = take(Id, "data", np.float64, (None,))
        indices = take_ids(Id, "indices", len(data))
        if indptr[0] != 0 or indptr[-1] != len(data) or np.any(np.diff(indptr) < 0):
            raise SessionError("array 'indptr' is not a CSC column pointer")
        check_index(indices, n, "array 'indices'")
        self.info.set(sp.csc_matrix((data, indices, indptr), shape=(n, n)), take(d, "i", np.float64, (n,)))
        self._x[:n] = take(d, "x", np.float64, (n,))
        pp = sub(d, "prior_pose")
        pids = take_ids(pp, "ids")
        self._check_states(StateKind.POSE, pids, "prior_pose")
        for fid, p, q in zip(pids.tolist(), take(pp, "p", np.float64, (len(pids), 3)),
                             take(pp, "q", np.float64, (len(pids), 4))):
            self.priors.pose[fid] = (p.copy(), q.copy())
        sc = d.get("scale")
        if sc is not None:
            if not (isinstance(sc, list) and len(sc) == 3):
                raise SessionError("entry 'scale' must be [frame_a, frame_b, distance]")
            sd = dict(zip("abd", sc))
            a, b, dist = take_int(sd, "a", 0), take_int(sd, "b", 0), take_float(sd, "d")
            self._check_states(StateKind.POSE, np.array([a, b]), "scale")
            self.priors.scale = (a, b, dist)
        for kind, size in ((StateKind.POSE, POSE_DIM), (StateKind.FEATURE, FEATURE_DIM)):
            w = sub(d, f"weak_{kind.value}")
            wids = take_ids(w, "ids")
            self._check_states(kind, wids, f"weak_{kind.value}")
            for i, v in zip(wids.tolist(), take(w, "x", np.float64, (len(wids), size))):
                self.priors.weak[(kind, i)] = v.copy()
        obs = unpack_features(sub(d, "zm"))
        self._check_states(StateKind.POSE, obs.pose, "zm")
        self._check_states(StateKind.FEATURE, obs.feature, "zm")
        sizes = take_ids(d, "zm_batches")
        if int(sizes.sum()) != len(obs):
            raise SessionError("array 'zm_batches' does not add up to the stored Zm")
        bounds = np.cumsum(sizes)
        self.store.features = [obs.subset(slice(a, b)) for a, b in zip(bounds - sizes, bounds)]
        self.store.relative = unpack_relative(sub(d, "relative"))
        self._check_states(StateKind.POSE, np.array([[r.i, r.j] for r in self.store.relative], np.int64), "relative")
        # after info.set, which clears the recovery's bookkeeping
        self.recovery.load_state_dict(d.get("incremental"), None if d.get("online") is None else sub(d, "online"), n)
        g = d.get("zm_gate", [0, 0])
        if not (isinstance(g, list) and len(g) == 2):
            raise SessionError("entry 'zm_gate' must be [offered, refused]")
        self.zm_gate = GateCount(*(take_int({"zm_gate": v}, "zm_gate", 0) for v in g))
        self._factor = None

    # -- uncertainty ------------------------------------------------------------------
    def covariance(self, idx) -> Array:
        """Marginal covariance of arbitrary state entries ``idx`` (k,)."""
        return self.factor().covariance(np.asarray(idx, np.int64))

    def pose_covariance(self, frame_id: int) -> Array:
        """6x6 covariance of ``[p, dtheta]`` of a pose.

        ``dtheta`` is the right-multiplied rotation error in the camera frame
        (``R_true = R_est @ Exp(dtheta)``), mapped from the 4-vector quaternion block.
        """
        cols = self.layout.pose_columns([frame_id])[0]
        C = self.recovery.pose_covariance(cols)
        if C is None:
            C = self.covariance(cols)
        return pose_tangent_covariance(C, self.x[cols[3:]])

    def feature_covariances(self, track_ids) -> Array:
        """Marginal covariances of map features where they are cheap, for gating.

        Incremental recovery: from the active window as last recovered (exact marginals,
        :meth:`~eifslam.estimation.window.ActiveWindow.feature_covariances`), NaN for a
        feature outside the window or not in the state. Full recovery: from the
        factorisation of ``I`` the recovery caches (made when there is none, e.g. after
        a loaded session, so that the answer does not depend on what was cached).

        Parameters
        ----------
        track_ids : (N,) int
            Feature ids (repeats allowed).

        Returns
        -------
        (N, 3, 3) float
            Covariances, state units squared.
        """
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        out = np.full((len(ids), 3, 3), np.nan)
        known = self.layout.has_features(ids) if len(ids) else np.zeros(0, bool)
        if not known.any():
            return out
        uniq, inv = np.unique(ids[known], return_inverse=True)
        cols = self.layout.feature_columns(uniq)
        C = self.recovery.feature_covariances(self, cols)
        out[known] = C[inv.reshape(-1)]
        return out

    def feature_propagate(self, track_ids, G: Array) -> Array:
        """``G P G^T`` for the joint marginal covariance ``P`` of map features
        (:meth:`propagate` without poses; zero where it is not cheap)."""
        out = self.propagate([], track_ids, G)
        return np.zeros((G.shape[0], G.shape[0])) if out is None else out

    def propagate(self, frame_ids, track_ids, G: Array) -> Array | None:
        """``G P G^T`` for the joint marginal covariance ``P`` of poses and map features,
        where it is cheap: the incremental window as last recovered
        (:meth:`~eifslam.estimation.window.ActiveWindow.propagate`, ``O(F)``); full
        recovery: the cached factorisation. Features outside the window or not in the
        state count as exact.

        Parameters
        ----------
        frame_ids : (Np,) int, distinct pose ids.
        track_ids : (F,) int, distinct feature ids.
        G : (k, 7 Np + 3 F) float, 7 columns per pose (its ``[p, q]`` entries), then 3 per
            feature, in the order given.

        Returns
        -------
        (k, k) float; None when poses are asked for and neither window nor factorisation has them.
        """
        fr = [int(f) for f in np.asarray(frame_ids, np.int64).reshape(-1)]
        ids, G = np.asarray(track_ids, np.int64).reshape(-1), np.asarray(G, float)
        k, n_p = G.shape[0], POSE_DIM * len(fr)
        if not all(self.layout.has_pose(f) for f in fr):
            return None
        have = self.layout.has_features(ids) if len(ids) else np.zeros(0, bool)
        pcols = self.layout.pose_columns(fr) if fr else np.zeros((0, POSE_DIM), np.int64)
        fcols = self.layout.feature_columns(ids[have]) if have.any() else np.zeros((0, 3), np.int64)
        Gh = np.concatenate([G[:, :n_p], G[:, n_p:].reshape(k, len(ids), 3)[:, have].reshape(k, -1)], 1)
        if not fr and not have.any():
            return np.zeros((k, k))
        return self.recovery.propagate(self, pcols[:, 0], fcols[:, 0], Gh)

    def feature_covariance(self, track_id: int) -> Array:
        """3x3 covariance of a map feature."""
        return self.covariance(self.layout.feature_columns([track_id])[0])


__all__ = ["FilterConfig", "GateCount", "InformationFilter", "PriorStore", "Recovery", "POSE_DIM", "FEATURE_DIM"]
