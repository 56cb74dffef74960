"""The information store sums what is fused exactly, however its parts are folded."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.estimation import information
from eifslam.estimation.information import InformationStore


@pytest.mark.parametrize("fold", [10**9, 300, 50])
def test_the_matrix_is_the_sum_of_every_block_whatever_the_folding(monkeypatch, fold):
    monkeypatch.setattr(information, "FOLD_TRIPLETS", fold)
    monkeypatch.setattr(information, "BLOCK_NONZEROS", 7)
    rng = np.random.default_rng(0)
    store, dense, vec = InformationStore(), np.zeros((0, 0)), np.zeros(0)
    n = 3
    for step in range(40):  # the state grows, blocks land on old and new entries
        n += int(rng.integers(1, 6))
        store.grow(n)
        dense = np.pad(dense, ((0, n - len(dense)), (0, n - len(dense))))
        vec = np.pad(vec, (0, n - len(vec)))
        idx = np.array([rng.choice(n, 3, replace=False) for _ in range(int(rng.integers(1, 8)))])
        A = rng.normal(size=(len(idx), 3, 3))
        Lam, eta = A @ A.transpose(0, 2, 1), rng.normal(size=(len(idx), 3))
        store.add(idx, Lam, eta)
        for b, e, ix in zip(Lam, eta, idx):
            dense[np.ix_(ix, ix)] += b
            np.add.at(vec, ix, e)
        if step % 13 == 12:  # somebody reads I in between
            np.testing.assert_allclose(store.matrix().toarray(), dense, atol=1e-12)
        if step % 7 == 3:  # or some of its rows, without summing its parts
            R = store.rows()
            rows = rng.choice(n, min(n, 5), replace=False)
            Ir = R[rows]
            assert Ir.format == "csr" and Ir.shape == (len(rows), n) and Ir.has_canonical_format
            np.testing.assert_allclose(Ir.toarray(), dense[rows], atol=1e-12)
            np.testing.assert_allclose(R.tocsr().toarray(), dense, atol=1e-12)
            cols = rng.choice(n, min(n, 4), replace=False)
            for A in (R, R.tocsr()):  # a block read a few entries at a time, of the parts or of one matrix
                Ib = information.block(A, rows, cols)
                assert Ib.format == "csr" and Ib.shape == (len(rows), len(cols)) and Ib.has_canonical_format
                np.testing.assert_allclose(Ib.toarray(), dense[np.ix_(rows, cols)], atol=1e-12)
    I = store.matrix()
    assert I.shape == (n, n) and I.has_canonical_format
    np.testing.assert_allclose(I.toarray(), dense, atol=1e-12)
    np.testing.assert_allclose(store.vector, vec, atol=1e-12)
    np.testing.assert_allclose(store.matrix_csr().toarray(), dense, atol=1e-12)
