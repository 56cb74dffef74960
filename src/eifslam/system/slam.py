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

import pickle
import time
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from .config import SlamConfig
from ..errors import EifslamError, EstimatorError
from ..estimation.filter import InformationFilter
from ..frontend import FrontEnd
from ..frontend.results import RelativePoseResult
from ..estimation.initialisation import pose_from_relative, triangulate
from ..estimation.localisation import localise_pose
from ..estimation.measurements import FeatureObservations
from ..estimation.smoothing import SmoothingReport, recover_scale, smooth

Array = NDArray[np.float64]


def _agrees(p_i: Array, p_k: Array, q_k: Array, sol, max_rot_deg: float, max_dir_deg: float) -> bool:
    """Whether a map-refined pose agrees with the relative-pose guess (rotation within
    ``max_rot_deg``, step direction from ``p_i`` within ``max_dir_deg``) and fits most of
    the known features; a refinement that disagrees was pulled away by bad matches."""
    from ..geometry.rotations import quat_conjugate, quat_log, quat_multiply

    p, q, inl = sol
    rot = np.degrees(np.linalg.norm(quat_log(quat_multiply(quat_conjugate(q_k), q))))
    a, b = p_k - p_i, p - p_i
    cosang = float(a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))
    return bool(rot <= max_rot_deg and cosang >= np.cos(np.radians(max_dir_deg)) and inl.mean() >= 0.5)


def _project(camera: PinholeCamera, p: Array, q: Array, X: Array) -> tuple[Array, Array]:
    """Pixels ``(N, 2)`` and depths ``(N,)`` of world points ``X`` (N, 3) seen from poses
    ``p`` (3,) or (N, 3), ``q`` (4,) or (N, 4) (the ``Zm`` model)."""
    from ..geometry.models import feature_model

    N = len(X)
    h, _, _, z = feature_model(np.broadcast_to(p, (N, 3)), np.broadcast_to(q, (N, 4)), X,
                               camera.fx, camera.fy, camera.cx, camera.cy)
    return h, z


def _inlier_fraction(camera: PinholeCamera, p: Array, q: Array, X: Array, uv: Array, px: float = 4.0) -> float:
    """Fraction of known features ``X`` (N, 3) that pose ``(p, q)`` projects within ``px``
    pixels of their measurements ``uv`` (N, 2)."""
    h, z = _project(camera, p, q, X)
    return float(np.mean((z > 0) & (np.linalg.norm(uv - h, axis=1) < px)))


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
    reference : frame id of the reference pose, or None.
    timings_ms : per-stage milliseconds.
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


