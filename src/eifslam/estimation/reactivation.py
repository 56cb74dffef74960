"""Re-activation of marginalised states: undoing eliminations (iSAM2's re-elimination).

What a measurement of a marginalised state needs, as functions of the
:class:`~eifslam.estimation.window.ActiveWindow` and the
:class:`~eifslam.estimation.backsub.Conditionals` they are given: the plan of which
conditionals to undo (:func:`plan_reactivation`), its cost in dense floating-point
operations (:func:`reactivation_flops`, compared by
:class:`~eifslam.estimation.incremental.IncrementalRecovery` with a full sparse solve) and
the undoing itself (:func:`reactivate`). Pure NumPy/SciPy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
import scipy.sparse as sp
from scipy.linalg import cho_solve

from ..errors import EstimatorError
from .state import FEATURE_DIM, POSE_DIM
from .backsub import Conditional, Conditionals
from .blocks import apply_blocks, pose_cholesky
from .window import ActiveWindow

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
        :func:`reactivate`).
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


def reactivation_flops(plan: ReactivationPlan, window: ActiveWindow, conds: Conditionals) -> float:
    """Extra dense work (floating-point operations, order of magnitude) of carrying out
    ``plan`` and solving the grown window once, over solving the current window: every
    undone batch re-allocates the pose block (``p'^2`` each), a pose batch undone in part
    re-eliminates the rest (``q^3``, ``q`` its entries), and the pose Schur complement and
    its Cholesky factorisation grow from ``3 f p^2 + 2 p^3`` to ``3 f' p'^2 + 2 p'^3``
    (``p``, ``p'`` the pose entries of the window before and after, ``f``, ``f'`` its
    feature entries)."""
    p0, f0 = len(window.pidx), len(window.fidx)
    part = 0.0
    back = 0
    for s, blocks in plan.poses.items():
        q = len(conds[s].idx)
        back += POSE_DIM * len(blocks)
        if POSE_DIM * len(blocks) < q:
            part += float(q) ** 3
    p = p0 + back
    f = f0 + FEATURE_DIM * sum(len(v) for v in plan.features.values())
    n_undo = len(plan.poses) + len(plan.features)
    grow = 3.0 * f * p**2 + 2.0 * p**3 - (3.0 * f0 * p0**2 + 2.0 * p0**3)
    return float(n_undo * p**2 + part + max(grow, 0.0))


def plan_reactivation(blocks: IntArray, window: ActiveWindow, conds: Conditionals,
                      start: IntArray) -> ReactivationPlan | None:
    """What :func:`reactivate` would undo for marginalised ``blocks`` (block starts),
    without changing anything: the feature batches (and which of their features) and the
    pose batches (and which of their poses), latest elimination first. ``start`` is the
    block start of every state entry. None when a state lies in a rebuild conditional (a
    sparse factorisation, which cannot be undone).

    A state comes back with the separator of its conditional: the poses its conditional
    was coupled to when it was eliminated (for a pose batch: every separator entry of the
    batch), recursively, as in iSAM2's path to the root."""
    pos, owner = window.pos, conds.owner
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
        c = conds[slot]
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


def reactivate(plan: ReactivationPlan, window: ActiveWindow, conds: Conditionals, start: IntArray) -> None:
    """Bring marginalised states back into the window by undoing their eliminations
    (``plan`` from :func:`plan_reactivation`).

    Eliminating states ``q`` with separator ``S`` (the active states they were coupled
    to) subtracted ``C^T A^-1 C`` from the window's ``S`` block and stored the conditional
    ``(A, C, b)``. While no measurement touches ``q``, adding back ``C^T A^-1 C`` and
    re-inserting the rows ``[A C]`` restores the marginal information of ``q`` and the
    window exactly, provided every state of ``S`` is active again: the conditionals that
    eliminated them later are undone first (as iSAM2 re-eliminates the path from a clique
    to the root of its Bayes tree). Conditionals eliminated earlier that depend on ``q``
    stay valid. A batch is split: only the requested features or poses come back, the
    rest of a pose batch is eliminated again onto the window and the poses brought back
    (:func:`_undo_poses`). Costs ``O(|S|^2 (|q| + |S|))`` per undone conditional, no
    access to the full ``I``.
    """
    feats, poses = plan.features, plan.poses
    parts: list[tuple] = []  # features undone, joining the window together
    for slot in sorted(set(feats) | set(poses), reverse=True):  # latest elimination first
        if slot in poses:
            window.restore_features(parts)  # before the window's poses change
            parts = []
            _undo_poses(slot, np.fromiter(poses[slot], np.int64), window, conds, start)
        else:
            parts.append(_undo_features(slot, np.fromiter(feats[slot], np.int64), window, conds))
    window.restore_features(parts)


def _undo_poses(slot: int, blocks: IntArray, window: ActiveWindow, conds: Conditionals, start: IntArray) -> None:
    """Undo the elimination of poses ``blocks`` (block starts) of the pose batch in
    ``conds[slot]`` (its separator ``k`` is active).

    Undone in part, the batch ``q = r + q'`` splits: ``r`` comes back with the marginal
    information of ``(k, r)`` after eliminating ``q'`` alone, ``H = [[A_rr, C_r], [C_r^T,
    .]] - [A_rq'; C_q'^T] A_q'q'^-1 [A_q'r, C_q']``, and the window's ``k`` block gets
    ``C^T A^-1 C - C_q'^T A_q'q'^-1 C_q' = H_kr H_rr^-1 H_rk`` back (the same with ``b`` as
    one more column); ``q'`` stays eliminated with separator ``k + r``. Exact,
    ``O(q^3)``."""
    c = conds[slot]
    k = window.pos[c.cidx]
    if np.any(k < 0):
        raise EstimatorError("internal: re-activating poses whose separator is not active")
    rsel = np.isin(start[c.idx], blocks)
    if not rsel.any():
        return
    q = c.idx[rsel]
    nq = len(q)
    if rsel.all():
        Y = cho_solve(c.chol, np.column_stack([c.C, c.b]), check_finite=False)
        dK, db = c.C.T @ Y[:, :-1], c.C.T @ Y[:, -1]
        Hrr, Hrk, hr = c.A, c.C, c.b
        conds.replace(slot, None)
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
        Z = cho_solve(pose_cholesky(Hrr), np.column_stack([Hrk, hr]), check_finite=False)
        dK, db = Hrk.T @ Z[:, :-1], Hrk.T @ Z[:, -1]
        Cn = np.column_stack([C[keep], Aqr])
        cidx = np.concatenate([c.cidx, q])
        nz = np.flatnonzero(np.any(Cn != 0, axis=0))
        conds.replace(slot, Conditional(c.idx[keep], b[keep].copy(), Cn[:, nz], cidx[nz], chol=chol, A=Aqq))
    window.restore_poses(q, k, dK, db, Hrr, Hrk, hr)
    conds.release(q)


def _undo_features(slot: int, blocks: IntArray, window: ActiveWindow, conds: Conditionals) -> tuple:
    """Undo the elimination of features ``blocks`` (block starts) of the feature batch in
    ``conds[slot]``; the other features of the batch stay eliminated. ``C`` may be dense
    or CSR (a rebuild's batch of every eliminated feature). Returns the part for
    :meth:`ActiveWindow.restore_features` (the caller restores several together)."""
    c = conds[slot]
    fb = c.idx[::FEATURE_DIM]
    sel = np.isin(fb, blocks)
    rows = np.repeat(sel, FEATURE_DIM)
    cols = _row_columns(c.C, rows)
    Cs = c.C[rows][:, cols]
    Cs = Cs.toarray() if sp.issparse(Cs) else Cs
    k = window.pos[c.cidx[cols]]
    if np.any(k < 0):
        raise EstimatorError("internal: re-activating features whose poses are not active")
    Dinv = c.Dinv[sel]
    DC = apply_blocks(Dinv, Cs)
    Db = apply_blocks(Dinv, c.b[rows])
    idx = c.idx[rows]
    part = (idx, k, Cs.T @ DC, Cs.T @ Db, c.A[sel], Cs, c.b[rows])
    conds.release(idx)
    keep = ~rows
    if not np.any(keep):
        conds.replace(slot, None)
        return part
    Ck = c.C[keep]
    nz = _row_columns(Ck, slice(None))
    conds.replace(slot, Conditional(c.idx[keep], c.b[keep], Ck[:, nz], c.cidx[nz], Dinv=c.Dinv[~sel], A=c.A[~sel]))
    return part


__all__ = ["ReactivationPlan", "plan_reactivation", "reactivate", "reactivation_flops"]
