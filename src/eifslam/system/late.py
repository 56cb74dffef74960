"""Frames placed late: frames without a pose localised after the frames that followed them.

Two kinds: frames that came before the first baseline (``INITIALISING``: the map did not
exist yet) and frames lost on the way. :meth:`~eifslam.system.slam.Slam.track` retries the
first kind once the map exists and again at keyframes while the young map grows (as long
as they share map tracks with the keyframe);
:meth:`~eifslam.system.slam.Slam.retry_lost` retries every frame still without a pose
against the final map. Several frames placed together share one recovery: recovering an
old state alone rebuilds the incremental recovery window, so one recovery per frame
would rebuild it once per frame (16 rebuilds, 9.5 s, at the end of the 7scenes ORB run).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from ..errors import EstimatorError

if TYPE_CHECKING:  # pragma: no cover
    from .slam import Slam, TrackResult

__all__ = ["place_late", "unplaced_initial", "retry_passes"]


def place_late(slam: "Slam", frames: Sequence[int], reason: str, relative: bool = True, wide: Any = None,
               relative_first: bool = False) -> int:
    """Localise earlier frames that have no pose, in the given order, then recover once.

    Parameters
    ----------
    slam : Slam
    frames : sequence of int
        Frame ids without a pose.
    reason : str
        The reason of each placed frame's updated :class:`TrackResult`.
    relative, relative_first
        As :meth:`~eifslam.system.tracking.Tracker.place_late`.
    wide : WideMatch, optional
        Wide-baseline matches of the (single) frame: placed with
        :meth:`~eifslam.system.tracking.Tracker.place_wide` instead (which recovers itself).

    Returns
    -------
    int
        How many frames were placed; their :class:`TrackResult` are updated in place.
    """
    from .results import TrackingState, TrackResult

    placed: list[tuple[int, int | None, dict[str, float]]] = []
    for j in frames:
        timings: dict[str, float] = {}
        try:
            ok, ref = slam.tracker.place_late(j, relative, timings, relative_first, recover=False) \
                if wide is None else slam.tracker.place_wide(j, wide, timings)
        except EstimatorError:
            continue
        if ok:
            placed.append((int(j), ref, timings))
    if not placed:
        return 0
    filt = slam.filter
    t0 = time.perf_counter()
    if wide is None:  # place_wide recovered already
        slam.mapper.recover()
    recover_ms = 1e3 * (time.perf_counter() - t0) / len(placed)
    for j, ref, timings in placed:
        p, q = filt.pose(j)
        old: TrackResult = slam.results[j]
        if wide is None:
            timings["recover"] = recover_ms  # the shared recovery, per frame placed
        slam.results[j] = TrackResult(j, old.timestamp, TrackingState.TRACKING, p, q, filt.pose_covariance(j),
                                      reason=reason, reference=ref, timings_ms={**old.timings_ms, **timings},
                                      map_features=filt.layout.n_features, state_dim=filt.dim)
    return len(placed)


def unplaced_initial(slam: "Slam", k: int) -> list[int]:
    """Frames that waited for the first baseline and that the young map could not place
    yet, nearest to frame *k* first, while they still share a map track with frame *k*
    (once the camera has moved on they wait for
    :meth:`~eifslam.system.slam.Slam.retry_lost`).

    They all come before the frame that initialised the map, so the search is bounded by
    that frame's index, not by the length of the run.

    Parameters
    ----------
    slam : Slam
    k : int
        The current frame (a keyframe with a pose).
    """
    from .results import TrackingState

    results = slam.results
    first = next((r.frame_id for r in results if r.position is not None
                  and r.state is TrackingState.TRACKING and r.reference is not None), None)
    if first is None:
        return []
    waiting = [r.frame_id for r in results[:first] if r.position is None and r.state is TrackingState.INITIALISING]
    if not waiting:
        return []
    seen = slam.frontend.map_observations(k)[0]
    return sorted((j for j in waiting if np.isin(slam.frontend.map_observations(j)[0], seen).any()), reverse=True)


def retry_passes(slam: "Slam", max_passes: int, first_map_only: bool) -> int:
    """Passes of :func:`place_late` over the frames without a pose until one adds none;
    how many it added. ``first_map_only``: the first pass against the map alone, then
    relative poses once the map is exhausted; otherwise (after a frame placed by
    wide-baseline matching) relative poses first, as in the run."""
    added = 0
    reason = "localised after the run, against the final map" if first_map_only \
        else "localised after the run, after a wide-baseline placement"
    for n in range(max_passes):
        new = place_late(slam, slam.untracked(), reason, relative=n > 0 or not first_map_only,
                         relative_first=not first_map_only)
        added += new
        if new == 0 and (n > 0 or not first_map_only):
            break
    return added
