"""What tracking reports per image: the tracking state and :class:`TrackResult` (ORB-SLAM's
``eTrackingState`` and the pose it returns), apart from :mod:`~.slam` so that the modules
``Slam`` uses read them without importing it."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from ..geometry.rotations import quat_to_rotmat

Array = NDArray[np.float64]

__all__ = ["TrackingState", "TrackResult", "pose_matrix"]


class TrackingState(str, Enum):
    """Per-frame tracking state (ORB-SLAM's ``eTrackingState``)."""

    INITIALISING = "initialising"
    TRACKING = "tracking"
    LOST = "lost"


@dataclass
class TrackResult:
    """What :meth:`Slam.track` returns for one image.

    Attributes
    ----------
    frame_id : int
    timestamp : float, seconds.
    state : TrackingState
    position : (3,) camera centre in the world frame, or None when lost.
    quat_wxyz : (4,) orientation ``q_wc``, or None when lost.
    covariance : (6, 6) covariance of ``[p, dtheta]`` (see
        :meth:`InformationFilter.pose_covariance`), or None.
    reason : why the frame is lost / initialising ("" when tracking).
    reference : frame id of the reference pose (for a frame between keyframes, the last
        keyframe), or None.
    timings_ms : per-stage milliseconds.
    keyframe : whether the frame is a state of the filter (False: localised on the map
        between keyframes, :mod:`eifslam.system.keyframes`).
    """

    frame_id: int
    timestamp: float
    state: TrackingState
    position: Array | None = None
    quat_wxyz: Array | None = None
    covariance: Array | None = None
    reason: str = ""
    reference: int | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    map_features: int = 0
    state_dim: int = 0
    keyframe: bool = True

    @property
    def T_wc(self) -> Array | None:
        """(4, 4) camera-to-world transform ``[[R_wc, p], [0, 1]]`` of this result (world
        units), or None when the frame has no pose."""
        return None if self.position is None else pose_matrix(self.position, self.quat_wxyz)


def pose_matrix(p: Array, q_wxyz: Array) -> Array:
    """(4, 4) homogeneous camera-to-world transform from a centre ``p (3,)`` and ``q_wc
    (4,)`` ``[w, x, y, z]``: maps camera-frame points (x right, y down, z forward) to the
    world frame."""
    T = np.eye(4)
    T[:3, :3] = quat_to_rotmat(np.asarray(q_wxyz, float))
    T[:3, 3] = np.asarray(p, float)
    return T
