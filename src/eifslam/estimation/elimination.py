"""The elimination of marginalised map features onto the poses, kept between rebuilds of the
incremental recovery (pure NumPy / SciPy).

A rebuild of the recovery window (:meth:`~eifslam.estimation.incremental.IncrementalRecovery._rebuild`)
eliminates every feature outside the window: with ``D_f`` a feature's 3x3 information block
and ``B_f`` its coupling to the poses, the poses' reduced system loses
``G = sum_f B_f^T D_f^-1 B_f`` and their vector ``g = sum_f B_f^T D_f^-1 i_f``. On the loop
world that is reading the feature rows of ``I`` (35 M non-zeros) and a block Gram product:
2-3 s of a 5 s rebuild. Between two rebuilds most of those features are untouched (no
fusion changed their rows of ``I`` or ``i``), so their terms are the same.

:class:`FeatureElimination` keeps ``G``, ``g`` and the features' blocks over *every* pose
entry (columns: positions among the state's pose entries, which only grow by appending),
and at the next rebuild takes out the terms of the features that were touched since or
are no longer to be eliminated, and adds those of the features newly to be eliminated,
read from ``I``. The sums equal a fresh elimination up to rounding
(``tests/test_incremental.py``).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from .blocks import apply_blocks, block_entries, inverse_spd_blocks
from .information import SummedRows
from .recovery import SchurFactor, factorize_onto, feature_blocks, gram_by_blocks, reduced_onto

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["FeatureElimination"]

#: Entries gathered per pass when ``B`` loses rows (a 16 MB index at a time).
_GATHER_ENTRIES = 2_000_000


class FeatureElimination:
    """``G``, ``g`` of a set of eliminated features, kept up to date between rebuilds.

    Attributes
    ----------
    starts : (F,) int
        State index of the first entry of each eliminated feature (in the order of the
        rows of ``B``, not sorted).
    Dinv : (F, 3, 3)
        Inverses of their information blocks.
    B : CSR (3 F, N)
        Their coupling to the poses, columns the positions of the state's pose entries
        (``N`` of them when last updated).
    G : CSR (N, N)
        ``B^T D^-1 B``.
    g : (N,)
        ``B^T D^-1 i_f``.
    y : (3 F,)
        ``D^-1 i_f`` of each feature (``B``'s row order), to take its term out of ``g``.
    """

    def __init__(self) -> None:
        self.starts = np.zeros(0, np.int64)
        self.Dinv = np.zeros((0, 3, 3))
        self.B = sp.csr_matrix((0, 0))
        self.G = sp.csr_matrix((0, 0))
        self.g = np.zeros(0)
        self.y = np.zeros(0)  # D^-1 i_f of each feature as it was added, in B's row order
        self._dirty = np.zeros(0, bool)  # per state entry: touched by a fusion since the last update

    def touch(self, idx: IntArray) -> None:
        """Note state entries ``idx`` (any shape) whose rows of ``I`` or ``i`` a fusion changed."""
        idx = np.asarray(idx, np.int64).ravel()
        if len(idx) == 0:
            return
        top = int(idx.max()) + 1
        if top > len(self._dirty):
            self._dirty = np.concatenate([self._dirty, np.zeros(max(top, 2 * len(self._dirty)) - len(self._dirty),
                                                                bool)])
        self._dirty[idx] = True

    def update(self, I: sp.csr_matrix | SummedRows, i: Array, feat_starts: IntArray, pose_entries: IntArray) -> None:
        """Make the kept sums those of the features starting at ``feat_starts``.

        Parameters
        ----------
        I : (n, n) CSR or SummedRows
            The information matrix now (only rows are read).
        i : (n,)
            The information vector now.
        feat_starts : (F',) int
            First entries of the features to be eliminated now.
        pose_entries : (N',) int
            The state's pose entries in state order (``N' >= N``: the ones kept are a prefix).
        """
        feat_starts = np.asarray(feat_starts, np.int64)
        touched = np.zeros(len(self.starts), bool)
        known = self.starts < len(self._dirty)
        touched[known] = self._dirty[self.starts[known]]
        keep = np.isin(self.starts, feat_starts) & ~touched
        self._pad(len(pose_entries))
        if not keep.all():
            drop_rows = self._rows(np.flatnonzero(~keep))
            Bd = self.B[drop_rows]
            self.G = self.G - gram_by_blocks(Bd, self.Dinv[~keep])
            self.g = self.g - Bd.T @ self.y[drop_rows]
            del Bd
        kept_starts = self.starts[keep]
        add = feat_starts[~np.isin(feat_starts, kept_starts)]
        Ba = None
        if len(add):
            D, Ba = feature_blocks(I, block_entries(add), pose_entries)
            Dinv = inverse_spd_blocks(D)
            y = apply_blocks(Dinv, np.asarray(i, float)[block_entries(add)])
            self.G = self.G + gram_by_blocks(Ba, Dinv)
            self.g = self.g + Ba.T @ y
        if len(add) or not keep.all():
            kept_rows = self._rows(np.flatnonzero(keep))
            self.B = _rows_then(self.B, kept_rows, Ba)  # one copy of B, not one per step
            self.starts, self.Dinv, self.y = kept_starts, self.Dinv[keep], self.y[kept_rows]
            if len(add):
                self.starts = np.concatenate([self.starts, add])
                self.Dinv = np.concatenate([self.Dinv, Dinv])
                self.y = np.concatenate([self.y, y])
        self.G = sp.csr_matrix(self.G)
        self._dirty[:] = False

    def onto(self, I: sp.csr_matrix | SummedRows, i: Array, mp: IntArray, mf: IntArray, pa: IntArray, pose_entries: IntArray,
             block_start: IntArray) -> tuple[SchurFactor, Array, Array]:
        """A sparse rebuild's elimination of ``m = mp + mf`` onto the poses ``pa``
        (:func:`~eifslam.estimation.recovery.factorize_onto`), the features' part from the
        kept sums after :meth:`update`.

        Parameters
        ----------
        I, i : the information now, ``(n, n)`` CSR (or its parts, read by rows) and ``(n,)``.
        mp, mf, pa : int arrays
            Pose and feature entries eliminated, pose entries kept.
        pose_entries : (N,) int
            Every pose entry of the state, in state order.
        block_start : (n,) int
            First entry of each entry's block.

        Returns
        -------
        factor, P, b : as :func:`~eifslam.estimation.recovery.factorize_onto`.
        """
        if not (len(mf) and len(pa)):
            return factorize_onto(I.tocsr(), mp, mf, pa, i)  # a CSR matrix is its own tocsr()
        self.update(I, i, np.unique(block_start[mf]), pose_entries)
        pos = np.full(len(block_start), -1, np.int64)
        pos[pose_entries] = np.arange(len(pose_entries))
        cols = pos[np.concatenate([mp, pa])]
        # the factor shares B (every pose column) rather than a copy of the columns of mp
        return reduced_onto(I, mp, self.entries(), pa, i, self.Dinv, self.B, self.G[cols][:, cols], self.g[cols],
                            B_cols=pos[mp])

    def entries(self) -> IntArray:
        """The eliminated features' state entries ``(3 F,)``, in the order of ``B``'s rows."""
        return block_entries(self.starts)

    def _pad(self, N: int) -> None:
        """Grow the pose columns to ``N`` (new poses: no eliminated feature couples to them yet)."""
        n0 = self.G.shape[0]
        if N > n0:
            self.G = sp.csr_matrix((self.G.data, self.G.indices, np.concatenate(
                [self.G.indptr, np.full(N - n0, self.G.indptr[-1], self.G.indptr.dtype)])), shape=(N, N))
            self.g = np.concatenate([self.g, np.zeros(N - n0)])
        if self.B.shape[1] < N:
            self.B = sp.csr_matrix((self.B.data, self.B.indices, self.B.indptr), shape=(self.B.shape[0], N))

    @staticmethod
    def _rows(blocks: IntArray) -> IntArray:
        """The rows of ``B`` (and ``y``) of the features at positions ``blocks``."""
        return block_entries(3 * np.asarray(blocks, np.int64))


def _rows_then(B: sp.csr_matrix, rows: IntArray, more: sp.csr_matrix | None) -> sp.csr_matrix:
    """``vstack([B[rows], more])`` (CSR, sorted indices as ``B``'s and ``more``'s) written
    straight into the result's arrays: the old ``B`` and the result are the only copies
    alive at once."""
    counts = np.diff(B.indptr)[rows]
    extra = 0 if more is None else more.nnz
    indptr = np.zeros(len(rows) + 1 + (0 if more is None else more.shape[0]), np.int64)
    np.cumsum(counts, out=indptr[1: len(rows) + 1])
    nnz = int(indptr[len(rows)])
    data = np.empty(nnz + extra, B.data.dtype)
    indices = np.empty(nnz + extra, B.indices.dtype if extra == 0 else np.result_type(B.indices, more.indices))
    step = max(1, len(rows) * _GATHER_ENTRIES // max(nnz, 1))  # rows per pass: a bounded gather index
    for a in range(0, len(rows), step):
        b = min(a + step, len(rows))
        lo, hi = int(indptr[a]), int(indptr[b])
        src = np.repeat(B.indptr[rows[a:b]] - indptr[a:b], counts[a:b]) + np.arange(lo, hi)  # positions in B
        data[lo:hi], indices[lo:hi] = B.data[src], B.indices[src]
    if more is not None:
        indptr[len(rows) + 1:] = nnz + more.indptr[1:]
        data[nnz:], indices[nnz:] = more.data, more.indices
    out = sp.csr_matrix((data, indices, indptr), shape=(len(indptr) - 1, B.shape[1]))
    out.has_sorted_indices = B.has_sorted_indices and (more is None or more.has_sorted_indices)
    return out
