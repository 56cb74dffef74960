"""The state layout: the one place that owns index arithmetic of the state vector.

The state (paper eq. 1) is ``X = (Xc1, Xc2, ..., Xf1, Xf2, ...)`` with poses
``Xc = [p (3), q (4)]`` and features ``Xf = [x, y, z]``. Entries are stored in the order
they were added (chronological), which keeps the information matrix of an exploration
close to banded. Poses are keyed by frame id, features by track id.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ..errors import EstimatorError

IntArray = NDArray[np.int64]

POSE_DIM = 7
FEATURE_DIM = 3


class StateLayout:
    """Maps ``("pose", frame_id)`` and ``("feature", track_id)`` to slices of the state.

    Examples
    --------
    >>> lay = StateLayout()
    >>> lay.add_pose(0), lay.add_feature(5), lay.add_pose(1)
    (0, 7, 10)
    >>> lay.dim
    17
    >>> lay.pose_columns([1]).tolist()
    [[10, 11, 12, 13, 14, 15, 16]]
    """

    def __init__(self) -> None:
        self._pose: dict[int, int] = {}
        self._feature: dict[int, int] = {}
        self._order: list[tuple[str, int]] = []
        self.dim = 0

    # -- adding -------------------------------------------------------------------
    def add_pose(self, frame_id: int) -> int:
        """Append a pose; return its offset."""
        frame_id = int(frame_id)
        if frame_id in self._pose:
            raise EstimatorError(f"pose {frame_id} is already in the state")
        off = self.dim
        self._pose[frame_id] = off
        self._order.append(("pose", frame_id))
        self.dim += POSE_DIM
        return off

    def add_feature(self, track_id: int) -> int:
        """Append a feature; return its offset."""
        track_id = int(track_id)
        if track_id in self._feature:
            raise EstimatorError(f"feature {track_id} is already in the state")
        off = self.dim
        self._feature[track_id] = off
        self._order.append(("feature", track_id))
        self.dim += FEATURE_DIM
        return off

    # -- queries --------------------------------------------------------------------
    def has_pose(self, frame_id: int) -> bool:
        return int(frame_id) in self._pose

    def has_feature(self, track_id: int) -> bool:
        return int(track_id) in self._feature

    def has_features(self, track_ids) -> NDArray[np.bool_]:
        """Mask of which track ids are features in the state."""
        f = self._feature
        return np.fromiter((int(t) in f for t in track_ids), bool, count=len(track_ids))

    @property
    def order(self) -> tuple[tuple[str, int], ...]:
        """``(kind, id)`` of every state, in state (chronological) order (a copy)."""
        return tuple(self._order)

    @property
    def n_states(self) -> int:
        """Number of states (poses and features) in the layout."""
        return len(self._order)

    def keys_since(self, start: int) -> list[tuple[str, int]]:
        """``(kind, id)`` of the states added after the first ``start`` ones, in order
        (``O(new states)``; to follow a growing layout)."""
        return self._order[start:]

    @property
    def pose_ids(self) -> list[int]:
        """Frame ids of the poses, in state order."""
        return [k for kind, k in self._order if kind == "pose"]

    @property
    def feature_ids(self) -> list[int]:
        """Track ids of the features, in state order."""
        return [k for kind, k in self._order if kind == "feature"]

    @property
    def n_poses(self) -> int:
        return len(self._pose)

    @property
    def n_features(self) -> int:
        return len(self._feature)

    def pose_slice(self, frame_id: int) -> slice:
        off = self.pose_offset(frame_id)
        return slice(off, off + POSE_DIM)

    def feature_slice(self, track_id: int) -> slice:
        off = self.feature_offset(track_id)
        return slice(off, off + FEATURE_DIM)

    def pose_offset(self, frame_id: int) -> int:
        try:
            return self._pose[int(frame_id)]
        except KeyError:
            raise EstimatorError(f"pose {frame_id} is not in the state") from None

    def feature_offset(self, track_id: int) -> int:
        try:
            return self._feature[int(track_id)]
        except KeyError:
            raise EstimatorError(f"feature {track_id} is not in the state") from None

    def pose_offsets(self, frame_ids) -> IntArray:
        """Offsets ``(N,)`` of poses; raises :class:`EstimatorError` on an unknown id."""
        return np.fromiter((self.pose_offset(f) for f in frame_ids), np.int64, count=len(frame_ids))

    def feature_offsets(self, track_ids) -> IntArray:
        """Offsets ``(N,)`` of features; raises :class:`EstimatorError` on an unknown id."""
        return np.fromiter((self.feature_offset(t) for t in track_ids), np.int64, count=len(track_ids))

    def pose_columns(self, frame_ids) -> IntArray:
        """State indices ``(N, 7)`` of poses."""
        return self.pose_offsets(frame_ids)[:, None] + np.arange(POSE_DIM)

    def feature_columns(self, track_ids) -> IntArray:
        """State indices ``(N, 3)`` of features."""
        return self.feature_offsets(track_ids)[:, None] + np.arange(FEATURE_DIM)

    def position_mask(self) -> NDArray[np.bool_]:
        """Mask ``(dim,)`` of entries that are positions (scale with the map)."""
        m = np.ones(self.dim, bool)
        for off in self._pose.values():
            m[off + 3 : off + POSE_DIM] = False
        return m

    def blocks(self) -> list[tuple[str, int, int, int]]:
        """``(kind, id, offset, size)`` of every state in order."""
        out = []
        for kind, k in self._order:
            if kind == "pose":
                out.append((kind, k, self._pose[k], POSE_DIM))
            else:
                out.append((kind, k, self._feature[k], FEATURE_DIM))
        return out
