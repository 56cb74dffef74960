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
from scipy.linalg import cho_solve

from ..errors import EstimatorError
from .state import FEATURE_DIM, POSE_DIM
from .window import ActiveWindow, Conditional

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class ReactivationPlan:
    """Conditionals to undo so that some marginalised states become active again.

    Attributes
    ----------
    features : slot in the conditionals -> block starts of the features to bring back.
    poses : slots of pose batches (undone whole).
    """

    features: dict[int, set[int]] = field(default_factory=dict)
    poses: set[int] = field(default_factory=set)


class ReactivatingWindow(ActiveWindow):
    """An :class:`ActiveWindow` whose eliminations can be undone (see the module)."""

    def reactivation_flops(self, plan: ReactivationPlan) -> float:
        """Dense work (floating-point operations, order of magnitude) of carrying out
        ``plan`` and solving and re-marginalising the grown window once: every undone
        pose batch re-allocates the pose block (``p'^2`` each), the pose Schur complement
        and its Cholesky factorisation cost ``3 f p'^2 + p'^3`` with ``p'`` the pose
        entries of the grown window and ``f`` its features."""
        p = len(self.pidx) + sum(len(self._conds[s].idx) for s in plan.poses)
        f = len(self.fidx) + FEATURE_DIM * sum(len(v) for v in plan.features.values())
        n_undo = len(plan.poses) + len(plan.features)
        return float(n_undo * p**2 + 3.0 * f * p**2 + 2.0 * p**3)

    def plan_reactivation(self, blocks: IntArray) -> "ReactivationPlan | None":
        """What :meth:`_reactivate` would undo for marginalised ``blocks`` (block starts),
        without changing anything: the feature batches (and which of their features) and
        the pose batches, latest elimination first. None when a state lies in a rebuild
        conditional (a sparse factorisation, which cannot be undone)."""
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
                return None
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
        Conditionals eliminated earlier that depend on ``q`` stay valid. A feature
        batch is split: only the requested features come back. Costs
        ``O(|S|^2 (|q| + |S|))`` per undone conditional, no access to the full ``I``.

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
        self._conds[slot] = Conditional(c.idx[keep], c.b[keep], Ck[:, nz], c.cidx[nz], Dinv=c.Dinv[~sel],
                                         A=c.A[~sel])


__all__ = ["ReactivatingWindow", "ReactivationPlan"]
