"""Feature-track identities (pure NumPy).

A track id is an ``int64`` allocated once. Tracks can later be merged (relocalisation: a
feature seen again after tracking was lost regains its old identity); merges are kept in
a union-find forest, and :meth:`TrackStore.resolve` maps any id ever handed out to the
current identity, the oldest (smallest) id of the merged group. Each track carries its
set flag (``Ωm`` = map, else ``Ωp``), fixed at creation; only tracks of the same set merge.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import SessionError
from ..estimation.statedict import take, take_ids

IntArray = NDArray[np.int64]

__all__ = ["TrackStore"]


class TrackStore:
    """Allocation, set membership and merging of track ids.

    Examples
    --------
    >>> ts = TrackStore()
    >>> ts.allocate(np.array([True, False, True]))
    array([0, 1, 2])
    >>> ts.merge(2, 0)
    True
    >>> ts.resolve(np.array([0, 1, 2]))
    array([0, 1, 0])
    """

    def __init__(self) -> None:
        self._parent = np.zeros(0, np.int64)
        self._in_map = np.zeros(0, bool)
        self._length = np.zeros(0, np.int64)

    def state_dict(self) -> dict:
        """What a session keeps: ``parent``, ``in_map`` and ``length`` per id ever allocated."""
        return {"parent": self._parent.copy(), "in_map": self._in_map.copy(), "length": self._length.copy()}

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict`, checked (:class:`~eifslam.errors.SessionError`)."""
        parent = take_ids(d, "parent")
        n = len(parent)
        in_map, length = take(d, "in_map", bool, (n,)), take_ids(d, "length", n)
        if np.any(parent > np.arange(n)):
            raise SessionError("array 'parent' points to a younger track (merges point to the older id)")
        self._parent, self._in_map, self._length = parent.copy(), in_map.copy(), length.copy()

    def __len__(self) -> int:
        """Number of ids ever allocated."""
        return int(len(self._parent))

    def allocate(self, in_map: NDArray[np.bool_]) -> IntArray:
        """New track ids, one per flag (True: the track belongs to ``Ωm``)."""
        in_map = np.asarray(in_map, bool).reshape(-1)
        start = len(self._parent)
        ids = np.arange(start, start + len(in_map), dtype=np.int64)
        self._parent = np.concatenate([self._parent, ids])
        self._in_map = np.concatenate([self._in_map, in_map])
        self._length = np.concatenate([self._length, np.zeros(len(ids), np.int64)])
        return ids

    def observe(self, ids: IntArray) -> None:
        """Count one more frame for each (distinct) track id."""
        roots = self.resolve(np.asarray(ids, np.int64).reshape(-1))
        np.add.at(self._length, roots, 1)

    def length(self, ids: IntArray) -> IntArray:
        """Number of frames each track has been seen in (via :meth:`observe`)."""
        ids = np.asarray(ids, np.int64)
        return self._length[self.resolve(ids)] if ids.size else np.zeros(ids.shape, np.int64)

    def resolve(self, ids: IntArray) -> IntArray:
        """Current identity of each id, shape preserved (path-compressing)."""
        ids = np.asarray(ids, np.int64)
        if ids.size == 0:
            return ids.copy()
        cur = ids.copy()
        while True:
            nxt = self._parent[cur]
            if np.array_equal(nxt, cur):
                break
            cur = nxt
        self._parent[ids] = cur
        return cur

    def in_map(self, ids: IntArray) -> NDArray[np.bool_]:
        """Set flag of each id (True: ``Ωm``)."""
        ids = np.asarray(ids, np.int64)
        return self._in_map[ids] if ids.size else np.zeros(ids.shape, bool)

    def merge(self, a: int, b: int) -> bool:
        """Merge the tracks of ids ``a`` and ``b`` into the older identity.

        The caller checks that the two tracks share no frame.

        Returns
        -------
        bool
            False (nothing done) when they are of different sets; True otherwise.
        """
        ra, rb = (int(v) for v in self.resolve(np.array([a, b])))
        if ra == rb:
            return True
        if self._in_map[ra] != self._in_map[rb]:
            return False
        lo, hi = min(ra, rb), max(ra, rb)
        self._parent[hi] = lo
        self._length[lo] += self._length[hi]
        return True
