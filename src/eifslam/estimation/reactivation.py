"""Re-activation of marginalised states: undoing eliminations (iSAM2's re-elimination).

:class:`ReactivatingWindow` adds to the :class:`~eifslam.estimation.window.ActiveWindow`
what a measurement of a marginalised state needs: the plan of which conditionals to
undo (:meth:`ReactivatingWindow.plan_reactivation`), its cost in dense floating-point
operations (:meth:`ReactivatingWindow.reactivation_flops`, compared by the driver with a
full sparse solve) and the undoing itself (:meth:`ReactivatingWindow._reactivate`).
Pure NumPy/SciPy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
import scipy.sparse as sp
from scipy.linalg import cho_solve

from ..errors import EstimatorError
from .state import FEATURE_DIM, POSE_DIM
from .backsub import Conditional
from .window import ActiveWindow, pose_cholesky

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class ReactivationPlan:
    """Conditionals to undo so that some marginalised states become active again.

    Attributes
    ----------
    features : slot in the conditionals -> block starts of the features to bring back.
    poses : slot of a pose batch -> block starts of its poses to bring back (the whole
        batch, or part of it: the rest stays eliminated, see
        :meth:`ReactivatingWindow._undo_poses`).
    """

    features: dict[int, set[int]] = field(default_factory=dict)
    poses: dict[int, set[int]] = field(default_factory=dict)


def _row_columns(C: Array | sp.csr_matrix, rows: slice | NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Which columns of ``C`` (dense or CSR) are non-zero in ``rows``."""
    Cr = C[rows]
    if sp.issparse(Cr):
        out = np.zeros(C.shape[1], bool)
        out[sp.csr_matrix(Cr).indices] = True
        return out
    return np.any(Cr != 0, axis=0)


