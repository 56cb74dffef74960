"""The active window of incremental recovery and the conditionals of what left it.

:class:`ActiveWindow` holds the *marginal* information of the active states in the
structure of the reduced camera system (see :mod:`eifslam.estimation.incremental`):

* active poses: a dense block ``P`` (``7 p x 7 p``) and vector ``bp``;
* active features: 3x3 blocks ``D`` and vector ``bf``, coupled to the active poses by
  ``B`` (``3 f x 7 p``).

It adds fused blocks into the window (:meth:`ActiveWindow._route`), solves it exactly
(:meth:`ActiveWindow._solve`), eliminates stale states into conditionals
(:meth:`ActiveWindow._marginalise`) and back-substitutes the conditionals
(:meth:`ActiveWindow.full_solution`); undoing eliminations when a measurement touches an
eliminated state is :mod:`eifslam.estimation.reactivation`'s. When and what to do is decided by
the driver, :class:`~eifslam.estimation.incremental.IncrementalRecovery`, which
subclasses it. Pure NumPy/SciPy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve, solve

from ..errors import EstimatorError
from .backsub import BackSubstitution, Conditional
from .schur import coupled_poses, subtract_gram
from .state import FEATURE_DIM, POSE_DIM

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class RecoveryStats:
    """Counters of :class:`IncrementalRecovery`.

    Attributes
    ----------
    steps : recoveries done.
    fallbacks : steps where a measurement touched a marginalised state that could not be
        re-activated (full rebuild), plus solves that failed (see
        :meth:`eifslam.estimation.filter.InformationFilter.recover_active`).
    rebuilds : full rebuilds for any reason (fallbacks, ``I`` reset/set, first use).
    reactivations : steps where a measurement touched marginalised states and they were
        re-activated (their conditionals undone, no rebuild).
    reactivated_poses, reactivated_features : states brought back into the window so far
        (the touched ones and the later-eliminated poses they were conditioned on).
    marginalised_poses, marginalised_features : states eliminated so far (re-eliminations
        included).
    window_poses, window_features : size of the active window after the last step.
    max_window_poses : largest number of active poses solved in one step.
    indefinite_solves : steps whose pose Schur complement was numerically indefinite
        (solved by ``LDL^T`` instead of Cholesky; see :meth:`IncrementalRecovery._solve`).
    """

    steps: int = 0
    fallbacks: int = 0
    rebuilds: int = 0
    reactivations: int = 0
    reactivated_poses: int = 0
    reactivated_features: int = 0
    marginalised_poses: int = 0
    marginalised_features: int = 0
    window_poses: int = 0
    window_features: int = 0
    max_window_poses: int = 0
    indefinite_solves: int = 0


def _scatter_add(A: Array, flat: IntArray, v: Array) -> None:
    """``A.flat[flat] += v`` (C order) with repeated indices summed, in ``O(len(v) log len(v))``
    (not ``O(A.size)``: the window's ``P`` has up to ~10^6 entries)."""
    if len(v):
        u, inv = np.unique(flat, return_inverse=True)
        A[np.unravel_index(u, A.shape)] += np.bincount(inv.ravel(), v, minlength=len(u))  # u unique


def _cholesky_3x3(D: Array) -> Array:
    """Lower Cholesky factors of ``(F, 3, 3)`` blocks; raises if a block is not positive definite."""
    try:
        return np.linalg.cholesky(D)
    except np.linalg.LinAlgError:
        raise EstimatorError("a feature has no information in some direction (seen from one pose only?)") from None


def pose_cholesky(A: Array) -> tuple[Array, bool]:
    """``cho_factor(A, lower=True)`` of the information of poses being eliminated; raises
    :class:`EstimatorError` when ``A`` is numerically indefinite (``I`` too ill-conditioned
    for a Cholesky factorisation), so that the caller falls back to a full sparse solve
    instead of stopping the run."""
    try:
        return cho_factor(A, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        raise EstimatorError(f"the information of {len(A) // POSE_DIM} pose(s) to eliminate is numerically "
                             "indefinite") from None


def spd_inverse_3x3(D: Array) -> Array:
    """Inverses of ``(F, 3, 3)`` blocks; raises if a block is not positive definite."""
    try:
        np.linalg.cholesky(D)
    except np.linalg.LinAlgError:
        raise EstimatorError("a feature has no information in some direction (seen from one pose only?)") from None
    return np.linalg.inv(D)


class ActiveWindow:
    """The active window's marginal information and the conditionals of eliminated states.

    Attributes
    ----------
    pidx, fidx : (7 p,), (3 f,) int64
        State indices of the active poses and features.
    P, bp : (7 p, 7 p), (7 p,)
        Marginal information of the active poses.
    D, bf : (f, 3, 3), (3 f,)
        Information blocks of the active features.
    B : (3 f, 7 p)
        Feature-pose coupling.
    xp, xf : (7 p,), (3 f,)
        The last solution of the window.

    The driver sets, before use: ``feature_window``, ``pose_window`` (int), ``stats``
    (:class:`RecoveryStats`), ``_map`` (an ``EntryMap``: per-entry kind and block start),
    ``_last`` (step of the last measurement of each block), ``_pos`` (window position
    of each entry, ``-1`` when eliminated), ``_owner`` (slot in ``_conds`` of each
    eliminated entry, else ``-1``) and ``_conds`` (conditionals in elimination order,
    ``None`` once undone).
    """

    feature_window: int
    pose_window: int
    stats: RecoveryStats

    @staticmethod
    def empty_window() -> dict:
        """The fields of an empty window (no active state, nothing solved)."""
        return dict(pidx=np.zeros(0, np.int64), fidx=np.zeros(0, np.int64), P=np.zeros((0, 0)), bp=np.zeros(0),
                    D=np.zeros((0, 3, 3)), bf=np.zeros(0), B=np.zeros((0, 0)), xp=np.zeros(0), xf=np.zeros(0),
                    _S_cho=None, _S_pidx=np.zeros(0, np.int64), _S_fidx=np.zeros(0, np.int64),
                    _Dinv=np.zeros((0, 3, 3)), _DB=np.zeros((0, 0)), _W=np.zeros((0, 0)),
                    _coupled=np.zeros((0, 0), bool), _W_of=None)

    def _reset_window(self) -> None:
        self.__dict__.update(self.empty_window())

    @property
    def active_indices(self) -> IntArray:
        """State indices of the active window (poses then features)."""
        return np.concatenate([self.pidx, self.fidx])

    def pose_covariance(self, cols: IntArray) -> Array | None:
        """Marginal covariance of active pose entries ``cols`` (k,) from the window.

        The window holds the exact marginal information of its states, so the block of
        the inverse of its pose Schur complement is the exact marginal covariance.
        Returns None when an entry is not an active pose or the window is stale.
        """
        if not self._valid or getattr(self, "_S_cho", None) is None:
            return None
        where = {int(v): i for i, v in enumerate(self._S_pidx)}  # the window as solved
        pos = [where.get(int(c), -1) for c in cols]
        if min(pos) < 0:
            return None
        E = np.zeros((len(self._S_pidx), len(pos)))
        E[pos, np.arange(len(pos))] = 1.0
        C = cho_solve(self._S_cho, E)[pos]
        return 0.5 * (C + C.T)

    def feature_covariances(self, starts: IntArray) -> Array:
        """Marginal covariances of features from the window as last solved.

        ``D_f^-1 + (D^-1 B)_f S^-1 (D^-1 B)_f^T`` (``S`` the pose Schur complement): the
        window holds the exact marginal information of its states, so this is the
        feature's exact marginal covariance as of the last :meth:`_solve` (before what
        was fused since).

        Parameters
        ----------
        starts : (F,) int
            State index of each feature's first entry.

        Returns
        -------
        (F, 3, 3) float
            Covariances (state units squared); NaN for a feature that was not active at
            the last solve (or when the window is stale).
        """
        starts = np.asarray(starts, np.int64).reshape(-1)
        out = np.full((len(starts), 3, 3), np.nan)
        fidx = getattr(self, "_S_fidx", np.zeros(0, np.int64))
        if not self._valid or len(fidx) == 0 or len(self._Dinv) != len(fidx) // 3:
            return out
        where = {int(v): i for i, v in enumerate(fidx[::3])}
        blk = np.array([where.get(int(c), -1) for c in starts], np.int64)
        sel = blk >= 0
        if not sel.any():
            return out
        C = self._Dinv[blk[sel]].copy()
        npw = len(self._S_pidx)
        if self._S_cho is not None and npw and self._DB.shape == (len(fidx), npw):
            DB = self._DB.reshape(-1, 3, npw)[blk[sel]]  # (m, 3, 7p)
            X = cho_solve(self._S_cho, DB.reshape(-1, npw).T).T.reshape(DB.shape)
            C += DB @ X.transpose(0, 2, 1)
        out[sel] = 0.5 * (C + C.transpose(0, 2, 1))
        return out

    def feature_propagate(self, starts: IntArray, G: Array) -> Array:
        """``G P G^T`` for the joint marginal covariance ``P`` of features, from the window
        as last solved, without forming ``P`` (:meth:`propagate` without poses).

        Parameters
        ----------
        starts : (F,) int
            State index of each feature's first entry (distinct).
        G : (k, 3 F) float
            A linear map of the features' errors (3 columns per feature, in order).

        Returns
        -------
        (k, k) float
        """
        out = self.propagate(np.zeros(0, np.int64), starts, G)
        return np.zeros((G.shape[0], G.shape[0])) if out is None else out

    def propagate(self, pose_starts: IntArray, starts: IntArray, G: Array) -> Array | None:
        """``G P G^T`` for the joint marginal covariance ``P`` of active poses and
        features, from the window as last solved, without forming ``P``.

        With ``I`` over the window ``[[P, B^T], [B, D]]`` (poses, features) and ``S = P -
        B^T D^-1 B``, the covariance is ``S^-1`` over the poses, ``-D^-1 B S^-1`` between
        features and poses and ``D^-1 + D^-1 B S^-1 B^T D^-1`` over the features, so ``G P
        G^T = sum_f G_f D_f^-1 G_f^T + H S^-1 H^T`` with ``H = G_p - G_f D^-1 B``: ``O(F)``.
        Features that were not active at the last :meth:`_solve` count as exact (zero
        covariance, no correlation).

        Parameters
        ----------
        pose_starts : (Np,) int
            State index of each pose's first entry (distinct).
        starts : (F,) int
            State index of each feature's first entry (distinct).
        G : (k, 7 Np + 3 F) float
            A linear map of the states' errors: 7 columns per pose (``[p, q]``, the state's
            own entries), then 3 per feature, in the order given.

        Returns
        -------
        (k, k) float, or None when a pose was not active at the last solve (or the window
        is stale and poses were asked for).
        """
        pose_starts = np.asarray(pose_starts, np.int64).reshape(-1)
        starts = np.asarray(starts, np.int64).reshape(-1)
        G = np.asarray(G, float)
        k, n_p = G.shape[0], POSE_DIM * len(pose_starts)
        out = np.zeros((k, k))
        npw = len(self._S_pidx)
        H = np.zeros((k, npw))
        if len(pose_starts):
            if not self._valid or self._S_cho is None:
                return None
            where_p = {int(v): i for i, v in enumerate(self._S_pidx)}
            pos = [where_p.get(int(c), -1) for c in (pose_starts[:, None] + np.arange(POSE_DIM)).ravel()]
            if min(pos) < 0:
                return None
            np.add.at(H.T, np.asarray(pos), G[:, :n_p].T)
        fidx = getattr(self, "_S_fidx", np.zeros(0, np.int64))
        if self._valid and len(fidx) and len(self._Dinv) == len(fidx) // 3 and len(starts):
            where = {int(v): i for i, v in enumerate(fidx[::3])}
            blk = np.array([where.get(int(c), -1) for c in starts], np.int64)
            have = blk >= 0
            if have.any():
                b = blk[have]
                Gh = G[:, n_p:].reshape(k, len(starts), 3)[:, have]  # (k, m, 3)
                GD = np.einsum("kmi,mij->kmj", Gh, self._Dinv[b])
                out += np.einsum("kmj,lmj->kl", GD, Gh)
                if self._S_cho is not None and npw and self._DB.shape == (len(fidx), npw):
                    H -= np.einsum("kmi,mip->kp", Gh, self._DB.reshape(-1, 3, npw)[b])
        if self._S_cho is not None and npw and np.any(H):
            out += H @ cho_solve(self._S_cho, H.T)
        return 0.5 * (out + out.T)

    def recent_solution(self, x: Array, slots: int) -> Array:
        """:meth:`full_solution` for the states of the last ``slots`` conditionals only
        (about two a step: one feature batch, one pose batch), exact for those; older
        marginalised states keep the values ``x`` has. The cost is bounded by ``slots``,
        not by the size of the state."""
        if len(self.xp) != len(self.pidx) or len(self.xf) != len(self.fidx):
            return x
        x[self.pidx], x[self.fidx] = self.xp, self.xf
        backsub = self.__dict__.get("_backsub")
        if backsub is None:
            backsub = self._backsub = BackSubstitution()
        return backsub.apply(self._conds, x, start=len(self._conds) - int(slots))

    def full_solution(self, x: Array) -> Array:
        """Back-substitute every marginalised state into ``x`` (in place) in ``O(n)``
        (:class:`~eifslam.estimation.backsub.BackSubstitution`: the poses newest first,
        then the features in merged chunks).

        ``x`` must hold the current window solution (as :meth:`step` left it); entries
        added to the layout after the last step are left untouched.
        """
        if len(self.xp) != len(self.pidx) or len(self.xf) != len(self.fidx):
            return x  # the window changed without a solve: nothing consistent to add
        x[self.pidx], x[self.fidx] = self.xp, self.xf
        backsub = self.__dict__.get("_backsub")
        if backsub is None:
            backsub = self._backsub = BackSubstitution()
        return backsub.apply(self._conds, x)

    # -- window maintenance -------------------------------------------------------------
    def _append(self, new: list[tuple[bool, int]]) -> None:
        """New states join the window with zero information."""
        if not new:
            return
        pn = np.concatenate([np.arange(o, o + POSE_DIM) for f, o in new if not f] or [np.zeros(0, np.int64)])
        fn = np.concatenate([np.arange(o, o + FEATURE_DIM) for f, o in new if f] or [np.zeros(0, np.int64)])
        p0, f0 = len(self.pidx), len(self.fidx)
        p1, f1 = p0 + len(pn), f0 + len(fn)
        if len(pn):
            P = np.zeros((p1, p1))
            P[:p0, :p0] = self.P
            self.P, self.bp = P, np.concatenate([self.bp, np.zeros(len(pn))])
            self.pidx = np.concatenate([self.pidx, pn])
        self.D = np.concatenate([self.D, np.zeros((len(fn) // 3, 3, 3))])
        self.bf = np.concatenate([self.bf, np.zeros(len(fn))])
        self.fidx = np.concatenate([self.fidx, fn])
        B = np.zeros((f1, p1))
        B[:f0, :p0] = self.B
        self.B = B
        self._pos[pn] = np.arange(p0, p1)
        self._pos[fn] = np.arange(f0, f1)

    def _route(self, idx: IntArray, Lam: Array, eta: Array) -> None:
        """Add ``N`` blocks ``(idx (N,k), Lam (N,k,k), eta (N,k))`` into the window."""
        k = idx.shape[1]
        r = np.repeat(idx, k, axis=1).ravel()
        c = np.tile(idx, (1, k)).ravel()
        v = Lam.ravel()
        isf = self._map.is_feature
        fr, fc = isf[r], isf[c]
        pr, pc = self._pos[r], self._pos[c]
        m = ~fr & ~fc
        _scatter_add(self.P, pr[m] * self.P.shape[1] + pc[m], v[m])
        m = fr & ~fc
        _scatter_add(self.B, pr[m] * self.B.shape[1] + pc[m], v[m])
        m = fr & fc
        if np.any(self._map.start[r[m]] != self._map.start[c[m]]):
            raise EstimatorError("two features share a measurement: the information matrix is not of SLAM form")
        _scatter_add(self.D, 3 * pr[m] + pc[m] % 3, v[m])  # D[f, a, c] at 9 f + 3 a + c
        e, ev = idx.ravel(), eta.ravel()
        fe = isf[e]
        self.bp += np.bincount(self._pos[e[~fe]], ev[~fe], minlength=len(self.bp))
        self.bf += np.bincount(self._pos[e[fe]], ev[fe], minlength=len(self.bf))

    def _solve(self) -> None:
        """``x`` of the window: Schur complement onto the poses, dense Cholesky.

        When the Cholesky factorisation fails (the pose Schur complement is numerically
        indefinite: ``I`` itself is then too ill-conditioned for any Cholesky, the full
        sparse solve meets negative pivots as well), the same system is solved by a
        symmetric indefinite factorisation (Bunch-Kaufman ``LDL^T``) and the event is
        counted in :attr:`RecoveryStats.indefinite_solves`. The window stays valid: it is
        the exact marginal information of its states, rebuilding it would give the same
        matrix.
        """
        F, npw = len(self.D), len(self.pidx)
        Linv = np.linalg.inv(_cholesky_3x3(self.D)) if F else np.zeros((0, 3, 3))  # D_f = L L^T
        self._Dinv = Linv.transpose(0, 2, 1) @ Linv
        B3 = self.B.reshape(F, 3, npw)
        self._DB = (self._Dinv @ B3).reshape(3 * F, npw)
        Dbf = np.einsum("fij,fj->fi", self._Dinv, self.bf.reshape(F, 3)).ravel()
        r = self.bp - self.B.T @ Dbf
        self._S_cho, self._S_pidx, self._S_fidx = None, self.pidx.copy(), self.fidx.copy()
        self._W, self._coupled, self._W_of = np.zeros((0, npw)), np.zeros((0, npw // POSE_DIM), bool), None
        if npw:
            # S = P - B^T D^-1 B = P - W^T W with W = L^-1 B, lower triangle only, by
            # chunks of the staircase of B (a feature is coupled to the few poses that
            # saw it; :mod:`.schur`)
            W = (Linv @ B3).reshape(3 * F, npw)
            S = self.P.copy()
            if F:
                self._W, self._coupled = W, coupled_poses(self.B, npw // POSE_DIM)
                self._W_of = self.B  # the coupling W was made of (_marginalise reuses it)
                subtract_gram(S, W, self._coupled)
            try:
                self._S_cho = cho_factor(S, lower=True, check_finite=False)
                xp = cho_solve(self._S_cho, r)
            except np.linalg.LinAlgError:
                try:
                    xp = solve(S, r, assume_a="sym", lower=True, check_finite=False)
                except np.linalg.LinAlgError:
                    raise EstimatorError("information matrix is singular; is the gauge fixed?") from None
                self.stats.indefinite_solves += 1
        else:
            xp = r
        xf = Dbf - np.einsum("fij,fj->fi", self._Dinv, (self.B @ xp).reshape(F, 3)).ravel()
        if not (np.all(np.isfinite(xp)) and np.all(np.isfinite(xf))):
            raise EstimatorError("state recovery produced non-finite values")
        self.xp, self.xf = xp, xf

    def _marginalise(self, s: int) -> None:
        """Eliminate stale features, then stale poses no active feature is coupled to."""
        last = self._last
        fstale = (s - last[self.fidx[::3]]) >= self.feature_window
        if np.any(fstale):
            rows = np.repeat(fstale, 3)
            Bm = self.B[rows]
            if self._W_of is self.B and self._W.shape == self.B.shape:
                # P -= Bm^T D^-1 Bm = W_m^T W_m, by the staircase (B as solved)
                subtract_gram(self.P, self._W[rows], self._coupled[fstale], lower=False)
            else:
                self.P -= Bm.T @ self._DB[rows]
            Dinv_m = self._Dinv[fstale]
            self.bp -= Bm.T @ np.einsum("fij,fj->fi", Dinv_m, self.bf[rows].reshape(-1, 3)).ravel()
            nz = np.flatnonzero(np.any(Bm != 0, axis=0))
            # CSR: a feature is coupled to the few poses that saw it, not to every pose
            # the batch's features saw (dense, the batch's C was ~80% zeros on the loop world)
            self._conds.append(Conditional(self.fidx[rows], self.bf[rows], sp.csr_matrix(Bm[:, nz]), self.pidx[nz],
                                            Dinv=Dinv_m, A=self.D[fstale]))
            self._owner[self.fidx[rows]] = len(self._conds) - 1
            self._pos[self.fidx[rows]] = -1
            keep = ~rows
            self.B, self.bf, self.fidx = self.B[keep], self.bf[keep], self.fidx[keep]
            self.D, self.xf = self.D[~fstale], self.xf[keep]
            self._pos[self.fidx] = np.arange(len(self.fidx))
            self.stats.marginalised_features += int(fstale.sum())
        pblk = self.pidx[::POSE_DIM]
        coupled = np.any(self.B != 0, axis=0).reshape(-1, POSE_DIM).any(axis=1)
        pstale = ((s - last[pblk]) >= self.pose_window) & ~coupled
        if np.any(pstale):
            q = np.repeat(pstale, POSE_DIM)
            k = ~q
            Pqq, Pqk = self.P[np.ix_(q, q)], self.P[np.ix_(q, k)]
            bq = self.bp[q]
            chol = pose_cholesky(Pqq)  # Pqq is a copy (fancy indexing)
            self.P = self.P[np.ix_(k, k)] - Pqk.T @ cho_solve(chol, Pqk)
            self.bp = self.bp[k] - Pqk.T @ cho_solve(chol, bq)
            nz = np.flatnonzero(np.any(Pqk != 0, axis=0))
            kidx = self.pidx[k]
            self._conds.append(Conditional(self.pidx[q], bq, Pqk[:, nz], kidx[nz], chol=chol, A=Pqq))
            self._owner[self.pidx[q]] = len(self._conds) - 1
            self._pos[self.pidx[q]] = -1
            self.pidx, self.xp, self.B = kidx, self.xp[k], self.B[:, k]
            self._pos[self.pidx] = np.arange(len(self.pidx))
            self.stats.marginalised_poses += int(pstale.sum())
        self.P = 0.5 * (self.P + self.P.T)  # keep the rounding of the Schur updates symmetric


__all__ = ["ActiveWindow", "RecoveryStats", "pose_cholesky"]
