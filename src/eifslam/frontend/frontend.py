"""The front end: everything between an image and the measurements the filter fuses.

One class, :class:`FrontEnd`, in banner-marked parts by role:

- **set-up and pickling**: the OpenCV detector (one per thread) and matcher, made from the
  config, never pickled;
- **queries** by frame id: keypoints with track ids, tracks common to two frames, the
  ``Ωm`` observations of a frame (``Zm``) and the relative pose of two frames from their
  ``Ωp`` tracks (``ZR``, ``ZT``);
- **updates**: one entry point per image (:meth:`FrontEnd.add_frame`, which is
  :meth:`FrontEnd.detect`, thread-safe and free of the front end's state, then
  :meth:`FrontEnd.add_features`), matching against the last frames under the epipolar
  RANSAC;
- **re-association**: tracks that are the same point seen again are merged (guided
  matching of lost ``Ωm`` tracks, relocalisation against older frames, the tracks a
  verified loop joins);
- **sessions**: the stored frames, descriptors and tracks as arrays
  (:meth:`FrontEnd.state_dict`), checked on loading (:meth:`FrontEnd.load_state_dict`).
  :mod:`eifslam.system.session` writes these arrays into a ``.npz`` read with
  ``allow_pickle=False``; nothing a user's file contains is executed.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, replace
from itertools import islice

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from ..errors import EstimatorError, SessionError
from ..estimation.statedict import check_index, sub, take, take_ids
from .config import FrontEndConfig
from .features import AheadMatch, Features, detect_features, make_detector, run_contrast_threshold
from .matching import (DescriptorIndex, DescriptorMatcher, ImageMotion, essential_ransac,
                       guided_search, homography_ransac, image_motion, lone_candidate_bound, windowed_match)
from .relative_pose import estimate_relative_pose
from .results import FrameFeatures, FrameResult, Reason, RelativePoseResult
from .split import assign_to_map
from .tracks import TrackStore

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["FrontEnd"]

#: The first match searches the whole frame when its window finds fewer epipolar inliers
#: than this fraction of the last whole-frame search's (the prediction missed).
FALLBACK_FRACTION = 0.5
_EMPTY = (np.zeros(0, np.int64), np.zeros(0, np.int64))


@dataclass
class StoredFrame:
    """One stored frame of the front end."""

    feats: Features
    raw_ids: IntArray  # as assigned; resolve through the TrackStore before use


class FrontEnd:
    """Feature detection, track management and relative poses for one calibrated camera,
    with the merging of tracks seen again and the front end's part of a session.

    Parameters
    ----------
    camera : PinholeCamera
        Intrinsics; images must have its size.
    config : FrontEndConfig, optional

    Raises
    ------
    ConfigError
        When the configured detector is not available in the installed OpenCV.

    Notes
    -----
    Track ids are stable: a keypoint matched to a keypoint of an earlier frame takes its
    track id; unmatched keypoints start new tracks, each assigned for ever to ``Ωm`` or
    ``Ωp`` (:mod:`eifslam.frontend.split`). A track never holds two keypoints of one
    frame, and matches rejected by the epipolar RANSAC never extend a track.
    """

    def __init__(self, camera: PinholeCamera, config: FrontEndConfig = FrontEndConfig()) -> None:
        self.camera = camera
        self.config = config
        if config.seed is not None:
            cv2.setRNGSeed(int(config.seed))
        self._local = threading.local()  # one OpenCV detector per thread (see detect)
        self._local.detector = make_detector(config)  # made now: a bad detector fails here
        self._matcher = self._make_matcher()
        self._tracks = TrackStore()
        self._frames: dict[int, StoredFrame] = {}
        self._desc: dict[int, NDArray] = {}
        self._index: dict[int, DescriptorIndex] = {}  # the match window's descriptor indices
        self._motion: dict[int, ImageMotion] = {}  # the last frame's keypoints' motion
        self._order: list[int] = []
        self._released: set[int] = set()  # frames whose descriptors go when they leave the match window
        self._last_desc: dict[int, tuple[IntArray, NDArray]] = {}  # forgotten frames: (rows, descriptors)
        # of their keypoints that are a track's last observation (re-observation's reference)
        self._last_frame = np.zeros(0, np.int64)  # per raw track id: last frame seen in
        self._last_kp = np.zeros(0, np.int64)  # ... and the keypoint index there
        self._ahead_last: Features | None = None  # match_ahead's last features (its thread's)
        self._contrast: float | None = None  # SIFT's contrast threshold of the run (see detect)
        self._contrast_lock = threading.Lock()

    # ------------------------------------------------------------------ pickling
    def __getstate__(self) -> dict:
        """Pickle without the OpenCV detectors and matcher (they do not pickle); they are
        recreated from the config when loaded (:meth:`__setstate__`)."""
        state = self.__dict__.copy()
        state["_local"] = None
        state["_matcher"] = None
        state["_index"] = {}  # FLANN indices do not pickle; rebuilt when next needed
        state["_ahead_last"] = None
        state["_contrast_lock"] = None
        return state

    def __setstate__(self, state: dict) -> None:
        state.pop("_detector", None)  # a pickle holding one shared detector: detectors are per thread
        self.__dict__.update(state)
        self.__dict__.setdefault("_index", {})
        self.__dict__.setdefault("_motion", {})
        self.__dict__.pop("_ahead_previous", None)  # a pickle without the ahead matching's state
        self.__dict__.setdefault("_ahead_last", None)
        self.__dict__.setdefault("_contrast", None)
        self.__dict__.setdefault("_released", set())
        self.__dict__.setdefault("_last_desc", {})
        self._contrast_lock = threading.Lock()
        self._local = threading.local()
        self._matcher = self._make_matcher()

    def _make_matcher(self) -> DescriptorMatcher:
        c = self.config
        return DescriptorMatcher(c.ratio, c.mutual, c.flann_trees, c.flann_checks)

    # ------------------------------------------------------------------ queries
    @property
    def frame_ids(self) -> list[int]:
        """Ids of the stored frames, in the order they were added."""
        return list(self._order)

    def _get(self, frame_id: int) -> StoredFrame:
        fr = self._frames.get(int(frame_id))
        if fr is None:
            raise EstimatorError(f"frame {frame_id} is not stored in the front end")
        return fr

    def frame(self, frame_id: int) -> FrameFeatures:
        """Keypoints of a stored frame with their current track ids and sets."""
        fr = self._get(frame_id)
        ids = self._tracks.resolve(fr.raw_ids)
        f = fr.feats
        return FrameFeatures(int(frame_id), f.uv, f.uv_raw, ids, self._tracks.in_map(ids), f.colors)

    def descriptors(self, frame_id: int, rows: NDArray[np.int64] | None = None) -> NDArray | None:
        """Descriptors ``(N, D)`` of a stored frame's keypoints (rows as in :meth:`frame`;
        only the keypoints ``rows`` when given), as the detector gives them (``float32``
        for SIFT), or None when they were dropped (:meth:`forget`)."""
        self._get(frame_id)
        d = self._desc.get(int(frame_id))
        if d is None:
            return None
        return self._searchable(d if rows is None else d[np.asarray(rows, np.int64)])

    def _searchable(self, d: NDArray) -> NDArray:
        """Stored descriptors ``d`` as the detector gives them: SIFT's bytes as ``float32``."""
        return d.astype(np.float32) if self.config.detector.float_descriptors and d.dtype == np.uint8 else d

    def _compact(self, d: NDArray) -> NDArray:
        """Descriptors as stored: OpenCV's SIFT descriptors are floats holding the integers
        0..255, kept as bytes (a quarter of the memory, exactly); others as they are."""
        if d.dtype != np.float32 or not self.config.detector.float_descriptors:
            return d
        b = d.astype(np.uint8)
        return b if np.array_equal(b, d) else d

    @property
    def matcher(self) -> DescriptorMatcher:
        """The descriptor matcher (ratio test and mutual check of the config)."""
        return self._matcher

    def common_tracks(
        self, i: int, j: int, in_map: bool | None = None
    ) -> tuple[IntArray, Array, Array]:
        """Tracks seen in both frames.

        Parameters
        ----------
        i, j : int
            Frame ids.
        in_map : bool or None
            None: all tracks; True: only ``Ωm`` tracks; False: only ``Ωp`` tracks.

        Returns
        -------
        track_ids : (M,) int64, sorted.
        uv_i, uv_j : (M, 2) undistorted pixels in frames *i* and *j*.
        """
        fi, fj = self._get(i), self._get(j)
        ids_i = self._tracks.resolve(fi.raw_ids)
        ids_j = self._tracks.resolve(fj.raw_ids)
        ids, a, b = np.intersect1d(ids_i, ids_j, assume_unique=True, return_indices=True)
        if in_map is not None:
            keep = self._tracks.in_map(ids) == bool(in_map)
            ids, a, b = ids[keep], a[keep], b[keep]
        return ids.astype(np.int64), fi.feats.uv[a], fj.feats.uv[b]

    def map_observations(self, frame_id: int, min_track_length: int = 1) -> tuple[IntArray, Array]:
        """The ``Ωm`` (map) tracks seen in a frame: their ids are the map feature ids.

        Parameters
        ----------
        frame_id : int
        min_track_length : int
            Only tracks seen in at least this many frames so far.

        Returns
        -------
        track_ids : (M,) int64; uv : (M, 2) undistorted pixels (``Zm``).
        """
        fr = self._get(frame_id)
        ids = self._tracks.resolve(fr.raw_ids)
        keep = self._tracks.in_map(ids) & (self._tracks.length(ids) >= min_track_length)
        return ids[keep], fr.feats.uv[keep]

    def relative_pose(self, i: int, j: int) -> RelativePoseResult:
        """Relative pose of frame *j* seen from frame *i*, from their common ``Ωp`` tracks.

        Returns
        -------
        RelativePoseResult
            ``measurement`` is a :class:`~eifslam.estimation.measurements.RelativePose` with ``i, j``
            set when ``ok``; otherwise ``reason`` says why.
        """
        if int(i) == int(j):
            self._get(i)
            return RelativePoseResult(False, Reason.SAME_FRAME, None,
                                      timings_ms={"relative_pose": 0.0, "covariance": 0.0})
        ids, ui, uj = self.common_tracks(i, j, in_map=False)
        return estimate_relative_pose(ui, uj, self.camera, self.config, int(i), int(j), ids)

    # ----------------------------------------------------------------- updates
    def detect(self, image: np.ndarray) -> Features:
        """Detect and describe the keypoints of an image, without changing the front end.

        Thread-safe: each calling thread uses its own OpenCV detector (made on its first
        call), and nothing of the front end's state is read but its camera, its config and
        the run's SIFT contrast threshold (decided once, on the first image detected:
        :func:`~eifslam.frontend.features.run_contrast_threshold`), so a worker thread may
        detect the next frames while another thread adds features (:meth:`add_features`).
        The same image always gives the same features within a run.

        Parameters
        ----------
        image : ndarray
            ``(H, W)`` or ``(H, W, 3|4)`` image of the camera's size (``uint8``, ``uint16``
            or float in [0, 1]).

        Returns
        -------
        Features
            Undistorted and raw pixels ``(N, 2)``, descriptors ``(N, D)``, and the time
            the detection took (``detect_ms``).

        Raises
        ------
        ImageError
            On unreadable input (None, wrong dtype, shape or size).
        """
        detector = self._thread_detector()
        return detect_features(image, self.camera, self.config, detector, self._run_contrast(image, detector))

    def _run_contrast(self, image: np.ndarray, detector) -> float | None:
        """SIFT's contrast threshold for the run (None for the other detectors), decided on
        the first image detected, the run's first frame (:func:`run_contrast_threshold`),
        and kept in sessions."""
        if self.config.detector != "sift":
            return None
        if self._contrast is None:
            with self._contrast_lock:
                if self._contrast is None:
                    default = float(self.config.sift_contrast_threshold)
                    n = len(detect_features(image, self.camera, self.config, detector, default))
                    self._contrast = run_contrast_threshold(image, n, self.camera, self.config)
        return self._contrast

    def match_ahead(self, feats: Features) -> Features:
        """What :meth:`add_features` would do first with the features of a new frame
        (:meth:`detect`'s) that depends on them and the frame before them alone, so that a
        prefetch worker can make it: the new frame's search index (``Features.index``,
        for float descriptors; a FLANN forest above ``EXACT_ROWS`` keypoints, seeded from
        the descriptors themselves), and the first match :meth:`add_features` makes, with
        the previous frame, every row free, predicted by that frame's motion, with its
        epipolar RANSAC (``Features.ahead``; OpenCV's estimators draw from their own fixed
        seed) and the new frame's motion (``Features.motion``). :meth:`add_features` makes
        what was not made ahead itself and uses the matches only when its previous frame
        holds those descriptors and that motion, so the results are those of
        :meth:`detect` alone either way. One thread calls it, in frame order."""
        previous = self._ahead_last
        index = None
        if self.config.detector.float_descriptors:  # made here, once: the matches of the next frames search it
            index = self._seeded_index(feats.descriptors)
            index.build()  # (a FLANN forest only above EXACT_ROWS keypoints)
        feats = replace(feats, index=index)
        if previous is not None:
            t0 = time.perf_counter()
            i_new, i_prev, inliers, motion = self._first_match(feats, previous, previous.index, previous.motion)
            feats = replace(feats, motion=motion, ahead=AheadMatch(
                previous.descriptors, i_new, i_prev, (time.perf_counter() - t0) * 1e3, inliers, previous.motion))
        self._ahead_last = feats
        return feats

    def _thread_detector(self):
        """This thread's OpenCV detector (made on first use: detectors are not thread-safe)."""
        detector = getattr(self._local, "detector", None)
        if detector is None:
            detector = self._local.detector = make_detector(self.config)
        return detector

    def add_frame(self, image: np.ndarray | Features, frame_id: int) -> FrameResult:
        """Detect features, match them against the previous frame(s), extend/create tracks.

        :meth:`detect` followed by :meth:`add_features`.

        Parameters
        ----------
        image : ndarray or Features
            ``(H, W)`` or ``(H, W, 3|4)`` image of the camera's size (``uint8``, ``uint16``
            or float in [0, 1]); or the :class:`Features` :meth:`detect` gave for it
            (detected ahead, e.g. in a worker thread), which are then added as they are.
        frame_id : int
            New, unique frame id.

        Returns
        -------
        FrameResult

        Raises
        ------
        ImageError
            On unreadable input (None, wrong dtype, shape or size).
        EstimatorError
            When ``frame_id`` is already stored.
        """
        fid = int(frame_id)
        if fid in self._frames:
            raise EstimatorError(f"frame {fid} was already added to the front end")
        feats = image if isinstance(image, Features) else self.detect(image)
        return self.add_features(feats, fid)

    def add_features(self, features: Features, frame_id: int) -> FrameResult:
        """Match detected features against the previous frame(s), extend/create tracks.

        The part of :meth:`add_frame` after the detection: descriptor matching against
        the last ``match_window`` frames with the epipolar RANSAC, track extension, new
        tracks split into ``Ωp``/``Ωm``. Must be called in frame order (from one thread).

        Parameters
        ----------
        features : Features
            From :meth:`detect` (for an image of this front end's camera and config).
        frame_id : int
            New, unique frame id.

        Returns
        -------
        FrameResult
            ``timings_ms`` has ``detect`` (``features.detect_ms``) and ``match``.

        Raises
        ------
        EstimatorError
            When ``frame_id`` is already stored, or ``features`` is not a
            :class:`Features`.
        """
        fid = int(frame_id)
        if fid in self._frames:
            raise EstimatorError(f"frame {fid} was already added to the front end")
        if not isinstance(features, Features):
            raise EstimatorError(f"add_features takes Features, got {type(features).__name__}")
        feats = replace(features, ahead=None, index=None, motion=None)
        if self.config.seed is not None:  # per frame: a resumed session draws what an uninterrupted run would
            cv2.setRNGSeed(int(self.config.seed) + fid)  # (OpenCV's generator is per thread: this one's)
        t1 = time.perf_counter()
        ids = np.full(len(feats), -1, np.int64)
        previous = self._match_window()
        for p in reversed(previous):  # indices not kept (a loaded session): made as when added
            if p not in self._index:
                self._index[p] = self._seeded_index(self._searchable(self._desc[p]))
        index = features.index if features.index is not None else self._seeded_index(feats.descriptors)
        feats = replace(feats, index=index)
        n_matches, motion, ms_ahead = 0, None, None
        for n, p in enumerate(previous):
            prev = self._frames[p]
            pid = self._tracks.resolve(prev.raw_ids)
            if n == 0:
                ia, ib, motion, ms_ahead = self._match_previous(feats, p, features)
            else:
                ia, ib = self._match_free(feats, ids, prev, pid, p)
            ids[ia] = pid[ib]
            n_matches += int(len(ia))
        new = ids < 0
        in_map = assign_to_map(feats.sign[new], feats.response[new], self.config.map_fraction)
        ids[new] = self._tracks.allocate(in_map)
        self._tracks.observe(ids)
        self._note_last_seen(fid, ids)
        stored = replace(feats, descriptors=self._compact(feats.descriptors), index=None)
        self._frames[fid] = StoredFrame(stored, ids)
        self._desc[fid] = stored.descriptors
        self._order.append(fid)
        self._index[fid] = index
        self._motion = {} if motion is None else {fid: motion}  # what the next frame's search needs
        window = self._match_window()  # the next frame's
        for p in [p for p in self._index if p not in window]:
            del self._index[p]  # only the next frame's match window keeps its index
        for p in [p for p in self._released if p not in window]:
            self.forget(p)
        if self.config.seed is not None:  # the draws after this frame whichever thread built its index
            cv2.setRNGSeed(int(self.config.seed) + fid)
        t2 = time.perf_counter()
        if len(feats) == 0:
            ok, reason = False, Reason.NO_FEATURES
        elif previous and n_matches < self.config.min_matches:
            ok, reason = False, Reason.TOO_FEW_MATCHES
        else:
            ok, reason = True, Reason.OK
        ms = {"detect": float(feats.detect_ms), "match": (t2 - t1) * 1e3}
        if ms_ahead is not None:
            ms["match_ahead"] = ms_ahead  # the part of the matching made where detected
        return FrameResult(fid, ok, reason, len(feats), int(n_matches), int(new.sum()), ms)

    def _seeded_index(self, descriptors: NDArray) -> DescriptorIndex:
        """A :class:`DescriptorIndex` of ``descriptors``, its FLANN trees (built when first
        searched) drawn from OpenCV's generator set from the config's seed and the
        descriptors: the same whenever and wherever built (in a prefetch worker, after
        loading a session)."""
        return self._matcher.index(descriptors, self.config.seed)

    def _match_previous(self, feats: Features, p: int, detected: Features
                        ) -> tuple[IntArray, IntArray, ImageMotion | None, float | None]:
        """The first match of a new frame, with the front end's previous frame ``p``: the
        one :meth:`match_ahead` made (``detected.ahead``) when it was made against these
        descriptors and this motion of frame ``p``, else :meth:`_first_match` now.

        Returns
        -------
        idx_new, idx_previous : (M,) int64 epipolar-consistent matches.
        motion : ImageMotion or None
            The new frame's.
        ms_ahead : float or None
            The time the match took where it was made ahead; None when made now.
        """
        ahead, index, motion_p = detected.ahead, self._index[p], self._motion.get(p)
        if ahead is not None and ahead.previous is index.descriptors and ahead.motion_previous is motion_p:
            i_new, i_prev, inliers, ms = ahead.idx_new, ahead.idx_previous, ahead.inliers, ahead.ms
            motion = detected.motion
        else:  # not made ahead, or against another frame or motion (a frame skipped, a session loaded)
            previous = replace(self._frames[p].feats, descriptors=index.descriptors)
            (i_new, i_prev, inliers, motion), ms = self._first_match(feats, previous, index, motion_p), None
        ia, ib = self._consistent(i_new, i_prev, inliers)
        return ia, ib, motion, ms

    def _first_match(self, feats: Features, previous: Features, previous_index: DescriptorIndex | None,
                     previous_motion: ImageMotion | None
                     ) -> tuple[IntArray, IntArray, NDArray[np.bool_] | None, ImageMotion | None]:
        """Match a new frame with the frame before it, every keypoint free.

        With float descriptors (SIFT) and a previous frame's motion whose prediction held
        (a finite ``radius_px``), each keypoint is looked for only near where the previous
        frame's keypoints are predicted
        (:func:`~eifslam.frontend.matching.windowed_match`, within ``radius_px``); the
        whole-frame search (:meth:`DescriptorMatcher.match`) runs otherwise, or when the
        window finds fewer epipolar inliers than ``FALLBACK_FRACTION`` of the last
        whole-frame search (the camera changed pace, or the view).

        Parameters
        ----------
        feats, previous : Features
            The new and the previous frame's (searchable descriptors: SIFT's as floats).
        previous_index : DescriptorIndex or None
            The previous frame's search index, for the whole-frame search.
        previous_motion : ImageMotion or None

        Returns
        -------
        idx_new, idx_previous : (M,) int64 descriptor matches.
        inliers : (M,) bool or None
            Their epipolar inliers; None when there were fewer than ``min_matches``.
        motion : ImageMotion or None
            The new frame's motion (None with too few inliers, and for binary descriptors:
            their exact whole-frame search, SIMD Hamming distances, costs less than the
            windowed one).
        """
        c = self.config
        predicted = previous_motion is not None and np.isfinite(previous_motion.radius_px)
        if predicted:
            i_new, i_prev = windowed_match(feats.descriptors, feats.uv, previous.descriptors,
                                           previous.uv + previous_motion.flow, previous_motion.radius_px,
                                           self._matcher.ratio)
            inliers = self._inliers_of(feats.uv[i_new], previous.uv[i_prev])
            n = 0 if inliers is None else int(inliers.sum())
            predicted = n >= max(c.min_matches, FALLBACK_FRACTION * previous_motion.reference)
        if not predicted:  # no prediction, or it missed: the whole frame
            i_new, i_prev = self._matcher.match(feats.descriptors, previous.descriptors,
                                                index1=feats.index, index2=previous_index)
            inliers = self._inliers_of(feats.uv[i_new], previous.uv[i_prev])
        motion = None
        if inliers is not None and inliers.sum() >= c.min_matches and c.detector.float_descriptors:
            motion = image_motion(feats.uv, previous.uv, i_new[inliers], i_prev[inliers], previous_motion,
                                  whole_frame=not predicted)
        return i_new, i_prev, inliers, motion

    def _inliers_of(self, uv_new: Array, uv_old: Array) -> NDArray[np.bool_] | None:
        """Epipolar inliers of matched pixels (:meth:`_epipolar_inliers`), or None for fewer
        than ``min_matches`` matches."""
        return self._epipolar_inliers(uv_new, uv_old) if len(uv_new) >= self.config.min_matches else None

    def _consistent(self, ia: IntArray, ib: IntArray, inliers: NDArray[np.bool_] | None) -> tuple[IntArray, IntArray]:
        """The matches ``(ia, ib)`` that pass the epipolar RANSAC, none when fewer than
        ``min_matches`` do."""
        if inliers is None or inliers.sum() < self.config.min_matches:
            return ia[:0], ib[:0]
        return ia[inliers], ib[inliers]

    def _epipolar_inliers(self, uv_new: Array, uv_old: Array) -> NDArray[np.bool_]:
        """Inliers ``(M,)`` of the five-point RANSAC between matched pixels ``(M, 2)`` of
        the new and an older frame."""
        c = self.config
        E, inl = essential_ransac(uv_old, uv_new, self.camera.K, c.ransac_threshold_px, c.ransac_confidence,
                                  c.ransac_method)
        if E is None:  # no parallax (e.g. the same view twice): degenerate for E, not for H
            inl = homography_ransac(uv_old, uv_new, 2.0 * c.ransac_threshold_px, c.ransac_confidence,
                                    c.ransac_method)[1]
        return inl

    def _match_free(self, feats: Features, ids: IntArray, prev: StoredFrame, pid: IntArray,
                    p: int) -> tuple[IntArray, IntArray]:
        """Matches of the new frame's unassigned keypoints with an older frame ``p``'s
        keypoints whose track is not continued, under the epipolar RANSAC, searched in the
        whole frame (its index and the new frame's): a window, along the new frame's motion
        two or three frames back, lost accuracy on the shared sets (docs/frontend.md)."""
        free_new = ids < 0
        free_old = ~np.isin(pid, ids[ids >= 0])
        if free_new.sum() < 5 or free_old.sum() < 5:
            return _EMPTY
        ia, ib = self._matcher.match(feats.descriptors, self._index[p].descriptors, free_new, free_old,
                                     feats.index, self._index[p])
        return self._consistent(ia, ib, self._inliers_of(feats.uv[ia], prev.feats.uv[ib]))

    def _note_last_seen(self, fid: int, ids: IntArray) -> None:
        n = len(self._tracks)
        if len(self._last_frame) < n:
            grow = n - len(self._last_frame)
            self._last_frame = np.concatenate([self._last_frame, np.full(grow, -1, np.int64)])
            self._last_kp = np.concatenate([self._last_kp, np.full(grow, -1, np.int64)])
        self._last_frame[ids] = fid
        self._last_kp[ids] = np.arange(len(ids))

    def forget(self, frame_id: int) -> None:
        """Drop the descriptors of a frame (it can no longer be matched; its keypoints and
        track ids stay available). Those of its keypoints that are the last observation of
        a track stay, as the reference :meth:`reobserve` compares with."""
        fr = self._get(frame_id)
        fid = int(frame_id)
        if fid in self._desc:
            rows = self._last_rows(fid)
            self._last_desc[fid] = (rows, self._desc[fid][rows].copy())
            self._prune_last_desc(2)
        self._desc.pop(fid, None)
        self._index.pop(fid, None)
        self._released.discard(fid)
        d = fr.feats.descriptors
        fr.feats = replace(fr.feats, descriptors=np.empty((0,) + d.shape[1:], d.dtype))  # not a view: it would keep d

    def _prune_last_desc(self, n: int) -> None:
        """Drop from the ``n`` entries of the forgotten frames' descriptors pruned longest ago
        the rows that are no longer some track's last observation (re-observation or a
        loop moved the track's end to a later frame); a pruned entry goes to the back of the
        turns. Each forget prunes two, so what is kept stays what :meth:`reobserve` can
        read, not every track end ever forgotten."""
        for f in list(islice(self._last_desc, n)):
            kept, d = self._last_desc.pop(f)
            keep = np.isin(kept, self._last_rows(f))
            if keep.any():
                self._last_desc[f] = (kept[keep], d[keep])  # to the end of the turns

    def _match_window(self) -> list[int]:
        """The frames a new frame is matched against, newest first: the last
        ``match_window`` stored frames that still have descriptors."""
        return list(islice((p for p in reversed(self._order) if p in self._desc), self.config.match_window))

    def _last_rows(self, frame_id: int) -> IntArray:
        """Rows of frame ``frame_id``'s keypoints that are the last observation of a track,
        sorted. Only shrinks as later frames see those tracks again."""
        return np.unique(self._last_kp[self._last_frame == int(frame_id)])

    def release(self, frame_id: int) -> None:
        """Frame ``frame_id`` will not be matched again once it leaves the match window
        (a frame between keyframes: loop closing and relocalisation match keyframes only).
        Its descriptors are dropped then (:meth:`forget`): SIFT's take 256 KB per frame of
        2000 keypoints, most of the front end's memory."""
        fid = int(frame_id)
        self._get(fid)
        if fid in self._desc:
            self._released.add(fid)
        if fid not in self._match_window():
            self.forget(fid)

    # ------------------------------------------------------------ re-association
    def reobserve(self, frame_id: int, track_ids: IntArray, uv_predicted: Array, radius_px: float,
                  ratio: float | None = None) -> int:
        """Guided search: find known ``Ωm`` tracks again in a frame where tracking lost them.

        Each track is looked for only inside the window of ``radius_px`` around where it is
        predicted (search by projection, :func:`~eifslam.frontend.matching.guided_search`):
        its descriptor (from its last observation) is compared with the frame's keypoints
        in the window, and the nearest is taken when it is nearer than
        :func:`~eifslam.frontend.matching.lone_candidate_bound`, passes the ratio test
        against the second nearest of the window (if any) and started a new ``Ωm``
        track in this frame. A keypoint goes to one track, the one with the nearest
        descriptor; its track is merged into the old one (so the map feature gets this
        measurement and the keypoint's measurements are never used twice).

        Parameters
        ----------
        frame_id : int
            A stored frame with descriptors.
        track_ids : (M,) int64
            ``Ωm`` track ids (current identities) not seen in the frame.
        uv_predicted : (M, 2)
            Undistorted pixels where each track is expected in the frame.
        radius_px : float
            Search radius, pixels.
        ratio : float, optional
            Ratio-test threshold (default: the matcher's).

        Returns
        -------
        int
            How many tracks were found again.
        """
        fid = int(frame_id)
        fr = self._get(fid)
        track_ids = np.asarray(track_ids, np.int64).reshape(-1)
        uv_predicted = np.asarray(uv_predicted, float).reshape(-1, 2)
        if len(track_ids) == 0 or fid not in self._desc or len(fr.feats) == 0:
            return 0
        ratio = self._matcher.ratio if ratio is None else float(ratio)
        lf, lk = self._last_frame[track_ids], self._last_kp[track_ids]
        have = (lf >= 0) & (lf != fid) & np.isin(lf, list(self._desc) + list(self._last_desc))
        track_ids, uv_predicted, lf, lk = track_ids[have], uv_predicted[have], lf[have], lk[have]
        if len(track_ids) == 0:
            return 0
        frame_desc = self._searchable(self._desc[fid])  # SIFT's as floats: L2, not Hamming
        D = np.empty((len(lf), frame_desc.shape[1]), frame_desc.dtype)  # each track's, where last seen
        for f in np.unique(lf).tolist():
            rows = lf == f
            if f in self._desc:
                D[rows] = self._desc[f][lk[rows]]
            else:
                kept, d = self._last_desc[f]
                D[rows] = d[np.searchsorted(kept, lk[rows])]
        rows, best, d1 = guided_search(D, uv_predicted, frame_desc, fr.feats.uv, radius_px, ratio,
                                       lone_candidate_bound(frame_desc, ratio))
        kid = self._tracks.resolve(fr.raw_ids)
        fresh = self._tracks.in_map(kid) & (self._tracks.length(kid) == 1)
        ok = fresh[best]
        rows, best, d1 = rows[ok], best[ok], d1[ok]
        # a keypoint goes to one track only: the closest descriptor wins
        order = np.argsort(d1, kind="stable")
        _, first = np.unique(best[order], return_index=True)
        found = 0
        for i in order[np.sort(first)]:
            t, b = int(track_ids[rows[i]]), int(best[i])
            if self._tracks.merge(t, int(kid[b])):
                self._last_frame[t], self._last_kp[t] = fid, b
                found += 1
        return found

    def relocalise(self, frame_id: int, candidate_frame_ids) -> list[tuple[int, int]]:
        """Match a frame against older stored frames and merge the matched tracks.

        Map features (and ``Ωp`` tracks) seen in a candidate regain their identity in
        ``frame_id``: each matched pair of tracks is merged into the older id, unless the
        two tracks are of different sets or share a frame.

        Parameters
        ----------
        frame_id : int
            A stored frame (with descriptors).
        candidate_frame_ids : iterable of int
            Stored frames to try (those without descriptors are skipped).

        Returns
        -------
        list of (candidate_id, n_matches)
            Epipolar-consistent matches found with each candidate (0 when none).
        """
        fr = self._get(frame_id)
        out: list[tuple[int, int]] = []
        pairs = []
        for c in candidate_frame_ids:
            c = int(c)
            if c == int(frame_id) or c not in self._desc or int(frame_id) not in self._desc:
                out.append((c, 0))
                continue
            cf = self._get(c)
            ia, ib = self._matcher.match(self.descriptors(frame_id), self.descriptors(c))
            ia, ib = self._consistent(ia, ib, self._inliers_of(fr.feats.uv[ia], cf.feats.uv[ib]))
            out.append((c, int(len(ia))))
            if len(ia):
                pairs.append(np.stack([fr.raw_ids[ia], cf.raw_ids[ib]], 1))
        if pairs:
            self._merge_pairs(np.concatenate(pairs))
        return out

    def join_tracks(self, frame_id: int, keypoints: IntArray, track_ids: IntArray) -> None:
        """Merge the tracks of keypoints of a frame into known tracks (a verified loop): as
        :meth:`relocalise` merges matched pairs (same set, no shared frame)."""
        kp = np.asarray(keypoints, np.int64).reshape(-1)
        if kp.size:
            self._merge_pairs(np.stack([self._get(frame_id).raw_ids[kp], np.asarray(track_ids, np.int64)], 1))

    def _merge_pairs(self, pairs: IntArray) -> None:
        """Merge each pair ``(a, b)`` of raw track ids ``(P, 2)`` into the older id, unless
        the two are one track already, are of different sets or share a frame."""
        roots = np.unique(self._tracks.resolve(pairs.reshape(-1)))
        frames: dict[int, set[int]] = {int(r): set() for r in roots}
        for fid, fr in self._frames.items():
            ids = self._tracks.resolve(fr.raw_ids)
            for h in ids[np.isin(ids, roots)]:
                frames[int(h)].add(fid)
        for a, b in pairs:
            ra, rb = (int(v) for v in self._tracks.resolve(np.array([a, b])))
            if ra == rb or frames[ra] & frames[rb]:
                continue
            if self._tracks.merge(ra, rb):
                frames[min(ra, rb)] = frames[ra] | frames[rb]

    # ------------------------------------------------------------------ sessions
    def state_dict(self) -> dict:
        """What a session keeps, as arrays (:mod:`eifslam.estimation.statedict`): every
        stored frame's keypoints, descriptors and raw track ids (concatenated in frame
        order, ``n_keypoints`` per frame), which frames can still be matched, the track
        store, where each track was last seen, the last frame's keypoints' motion
        (``motion_*``) and the run's SIFT contrast threshold. The detector and matcher are
        not kept (they are made from the config)."""
        frames = [self._frames[f] for f in self._order]

        def cat(get, tail: tuple, dtype) -> NDArray:
            parts = [np.asarray(get(f)).reshape((-1,) + tail) for f in frames]
            return np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros((0,) + tail, dtype)

        desc = [f.feats.descriptors for f in frames if f.feats.descriptors.size]
        width, dtype = (desc[0].shape[1], np.result_type(*[d.dtype for d in desc])) if desc else (0, np.uint8)
        parts = [f.feats.descriptors if len(f.feats.descriptors) else self._forgotten_rows(fid, len(f.feats), width, dtype)
                 for fid, f in zip(self._order, frames)]
        D = np.concatenate(parts).astype(dtype, copy=False) if parts else np.zeros((0, width), dtype)
        # OpenCV's SIFT descriptors are floats holding integers 0..255: kept as bytes (4x
        # smaller), exactly
        as_bytes = self.config.detector.float_descriptors and (D.dtype == np.uint8 or bool(
            np.all((D >= 0) & (D <= 255) & (D == np.round(D)))))
        return {
            "descriptors_float32": as_bytes,
            "order": np.array(self._order, np.int64),
            "n_keypoints": np.array([len(f.feats) for f in frames], np.int64),
            "matchable": np.array([f in self._desc for f in self._order], bool),
            "released": np.array(sorted(self._released), np.int64),
            "uv": cat(lambda f: f.feats.uv, (2,), float),
            "uv_raw": cat(lambda f: f.feats.uv_raw, (2,), float),
            "descriptors": D.astype(np.uint8) if as_bytes else D,
            "scale_px": cat(lambda f: f.feats.scale_px, (), float),
            "response": cat(lambda f: f.feats.response, (), float),
            "sign": cat(lambda f: f.feats.sign, (), np.int8),
            "colors": cat(lambda f: f.feats.colors, (3,), np.uint8),
            "raw_ids": cat(lambda f: f.raw_ids, (), np.int64),
            "tracks": self._tracks.state_dict(),
            "last_frame": self._last_frame.copy(),
            "last_kp": self._last_kp.copy(),
            "sift_contrast": np.array([] if self._contrast is None else [self._contrast], float),
            "motion_frames": np.array(sorted(self._motion), np.int64),
            "motion_flow": np.concatenate([self._motion[f].flow for f in sorted(self._motion)]).reshape(-1, 2)
            if self._motion else np.zeros((0, 2)),
            "motion_radius": np.array([self._motion[f].radius_px if np.isfinite(self._motion[f].radius_px) else 0.0
                                       for f in sorted(self._motion)], float),  # 0: the whole frame
            "motion_reference": np.array([self._motion[f].reference for f in sorted(self._motion)], np.int64),
        }

    def _forgotten_rows(self, fid: int, n: int, width: int, dtype) -> NDArray:
        """A forgotten frame's ``n`` descriptors as :meth:`state_dict` writes them: what
        :meth:`forget` kept in its rows, zeros elsewhere."""
        out = np.zeros((n, width), dtype)
        rows, d = self._last_desc.get(fid, (np.zeros(0, np.int64), None))
        if len(rows):
            out[rows] = d
        return out

    def load_state_dict(self, d) -> None:
        """Restore :meth:`state_dict` into this (new, empty) front end, checked.

        Raises
        ------
        SessionError
            On a missing, malformed or inconsistent entry.
        """
        if self._order:
            raise SessionError("a session loads into a new front end only")
        order = take_ids(d, "order")
        F = len(order)
        if len(np.unique(order)) != F:
            raise SessionError("array 'order' repeats a frame")
        nk = take_ids(d, "n_keypoints", F)
        matchable = take(d, "matchable", bool, (F,))
        N = int(nk.sum())
        uv, uv_raw = take(d, "uv", np.float64, (N, 2)), take(d, "uv_raw", np.float64, (N, 2))
        desc = take(d, "descriptors", (np.uint8, np.float32), (N, None))
        if d.get("descriptors_float32") is True and desc.dtype == np.uint8:
            desc = desc.astype(np.float32)
        scale, resp = take(d, "scale_px", np.float64, (N,)), take(d, "response", np.float64, (N,))
        sign, colors = take(d, "sign", np.int8, (N,)), take(d, "colors", np.uint8, (N, 3))
        want = (np.float32 if self.config.detector.float_descriptors else np.uint8, self._thread_detector().descriptorSize())
        if N and (desc.dtype, desc.shape[1]) != want:
            raise SessionError(f"descriptors are {desc.dtype} x {desc.shape[1]}, the detector's are "
                               f"{np.dtype(want[0])} x {want[1]}")
        raw = take_ids(d, "raw_ids", N)
        tracks = TrackStore()
        tracks.load_state_dict(sub(d, "tracks"))
        check_index(raw, len(tracks), "array 'raw_ids'")
        last_f, last_k = take_ids(d, "last_frame", None, -1), take_ids(d, "last_kp", None, -1)
        if len(last_f) != len(last_k) or len(last_f) > len(tracks):
            raise SessionError("arrays 'last_frame' and 'last_kp' do not match the tracks")
        n_of = dict(zip(order.tolist(), nk.tolist()))
        seen = last_f >= 0
        if not np.all(np.isin(last_f[seen], order)) or np.any(
                last_k[seen] >= np.array([n_of.get(f, 0) for f in last_f[seen].tolist()], np.int64)) \
                or np.any(last_k[seen] < 0):
            raise SessionError("arrays 'last_frame' and 'last_kp' name a keypoint that is not stored")
        ends = np.cumsum(nk)
        for fid, a, b, m in zip(order.tolist(), (ends - nk).tolist(), ends.tolist(), matchable.tolist()):
            feats = Features(uv[a:b].copy(), uv_raw[a:b].copy(), self._compact(desc[a:b] if m else desc[a:a]).copy(),
                             scale[a:b].copy(), resp[a:b].copy(), sign[a:b].copy(), colors[a:b].copy())
            self._frames[fid] = StoredFrame(feats, raw[a:b].copy())
            if m:
                self._desc[fid] = feats.descriptors
        self._order = order.tolist()
        self._tracks, self._last_frame, self._last_kp = tracks, last_f.copy(), last_k.copy()
        for fid, a, m in zip(order.tolist(), (ends - nk).tolist(), matchable.tolist()):
            rows = np.zeros(0, np.int64) if m else self._last_rows(fid)
            if len(rows):  # a forgotten frame's reference descriptors
                self._last_desc[fid] = (rows, self._compact(desc[a + rows]).copy())
        released = take_ids(d, "released") if "released" in d else np.zeros(0, np.int64)
        if not np.all(np.isin(released, order[matchable])):
            raise SessionError("array 'released' names a frame that cannot be matched")
        self._released = set(released.tolist())
        contrast = take(d, "sift_contrast", np.float64, (None,)) if "sift_contrast" in d else np.zeros(0)
        if len(contrast) > 1 or np.any(contrast <= 0):
            raise SessionError("array 'sift_contrast' must hold at most one positive threshold")
        self._contrast = float(contrast[0]) if len(contrast) else None
        self._load_motion(d, n_of)

    def _load_motion(self, d, n_keypoints: dict[int, int]) -> None:
        """Restore the ``motion_*`` arrays of :meth:`state_dict` (absent in older sessions:
        no motion, the next frame searches the whole frame), and start :meth:`match_ahead`
        from the last matchable frame as an uninterrupted run would have it."""
        if "motion_frames" in d:
            fids = take_ids(d, "motion_frames")
            if not all(f in self._desc for f in fids.tolist()):
                raise SessionError("array 'motion_frames' names a frame that cannot be matched")
            nk = np.array([n_keypoints[f] for f in fids.tolist()], np.int64)
            flow = take(d, "motion_flow", np.float64, (int(nk.sum()), 2))
            radius = take(d, "motion_radius", np.float64, (len(fids),))
            reference = take_ids(d, "motion_reference", len(fids))
            if np.any(radius < 0):
                raise SessionError("array 'motion_radius' must not be negative")
            ends = np.cumsum(nk)
            radius = np.where(radius > 0, radius, np.inf)  # 0: search the whole frame
            self._motion = {f: ImageMotion(flow[b - n:b].copy(), float(r), int(m))
                            for f, n, b, r, m in zip(fids.tolist(), nk.tolist(), ends.tolist(), radius, reference)}
        last = [f for f in self._order if f in self._desc][-1:]
        if last:
            f = last[0]
            self._index[f] = self._seeded_index(self._searchable(self._desc[f]))
            self._ahead_last = replace(self._frames[f].feats, descriptors=self._index[f].descriptors,
                                       index=self._index[f], motion=self._motion.get(f))

