"""Incremental exact state recovery over an active window (paper III-G; pure NumPy/SciPy).

The paper obtains the Cholesky factor ``L(k)`` of the information matrix from ``L(k-1)``.
During an exploration this is possible because a new image only touches recent states:
the current pose, the previous one, and the features in view. In the chronological
elimination order the factor of every state that is never touched again is final.

This module keeps the *marginal* information of an active window of states, in the
structure of the reduced camera system:

* active poses: a dense block ``P`` (``7 p x 7 p``) and vector ``bp``;
* active features: 3x3 blocks ``D`` (no measurement involves two features) and vector
  ``bf``, coupled to the active poses only, by ``B`` (``3 f x 7 p``, dense).

A new measurement whose states are all active adds into ``P``, ``D``, ``B``, ``b``
directly. Each step solves the window exactly (Schur complement onto the poses, dense
Cholesky) in ``O(f p^2)``, independent of the map size, then marginalises:

* features not measured for ``feature_window`` steps: ``P -= B_f^T D_f^-1 B_f`` (fill
  only among poses);
* poses not measured for ``pose_window`` steps *and* no longer coupled to an active
  feature: ``P -= P_kq P_qq^-1 P_qk`` (fill only among poses again).

So the window keeps its structure forever. Each elimination stores its conditional
(``x_q = A^-1 (b_q - C x_rest)``), which is one block row of a Cholesky factorisation in
elimination order: the full state follows by back substitution in reverse order in
``O(n)`` (:meth:`IncrementalRecovery.full_solution`). The result is exact (equal to the
full sparse solve). When a measurement touches a marginalised state (loop closure,
relocalisation, a feature seen again after a gap, a frame localised late, earlier
observations of a newly triangulated feature), the state is re-activated: its
conditional is undone (``C^T A^-1 C`` added back to the window, its rows re-inserted),
after the conditionals of the later-eliminated poses it was conditioned on, as iSAM2
re-eliminates the path to the root of its Bayes tree; no access to the full ``I``. Only
a state inside a rebuild's sparse factorisation cannot be re-activated: then the window
is rebuilt from the full sparse ``I`` (:func:`eifslam.recovery.factorize` on the
eliminated part) and the event is counted as a fallback. Rebuilding also follows
:meth:`InformationStore.reset` / ``set`` (smoothing, rescaling).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve, solve

from ..errors import ConfigError, EstimatorError
from .information import InformationStore
from .state import FEATURE_DIM, POSE_DIM, StateLayout
from .recovery import factorize

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


class InformationListener(Protocol):
    """Something told about every fusion and every wholesale change of ``I``, ``i``."""

    def on_add(self, idx: IntArray, Lam: Array, eta: Array) -> None: ...

    def on_invalidate(self) -> None: ...


class TrackedInformationStore(InformationStore):
    """An :class:`InformationStore` that reports every ``add`` to its listeners.

    ``reset`` and ``set`` (smoothing, rescaling) report ``on_invalidate``.
    """

    def __init__(self) -> None:
        super().__init__()
        self.listeners: list[InformationListener] = []

    def add(self, idx: IntArray, Lam: Array, eta: Array) -> None:
        super().add(idx, Lam, eta)
        if len(idx):
            for lis in self.listeners:
                lis.on_add(idx, Lam, eta)

    def reset(self) -> None:
        super().reset()
        for lis in self.listeners:
            lis.on_invalidate()

    def set(self, I: sp.spmatrix, i: Array) -> None:
        super().set(I, i)
        for lis in self.listeners:
            lis.on_invalidate()


class EntryMap:
    """Per-entry kind and block start of the state, followed as the layout grows.

    Attributes
    ----------
    n : int                 entries seen so far.
    start : (n,) int        state index of the first entry of each entry's block.
    is_feature : (n,) bool  whether an entry belongs to a feature.
    """

    def __init__(self) -> None:
        self.n = 0
        self._nblocks = 0
        self._start = np.zeros(1024, np.int64)
        self._isf = np.zeros(1024, bool)

    @property
    def start(self) -> IntArray:
        return self._start[: self.n]

    @property
    def is_feature(self) -> NDArray[np.bool_]:
        return self._isf[: self.n]

    def sync(self, layout: StateLayout) -> list[tuple[bool, int]]:
        """Follow the layout; return ``(is_feature, offset)`` of the blocks added since."""
        new = []
        for kind, ident in layout.keys_since(self._nblocks):
            isf = kind == "feature"
            new.append((isf, layout.feature_offset(ident) if isf else layout.pose_offset(ident)))
        self._nblocks = layout.n_states
        if layout.dim > len(self._start):
            cap = max(layout.dim, 2 * len(self._start))
            self._start = np.concatenate([self._start, np.zeros(cap - len(self._start), np.int64)])
            self._isf = np.concatenate([self._isf, np.zeros(cap - len(self._isf), bool)])
        for isf, off in new:
            size = FEATURE_DIM if isf else POSE_DIM
            self._start[off : off + size] = off
            self._isf[off : off + size] = isf
        self.n = layout.dim
        return new


@dataclass
class RecoveryStats:
    """Counters of :class:`IncrementalRecovery`.

    Attributes
    ----------
    steps : recoveries done.
    fallbacks : steps where a measurement touched a marginalised state that could not be
        re-activated (full rebuild), plus solves that failed (see
        :meth:`eifslam.filter.InformationFilter.recover_active`).
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


