"""Placing the frames a run left without a pose by wide-baseline matching (the offline
part of :meth:`~eifslam.system.slam.Slam.retry_lost` with ``experimental.wide_baseline``).

The front end's :class:`~eifslam.frontend.wide.WideBaselineMatcher` matches two images
with affine-simulated features (ASIFT); this module chooses which frames to match and how
to place them (docs/frontend.md, "Wide-baseline views").
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["retry_wide"]


def retry_wide(slam, images: Callable[[int], np.ndarray], max_rounds: int = 3) -> int:
    """Place frames without a pose from wide-baseline matches; how many it placed.

    The frames without a pose, in frame order, are matched with affine-simulated
    features to their ``ExperimentalConfig.wide_baseline_references`` nearest known frames (joining
    the tracks both ends of a match land on). The first placed is localised on the known
    map features it now sees, starting from the relative pose of its best matches
    (:meth:`~eifslam.system.tracking.Tracker.place_wide`). Each later one is matched to
    its nearest known frames and to that first reference across the gap (which brings
    back tracks the run lost, and more of the old map's features in view) and placed as
    in the run: a relative pose to
    the nearest known frames, else the map, else from its own wide-baseline matches.
    A frame that fails is tried again in the next round (at most ``max_rounds``) when the
    round placed others (its nearest known frames may have changed); the affine features
    of each frame are computed once.

    Parameters
    ----------
    slam : Slam
        After its run (:meth:`~eifslam.system.slam.Slam.untracked`,
        :meth:`~eifslam.system.slam.Slam.retry_frame`).
    images : callable
        Frame id -> the image :meth:`~eifslam.system.slam.Slam.track` was given.
    max_rounds : int
        Rounds over the frames without a pose.
    """
    from ..frontend.wide import WideBaselineMatcher

    cfg = slam.config
    matcher = WideBaselineMatcher(slam.camera, slam.frontend.config, cfg.experimental.wide_baseline_max_tilt)
    added, anchor = 0, None
    for _ in range(max_rounds):
        placed = 0
        for j in slam.untracked():
            refs = slam.tracker.nearest_known(j)[: cfg.experimental.wide_baseline_references]
            refs += [anchor] if anchor is not None and anchor not in refs else []
            wides = [matcher.relate(slam.frontend, ref, j, images) for ref in refs]
            best = max(wides, key=lambda w: len(w.uv))
            if anchor is not None and slam.retry_frame(
                    j, "localised after the run, after a wide-baseline placement", relative_first=True):
                placed += 1
            elif slam.retry_frame(j, f"localised after the run by wide-baseline matching to frame "
                                     f"{best.reference} ({len(best.uv)} affine matches)", wide=best):
                placed += 1
                anchor = best.reference if anchor is None else anchor
        added += placed
        if placed == 0 or not slam.untracked():
            break
    return added