class Slam:
    """Monocular SLAM with the exactly sparse EIF.

    Parameters
    ----------
    camera : PinholeCamera
    config : SlamConfig, optional
    frontend : object, optional
        What turns an image into ``Zm`` and ``ZR``/``ZT`` (default: the OpenCV
        :class:`~eifslam.frontend.FrontEnd` made from ``config.frontend``). Any object with
        the same methods will do; :class:`eifslam.sim.frontend.SyntheticFrontEnd` feeds
        simulated measurements through the same Algorithm 1.
    backend : object, optional
        The estimator (default: the :class:`~eifslam.estimation.filter.InformationFilter`
        made from ``config.filter`` and ``config.system``).
    """

    def __init__(self, camera: PinholeCamera, config: SlamConfig | None = None, *,
                 frontend=None, backend=None) -> None:
        self.camera = camera
        self.config = config or SlamConfig()
        self.frontend = frontend if frontend is not None else FrontEnd(camera, self.config.frontend)
        self.filter = backend if backend is not None else InformationFilter(
            camera, self.config.filter, recovery=self.config.system.recovery, window=self.config.system.window)
        self.results: list[TrackResult] = []
        self._timestamps: dict[int, float] = {}
        self._track_obs: dict[int, list[tuple[int, Array]]] = {}
        self._colors: dict[int, NDArray[np.uint8]] = {}
        self._last_step = self.config.system.scale_distance
        self.smoothing: SmoothingReport | None = None
        self.rejected_relative: list = []  # relative poses the map contradicted (not fused)
        self._waiting: list[int] = []  # frames that waited for the first baseline

    # -- queries ------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return len(self.results)

    def trajectory(self) -> tuple[Array, Array, Array]:
        """Timestamps ``(P,)``, positions ``(P, 3)`` and quaternions ``(P, 4)`` of every
        tracked frame, in frame order, from the current estimate."""
        self.filter.complete_estimate()
        ids, P, Q = self.filter.poses()
        order = np.argsort(ids)
        t = np.array([self._timestamps[i] for i in ids])[order]
        return t, P[order], Q[order]

    def map(self) -> tuple[NDArray[np.int64], Array, NDArray[np.uint8]]:
        """Map feature ids ``(F,)``, positions ``(F, 3)`` and RGB colours ``(F, 3)``."""
        self.filter.complete_estimate()
        ids, X = self.filter.features()
        cols = np.array([self._colors.get(i, np.array([200, 200, 200], np.uint8)) for i in ids], np.uint8).reshape(-1, 3)
        return np.asarray(ids, np.int64), X, cols

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
        t0 = time.perf_counter()
        fr = self.frontend.add_frame(image, k)
        timings = dict(fr.timings_ms)
        self._timestamps[k] = ts
        if fr.n_features == 0 and not fr.ok:
            return self._finish(TrackResult(k, ts, self._lost_state(), reason=fr.reason, timings_ms=timings), t0)
        if self.filter.layout.n_poses == 0:
            self.filter.add_pose(k, np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0]))
            self.filter.fix_pose(k)
            self._record_map_observations(k)
            res = TrackResult(k, ts, TrackingState.INITIALISING, np.zeros(3), np.array([1.0, 0, 0, 0]),
                              reason="first frame: world frame", timings_ms=timings)
            return self._finish(res, t0)
        try:
            rp, tried = self._find_reference(k, timings, relocalise=False)
            if rp is not None:
                self._localise_and_fuse(k, rp, timings)
            elif self._localise_from_map(k, timings):
                p, q = self.filter.pose(k)
                res = TrackResult(k, ts, TrackingState.TRACKING, p, q, self.filter.pose_covariance(k),
                                  reason="localised from map features (no baseline to a known pose)",
                                  timings_ms=timings)
                return self._finish(res, t0)
            else:
                rp, tried2 = self._find_reference(k, timings, relocalise=True)
                tried = tried2 or tried
                if rp is None:
                    reason = tried.reason if tried is not None else "no known pose to relate to"
                    return self._finish(TrackResult(k, ts, self._lost_state(), reason=f"lost: {reason}",
                                                    timings_ms=timings), t0)
                self._localise_and_fuse(k, rp, timings)
        except EstimatorError as exc:  # keep the run alive; the frame counts as lost
            return self._finish(TrackResult(k, ts, self._lost_state(), reason=f"lost: {exc}", timings_ms=timings), t0)
        p, q = self.filter.pose(k)
        cov = self.filter.pose_covariance(k)
        res = TrackResult(k, ts, TrackingState.TRACKING, p, q, cov, reference=rp.measurement.i, timings_ms=timings)
        return self._finish(res, t0)

    def _untracked(self) -> list[int]:
        """Frames (after the first) that have no pose in the state, in frame order."""
        return [r.frame_id for r in self.results
                if r.frame_id > 0 and not self.filter.layout.has_pose(r.frame_id)]

    def _retry(self, j: int, reason: str, relative: bool = True) -> bool:
        """Localise an earlier frame *j* that has no pose: from the map alone, else (with
        ``relative``) from a relative pose to the nearest known poses. On success the
        frame's :class:`TrackResult` is updated in place (``reason`` says why it was late)."""
        timings: dict[str, float] = {}
        last_step = self._last_step
        try:
            if self._localise_from_map(j, timings):
                ref = None
            elif not relative:
                return False
            else:
                rp, _ = self._find_reference(j, timings, relocalise=False)
                if rp is None:
                    return False
                self._localise_and_fuse(j, rp, timings)
                ref = rp.measurement.i
        except EstimatorError:
            return False
        finally:
            self._last_step = last_step  # the step between consecutive frames, not this one's
        p, q = self.filter.pose(j)
        old = self.results[j]
        self.results[j] = TrackResult(j, old.timestamp, TrackingState.TRACKING, p, q, self.filter.pose_covariance(j),
                                      reason=reason, reference=ref, timings_ms={**old.timings_ms, **timings},
                                      map_features=self.filter.layout.n_features, state_dim=self.filter.dim)
        return True

    def finish(self, max_passes: int = 3) -> int:
        """Give every frame without a pose one more chance against the final map (an
        offline step, run by ``eifslam run`` before smoothing): frames lost on the way, and
        frames that waited for the first baseline. Returns how many frames it added."""
        added = 0
        if self.filter.layout.n_poses < 2:
            return 0
        for n in range(max_passes):  # the map first; relative poses once the map is exhausted
            new = sum(self._retry(j, "localised after the run, against the final map", relative=n > 0)
                      for j in self._untracked())
            added += new
            if new == 0 and n > 0:
                break
        if added:
            self.filter.recover_active()
        return added

    def _lost_state(self) -> TrackingState:
        return TrackingState.INITIALISING if self.filter.layout.n_poses < 2 else TrackingState.LOST

    def _finish(self, res: TrackResult, t0: float) -> TrackResult:
        self.results.append(res)
        if res.position is None and res.state is TrackingState.INITIALISING and res.frame_id > 0:
            self._waiting.append(res.frame_id)
        elif res.state is TrackingState.TRACKING and self._waiting and self.filter.layout.n_poses >= 2:
            # the map now exists: the frames that waited for a baseline are localised on it,
            # nearest to the new frame first (they share the most features with it), from
            # the map only (a waiting frame is on a short baseline to its neighbours and its
            # ZR/ZT would be poor; finish() tries relative poses at the end)
            for j in sorted(self._waiting, reverse=True):
                self._retry(j, "localised once the map was initialised (waited for a baseline)", relative=False)
            self._waiting = []
        res.timings_ms["total"] = 1e3 * (time.perf_counter() - t0)
        res.map_features = self.filter.layout.n_features
        res.state_dim = self.filter.dim
        return res

    def _find_reference(self, k: int, timings: dict, relocalise: bool) -> tuple[RelativePoseResult | None, RelativePoseResult | None]:
        """A known pose related to frame *k* by ``ZR``/``ZT`` (III-C, III-F).

        Without ``relocalise``: the most recent known poses, then a few further back (a
        larger baseline when the camera moves slowly). With ``relocalise``: older poses,
        after matching the frame against them (tracking lost).
        """
        sysc = self.config.system
        known = self._nearest_known(k)
        n = sysc.reference_candidates
        if relocalise:
            older = known[n : n + sysc.relocalise_candidates]
            if not older:
                return None, None
            matches = self.frontend.relocalise(k, older)
            group = [c for c, m in sorted(matches, key=lambda cm: -cm[1]) if m > 0][:5]
        else:
            group = known[:n] + [known[i] for i in (2 * n, 4 * n) if i < len(known)]
        last = None
        for c in group:
            r = self.frontend.relative_pose(c, k)
            timings["relative_pose"] = timings.get("relative_pose", 0.0) + r.timings_ms.get("relative_pose", 0.0)
            timings["covariance"] = timings.get("covariance", 0.0) + r.timings_ms.get("covariance", 0.0)
            last = r
            if r.ok and self.filter.layout.n_poses == 1 and r.parallax_deg < sysc.init_parallax_deg:
                continue  # too narrow a baseline to initialise the map on
            if r.ok:
                return r, r
        return None, last

    def _nearest_known(self, k: int) -> list[int]:
        """Known pose ids, nearest to frame *k* first (for a new frame: most recent first)."""
        return sorted(self.filter.layout.pose_ids, key=lambda c: (abs(c - k), -c))

    def _localise_from_map(self, k: int, timings: dict) -> bool:
        """Add frame *k* from ``Zm`` of known map features alone (no usable baseline)."""
        filt = self.filter
        if filt.layout.n_poses < 2 or filt.layout.n_features == 0:
            return False
        t0 = time.perf_counter()
        ids, uv = self.frontend.map_observations(k)
        known = filt.layout.has_features(ids)
        if known.sum() < 12:
            return False
        X = filt.x[filt.layout.feature_columns(ids[known])]
        p0, q0 = filt.pose(self._nearest_known(k)[0])
        sol = localise_pose(self.camera, p0, q0, X, uv[known])
        if sol is None:
            return False
        p, q, _ = sol
        self._reobserve(k, p, q)
        filt.add_pose(k, p, q)
        self._fuse_map_and_recover(k, t0, timings)
        return True

    def _reobserve(self, k: int, p: Array, q: Array) -> int:
        """Find map features that tracking lost again in frame *k*, by projecting them
        with the pose guess ``(p, q)`` and matching descriptors nearby
        (:meth:`FrontEnd.reobserve`); returns how many were found."""
        r = self.config.reobserve_px
        filt = self.filter
        if not r or filt.layout.n_features == 0:
            return 0
        fids, X = filt.features()
        fids = np.asarray(fids, np.int64)
        seen, _ = self.frontend.map_observations(k)
        cand = ~np.isin(fids, seen)
        if not cand.any():
            return 0
        fids, X = fids[cand], X[cand]
        c = self.camera
        h, z = _project(c, p, q, X)
        vis = (z > filt.config.min_depth) & np.all(np.isfinite(h), 1) & (h[:, 0] >= 0) & (h[:, 1] >= 0) \
            & (h[:, 0] <= c.width - 1) & (h[:, 1] <= c.height - 1)
        if not vis.any():
            return 0
        return self.frontend.reobserve(k, fids[vis], h[vis], r)

    def _fuse_map_and_recover(self, k: int, t0: float, timings: dict) -> None:
        """Algorithm 1 steps 3-5 for a frame whose pose is in the state: new features,
        fuse every ``Zm``, recover; ``t0`` is when initialisation started."""
        ids, uv = self._record_map_observations(k)
        batch = self._new_features(k, ids, uv)
        t1 = time.perf_counter()
        self.filter.fuse_features(batch)
        t2 = time.perf_counter()
        self.filter.recover_active()
        t3 = time.perf_counter()
        timings.update(init=1e3 * (t1 - t0), fuse=1e3 * (t2 - t1), recover=1e3 * (t3 - t2))

    def _record_map_observations(self, k: int) -> tuple[NDArray[np.int64], Array]:
        ids, uv = self.frontend.map_observations(k)
        ff = self.frontend.frame(k)
        col = dict(zip(ff.track_ids.tolist(), ff.colors))
        for t, u in zip(ids.tolist(), uv):
            self._track_obs.setdefault(t, []).append((k, u))
            if t not in self._colors and t in col:
                self._colors[t] = np.asarray(col[t], np.uint8)
        return ids, uv

    def _localise_and_fuse(self, k: int, rpr: RelativePoseResult, timings: dict) -> None:
        """Algorithm 1: initial guesses, augment with zeros, fuse, recover."""
        filt, sysc = self.filter, self.config.system
        rp = rpr.measurement
        t0 = time.perf_counter()
        ids, uv = self.frontend.map_observations(k)
        known = filt.layout.has_features(ids)
        Xk = filt.x[filt.layout.feature_columns(ids[known])] if known.any() else np.zeros((0, 3))
        p_i, q_i = filt.pose(rp.i)
        first_step = filt.layout.n_poses == 1
        init = pose_from_relative(p_i, q_i, rp, self.camera, Xk, uv[known],
                                  default_step=sysc.scale_distance if first_step else self._last_step)
        p_k, q_k, step = init
        use_relative, refined = True, False
        if known.sum() >= 12:  # a better linearisation point: refine on the known map
            sol = localise_pose(self.camera, p_k, q_k, Xk, uv[known])
            frac = sol[2].mean() if sol is not None else 0.0
            if sol is not None and _agrees(p_i, p_k, q_k, sol, max_rot_deg=2.0, max_dir_deg=10.0):
                p_k, q_k, refined = sol[0], sol[1], frac >= 0.7
            elif sol is not None and frac > 1.5 * _inlier_fraction(self.camera, p_k, q_k, Xk, uv[known]):
                # the map contradicts this relative pose: trust the map, drop the ZR/ZT
                p_k, q_k, use_relative = sol[0], sol[1], False
                self.rejected_relative.append(rp)
            elif sol is not None and frac >= 0.7:
                # the map fits well where the relative pose points elsewhere (on a short
                # baseline both guesses fit the map): linearise at the map's pose and let
                # the chi-square gate below decide on the ZR/ZT
                p_k, q_k, refined = sol[0], sol[1], True
        self._reobserve(k, p_k, q_k)
        filt.add_pose(k, p_k, q_k)
        if first_step:
            filt.set_scale(rp.i, k, sysc.scale_distance)
        self._last_step = step if step > 0 else self._last_step
        if use_relative and refined and sysc.relative_gate_chi2 is not None:
            # ZR/ZT against the pose the map supports: an inconsistent one is not fused
            _, _, W, innov = filt.linearise_relative([rp])
            if float(innov[0] @ W[0] @ innov[0]) > sysc.relative_gate_chi2:
                use_relative = False
                self.rejected_relative.append(rp)
        if use_relative:
            filt.fuse_relative([rp])
        self._fuse_map_and_recover(k, t0, timings)

    def _new_features(self, k: int, ids: NDArray[np.int64], uv: Array) -> FeatureObservations:
        """``Zm`` of frame *k* for known features, plus every observation of features that
        can now be triangulated (Algorithm 1 step 3)."""
        filt, sysc = self.filter, self.config.system
        known = filt.layout.has_features(ids)
        p_k, q_k = filt.pose(k)
        poses, feats, uvs = [np.full(int(known.sum()), k)], [ids[known]], [uv[known]]
        new_ids, new_X = [], []
        # first observation from a known pose of every unknown track, grouped by that pose
        cand: dict[int, list[tuple[int, Array, Array, list]]] = {}
        for t, u in zip(ids[~known].tolist(), uv[~known]):
            hist = [(j, v) for j, v in self._track_obs.get(t, []) if j != k and filt.layout.has_pose(j)]
            if hist:
                cand.setdefault(hist[0][0], []).append((t, hist[0][1], u, hist))
        tri: list[tuple[int, Array, NDArray[np.int64], Array]] = []  # (track, X, frames, uv)
        for j, items in cand.items():
            p_j, q_j = filt.pose(j)
            uv_j = np.array([it[1] for it in items])
            uv_k = np.array([it[2] for it in items])
            X, par, ok = triangulate(p_j, q_j, uv_j, p_k, q_k, uv_k, self.camera)
            for (t, _, u, hist), Xt, good in zip(items, X, ok & (par >= sysc.feature_parallax_deg)):
                if good:
                    tri.append((t, Xt, np.array([jj for jj, _ in hist] + [k]), np.array([vv for _, vv in hist] + [u])))
        if tri:
            counts = np.array([len(fr) for _, _, fr, _ in tri])
            fits_all = self._fits(np.repeat(np.array([X for _, X, _, _ in tri]), counts, axis=0),
                                  np.concatenate([fr for _, _, fr, _ in tri]),
                                  np.concatenate([z for _, _, _, z in tri]))
            for (t, Xt, fr, zs), fits in zip(tri, np.split(fits_all, np.cumsum(counts)[:-1])):
                if not (fits[0] and fits[-1]):
                    # the triangulating pair itself fails the gate: the feature would
                    # enter with single-view (rank-2) information; leave it out
                    continue
                new_ids.append(t)
                new_X.append(Xt)
                poses.append(fr[fits])
                feats.append(np.full(int(fits.sum()), t))
                uvs.append(zs[fits])
        if new_ids:
            filt.add_features(new_ids, np.array(new_X))
        return FeatureObservations.make(np.concatenate(poses), np.concatenate(feats),
                                        np.concatenate(uvs).reshape(-1, 2), self.config.zm_sigma_px)

    def _fits(self, X: Array, frames: NDArray[np.int64], uv: Array) -> NDArray[np.bool_]:
        """Which observations ``uv`` (N, 2) from poses ``frames`` (N,) of points ``X``
        (N, 3) pass the filter's gate (in front of the camera, normalised innovation
        squared within ``gate_chi2``): the ones :meth:`InformationFilter.fuse_features`
        would take."""
        filt = self.filter
        cols = filt.layout.pose_columns(frames)
        h, z = _project(self.camera, filt.x[cols[:, :3]], filt.x[cols[:, 3:]], np.asarray(X, float).reshape(-1, 3))
        chi2 = np.sum((uv - h) ** 2, 1) / self.config.zm_sigma_px**2
        ok = (z > filt.config.min_depth) & np.isfinite(chi2)
        if filt.config.gate_chi2 is not None:
            ok &= chi2 <= filt.config.gate_chi2
        return ok

    # -- after the run ------------------------------------------------------------
    def smooth(self, max_passes: int | None = None) -> SmoothingReport:
        """Relinearise every stored measurement and recover (paper III-E)."""
        if self.filter.layout.n_poses < 2:
            raise EifslamError("nothing to smooth: fewer than two poses are tracked")
        self.filter.complete_estimate()
        sysc = self.config.system
        gates = dict(feature_chi2=self.filter.config.gate_chi2, relative_chi2=sysc.relative_gate_chi2) \
            if sysc.robust_smoothing else {}
        self.smoothing = smooth(self.filter, max_passes or sysc.smooth_passes, **gates)
        return self.smoothing

    def set_scale(self, a: tuple[str, int], b: tuple[str, int], length: float) -> float:
        """Scale recovery (paper V): make the distance between two states ``length``."""
        return recover_scale(self.filter, a, b, length)

    # -- sessions -----------------------------------------------------------------
    def save(self, path: str | Path) -> None:
        """Save the whole session (filter, front end, results) to a file."""
        fe, filt = self.frontend, self.filter
        inc = filt.incremental
        filt.complete_estimate()  # every state at the solution, so the window can be dropped
        detector, matcher, factor = fe._detector, fe._matcher, filt._factor
        fe._detector = fe._matcher = None
        filt._factor = None  # factorisations (SuperLU) do not pickle; rebuilt on demand
        saved_inc = None
        if inc is not None:  # the window's conditionals hold factorisations: rebuild after load
            saved_inc = inc.__dict__.copy()
            inc.on_invalidate()
            inc._conds = []
        try:
            with open(path, "wb") as fh:
                pickle.dump({"version": 1, "slam": self}, fh, protocol=pickle.HIGHEST_PROTOCOL)
        except (OSError, TypeError, pickle.PicklingError) as exc:
            raise EifslamError(f"cannot save session to {path}: {exc}") from exc
        finally:
            fe._detector, fe._matcher, filt._factor = detector, matcher, factor
            if saved_inc is not None:
                inc.__dict__.update(saved_inc)

    @staticmethod
    def load(path: str | Path) -> "Slam":
        """Load a session saved by :meth:`save`."""
        from ..frontend.features import make_detector
        from ..frontend.matching import DescriptorMatcher

        try:
            with open(path, "rb") as fh:
                blob = pickle.load(fh)
        except (OSError, pickle.UnpicklingError, EOFError) as exc:
            raise EifslamError(f"cannot load session {path}: {exc}") from exc
        if not isinstance(blob, dict) or blob.get("version") != 1:
            raise EifslamError(f"{path} is not an eifslam session file")
        slam: Slam = blob["slam"]
        if not hasattr(slam, "_waiting"):  # saved by an older version
            slam._waiting = []
        if not hasattr(slam.frontend, "_last_frame"):  # ... without re-observation records
            slam.frontend._last_frame = np.full(len(slam.frontend._tracks), -1, np.int64)
            slam.frontend._last_kp = np.full(len(slam.frontend._tracks), -1, np.int64)
        cfg = slam.config.frontend
        slam.frontend._detector = make_detector(cfg)
        slam.frontend._matcher = DescriptorMatcher(cfg.ratio, cfg.mutual)
        return slam
