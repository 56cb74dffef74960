"""The map observations of every keyframe, per track, in flat arrays.

:class:`TrackObservations` keeps each recorded observation (track, frame, pixel) as one row
of growing NumPy arrays, with a link from each row to the track's previous row: appending
costs constant time per observation, and the history of many tracks at once (the frames
that saw them, in recording order) is a walk along the links, one vectorised step per
observation of the longest history. About 40 bytes an observation, where a tuple and a
NumPy view per observation in a dictionary of lists take over 300 (a third of a megabyte
per keyframe on a walking camera).

A history query walks only the observations recorded since the last *snapshot*: the rows
then recorded, sorted by track with each track's range (a compressed sparse row index),
are read as slices. The snapshot is taken again when :data:`SNAPSHOT_ROWS` rows have been
recorded since, so a walk is at most that many rows deep (a few dozen keyframes) whatever
the age of a track, and the sort (``O(N log N)``) is amortised over those rows.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["TrackObservations"]

#: Rows recorded after which the sorted snapshot of :class:`TrackObservations` is taken again.
SNAPSHOT_ROWS = 1 << 15


def _grown(a: np.ndarray, n: int, fill) -> np.ndarray:
    """``a`` with room for at least ``n`` rows (capacity doubled), new rows ``fill``."""
    if n <= len(a):
        return a
    out = np.full((max(n, 2 * len(a), 64),) + a.shape[1:], fill, a.dtype)
    out[: len(a)] = a
    return out


class TrackObservations:
    """Recorded observations of tracks by frames, with per-track history queries.

    Track ids are non-negative integers (the front end's); a track has at most one
    observation per frame.

    Parameters
    ----------
    tracks, frames : (N,) int, optional
        Observations to start with (a session's, :meth:`arrays`), each track's in
        recording order.
    uv : (N, 2), optional
        Their pixels.
    """

    def __init__(self, tracks: IntArray | None = None, frames: IntArray | None = None, uv: Array | None = None
                 ) -> None:
        tracks = np.zeros(0, np.int64) if tracks is None else np.asarray(tracks, np.int64).reshape(-1)
        frames = np.zeros(0, np.int64) if frames is None else np.asarray(frames, np.int64).reshape(-1)
        uv = np.zeros((0, 2)) if uv is None else np.asarray(uv, float).reshape(-1, 2)
        if not len(tracks) == len(frames) == len(uv):
            raise ValueError("tracks, frames and pixels must have one row per observation")
        if len(tracks) and tracks.min() < 0:
            raise ValueError("track ids must be non-negative")
        n = len(tracks)
        self.n = n  # rows used
        self._frame, self._track, self._uv = frames.copy(), tracks.copy(), uv.copy()
        self._alive = np.ones(n, bool)  # False: taken back (forget)
        self._last = np.full(int(tracks.max()) + 1 if n else 0, -1, np.int64)  # per track id: its last row
        self._snapshot()  # the rows by track, then as given
        order = self._snap_rows
        same = tracks[order][1:] == tracks[order][:-1]
        end = np.append(~same, True) if n else np.zeros(0, bool)  # each track's last row
        self._prev = np.full(n, -1, np.int64)  # the track's previous row, -1: none
        self._prev[order[1:][same]] = order[:-1][same]
        self._last[tracks[order][end]] = order[end]

    def __len__(self) -> int:
        """Observations kept (taken-back ones excluded)."""
        return int(self._alive[: self.n].sum())

    # -- recording ---------------------------------------------------------------------
    def add(self, frame: int, tracks: IntArray, uv: Array, only_new: bool = False) -> NDArray[np.bool_]:
        """Record that ``frame`` observed ``tracks`` ``(M,)`` at pixels ``uv`` ``(M, 2)``.

        With ``only_new``, a track whose last observation is already of ``frame`` is left
        as it is. Returns which of ``tracks`` were recorded ``(M,)``.
        """
        tracks = np.asarray(tracks, np.int64).reshape(-1)
        uv = np.asarray(uv, float).reshape(-1, 2)
        if len(tracks) and tracks.min() < 0:
            raise ValueError("track ids must be non-negative")
        self._last = _grown(self._last, int(tracks.max()) + 1 if len(tracks) else 0, -1)
        prev = self._last[tracks]
        new = np.ones(len(tracks), bool)
        if only_new:
            has = prev >= 0
            new[has] = ~((self._frame[prev[has]] == frame) & self._alive[prev[has]])
        tracks, uv, prev = tracks[new], uv[new], prev[new]
        m = len(tracks)
        a, b = self.n, self.n + m
        self._frame = _grown(self._frame, b, -1)
        self._track = _grown(self._track, b, -1)
        self._uv = _grown(self._uv, b, 0.0)
        self._prev = _grown(self._prev, b, -1)
        self._alive = _grown(self._alive, b, False)
        self._frame[a:b], self._track[a:b], self._uv[a:b] = frame, tracks, uv
        self._prev[a:b], self._alive[a:b] = prev, True
        self._last[tracks] = np.arange(a, b)
        self.n = b
        return new

    def forget(self, frame: int, tracks: IntArray) -> None:
        """Take back the observations of ``tracks`` by ``frame`` (kept as dead rows)."""
        _, rows = self._rows(tracks)
        self._alive[rows[self._frame[rows] == frame]] = False

    # -- queries ---------------------------------------------------------------------
    def rows_of(self, tracks: IntArray) -> tuple[IntArray, IntArray]:
        """The live observations of ``tracks`` ``(M,)``: for each, the index into
        ``tracks`` it belongs to and its row, grouped by that index and in recording order
        within a track (``(R,)``, ``(R,)``)."""
        owner, row = self._rows(tracks)
        order = np.lexsort((row, owner))
        return owner[order], row[order]

    def _rows(self, tracks: IntArray) -> tuple[IntArray, IntArray]:
        """:meth:`rows_of` in no particular order."""
        tracks = np.asarray(tracks, np.int64).reshape(-1)
        if self.n - self._snap_n >= SNAPSHOT_ROWS:
            self._snapshot()
        inside = (tracks >= 0) & (tracks < len(self._last))
        owner = np.flatnonzero(inside)
        # the rows recorded since the snapshot: a walk back along the links until the
        # snapshot's rows
        cur = self._last[tracks[inside]]
        owners, rows = [], []
        while len(cur):
            m = cur >= self._snap_n
            owner, cur = owner[m], cur[m]
            owners.append(owner)
            rows.append(cur)
            cur = self._prev[cur]
        # the snapshot's rows: each track's slice of the sorted rows
        owner_old = np.flatnonzero(inside)
        t_old = tracks[owner_old]
        inside_snap = t_old < len(self._snap_ptr) - 1
        owner_old, t_old = owner_old[inside_snap], t_old[inside_snap]
        lo, hi = self._snap_ptr[t_old], self._snap_ptr[t_old + 1]
        count = hi - lo
        if count.sum():
            owners.append(np.repeat(owner_old, count))
            first = np.repeat(lo - np.cumsum(count) + count, count)  # each slice's start, minus its offset
            rows.append(self._snap_rows[first + np.arange(int(count.sum()))])
        if not rows:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        owner, row = np.concatenate(owners), np.concatenate(rows)
        live = self._alive[row]
        return owner[live], row[live]

    def _snapshot(self) -> None:
        """Sort the rows recorded so far by track (then row) and index each track's range."""
        n = self.n
        t = self._track[:n]
        order = np.lexsort((np.arange(n), t)).astype(np.int64)
        self._snap_rows = order
        self._snap_ptr = np.searchsorted(t[order], np.arange(len(self._last) + 1)).astype(np.int64) \
            if n else np.zeros(1, np.int64)
        self._snap_n = n

    def frames(self, rows: IntArray) -> IntArray:
        """Frames of observation rows ``(R,)``."""
        return self._frame[rows]

    def pixels(self, rows: IntArray) -> Array:
        """Pixels ``(R, 2)`` of observation rows."""
        return self._uv[rows]

    def covisible(self, tracks: IntArray) -> dict[int, int]:
        """Frames that observed any of ``tracks``, with how many of them each observed."""
        _, rows = self._rows(tracks)
        if not len(rows):
            return {}
        f = self._frame[rows]
        lo = int(f.min())
        c = np.bincount(f - lo)
        nz = np.flatnonzero(c)
        return dict(zip((nz + lo).tolist(), c[nz].tolist()))

    # -- sessions --------------------------------------------------------------------
    def arrays(self) -> tuple[IntArray, IntArray, Array]:
        """Tracks, frames ``(N,)`` and pixels ``(N, 2)`` of the live observations, in
        recording order (what :meth:`from_arrays` takes back)."""
        live = np.flatnonzero(self._alive[: self.n])
        return self._track[live].copy(), self._frame[live].copy(), self._uv[live].copy()

    @classmethod
    def from_arrays(cls, tracks: IntArray, frames: IntArray, uv: Array) -> "TrackObservations":
        """The store holding these observations ``(N,)``, ``(N,)``, ``(N, 2)``, each track's
        in the order given (what :meth:`arrays` gives)."""
        return cls(tracks, frames, uv)
