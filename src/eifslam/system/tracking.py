"""Tracking: which known pose a new frame is related to (paper III-C, III-F; ORB-SLAM's Tracking).

The :class:`Tracker` finds a known pose related to a new frame by ``ZR``/``ZT`` (recent
poses, then older ones after descriptor matching when tracking is lost), places earlier
frames that have no pose, and keeps what tracking carries from frame to frame (the last
step length, the relative poses not fused). Placing a frame in the state is Algorithm 1,
:func:`~.algorithm1.algorithm1`.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
from numpy.typing import NDArray

from ..estimation.initialisation import pose_from_relative
from ..estimation.measurements import pack_relative, unpack_relative
from ..estimation.statedict import sub, take_float
from ..frontend.config import FrontEndConfig
from ..frontend.results import RelativePoseResult
from ..geometry.camera import PinholeCamera
from .algorithm1 import OnMap, algorithm1
from .config import SlamConfig
from .mapping import Mapper

Array = NDArray[np.float64]

__all__ = ["Tracker"]


class Tracker:
    """Places frames in the state for a :class:`~eifslam.system.slam.Slam`.

    Parameters
    ----------
    camera : PinholeCamera
    config : SlamConfig
    frontend : object
        The front end (``relative_pose``, ``relocalise``, ``map_observations``).
    backend : object
        The estimator (:class:`~eifslam.estimation.filter.InformationFilter`).
    mapper : Mapper
        Takes a frame over once its pose is in the state.

    Attributes
    ----------
    rejected_relative : list of RelativePose
        Relative poses the map contradicted or the gate refused (not fused).
    last_step : float
        Distance between the last two consecutive frames placed by ``ZR``/``ZT``: the
        scale guess of the next one (:func:`~.algorithm1.pose_from_reference`).
    """

    def __init__(self, camera: PinholeCamera, config: SlamConfig, frontend, backend, mapper: Mapper) -> None:
        self.camera = camera
        self.config = config
        self.frontend = frontend
        self.filter = backend
        self.mapper = mapper
        self.rejected_relative: list = []
        self.last_step = config.tracking.scale_distance

    # -- sessions -----------------------------------------------------------------
    def state_dict(self) -> dict:
        """What a session keeps: the refused relative poses and the last step length."""
        return {"rejected_relative": pack_relative(self.rejected_relative), "last_step": float(self.last_step)}

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict`, checked (:class:`~eifslam.errors.SessionError`)."""
        self.rejected_relative = unpack_relative(sub(d, "rejected_relative"))
        self.last_step = take_float(d, "last_step")

    def remember_step(self, step: float) -> None:
        """Keep the step length of the frame just placed (if it took one, ``step > 0``)."""
        self.last_step = step if step > 0 else self.last_step

    # -- references ---------------------------------------------------------------
    def nearest_known(self, k: int) -> list[int]:
        """Known pose ids, nearest to frame *k* first (for a new frame: most recent first)."""
        ids = np.asarray(self.filter.layout.pose_ids, np.int64)
        return ids[np.lexsort((-ids, np.abs(ids - int(k))))].tolist()

    def find_reference(self, k: int, timings: dict[str, float], relocalise: bool
                       ) -> tuple[RelativePoseResult | None, RelativePoseResult | None]:
        """A known pose related to frame *k* by ``ZR``/``ZT`` (III-C, III-F).

        Without ``relocalise``: the most recent known poses, then a few further back (a
        larger baseline when the camera moves slowly). With ``relocalise``: older poses,
        after matching the frame against them (tracking lost).

        Returns
        -------
        found : RelativePoseResult or None
            The usable relative pose.
        last : RelativePoseResult or None
            The last one tried (its ``reason`` says why tracking failed).
        """
        cfg = self.config
        known = self.nearest_known(k)
        n = cfg.tracking.reference_candidates
        if relocalise:
            older = known[n: n + cfg.tracking.relocalise_candidates]
            if not older:
                return None, None
            matches = self.frontend.relocalise(k, older)
            group = [c for c, m in sorted(matches, key=lambda cm: -cm[1]) if m > 0][: cfg.tracking.relocalise_top]
        else:
            group = known[:n] + [known[i] for i in (2 * n, 4 * n) if i < len(known)]
        last = None
        for c in group:
            r = self.frontend.relative_pose(c, k)
            timings["relative_pose"] = timings.get("relative_pose", 0.0) + r.timings_ms.get("relative_pose", 0.0)
            timings["covariance"] = timings.get("covariance", 0.0) + r.timings_ms.get("covariance", 0.0)
            last = r
            need = cfg.experimental.init_map_features
            need = cfg.tracking.min_map_features if need is None else need
            if r.ok and self.filter.layout.n_poses == 1 and (r.parallax_deg < FrontEndConfig.min_parallax_deg or (
                    need and self.first_map_size(r) < need)):
                continue  # too narrow a baseline to initialise the map on
            if r.ok:
                return r, r
        return None, last

    def first_map_size(self, r: RelativePoseResult) -> int:
        """How many map features the relative pose ``r`` of the first baseline would give
        the map: the ``Ωm`` tracks both frames see whose rays, the rotation ``ZR`` taken
        out, span ``MappingConfig.feature_parallax_deg`` (what makes a track a feature).

        The first baseline is taken only when this reaches ``TrackingConfig.min_map_features``
        (what the next frames need to be placed on the map; ``experimental.init_map_features``
        when set): on a slowly moving camera
        the relative pose passes its own parallax test long before any track has the
        parallax of a feature, and a first map without features leaves the next frames
        nothing but relative poses on short baselines (ICL-NUIM's living room: about 17
        of the 25 frames after such a start are lost). The frames before wait and are
        placed once the map exists."""
        from ..geometry.rotations import quat_to_rotmat

        m = r.measurement
        ids_i, uv_i = self.frontend.map_observations(m.i)
        ids_j, uv_j = self.frontend.map_observations(m.j)
        _, a, b = np.intersect1d(ids_i, ids_j, return_indices=True)
        if not len(a):
            return 0
        bi = self.camera.bearing(uv_i[a])
        bj = self.camera.bearing(uv_j[b]) @ quat_to_rotmat(m.q_ij).T  # in frame i
        c = np.sum(bi * bj, axis=1) / (np.linalg.norm(bi, axis=1) * np.linalg.norm(bj, axis=1))
        angle = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
        return int(np.sum(angle >= self.config.mapping.feature_parallax_deg))

    # -- the known map ---------------------------------------------------------------
    def known_map(self, k: int) -> tuple[NDArray[np.bool_], Array, Array, Callable[[NDArray[np.int64]], Array],
                                          NDArray[np.int64]]:
        """Which of frame *k*'s ``Zm`` are of known features, their positions and pixels,
        their marginal covariances on demand (``cov(idx) -> (m, 3, 3)``, NaN where the
        filter has none cheaply, :meth:`InformationFilter.feature_covariances`), and their
        ids."""
        filt = self.filter
        ids, uv = self.frontend.map_observations(k)
        known = filt.layout.has_features(ids)
        X = filt.x[filt.layout.feature_columns(ids[known])] if known.any() else np.zeros((0, 3))
        ids_known = np.asarray(ids, np.int64)[known]
        return known, X, uv[known], lambda idx: filt.feature_covariances(ids_known[idx]), ids_known

    # -- earlier frames ------------------------------------------------------------
    def place_late(self, j: int, relative: bool, timings: dict[str, float],
                   relative_first: bool = False, recover: bool = True) -> tuple[bool, int | None]:
        """Localise an earlier frame *j* that has no pose: from the map alone, else (with
        ``relative``) from a relative pose to the nearest known poses; with
        ``relative_first`` the relative pose first and then the map, as a frame of the
        run is placed (for the frames after one placed by wide-baseline matching: the map
        there is young, and their ``ZR``/``ZT`` hold the scale along them).
        ``recover=False`` fuses it without the recovery (the caller recovers once for
        several frames).

        The step length between consecutive frames (the scale guess of the next frame)
        is left as it was. Raises :class:`~eifslam.errors.EstimatorError` as
        :func:`~.algorithm1.algorithm1` does.

        Returns
        -------
        placed : bool
        reference : int or None
            The reference pose of the relative pose used (None: placed on the map).
        """
        last_step = self.last_step
        try:
            if relative_first:
                rp, _ = self.find_reference(j, timings, relocalise=False)
                if rp is not None:
                    algorithm1(j, rp, self, timings, recover)
                    return True, rp.measurement.i
            if algorithm1(j, OnMap(), self, timings, recover) is not None:
                return True, None
            if not relative or relative_first:
                return False, None
            rp, _ = self.find_reference(j, timings, relocalise=False)
            if rp is None:
                return False, None
            algorithm1(j, rp, self, timings, recover)
            return True, rp.measurement.i
        finally:
            self.last_step = last_step  # the step between consecutive frames, not this one's

    def place_wide(self, j: int, wide, timings: dict[str, float]) -> tuple[bool, int | None]:
        """Localise an earlier frame *j* that has no pose from wide-baseline matches to a
        known frame (:class:`~eifslam.frontend.wide.WideMatch`): on the known map features
        their joined tracks made visible (at least ``TrackingConfig.min_map_features`` from the
        nearest known pose, else ``ExperimentalConfig.wide_baseline_min_map_features`` from the
        relative pose of the matches). That relative pose is never fused (with a narrow
        field of view it is poorly conditioned: 7 degrees off on templering). The step length is left as it was, as
        in :meth:`place_late`. Raises :class:`~eifslam.errors.EstimatorError` as
        :func:`~.algorithm1.algorithm1` does.

        Returns
        -------
        placed : bool
        reference : int or None
            The reference pose of the relative pose used (None: placed on the map).
        """
        # imported here: it needs OpenCV, and importing eifslam.system.config must not
        from ..frontend.relative_pose import estimate_relative_pose

        last_step = self.last_step
        try:
            if algorithm1(j, OnMap(), self, timings) is not None:
                return True, None
            rpr = estimate_relative_pose(wide.uv_ref, wide.uv, self.camera, self.frontend.config,
                                         wide.reference, j)
            timings["relative_pose"] = timings.get("relative_pose", 0.0) + rpr.timings_ms.get("relative_pose", 0.0)
            if not rpr.ok:
                return False, None
            # the relative pose is a starting point only: with a narrow field of view its
            # rotation can be degrees off, the map's features fix it
            known, Xk, uvk, _, _ = self.known_map(j)
            p_i, q_i = self.filter.pose(wide.reference)
            p_k, q_k, _ = pose_from_relative(p_i, q_i, rpr.measurement, self.camera, Xk, uvk,
                                             default_step=self.last_step)
            n_min = self.config.experimental.wide_baseline_min_map_features
            return algorithm1(j, OnMap((p_k, q_k), n_min), self, timings) is not None, None
        finally:
            self.last_step = last_step
