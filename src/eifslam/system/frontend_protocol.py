"""What the system asks of a front end: :class:`FrontEndProtocol` and :class:`LoopFrontEnd`.

Two classes satisfy them: the OpenCV front end, :class:`~eifslam.frontend.FrontEnd`
(both protocols), and the synthetic one, :class:`~eifslam.sim.frontend.SyntheticFrontEnd`
(the per-frame protocol only: it draws measurements from a known scene and has no
descriptors). :class:`~eifslam.system.slam.Slam` takes either as ``frontend``; its
tracker, mapper and keyframes use the members of :class:`FrontEndProtocol`, and its loop
closer runs when the front end also has those of :class:`LoopFrontEnd`.

The wide-baseline matching of late frames (``system.wide_baseline``,
:mod:`eifslam.system.wide`) and sessions (:mod:`eifslam.system.session`) need the
OpenCV front end itself. ``tests/test_frontend_protocol.py`` runs ``Slam`` at the default
settings on each front end. This module imports neither OpenCV nor the front end.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from ..frontend.results import FrameFeatures, FrameResult, RelativePoseResult

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@runtime_checkable
class FrontEndProtocol(Protocol):
    """Per-frame front end: features and tracks of each image, relative poses between frames.

    Frames are keyed by the frame id given to :meth:`add_frame`; tracks by track id (a map
    feature's id in the back end is its track id). Pixels are undistorted.
    """

    @property
    def frame_ids(self) -> list[int]:
        """Ids of the stored frames, in the order they were added."""
        ...

    def add_frame(self, image: Any, frame_id: int) -> "FrameResult":
        """Detect (or draw) the features of a new frame and extend the tracks into it."""
        ...

    def frame(self, frame_id: int) -> "FrameFeatures":
        """Keypoints ``uv (N, 2)``, track ids ``(N,)`` and the map/pose split of a stored frame."""
        ...

    def map_observations(self, frame_id: int, min_track_length: int = 1) -> tuple[IntArray, Array]:
        """Track ids ``(M,)`` and pixels ``(M, 2)`` of the map (``Ωm``) keypoints of a frame."""
        ...

    def relative_pose(self, i: int, j: int) -> "RelativePoseResult":
        """``ZR``/``ZT`` from frame ``i`` to frame ``j`` with their covariance, or why not."""
        ...

    def release(self, frame_id: int) -> None:
        """A frame placed between keyframes: it need not be matched once it leaves the
        match window (what it keeps for that may go)."""
        ...

    def relocalise(self, frame_id: int, candidate_frame_ids) -> list[tuple[int, int]]:
        """Match a frame against older ones and merge the matched tracks; returns
        ``(candidate, matches)`` pairs."""
        ...

    def reobserve(self, frame_id: int, track_ids: IntArray, uv_predicted: Array, radius_px: float,
                  ratio: float | None = None) -> int:
        """Guided search for known map tracks around their predicted pixels; returns how
        many were found again."""
        ...


@runtime_checkable
class LoopFrontEnd(FrontEndProtocol, Protocol):
    """A front end with descriptors: what the loop closer (:mod:`eifslam.system.loops`) adds."""

    @property
    def matcher(self) -> Any:
        """The descriptor matcher (:class:`~eifslam.frontend.matching.DescriptorMatcher`)."""
        ...

    def descriptors(self, frame_id: int) -> NDArray | None:
        """Descriptors ``(N, D)`` of a stored frame's keypoints (rows as in :meth:`frame`),
        or None when they were dropped."""
        ...

    def join_tracks(self, frame_id: int, keypoints: IntArray, track_ids: IntArray) -> None:
        """Merge the tracks of keypoints of a frame into known tracks (a verified loop)."""
        ...


__all__ = ["FrontEndProtocol", "LoopFrontEnd"]
