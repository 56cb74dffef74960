"""Loop closure: place recognition, geometric verification and fusion into the EIF.

For each frame that became a state of the filter, the :class:`LoopCloser`

1. indexes the frame's descriptors in a bag of visual words
   (:class:`~eifslam.frontend.places.PlaceIndex`);
2. looks for candidate places among the frames *older than every frame its place is
   already joined with* (:meth:`LoopCloser._joined`: the frames that share at least
   ``loop_min_inliers`` map tracks with it, and through a loop frame among them the old
   place that loop joined; the exclusion is the frame's covisibility, not a fixed count
   of frames; a few long tracks do not join two places), whose
   similarity reaches the lowest similarity of the frame to its strongly covisible
   frames (those sharing at least ``loop_min_inliers`` map tracks; ORB-SLAM's rule);
   a candidate whose own place reaches a frame as recent as the current place's oldest
   is already joined to the trajectory (no new loop);
3. keeps a candidate only when its place (the span of frames covisible with it) came back
   in ``loop_consistency`` consecutive queries;
4. verifies it geometrically (:func:`~eifslam.frontend.loop_verification.verify_place`:
   PnP on the old map features seen around the candidate and a five-point check with the
   candidate frame (or, when the candidate's view is too far from this one for enough
   direct matches, with the old frame that observes the most PnP inliers), both with
   chance-derived inlier counts, and the five-point rotation
   within ``agree_rotation_deg`` of the rotation the PnP implies when the baseline has
   the parallax a new feature needs);
5. fuses the PnP inliers as ``Zm`` of the *old* map features in the current pose, not
   gated (after drift the filter is overconfident about where it is: the loop is trusted
   on its geometric verification alone). When the estimate does not predict them (median
   normalised innovation above the 99% bound) and ``loop_smooth_passes`` > 0, the
   estimate is first moved along the loop
   (:func:`~eifslam.estimation.loop_correction.correct_loop`) and every stored
   measurement is relinearised there after the fusion
   (:func:`~eifslam.estimation.loop_correction.relinearise_all`); otherwise it recovers;
6. merges the tracks of the inlier keypoints that are not map features yet into the old
   features' tracks (:meth:`FrontEnd.join_tracks`), so that the following frames observe
   the old features through ordinary tracking (their ``Zm`` gated as usual). Keypoints
   whose tracks are already map features keep them: the filter does not merge two
   feature states, so a place mapped twice keeps both copies, each with its own ``Zm``.

Sparsity: each loop ``Zm`` couples the current pose with one old feature, so ``I`` gains
exactly the pose-feature blocks of the verified inliers (nothing else fills in). Over the
poses alone (features eliminated) the current pose becomes linked to every pose that saw
those features, which is what moves the whole loop.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ..estimation.measurements import FeatureObservations
from ..estimation.statedict import sub, take
from ..frontend.places import PlaceIndex
from ..geometry.camera import PinholeCamera
from ..geometry.rotations import quat_conjugate, quat_multiply, quat_to_rotmat
from .config import SlamConfig

if TYPE_CHECKING:  # imported where used: the front end's verification needs OpenCV
    from ..frontend.loop_verification import FivePoint

Array = NDArray[np.float64]

__all__ = ["FusedLoop", "LoopCloser", "LoopClosure", "most_observing"]


@dataclass
class LoopClosure:
    """One verified and fused loop (frame ids are input-frame indices).

    Attributes
    ----------
    frame, matched_frame : int
        The current frame and the old frame it was recognised as.
    score : float
        Bag-of-words similarity of the two.
    matches, inliers, required : int
        Descriptor matches to old map features, PnP inliers, inliers required.
    five_point_inliers, five_point_required : int
    fused : int
        ``Zm`` of old features fused into the current pose.
    correction_m, correction_deg : float
        How far the PnP pose lies from the filter's pose of the frame before fusion.
    """

    frame: int
    matched_frame: int
    score: float
    matches: int
    inliers: int
    required: int
    five_point_inliers: int
    five_point_required: int
    fused: int
    correction_m: float
    correction_deg: float

    def to_dict(self) -> dict:
        """Plain JSON values."""
        return {k: (float(v) if isinstance(v, float) else int(v)) for k, v in asdict(self).items()}


_FIELDS = [f for f in LoopClosure.__dataclass_fields__]

CHI2_2DOF_99 = 9.21
"""99% quantile of chi-square with 2 degrees of freedom (a pixel residual)."""

MAX_DRIFT_FRACTION = 0.5
"""A loop may correct the current position by at most this fraction of the path travelled
since the old frame: a monocular estimate that drifts half the distance it travels is lost,
not drifting; a copy of a place further away than that is another place."""

AGREEMENT_FALSE_ALARM = 1e-3
"""Probability that the agreement tests of a loop with the estimate refuse a true loop whose
covariances are honest (:meth:`LoopCloser._disagreement`)."""


@dataclass
class PendingLoop:
    """A verified loop held until consecutive keyframes confirm it: frame, old frame, its
    loop pose ``p (3,)``, ``q (4,)`` with covariance ``(6, 6)``, and how many consecutive
    keyframes agreed so far."""

    frame: int
    old: int
    p: Array
    q: Array
    covariance: Array
    count: int


CHECK_KEYFRAMES = 3
"""Keyframes after a loop's own whose estimate must still agree with it (:meth:`LoopCloser.check`);
the loop's own keyframe tests it right after its fusion too."""


