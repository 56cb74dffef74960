"""Tracking: placing a frame in the state (paper III-C, III-F; ORB-SLAM's Tracking).

The :class:`Tracker` finds a known pose related to a new frame by ``ZR``/``ZT`` (recent
poses, then older ones after descriptor matching when tracking is lost), or localises the
frame on the known map alone; it chooses the linearisation point (relative-pose guess,
refined on the map when they agree), gates the ``ZR``/``ZT`` against the pose the map
supports, adds the pose and fuses, then hands the frame to the :class:`~.mapping.Mapper`.
"""

from __future__ import annotations

import time
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from ..estimation.initialisation import pose_from_relative
from ..estimation.localisation import localise_pose
from ..estimation.measurements import pack_relative, unpack_relative
from ..estimation.statedict import sub, take_float
from ..frontend.results import RelativePoseResult
from ..geometry.camera import PinholeCamera
from .config import SlamConfig
from .mapping import Mapper, project

Array = NDArray[np.float64]

__all__ = ["Tracker", "agrees", "inlier_fraction", "relative_gate_statistic"]


def agrees(p_i: Array, p_k: Array, q_k: Array, sol, max_rot_deg: float, max_dir_deg: float) -> bool:
    """Whether a map-refined pose agrees with the relative-pose guess.

    Parameters
    ----------
    p_i : (3,) position of the reference pose.
    p_k, q_k : (3,), (4,) the relative-pose guess of the new pose.
    sol : tuple
        ``(p, q, inliers)`` from :func:`~eifslam.estimation.localisation.localise_pose`.
    max_rot_deg, max_dir_deg : float
        Largest rotation between the two, and largest angle between their step
        directions from ``p_i``, degrees.

    Returns
    -------
    bool
        Rotation and direction within bounds and most known features fit; a refinement
        that disagrees was pulled away by bad matches.
    """
    from ..geometry.rotations import quat_conjugate, quat_log, quat_multiply

    p, q, inl = sol
    rot = np.degrees(np.linalg.norm(quat_log(quat_multiply(quat_conjugate(q_k), q))))
    a, b = p_k - p_i, p - p_i
    cosang = float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))
    return bool(rot <= max_rot_deg and cosang >= np.cos(np.radians(max_dir_deg)) and inl.mean() >= 0.5)


def relative_gate_statistic(filt, rp) -> float:
    """Normalised innovation squared of a ``ZR``/``ZT`` against its own covariance ``R``
    (5 DOF), at the filter's current estimate of the two poses.

    The poses' uncertainty is left out: adding it admits wrong relative poses on real
    images, whose stated pixel noise is several times the true one.
    """
    _, _, W, innov = filt.linearise_relative([rp])
    return float(innov[0] @ W[0] @ innov[0])


