"""The active window of incremental recovery: the marginal information of the active states.

:class:`ActiveWindow` holds the *marginal* information of the active states in the
structure of the reduced camera system (see :mod:`eifslam.estimation.incremental`):

* active poses: a dense block ``P`` (``7 p x 7 p``) and vector ``bp``;
* active features: 3x3 blocks ``D`` and vector ``bf``, coupled to the active poses by
  ``B`` (``3 f x 7 p``).

It adds fused blocks (:meth:`ActiveWindow.add`), solves itself exactly
(:meth:`ActiveWindow.solve`), eliminates the states it is told are stale into
conditionals it hands back (:meth:`ActiveWindow.eliminate_features`,
:meth:`ActiveWindow.eliminate_poses`), takes eliminated states back
(:meth:`ActiveWindow.restore_features`, :meth:`ActiveWindow.restore_poses`, used by
:mod:`eifslam.estimation.reactivation`) and answers marginal covariances of its states
from its last solve. It decides nothing: when and what is done is decided by
:class:`~eifslam.estimation.incremental.IncrementalRecovery`, which owns the window and
the conditionals (:class:`~eifslam.estimation.backsub.Conditionals`). Pure NumPy/SciPy.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_factor, cho_solve, solve

from ..errors import EstimatorError
from .backsub import Conditional
from .blocks import apply_blocks, cholesky_blocks, pose_cholesky
from .schur import coupled_poses, subtract_gram
from .state import FEATURE_DIM, POSE_DIM

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


def _scatter_add(A: Array, flat: IntArray, v: Array) -> None:
    """``A.flat[flat] += v`` (C order) with repeated indices summed, in ``O(len(v) log len(v))``
    (not ``O(A.size)``: the window's ``P`` has up to ~10^6 entries)."""
    if len(v):
        u, inv = np.unique(flat, return_inverse=True)
        A[np.unravel_index(u, A.shape)] += np.bincount(inv.ravel(), v, minlength=len(u))  # u unique


def _positions(values: IntArray, keys: IntArray) -> IntArray:
    """Position of each of ``keys`` in ``values`` (distinct), -1 where it is not there."""
    values, keys = np.asarray(values, np.int64), np.asarray(keys, np.int64).reshape(-1)
    if len(values) == 0:
        return np.full(len(keys), -1, np.int64)
    order = np.argsort(values, kind="stable")
    at = np.minimum(np.searchsorted(values, keys, sorter=order), len(values) - 1)
    pos = order[at]
    return np.where(values[pos] == keys, pos, -1)


class ActiveWindow:
    """The marginal information of the active states and its last solve.

    Parameters
    ----------
    n : int
        Entries of the state so far (the length of :attr:`pos`).

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
    pos : (n,) int64
        Position of each state entry in ``pidx`` or ``fidx``, -1 when not active.
    """

    def __init__(self, n: int = 0) -> None:
        self.pidx, self.fidx = np.zeros(0, np.int64), np.zeros(0, np.int64)
        self.P, self.bp = np.zeros((0, 0)), np.zeros(0)
        self.D, self.bf, self.B = np.zeros((0, 3, 3)), np.zeros(0), np.zeros((0, 0))
        self.xp, self.xf = np.zeros(0), np.zeros(0)
        self.pos = np.full(n, -1, np.int64)
        # the last solve: pose Schur complement's factor, the states it was of, D^-1,
        # D^-1 B, W = L^-1 B (D = L L^T), the poses each feature is coupled to, and the
        # coupling W was made of (eliminate_features reuses W while B is unchanged)
        self._S_cho: tuple | None = None
        self._S_pidx, self._S_fidx = np.zeros(0, np.int64), np.zeros(0, np.int64)
        self._Dinv, self._DB, self._W = np.zeros((0, 3, 3)), np.zeros((0, 0)), np.zeros((0, 0))
        self._coupled = np.zeros((0, 0), bool)
        self._W_of: Array | None = None

    @property
    def active_indices(self) -> IntArray:
        """State indices of the active window (poses then features)."""
        return np.concatenate([self.pidx, self.fidx])

    @property
    def solved(self) -> bool:
        """Whether ``xp``, ``xf`` are of the window's current states (no state joined or
        came back since the last :meth:`solve`)."""
        return len(self.xp) == len(self.pidx) and len(self.xf) == len(self.fidx)

    def grow(self, n: int) -> None:
        """The state has ``n`` entries now (the new ones are not active)."""
        self.pos = np.concatenate([self.pos, np.full(n - len(self.pos), -1, np.int64)])

    def write_solution(self, x: Array) -> None:
        """Write the last solution into the active entries of ``x`` (in place)."""
        x[self.pidx], x[self.fidx] = self.xp, self.xf

    # -- marginal covariances from the last solve --------------------------------------------
    def pose_covariance(self, cols: IntArray) -> Array | None:
        """Marginal covariance of active pose entries ``cols`` (k,) from the window.

        The window holds the exact marginal information of its states, so the block of
        the inverse of its pose Schur complement is the exact marginal covariance.
        Returns None when an entry is not a pose of the last solve.
        """
        if self._S_cho is None:
            return None
        pos = _positions(self._S_pidx, cols)  # the window as solved
        if len(pos) == 0 or pos.min() < 0:
            return None
        E = np.zeros((len(self._S_pidx), len(pos)))
        E[pos, np.arange(len(pos))] = 1.0
        C = cho_solve(self._S_cho, E)[pos]
        return 0.5 * (C + C.T)

    def feature_covariances(self, starts: IntArray) -> Array:
        """Marginal covariances of features from the window as last solved.

        ``D_f^-1 + (D^-1 B)_f S^-1 (D^-1 B)_f^T`` (``S`` the pose Schur complement): the
        window holds the exact marginal information of its states, so this is the
        feature's exact marginal covariance as of the last :meth:`solve` (before what
        was fused since).

        Parameters
        ----------
        starts : (F,) int
            State index of each feature's first entry.

        Returns
        -------
        (F, 3, 3) float
            Covariances (state units squared); NaN for a feature that was not active at
            the last solve.
        """
        starts = np.asarray(starts, np.int64).reshape(-1)
        out = np.full((len(starts), 3, 3), np.nan)
        fidx = self._S_fidx
        if len(fidx) == 0 or len(self._Dinv) != len(fidx) // 3:
            return out
        blk = _positions(fidx[::3], starts)
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

    def propagate(self, pose_starts: IntArray, starts: IntArray, G: Array) -> Array | None:
        """``G P G^T`` for the joint marginal covariance ``P`` of active poses and
        features, from the window as last solved, without forming ``P``.

        With ``I`` over the window ``[[P, B^T], [B, D]]`` (poses, features) and ``S = P -
        B^T D^-1 B``, the covariance is ``S^-1`` over the poses, ``-D^-1 B S^-1`` between
        features and poses and ``D^-1 + D^-1 B S^-1 B^T D^-1`` over the features, so ``G P
        G^T = sum_f G_f D_f^-1 G_f^T + H S^-1 H^T`` with ``H = G_p - G_f D^-1 B``: ``O(F)``.
        Features that were not active at the last :meth:`solve` count as exact (zero
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
        (k, k) float, or None when a pose was not active at the last solve.
        """
        pose_starts = np.asarray(pose_starts, np.int64).reshape(-1)
        starts = np.asarray(starts, np.int64).reshape(-1)
        G = np.asarray(G, float)
        k, n_p = G.shape[0], POSE_DIM * len(pose_starts)
        out = np.zeros((k, k))
        npw = len(self._S_pidx)
        H = np.zeros((k, npw))
        if len(pose_starts):
            if self._S_cho is None:
                return None
            pos = _positions(self._S_pidx, (pose_starts[:, None] + np.arange(POSE_DIM)).ravel())
            if pos.min() < 0:
                return None
            np.add.at(H.T, pos, G[:, :n_p].T)
        fidx = self._S_fidx
        if len(fidx) and len(self._Dinv) == len(fidx) // 3 and len(starts):
            blk = _positions(fidx[::3], starts)
            have = blk >= 0
            if have.any():
                b = blk[have]
                Gh = G[:, n_p:].reshape(k, len(starts), 3)[:, have]  # (k, m, 3)
                GD = np.einsum("kmi,mij->kmj", Gh, self._Dinv[b])
                out += np.einsum("kmj,lmj->kl", GD, Gh)
                if self._S_cho is not None and npw and self._DB.shape == (len(fidx), npw):
                    H -= Gh.reshape(k, -1) @ self._DB.reshape(-1, 3, npw)[b].reshape(-1, npw)
        if self._S_cho is not None and npw and np.any(H):
            out += H @ cho_solve(self._S_cho, H.T)
        return 0.5 * (out + out.T)

    # -- what joins the window -----------------------------------------------------------------
    def reset_to(self, pidx: IntArray, fidx: IntArray, P: Array, bp: Array, D: Array, B: Array,
                 bf: Array) -> None:
        """Make the window the states ``pidx``, ``fidx`` with the given marginal
        information (a rebuild); the last solve is kept until the next :meth:`solve`."""
        self.pos[:] = -1
        self.pidx, self.fidx = pidx, fidx
        self.pos[pidx] = np.arange(len(pidx))
        self.pos[fidx] = np.arange(len(fidx))
        self.P, self.bp = 0.5 * (P + P.T), bp
        self.D, self.B, self.bf = D, B, bf

    def append(self, new: list[tuple[bool, int]]) -> None:
        """New states ``(is_feature, offset)`` join the window with zero information."""
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
        self.pos[pn] = np.arange(p0, p1)
        self.pos[fn] = np.arange(f0, f1)

    def add(self, idx: IntArray, Lam: Array, eta: Array, is_feature: NDArray[np.bool_], start: IntArray) -> None:
        """Add ``N`` blocks ``(idx (N,k), Lam (N,k,k), eta (N,k))`` of active states into the
        window; ``is_feature`` and ``start`` give each state entry's kind and block start.

        Raises
        ------
        EstimatorError
            When a block couples two features (``I`` not of SLAM form).
        """
        k = idx.shape[1]
        r = np.repeat(idx, k, axis=1).ravel()
        c = np.tile(idx, (1, k)).ravel()
        v = Lam.ravel()
        isf = is_feature
        fr, fc = isf[r], isf[c]
        pr, pc = self.pos[r], self.pos[c]
        m = ~fr & ~fc
        _scatter_add(self.P, pr[m] * self.P.shape[1] + pc[m], v[m])
        m = fr & ~fc
        _scatter_add(self.B, pr[m] * self.B.shape[1] + pc[m], v[m])
        m = fr & fc
        if np.any(start[r[m]] != start[c[m]]):
            raise EstimatorError("two features share a measurement: the information matrix is not of SLAM form")
        _scatter_add(self.D, 3 * pr[m] + pc[m] % 3, v[m])  # D[f, a, c] at 9 f + 3 a + c
        e, ev = idx.ravel(), eta.ravel()
        fe = isf[e]
        self.bp += np.bincount(self.pos[e[~fe]], ev[~fe], minlength=len(self.bp))
        self.bf += np.bincount(self.pos[e[fe]], ev[fe], minlength=len(self.bf))

    def restore_poses(self, idx: IntArray, sep: IntArray, dK: Array, db: Array, A: Array, C: Array,
                      b: Array) -> None:
        """Eliminated poses ``idx`` come back with information ``A`` (``(q, q)``), coupling
        ``C`` (``(q, len(sep))``) to the active poses at window positions ``sep`` and vector
        ``b``; the ``sep`` block of the window gets ``dK``, ``db`` back (what their
        elimination had subtracted)."""
        nq = len(idx)
        p0 = len(self.pidx)
        P = np.zeros((p0 + nq, p0 + nq))
        P[:p0, :p0] = self.P
        P[np.ix_(sep, sep)] += dK
        P[p0:, p0:] = A
        P[p0:, sep] = C
        P[sep, p0:] = C.T
        bp = np.concatenate([self.bp, b])
        bp[sep] += db
        self.P, self.bp = 0.5 * (P + P.T), bp
        self.B = np.concatenate([self.B, np.zeros((len(self.fidx), nq))], axis=1)
        self.pidx = np.concatenate([self.pidx, idx])
        self.pos[idx] = np.arange(p0, p0 + nq)

    def restore_features(self, parts: "list[tuple[IntArray, IntArray, Array, Array, Array, Array, Array]]") -> None:
        """Eliminated features come back, several batches at once: each part
        ``(idx, sep, dK, db, D, C, b)`` holds features ``idx`` (``3 g`` entries) with 3x3
        blocks ``D`` (``(g, 3, 3)``), coupling ``C`` (``(3 g, len(sep))``) to the active poses
        at window positions ``sep`` and vector ``b``; the ``sep`` block of the window gets
        ``dK``, ``db`` back. The rows of every part join the window in one copy (a copy
        per part would make a re-activation cost the window's size times the parts)."""
        if not parts:
            return
        rows = sum(len(p[0]) for p in parts)
        Bn = np.zeros((rows, len(self.pidx)))
        r = 0
        for idx, sep, dK, db, _, C, _ in parts:
            self.P[np.ix_(sep, sep)] += dK
            self.bp[sep] += db
            Bn[r:r + len(idx), sep] = C
            r += len(idx)
        self.P = 0.5 * (self.P + self.P.T)
        idx = np.concatenate([p[0] for p in parts])
        f0 = len(self.fidx)
        self.B = np.concatenate([self.B, Bn])
        self.D = np.concatenate([self.D] + [p[4] for p in parts])
        self.bf = np.concatenate([self.bf] + [p[6] for p in parts])
        self.fidx = np.concatenate([self.fidx, idx])
        self.pos[idx] = np.arange(f0, f0 + len(idx))

    # -- solve and eliminate -------------------------------------------------------------------
    def solve(self) -> bool:
        """Solve the window into ``xp``, ``xf``: Schur complement onto the poses, dense
        Cholesky. Returns whether the pose Schur complement was numerically indefinite.

        When the Cholesky factorisation fails (the pose Schur complement is numerically
        indefinite: ``I`` itself is then too ill-conditioned for any Cholesky, the full
        sparse solve meets negative pivots as well), the same system is solved by a
        symmetric indefinite factorisation (Bunch-Kaufman ``LDL^T``) and True is returned.
        The window stays valid: it is the exact marginal information of its states,
        rebuilding it would give the same matrix.

        Raises
        ------
        EstimatorError
            When a feature block is not positive definite, the system is singular or the
            solution is not finite.
        """
        F, npw = len(self.D), len(self.pidx)
        Linv = np.linalg.inv(cholesky_blocks(self.D)) if F else np.zeros((0, 3, 3))  # D_f = L L^T
        self._Dinv = Linv.transpose(0, 2, 1) @ Linv
        B3 = self.B.reshape(F, 3, npw)
        self._DB = (self._Dinv @ B3).reshape(3 * F, npw)
        Dbf = apply_blocks(self._Dinv, self.bf)
        r = self.bp - self.B.T @ Dbf
        self._S_cho, self._S_pidx, self._S_fidx = None, self.pidx.copy(), self.fidx.copy()
        self._W, self._coupled, self._W_of = np.zeros((0, npw)), np.zeros((0, npw // POSE_DIM), bool), None
        indefinite = False
        if npw:
            # S = P - B^T D^-1 B = P - W^T W with W = L^-1 B, lower triangle only, by
            # chunks of the staircase of B (a feature is coupled to the few poses that
            # saw it; :mod:`.schur`)
            W = (Linv @ B3).reshape(3 * F, npw)
            S = self.P.copy()
            if F:
                self._W, self._coupled = W, coupled_poses(self.B, npw // POSE_DIM)
                self._W_of = self.B  # the coupling W was made of (eliminate_features reuses it)
                subtract_gram(S, W, self._coupled)
            try:
                self._S_cho = cho_factor(S, lower=True, check_finite=False)
                xp = cho_solve(self._S_cho, r)
            except np.linalg.LinAlgError:
                try:
                    xp = solve(S, r, assume_a="sym", lower=True, check_finite=False)
                except np.linalg.LinAlgError:
                    raise EstimatorError("information matrix is singular; is the gauge fixed?") from None
                indefinite = True
        else:
            xp = r
        xf = Dbf - apply_blocks(self._Dinv, self.B @ xp)
        if not (np.all(np.isfinite(xp)) and np.all(np.isfinite(xf))):
            raise EstimatorError("state recovery produced non-finite values")
        self.xp, self.xf = xp, xf
        return indefinite

    def eliminate_features(self, stale: NDArray[np.bool_]) -> Conditional:
        """Eliminate the active features ``stale`` (``(f,)`` bool, at least one):
        ``P -= B_s^T D_s^-1 B_s`` (fill only among poses); returns their conditional.
        Uses the last :meth:`solve`'s ``D^-1`` (call right after it)."""
        rows = np.repeat(stale, 3)
        Bm = self.B[rows]
        if self._W_of is self.B and self._W.shape == self.B.shape:
            # P -= Bm^T D^-1 Bm = W_m^T W_m, by the staircase (B as solved)
            subtract_gram(self.P, self._W[rows], self._coupled[stale], lower=False)
        else:
            self.P -= Bm.T @ self._DB[rows]
        Dinv_m = self._Dinv[stale]
        self.bp -= Bm.T @ apply_blocks(Dinv_m, self.bf[rows])
        nz = np.flatnonzero(np.any(Bm != 0, axis=0))
        # CSR: a feature is coupled to the few poses that saw it, not to every pose
        # the batch's features saw (dense, the batch's C was ~80% zeros on the loop world)
        cond = Conditional(self.fidx[rows], self.bf[rows], sp.csr_matrix(Bm[:, nz]), self.pidx[nz],
                           Dinv=Dinv_m, A=self.D[stale])
        self.pos[self.fidx[rows]] = -1
        keep = ~rows
        self.B, self.bf, self.fidx = self.B[keep], self.bf[keep], self.fidx[keep]
        self.D, self.xf = self.D[~stale], self.xf[keep]
        self.pos[self.fidx] = np.arange(len(self.fidx))
        return cond

    def coupled_poses(self) -> NDArray[np.bool_]:
        """(p,) bool: whether each active pose is coupled to an active feature."""
        return np.any(self.B != 0, axis=0).reshape(-1, POSE_DIM).any(axis=1)

    def eliminate_poses(self, stale: NDArray[np.bool_]) -> Conditional:
        """Eliminate the active poses ``stale`` (``(p,)`` bool, at least one, coupled to no
        active feature): ``P -= P_kq P_qq^-1 P_qk`` (fill only among poses); returns their
        conditional.

        Raises
        ------
        EstimatorError
            When ``P_qq`` is numerically indefinite.
        """
        q = np.repeat(stale, POSE_DIM)
        k = ~q
        Pqq, Pqk = self.P[np.ix_(q, q)], self.P[np.ix_(q, k)]
        bq = self.bp[q]
        chol = pose_cholesky(Pqq)  # Pqq is a copy (fancy indexing)
        self.P = self.P[np.ix_(k, k)] - Pqk.T @ cho_solve(chol, Pqk)
        self.bp = self.bp[k] - Pqk.T @ cho_solve(chol, bq)
        nz = np.flatnonzero(np.any(Pqk != 0, axis=0))
        kidx = self.pidx[k]
        cond = Conditional(self.pidx[q], bq, Pqk[:, nz], kidx[nz], chol=chol, A=Pqq)
        self.pos[self.pidx[q]] = -1
        self.pidx, self.xp, self.B = kidx, self.xp[k], self.B[:, k]
        self.pos[self.pidx] = np.arange(len(self.pidx))
        return cond

    def symmetrise(self) -> None:
        """Keep the rounding of the Schur updates of ``P`` symmetric."""
        self.P = 0.5 * (self.P + self.P.T)


__all__ = ["ActiveWindow"]
