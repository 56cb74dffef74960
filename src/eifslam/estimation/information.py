"""Storage of the sparse information matrix and vector (pure NumPy / SciPy).

Fusing a batch (paper eq. 8) appends the blocks ``J^T Q^-1 J`` as triplets in constant
time per measurement. The matrix is kept in two summed parts, like a log-structured merge:
the triplets are summed into a small CSC matrix of recent additions once
:data:`FOLD_TRIPLETS` of them wait, and that one into the main CSC matrix once it holds a
:data:`MERGE_FRACTION` of the main one's non-zeros; :meth:`InformationStore.matrix` sums
what waits when somebody needs ``I`` (recovery, plots). A ``Zm`` leaves 42 to 100 triplets
(16 bytes each) but about 50 non-zeros, so the waiting triplets never take more than
32 MB, the recent part a fraction of the main one, and a merge's temporaries are the main
matrix, the recent part and their sum (letting every triplet wait until it outnumbers
twice the matrix's non-zeros and summing them at once takes several times the matrix);
each entry is summed into the main matrix about ``1 / MERGE_FRACTION`` times, so the
cost stays proportional to the non-zeros added.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


_INT32_MAX = np.iinfo(np.int32).max

#: Triplets that may wait before they are summed into the recent part (32 MB of them).
FOLD_TRIPLETS = 2_000_000

#: The recent part is summed into the main matrix once it holds this fraction of the main
#: one's non-zeros.
MERGE_FRACTION = 0.25

#: Stored entries read at a time by :func:`block` (about 24 MB of them).
BLOCK_NONZEROS = 2_000_000


class InformationStore:
    """Information matrix ``I`` (sparse, symmetric) and vector ``i`` of a growing state."""

    def __init__(self) -> None:
        self.dim = 0
        self._vec = np.zeros(64)
        self._rows: list[IntArray] = []
        self._cols: list[IntArray] = []
        self._vals: list[Array] = []
        self._pending = 0
        self._cached: sp.csc_matrix = sp.csc_matrix((0, 0))  # the main part
        self._recent: sp.csc_matrix | None = None  # summed triplets not yet in the main part
        #: Times ``I`` and ``i`` were replaced wholesale (:meth:`reset`, :meth:`set`): a sum of
        #: fusions recorded at one generation can be subtracted only at that generation.
        self.generation = 0
        self._changes = 0  # additions and replacements so far (what a count of non-zeros is valid for)
        self._nnz: tuple[int, int] | None = None  # (changes, nnz) of the last count

    def grow(self, dim: int) -> None:
        """Augment the state with zeros up to ``dim`` entries (Algorithm 1, step 4)."""
        if dim < self.dim:
            raise ValueError("the state cannot shrink")
        if dim > len(self._vec):
            new = np.zeros(max(dim, 2 * len(self._vec)))
            new[: self.dim] = self._vec[: self.dim]
            self._vec = new
        self.dim = dim

    @property
    def vector(self) -> Array:
        """The information vector ``i``, shape ``(dim,)`` (a view)."""
        return self._vec[: self.dim]

    def add(self, idx: IntArray, Lam: Array, eta: Array) -> None:
        """Add ``N`` dense blocks.

        Parameters
        ----------
        idx : (N, k) int
            State indices of each block's rows/columns.
        Lam : (N, k, k) float
            Information blocks ``J^T Q^-1 J``.
        eta : (N, k) float
            Information-vector contributions ``J^T Q^-1 (z - h + J x)``.
        """
        if len(idx) == 0:
            return
        if not (np.all(np.isfinite(Lam)) and np.all(np.isfinite(eta))):
            raise FloatingPointError("refusing to fuse non-finite information")
        k = idx.shape[1]
        idx = self._indices(idx)
        self._changes += 1
        self._rows.append(np.repeat(idx, k, axis=1).ravel())
        self._cols.append(np.tile(idx, (1, k)).ravel())
        self._vals.append(Lam.ravel())
        self._pending += Lam.size
        np.add.at(self._vec, idx.ravel(), eta.ravel())
        self._fold_if_due()

    def _fold_if_due(self) -> None:
        """Sum the waiting triplets into the recent part once there are
        :data:`FOLD_TRIPLETS` of them, and the recent part into the main matrix once it
        holds :data:`MERGE_FRACTION` of its non-zeros."""
        if self._pending <= FOLD_TRIPLETS:
            return
        self._fold()
        if self._recent.nnz > MERGE_FRACTION * self._cached.nnz:
            self.matrix()

    def _fold(self) -> None:
        """Sum the waiting triplets into the recent part."""
        n = self.dim
        r, c, v = self.pending_triplets()
        self._rows, self._cols, self._vals, self._pending = [], [], [], 0
        new = sp.csc_matrix((v, (r, c)), shape=(n, n))
        del r, c, v
        self._recent = new if self._recent is None else (_extend(self._recent, n) + new).tocsc()

    def _indices(self, idx: IntArray) -> NDArray:
        """State indices as stored in the triplets: 32-bit while the state allows (summing
        them into CSC in :meth:`matrix` is about twice as fast as with 64-bit ones, and
        they take half the memory)."""
        return np.asarray(idx, np.int32 if self.dim < _INT32_MAX else np.int64)

    def add_split(self, idx: IntArray, Lam: Array, eta: Array, split: int) -> None:
        """:meth:`add` for blocks of two parts, each shared by many blocks (the pose and
        the feature of ``Zm``): the two diagonal sub-blocks are first summed per distinct
        part (by its first index), and only the cross blocks stay one per block. The same
        ``I`` and ``i`` up to the order of the sums, from about 42 triplets a ``Zm``
        instead of 100, which is what :meth:`matrix` spends its time summing after a
        relinearisation.

        Parameters
        ----------
        idx, Lam, eta : as :meth:`add`, ``(N, k)``, ``(N, k, k)``, ``(N, k)``.
        split : int
            The first part is ``idx[:, :split]``, the second the rest.
        """
        if len(idx) == 0:
            return
        if not (np.all(np.isfinite(Lam)) and np.all(np.isfinite(eta))):
            raise FloatingPointError("refusing to fuse non-finite information")
        for part in (slice(0, split), slice(split, idx.shape[1])):
            first, inv = np.unique(idx[:, part.start], return_inverse=True)
            G = sp.csr_matrix((np.ones(len(idx)), (inv, np.arange(len(idx)))), shape=(len(first), len(idx)))
            block = idx[np.unique(inv, return_index=True)[1], part]  # one row of indices per distinct part
            n = part.stop - part.start
            # the base class's add: a tracking subclass reports the blocks as given, once
            InformationStore.add(self, block, (G @ Lam[:, part, part].reshape(len(idx), n * n)).reshape(-1, n, n),
                                 G @ eta[:, part])
        a, b = idx[:, :split], idx[:, split:]
        a, b = self._indices(a), self._indices(b)
        self._changes += 1
        na, nb = a.shape[1], b.shape[1]
        cross = Lam[:, :split, split:]
        self._rows += [np.repeat(a, nb, axis=1).ravel(), np.repeat(b, na, axis=1).ravel()]
        self._cols += [np.tile(b, (1, na)).ravel(), np.tile(a, (1, nb)).ravel()]
        self._vals += [cross.ravel(), np.swapaxes(cross, 1, 2).ravel()]
        self._pending += 2 * cross.size
        self._fold_if_due()

    def pending_triplets(self) -> tuple[IntArray, IntArray, Array]:
        """Triplets added and not yet summed into either part of the matrix."""
        if not self._rows:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        return np.concatenate(self._rows), np.concatenate(self._cols), np.concatenate(self._vals)

    def matrix(self) -> sp.csc_matrix:
        """The information matrix ``I`` as CSC, shape ``(dim, dim)``: every part summed
        into the main one."""
        n = self.dim
        base = _extend(self._cached, n)
        parts = [self._recent] if self._recent is not None else []
        if self._pending:
            r, c, v = self.pending_triplets()
            self._rows, self._cols, self._vals, self._pending = [], [], [], 0
            parts.append(sp.csc_matrix((v, (r, c)), shape=(n, n)))
            del r, c, v
        self._recent = None
        for part in parts:
            base = (base + _extend(part, n)).tocsc()
        self._cached = base
        return base

    def column_blocks(self) -> Iterator[sp.csc_matrix]:
        """``I`` as consecutive blocks of whole columns, each the sum of its parts (CSC,
        ``(dim, w)``, about :data:`BLOCK_NONZEROS` stored entries each), without summing
        the whole matrix: what :meth:`matrix` returns, one block at a time, for a writer
        that streams it (summing the parts into one matrix holds the old and the new main
        part at once: 0.3 GB more at the loop world's end)."""
        parts = self._parts()
        bounds = _runs(sum(np.diff(P.indptr) for P in parts))
        changes, nnz = self._changes, 0
        for a, b in zip(bounds[:-1], bounds[1:]):
            piece = sp.csc_matrix(_summed([P[:, a:b] for P in parts]))
            piece.sum_duplicates()
            nnz += piece.nnz
            yield piece
        if changes == self._changes:
            self._nnz = (changes, int(nnz))  # every block read: the count of :attr:`nnz`

    @property
    def nnz(self) -> int:
        """Stored entries of :meth:`matrix` (its parts' sum counted a block at a time when
        they are not summed yet: the count does not sum the whole matrix)."""
        if self._recent is None and not self._pending:
            return int(self._cached.nnz)
        if self._nnz is None or self._nnz[0] != self._changes:
            for _ in self.column_blocks():  # counts as it goes
                pass
        return self._nnz[1]

    def rows(self) -> "SummedRows":
        """``I`` read by rows without summing its parts into one matrix: the waiting
        triplets are summed into the recent part (as they would be anyway) and the main
        and recent parts are read as CSR (their CSC arrays, ``I`` being symmetric, as in
        :meth:`matrix_csr`). Taking some rows of the sum costs the non-zeros of those rows
        only, where :meth:`matrix` first sums every non-zero of ``I`` (about 1 s and a
        second copy of the matrix at the loop world's 35 M non-zeros)."""
        return SummedRows([sp.csr_matrix((C.data, C.indices, C.indptr), shape=C.shape) for C in self._parts()])

    def _parts(self) -> list[sp.csc_matrix]:
        """The main and the recent part, ``(dim, dim)`` each, the waiting triplets summed
        into the recent one first (as they would be anyway)."""
        n = self.dim
        if self._pending:
            self._fold()
        return [_extend(self._cached, n)] + ([_extend(self._recent, n)] if self._recent is not None else [])

    def matrix_csr(self) -> sp.csr_matrix:
        """``I`` as CSR without a format conversion: ``I`` is symmetric, so the arrays of
        its CSC form (:meth:`matrix`) read as CSR are ``I^T``, which equals ``I`` up to the
        rounding of the sums (each entry and its mirror are sums of the same numbers,
        possibly in another order). SciPy's conversion copies and re-sorts every entry:
        about 1.2 s at the loop world's 35 M non-zeros. Shares the arrays of
        :meth:`matrix`'s result (neither may be changed in place)."""
        C = self.matrix()
        return sp.csr_matrix((C.data, C.indices, C.indptr), shape=C.shape)

    def reset(self) -> None:
        """Zero information, same dimension (smoothing starts from here)."""
        self._vec[:] = 0.0
        self.generation += 1
        self._changes += 1
        self._rows, self._cols, self._vals, self._pending = [], [], [], 0
        self._recent = None
        self._cached = sp.csc_matrix((self.dim, self.dim))

    def set(self, I: sp.spmatrix, i: Array) -> None:
        """Replace ``I`` and ``i`` (scale recovery)."""
        self.generation += 1
        self._changes += 1
        self._rows, self._cols, self._vals, self._pending = [], [], [], 0
        self._recent = None
        self._cached = sp.csc_matrix(I)
        self._vec[: self.dim] = i


class SummedRows:
    """A sparse matrix kept as a sum of CSR parts of one shape, read by rows.

    ``A[rows]`` (rows an integer array or slice) is the CSR matrix of those rows of the
    sum, canonical (sorted indices, no duplicates); :meth:`tocsr` sums everything.

    Parameters
    ----------
    parts : list of CSR, each ``(n, n)``, at least one.
    """

    def __init__(self, parts: list[sp.csr_matrix]) -> None:
        if not parts:
            raise ValueError("SummedRows needs at least one part")
        self.parts = parts
        self.shape = parts[0].shape

    def __getitem__(self, rows) -> sp.csr_matrix:
        out = sp.csr_matrix(_summed([p[rows] for p in self.parts]))
        out.sum_duplicates()
        return out

    def block(self, rows: IntArray, cols: IntArray) -> sp.csr_matrix:
        """``A[rows][:, cols]`` (canonical CSR), read :data:`BLOCK_NONZEROS` non-zeros of
        the parts' rows at a time: the rows of a pose hold its coupling to every feature
        it saw, so ``A[rows]`` of many poses is a copy of much of ``A`` (and the sum of
        the parts two more) for the few columns kept."""
        return _chunked_block(self.parts, np.asarray(rows, np.int64), np.asarray(cols, np.int64))

    def tocsr(self) -> sp.csr_matrix:
        """The whole sum as one CSR matrix."""
        return sp.csr_matrix(_summed(self.parts))


def block(A: sp.csr_matrix | SummedRows, rows: IntArray, cols: IntArray) -> sp.csr_matrix:
    """``A[rows][:, cols]`` of a CSR matrix or a :class:`SummedRows` (canonical CSR),
    read a bounded number of non-zeros at a time (:meth:`SummedRows.block`)."""
    if isinstance(A, SummedRows):
        return A.block(rows, cols)
    return _chunked_block([sp.csr_matrix(A)], np.asarray(rows, np.int64), np.asarray(cols, np.int64))


def _chunked_block(parts: list[sp.csr_matrix], rows: IntArray, cols: IntArray) -> sp.csr_matrix:
    """The sum of ``P[rows][:, cols]`` over the CSR ``parts``, rows taken in runs of at most
    :data:`BLOCK_NONZEROS` stored entries (each run's rows cut to ``cols`` before the next
    is read)."""
    bounds = _runs(sum(np.diff(P.indptr)[rows] for P in parts))
    out = [sp.csr_matrix(_summed([P[rows[a:b]][:, cols] for P in parts])) for a, b in zip(bounds[:-1], bounds[1:])]
    if not out:
        return sp.csr_matrix((0, len(cols)))
    res = out[0] if len(out) == 1 else sp.vstack(out, format="csr")
    res.sum_duplicates()
    return res


def _runs(counts: IntArray) -> IntArray:
    """Bounds ``[0, ..., len(counts)]`` cutting consecutive items (rows or columns holding
    ``counts`` stored entries) into runs of about :data:`BLOCK_NONZEROS` entries; an item
    holding more is a run of its own."""
    n = len(counts)
    ends = np.searchsorted(np.cumsum(counts), BLOCK_NONZEROS * np.arange(1, int(np.sum(counts)) // BLOCK_NONZEROS + 1),
                           side="right")
    return np.unique(np.concatenate([[0], np.clip(ends, 1, max(n, 1)), [n]])).astype(np.int64)


def _summed(pieces: list[sp.spmatrix]) -> sp.spmatrix:
    """The sum of sparse matrices of one shape (the first one itself when alone)."""
    out = pieces[0]
    for p in pieces[1:]:
        out = out + p
    return out


def _extend(A: sp.csc_matrix, n: int) -> sp.csc_matrix:
    """``A`` as an ``(n, n)`` matrix, the new states' columns empty: the column pointers
    extended and the entries shared (a copy and SciPy's resize cost about 0.7 s at 35 M
    non-zeros, this 1 ms). The matrices handed out are never changed in place."""
    if A.shape == (n, n):
        return A
    return sp.csc_matrix((A.data, A.indices, np.concatenate(
        [A.indptr, np.full(n - A.shape[1], A.indptr[-1], A.indptr.dtype)])), shape=(n, n))

