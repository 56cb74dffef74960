"""Result types of the front end (pure NumPy dataclasses).

Expected failures are values: every result has ``ok`` and a human-readable ``reason``
(empty when ``ok``), and nothing in a result is NaN or inf.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from ..estimation.measurements import RelativePose

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["FrameFeatures", "FrameResult", "RelativePoseResult", "Reason"]


class Reason:
    """The reasons a result can carry (strings, so they print well)."""

    OK = ""
    NO_FEATURES = "no features"
    FIRST_FRAME = "first frame"
    TOO_FEW_MATCHES = "too few matches"
    TOO_FEW_COMMON = "too few common features"
    ESSENTIAL_FAILED = "essential matrix failed"
    TOO_FEW_INLIERS = "too few inliers"
    NO_PARALLAX = "no parallax"
    DEGENERATE = "degenerate covariance"
    SAME_FRAME = "same frame"


@dataclass(frozen=True)
class FrameFeatures:
    """The keypoints of one stored frame and their track identities.

    Attributes
    ----------
    frame_id : int
    uv : (N, 2) float64, undistorted pixels.
    uv_raw : (N, 2) float64, pixels as detected.
    track_ids : (N,) int64, current track identity of each keypoint (unique in a frame).
    in_map : (N,) bool, True when the keypoint's track is in ``Ωm`` (map), else ``Ωp``.
    colors : (N, 3) uint8, RGB.
    """

    frame_id: int
    uv: Array
    uv_raw: Array
    track_ids: IntArray
    in_map: NDArray[np.bool_]
    colors: NDArray[np.uint8]


@dataclass(frozen=True)
class FrameResult:
    """Outcome of :meth:`FrontEnd.add_frame`.

    Attributes
    ----------
    frame_id : int
    ok : bool
        True when the frame has features and was associated with a previous frame (or is
        the first frame).
    reason : str
        Why not ok (see :class:`Reason`), else "".
    n_features : int
        Keypoints detected.
    n_matches : int
        Keypoints that extended an existing track (epipolar inliers).
    n_new_tracks : int
        Tracks started in this frame.
    timings_ms : dict
        ``{"detect": ..., "match": ...}`` wall time in milliseconds.
    """

    frame_id: int
    ok: bool
    reason: str
    n_features: int
    n_matches: int
    n_new_tracks: int
    timings_ms: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class RelativePoseResult:
    """Outcome of a relative-pose computation between frames *i* and *j*.

    Attributes
    ----------
    ok : bool
    reason : str
        Why not ok (see :class:`Reason`), else "".
    measurement : RelativePose or None
        ``ZR``, ``ZT`` direction and the joint 5x5 covariance, when ok.
    n_common : int
        ``Ωp`` correspondences offered to the solver.
    n_inliers : int
        Correspondences consistent with the estimate (after the cheirality test).
    parallax_deg : float
        Median triangulation angle with the estimated rotation, degrees (when the pair
        failed the pure-rotation test: the median angle left by the best rotation fit).
    inlier_track_ids : (M,) int64
        Track ids of the inliers (empty when no ids were given).
    timings_ms : dict
        ``{"relative_pose": ..., "covariance": ...}`` in milliseconds.
    """

    ok: bool
    reason: str
    measurement: RelativePose | None
    n_common: int = 0
    n_inliers: int = 0
    parallax_deg: float = 0.0
    inlier_track_ids: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    timings_ms: dict[str, float] = field(default_factory=dict)
