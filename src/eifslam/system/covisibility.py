"""Which frames observed which map tracks, counted fast for a frame's tracks (the
covisibility that loop closure queries several times a frame).

The observations are unique ``(track, frame)`` pairs. Most of them sit in a sparse
track-by-frame matrix, so that the frames covisible with a set of tracks are the column
sums of its rows; the pairs recorded since the matrix was last rebuilt sit in a second,
small matrix, rebuilt when pairs are added. On the loop world this takes a query from
about 3 ms (a Python chain over every track's frame set) to well under 1 ms.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

IntArray = NDArray[np.int64]

__all__ = ["Covisibility"]


class Covisibility:
    """Unique ``(track, frame)`` observation pairs and their counts per frame.

    Parameters
    ----------
    merge_every : int
        Pairs recorded since the big matrix was built; at this many it is rebuilt with them.
    """

    def __init__(self, merge_every: int = 50_000) -> None:
        self.merge_every = int(merge_every)
        self._frames: dict[int, set[int]] = {}  # per track: the frames that observed it
        self._base = sp.csr_matrix((0, 0), dtype=np.int64)
        self._new: list[tuple[int, int]] = []  # pairs not in _base yet
        self._recent: sp.csr_matrix | None = None  # _new as a matrix (None: to build)

    def add(self, track: int, frame: int) -> bool:
        """Record that ``frame`` observed ``track``; False if it was recorded already."""
        seen = self._frames.setdefault(int(track), set())
        if int(frame) in seen:
            return False
        seen.add(int(frame))
        self._new.append((int(track), int(frame)))
        self._recent = None
        if len(self._new) >= self.merge_every:
            self._base = self._matrix(self._new, self._base)
            self._new = []
        return True

    def frames_of(self, track: int) -> set[int]:
        """The frames that observed ``track`` (a copy)."""
        return set(self._frames.get(int(track), ()))

    def count(self, track_ids) -> dict[int, int]:
        """Frames that observed any of ``track_ids`` (any shape; repeated ids count again,
        negative ids never match), with how many of the ids each observed; sorted by frame."""
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        ids = ids[ids >= 0]
        if self._recent is None:
            self._recent = self._matrix(self._new)
        width = max(self._base.shape[1], self._recent.shape[1])
        total = np.zeros(width, np.int64)
        for M in (self._base, self._recent):
            rows = ids[ids < M.shape[0]]
            if len(rows) and M.nnz:
                total[: M.shape[1]] += np.asarray(M[rows].sum(axis=0)).ravel()
        f = np.flatnonzero(total)
        return dict(zip(f.tolist(), total[f].tolist()))

    @staticmethod
    def _matrix(pairs: list[tuple[int, int]], base: sp.csr_matrix | None = None) -> sp.csr_matrix:
        """The track-by-frame 0/1 matrix of ``pairs`` (plus ``base``'s pairs, all distinct)."""
        P = np.array(pairs, np.int64).reshape(-1, 2)
        rows, cols = P[:, 0], P[:, 1]
        if base is not None and base.nnz:
            coo = base.tocoo()
            rows, cols = np.concatenate([coo.row, rows]), np.concatenate([coo.col, cols])
        shape = (int(rows.max()) + 1 if len(rows) else 0, int(cols.max()) + 1 if len(cols) else 0)
        return sp.csr_matrix((np.ones(len(rows), np.int64), (rows, cols)), shape=shape)