class ReactivatingWindow(ActiveWindow):
    """An :class:`ActiveWindow` whose eliminations can be undone (see the module)."""

    def reactivation_flops(self, plan: ReactivationPlan) -> float:
        """Extra dense work (floating-point operations, order of magnitude) of carrying
        out ``plan`` and solving the grown window once, over solving the current window:
        every undone batch re-allocates the pose block (``p'^2`` each), a pose batch
        undone in part re-eliminates the rest (``q^3``, ``q`` its entries), and the pose
        Schur complement and its Cholesky factorisation grow from ``3 f p^2 + 2 p^3`` to
        ``3 f' p'^2 + 2 p'^3`` (``p``, ``p'`` the pose entries of the window before and
        after, ``f``, ``f'`` its feature entries)."""
        p0, f0 = len(self.pidx), len(self.fidx)
        part = 0.0
        back = 0
        for s, blocks in plan.poses.items():
            q = len(self._conds[s].idx)
            back += POSE_DIM * len(blocks)
            if POSE_DIM * len(blocks) < q:
                part += float(q) ** 3
        p = p0 + back
        f = f0 + FEATURE_DIM * sum(len(v) for v in plan.features.values())
        n_undo = len(plan.poses) + len(plan.features)
        grow = 3.0 * f * p**2 + 2.0 * p**3 - (3.0 * f0 * p0**2 + 2.0 * p0**3)
        return float(n_undo * p**2 + part + max(grow, 0.0))

    def plan_reactivation(self, blocks: IntArray) -> "ReactivationPlan | None":
        """What :meth:`_reactivate` would undo for marginalised ``blocks`` (block starts),
        without changing anything: the feature batches (and which of their features) and
        the pose batches (and which of their poses), latest elimination first. None when
        a state lies in a rebuild conditional (a sparse factorisation, which cannot be
        undone).

        A state comes back with the separator of its conditional: the poses its
        conditional was coupled to when it was eliminated (for a pose batch: every
        separator entry of the batch), recursively, as in iSAM2's path to the root."""
        start, pos, owner = self._map.start, self._pos, self._owner
        feats: dict[int, set[int]] = {}  # slot -> block starts of the features to bring back
        poses: dict[int, set[int]] = {}  # slot -> block starts of the poses to bring back
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
                return None
            if c.Dinv is not None:
                feats.setdefault(slot, set()).add(b)
                r = int(np.flatnonzero(c.idx == b)[0])
                sep = c.cidx[_row_columns(c.C, slice(r, r + FEATURE_DIM))]
            else:
                first = slot not in poses
                poses.setdefault(slot, set()).add(b)
                if not first:
                    continue
                sep = c.cidx
            sep = np.unique(start[sep])
            stack.extend(int(v) for v in sep[pos[sep] < 0])
        return ReactivationPlan(feats, poses)

    # -- re-activation of marginalised states ---------------------------------------------
    def _reactivate(self, blocks: IntArray, plan: "ReactivationPlan | None" = None) -> bool:
        """Bring marginalised states back into the window by undoing their eliminations.

        Eliminating states ``q`` with separator ``S`` (the active states they were coupled
        to) subtracted ``C^T A^-1 C`` from the window's ``S`` block and stored the
        conditional ``(A, C, b)``. While no measurement touches ``q``, adding back
        ``C^T A^-1 C`` and re-inserting the rows ``[A C]`` restores the marginal
        information of ``q`` and the window exactly, provided every state of ``S`` is
        active again: the conditionals that eliminated them later are undone first (as
        iSAM2 re-eliminates the path from a clique to the root of its Bayes tree).
        Conditionals eliminated earlier that depend on ``q`` stay valid. A batch is
        split: only the requested features or poses come back, the rest of a pose batch
        is eliminated again onto the window and the poses brought back
        (:meth:`_undo_poses`). Costs ``O(|S|^2 (|q| + |S|))`` per undone conditional, no
        access to the full ``I``.

        Parameters
        ----------
        blocks : (k,) block starts of marginalised states to re-activate.
        plan : :meth:`plan_reactivation` of ``blocks``, when already made.

        Returns
        -------
        False, with nothing changed, when a requested state lies in a rebuild
        conditional (a sparse factorisation, which cannot be undone); True otherwise.
        """
        plan = self.plan_reactivation(blocks) if plan is None else plan
        if plan is None:
            return False
        feats, poses = plan.features, plan.poses
        n_poses = sum(len(v) for v in poses.values())
        for slot in sorted(set(feats) | set(poses), reverse=True):  # latest elimination first
            if slot in poses:
                self._undo_poses(slot, np.fromiter(poses[slot], np.int64))
            else:
                self._undo_features(slot, np.fromiter(feats[slot], np.int64))
        st = self.stats
        st.reactivations += 1
        st.reactivated_poses += n_poses
        st.reactivated_features += sum(len(v) for v in feats.values())
        return True

    def _undo_poses(self, slot: int, blocks: IntArray | None = None) -> None:
        """Undo the elimination of poses ``blocks`` (block starts; None: all) of the pose
        batch in ``_conds[slot]`` (its separator ``k`` is active).

        Undone in part, the batch ``q = r + q'`` splits: ``r`` comes back with the
        marginal information of ``(k, r)`` after eliminating ``q'`` alone,
        ``H = [[A_rr, C_r], [C_r^T, .]] - [A_rq'; C_q'^T] A_q'q'^-1 [A_q'r, C_q']``, and
        the window's ``k`` block gets ``C^T A^-1 C - C_q'^T A_q'q'^-1 C_q' =
        H_kr H_rr^-1 H_rk`` back (the same with ``b`` as one more column); ``q'`` stays
        eliminated with separator ``k + r``. Exact, ``O(q^3)``."""
        c = self._conds[slot]
        k = self._pos[c.cidx]
        if np.any(k < 0):
            raise EstimatorError("internal: re-activating poses whose separator is not active")
        rsel = np.ones(len(c.idx), bool) if blocks is None else np.isin(self._map.start[c.idx], blocks)
        if not rsel.any():
            return
        q = c.idx[rsel]
        nq = len(q)
        if rsel.all():
            Y = cho_solve(c.chol, np.column_stack([c.C, c.b]), check_finite=False)
            dK, db = c.C.T @ Y[:, :-1], c.C.T @ Y[:, -1]
            Hrr, Hrk, hr = c.A, c.C, c.b
            self._conds[slot] = None
        else:
            keep = ~rsel
            A, C, b = c.A, c.C, c.b
            Aqq, Aqr = A[np.ix_(keep, keep)], A[np.ix_(keep, rsel)]
            chol = pose_cholesky(Aqq)
            Y = cho_solve(chol, np.column_stack([Aqr, C[keep], b[keep]]), check_finite=False)
            Hrr = A[np.ix_(rsel, rsel)] - Aqr.T @ Y[:, :nq]
            Hrr = 0.5 * (Hrr + Hrr.T)
            Hrk = C[rsel] - Aqr.T @ Y[:, nq:-1]
            hr = b[rsel] - Aqr.T @ Y[:, -1]
            Z = cho_solve(pose_cholesky(Hrr), np.column_stack([Hrk, hr]),
                          check_finite=False)
            dK, db = Hrk.T @ Z[:, :-1], Hrk.T @ Z[:, -1]
            Cn = np.column_stack([C[keep], Aqr])
            cidx = np.concatenate([c.cidx, q])
            nz = np.flatnonzero(np.any(Cn != 0, axis=0))
            self._conds[slot] = Conditional(c.idx[keep], b[keep].copy(), Cn[:, nz], cidx[nz], chol=chol, A=Aqq)
        p0 = len(self.pidx)
        P = np.zeros((p0 + nq, p0 + nq))
        P[:p0, :p0] = self.P
        P[np.ix_(k, k)] += dK
        P[p0:, p0:] = Hrr
        P[p0:, k] = Hrk
        P[k, p0:] = Hrk.T
        bp = np.concatenate([self.bp, hr])
        bp[k] += db
        self.P, self.bp = 0.5 * (P + P.T), bp
        self.B = np.concatenate([self.B, np.zeros((len(self.fidx), nq))], axis=1)
        self.pidx = np.concatenate([self.pidx, q])
        self._pos[q] = np.arange(p0, p0 + nq)
        self._owner[q] = -1

    def _undo_features(self, slot: int, blocks: IntArray) -> None:
        """Undo the elimination of features ``blocks`` (block starts) of the feature batch in
        ``_conds[slot]``; the other features of the batch stay eliminated. ``C`` may be
        dense or CSR (a rebuild's batch of every eliminated feature)."""
        c = self._conds[slot]
        fb = c.idx[::FEATURE_DIM]
        sel = np.isin(fb, blocks)
        rows = np.repeat(sel, FEATURE_DIM)
        cols = _row_columns(c.C, rows)
        Cs = c.C[rows][:, cols]
        Cs = Cs.toarray() if sp.issparse(Cs) else Cs
        k = self._pos[c.cidx[cols]]
        if np.any(k < 0):
            raise EstimatorError("internal: re-activating features whose poses are not active")
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
        nz = _row_columns(Ck, slice(None))
        self._conds[slot] = Conditional(c.idx[keep], c.b[keep], Ck[:, nz], c.cidx[nz], Dinv=c.Dinv[~sel],
                                         A=c.A[~sel])


__all__ = ["ReactivatingWindow", "ReactivationPlan"]