@dataclass
class FusedLoop:
    """What a fused loop added to the filter, so that it can be taken back.

    Attributes
    ----------
    closure : LoopClosure
    obs : FeatureObservations
        The loop's ``Zm`` (old map features in frame ``closure.frame``), as stored.
    idx, Lam, eta : (N, 10) int, (N, 10, 10), (N, 10) float or None
        What the fusion added to ``I`` and ``i`` (None when the fusion was followed by a
        relinearisation of every measurement: ``I`` was rebuilt).
    generation : int
        ``info.generation`` right after the fusion: ``idx, Lam, eta`` are still in ``I``
        while it is unchanged.
    x_before : (n,)
        The complete estimate before the fusion (the state then had ``n`` entries).
    joined : (M,) int
        Old features whose tracks the loop merged with the loop frame's keypoints.
    checks : int
        Agreement checks still due (:data:`CHECK_KEYFRAMES` at first, plus the loop's own).
    """

    closure: LoopClosure
    obs: FeatureObservations
    idx: NDArray[np.int64] | None
    Lam: Array | None
    eta: Array | None
    generation: int
    x_before: Array
    joined: NDArray[np.int64]
    checks: int


_PLACE_REFUSED = ("too few old map features", "too few matches to the map", "PnP failed", "too few PnP inliers",
                  "five-point rotation disagrees with the estimate")
"""Verification failures that refuse the candidate's place as a whole (its map features, or the
rotation its view implies against the estimate)."""


def most_observing(frames, track_ids_of, features: NDArray[np.int64]) -> int | None:
    """The frame among ``frames`` whose tracks include the most of ``features``.

    Parameters
    ----------
    frames : iterable of int
        Candidate frame ids, in order (ties go to the first).
    track_ids_of : callable
        ``f -> (N,) int`` track ids observed in frame ``f``.
    features : (M,) int
        Track ids (e.g. a loop's PnP inliers).

    Returns
    -------
    int or None
        None when no frame observes any of them.
    """
    best, count = None, 0
    for f in frames:
        n = int(np.isin(track_ids_of(f), features).sum())
        if n > count:
            best, count = f, n
    return best