@dataclass
class _Conditional:
    """``x[idx] = solve(b - C @ x[cidx])``; ``solve`` is 3x3 blocks, a Cholesky or a factor.

    Attributes
    ----------
    idx : (m,) state entries eliminated.
    b : (m,) their information vector at elimination.
    C : (m, c) their information coupling to the separator ``cidx`` (dense, or CSR for
        a rebuild).
    cidx : (c,) separator: entries that were active when ``idx`` was eliminated.
    Dinv : (m/3, 3, 3) features: inverses of the 3x3 information blocks ``A``.
    chol : poses: Cholesky factor of ``A`` (``cho_factor``).
    factor : rebuild: factorisation of the eliminated part (cannot be undone).
    A : (m/3, 3, 3) features or (m, m) poses: the eliminated information block, kept so
        that the elimination can be undone exactly (:meth:`IncrementalRecovery._reactivate`).
    """

    idx: IntArray
    b: Array
    C: Array | sp.csr_matrix
    cidx: IntArray
    Dinv: Array | None = None
    chol: tuple | None = None
    factor: object | None = None
    A: Array | None = None

    def apply(self, x: Array) -> None:
        r = self.b - self.C @ x[self.cidx] if len(self.cidx) else self.b.copy()
        if self.Dinv is not None:
            x[self.idx] = np.einsum("fij,fj->fi", self.Dinv, r.reshape(-1, 3)).ravel()
        elif self.chol is not None:
            x[self.idx] = cho_solve(self.chol, r)
        else:
            x[self.idx] = self.factor.solve(r)


def _scatter_add(A: Array, flat: IntArray, v: Array) -> None:
    """``A.flat[flat] += v`` (C order) with repeated indices summed, in ``O(len(v) log len(v))``
    (not ``O(A.size)``: the window's ``P`` has up to ~10^6 entries)."""
    if len(v):
        u, inv = np.unique(flat, return_inverse=True)
        A[np.unravel_index(u, A.shape)] += np.bincount(inv.ravel(), v, minlength=len(u))  # u unique


def _spd_inverse_3x3(D: Array) -> Array:
    """Inverses of ``(F, 3, 3)`` blocks; raises if a block is not positive definite."""
    try:
        np.linalg.cholesky(D)
    except np.linalg.LinAlgError:
        raise EstimatorError("a feature has no information in some direction (seen from one pose only?)") from None
    return np.linalg.inv(D)


