"""After the run: what :meth:`Slam.finish <eifslam.system.slam.Slam.finish>` does for each mode.

``finish`` gives every frame without a pose one more chance against the final map, then
relinearises and smooths (mode ``smooth``, paper III-E) or bundle-adjusts every track
(mode ``ba``, :func:`bundle_adjust_slam`). This module holds the bundle-adjustment glue
and the :class:`FinishReport`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..baselines.bundle_adjustment import BAConfig, BAResult, bundle_adjust, observations_from_frontend
from ..estimation.smoothing import SmoothingReport

__all__ = ["FinishReport", "bundle_adjust_slam"]


@dataclass
class FinishReport:
    """What :meth:`Slam.finish` did.

    Attributes
    ----------
    added : int
        Frames localised after the run (:meth:`Slam.retry_lost`).
    retry_error : str or None
        Why retrying lost frames failed (the estimate is kept).
    smoothing : SmoothingReport or None
        Mode ``smooth``: the smoothing passes.
    ba : BAResult or None
        Mode ``ba``: the bundle adjustment.
    failures : list of str
        Steps that failed (``"smoothing failed: ..."``, ``"bundle adjustment failed:
        ..."``); the filter's estimate is kept then.
    """

    added: int = 0
    retry_error: str | None = None
    smoothing: SmoothingReport | None = None
    ba: BAResult | None = None
    failures: list[str] = field(default_factory=list)


def bundle_adjust_slam(slam, config: BAConfig | None = None) -> BAResult:
    """Bundle-adjust a :class:`~eifslam.system.slam.Slam` after its run and write the result back.

    Poses come from the filter's estimate, tracks (``Ωp`` and ``Ωm``) from its front end.
    The adjusted poses replace the filter's; map features that BA triangulated take the
    BA positions (others keep the filter's). The gauge pair is that of the filter's scale
    prior when there is one (else the first two poses).

    Parameters
    ----------
    slam : Slam
    config : BAConfig, optional

    Returns
    -------
    BAResult
    """
    filt = slam.filter
    filt.complete_estimate()  # every state at the filter's solution before BA starts from it
    ids, P, Q = filt.poses()
    order = np.argsort(ids)
    fids = np.asarray(ids, np.int64)[order]
    P, Q = P[order], Q[order]
    gauge = (0, 1)
    if filt.priors.scale is not None:
        fa, fb, _ = filt.priors.scale
        where = {int(f): k for k, f in enumerate(fids)}
        if fa in where and fb in where:
            gauge = (where[fa], where[fb])
    obs = observations_from_frontend(slam.frontend, fids, slam.config.zm_sigma_px)
    res = bundle_adjust(slam.camera, fids, P, Q, obs, config, gauge)
    lay = filt.layout
    x = filt.x.copy()
    for f, p, q in zip(res.frame_ids, res.positions, res.quats):
        x[lay.pose_slice(int(f))] = np.concatenate([p, q])
    in_map = lay.has_features(res.track_ids)
    if in_map.any():
        x[lay.feature_columns(res.track_ids[in_map])] = res.points[in_map]
    filt.set_estimate(x)
    return res