def inlier_fraction(camera: PinholeCamera, p: Array, q: Array, X: Array, uv: Array, px: float) -> float:
    """Fraction of known features ``X`` (N, 3) that pose ``(p, q)`` projects within ``px``
    pixels of their measurements ``uv`` (N, 2)."""
    h, z = project(camera, p, q, X)
    return float(np.mean((z > 0) & (np.linalg.norm(uv - h, axis=1) < px)))


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
    """

    def __init__(self, camera: PinholeCamera, config: SlamConfig, frontend, backend, mapper: Mapper) -> None:
        self.camera = camera
        self.config = config
        self.frontend = frontend
        self.filter = backend
        self.mapper = mapper
        self.rejected_relative: list = []
        self._last_step = config.tracking.scale_distance

    # -- sessions -----------------------------------------------------------------
    def state_dict(self) -> dict:
        """What a session keeps: the refused relative poses and the last step length."""
        return {"rejected_relative": pack_relative(self.rejected_relative), "last_step": float(self._last_step)}

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict`, checked (:class:`~eifslam.errors.SessionError`)."""
        self.rejected_relative = unpack_relative(sub(d, "rejected_relative"))
        self._last_step = take_float(d, "last_step")

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
            if r.ok and self.filter.layout.n_poses == 1 and r.parallax_deg < cfg.experimental.init_parallax_deg:
                continue  # too narrow a baseline to initialise the map on
            if r.ok:
                return r, r
        return None, last

    # -- placing a frame ------------------------------------------------------------
    def _known_map(self, k: int) -> tuple[NDArray[np.bool_], Array, Array, Callable[[NDArray[np.int64]], Array],
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

    def localise_from_map(self, k: int, timings: dict[str, float], guess: tuple[Array, Array] | None = None,
                          min_features: int | None = None, recover: bool = True) -> bool:
        """Add frame *k* from ``Zm`` of known map features alone (no usable baseline);
        False when there are too few of them or the pose does not converge.

        ``guess`` (position, ``q_wc``) starts the localisation (default: the nearest
        known pose); ``min_features`` overrides ``TrackingConfig.min_map_features``;
        ``recover=False`` fuses without the recovery (the caller recovers once)."""
        filt = self.filter
        if filt.layout.n_poses < 2 or filt.layout.n_features == 0:
            return False
        t0 = time.perf_counter()
        known, X, uv, map_cov, _ = self._known_map(k)
        n_min = self.config.tracking.min_map_features if min_features is None else int(min_features)
        if known.sum() < n_min:
            return False
        p0, q0 = filt.pose(self.nearest_known(k)[0]) if guess is None else guess
        sol = localise_pose(self.camera, p0, q0, X, uv, min_inliers=min(n_min, 12), X_cov=map_cov)
        if sol is None:
            return False
        p, q, _ = sol
        self.mapper.reobserve(k, p, q)
        filt.add_pose(k, p, q)
        self.mapper.fuse_and_recover(k, t0, timings, recover)
        return True

    def localise_and_fuse(self, k: int, rpr: RelativePoseResult, timings: dict[str, float],
                          recover: bool = True) -> None:
        """Algorithm 1 for frame *k* related to a known pose by ``rpr``: initial guesses,
        augment with zeros, fuse ``ZR``/``ZT`` (unless gated out) and ``Zm``, recover
        (unless ``recover`` is False: the caller recovers once)."""
        filt, cfg = self.filter, self.config
        rp = rpr.measurement
        t0 = time.perf_counter()
        known, Xk, uvk, map_cov, _ = self._known_map(k)
        p_i, q_i = filt.pose(rp.i)
        first_step = filt.layout.n_poses == 1
        init = pose_from_relative(p_i, q_i, rp, self.camera, Xk, uvk,
                                  default_step=cfg.tracking.scale_distance if first_step else self._last_step)
        p_k, q_k, step = init
        use_relative, refined = True, False
        if known.sum() >= cfg.tracking.min_map_features:  # a better linearisation point: refine on the known map
            sol = localise_pose(self.camera, p_k, q_k, Xk, uvk, X_cov=map_cov)
            if sol is None:  # the map does not converge from the relative pose's guess: from the
                # nearest known pose, as a frame without a relative pose (ORB kitti-07: a guess
                # 50 m off from a reference 15 frames back was fused as it was)
                p0, q0 = filt.pose(self.nearest_known(k)[0])
                sol = localise_pose(self.camera, p0, q0, Xk, uvk, X_cov=map_cov)
            frac = sol[2].mean() if sol is not None else 0.0
            if sol is not None and agrees(p_i, p_k, q_k, sol, max_rot_deg=cfg.tracking.agree_rotation_deg,
                                          max_dir_deg=cfg.tracking.agree_direction_deg):
                p_k, q_k, refined = sol[0], sol[1], frac >= cfg.tracking.map_inlier_fraction
            elif sol is not None and frac > cfg.tracking.contradiction_ratio * inlier_fraction(
                    self.camera, p_k, q_k, Xk, uvk, cfg.tracking.inlier_radius_px):
                # the map contradicts this relative pose: trust the map, drop the ZR/ZT
                p_k, q_k, use_relative = sol[0], sol[1], False
                self.rejected_relative.append(rp)
            elif sol is not None and frac >= cfg.tracking.map_inlier_fraction:
                # the map fits well where the relative pose points elsewhere (on a short
                # baseline both guesses fit the map): linearise at the map's pose and let
                # the chi-square gate below decide on the ZR/ZT
                p_k, q_k, refined = sol[0], sol[1], True
        self.mapper.reobserve(k, p_k, q_k)
        filt.add_pose(k, p_k, q_k)
        if first_step:
            filt.set_scale(rp.i, k, cfg.tracking.scale_distance)
        self._last_step = step if step > 0 else self._last_step
        if use_relative and refined and cfg.experimental.relative_gate_chi2 is not None:
            # ZR/ZT against the pose the map supports: an inconsistent one is not fused
            if relative_gate_statistic(filt, rp) > cfg.experimental.relative_gate_chi2:
                use_relative = False
                self.rejected_relative.append(rp)
        if use_relative:
            filt.fuse_relative([rp])
        self.mapper.fuse_and_recover(k, t0, timings, recover)

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
        :meth:`localise_and_fuse` does.

        Returns
        -------
        placed : bool
        reference : int or None
            The reference pose of the relative pose used (None: placed on the map).
        """
        last_step = self._last_step
        try:
            if relative_first:
                rp, _ = self.find_reference(j, timings, relocalise=False)
                if rp is not None:
                    self.localise_and_fuse(j, rp, timings, recover)
                    return True, rp.measurement.i
            if self.localise_from_map(j, timings, recover=recover):
                return True, None
            if not relative or relative_first:
                return False, None
            rp, _ = self.find_reference(j, timings, relocalise=False)
            if rp is None:
                return False, None
            self.localise_and_fuse(j, rp, timings, recover)
            return True, rp.measurement.i
        finally:
            self._last_step = last_step  # the step between consecutive frames, not this one's

    def place_wide(self, j: int, wide, timings: dict[str, float]) -> tuple[bool, int | None]:
        """Localise an earlier frame *j* that has no pose from wide-baseline matches to a
        known frame (:class:`~eifslam.frontend.wide.WideMatch`): on the known map features
        their joined tracks made visible (at least ``TrackingConfig.min_map_features`` from the
        nearest known pose, else ``ExperimentalConfig.wide_baseline_min_map_features`` from the
        relative pose of the matches). That relative pose is never fused (with a narrow
        field of view it is poorly conditioned: 7 degrees off on templering). The step length is left as it was, as
        in :meth:`place_late`. Raises :class:`~eifslam.errors.EstimatorError` as
        :meth:`localise_and_fuse` does.

        Returns
        -------
        placed : bool
        reference : int or None
            The reference pose of the relative pose used (None: placed on the map).
        """
        # imported here: it needs OpenCV, and importing eifslam.system.config must not
        from ..frontend.relative_pose import estimate_relative_pose

        last_step = self._last_step
        try:
            if self.localise_from_map(j, timings):
                return True, None
            rpr = estimate_relative_pose(wide.uv_ref, wide.uv, self.camera, self.frontend.config,
                                         wide.reference, j)
            timings["relative_pose"] = timings.get("relative_pose", 0.0) + rpr.timings_ms.get("relative_pose", 0.0)
            if not rpr.ok:
                return False, None
            # the relative pose is a starting point only: with a narrow field of view its
            # rotation can be degrees off, the map's features fix it
            known, Xk, uvk, _, _ = self._known_map(j)
            p_i, q_i = self.filter.pose(wide.reference)
            p_k, q_k, _ = pose_from_relative(p_i, q_i, rpr.measurement, self.camera, Xk, uvk,
                                             default_step=self._last_step)
            n_min = self.config.experimental.wide_baseline_min_map_features
            return self.localise_from_map(j, timings, guess=(p_k, q_k), min_features=n_min), None
        finally:
            self._last_step = last_step
