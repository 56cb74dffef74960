"""Local mapping: the map side of Algorithm 1 (:func:`~.algorithm1.algorithm1`).

The :class:`Mapper` records each frame's map observations (``Zm``) per track, finds map
features that tracking lost again (re-observation), computes the initial guesses of new
map features whose observations pass the filter's gate (step 3,
:meth:`Mapper.triangulate_new`) and recovers the state after fusion (step 5). It owns the
per-track observation history and the feature colours; it talks to the front end and the
filter through their public methods only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..estimation.initialisation import refine_points, triangulate
from ..estimation.measurements import FeatureObservations
from ..estimation.statedict import take, take_ids
from ..geometry.camera import PinholeCamera
from ..geometry.rotations import quat_normalize
from .config import SlamConfig
from .observations import TrackObservations

Array = NDArray[np.float64]

__all__ = ["Mapper", "NewFeatures", "project"]

_GREY = np.array([200, 200, 200], np.uint8)

#: Keyframes whose marginalised states are back-substituted after each recovery: what
#: tracking reads (the features in view, the poses that first saw them) is exact, at a cost
#: that does not grow with the map; older states keep their values until the next complete
#: back substitution (loop verification, the end of the run).
RECENT_STEPS = 30

#: The ``Zm`` of features outside the local map wait (:meth:`Mapper.fuse_zm`) until a loop is
#: fused (its recovery solves the whole state anyway), or at most this many keyframes ...
DEFER_KEYFRAMES = 30

#: ... or this fraction of the keyframes in the state, whichever is more. Fusing them costs a
#: solve of the whole state, ``O(n)``; waiting a fixed fraction of the keyframes makes its
#: share of a keyframe's cost bounded whatever the map's size, as a growing array that
#: doubles its capacity has a bounded cost per element.
DEFER_FRACTION = 0.1


def project(camera: PinholeCamera, p: Array, q: Array, X: Array) -> tuple[Array, Array]:
    """Pixels and depths of world points seen from poses (the ``Zm`` model).

    Parameters
    ----------
    camera : PinholeCamera
    p : (3,) or (N, 3) camera centres.
    q : (4,) or (N, 4) orientations ``q_wc``.
    X : (N, 3) world points.

    Returns
    -------
    h : (N, 2) pixels.
    z : (N,) depths.
    """
    from ..geometry.models import feature_model, feature_model_one_pose

    c = camera
    if np.ndim(p) == 1 and np.ndim(q) == 1:
        h, _, _, z = feature_model_one_pose(p, q, X, c.fx, c.fy, c.cx, c.cy)
    else:
        N = len(X)
        h, _, _, z = feature_model(np.broadcast_to(p, (N, 3)), np.broadcast_to(q, (N, 4)), X, c.fx, c.fy, c.cx, c.cy)
    return h, z


@dataclass(frozen=True)
class NewFeatures:
    """Algorithm 1 step 3 for one frame: the new map features and the ``Zm`` step 5 fuses.

    Attributes
    ----------
    ids : (F,) int64 track ids of the new features.
    X : (F, 3) their initial guesses, world frame.
    zm : FeatureObservations
        The frame's ``Zm`` of known features and every view of the new ones that passes
        the gate.
    """

    ids: NDArray[np.int64]
    X: Array
    zm: FeatureObservations


class Mapper:
    """Map maintenance for a :class:`~eifslam.system.slam.Slam` (ORB-SLAM's LocalMapping).

    Parameters
    ----------
    camera : PinholeCamera
    config : SlamConfig
    frontend : object
        The front end (:class:`~eifslam.frontend.FrontEnd` or a stand-in with the same
        methods).
    backend : object
        The estimator (:class:`~eifslam.estimation.filter.InformationFilter`).
    """

    def __init__(self, camera: PinholeCamera, config: SlamConfig, frontend, backend) -> None:
        self.camera = camera
        self.config = config
        self.frontend = frontend
        self.filter = backend
        self._obs = TrackObservations()  # every keyframe's map observations, per track
        self._colors = np.zeros((0, 3), np.uint8)  # per track id: its first colour
        self._colored = np.zeros(0, bool)  # ... and whether it has one
        self._deferred: list[FeatureObservations] = []  # Zm of features older than the local map
        self._deferred_for = 0  # keyframes the oldest of them has waited

    # -- sessions -----------------------------------------------------------------
    def state_dict(self) -> dict:
        """What a session keeps: every recorded observation (track, frame, pixel; per
        track in recording order) and the feature colours."""
        tracks, frames, uv = self._obs.arrays()
        ci = np.flatnonzero(self._colored)
        return {"obs_track": tracks, "obs_frame": frames, "obs_uv": uv,
                "color_ids": ci.astype(np.int64), "colors": self._colors[ci].copy()}

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict`, checked (:class:`~eifslam.errors.SessionError`)."""
        tr = take_ids(d, "obs_track")
        fr, uv = take_ids(d, "obs_frame", len(tr)), take(d, "obs_uv", np.float64, (len(tr), 2))
        ci = take_ids(d, "color_ids")
        col = take(d, "colors", np.uint8, (len(ci), 3))
        self._obs = TrackObservations.from_arrays(tr, fr, uv)
        n = int(ci.max()) + 1 if len(ci) else 0
        self._colors, self._colored = np.zeros((n, 3), np.uint8), np.zeros(n, bool)
        self._colors[ci], self._colored[ci] = col, True

    # -- queries ------------------------------------------------------------------
    def colors(self, track_ids) -> NDArray[np.uint8]:
        """RGB colours ``(F, 3)`` of map features (grey for a feature never coloured)."""
        ids = np.asarray(track_ids, np.int64).reshape(-1)
        out = np.tile(_GREY, (len(ids), 1))
        inside = np.flatnonzero((ids >= 0) & (ids < len(self._colored)))
        has = inside[self._colored[ids[inside]]]
        out[has] = self._colors[ids[has]]
        return out

    def covisible(self, track_ids) -> dict[int, int]:
        """Frames that observed any of the given tracks (recorded map observations), with
        how many of the tracks each observed: the covisibility of a frame's map tracks."""
        return self._obs.covisible(np.unique(np.asarray(track_ids, np.int64).reshape(-1)))

    def record_loop(self, k: int, track_ids, uv: Array) -> None:
        """Record the ``Zm`` a verified loop fused into frame *k* (old map features, found
        by place recognition rather than tracking) as observations of frame *k*, so that
        :meth:`covisible` joins the frame with the place it closed the loop with.

        Parameters
        ----------
        k : int
            The loop's current frame (a pose of the filter).
        track_ids : (M,) int
            The old map features fused.
        uv : (M, 2)
            Their pixels in frame *k* (undistorted).
        """
        self._obs.add(int(k), np.asarray(track_ids, np.int64).reshape(-1), np.asarray(uv, float).reshape(-1, 2),
                      only_new=True)

    def forget_frame(self, k: int) -> None:
        """Take back :meth:`record_observations` of frame *k* (a world frame that moved on
        before the map existed)."""
        ids, _ = self.frontend.map_observations(k)
        self._obs.forget(int(k), np.asarray(ids, np.int64).reshape(-1))

    def forget_loop(self, k: int, track_ids) -> None:
        """Take back :meth:`record_loop`: frame *k* no longer observes the old map features
        ``track_ids (M,)`` (a loop taken back)."""
        self._obs.forget(int(k), np.asarray(track_ids, np.int64).reshape(-1))

    # -- per frame ----------------------------------------------------------------
    def record_observations(self, k: int) -> tuple[NDArray[np.int64], Array]:
        """Store frame *k*'s map observations per track (and first colours); return the
        frame's ``Zm``: track ids ``(M,)`` and pixels ``(M, 2)``."""
        ids, uv = self.frontend.map_observations(k)
        self._obs.add(int(k), ids, uv)
        ff = self.frontend.frame(k)
        t = np.asarray(ff.track_ids, np.int64)
        ok = t >= 0
        t, c = t[ok], np.asarray(ff.colors, np.uint8)[ok]
        if len(t):
            n = max(len(self._colored), int(t.max()) + 1)
            if n > len(self._colored):
                self._colors = np.concatenate([self._colors, np.zeros((n - len(self._colors), 3), np.uint8)])
                self._colored = np.concatenate([self._colored, np.zeros(n - len(self._colored), bool)])
            first = ~self._colored[t]
            self._colors[t[first]], self._colored[t[first]] = c[first], True
        return ids, uv

    def reobserve(self, k: int, p: Array, q: Array) -> int:
        """Find map features of the local map that tracking lost again in frame *k*, by
        projecting them with the pose guess ``(p, q)`` and matching descriptors nearby
        (:meth:`FrontEnd.reobserve`); returns how many were found.

        The local map is the features measured in the last :data:`RECENT_STEPS` keyframes
        (:meth:`InformationFilter.local_map`), whose estimate the recent
        back-substitution keeps exact; those of them the recovery has marginalised have
        their ``Zm`` wait (:meth:`fuse_zm`). An older feature seen again (a revisit) is the
        loop closer's to find."""
        r = self.config.reobserve_px
        filt = self.filter
        if not r or filt.layout.n_features == 0:
            return 0
        fids, X = filt.local_map(RECENT_STEPS)
        seen, _ = self.frontend.map_observations(k)
        cand = ~np.isin(fids, seen)
        if not cand.any():
            return 0
        fids, X = fids[cand], X[cand]
        c = self.camera
        h, z = project(c, p, q, X)
        vis = (z > filt.config.min_depth) & np.all(np.isfinite(h), 1) & (h[:, 0] >= 0) & (h[:, 1] >= 0) \
            & (h[:, 0] <= c.width - 1) & (h[:, 1] <= c.height - 1)
        if not vis.any():
            return 0
        return self.frontend.reobserve(k, fids[vis], h[vis], r)

    def fuse_zm(self, zm: FeatureObservations) -> FeatureObservations:
        """Algorithm 1 step 5's ``Zm``: they are fused now, except those of features the
        recovery has marginalised when taking them back would cost a solve of the whole
        state (:meth:`InformationFilter.affordable_features`): those wait
        (:meth:`flush_deferred`).

        Fusing a measurement of a state the recovery has marginalised makes it take the
        marginalisation back: cheap for a feature marginalised a few keyframes ago (it is
        re-activated), a rebuild of the window for one of a lap ago; on a revisit every
        keyframe sees more of them. Waiting changes only when
        they enter: a measurement is linearised when it is fused, and the information
        form is a sum. They are fused together (one solve for the lot) with the next loop,
        after :data:`DEFER_KEYFRAMES` keyframes or :data:`DEFER_FRACTION` of the state's
        keyframes if no loop comes, before a session is saved and at the end of the run.
        Returns the ``Zm`` fused now."""
        recent = self.filter.recent_features(zm.feature)
        if not np.all(recent) and not self.filter.affordable_features(zm.feature[~recent]):
            self._deferred.append(zm.subset(~recent))
            zm = zm.subset(recent)
        return self.filter.fuse_features(zm)

    @property
    def deferred(self) -> int:
        """How many ``Zm`` wait to be fused (:meth:`fuse_zm`)."""
        return sum(len(b) for b in self._deferred)

    def deferred_features(self) -> NDArray[np.int64]:
        """Track ids of the map features whose ``Zm`` wait (:meth:`fuse_zm`), sorted."""
        if not self._deferred:
            return np.zeros(0, np.int64)
        return np.unique(np.concatenate([np.asarray(b.feature, np.int64) for b in self._deferred]))

    def flush_deferred(self) -> int:
        """Fuse the ``Zm`` that waited (:meth:`fuse_zm`); returns how many were fused.

        They are fused as late measurements: the old features they measure stay out of the
        recovery's window (their later ``Zm`` wait again), so that the window keeps the
        states of the local map only and its cost does not grow on a revisit."""
        if not self._deferred:
            return 0
        zm = FeatureObservations.concatenate(self._deferred)
        self._deferred, self._deferred_for = [], 0
        return len(self.filter.fuse_features(zm, recent=False))

    def recover(self) -> None:
        """Recover the state after fusing: the active window, then the states marginalised
        in the last :data:`RECENT_STEPS` keyframes (their back substitution).

        The states outside the recovery window keep the values they had when they left it
        unless back-substituted, and tracking reads them (localisation on the map,
        re-observation, triangulation from the poses that first saw a track), so the
        recent ones are made exact each keyframe. Back-substituting every state would cost
        ``O(n)`` a keyframe; the older states are brought up to date where the whole
        estimate is read (:meth:`InformationFilter.complete_estimate`)."""
        if self._deferred:
            self._deferred_for += 1
            if self._deferred_for >= max(DEFER_KEYFRAMES, DEFER_FRACTION * self.filter.layout.n_poses):
                self.flush_deferred()
        self.filter.recover_active()
        self.filter.recent_estimate(RECENT_STEPS)

    def triangulate_new(self, k: int, ids: NDArray[np.int64], uv: Array, p_k: Array, q_k: Array) -> NewFeatures:
        """Algorithm 1 step 3: initial guesses of the map features frame *k* makes
        triangulable, from the initial guess of its pose, before anything enters the state.

        A track of ``Zm`` becomes a feature when its first observation from a known pose
        and frame *k*'s rays differ by ``MappingConfig.feature_parallax_deg``; the two-view
        midpoint is refined on every view of the track with the poses held fixed (every
        one of those observations is linearised there for good), and the feature is left
        out when one of its two triangulating observations fails the ``Zm`` gate
        (:meth:`fits`: it would enter with single-view, rank-2 information).

        Parameters
        ----------
        k : int
            The frame (not a pose of the state yet).
        ids, uv : (M,) int, (M, 2)
            Its ``Zm``: track ids and pixels (:meth:`record_observations`).
        p_k, q_k : (3,), (4,)
            The initial guess of its pose (``q_wc``), as given to ``add_pose``.

        Returns
        -------
        NewFeatures
            The new features and every ``Zm`` step 5 fuses: frame *k*'s of known features,
            and each view of a new feature that passes the gate.
        """
        filt, cfg = self.filter, self.config
        # pose k as the state will hold it (add_pose normalises q) and read it back
        p_k, q_held = np.asarray(p_k, float), quat_normalize(np.asarray(q_k, float))
        q_k = quat_normalize(q_held)
        known = filt.layout.has_features(ids)
        poses, feats, uvs = [np.full(int(known.sum()), k)], [ids[known]], [uv[known]]
        new_ids, new_X = [], []
        # first observation from a known pose of every unknown track, grouped by that pose
        unknown, uv_unknown = ids[~known], uv[~known]
        owner, rows = self._obs.rows_of(unknown)  # each unknown track's history, in order
        hf = self._obs.frames(rows)
        posed = np.isin(hf, np.asarray(filt.layout.pose_ids, np.int64)) & (hf != k)
        owner, rows, hf = owner[posed], rows[posed], hf[posed]
        hu = self._obs.pixels(rows)
        starts = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]]) if len(owner) else np.zeros(0, np.int64)
        ends = np.r_[starts[1:], len(owner)]
        cand: dict[int, list[tuple[int, Array, Array, tuple[int, int]]]] = {}
        for a, b in zip(starts.tolist(), ends.tolist()):
            n = int(owner[a])
            # the first observation from a known pose of the track, grouped by that pose
            cand.setdefault(int(hf[a]), []).append((int(unknown[n]), hu[a], uv_unknown[n], (a, b)))
        tri: list[tuple[int, Array, NDArray[np.int64], Array]] = []  # (track, X, frames, uv)
        for j, items in cand.items():
            p_j, q_j = filt.pose(j)
            uv_j = np.array([it[1] for it in items])
            uv_k = np.array([it[2] for it in items])
            X, par, ok = triangulate(p_j, q_j, uv_j, p_k, q_k, uv_k, self.camera)
            for (t, _, u, (a, b)), Xt, good in zip(items, X, ok & (par >= cfg.mapping.feature_parallax_deg)):
                if good:
                    tri.append((t, Xt, np.append(hf[a:b], k), np.vstack([hu[a:b], u[None]])))
        if tri:
            counts = np.array([len(fr) for _, _, fr, _ in tri])
            frames = np.concatenate([fr for _, _, fr, _ in tri])
            zs_all = np.concatenate([z for _, _, _, z in tri])
            P, Q = self._poses_of(frames, k, p_k, q_held)
            # the first estimate every view of the feature will be linearised at: the best
            # point those views give for the current poses, not the two-view midpoint
            X_ref, front = refine_points(np.array([X for _, X, _, _ in tri]), np.repeat(np.arange(len(tri)), counts),
                                         P, Q, zs_all, self.camera)
            tri = [(t, X_ref[n] if front[n] else X, fr, z) for n, (t, X, fr, z) in enumerate(tri)]
            fits_all = self.fits(np.repeat(np.array([X for _, X, _, _ in tri]), counts, axis=0), P, Q, zs_all)
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
        zm = FeatureObservations.make(np.concatenate(poses), np.concatenate(feats),
                                      np.concatenate(uvs).reshape(-1, 2), self.config.zm_sigma_px)
        return NewFeatures(np.array(new_ids, np.int64), np.array(new_X, float).reshape(-1, 3), zm)

    def _poses_of(self, frames: NDArray[np.int64], k: int, p_k: Array, q_k: Array) -> tuple[Array, Array]:
        """Positions ``(N, 3)`` and orientations ``(N, 4)`` of the poses ``frames`` as the
        state holds them, frame *k* (not in the state yet) at ``(p_k, q_k)``."""
        x, old = self.filter.x, frames != k
        P, Q = np.empty((len(frames), 3)), np.empty((len(frames), 4))
        if old.any():
            cols = self.filter.layout.pose_columns(frames[old])
            P[old], Q[old] = x[cols[:, :3]], x[cols[:, 3:]]
        P[~old], Q[~old] = p_k, q_k
        return P, Q

    def fits(self, X: Array, p: Array, q: Array, uv: Array) -> NDArray[np.bool_]:
        """Which observations pass the filter's gate.

        Parameters
        ----------
        X : (N, 3) points.
        p, q : (N, 3), (N, 4) the observing poses (centres, ``q_wc`` as the state holds them).
        uv : (N, 2) measured pixels.

        Returns
        -------
        (N,) bool
            In front of the camera and normalised innovation squared within the filter's
            ``gate_chi2``: the observations :meth:`InformationFilter.fuse_features` would take.
        """
        filt = self.filter
        h, z = project(self.camera, p, q, np.asarray(X, float).reshape(-1, 3))
        chi2 = np.sum((uv - h) ** 2, 1) / self.config.zm_sigma_px**2
        ok = (z > filt.config.min_depth) & np.isfinite(chi2)
        if filt.config.gate_chi2 is not None:
            ok &= chi2 <= filt.config.gate_chi2
        return ok
