"""The exactly sparse Extended Information Filter (paper III-D, III-G, III-H; pure NumPy/SciPy).

The filter keeps the information matrix ``I`` and vector ``i`` of every pose and map
feature, and the current estimate ``x`` used for linearisation. Fusing a measurement
(paper eq. 8) touches only the blocks of the states it involves, so ``I`` stays exactly
sparse. Gauge and quaternion handling follow METHOD.md §6.1-6.2:

* the first pose gets a strong prior (position and quaternion) at its initial value;
* one scale prior fixes the distance between two poses (by default the first two);
* every pose gets a pseudo-measurement ``|q|^2 = 1`` (the models are invariant to the
  quaternion's norm, so this is the only information in that direction).

Priors and pseudo-measurements are stored with the measurements, so smoothing
(:mod:`eifslam.smoothing`) relinearises them too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from ..geometry import models
from ..geometry.camera import PinholeCamera
from ..errors import ConfigError, EstimatorError
from ..geometry.rotations import quat_left_matrix, quat_normalize
from .information import InformationStore
from .state import FEATURE_DIM, POSE_DIM, StateLayout
from .measurements import FeatureObservations, MeasurementStore, RelativePose
from .recovery import SchurFactor, factorize
from .incremental import IncrementalRecovery, TrackedInformationStore

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FilterConfig:
    """Settings of the information filter.

    Attributes
    ----------
    prior_sigma : float
        Standard deviation of the first-pose prior (position units, and quaternion units).
    scale_prior_sigma : float
        Relative standard deviation of the scale prior (fraction of the prior distance).
    quat_norm_sigma : float
        Standard deviation of the ``|q|^2 = 1`` pseudo-measurement.
    zt_form : {"auto", "paper", "bearing"}
        ``ZT`` model: the paper's ``[x/z, y/z]``, the non-singular bearing form, or the
        paper's form when the measured direction is within ``zt_paper_max_angle_deg`` of
        the optical axis and the bearing form otherwise.
    zt_paper_max_angle_deg : float
        Largest angle between the translation direction and the optical axis for which
        ``auto`` uses the paper's form.
    gate_chi2 : float or None
        Reject a ``Zm`` whose normalised innovation squared exceeds this (2 DOF); ``None``
        fuses everything.
    min_depth : float
        Reject a ``Zm`` whose predicted depth is below this (state units).
    weak_prior_sigma : float
        Standard deviation of a weak prior put on every new pose position and feature at
        its initial guess, so that a state whose measurements were all rejected (gate,
        depth) never makes ``I`` singular. Its information, ``1e-6`` by default, is
        negligible next to any measurement's; it touches diagonal blocks only.
    """

    prior_sigma: float = 1e-6
    scale_prior_sigma: float = 1e-6
    quat_norm_sigma: float = 1e-3
    zt_form: str = "auto"
    zt_paper_max_angle_deg: float = 60.0
    gate_chi2: float | None = None
    min_depth: float = 1e-6
    weak_prior_sigma: float = 1e3

    def __post_init__(self) -> None:
        for key in ("prior_sigma", "scale_prior_sigma", "quat_norm_sigma", "min_depth", "weak_prior_sigma"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"filter.{key} must be a positive number, got {v!r}")
        if self.zt_form not in ("auto", "paper", "bearing"):
            raise ConfigError(f"filter.zt_form must be auto, paper or bearing, got {self.zt_form!r}")
        if not 0.0 < self.zt_paper_max_angle_deg < 90.0:
            raise ConfigError("filter.zt_paper_max_angle_deg must lie in (0, 90)")
        if self.gate_chi2 is not None and not self.gate_chi2 > 0:
            raise ConfigError("filter.gate_chi2 must be positive or None")


@dataclass
class PriorStore:
    """Priors kept for relinearisation: first pose and scale."""

    pose: dict[int, tuple[Array, Array]] = field(default_factory=dict)  # fid -> (p, q)
    scale: tuple[int, int, float] | None = None  # (fid_a, fid_b, distance)
    weak: dict[tuple[str, int], Array] = field(default_factory=dict)  # weak priors at initial guesses


class InformationFilter:
    """Exactly sparse EIF over camera poses and map features.

    Parameters
    ----------
    camera : PinholeCamera
        Intrinsics used by ``Zm`` (pixels are undistorted).
    config : FilterConfig
    recovery : {"incremental", "full"}
        What :meth:`recover_active` (the per-frame recovery) does: solve exactly an active
        window of recent states and marginalise the rest (:mod:`eifslam.incremental`;
        default, constant time per frame during an exploration, see ``docs/backend.md``),
        or solve the whole system (:meth:`recover`). :meth:`recover` is always the full
        solve; :meth:`complete_estimate` back-substitutes the marginalised states.
    window : int
        Incremental recovery only: steps without a measurement before a state leaves the
        active window.
    """

    def __init__(
        self, camera: PinholeCamera, config: FilterConfig | None = None,
        recovery: str = "incremental", window: int = 2,
    ) -> None:
        self.camera = camera
        self.config = config or FilterConfig()
        self.layout = StateLayout()
        self.info = InformationStore()
        self.store = MeasurementStore()
        self.priors = PriorStore()
        self._x = np.zeros(64)
        self._factor: SchurFactor | None = None
        # -- incremental recovery hook (eifslam.incremental) --
        if recovery not in ("full", "incremental"):
            raise ConfigError(f"recovery must be 'full' or 'incremental', got {recovery!r}")
        self.recovery = recovery
        self.incremental: IncrementalRecovery | None = None
        if recovery == "incremental":
            self.incremental = IncrementalRecovery(window, window)
            self.info = TrackedInformationStore()
            self.info.listeners.append(self.incremental)
        # -- end incremental recovery hook --

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
            new = np.zeros(max(n, 2 * len(self._x)))
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
        self._fuse_quat_norm(np.array([frame_id]))
        self.priors.weak[("pose", int(frame_id))] = np.concatenate([p, q])
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
            self.priors.weak[("feature", int(tid))] = xyz.copy()
        self._factor = None
        if len(X):
            self._fuse_weak(self.layout.feature_columns(list(track_ids)), X)

    def _fuse_weak(self, cols, X: Array) -> None:
        """Weak prior ``X ~ N(X0, weak_prior_sigma^2 I)`` on state entries ``cols`` (N, k)."""
        w = 1.0 / self.config.weak_prior_sigma**2
        k = cols.shape[1]
        self.info.add(cols, np.broadcast_to(w * np.eye(k), (len(cols), k, k)).copy(), w * X)
        self._factor = None

    def refuse_weak_priors(self) -> None:
        """Fuse every weak prior again (smoothing starts from zero information)."""
        for kind, columns in (("pose", self.layout.pose_columns), ("feature", self.layout.feature_columns)):
            keys = [i for (kd, i) in self.priors.weak if kd == kind]
            if keys:
                self._fuse_weak(columns(keys), np.stack([self.priors.weak[(kind, i)] for i in keys]))

    def pose(self, frame_id: int) -> tuple[Array, Array]:
        """Estimated ``(p (3,), q_wc (4,) unit)`` of a pose."""
        s = self.layout.pose_slice(frame_id)
        v = self.x[s]
        return v[:3].copy(), quat_normalize(v[3:])

    def poses(self) -> tuple[list[int], Array, Array]:
        """Frame ids, positions ``(P, 3)`` and unit quaternions ``(P, 4)`` of every pose."""
        ids = self.layout.pose_ids
        cols = self.layout.pose_columns(ids) if ids else np.zeros((0, 7), np.int64)
        v = self.x[cols]
        return ids, v[:, :3].copy(), quat_normalize(v[:, 3:]) if len(ids) else np.zeros((0, 4))

    def features(self) -> tuple[list[int], Array]:
        """Track ids and positions ``(F, 3)`` of every map feature."""
        ids = self.layout.feature_ids
        cols = self.layout.feature_columns(ids) if ids else np.zeros((0, 3), np.int64)
        return ids, self.x[cols].copy()

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
        cols = self.layout.pose_columns([fid])  # (1, 7)
        w = 1.0 / self.config.prior_sigma**2
        z = np.concatenate([p, q])
        Lam = w * np.eye(7)[None]
        self.info.add(cols, Lam, (w * z)[None])
        self._factor = None

    def _fuse_scale(self, fa: int, fb: int, d: float) -> None:
        ca = self.layout.pose_columns([fa])[:, :3]
        cb = self.layout.pose_columns([fb])[:, :3]
        a, b = self.x[ca], self.x[cb]
        h, Ja, Jb = models.distance_model(a, b)
        J = np.concatenate([Ja, Jb], axis=2)
        w = np.array([[[1.0 / (self.config.scale_prior_sigma * d) ** 2]]])
        self._add_linearised(np.concatenate([ca, cb], 1), J, w, (d - h)[:, None])

    def _fuse_quat_norm(self, fids) -> None:
        cols = self.layout.pose_columns(list(fids))[:, 3:]
        h, J = models.quat_norm_model(self.x[cols])
        w = np.full((len(cols), 1, 1), 1.0 / self.config.quat_norm_sigma**2)
        self._add_linearised(cols, J, w, (1.0 - h)[:, None])

    # -- fusion (paper eq. 8) -----------------------------------------------------------
    def _add_linearised(self, idx, J: Array, W: Array, innov: Array) -> None:
        """``I += J^T W J``, ``i += J^T W (innov + J x)`` for N measurements.

        Parameters
        ----------
        idx : (N, k) state indices; J : (N, m, k); W : (N, m, m) information;
        innov : (N, m) ``z - h(x)``.
        """
        Jt = np.swapaxes(J, 1, 2)
        JtW = Jt @ W
        Lam = JtW @ J
        eta = np.einsum("nkm,nm->nk", JtW, innov + np.einsum("nmk,nk->nm", J, self.x[idx]))
        self.info.add(idx, Lam, eta)
        self._factor = None

    def linearise_features(self, obs: FeatureObservations, gate: bool = True):
        """Linearise ``Zm`` at the current estimate.

        Returns
        -------
        ok : (N,) bool, usable (predicted depth above ``min_depth``, finite, inside the gate).
        idx : (N, 10) state indices ``[pose 7, feature 3]``; J : (N, 2, 10);
        W : (N, 2, 2) information; innov : (N, 2) ``z - h(x)``; chi2 : (N,) normalised
        innovation squared (``inf`` where not finite or behind the camera).
        """
        pc = self.layout.pose_columns(obs.pose)
        fc = self.layout.feature_columns(obs.feature)
        x, c = self.x, self.camera
        h, Jp, Jf, depth = models.feature_model(x[pc[:, :3]], x[pc[:, 3:]], x[fc], c.fx, c.fy, c.cx, c.cy)
        innov = obs.uv - h
        chi2 = np.sum(innov**2, 1) / obs.sigma_px**2
        ok = (depth > self.config.min_depth) & np.isfinite(chi2)
        chi2 = np.where(ok, chi2, np.inf)
        if gate and self.config.gate_chi2 is not None:
            ok &= chi2 <= self.config.gate_chi2
        W = np.eye(2)[None] / (obs.sigma_px**2)[:, None, None]
        return ok, np.concatenate([pc, fc], 1), np.concatenate([Jp, Jf], 2), W, innov, chi2

    def fuse_features(self, obs: FeatureObservations, store: bool = True, gate: bool = True) -> FeatureObservations:
        """Fuse a batch of ``Zm``; return the measurements actually fused.

        Measurements whose predicted depth is below ``min_depth`` or whose innovation
        fails the ``gate_chi2`` test are skipped (never fused as NaN/inf).
        """
        if len(obs) == 0:
            return obs
        ok, idx, J, W, innov, _ = self.linearise_features(obs, gate)
        if not np.all(ok):
            obs, idx, J, W, innov = obs.subset(ok), idx[ok], J[ok], W[ok], innov[ok]
        self._add_linearised(idx, J, W, innov)
        if store and len(obs):
            self.store.features.append(obs)
        return obs

    def _zt_uses_paper(self, t: Array) -> Array:
        form = self.config.zt_form
        if form == "paper":
            return np.ones(len(t), bool)
        if form == "bearing":
            return np.zeros(len(t), bool)
        return t[:, 2] >= np.cos(np.radians(self.config.zt_paper_max_angle_deg))

    def linearise_relative(self, rps: list[RelativePose]):
        """Linearise ``ZR`` and ``ZT`` jointly at the current estimate.

        Returns
        -------
        idx : (N, 14) state indices ``[pose i, pose j]``; J : (N, 5, 14);
        W : (N, 5, 5) information of the joint measurement; innov : (N, 5).
        """
        ci = self.layout.pose_columns([r.i for r in rps])
        cj = self.layout.pose_columns([r.j for r in rps])
        qm = np.stack([r.q_ij for r in rps])
        tm = np.stack([r.t_ij for r in rps])
        cov = np.stack([r.cov for r in rps])
        x = self.x
        hR, JRi, JRj = models.rotation_model(x[ci[:, 3:]], x[cj[:, 3:]], qm)
        N = len(rps)
        J = np.zeros((N, 5, 14))
        J[:, :3, 3:7], J[:, :3, 10:14] = JRi, JRj
        innov = np.zeros((N, 5))
        innov[:, :3] = -hR
        paper = self._zt_uses_paper(tm)
        hB, JBi, JBj = models.bearing_model(x[ci[:, :3]], x[ci[:, 3:]], x[cj[:, :3]], tm)
        T = np.broadcast_to(np.eye(5), (N, 5, 5)).copy()
        J[:, 3:, :7], J[:, 3:, 7:] = JBi, JBj
        innov[:, 3:] = -hB
        if np.any(paper):
            hT, JTi, JTj = models.translation_model(x[ci[paper, :3]], x[ci[paper, 3:]], x[cj[paper, :3]])
            zT, G = models.zt_paper_covariance(tm[paper])
            J[paper, 3:, :7], J[paper, 3:, 7:] = JTi, JTj
            innov[paper, 3:] = zT - hT
            T[paper, 3:, 3:] = G
        Q = T @ cov @ np.swapaxes(T, 1, 2)
        W = np.linalg.inv(Q)
        if not np.all(np.isfinite(W)) or not np.all(np.isfinite(innov)):
            raise EstimatorError("relative pose measurement produced a non-finite information")
        return np.concatenate([ci, cj], 1), J, 0.5 * (W + np.swapaxes(W, 1, 2)), innov

    def fuse_relative(self, rps: list[RelativePose], store: bool = True) -> None:
        """Fuse ``ZR`` and ``ZT`` of each relative pose jointly (5x5 covariance)."""
        if not rps:
            return
        self._add_linearised(*self.linearise_relative(rps))
        if store:
            self.store.relative.extend(rps)

    # -- recovery (paper eq. 9) -------------------------------------------------------
    def information_matrix(self) -> sp.csc_matrix:
        """``I`` as a sparse matrix ``(dim, dim)``."""
        return self.info.matrix()

    def information_vector(self) -> Array:
        """``i`` as a vector ``(dim,)`` (a copy)."""
        return self.info.vector.copy()

    def _index_sets(self) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        pids, fids = self.layout.pose_ids, self.layout.feature_ids
        pose_idx = self.layout.pose_columns(pids).ravel() if pids else np.zeros(0, np.int64)
        feat_idx = self.layout.feature_columns(fids).ravel() if fids else np.zeros(0, np.int64)
        return pose_idx, feat_idx

    def factor(self) -> SchurFactor:
        """The (cached) factorisation of ``I``."""
        if self._factor is None:
            self._factor = factorize(self.info.matrix(), *self._index_sets())
        return self._factor

    def recover(self) -> Array:
        """Solve ``I x = i`` and make the result the new linearisation point."""
        x = self.factor().solve(self.info.vector)
        if not np.all(np.isfinite(x)):
            raise EstimatorError("state recovery produced non-finite values")
        self._x[: self.dim] = x
        return self.x

    # -- incremental recovery (eifslam.incremental) -------------------------------------
    def recover_active(self) -> Array:
        """Per-frame recovery: exact over the active window (``recovery="incremental"``;
        other states keep their last estimate) or :meth:`recover` (``"full"``)."""
        if self.incremental is None:
            return self.recover()
        try:
            self.incremental.step(self.layout, self.info, self._x[: self.dim])
        except EstimatorError:
            # the dense window could not be solved (numerically indefinite): rebuild it at
            # the next step and use the full sparse solve for this one
            self.incremental.on_invalidate()
            self.incremental.stats.fallbacks += 1
            return self.recover()
        return self.x

    def complete_estimate(self) -> Array:
        """Incremental mode: back-substitute every marginalised state (``O(n)``), so that
        ``x`` equals the full solve of the information as of the last
        :meth:`recover_active`. Full mode: nothing to do."""
        if self.incremental is not None and self.incremental.valid:
            self.incremental.full_solution(self._x[: self.dim])
        return self.x

    # -- set from outside (issue 11: bundle adjustment in the system layer) ----------------
    def set_estimate(self, x: Array) -> None:
        """Replace the estimate (the linearisation point) by ``x`` ``(dim,)``, e.g. a
        bundle adjustment's. The information is unchanged; in incremental mode the
        recovery window is rebuilt at the next step (its back-substitution would put the
        previous answer back)."""
        x = np.asarray(x, float)
        if x.shape != (self.dim,):
            raise EstimatorError(f"set_estimate: expected shape ({self.dim},), got {x.shape}")
        self._x[: self.dim] = x
        if self.incremental is not None:
            self.incremental.on_invalidate()

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
        C = self.incremental.pose_covariance(cols) if self.incremental is not None else None
        if C is None:
            C = self.covariance(cols)
        q = self.x[cols[3:]]
        n = np.linalg.norm(q)
        qn = q / n
        # dtheta = 2 vec(q_est^* ⊗ q) for a small change of the normalised quaternion
        G = 2.0 * quat_left_matrix(qn * np.array([1, -1, -1, -1]))[1:] @ ((np.eye(4) - np.outer(qn, qn)) / n)
        T = np.zeros((6, 7))
        T[:3, :3] = np.eye(3)
        T[3:, 3:] = G
        return T @ C @ T.T

    def feature_covariance(self, track_id: int) -> Array:
        """3x3 covariance of a map feature."""
        return self.covariance(self.layout.feature_columns([track_id])[0])


__all__ = ["FilterConfig", "InformationFilter", "POSE_DIM", "FEATURE_DIM"]
