"""The batched small-block kernels (estimation/blocks.py) against dense references."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp

from eifslam.errors import EstimatorError
from eifslam.estimation import blocks


def spd_blocks(rng: np.random.Generator, F: int, s: int = 3) -> np.ndarray:
    A = rng.normal(size=(F, s, s))
    return A @ A.transpose(0, 2, 1) + s * np.eye(s)


def test_block_entries():
    np.testing.assert_array_equal(blocks.block_entries(np.array([3, 10]), 7), [3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15, 16])
    assert blocks.block_entries(np.zeros(0, np.int64)).shape == (0,)


def test_diagonal_blocks_of_sparse_and_dense_match_the_blocks_that_made_them():
    rng = np.random.default_rng(0)
    D = spd_blocks(rng, 5)
    M = sp.csr_matrix(scipy.linalg.block_diag(*D))
    np.testing.assert_array_equal(blocks.sparse_diagonal_blocks(M), D)
    np.testing.assert_array_equal(blocks.dense_diagonal_blocks(M.toarray()), D)
    np.testing.assert_array_equal(blocks.block_diagonal_csr(D).toarray(), M.toarray())
    assert blocks.dense_diagonal_blocks(np.zeros((0, 0))).shape == (0, 3, 3)
    P = spd_blocks(rng, 2, 7)
    np.testing.assert_array_equal(blocks.dense_diagonal_blocks(scipy.linalg.block_diag(*P), 7), P)


def test_gathered_duplicates_are_summed_and_a_coupling_between_blocks_is_refused():
    D = blocks.gather_diagonal_blocks(np.array([0, 0, 4]), np.array([1, 1, 5]), np.array([1.0, 2.0, 5.0]), 2)
    assert D[0, 0, 1] == 3.0 and D[1, 1, 2] == 5.0 and np.count_nonzero(D) == 2
    E = np.eye(6)
    E[0, 4] = 1.0
    M = sp.csr_matrix(E)
    with pytest.raises(EstimatorError, match="SLAM form"):
        blocks.sparse_diagonal_blocks(M)


def test_apply_factor_and_invert_blocks():
    rng = np.random.default_rng(1)
    D = spd_blocks(rng, 4)
    dense = scipy.linalg.block_diag(*D)
    v, V = rng.normal(size=12), rng.normal(size=(12, 5))
    np.testing.assert_allclose(blocks.apply_blocks(D, v), dense @ v, rtol=1e-12)
    np.testing.assert_allclose(blocks.apply_blocks(D, V), dense @ V, rtol=1e-12)
    L = blocks.cholesky_blocks(D)
    np.testing.assert_allclose(L @ L.transpose(0, 2, 1), D, rtol=1e-12)
    np.testing.assert_allclose(scipy.linalg.block_diag(*blocks.inverse_spd_blocks(D)), np.linalg.inv(dense),
                               rtol=1e-10, atol=1e-14)
    D[2] = np.diag([1.0, 0.0, 1.0])  # a feature without information along one axis
    with pytest.raises(EstimatorError, match="no information"):
        blocks.inverse_spd_blocks(D)


def test_pose_cholesky_solves_and_refuses_indefinite_information():
    rng = np.random.default_rng(2)
    A = spd_blocks(rng, 1, 14)[0]
    b = rng.normal(size=14)
    np.testing.assert_allclose(scipy.linalg.cho_solve(blocks.pose_cholesky(A), b), np.linalg.solve(A, b), rtol=1e-10)
    with pytest.raises(EstimatorError, match="numerically indefinite"):
        blocks.pose_cholesky(np.diag([1.0, -1.0, 1.0, 1.0, 1.0, 1.0, 1.0]))