class LoopCloser:
    """Loop detection and fusion for a :class:`~eifslam.system.slam.Slam`.

    Parameters
    ----------
    camera : PinholeCamera
    config : SlamConfig
    frontend : object
        Needs ``descriptors``, ``frame``, ``map_observations`` and ``matcher`` (the OpenCV
        front end); a front end without descriptors (the synthetic one) has no loop closure.
    backend : object
        The estimator.
    mapper : Mapper
        For the covisibility of map tracks.
    """

    def __init__(self, camera: PinholeCamera, config: SlamConfig, frontend, backend, mapper) -> None:
        self.camera = camera
        self.config = config
        self.frontend = frontend
        self.filter = backend
        self.mapper = mapper
        cfg = config
        self.enabled = bool(cfg.loops.enabled) and callable(getattr(frontend, "descriptors", None))
        seed = config.frontend.seed if config.frontend.seed is not None else 0
        self.index = PlaceIndex(cfg.loops.words, cfg.experimental.loop_train_frames, seed=int(seed),
                               learn_lag=cfg.experimental.loop_learn_lag)
        self.closures: list[LoopClosure] = []
        self.rejected: list[tuple[int, int, str]] = []  # (frame, candidate, why) verifications that failed
        self._streak: list[tuple[int, int, int]] = []  # (lo, hi, count) places of the last query
        self._loop_tracks: dict[int, NDArray[np.int64]] = {}  # loop frame -> old features fused there
        self._pending: PendingLoop | None = None  # a loop awaiting confirmation
        self._fused: list[FusedLoop] = []  # the kept loops that can be taken back, in closures' order
        self.removed: list[tuple[LoopClosure, int, str]] = []  # (loop, frame at which it was taken back, why)

    # -- per frame ------------------------------------------------------------------
    def process(self, k: int) -> LoopClosure | None:
        """Check the loops fused in the last keyframes against the estimate (:meth:`check`),
        then seek, verify and fuse a loop for frame *k* (a pose of the filter, just fused)."""
        if self._fused and self.filter.layout.has_pose(k):
            self.check(k)
        if not self.enabled or not self.filter.layout.has_pose(k):
            return None
        desc = self.frontend.descriptors(k)
        if desc is None or len(desc) < 2 or not self.index.add(k, desc):
            return None
        covis, hop = self._place_parts(k)
        covis.pop(k, None)
        hop.discard(k)
        if not covis and not hop:
            self._streak = []
            return None
        cfg = self.config
        oldest = min(self._joined(covis, hop))
        ids = np.array(self.index.frame_ids, np.int64)
        scores = self.index.query(self.index.vector(k))
        pos = {int(f): i for i, f in enumerate(ids)}
        strong = [f for f, n in covis.items() if n >= cfg.loops.min_inliers and f in pos]
        if not strong and covis:
            strong = [max(covis)] if max(covis) in pos else []
        if not strong:
            self._streak = []
            return None
        thr = min(scores[pos[f]] for f in strong)
        cand = np.flatnonzero((ids < oldest) & (scores >= thr) & (scores > 0))
        cand = [int(i) for i in cand[np.argsort(-scores[cand], kind="stable")] if self.filter.layout.has_pose(int(ids[i]))]
        streak, best = [], None
        for i in cand[:5]:
            j = int(ids[i])
            near, hop_j = self._place_parts(j)
            if max(self._joined(near, hop_j) | {j}) >= oldest:
                # the candidate's place is already joined with a frame as recent as the
                # current place (shares loop_min_inliers map tracks with it, or an earlier
                # loop joined it to the trajectory since): this is no new loop
                continue
            # the place verified and counted: every frame covisible with the candidate
            # (their map features are what the frame is matched against), older than the
            # current place
            span = [f for f in set(near) | hop_j | {j} if f < oldest]
            lo, hi = min(span), max(span)
            n = 1 + max([c for a, b, c in self._streak if a <= hi and lo <= b], default=0)
            streak.append((lo, hi, n))
            if best is None and n >= cfg.loops.consistency:
                best = (j, float(scores[i]), lo, hi)
        self._streak = streak
        if best is None:
            return None
        n_rejected = len(self.rejected)
        lc = self._verify_and_fuse(k, *best)
        if lc is None and len(self.rejected) > n_rejected and self.rejected[-1][2].startswith(_PLACE_REFUSED):
            # a place whose map the frame does not fit must come back in loop_consistency
            # more queries before it is verified again: a place that aliases the current one
            # (repeated texture, a view from too far) is otherwise verified at every frame it
            # stays a candidate. Every candidate place of the query starts again (their
            # spans overlap in chains, so the count would pass from one to the next). (A
            # five-point refusal is about the old frame j, not the place: the next query
            # may propose another frame of it.)
            self._streak = [(a, b, 0) for a, b, _ in streak]
        return lc

    def place(self, k: int) -> dict[int, int]:
        """Frames covisible with frame *k*, with how many of *k*'s map tracks each observed.

        The tracks are those the front end has in frame *k* plus the old features a loop
        fused there (:meth:`~eifslam.system.mapping.Mapper.record_loop`). A loop joins its
        frame with the old place, so the frames that observed the features fused at a
        loop frame of this covisibility are covisible too (one hop through loop frames,
        count 0: they do not enter the score threshold). Without that hop the frames after
        a loop, which track the features of the second visit rather than the old ones,
        would find the same place again and again."""
        covis, hop = self._place_parts(k)
        for f in hop:
            covis.setdefault(f, 0)
        return covis

    def _place_parts(self, k: int) -> tuple[dict[int, int], set[int]]:
        """:meth:`place` in two parts: the frames sharing map tracks with frame *k* (with
        how many), and the frames reached through a loop frame among them (the hop)."""
        mids, _ = self.frontend.map_observations(k)
        own = self._loop_tracks.get(int(k))
        if own is not None:
            mids = np.union1d(mids, own)
        covis = self.mapper.covisible(mids)
        hop = [self._loop_tracks[f] for f in covis if f in self._loop_tracks and f != k]
        reached = set(self.mapper.covisible(np.unique(np.concatenate(hop)))) if hop else set()
        return covis, reached

    def _joined(self, covis: dict[int, int], hop: set[int]) -> set[int]:
        """The frames the map already joins with a place: those sharing at least
        ``loop_min_inliers`` map tracks with it (as many as a verified loop must have
        inliers) and those reached through a loop frame. A few long tracks re-observed
        across a revisit (SIFT keeps some over hundreds of frames) do not join two places:
        the loop they hint at still has to be found and verified. Without any such frame,
        every covisible frame counts (the cautious rule)."""
        m = self.config.loops.min_inliers
        joined = {f for f, n in covis.items() if n >= m} | hop
        return joined if joined else set(covis)

    def _verify_and_fuse(self, k: int, j: int, score: float, lo: int, hi: int) -> LoopClosure | None:
        from ..frontend.loop_verification import five_point, match_to_frame, match_to_map, verify_place
        from ..geometry.rotations import quat_conjugate, quat_log, quat_multiply, quat_to_rotmat

        filt, fe, cfg = self.filter, self.frontend, self.config
        fk, dk, dj = fe.frame(k), fe.descriptors(k), fe.descriptors(j)
        if dj is None:
            self.rejected.append((k, j, "no old frame with descriptors"))
            return None
        # the cheap tests first: the direct matches to the old frame, their count and their
        # rotation; most candidates fail here. Then the place's map, whose old
        # (marginalised) features need the complete estimate, a back substitution over the
        # whole state
        direct = match_to_frame(self.camera, fe.matcher, dk, dj, self.config.zm_sigma_px,
                                cfg.loops.min_inliers, cfg.loops.false_alarm)
        if len(direct[0]) < direct[2]:  # the five-point check would refuse it
            self.rejected.append((k, j, "too few matches to the old frame"))
            return None
        why = self._five_point_disagreement(j, k, five_point(self.camera, fk.uv, fe.frame(j).uv, direct[:2],
                                                             self.config.zm_sigma_px, cfg.loops.min_inliers,
                                                             cfg.loops.false_alarm))
        if why:
            self.rejected.append((k, j, why))
            return None
        stored = set(fe.frame_ids)
        none = np.zeros(0, np.int64)
        span = [f for f in range(lo, hi + 1)  # the old frames around the candidate, with descriptors
                if f in stored and filt.layout.has_pose(f) and fe.descriptors(f, none) is not None]
        tids = [fe.frame(f).track_ids for f in span]
        t_all = np.concatenate(tids)
        has = np.flatnonzero(filt.layout.has_features(t_all))
        fids, first = np.unique(t_all[has], return_index=True)  # one descriptor per feature: its first
        keep = ~np.isin(fids, fk.track_ids)
        if keep.sum() < cfg.loops.min_inliers:
            self.rejected.append((k, j, "too few old map features"))
            return None
        fids = fids[keep].astype(np.int64)
        # the descriptors of those keypoints alone, frame by frame (not every keypoint of the span)
        at = has[first[keep]]  # positions in t_all
        starts = np.cumsum([0] + [len(t) for t in tids])
        which = np.searchsorted(starts, at, side="right") - 1
        rows = [np.flatnonzero(which == n) for n in range(len(span))]
        D = np.concatenate([fe.descriptors(f, at[r] - starts[n]) for n, (f, r) in enumerate(zip(span, rows))])
        D = D[np.argsort(np.concatenate(rows))]  # back in the order of fids
        ia, ib, need = match_to_map(self.camera, fe.matcher, dk, D, self.config.zm_sigma_px,
                                    cfg.loops.min_inliers, cfg.loops.false_alarm)
        if len(ia) < need:
            self.rejected.append((k, j, "too few matches to the map"))
            return None
        filt.complete_estimate()
        X = np.zeros((len(fids), 3))
        X[ib] = filt.x[filt.layout.feature_columns(fids[ib])]

        def verify(f: int, direct_f: tuple[NDArray[np.int64], NDArray[np.int64]] | None = None):
            return verify_place(self.camera, fe.matcher, fk.uv, dk, X, D, fe.frame(f).uv, fe.descriptors(f),
                                self.config.zm_sigma_px, filt.pose(f)[0], quat_to_rotmat(filt.pose(f)[1]),
                                max_rot_deg=cfg.tracking.agree_rotation_deg, min_parallax_deg=cfg.mapping.feature_parallax_deg,
                                floor=cfg.loops.min_inliers, alpha=cfg.loops.false_alarm, matches=(ia, ib),
                                direct=direct_f)

        chk = verify(j, direct[:2])
        if not chk.ok and chk.reason == "too few five-point inliers":
            # the place's map fits the frame but the candidate frame's view is too far from
            # it for direct matches: the five-point check once more, with the old frame
            # that observes the most PnP inliers (the place's view nearest this one)
            seen = dict(zip(span, tids))
            partner = most_observing([f for f in span if f != j], seen.__getitem__, fids[chk.features])
            if partner is not None:
                chk2 = verify(partner)
                if chk2.ok:
                    chk, j = chk2, partner
        if not chk.ok:
            self.rejected.append((k, j, chk.reason))
            return None
        p_f, q_f = filt.pose(k)
        why = self._disagreement(j, k, chk.p, chk.q, X[chk.features])
        if why:
            self.rejected.append((k, j, why))
            return None
        dp = float(np.linalg.norm(chk.p - p_f))
        dq = float(np.degrees(np.linalg.norm(quat_log(quat_multiply(quat_conjugate(q_f), chk.q)))))
        obs = FeatureObservations.make(np.full(len(chk.keypoints), k), fids[chk.features], fk.uv[chk.keypoints],
                                       self.config.zm_sigma_px)
        lc = LoopClosure(k, j, score, chk.matches, chk.inliers, chk.required, chk.five_point_inliers,
                         chk.five_point_required, 0, dp, dq)
        # track merging: keypoints whose tracks are not map features yet continue the old
        # features' tracks, so the next frames observe the old features as usual (Zm, gated)
        free = ~filt.layout.has_features(fk.track_ids[chk.keypoints])
        fused = self.fuse(lc, obs, chk.p, chk.q, joined=fids[chk.features][free])
        fe.join_tracks(k, chk.keypoints[free], fids[chk.features][free])
        if len(fused) and not self.check(k, only=lc):  # the estimate with the loop contradicts it at once
            return None
        return lc

    def fuse(self, lc: LoopClosure, obs: FeatureObservations, p_m: Array, q_m: Array,
             joined: NDArray[np.int64] | None = None) -> FeatureObservations:
        """Fuse a verified loop: its ``Zm`` ``obs`` (old map features observed in frame
        ``lc.frame``), not gated, with the loop frame's pose ``(p_m, q_m)`` from the old map
        (for the loop correction). Records the loop in :attr:`closures` (``lc.fused`` set)
        with what it added, so that :meth:`remove` can take it back; ``joined``: the old
        features whose tracks the caller merges with the frame's (their later ``Zm`` come
        through the loop and leave with it).

        Returns
        -------
        FeatureObservations
            The ``Zm`` fused (those in front of the camera).
        """
        filt, cfg = self.filter, self.config
        k, j = lc.frame, lc.matched_frame
        x_before = filt.complete_estimate().copy()
        ok, idx, J, W, innov, _ = filt.linearise_features(obs, gate=False)
        obs = obs.subset(ok)
        record: tuple | None = None
        if cfg.loops.smooth_passes and not self._predicted(obs):
            # the loop's correction can be far from the linearisation point of the poses it
            # moves (on the loop world 3.8 deg and 1 m after a lap): first move the estimate as a
            # pose graph would (the correction spread along the loop), then fuse the loop and
            # relinearise every stored measurement there (paper III-E) a few Gauss-Newton
            # passes, as ORB-SLAM optimises its essential graph after a loop
            from ..estimation.loop_correction import correct_loop, relinearise_all

            info = filt.information_form()
            correct_loop(info, j, k, p_m, q_m)
            fused = info.fuse_features(obs, gate=False)
            relinearise_all(info, cfg.loops.smooth_passes)
            filt.set_from_information_form(info)
            # x is now the full solution; the incremental window is rebuilt at the next step,
            # which takes in a revisit's waiting Zm at no extra cost (Mapper.fuse_zm)
            self.mapper.flush_deferred()
        else:
            from ..estimation.factors import Linearised

            # what the fusion adds (the filter linearises the same Zm at the same x)
            Lam, eta = Linearised(idx[ok], J[ok], W[ok], innov[ok]).information(filt.x)
            record = (idx[ok], Lam, eta)
            fused = filt.fuse_features(obs, gate=False)
            self.mapper.flush_deferred()
            filt.recover_active()
        lc.fused = len(fused)
        self.closures.append(lc)
        if not len(fused):
            return fused
        # the loop's Zm are observations of frame k (covisibility): the frames after it do not
        # find the same place again (see place())
        self.mapper.record_loop(k, fused.feature, fused.uv)
        self._loop_tracks[int(k)] = np.union1d(self._loop_tracks.get(int(k), np.zeros(0, np.int64)),
                                               np.asarray(fused.feature, np.int64))
        idx_, Lam_, eta_ = record if record is not None else (None, None, None)
        self._fused.append(FusedLoop(lc, fused, idx_, Lam_, eta_, filt.info.generation, x_before,
                                     np.zeros(0, np.int64) if joined is None else np.asarray(joined, np.int64),
                                     CHECK_KEYFRAMES + 1))
        return fused

    # -- taking a loop back ---------------------------------------------------------
    def check(self, k: int, only: LoopClosure | None = None) -> bool:
        """Test the loops fused in the last :data:`CHECK_KEYFRAMES` keyframes (or ``only``)
        against the current estimate, which holds the measurements of the frames after each
        of them; take back those it contradicts (:meth:`remove`). Returns whether ``only``
        (or every loop tested) was kept.

        The test: the loop's ``Zm`` residuals at the estimate, normalised by their pixel
        noise, summed, ``D = sum_i |z_i - h_i(x)|^2 / sigma_i^2``, against the
        ``1 - AGREEMENT_FALSE_ALARM`` quantile of chi-square with ``2 n`` degrees of freedom
        (``n`` the loop's ``Zm``). Residuals of measurements the estimate has fused have
        covariance ``R - H P H^T <= R``, so ``D`` is at most chi-square with ``2 n`` degrees
        of freedom when the loop is true and the noise honest: a true loop is taken back
        with probability at most :data:`AGREEMENT_FALSE_ALARM` per test (the consistency test
        of loop clusters of Latif, Cadena and Neira's RRR). A loop the relative poses and
        map observations of the frames after it contradict is pulled away from its own
        measurements by them, and ``D`` grows with each such keyframe. A ``Zm`` behind its
        camera counts as contradicting.

        The bound holds at the minimum of the cost, not at a linearisation point far from
        it: a true loop fused where the estimate had drifted (one linearised update moves
        the states only part of the way) leaves residuals above it. So a loop over the bound
        is tested once more after relinearising every stored measurement at the estimate
        (Gauss-Newton passes of
        :func:`~eifslam.estimation.loop_correction.relinearise_all`), and taken back only
        when it is still over.
        """
        from ..estimation.agreement import chi2_quantile
        from ..estimation.loop_correction import relinearise_all

        kept = True
        for fl in list(self._fused):
            if fl.checks <= 0 or (only is not None and fl.closure is not only) or fl.closure.frame > k:
                continue
            obs = fl.obs
            bound = chi2_quantile(2 * len(obs), AGREEMENT_FALSE_ALARM) if len(obs) else np.inf
            D = self._residual(obs)
            fl.checks -= 1
            if not D <= bound:
                relinearise_all(self.filter, max(int(self.config.loops.smooth_passes), 1))
                D = self._residual(obs)
            if not D <= bound:
                self.remove(fl.closure, frame=k, why=f"the estimate after it contradicts it (residual {D:.3g} "
                                                   f"> {bound:.3g}, {2 * len(obs)} DOF)")
                kept = False
        return kept

    def _residual(self, obs: FeatureObservations) -> float:
        """``sum_i |z_i - h_i(x)|^2 / sigma_i^2`` of a loop's ``Zm`` at the current estimate
        (inf when one is behind its camera)."""
        if not len(obs):
            return 0.0
        self.filter.complete_estimate()
        return float(np.sum(self.filter.linearise_features(obs, gate=False)[5]))

    def remove(self, loop: int | LoopClosure, frame: int | None = None, why: str = "taken back by the caller"
               ) -> LoopClosure:
        """Take a fused loop back (``loop``: its index in :attr:`closures`, or the loop).

        Its ``Zm`` leave the measurement store (smoothing does not bring them back), with the
        ``Zm`` that frames after it fused on the old map features whose tracks the loop
        merged (their association came through the loop), and the loop frame stops observing the old
        place (covisibility). The information:

        * when nothing but the loop was taken out and ``I`` was not rebuilt since its
          fusion, exactly what the fusion added is subtracted (``I`` and ``i`` are sums),
          and the whole state is solved again: ``I``, ``i`` and ``x`` are those of the
          filter without the loop;
        * otherwise (the loop moved the linearisation point of every state and
          relinearised every measurement there, or later ``Zm`` go with it), the states
          that were there before the loop take back their estimate of that time, the states
          added since follow the loop frame back (the rigid motion that takes its current
          pose to its pose before the loop), and every remaining measurement is
          relinearised there (Gauss-Newton passes of
          :func:`~eifslam.estimation.loop_correction.relinearise_all`).

        Later ``Zm`` of the old features through the merged tracks fail the ``Zm`` gate
        once the estimate is back (the old features project elsewhere).

        Raises
        ------
        KeyError
            When ``loop`` names no loop this loop closer can take back.
        """
        from ..estimation.loop_correction import relinearise_all

        lc = self.closures[loop] if isinstance(loop, (int, np.integer)) else loop
        fl = next((f for f in self._fused if f.closure is lc), None)
        if fl is None:
            raise KeyError(f"no loop of frame {getattr(lc, 'frame', lc)} that can be taken back")
        filt = self.filter
        k, j = lc.frame, lc.matched_frame
        feats = np.asarray(fl.obs.feature, np.int64)
        own = {(int(f), float(u), float(v)) for f, (u, v) in zip(feats, fl.obs.uv)}

        def is_loop(b: FeatureObservations) -> NDArray[np.bool_]:
            return np.array([p == k and (int(f), float(u), float(v)) in own
                             for p, f, (u, v) in zip(b.pose, b.feature, b.uv)], bool).reshape(-1)

        def later(b: FeatureObservations) -> NDArray[np.bool_]:
            return (b.pose > k) & np.isin(b.feature, fl.joined)

        n_later = sum(int(later(b).sum()) for b in filt.store.features)
        filt.store.remove_features(lambda b: is_loop(b) | later(b))
        exact = fl.Lam is not None and n_later == 0 and filt.info.generation == fl.generation and filt.online is None
        if exact:
            filt.subtract_information(fl.idx, fl.Lam, fl.eta)
            filt.recover_rebuilt()
        else:
            filt.set_estimate(self._estimate_before(fl))
            relinearise_all(filt, max(int(self.config.loops.smooth_passes), 1))
        self.mapper.forget_loop(k, feats)
        left = np.setdiff1d(self._loop_tracks.get(int(k), np.zeros(0, np.int64)), feats)
        if len(left):
            self._loop_tracks[int(k)] = left
        else:
            self._loop_tracks.pop(int(k), None)
        self._fused.remove(fl)
        self.closures = [c for c in self.closures if c is not lc]
        self.removed.append((lc, int(k if frame is None else frame), why))
        return lc

    def _disagreement(self, j: int, k: int, p_m: Array, q_m: Array, X: Array) -> str:
        """Why a verified loop of frame *k* to the old frame *j* must not be fused yet ("" when
        it may): its pose ``(p_m, q_m)``, localised on the old map features ``X``, against
        what the estimate knows (:mod:`~eifslam.estimation.agreement`).

        1. **Rotation against the estimate.** The rotation the loop implies must agree with
           the estimate's, at the false-alarm rate :data:`AGREEMENT_FALSE_ALARM` of
           chi-square with 3 degrees of freedom, against the rotation drift the relative
           poses fused between the two frames allow (their ``ZR`` covariances summed in the
           world frame: dead reckoning, an upper bound of what the map-aided estimate can
           have drifted) plus the loop's own. A perceptual alias (the same picture on
           another wall) is seen from another direction and fails here however consistently
           it is recognised and however well its geometry fits.
        2. **Position by agreement of consecutive keyframes.** The position drift of a
           monocular estimate holds scale drift, which no fused measurement bounds (``ZT``
           is a direction), so the estimate cannot decide on a loop's position. The loop is
           held until ``loops.consistency`` consecutive keyframes have verified the same
           place with loop poses that agree with one another: the relative rotation of two
           consecutive loop poses against the estimate's relative rotation of the two
           frames (3 degrees of freedom, same rate, the rotation drift between them plus
           both loops' covariances), as ORB-SLAM asks a group of consistent keyframes
           before it corrects a loop.
        """
        from ..estimation.agreement import chi2_quantile, rotation_agreement
        from ..estimation.localisation import map_pose_covariance

        filt = self.filter
        C_m = map_pose_covariance(self.camera, p_m, q_m, X, self.config.zm_sigma_px)
        if C_m is None:
            return "the loop's pose is not determined"
        q_k = filt.pose(k)[1]
        nis_rot = rotation_agreement(q_k, q_m, self._rotation_drift(j, k), C_m[3:, 3:])
        bound = chi2_quantile(3, AGREEMENT_FALSE_ALARM)
        if not nis_rot <= bound:
            self._pending = None
            return f"rotation disagrees with the estimate (NIS {nis_rot:.3g}, 3 DOF)"
        travelled = self._path_length(j, k)
        if not float(np.linalg.norm(p_m - filt.pose(k)[0])) <= MAX_DRIFT_FRACTION * travelled:
            self._pending = None
            return (f"position disagrees with the path: a correction of {np.linalg.norm(p_m - filt.pose(k)[0]):.3g} "
                    f"after {travelled:.3g} travelled")
        pend, count = self._pending, 1
        if pend is not None and pend.frame < k and abs(pend.old - j) <= self._place_span(pend.old):
            # the loop rotation of frame k carried to frame pend.frame by the two loop poses'
            # relative rotation, against the estimate's rotation of frame k
            q_a = filt.pose(pend.frame)[1]
            q_c = quat_multiply(q_a, quat_multiply(quat_conjugate(pend.q), q_m))
            nis_pair = rotation_agreement(q_k, q_c, self._rotation_drift(pend.frame, k),
                                          C_m[3:, 3:] + pend.covariance[3:, 3:])
            count = pend.count + 1 if nis_pair <= bound else 1
        if count >= max(int(self.config.loops.consistency), 1):
            self._pending = None
            return ""
        self._pending = PendingLoop(k, j, p_m, q_m, C_m, count)
        return f"held until consecutive keyframes confirm it ({count} of {self.config.loops.consistency})"

    def _five_point_disagreement(self, j: int, k: int, five: "FivePoint") -> str:
        """Why the direct matches of frame *k* to the old frame *j* already rule the loop out
        ("" when they do not): the rotation test of :meth:`_disagreement`, made with the
        five-point relation (:class:`~eifslam.frontend.loop_verification.FivePoint`) before the
        place's map is read and matched and the PnP solved, which cost about five times as much
        (on the loop world with SIFT).

        A loop pose that passes :func:`~eifslam.frontend.loop_verification.verify_place` has
        its rotation within ``tracking.agree_rotation_deg`` (``d``) of the five-point one, so
        its normalised rotation error against the estimate is at least
        ``max(0, |phi| - d)^2 / lambda_max(C)``: ``phi`` the five-point rotation's error
        against the estimate, ``C`` the rotation drift between the two frames. When even that
        exceeds the bound of :meth:`_disagreement`, no pose the later tests accept can pass it.
        The test is made only when the inliers' parallax determines the rotation
        (``mapping.feature_parallax_deg``)."""
        from ..estimation.agreement import chi2_quantile
        from ..geometry.rotations import quat_log, rotmat_to_quat

        cfg = self.config
        if five.R_kj is None or five.parallax_deg < cfg.mapping.feature_parallax_deg:
            return ""
        filt = self.filter
        q_m = rotmat_to_quat(quat_to_rotmat(filt.pose(j)[1]) @ five.R_kj)
        phi = quat_log(quat_multiply(quat_conjugate(filt.pose(k)[1]), q_m))
        excess = max(0.0, float(np.linalg.norm(phi)) - np.radians(cfg.tracking.agree_rotation_deg))
        lam = float(np.linalg.eigvalsh(self._rotation_drift(j, k))[-1])
        nis = excess ** 2 / lam if lam > 0 else (np.inf if excess > 0 else 0.0)
        if nis > chi2_quantile(3, AGREEMENT_FALSE_ALARM):
            return f"five-point rotation disagrees with the estimate (NIS at least {nis:.3g}, 3 DOF)"
        return ""

    def _estimate_before(self, fl: FusedLoop) -> Array:
        """The estimate to relinearise at when loop ``fl`` is taken back: the states of the
        time of its fusion at their estimate then, the later ones moved rigidly with the loop
        frame from its current pose to its pose then."""
        from ..estimation.state import read_pose

        filt = self.filter
        x = filt.complete_estimate().copy()
        n0 = len(fl.x_before)
        k = fl.closure.frame
        p_b, q_b = read_pose(filt.layout, fl.x_before, k)
        p_n, q_n = filt.pose(k)
        R = quat_to_rotmat(q_b) @ quat_to_rotmat(q_n).T  # current world to the world before
        dq = quat_multiply(q_b, quat_conjugate(q_n))
        new_poses = [f for f in filt.layout.pose_ids if filt.layout.pose_columns([f])[0, 0] >= n0]
        if new_poses:
            c = filt.layout.pose_columns(new_poses)
            x[c[:, :3]] = (x[c[:, :3]] - p_n) @ R.T + p_b
            x[c[:, 3:]] = quat_multiply(dq[None], x[c[:, 3:]])
        fids = np.asarray(filt.layout.feature_ids, np.int64)
        if len(fids):
            c = filt.layout.feature_columns(fids)
            c = c[c[:, 0] >= n0]
            x[c] = (x[c] - p_n) @ R.T + p_b
        x[:n0] = fl.x_before
        return x

    def _place_span(self, j: int) -> int:
        """How far apart two old frames may be and still be one place: the frames that share
        map tracks with frame *j* span it."""
        near = self._place_parts(j)[0]
        return max((abs(f - j) for f in near), default=0)

    def _path_length(self, j: int, k: int) -> float:
        """Length of the estimated path from frame *j* to frame *k* through the poses of
        the filter between them (map units)."""
        ids = [i for i in self.filter.layout.pose_ids if j <= i <= k]
        P = np.array([self.filter.pose(i)[0] for i in sorted(ids)]).reshape(-1, 3)
        return float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())

    def _rotation_drift(self, j: int, k: int) -> Array:
        """(3, 3) covariance, in frame *k*'s camera frame, of the rotation drift the relative
        poses fused between frames *j* and *k* allow: their ``ZR`` covariances (each in its
        reference camera's frame) rotated into the world and summed."""
        filt = self.filter
        C = np.zeros((3, 3))
        for rp in filt.store.relative:
            if j < rp.j <= k and filt.layout.has_pose(rp.i):
                R = quat_to_rotmat(filt.pose(rp.i)[1]) @ quat_to_rotmat(rp.q_ij)  # frame rp.j to world
                C += R @ rp.cov[:3, :3] @ R.T
        R_k = quat_to_rotmat(filt.pose(k)[1])
        return R_k.T @ C @ R_k

    def _predicted(self, obs: FeatureObservations) -> bool:
        """Whether the filter's estimate already predicts the loop's ``Zm`` (the median
        normalised innovation within the 99% chi-square bound of a pixel): the linearised
        fusion is then valid and nothing needs relinearising (a loop found again a few
        frames after one was corrected)."""
        chi2 = self.filter.linearise_features(obs, gate=False)[5]
        return bool(np.all(np.isfinite(chi2)) and np.median(chi2) <= CHI2_2DOF_99)

    # -- sessions -------------------------------------------------------------------
    def state_dict(self) -> dict:
        """What a session keeps: the place index, the loops found and the last query's
        candidate places, the old features fused at each loop frame, and the loops taken
        back (with the frame and the reason). What taking a kept loop back needs (its
        fusion's record, the estimate before it) is not kept: a loop fused before the
        session was saved stays."""
        C = np.array([[getattr(c, f) for f in _FIELDS] for c in self.closures], float).reshape(-1, len(_FIELDS))
        L = [np.stack([np.full(len(t), f), t], 1) for f, t in self._loop_tracks.items()]
        R = np.array([[getattr(c, f) for f in _FIELDS] + [at] for c, at, _ in self.removed], float
                     ).reshape(-1, len(_FIELDS) + 1)
        return {"index": self.index.state_dict(), "closures": C,
                "removed": R, "removed_why": [str(why) for _, _, why in self.removed],
                "streak": np.array(self._streak, np.int64).reshape(-1, 3),
                "loop_tracks": np.concatenate(L).astype(np.int64) if L else np.zeros((0, 2), np.int64)}

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict`, checked (:class:`~eifslam.errors.SessionError`)."""
        self.index.load_state_dict(sub(d, "index"))
        C = take(d, "closures", np.float64, (None, len(_FIELDS)))
        ints = {"frame", "matched_frame", "matches", "inliers", "required", "five_point_inliers",
                "five_point_required", "fused"}
        def closure(row) -> LoopClosure:
            return LoopClosure(**{f: (int(v) if f in ints else float(v)) for f, v in zip(_FIELDS, row)})

        self.closures = [closure(row) for row in C]
        R = take(d, "removed", np.float64, (None, len(_FIELDS) + 1)) if "removed" in d \
            else np.zeros((0, len(_FIELDS) + 1))
        why = d.get("removed_why", [])
        if not isinstance(why, list) or len(why) != len(R) or not all(isinstance(w, str) for w in why):
            from ..errors import SessionError

            raise SessionError(f"loops: 'removed_why' must hold {len(R)} strings")
        self.removed = [(closure(row[:-1]), int(row[-1]), str(w)) for row, w in zip(R, why)]
        S = take(d, "streak", np.int64, (None, 3))
        self._streak = [tuple(int(v) for v in row) for row in S]
        T = take(d, "loop_tracks", np.int64, (None, 2)) if "loop_tracks" in d else np.zeros((0, 2), np.int64)
        self._loop_tracks = {int(f): T[T[:, 0] == f, 1].copy() for f in np.unique(T[:, 0])}
