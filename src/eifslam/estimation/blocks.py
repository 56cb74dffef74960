"""Small dense blocks of the information matrix, batched (pure NumPy/SciPy).

A feature's information is a 3x3 block on the diagonal of ``I`` (no measurement involves
two features) and a pose's a 7x7 one; the solvers gather these blocks, factorise or
invert them in one batched call, apply them to vectors and turn them back into a sparse
block-diagonal matrix. These kernels are written here once:

* :func:`block_entries`: the state entries of blocks given by their first entries;
* :func:`gather_diagonal_blocks`, :func:`sparse_diagonal_blocks`,
  :func:`dense_diagonal_blocks`: the diagonal blocks of a matrix;
* :func:`block_diagonal_csr`: the sparse block-diagonal matrix of a stack of blocks;
* :func:`apply_blocks`: ``blockdiag(A) v`` for a stack ``A``;
* :func:`cholesky_blocks`, :func:`inverse_spd_blocks`: batched factorisation and inverse
  of positive definite blocks, with an :class:`~eifslam.errors.EstimatorError` when one
  is not;
* :func:`pose_cholesky`: the dense Cholesky factorisation of the information of poses
  being eliminated.

>>> import numpy as np
>>> A = np.stack([np.eye(3), 2 * np.eye(3)])
>>> apply_blocks(inverse_spd_blocks(A), np.ones(6))
array([1. , 1. , 1. , 0.5, 0.5, 0.5])
>>> block_diagonal_csr(A).shape
(6, 6)
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.linalg import cho_factor

from ..errors import EstimatorError
from .state import FEATURE_DIM, POSE_DIM

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["apply_blocks", "block_diagonal_csr", "block_entries", "cholesky_blocks", "dense_diagonal_blocks",
           "gather_diagonal_blocks", "inverse_spd_blocks", "pose_cholesky", "sparse_diagonal_blocks"]

_NOT_SLAM_FORM = "two features share a measurement: the information matrix is not of SLAM form"
_NO_INFORMATION = "a feature has no information in some direction (seen from one pose only?)"


def block_entries(starts: IntArray, size: int = FEATURE_DIM) -> IntArray:
    """``(len(starts) * size,)`` state entries of the blocks whose first entries are
    ``starts``, block by block.

    >>> block_entries(np.array([0, 10]), 3)
    array([ 0,  1,  2, 10, 11, 12])
    """
    return (np.asarray(starts, np.int64).reshape(-1)[:, None] + np.arange(size)).ravel()


def gather_diagonal_blocks(row: IntArray, col: IntArray, val: Array, n_blocks: int,
                           size: int = FEATURE_DIM) -> Array:
    """``(n_blocks, size, size)`` diagonal blocks of a matrix given by its entries
    ``(row, col, val)`` (duplicates summed), whose blocks are ``size`` consecutive rows and
    columns.

    Raises
    ------
    EstimatorError
        When a non-zero entry lies outside the diagonal blocks (two features share a
        measurement: ``I`` is not of SLAM form).
    """
    same = row // size == col // size
    if np.any(~same & (val != 0)):
        raise EstimatorError(_NOT_SLAM_FORM)
    D = np.zeros((n_blocks, size, size))
    np.add.at(D, (row[same] // size, row[same] % size, col[same] % size), val[same])
    return D


def sparse_diagonal_blocks(M: sp.spmatrix, size: int = FEATURE_DIM) -> Array:
    """``(n / size, size, size)`` diagonal blocks of the square sparse ``M`` (``(n, n)``),
    which must be block diagonal (:func:`gather_diagonal_blocks`)."""
    coo = sp.coo_matrix(M)
    return gather_diagonal_blocks(coo.row, coo.col, coo.data, M.shape[0] // size, size)


def dense_diagonal_blocks(A: Array, size: int = FEATURE_DIM) -> Array:
    """``(n / size, size, size)`` diagonal blocks (copies) of the dense ``A`` (``(n, n)``).

    >>> dense_diagonal_blocks(np.arange(16.0).reshape(4, 4), 2)[1]
    array([[10., 11.],
           [14., 15.]])
    """
    F = A.shape[0] // size
    if F == 0:
        return np.zeros((0, size, size))
    ar = np.arange(F)
    return np.asarray(A).reshape(F, size, F, size)[ar, :, ar, :].copy()


def block_diagonal_csr(blocks: Array) -> sp.csr_matrix:
    """The ``(F s, F s)`` CSR block-diagonal matrix of ``blocks`` ``(F, s, s)``."""
    F, s = blocks.shape[0], blocks.shape[1]
    rows = np.repeat(np.arange(F * s), s)
    cols = (np.arange(F * s)[:, None] // s * s + np.arange(s)).ravel()
    return sp.csr_matrix((blocks.reshape(F * s, s).ravel(), (rows, cols)), shape=(F * s, F * s))


def apply_blocks(blocks: Array, v: Array) -> Array:
    """``blockdiag(blocks) v`` for ``blocks`` ``(F, s, s)`` and ``v`` ``(F s,)`` or
    ``(F s, m)``; the result has the shape of ``v``."""
    F, s = blocks.shape[0], blocks.shape[1]
    if v.ndim == 1:
        return np.einsum("fij,fj->fi", blocks, v.reshape(F, s)).ravel()
    m = v.shape[1]
    return np.einsum("fij,fjm->fim", blocks, v.reshape(F, s, m)).reshape(F * s, m)


def cholesky_blocks(D: Array) -> Array:
    """Lower Cholesky factors of ``(F, s, s)`` blocks.

    Raises
    ------
    EstimatorError
        When a block is not positive definite (a feature without information in some
        direction).
    """
    try:
        return np.linalg.cholesky(D)
    except np.linalg.LinAlgError:
        raise EstimatorError(_NO_INFORMATION) from None


def inverse_spd_blocks(D: Array) -> Array:
    """Inverses of ``(F, s, s)`` positive definite blocks.

    Raises
    ------
    EstimatorError
        When a block is not positive definite (:func:`cholesky_blocks`).
    """
    cholesky_blocks(D)
    return np.linalg.inv(D)


def pose_cholesky(A: Array) -> tuple[Array, bool]:
    """``cho_factor(A, lower=True)`` of the information of poses being eliminated
    (``(7 q, 7 q)``).

    Raises
    ------
    EstimatorError
        When ``A`` is numerically indefinite (``I`` too ill-conditioned for a Cholesky
        factorisation), so that the caller falls back to a full sparse solve instead of
        stopping the run.
    """
    try:
        return cho_factor(A, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        raise EstimatorError(f"the information of {len(A) // POSE_DIM} pose(s) to eliminate is numerically "
                             "indefinite") from None
