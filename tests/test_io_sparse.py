"""A sparse matrix written block by block reads back with SciPy as the same matrix."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from eifslam.errors import OutputError
from eifslam.io.sparse import write_csc_npz


def _blocks(A: sp.csc_matrix, bounds: list[int]) -> list[sp.csc_matrix]:
    return [sp.csc_matrix(A[:, a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


@pytest.mark.parametrize("bounds", [[0, 40], [0, 1, 2, 17, 17, 39, 40], [0, 10, 20, 30, 40]])
def test_blocks_written_read_back_as_the_matrix(tmp_path, bounds):
    A = sp.random(30, 40, density=0.2, random_state=3, format="csc")
    A.sort_indices()
    path = tmp_path / "information.npz"
    nnz = write_csc_npz(path, A.shape, _blocks(A, bounds))
    B = sp.load_npz(path)
    assert nnz == A.nnz and B.format == "csc" and B.shape == A.shape
    np.testing.assert_array_equal(B.indptr, A.indptr)
    np.testing.assert_array_equal(B.indices, A.indices)
    np.testing.assert_array_equal(B.data, A.data)
    assert not [p.name for p in tmp_path.iterdir() if p.name != "information.npz"]  # no scratch left


def test_empty_matrix(tmp_path):
    path = tmp_path / "m.npz"
    assert write_csc_npz(path, (0, 0), []) == 0
    assert sp.load_npz(path).shape == (0, 0)


def test_blocks_that_do_not_make_the_shape_are_refused_and_nothing_is_left(tmp_path):
    A = sp.random(5, 6, density=0.5, random_state=0, format="csc")
    with pytest.raises(ValueError, match="columns"):
        write_csc_npz(tmp_path / "m.npz", (5, 7), _blocks(A, [0, 6]))
    with pytest.raises(ValueError, match="rows"):
        write_csc_npz(tmp_path / "m.npz", (4, 6), _blocks(A, [0, 6]))
    assert not list(tmp_path.iterdir())


def test_unwritable_target_is_one_output_error(tmp_path):
    (tmp_path / "m.npz").mkdir()  # a folder where the file should go
    with pytest.raises(OutputError, match="m.npz"):
        write_csc_npz(tmp_path / "m.npz", (2, 2), [sp.csc_matrix(np.eye(2))])


def test_information_store_written_unsummed_reads_back_as_its_matrix(tmp_path, monkeypatch):
    from eifslam.estimation import information

    monkeypatch.setattr(information, "BLOCK_NONZEROS", 40)  # many column blocks
    rng = np.random.default_rng(2)
    store, n = information.InformationStore(), 0
    for step in range(30):
        n += 3
        store.grow(n)
        idx = np.array([rng.choice(n, 3, replace=False) for _ in range(4)])
        A = rng.normal(size=(4, 3, 3))
        store.add(idx, A @ A.transpose(0, 2, 1), rng.normal(size=(4, 3)))
        if step == 12:
            store.matrix()  # a main part, then more waiting beside it
    nnz = store.nnz
    assert write_csc_npz(tmp_path / "i.npz", (n, n), store.column_blocks()) == nnz
    I = store.matrix()
    assert store.nnz == I.nnz == nnz
    np.testing.assert_array_equal(sp.load_npz(tmp_path / "i.npz").toarray(), I.toarray())
