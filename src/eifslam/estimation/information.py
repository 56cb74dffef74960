"""Storage of the sparse information matrix and vector (pure NumPy / SciPy).

Fusing a batch (paper eq. 8) appends the blocks ``J^T Q^-1 J`` as triplets in constant
time per measurement; the matrix is summed into CSC form when somebody needs it
(recovery, plots), and when the triplets waiting outnumber twice the matrix's non-zeros
(and :data:`FOLD_TRIPLETS`): a ``Zm`` leaves 100 triplets (1.6 kB) but adds about 50
non-zeros, so folding bounds the memory to a few times the matrix's, at an amortised
cost proportional to the non-zeros.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


_INT32_MAX = np.iinfo(np.int32).max

#: Triplets that may wait before they are folded into the matrix (32 MB of them).
FOLD_TRIPLETS = 2_000_000


class InformationStore:
    """Information matrix ``I`` (sparse, symmetric) and vector ``i`` of a growing state."""

    def __init__(self) -> None:
        self.dim = 0
        self._vec = np.zeros(64)
        self._rows: list[IntArray] = []
        self._cols: list[IntArray] = []
        self._vals: list[Array] = []
        self._pending = 0
        self._cached: sp.csc_matrix = sp.csc_matrix((0, 0))
        #: Times ``I`` and ``i`` were replaced wholesale (:meth:`reset`, :meth:`set`): a sum of
        #: fusions recorded at one generation can be subtracted only at that generation.
        self.generation = 0

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
        self._rows.append(np.repeat(idx, k, axis=1).ravel())
        self._cols.append(np.tile(idx, (1, k)).ravel())
        self._vals.append(Lam.ravel())
        self._pending += Lam.size
        np.add.at(self._vec, idx.ravel(), eta.ravel())
        self._fold_if_due()

    def _fold_if_due(self) -> None:
        """Sum the waiting triplets into the matrix once they outnumber twice its
        non-zeros and :data:`FOLD_TRIPLETS` (the memory they take then stays within a few
        times the matrix's; the cost, amortised, stays proportional to its non-zeros)."""
        if self._pending > max(FOLD_TRIPLETS, 2 * self._cached.nnz):
            self.matrix()

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
        na, nb = a.shape[1], b.shape[1]
        cross = Lam[:, :split, split:]
        self._rows += [np.repeat(a, nb, axis=1).ravel(), np.repeat(b, na, axis=1).ravel()]
        self._cols += [np.tile(b, (1, na)).ravel(), np.tile(a, (1, nb)).ravel()]
        self._vals += [cross.ravel(), np.swapaxes(cross, 1, 2).ravel()]
        self._pending += 2 * cross.size
        self._fold_if_due()

    def pending_triplets(self) -> tuple[IntArray, IntArray, Array]:
        """Triplets added since the last :meth:`matrix` call (not yet summed)."""
        if not self._rows:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
        return np.concatenate(self._rows), np.concatenate(self._cols), np.concatenate(self._vals)

    def matrix(self) -> sp.csc_matrix:
        """The information matrix ``I`` as CSC, shape ``(dim, dim)``."""
        n = self.dim
        base = self._cached
        if base.shape != (n, n):
            # the new states' columns are empty: extend the column pointers and share the
            # entries (a copy and scipy's resize cost ~0.7 s at 35 M non-zeros, this 1 ms);
            # the matrices handed out are never changed in place
            base = sp.csc_matrix((base.data, base.indices, np.concatenate(
                [base.indptr, np.full(n - base.shape[1], base.indptr[-1], base.indptr.dtype)])), shape=(n, n))
        if self._pending:
            r, c, v = self.pending_triplets()
            base = (base + sp.csc_matrix((v, (r, c)), shape=(n, n))).tocsc()
            self._rows, self._cols, self._vals, self._pending = [], [], [], 0
        self._cached = base
        return base

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
        self._rows, self._cols, self._vals, self._pending = [], [], [], 0
        self._cached = sp.csc_matrix((self.dim, self.dim))

    def set(self, I: sp.spmatrix, i: Array) -> None:
        """Replace ``I`` and ``i`` (scale recovery)."""
        self.generation += 1
        self._rows, self._cols, self._vals, self._pending = [], [], [], 0
        self._cached = sp.csc_matrix(I)
        self._vec[: self.dim] = i