@dataclass
class IncrementalRecovery:
    """Exact recovery of ``I x = i`` restricted to an active window, updated per step.

    Parameters
    ----------
    feature_window : int
        A feature is marginalised after this many steps without a measurement (>= 1).
    pose_window : int
        A pose is marginalised after this many steps without a measurement, once no
        active feature is coupled to it (>= 1).
    """

    feature_window: int = 2
    pose_window: int = 2
    stats: RecoveryStats = field(default_factory=RecoveryStats)

    def __post_init__(self) -> None:
        for key in ("feature_window", "pose_window"):
            v = getattr(self, key)
            if not (isinstance(v, (int, np.integer)) and v >= 1):
                raise ConfigError(f"{key} must be an integer >= 1, got {v!r}")
        self._map = EntryMap()
        self._last = np.zeros(0, np.int64)  # step of the last measurement, at block starts
        self._pos = np.zeros(0, np.int64)  # position in the window, -1 once marginalised
        self._owner = np.zeros(0, np.int64)  # slot in _conds of a marginalised entry, else -1
        self._pending: list[tuple[IntArray, Array, Array]] = []
        self._valid = False
        self._conds: list[_Conditional | None] = []  # elimination order; None once undone
        self._reset_window()

    def _reset_window(self) -> None:
        self.pidx = np.zeros(0, np.int64)
        self.fidx = np.zeros(0, np.int64)
        self.P, self.bp = np.zeros((0, 0)), np.zeros(0)
        self.D, self.bf = np.zeros((0, 3, 3)), np.zeros(0)
        self.B = np.zeros((0, 0))
        self.xp, self.xf = np.zeros(0), np.zeros(0)

    # -- pickling -----------------------------------------------------------------------
    def __getstate__(self) -> dict:
        """Pickle without the window and the conditionals (a rebuild's conditional holds a
        sparse factorisation, which does not pickle): the unpickled recovery is invalid
        and rebuilds from the full ``I`` at its next :meth:`step`. Pickle the owner's
        complete estimate (:meth:`full_solution`) if it is needed after loading."""
        state = self.__dict__.copy()
        state.update(_conds=[], _pending=[], _valid=False, _S_cho=None, _S_pidx=np.zeros(0, np.int64),
                     _Dinv=np.zeros((0, 3, 3)), _DB=np.zeros((0, 0)))
        state["_owner"] = np.full(len(self._owner), -1, np.int64)
        state["_pos"] = np.full(len(self._pos), -1, np.int64)
        empty = IncrementalRecovery.__new__(IncrementalRecovery)
        empty._reset_window()
        state.update(empty.__dict__)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)

    # -- listener -----------------------------------------------------------------------
    def on_add(self, idx: IntArray, Lam: Array, eta: Array) -> None:
        """Record a fusion (processed at the next :meth:`step`)."""
        if self._valid:
            self._pending.append((idx, Lam, eta))

    def on_invalidate(self) -> None:
        """``I`` was replaced wholesale: rebuild at the next step."""
        self._valid = False
        self._pending = []

    # -- the step -------------------------------------------------------------------------
    @property
    def valid(self) -> bool:
        """False once ``I`` was replaced wholesale and until the next step rebuilds."""
        return self._valid

    @property
    def active_indices(self) -> IntArray:
        """State indices of the active window (poses then features)."""
        return np.concatenate([self.pidx, self.fidx])

    def step(self, layout: StateLayout, info: InformationStore, x: Array) -> None:
        """Fold the new fusions in, solve the window into ``x``, marginalise old states.

        Parameters
        ----------
        layout : the filter's state layout.
        info : the filter's information (used only to rebuild).
        x : (n,) the filter's estimate; active entries are overwritten with the exact
            solution of ``I x = i``, the others are left as they are.
        """
        if not any(lis is self for lis in getattr(info, "listeners", ())):
            raise EstimatorError("incremental recovery is not attached to this information store "
                                 "(was the store replaced?); use the full recovery")
        st = self.stats
        st.steps += 1
        s = st.steps
        new = self._map.sync(layout)
        n = self._map.n
        self._last = np.concatenate([self._last, np.full(n - len(self._last), s, np.int64)])
        self._pos = np.concatenate([self._pos, np.full(n - len(self._pos), -1, np.int64)])
        self._owner = np.concatenate([self._owner, np.full(n - len(self._owner), -1, np.int64)])
        pending, self._pending = self._pending, []
        touched = np.concatenate([p[0].ravel() for p in pending]) if pending else np.zeros(0, np.int64)
        self._last[self._map.start[touched]] = s
        if not self._valid:
            self._rebuild(info, s)
        else:
            self._append(new)
            marg = np.unique(self._map.start[touched[self._pos[touched] < 0]])
            if len(marg) and not self._reactivate(marg):
                st.fallbacks += 1
                self._rebuild(info, s)
            else:
                for idx, Lam, eta in pending:
                    self._route(idx, Lam, eta)
        self._solve()
        x[self.pidx], x[self.fidx] = self.xp, self.xf
        st.max_window_poses = max(st.max_window_poses, len(self.pidx) // POSE_DIM)
        self._marginalise(s)
        st.window_poses, st.window_features = len(self.pidx) // POSE_DIM, len(self.fidx) // FEATURE_DIM

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

    def full_solution(self, x: Array) -> Array:
        """Back-substitute every marginalised state into ``x`` (in place) in ``O(n)``.

        ``x`` must hold the current window solution (as :meth:`step` left it); entries
        added to the layout after the last step are left untouched.
        """
        if len(self.xp) != len(self.pidx) or len(self.xf) != len(self.fidx):
            return x  # the window changed without a solve: nothing consistent to add
        x[self.pidx], x[self.fidx] = self.xp, self.xf
        for c in reversed(self._conds):
            if c is not None:
                c.apply(x)
        return x

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
        self._Dinv = _spd_inverse_3x3(self.D) if F else np.zeros((0, 3, 3))
        B3 = self.B.reshape(F, 3, npw)
        self._DB = (self._Dinv @ B3).reshape(3 * F, npw)
        Dbf = np.einsum("fij,fj->fi", self._Dinv, self.bf.reshape(F, 3)).ravel()
        S = self.P - self.B.T @ self._DB
        r = self.bp - self.B.T @ Dbf
        self._S_cho, self._S_pidx = None, self.pidx.copy()
        if npw:
            S = 0.5 * (S + S.T)
            try:
                self._S_cho = cho_factor(S, lower=True, check_finite=False)
                xp = cho_solve(self._S_cho, r)
            except np.linalg.LinAlgError:
                try:
                    xp = solve(S, r, assume_a="sym", check_finite=False)
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
            Bm, DBm = self.B[rows], self._DB[rows]
            self.P -= Bm.T @ DBm
            Dinv_m = self._Dinv[fstale]
            self.bp -= Bm.T @ np.einsum("fij,fj->fi", Dinv_m, self.bf[rows].reshape(-1, 3)).ravel()
            nz = np.flatnonzero(np.any(Bm != 0, axis=0))
            self._conds.append(_Conditional(self.fidx[rows], self.bf[rows], Bm[:, nz], self.pidx[nz], Dinv=Dinv_m,
                                            A=self.D[fstale]))
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
            chol = cho_factor(Pqq, lower=True, check_finite=False)  # Pqq is a copy (fancy indexing)
            self.P = self.P[np.ix_(k, k)] - Pqk.T @ cho_solve(chol, Pqk)
            self.bp = self.bp[k] - Pqk.T @ cho_solve(chol, bq)
            nz = np.flatnonzero(np.any(Pqk != 0, axis=0))
            kidx = self.pidx[k]
            self._conds.append(_Conditional(self.pidx[q], bq, Pqk[:, nz], kidx[nz], chol=chol, A=Pqq))
            self._owner[self.pidx[q]] = len(self._conds) - 1
            self._pos[self.pidx[q]] = -1
            self.pidx, self.xp, self.B = kidx, self.xp[k], self.B[:, k]
            self._pos[self.pidx] = np.arange(len(self.pidx))
            self.stats.marginalised_poses += int(pstale.sum())
        self.P = 0.5 * (self.P + self.P.T)  # keep the rounding of the Schur updates symmetric

    # -- re-activation of marginalised states ---------------------------------------------
    def _reactivate(self, blocks: IntArray) -> bool:
        """Bring marginalised states back into the window by undoing their eliminations.

        Eliminating states ``q`` with separator ``S`` (the active states they were coupled
        to) subtracted ``C^T A^-1 C`` from the window's ``S`` block and stored the
        conditional ``(A, C, b)``. While no measurement touches ``q``, adding back
        ``C^T A^-1 C`` and re-inserting the rows ``[A C]`` restores the marginal
        information of ``q`` and the window exactly, provided every state of ``S`` is
        active again: the conditionals that eliminated them later are undone first (as
        iSAM2 re-eliminates the path from a clique to the root of its Bayes tree).
        Conditionals eliminated earlier that depend on ``q`` stay valid. A feature
        batch is split: only the requested features come back. Costs
        ``O(|S|^2 (|q| + |S|))`` per undone conditional, no access to the full ``I``.

        Parameters
        ----------
        blocks : (k,) block starts of marginalised states to re-activate.

        Returns
        -------
        False, with nothing changed, when a requested state lies in a rebuild
        conditional (a sparse factorisation, which cannot be undone); True otherwise.
        """
        start, pos, owner = self._map.start, self._pos, self._owner
        feats: dict[int, set[int]] = {}  # slot -> block starts of the features to bring back
        poses: set[int] = set()  # slots of pose batches (undone whole)
        seen: set[int] = set()
        stack = [int(b) for b in blocks]
        while stack:
            b = stack.pop()
            if b in seen:
                continue
            seen.add(b)
            slot = int(owner[b])
            c = self._conds[slot]
            if c is None or c.A is None:  # a rebuild's factorisation (or a bookkeeping bug)
                return False
            if c.Dinv is not None:
                feats.setdefault(slot, set()).add(b)
                r = np.flatnonzero(c.idx == b)[0]
                sep = c.cidx[np.any(c.C[r : r + FEATURE_DIM] != 0, axis=0)]
            else:
                if slot in poses:
                    continue
                poses.add(slot)
                seen.update(int(v) for v in c.idx[::POSE_DIM])
                sep = c.cidx
            sep = np.unique(start[sep])
            stack.extend(int(v) for v in sep[pos[sep] < 0])
        n_poses = sum(len(self._conds[slot].idx) // POSE_DIM for slot in poses)
        for slot in sorted(set(feats) | poses, reverse=True):  # latest elimination first
            if slot in poses:
                self._undo_poses(slot)
            else:
                self._undo_features(slot, np.fromiter(feats[slot], np.int64))
        st = self.stats
        st.reactivations += 1
        st.reactivated_poses += n_poses
        st.reactivated_features += sum(len(v) for v in feats.values())
        return True

    def _undo_poses(self, slot: int) -> None:
        """Undo the elimination of the pose batch in ``_conds[slot]`` (its separator is active)."""
        c = self._conds[slot]
        k = self._pos[c.cidx]
        if np.any(k < 0):
            raise EstimatorError("internal: re-activating poses whose separator is not active")
        q, nq = c.idx, len(c.idx)
        p0 = len(self.pidx)
        Y = cho_solve(c.chol, np.column_stack([c.C, c.b]), check_finite=False)
        P = np.zeros((p0 + nq, p0 + nq))
        P[:p0, :p0] = self.P
        P[np.ix_(k, k)] += c.C.T @ Y[:, :-1]
        P[p0:, p0:] = c.A
        P[p0:, k] = c.C
        P[k, p0:] = c.C.T
        bp = np.concatenate([self.bp, c.b])
        bp[k] += c.C.T @ Y[:, -1]
        self.P, self.bp = 0.5 * (P + P.T), bp
        self.B = np.concatenate([self.B, np.zeros((len(self.fidx), nq))], axis=1)
        self.pidx = np.concatenate([self.pidx, q])
        self._pos[q] = np.arange(p0, p0 + nq)
        self._owner[q] = -1
        self._conds[slot] = None

    def _undo_features(self, slot: int, blocks: IntArray) -> None:
        """Undo the elimination of features ``blocks`` (block starts) of the feature batch in
        ``_conds[slot]``; the other features of the batch stay eliminated."""
        c = self._conds[slot]
        fb = c.idx[::FEATURE_DIM]
        sel = np.isin(fb, blocks)
        rows = np.repeat(sel, FEATURE_DIM)
        Cs = c.C[rows]
        cols = np.any(Cs != 0, axis=0)
        k = self._pos[c.cidx[cols]]
        if np.any(k < 0):
            raise EstimatorError("internal: re-activating features whose poses are not active")
        Cs = Cs[:, cols]
        Dinv = c.Dinv[sel]
        g = int(sel.sum())
        DC = np.einsum("fij,fjm->fim", Dinv, Cs.reshape(g, 3, -1)).reshape(3 * g, -1)
        Db = np.einsum("fij,fj->fi", Dinv, c.b[rows].reshape(g, 3)).ravel()
        self.P[np.ix_(k, k)] += Cs.T @ DC
        self.P = 0.5 * (self.P + self.P.T)
        self.bp[k] += Cs.T @ Db
        Bn = np.zeros((3 * g, len(self.pidx)))
        Bn[:, k] = Cs
        f0 = len(self.fidx)
        idx = c.idx[rows]
        self.B = np.concatenate([self.B, Bn])
        self.D = np.concatenate([self.D, c.A[sel]])
        self.bf = np.concatenate([self.bf, c.b[rows]])
        self.fidx = np.concatenate([self.fidx, idx])
        self._pos[idx] = np.arange(f0, f0 + 3 * g)
        self._owner[idx] = -1
        keep = ~rows
        if not np.any(keep):
            self._conds[slot] = None
            return
        Ck = c.C[keep]
        nz = np.any(Ck != 0, axis=0)
        self._conds[slot] = _Conditional(c.idx[keep], c.b[keep], Ck[:, nz], c.cidx[nz], Dinv=c.Dinv[~sel],
                                         A=c.A[~sel])

    # -- rebuild from the full information --------------------------------------------------
    def _rebuild(self, info: InformationStore, s: int) -> None:
        """Window = recently measured features, their poses and recent poses; the rest is
        eliminated exactly from the full sparse ``I`` into one conditional."""
        self.stats.rebuilds += 1
        self._valid = True
        n = self._map.n
        I = sp.csr_matrix(info.matrix())
        i = np.asarray(info.vector[:n], dtype=float)
        isf, start = self._map.is_feature, self._map.start
        age = s - self._last[start]
        fa = np.flatnonzero(isf & (age < self.feature_window))
        pose_all = np.flatnonzero(~isf)
        Ifp = I[fa][:, pose_all]
        coupled = np.zeros(n, bool)
        coupled[pose_all[np.unique(Ifp.tocoo().col)]] = True
        blk_coupled = np.zeros(n, bool)
        blk_coupled[start[coupled]] = True
        pa = np.flatnonzero(~isf & ((age < self.pose_window) | blk_coupled[start]))
        active = np.zeros(n, bool)
        active[fa] = active[pa] = True
        m = np.flatnonzero(~active)
        self._conds = []
        self._owner = np.full(n, -1, np.int64)
        P = I[pa][:, pa].toarray()
        bp = i[pa].copy()
        if len(m):
            Imm = I[m][:, m]
            mf = isf[m]
            factor = factorize(Imm, np.flatnonzero(~mf), np.flatnonzero(mf))
            C = I[m][:, pa].tocsr()
            Y = factor.solve(C.toarray())
            P -= np.asarray(C.T @ Y)
            bp -= C.T @ factor.solve(i[m])
            self._conds.append(_Conditional(m, i[m].copy(), C, pa, factor=factor))
            self._owner[m] = 0
        self._pos[:] = -1
        self.pidx, self.fidx = pa, fa
        self._pos[pa] = np.arange(len(pa))
        self._pos[fa] = np.arange(len(fa))
        self.P, self.bp = 0.5 * (P + P.T), bp
        F = len(fa) // 3
        coo = I[fa][:, fa].tocoo()
        same = coo.row // 3 == coo.col // 3
        if not np.all(same | (coo.data == 0)):
            raise EstimatorError("two features share a measurement: the information matrix is not of SLAM form")
        self.D = np.zeros((F, 3, 3))
        np.add.at(self.D, (coo.row[same] // 3, coo.row[same] % 3, coo.col[same] % 3), coo.data[same])
        self.B = I[fa][:, pa].toarray()
        self.bf = i[fa].copy()
