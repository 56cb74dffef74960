"""The SLAM system a user runs: Algorithm 1 over a stream of images (paper III-C to III-E).

>>> slam = Slam(camera)                              # doctest: +SKIP
>>> result = slam.track(image, timestamp)            # doctest: +SKIP
>>> result.state, result.position, result.covariance # doctest: +SKIP

Each image goes through the front end (features, tracks, ``Ωp``/``Ωm`` split), is
related to a known pose by ``ZR``/``ZT``, initialised (III-C), augmented into the state
with zeros and fused (Algorithm 1). A frame that cannot be localised is reported
``LOST`` and does not enter the state; tracking resumes as soon as a later frame relates
to any known pose.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..baselines.bundle_adjustment import BAConfig, BAResult
from ..errors import EifslamError, EstimatorError
from ..estimation.filter import InformationFilter
from ..estimation.smoothing import SmoothingReport, recover_scale, smooth
from ..geometry.camera import PinholeCamera
from ..frontend.results import Reason
from .config import Mode, SlamConfig
from .algorithm1 import OnMap, algorithm1
from .finishing import FinishReport, bundle_adjust_slam
from .keyframes import Keyframes
from .late import place_late, retry_passes, unplaced_initial
from .loops import LoopCloser, LoopClosure
from .mapping import Mapper
from .results import TrackingState, TrackResult, pose_matrix
from .session import load_session, save_session
from .tracking import Tracker
from .wide import retry_wide

Array = NDArray[np.float64]


class Slam:
    """Monocular SLAM with the exactly sparse EIF (ORB-SLAM's ``System``).

    The front object: it owns the front end, the estimator, a :class:`~.tracking.Tracker`
    (placing each frame in the state) and a :class:`~.mapping.Mapper` (map observations,
    new features, fusion and recovery), and keeps one :class:`TrackResult` per image.

    Parameters
    ----------
    camera : PinholeCamera
    config : SlamConfig, optional
        Every setting is honoured, ``smoothing.mode`` included (by :meth:`finish`).
    frontend : object, optional
        What turns an image into ``Zm`` and ``ZR``/``ZT`` (default: the OpenCV
        :class:`~eifslam.frontend.FrontEnd` made from ``config.frontend``). Any object with
        the same methods will do; :class:`eifslam.sim.frontend.SyntheticFrontEnd` feeds
        simulated measurements through the same Algorithm 1.
    backend : object, optional
        The estimator (default: the :class:`~eifslam.estimation.filter.InformationFilter`
        made from ``config.filter`` and ``config.experimental``).
    """

    def __init__(self, camera: PinholeCamera, config: SlamConfig | None = None, *,
                 frontend=None, backend=None) -> None:
        self.camera = camera
        self.config = config or SlamConfig()
        if frontend is None:
            from ..frontend import FrontEnd

            frontend = FrontEnd(camera, self.config.frontend)
        self.frontend = frontend
        self.filter = backend if backend is not None else InformationFilter(
            camera, self.config.filter, recovery=self.config.experimental.recovery, window=self.config.experimental.window)
        self.mapper = Mapper(camera, self.config, self.frontend, self.filter)
        self.tracker = Tracker(camera, self.config, self.frontend, self.filter, self.mapper)
        self.keyframes = Keyframes(camera, self.config, self.frontend, self.filter)
        self.loops = LoopCloser(camera, self.config, self.frontend, self.filter, self.mapper)
        self.results: list[TrackResult] = []
        self.smoothing: SmoothingReport | None = None
        self.bundle_adjustment: BAResult | None = None
        self._timestamps: dict[int, float] = {}
        self._waiting: list[int] = []  # frames that waited for the first baseline
        self._keyframe_why = ""  # why the frame being tracked became a keyframe
        self._map_pose = None  # its map pose, should Algorithm 1 fail to place it

    # -- queries ------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """Number of images processed."""
        return len(self.results)

    @property
    def rejected_relative(self) -> list:
        """Relative poses the map contradicted or the gate refused (not fused)."""
        return self.tracker.rejected_relative

    def trajectory(self) -> tuple[Array, Array, Array]:
        """Timestamps ``(P,)``, positions ``(P, 3)`` and quaternions ``(P, 4)`` of every
        tracked frame, in frame order, from the current estimate."""
        self.filter.complete_estimate()
        ids, P, Q = self.filter.poses()
        mids, MP, MQ = self.keyframes.poses()
        ids = list(ids) + mids
        P, Q = np.concatenate([P, MP]), np.concatenate([Q, MQ])
        order = np.argsort(ids, kind="stable")
        t = np.array([self._timestamps[i] for i in ids])[order]
        return t, P[order], Q[order]

    def T_wc(self, frame_id: int) -> Array:
        """(4, 4) camera-to-world transform of a tracked frame from the current estimate
        (after smoothing or bundle adjustment: theirs). :class:`~eifslam.errors.EstimatorError`
        when the frame has no pose. A frame between keyframes has the pose the map gave it."""
        mp = self.keyframes.get(frame_id)
        if mp is not None:
            return pose_matrix(mp.p, mp.q)
        self.filter.complete_estimate()
        return pose_matrix(*self.filter.pose(frame_id))

    def map(self) -> tuple[NDArray[np.int64], Array, NDArray[np.uint8]]:
        """Map feature ids ``(F,)``, positions ``(F, 3)`` and RGB colours ``(F, 3)``."""
        self.filter.complete_estimate()
        ids, X = self.filter.features()
        return np.asarray(ids, np.int64), X, self.mapper.colors(ids)

    @property
    def loop_closures(self) -> list[LoopClosure]:
        """The loops found and fused so far (:mod:`~.loops`), in the order found."""
        return list(self.loops.closures)

    def remove_loop(self, loop: int | LoopClosure) -> LoopClosure:
        """Take a fused loop back (its index in :attr:`loop_closures`, or the loop): what its
        fusion added to the information leaves it, its ``Zm`` leave the measurement store,
        and the estimate is recovered without it (:meth:`~.loops.LoopCloser.remove`). The
        loop is then listed in ``loops.removed``, not in :attr:`loop_closures`.

        Raises
        ------
        KeyError
            When the loop is not one this run fused (or its record did not survive a session).
        """
        return self.loops.remove(loop)

    def feature_covariance(self, track_id: int) -> Array:
        """3x3 covariance of a map feature."""
        return self.filter.feature_covariance(track_id)

    # -- the per-image entry point -------------------------------------------------
    def track(self, image: np.ndarray, timestamp: float | None = None) -> TrackResult:
        """Process one image: the pose, its covariance and the tracking state.

        Bad input (an unreadable array) raises :class:`~eifslam.errors.ImageError`; a frame
        that cannot be localised (no texture, no parallax, too few matches) is a LOST
        result, not an exception.
        """
        k = self.n_frames
        ts = float(k if timestamp is None else timestamp)
        self._keyframe_why, self._map_pose = "", None
        t0 = time.perf_counter()
        fr = self.frontend.add_frame(image, k)
        timings = dict(fr.timings_ms)
        self._timestamps[k] = ts
        if fr.n_features == 0 and not fr.ok:
            return self._record(TrackResult(k, ts, self._lost_state(), reason=fr.reason, timings_ms=timings), t0)
        if self.filter.layout.n_poses >= 2 and not self._waiting:
            res = self._between_keyframes(k, ts, timings)
            if res is not None:
                return self._record(res, t0)
        if self.filter.layout.n_poses == 0:
            return self._record(self._world_frame(k, ts, timings, "first frame: world frame"), t0)
        tracker = self.tracker
        try:
            rp, tried = tracker.find_reference(k, timings, relocalise=False)
            if rp is not None:
                algorithm1(k, rp, tracker, timings)
            elif algorithm1(k, OnMap(), tracker, timings) is not None:
                p, q = self.filter.pose(k)
                res = TrackResult(k, ts, TrackingState.TRACKING, p, q, self.filter.pose_covariance(k),
                                  reason="localised from map features (no baseline to a known pose)",
                                  timings_ms=timings)
                return self._record(res, t0)
            else:
                rp, tried2 = tracker.find_reference(k, timings, relocalise=True)
                tried = tried2 or tried
                if rp is None:
                    reason = tried.reason if tried is not None else "no known pose to relate to"
                    if self.filter.layout.n_poses == 1 and reason == Reason.TOO_FEW_COMMON:
                        return self._record(self._move_world_frame(k, ts, timings), t0)
                    return self._record(TrackResult(k, ts, self._lost_state(), reason=f"lost: {reason}",
                                                    timings_ms=timings), t0)
                algorithm1(k, rp, tracker, timings)
        except EstimatorError as exc:  # keep the run alive; the frame counts as lost
            return self._record(TrackResult(k, ts, self._lost_state(), reason=f"lost: {exc}", timings_ms=timings), t0)
        t1 = time.perf_counter()
        try:
            loop = self.loops.process(k)
        except EstimatorError:  # a loop that cannot be fused is a loop not closed
            loop = None
        timings["loop"] = 1e3 * (time.perf_counter() - t1)
        why = self._keyframe_why if loop is None else f"{self._keyframe_why}{'; ' if self._keyframe_why else ''}" \
            f"loop closed with frame {loop.matched_frame}"
        p, q = self.filter.pose(k)
        cov = self.filter.pose_covariance(k)
        res = TrackResult(k, ts, TrackingState.TRACKING, p, q, cov, reason=why,
                          reference=rp.measurement.i, timings_ms=timings)
        return self._record(res, t0)

    def _world_frame(self, k: int, ts: float, timings: dict[str, float], reason: str) -> TrackResult:
        """Frame *k* becomes the world frame: the first pose, at the origin, fixed (the gauge)."""
        self.filter.add_pose(k, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
        self.filter.fix_pose(k)
        self.mapper.record_observations(k)
        return TrackResult(k, ts, TrackingState.INITIALISING, np.zeros(3), np.array([1.0, 0, 0, 0]),
                           reason=reason, timings_ms=timings)

    def _move_world_frame(self, k: int, ts: float, timings: dict[str, float]) -> TrackResult:
        """Before the map exists, frame *k* shares too few tracks with the world frame for a
        relative pose, and tracks only end: no later frame will share more. The world
        frame moves on to frame *k* (the filter starts again, :meth:`InformationFilter.restart`),
        and the old one waits, as the frames between them do, to be placed on the map once
        it exists (as ORB-SLAM's initialiser takes a new reference frame). On a weakly
        textured view the first frame's few tracks can end before the camera has moved
        enough for a baseline; without this no frame of the run would be placed."""
        old = self.filter.layout.pose_ids[0]
        self.filter.restart()
        self.mapper.forget_frame(old)
        r = self.results[old]
        self.results[old] = TrackResult(old, r.timestamp, TrackingState.INITIALISING,
                                        reason=f"initialising: the world frame moved to frame {k} "
                                               f"({Reason.TOO_FEW_COMMON} with frame {old})",
                                        timings_ms=r.timings_ms)
        self._waiting = sorted(set(self._waiting) | {old})
        return self._world_frame(k, ts, timings, f"world frame (too few common features with frame {old})")

    def _between_keyframes(self, k: int, ts: float, timings: dict[str, float]) -> TrackResult | None:
        """Frame *k* localised on the map, when it need not be a keyframe; None otherwise
        (why it must be one becomes the reason of its :class:`TrackResult`)."""
        due = self.keyframes.due(ts)
        if due is not None:  # a keyframe whatever the map says: skip the map localisation
            self._keyframe_why = f"keyframe: {due}"
            return None
        t1 = time.perf_counter()
        prev = next((r for r in reversed(self.results) if r.position is not None), None)
        p0, q0 = (prev.position, prev.quat_wxyz) if prev is not None else self.filter.pose(self.keyframes.last)
        mp = self.keyframes.localise(k, p0, q0)
        timings["localise"] = 1e3 * (time.perf_counter() - t1)
        why = "the map alone does not place it" if mp is None else self.keyframes.keyframe_reason(mp, ts)
        if why is not None:
            self._keyframe_why = f"keyframe: {why}"
            self._map_pose = mp  # kept if Algorithm 1 cannot place the frame
            return None
        return self._map_result(mp, ts, "", timings)

    def _map_result(self, mp, ts: float, reason: str, timings: dict[str, float]) -> TrackResult:
        """The result of a frame kept at its map pose ``mp`` (between keyframes)."""
        self.keyframes.add(mp)
        return TrackResult(mp.frame_id, ts, TrackingState.TRACKING, mp.p.copy(), mp.q.copy(), mp.covariance,
                           reason=reason, reference=mp.reference, timings_ms=timings, keyframe=False)

    def untracked(self) -> list[int]:
        """Frames that have no pose, in frame order."""
        return [r.frame_id for r in self.results if r.position is None]

    def retry_frame(self, j: int, reason: str, relative: bool = True, wide=None, relative_first: bool = False) -> bool:
        """Localise an earlier frame *j* that has no pose (:func:`~.late.place_late`:
        :meth:`Tracker.place_late`, or :meth:`Tracker.place_wide` with the wide-baseline
        matches ``wide``). On success the frame's :class:`TrackResult` is updated in place
        (``reason`` says why it was late)."""
        return place_late(self, [j], reason, relative, wide, relative_first) == 1

    def _lost_state(self) -> TrackingState:
        return TrackingState.INITIALISING if self.filter.layout.n_poses < 2 else TrackingState.LOST

    def _record(self, res: TrackResult, t0: float) -> TrackResult:
        """Store a frame's result (and localise the frames that waited for the map)."""
        mp = self._map_pose
        if res.position is None and mp is not None and mp.frame_id == res.frame_id:
            # a keyframe that Algorithm 1 could not place keeps the pose the map gave it
            res = self._map_result(mp, res.timestamp, f"{self._keyframe_why}; {res.reason}; kept its map pose",
                                   res.timings_ms)
        self.results.append(res)
        if res.keyframe and res.position is not None \
                and self.filter.layout.has_pose(res.frame_id):
            self.keyframes.note_keyframe(res.frame_id, res.timestamp)
        elif res.position is not None and not self.filter.layout.has_pose(res.frame_id):
            self.frontend.release(res.frame_id)  # placed between keyframes: never matched again
        if res.position is None and res.state is TrackingState.INITIALISING:
            self._waiting.append(res.frame_id)
        elif res.state is TrackingState.TRACKING and self._waiting and self.filter.layout.n_poses >= 2:
            # the map now exists: the frames that waited for a baseline are localised on it,
            # nearest to the new frame first (they share the most features with it), from
            # the map only (a waiting frame is on a short baseline to its neighbours and its
            # ZR/ZT would be poor; retry_lost() tries relative poses at the end)
            place_late(self, sorted(self._waiting, reverse=True),
                       "localised once the map was initialised (waited for a baseline)", relative=False)
            self._waiting = []
        elif res.state is TrackingState.TRACKING and res.keyframe and self.filter.layout.n_poses >= 2:
            # the first map is small (few features have the parallax yet): the frames it
            # could not place are tried again at the next keyframes, as the map grows
            late = unplaced_initial(self, res.frame_id)
            if late:
                place_late(self, late, "localised once the map had grown (waited for a baseline)", relative=False)
        res.timings_ms["total"] = 1e3 * (time.perf_counter() - t0)
        res.map_features = self.filter.layout.n_features
        res.state_dim = self.filter.dim
        return res

    # -- after the run ------------------------------------------------------------
    def retry_lost(self, max_passes: int = 3, images: Callable[[int], np.ndarray] | None = None) -> int:
        """Give every frame without a pose one more chance against the final map (an
        offline step, the first of :meth:`finish`): frames lost on the way, and frames
        that waited for the first baseline. With ``experimental.wide_baseline`` and ``images``
        (frame id -> the image given to :meth:`track`), the frames still without a pose
        are then matched with affine-simulated features to their nearest known frames
        (:func:`~.wide.retry_wide`) and the rest retried once they are placed. Returns
        how many frames it added."""
        added = 0
        if self.filter.layout.n_poses < 2:
            return 0
        added += self.retry_passes(max_passes, first_map_only=True)
        cfg = self.config
        if images is not None and cfg.experimental.wide_baseline:
            wide = retry_wide(self, images)
            added += wide + (self.retry_passes(max_passes, first_map_only=False) if wide else 0)
        return added

    def retry_passes(self, max_passes: int, first_map_only: bool) -> int:
        """Passes over the frames without a pose until one adds none (:func:`~.late.retry_passes`)."""
        return retry_passes(self, max_passes, first_map_only)

    def smooth(self, max_passes: int | None = None) -> SmoothingReport:
        """Relinearise every stored measurement and recover (paper III-E); the frames
        between keyframes are then re-localised on the smoothed map
        (:meth:`refine_between_keyframes`), so that :meth:`trajectory` is the smoothed one
        for every frame, however this is called."""
        if self.filter.layout.n_poses < 2:
            raise EifslamError("nothing to smooth: fewer than two poses are tracked")
        self.filter.complete_estimate()
        cfg = self.config
        gates = dict(feature_chi2=self.filter.config.gate_chi2, relative_chi2=cfg.experimental.relative_gate_chi2) \
            if cfg.experimental.robust_smoothing else {}
        info = self.filter.information_form()
        self.smoothing = smooth(info, max_passes or cfg.experimental.smooth_passes,
                                estimate_noise=cfg.experimental.noise_estimate, **gates)
        self.filter.set_from_information_form(info)
        self.refine_between_keyframes()
        return self.smoothing

    def bundle_adjust(self, config: BAConfig | None = None) -> BAResult:
        """Bundle-adjust every track and make the result the estimate
        (:func:`~.finishing.bundle_adjust_slam`); the frames between keyframes are then
        re-localised on the adjusted map, as after :meth:`smooth`."""
        if self.filter.layout.n_poses < 2:
            raise EifslamError("nothing to adjust: fewer than two poses are tracked")
        self.bundle_adjustment = bundle_adjust_slam(self, config)
        self.refine_between_keyframes()
        return self.bundle_adjustment

    def finish(self, retry: bool = True, images: Callable[[int], np.ndarray] | None = None) -> FinishReport:
        """End a run as ``smoothing.mode`` says (what ``eifslam run`` does after the last image).

        First every frame without a pose gets one more chance (:meth:`retry_lost`, unless
        ``retry`` is False; ``images`` as there: frame id -> image, for the wide-baseline
        matching of ``experimental.wide_baseline``); then mode ``smooth`` smooths (:meth:`smooth`) and mode ``ba``
        bundle-adjusts (:meth:`bundle_adjust`); mode ``filter`` keeps the filter's
        estimate. A step that fails is recorded in the report and the estimate so far is
        kept (the run is not lost).
        """
        rep = FinishReport()
        if self.mapper.flush_deferred():  # the Zm of a revisit that waited (Mapper.fuse_zm)
            self.filter.recover_active()
        if retry:
            try:
                rep.added = self.retry_lost(images=images)
            except EifslamError as exc:
                rep.retry_error = str(exc)
        if self.filter.layout.n_poses < 2:
            return rep
        mode = Mode(self.config.smoothing.mode)
        refined = False  # smooth() and bundle_adjust() re-localise the frames between keyframes
        if mode is Mode.SMOOTH:
            try:
                rep.smoothing = self.smooth()
                refined = True
            except EifslamError as exc:
                rep.failures.append(f"smoothing failed: {exc}")
        elif mode is Mode.BA:
            try:
                rep.ba = self.bundle_adjust()
                refined = True
            except EifslamError as exc:
                rep.failures.append(f"bundle adjustment failed: {exc}")
        if not refined:
            self.refine_between_keyframes()
        return rep

    def refine_between_keyframes(self) -> int:
        """Re-localise the frames between keyframes on the current map (the last step of
        :meth:`finish`) and update their :class:`TrackResult`; returns how many there are."""
        if len(self.keyframes) == 0:
            return 0
        self.filter.complete_estimate()
        for mp in self.keyframes.refine():
            old = self.results[mp.frame_id]
            self.results[mp.frame_id] = TrackResult(
                old.frame_id, old.timestamp, old.state, mp.p.copy(), mp.q.copy(), mp.covariance, old.reason,
                old.reference, old.timings_ms, old.map_features, old.state_dim, keyframe=False)
        return len(self.keyframes)

    def set_scale(self, a: tuple[str, int], b: tuple[str, int], length: float) -> float:
        """Scale recovery (paper V): make the distance between two states ``length``
        (the frames between keyframes are rescaled with the map)."""
        info = self.filter.information_form()
        s = recover_scale(info, a, b, length)
        self.filter.set_from_information_form(info)
        self.keyframes.rescale(s)
        for r in self.results:
            if r.position is not None and not r.keyframe:
                mp = self.keyframes.get(r.frame_id)
                if mp is not None:
                    r.position, r.covariance = mp.p.copy(), mp.covariance
        return s

    # -- sessions -----------------------------------------------------------------
    @property
    def waiting(self) -> list[int]:
        """Frames without a pose that wait for the first baseline (placed once the map exists)."""
        return list(self._waiting)

    def restore(self, results: list[TrackResult], waiting: list[int]) -> None:
        """Set the per-image record of a loaded session (:func:`~.session.load_session`)."""
        self.results = list(results)
        self._timestamps = {r.frame_id: r.timestamp for r in self.results}
        self._waiting = [int(j) for j in waiting]

    def save(self, path: str | Path) -> None:
        """Save the whole session (filter, front end, results) to a file
        (:func:`~.session.save_session`); measurements that wait to be fused are fused first
        (:meth:`~.mapping.Mapper.flush_deferred`)."""
        if self.mapper.flush_deferred():
            self.filter.recover_active()
        save_session(self, path)

    @staticmethod
    def load(path: str | Path) -> "Slam":
        """Load a session saved by :meth:`save` (:func:`~.session.load_session`)."""
        return load_session(path, Slam)
