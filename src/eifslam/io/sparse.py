"""A sparse matrix written block by block into the file ``scipy.sparse.save_npz`` writes.

:func:`write_csc_npz` takes a CSC matrix as consecutive blocks of whole columns and writes
the uncompressed ``.npz`` that :func:`scipy.sparse.load_npz` reads (``data``, ``indices``,
``indptr``, ``format``, ``shape``), holding one block in memory at a time: the entries go
to scratch files beside the target first (an ``.npy`` header names its length), then into
the archive. The run's information matrix is written this way
(:meth:`~eifslam.estimation.information.InformationStore.column_blocks`), so that saving
it does not sum its parts into a second copy of the matrix.
"""

from __future__ import annotations

import shutil
import tempfile
import zipfile
from pathlib import Path
from typing import Iterable

import numpy as np
import scipy.sparse as sp

from .files import atomic_path

__all__ = ["write_csc_npz"]

_INT32_MAX = np.iinfo(np.int32).max


def write_csc_npz(path: str | Path, shape: tuple[int, int], blocks: Iterable[sp.csc_matrix]) -> int:
    """Write the CSC matrix whose consecutive column blocks are ``blocks`` to ``path``.

    Parameters
    ----------
    path : file to write (atomically, :func:`~eifslam.io.files.atomic_path`).
    shape : (rows, columns) of the whole matrix.
    blocks : CSC matrices ``(rows, w_b)``, canonical, whose widths sum to ``columns``.

    Returns
    -------
    int
        The matrix's stored entries.

    Raises
    ------
    OutputError
        The file cannot be written (names it).
    ValueError
        The blocks do not make up ``shape``.
    """
    n_rows, n_cols = (int(s) for s in shape)
    target = Path(path)
    index = np.int32 if n_rows <= _INT32_MAX else np.int64
    with atomic_path(target) as tmp, tempfile.TemporaryDirectory(prefix=f".{target.name}.", dir=target.parent) as d:
        scratch = Path(d)
        indptr = [np.zeros(1, np.int64)]
        nnz = cols = 0
        with open(scratch / "data", "wb") as fd, open(scratch / "indices", "wb") as fi:
            for b in blocks:
                if b.shape[0] != n_rows:
                    raise ValueError(f"a block has {b.shape[0]} rows, the matrix {n_rows}")
                np.asarray(b.data, np.float64).tofile(fd)
                np.asarray(b.indices, index).tofile(fi)
                indptr.append(nnz + np.asarray(b.indptr[1:], np.int64))
                nnz += int(b.nnz)
                cols += b.shape[1]
        if cols != n_cols:
            raise ValueError(f"the blocks have {cols} columns, the matrix {n_cols}")
        ptr = np.concatenate(indptr)
        ptr = ptr.astype(np.int32) if nnz <= _INT32_MAX else ptr
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, dtype in (("indices", index), ("data", np.float64)):
                with zf.open(f"{name}.npy", "w", force_zip64=True) as out, open(scratch / name, "rb") as src:
                    np.lib.format.write_array_header_1_0(out, {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                                                               "fortran_order": False, "shape": (nnz,)})
                    shutil.copyfileobj(src, out, 1 << 24)
            for name, arr in (("indptr", ptr), ("format", np.array(b"csc")),
                              ("shape", np.array([n_rows, n_cols], np.int64))):
                with zf.open(f"{name}.npy", "w", force_zip64=True) as out:
                    np.lib.format.write_array(out, arr, allow_pickle=False)
    return nnz
