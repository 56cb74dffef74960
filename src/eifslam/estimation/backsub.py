"""Conditionals of the incremental window and their back-substitution (pure NumPy/SciPy).

:class:`Conditionals` holds the conditionals of the states the incremental window
eliminated, in elimination order, and which one holds each state entry;
:meth:`Conditionals.back_substitute` (used by
:meth:`~eifslam.estimation.incremental.IncrementalRecovery.full_solution`) recovers every
marginalised state from its conditional, ``x_q = A^-1 (b_q - C x_sep)``, newest first. Applied one by
one, a long run's thousands of small feature conditionals cost more in per-call overhead
than in arithmetic (on the loop world, ``recover`` grew from 17 to 60 ms a frame over
1040 frames without loop closure).

Every separator is made of poses: a pose batch is eliminated only when no active feature
is coupled to it, and features and rebuilds are conditioned on the active poses. So once
every pose conditional (and rebuild) is applied, newest first, the feature conditionals
no longer depend on one another and are applied together. :class:`BackSubstitution`
merges them in chunks of :data:`CHUNK` consecutive slots, each one CSR product with
global columns with the 3x3 inverses multiplied in, cached as long as the chunk's
conditionals are the same objects (an undone or split conditional is a new object, so
its chunk is merged again). The result is the one-by-one back-substitution's, up to
rounding.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_solve

from .blocks import apply_blocks, block_diagonal_csr

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["CHUNK", "BackSubstitution", "Conditional", "Conditionals"]

#: consecutive conditional slots merged into one product
CHUNK = 64


@dataclass
class Conditional:
    """``x[idx] = solve(b - C @ x[cidx])``; ``solve`` is 3x3 blocks, a Cholesky or a factor.

    Attributes
    ----------
    idx : (m,) state entries eliminated.
    b : (m,) their information vector at elimination.
    C : (m, c) their information coupling to the separator ``cidx`` (CSR for features
        and a rebuild, dense for poses).
    cidx : (c,) separator: entries that were active when ``idx`` was eliminated.
    Dinv : (m/3, 3, 3) features: inverses of the 3x3 information blocks ``A``.
    chol : poses: Cholesky factor of ``A`` (``cho_factor``).
    factor : rebuild: factorisation of the eliminated part (cannot be undone).
    A : (m/3, 3, 3) features or (m, m) poses: the eliminated information block, kept so
        that the elimination can be undone exactly (:mod:`eifslam.estimation.reactivation`).
    """

    idx: IntArray
    b: Array
    C: Array | sp.csr_matrix
    cidx: IntArray
    Dinv: Array | None = None
    chol: tuple | None = None
    factor: object | None = None
    A: Array | None = None

    _affine: tuple | None = field(default=None, repr=False, compare=False)

    def apply(self, x: Array, at: IntArray | None = None) -> None:
        """``x[idx] = solve(b - C x[cidx])`` in place; a pose batch as ``k - K x[cidx]``
        with ``k = A^-1 b``, ``K = A^-1 C`` solved once (a conditional is never changed:
        undoing one replaces it), one product a back-substitution; a rebuild as
        ``k - A^-1 (C x[cidx])`` with ``k`` solved once and the second solve reading only
        the rows ``C`` couples, and, given positions ``at`` of ``idx``, writing only
        ``x[idx[at]]`` (exact for those: every other kind writes all of ``idx``)."""
        if self.chol is not None:
            if self._affine is None:
                self._affine = (cho_solve(self.chol, self.b), cho_solve(self.chol, self.C))
            k, K = self._affine
            x[self.idx] = k - K @ x[self.cidx] if len(self.cidx) else k
            return
        if self.factor is not None:
            # a rebuild: x = A^-1 b - A^-1 (C x_sep), the first solved once, the second
            # from the few rows C couples (recovery.SparseSolve), at every back substitution
            if self._affine is None:
                k = self.factor.solve(self.b)
                rows = np.flatnonzero(np.diff(self.C.indptr)) if len(self.cidx) else None
                self._affine = (k, None, None) if rows is None else \
                    (k, self.factor.sparse(rows), sp.csr_matrix(self.C[rows]))
            k, sparse, Cr = self._affine
            sel = slice(None) if at is None else at
            x[self.idx[sel]] = k[sel] if sparse is None else \
                k[sel] - sparse.solve(np.asarray(Cr @ x[self.cidx]).ravel(), at)
            return
        r = self.b - self.C @ x[self.cidx] if len(self.cidx) else self.b.copy()
        x[self.idx] = apply_blocks(self.Dinv, r)



@dataclass
class _Merged:
    """Feature conditionals ``conds`` merged: ``x[idx] = m - M x[:ncols]`` with
    ``m = Dinv b`` and ``M = Dinv C`` (``Dinv`` block diagonal, ``C`` with global
    columns): one sparse product, the rows of ``M`` as sparse as ``C``'s (a feature's
    three rows couple to the same poses)."""

    conds: tuple[Conditional, ...]
    idx: IntArray
    m: Array
    M: sp.csr_matrix

    @staticmethod
    def of(conds: list[Conditional]) -> "_Merged":
        data, cols, ptr = [], [], [np.zeros(1, np.int64)]
        end = 0
        for c in conds:
            C = c.C
            data.append(C.data)
            cols.append(c.cidx[C.indices])
            ptr.append(C.indptr[1:].astype(np.int64) + end)
            end += int(C.indptr[-1])
        indices = np.concatenate(cols)
        ncols = int(indices.max()) + 1 if len(indices) else 0
        idx = np.concatenate([c.idx for c in conds])
        C = sp.csr_matrix((np.concatenate(data), indices, np.concatenate(ptr)), shape=(len(idx), ncols))
        D = block_diagonal_csr(np.concatenate([c.Dinv for c in conds]))
        return _Merged(tuple(conds), idx, D @ np.concatenate([c.b for c in conds]), sp.csr_matrix(D @ C))

    def same(self, conds: list[Conditional]) -> bool:
        return len(conds) == len(self.conds) and all(a is b for a, b in zip(conds, self.conds))

    def apply(self, x: Array) -> None:
        x[self.idx] = self.m - self.M @ x[: self.M.shape[1]]


class BackSubstitution:
    """:meth:`apply` back-substitutes a list of conditionals, with a cache of merged
    feature conditionals (see the module). Holds no state the estimate depends on:
    :meth:`clear` (or a new instance) only costs the next call the merging."""

    def __init__(self) -> None:
        self._chunks: dict[int, _Merged] = {}

    def clear(self) -> None:
        self._chunks.clear()

    def apply(self, conds: list[Conditional | None], x: Array, start: int = 0,
              wanted: NDArray[np.bool_] | None = None) -> Array:
        """Recover every eliminated state of ``conds[start:]`` (elimination order; ``None``
        for an undone slot) into ``x`` (in place), whose active entries hold the window's
        solution. Returns ``x``.

        The separator of a conditional holds only states that were active when it was
        made, i.e. active now or eliminated later; so the states of the slots from
        ``start`` on are recovered exactly whatever ``start`` is, and the older ones keep
        the values ``x`` has. With ``wanted`` (a flag per state entry), a rebuild's
        conditional, which holds every state that was old at the rebuild, recovers only
        the wanted ones among them (no later conditional's separator holds its states)."""
        features: dict[int, list[int]] = {}
        for s in range(len(conds) - 1, max(int(start), 0) - 1, -1):
            c = conds[s]
            if c is None:
                continue
            if c.Dinv is not None and sp.issparse(c.C):
                features.setdefault(s // CHUNK, []).append(s)
            elif wanted is not None and c.factor is not None:
                at = np.flatnonzero(wanted[c.idx])
                if len(at):
                    c.apply(x, at)
            else:  # poses and rebuilds newest first; a dense feature batch needs no merging
                c.apply(x)
        for chunk, slots in features.items():
            group = [conds[s] for s in reversed(slots)]
            if (chunk + 1) * CHUNK > len(conds) or len(group) == 1:  # still growing: one by one
                for c in group:
                    c.apply(x)
                continue
            merged = self._chunks.get(chunk)
            if merged is None or not merged.same(group):
                merged = self._chunks[chunk] = _Merged.of(group)
            merged.apply(x)
        return x


class Conditionals:
    """The conditionals of the eliminated states, in elimination order, and the slot that
    holds each eliminated state entry.

    Parameters
    ----------
    n : int
        Entries of the state so far (the length of :attr:`owner`).

    Attributes
    ----------
    slots : list of Conditional or None
        In elimination order; None once undone.
    owner : (n,) int64
        Slot of each eliminated entry, -1 for an entry that is not eliminated.
    backsub : BackSubstitution
        The back-substitution with its cache of merged feature conditionals.
    """

    def __init__(self, n: int = 0) -> None:
        self.slots: list[Conditional | None] = []
        self.owner = np.full(n, -1, np.int64)
        self.backsub = BackSubstitution()

    def __len__(self) -> int:
        return len(self.slots)

    def __getitem__(self, slot: int) -> Conditional | None:
        return self.slots[slot]

    def grow(self, n: int) -> None:
        """The state has ``n`` entries now (the new ones are not eliminated)."""
        self.owner = np.concatenate([self.owner, np.full(n - len(self.owner), -1, np.int64)])

    def clear(self, n: int) -> None:
        """No conditional (a rebuild starts afresh); the state has ``n`` entries."""
        self.slots = []
        self.owner = np.full(n, -1, np.int64)
        self.backsub = BackSubstitution()  # its merged chunks were of the old conditionals

    def append(self, cond: Conditional) -> int:
        """Store the conditional of a new elimination; returns its slot."""
        self.slots.append(cond)
        slot = len(self.slots) - 1
        self.owner[cond.idx] = slot
        return slot

    def replace(self, slot: int, cond: Conditional | None) -> None:
        """What remains eliminated of ``slot`` after part of it was undone (None: nothing)."""
        self.slots[slot] = cond

    def release(self, idx: IntArray) -> None:
        """Entries ``idx`` are no longer eliminated."""
        self.owner[idx] = -1

    def back_substitute(self, x: Array, start: int = 0, wanted: NDArray[np.bool_] | None = None) -> Array:
        """Recover the states of the slots from ``start`` on into ``x`` (in place), whose
        active entries hold the window's solution (:meth:`BackSubstitution.apply`; a
        rebuild's only where ``wanted``)."""
        return self.backsub.apply(self.slots, x, start=start, wanted=wanted)
