"""The state layout: the one place that owns index arithmetic of the state vector.

The state (paper eq. 1) is ``X = (Xc1, Xc2, ..., Xf1, Xf2, ...)`` with poses
``Xc = [p (3), q (4)]`` and features ``Xf = [x, y, z]``. Entries are stored in the order
they were added (chronological), which keeps the information matrix of an exploration
close to banded. Poses are keyed by frame id, features by track id; a state is named by
a :class:`StateKey` ``(kind, id)``, which is a tuple, so ``("pose", 3)`` names it too.

The ``read_*`` functions read poses and features out of an estimate ``x`` through a
layout; both back ends use them.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from ..errors import EstimatorError
from ..geometry.rotations import quat_left_matrix, quat_normalize
from .options import Choice

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

POSE_DIM = 7
FEATURE_DIM = 3
_SORTED_MIN = 512
"""Sparse track ids: from this many ids a query sorts the features once (binary search);
fewer are looked up in the dict one by one."""


class StateKind(Choice):
    """Kind of a state: a camera pose ``[p (3), q (4)]`` or a map feature ``[x, y, z]``."""

    POSE = "pose"
    FEATURE = "feature"


class StateKey(NamedTuple):
    """Name of one state: ``(kind, id)``, the id a frame id (poses) or a track id (features).

    A plain tuple ``("pose", 3)`` compares (and hashes) equal to ``StateKey(StateKind.POSE, 3)``.
    """

    kind: StateKind
    id: int

    @staticmethod
    def of(key: "tuple[str, int]") -> "StateKey":
        """Normalise ``(kind, id)`` (strings accepted); :class:`EstimatorError` on an unknown kind."""
        kind, ident = key
        try:
            return StateKey(StateKind(kind), int(ident))
        except ValueError:
            raise EstimatorError(f"unknown state kind {kind!r}; use 'feature' or 'pose'") from None


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
        self._order: list[StateKey] = []
        self.dim = 0

    # -- adding -------------------------------------------------------------------
    def add_pose(self, frame_id: int) -> int:
        """Append a pose; return its offset."""
        frame_id = int(frame_id)
        if frame_id in self._pose:
            raise EstimatorError(f"pose {frame_id} is already in the state")
        off = self.dim
        self._pose[frame_id] = off
        self._order.append(StateKey(StateKind.POSE, frame_id))
        self.dim += POSE_DIM
        return off

    def add_feature(self, track_id: int) -> int:
        """Append a feature; return its offset."""
        track_id = int(track_id)
        if track_id in self._feature:
            raise EstimatorError(f"feature {track_id} is already in the state")
        off = self.dim
        self._feature[track_id] = off
        self._order.append(StateKey(StateKind.FEATURE, track_id))
        self.dim += FEATURE_DIM
        starts = self.__dict__.get("_starts")
        if starts is not None:
            if off >= len(starts):
                starts = self._starts = np.concatenate([starts, np.full(max(len(starts), off + 1), -1, np.int64)])
            starts[off] = track_id
        lut = self.__dict__.get("_lut")
        if lut is not None:
            if 0 <= track_id < len(lut):
                lut[track_id] = off
            else:
                self._lut = None  # rebuilt (or given up) at the next vectorised query
        self._sorted = None
        return off

    # -- queries --------------------------------------------------------------------
    def has_pose(self, frame_id: int) -> bool:
        return int(frame_id) in self._pose

    def features_starting_at(self, columns) -> NDArray[np.int64]:
        """Track ids ``(N,)`` of the features whose blocks start at state entries
        ``columns (N,)``, ``-1`` where none does (an array kept up to date as features are
        added: ``O(N)`` per query)."""
        starts = self.__dict__.get("_starts")
        if starts is None:
            starts = np.full(max(2 * self.dim, 1024), -1, np.int64)
            if self._feature:
                starts[np.fromiter(self._feature.values(), np.int64, count=len(self._feature))] = \
                    np.fromiter(self._feature.keys(), np.int64, count=len(self._feature))
            self._starts = starts
        cols = np.asarray(columns, np.int64).reshape(-1)
        inside = (cols >= 0) & (cols < len(starts))
        out = np.full(len(cols), -1, np.int64)
        out[inside] = starts[cols[inside]]
        return out

    def has_feature(self, track_id: int) -> bool:
        return int(track_id) in self._feature

    def has_features(self, track_ids) -> NDArray[np.bool_]:
        """Mask of which track ids are features in the state."""
        ids = np.asarray(track_ids).reshape(-1)
        off = self._lookup(ids)
        if off is None:
            f = self._feature
            return np.fromiter((int(t) in f for t in ids.tolist()), bool, count=len(ids))
        return off >= 0

    def _lookup(self, ids: NDArray) -> IntArray | None:
        """Feature offsets ``(N,)`` of track ids ``ids (N,)``, ``-1`` where an id is not a
        feature; None when neither :meth:`_feature_lut` nor :meth:`_feature_sorted` serves
        them (a few ids, or ids that are not integers: use the dict)."""
        lut = self._feature_lut(ids)
        if lut is None:
            if len(ids) < _SORTED_MIN or not np.issubdtype(ids.dtype, np.integer):
                return None
            keys, offs = self._feature_sorted()
            if not len(keys):
                return np.full(len(ids), -1, np.int64)
            pos = np.minimum(np.searchsorted(keys, ids), len(keys) - 1)
            return np.where(keys[pos] == ids, offs[pos], -1)
        ids = ids.astype(np.int64, copy=False)
        inside = (ids >= 0) & (ids < len(lut))
        off = np.full(len(ids), -1, np.int64)
        off[inside] = lut[ids[inside]]
        return off

    def _feature_sorted(self) -> tuple[IntArray, IntArray]:
        """Track ids of the features, sorted, and their offsets: the lookup for ids too
        sparse for :meth:`_feature_lut` (binary search; rebuilt after features are added,
        ``O(F log F)``, so only for queries of many ids)."""
        cached = self.__dict__.get("_sorted")
        if cached is None:
            keys = np.fromiter(self._feature.keys(), np.int64, count=len(self._feature))
            offs = np.fromiter(self._feature.values(), np.int64, count=len(self._feature))
            order = np.argsort(keys, kind="stable")
            cached = self._sorted = (keys[order], offs[order])
        return cached

    def _feature_lut(self, ids: NDArray) -> IntArray | None:
        """Feature offset by track id (``-1``: none), for vectorised queries of the integer
        ids ``ids``; None (use the dict) when the ids are not integers or the largest track
        id is far beyond the number of features (no array that sparse)."""
        if not np.issubdtype(ids.dtype, np.integer) and len(ids):
            return None
        lut = self.__dict__.get("_lut")
        if lut is None:
            top = max(self._feature, default=-1)
            if min(self._feature, default=0) < 0 or top >= 8 * len(self._feature) + (1 << 16):
                return None
            lut = np.full(max(2 * (top + 1), 1024), -1, np.int64)
            if self._feature:
                keys = np.fromiter(self._feature.keys(), np.int64, count=len(self._feature))
                lut[keys] = np.fromiter(self._feature.values(), np.int64, count=len(self._feature))
            self._lut = lut
        return lut

    @property
    def order(self) -> tuple[StateKey, ...]:
        """``(kind, id)`` of every state, in state (chronological) order (a copy)."""
        return tuple(self._order)

    @property
    def n_states(self) -> int:
        """Number of states (poses and features) in the layout."""
        return len(self._order)

    def keys_since(self, start: int) -> list[StateKey]:
        """``(kind, id)`` of the states added after the first ``start`` ones, in order
        (``O(new states)``; to follow a growing layout)."""
        return self._order[start:]

    @property
    def pose_ids(self) -> list[int]:
        """Frame ids of the poses, in state order (``O(poses)``: the offsets dict is filled
        in state order and never shrinks)."""
        return list(self._pose)

    @property
    def feature_ids(self) -> list[int]:
        """Track ids of the features, in state order."""
        return list(self._feature)

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
        ids = np.asarray(track_ids).reshape(-1)
        off = self._lookup(ids)
        if off is None:
            return np.fromiter((self.feature_offset(t) for t in ids.tolist()), np.int64, count=len(ids))
        if np.any(off < 0):
            self.feature_offset(int(ids[np.flatnonzero(off < 0)[0]]))  # raises, naming the id
        return off

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

    def position(self, key: "tuple[str, int]", x: Array) -> Array:
        """Position ``(3,)`` of state ``key`` (a feature, or a pose's centre) in ``x`` (a view)."""
        kind, ident = StateKey.of(key)
        if kind == StateKind.FEATURE:
            return x[self.feature_slice(ident)]
        return x[self.pose_slice(ident)][:3]

    def blocks(self) -> list[tuple[StateKind, int, int, int]]:
        """``(kind, id, offset, size)`` of every state in order."""
        out = []
        for kind, k in self._order:
            if kind == StateKind.POSE:
                out.append((kind, k, self._pose[k], POSE_DIM))
            else:
                out.append((kind, k, self._feature[k], FEATURE_DIM))
        return out


def read_pose(layout: StateLayout, x: Array, frame_id: int) -> tuple[Array, Array]:
    """``(p (3,), q_wc (4,) unit)`` of a pose in the estimate ``x`` (copies)."""
    v = x[layout.pose_slice(frame_id)]
    return v[:3].copy(), quat_normalize(v[3:])


def read_poses(layout: StateLayout, x: Array) -> tuple[list[int], Array, Array]:
    """Frame ids, positions ``(P, 3)`` and unit quaternions ``(P, 4)`` of every pose in ``x``."""
    ids = layout.pose_ids
    cols = layout.pose_columns(ids) if ids else np.zeros((0, 7), np.int64)
    v = x[cols]
    return ids, v[:, :3].copy(), quat_normalize(v[:, 3:]) if len(ids) else np.zeros((0, 4))


def read_features(layout: StateLayout, x: Array) -> tuple[list[int], Array]:
    """Track ids and positions ``(F, 3)`` of every map feature in ``x``."""
    ids = layout.feature_ids
    cols = layout.feature_columns(ids) if ids else np.zeros((0, 3), np.int64)
    return ids, x[cols].copy()


def pose_tangent_jacobian(q: Array) -> Array:
    """(6, 7) map from a change of a pose block ``[p, q]`` to ``[dp, dtheta]``; ``dtheta``
    (rad) is the right-multiplied rotation error in the camera frame (``R_true = R_est @
    Exp(dtheta)``), ``q (4,)`` the (unnormalised) estimate."""
    n = np.linalg.norm(q)
    qn = q / n
    # dtheta = 2 vec(q_est^* ⊗ q) for a small change of the normalised quaternion
    G = 2.0 * quat_left_matrix(qn * np.array([1, -1, -1, -1]))[1:] @ ((np.eye(4) - np.outer(qn, qn)) / n)
    T = np.zeros((6, 7))
    T[:3, :3] = np.eye(3)
    T[3:, 3:] = G
    return T


def pose_tangent_covariance(C: Array, q: Array) -> Array:
    """Map the 7x7 covariance ``C`` of a pose block ``[p, q]`` to the 6x6 covariance of
    ``[p, dtheta]`` (:func:`pose_tangent_jacobian`)."""
    T = pose_tangent_jacobian(q)
    return T @ C @ T.T
