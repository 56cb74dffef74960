"""Wide-baseline matching for frames plain matching cannot relate (affine-simulated features).

A view taken far round an object (templering: 46 degrees after a gap in the ring) shares
too few plain SIFT matches with any known view for a relative pose or a map localisation.
ASIFT (Morel & Yu 2009, OpenCV's ``cv2.AffineFeature``) detects on affinely warped copies of
the image (tilts up to ``max_tilt``), so that surfaces seen at different slants match. The
descriptors are RootSIFT-normalised (Arandjelović & Zisserman 2012) when they are floats.
ASIFT repeats a keypoint over the simulated views, which defeats Lowe's ratio test: the
second-nearest descriptor is often the same point seen in another simulated view. The
ratio is therefore taken against the nearest descriptor of a keypoint more than
``distinct_px`` away from the nearest one (:func:`distinct_ratio_matches`), in both
directions (the mutual check up to the same distance); the five-point RANSAC then keeps
the consistent matches. On templering's 46-degree pair this more than doubles the correct
matches of a plain 0.9 ratio test with the mutual check (143 against 77, all correct).

Costly (a few seconds per 640x480 image on one core): meant for the frames left without a
pose after a run (:meth:`eifslam.system.slam.Slam.retry_lost`), never for every frame.
The matches give the relative pose of the two frames directly, and those landing on stored
keypoints of both frames join their tracks (:meth:`FrontEnd.join_tracks`), so the lost
frame sees known map features.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from .config import FrontEndConfig
from .features import Features, detect_features, make_detector
from .matching import DescriptorMatcher, essential_ransac

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["WideMatch", "WideBaselineMatcher", "affine_detector", "distinct_ratio_matches", "root_normalise",
           "snap_to_keypoints"]


@dataclass(frozen=True)
class WideMatch:
    """Epipolar-consistent wide-baseline matches between a reference frame and a frame.

    Attributes
    ----------
    reference, frame_id : int
    uv_ref, uv : (M, 2) float64
        Corresponding undistorted pixels (RANSAC inliers) in the two frames.
    n_matches : int
        Descriptor matches before the RANSAC.
    n_joined : int
        Matches that landed on stored keypoints of both frames and joined their tracks.
    """

    reference: int
    frame_id: int
    uv_ref: Array
    uv: Array
    n_matches: int
    n_joined: int


def affine_detector(config: FrontEndConfig, max_tilt: float) -> "cv2.AffineFeature":
    """OpenCV's ASIFT wrapper (``cv2.AffineFeature``) around the configured detector."""
    return cv2.AffineFeature.create(make_detector(config), maxTilt=int(max_tilt))


def root_normalise(desc: NDArray) -> NDArray:
    """RootSIFT: L1-normalise non-negative float descriptors and take square roots (the
    Euclidean distance then compares them by the Hellinger kernel); binary ones unchanged."""
    if desc.dtype == np.uint8 or len(desc) == 0:
        return desc
    d = np.asarray(desc, np.float32)
    return np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-7)).astype(np.float32)


def snap_to_keypoints(uv: Array, keypoints: Array, radius_px: float) -> IntArray:
    """Index of the keypoint ``(N, 2)`` nearest each pixel ``uv (M, 2)``, -1 beyond ``radius_px``."""
    if len(uv) == 0 or len(keypoints) == 0:
        return np.full(len(uv), -1, np.int64)
    d2 = ((uv[:, None, :] - keypoints[None, :, :]) ** 2).sum(axis=2)
    best = np.argmin(d2, axis=1)
    return np.where(d2[np.arange(len(uv)), best] <= radius_px ** 2, best, -1).astype(np.int64)


def _nearest_distinct(knn: list, n_query: int, uv_train: Array, ratio: float, distinct_px: float) -> IntArray:
    """Per query row: the nearest train row when it passes the ratio test against the
    nearest train keypoint more than ``distinct_px`` from it (or no such neighbour among
    the ``k`` returned), else -1."""
    best = np.full(n_query, -1, np.int64)
    r2 = distinct_px ** 2
    for m in knn:
        if not m:
            continue
        b = m[0]
        ub = uv_train[b.trainIdx]
        second = next((c for c in m[1:] if ((uv_train[c.trainIdx] - ub) ** 2).sum() > r2), None)
        if second is None or b.distance < ratio * second.distance:
            best[b.queryIdx] = b.trainIdx
    return best


def distinct_ratio_matches(matcher: DescriptorMatcher, fa: Features, fb: Features, ratio: float,
                           distinct_px: float = 4.0, k: int = 8) -> tuple[IntArray, IntArray]:
    """Mutual nearest-neighbour matches of two keypoint sets with repeated keypoints (ASIFT).

    Lowe's ratio test compares the nearest descriptor with the nearest one of a keypoint
    more than ``distinct_px`` away (among the ``k`` nearest), in both directions; a pair is
    kept when the reverse match lands within ``distinct_px`` of the query keypoint.

    Returns
    -------
    (ia, ib) : matched rows of ``fa`` and ``fb`` (each row of ``fa`` used at most once).
    """
    if len(fa) < 2 or len(fb) < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    fwd = _nearest_distinct(matcher.knn(fa.descriptors, fb.descriptors, k), len(fa), fb.uv, ratio, distinct_px)
    bwd = _nearest_distinct(matcher.knn(fb.descriptors, fa.descriptors, k), len(fb), fa.uv, ratio, distinct_px)
    ia = np.flatnonzero(fwd >= 0)
    ib = fwd[ia]
    back = bwd[ib]
    ok = back >= 0
    ok[ok] = ((fa.uv[back[ok]] - fa.uv[ia[ok]]) ** 2).sum(axis=1) <= distinct_px ** 2
    return ia[ok].astype(np.int64), ib[ok].astype(np.int64)


class WideBaselineMatcher:
    """Affine-simulated (ASIFT) matching of two frames, with the features cached per frame.

    Parameters
    ----------
    camera : PinholeCamera
    config : FrontEndConfig
        The front end's (detector, RANSAC threshold and confidence, FLANN settings).
    max_tilt : float >= 1
        Largest simulated tilt (``cv2.AffineFeature``'s ``maxTilt``; 2 simulates slants up
        to 60 degrees with 11 views).
    ratio : float
        Lowe's ratio against the nearest distinct keypoint (:func:`distinct_ratio_matches`).
    snap_px : float
        A match joins the tracks of the stored keypoints within this distance of its ends.
    """

    def __init__(self, camera: PinholeCamera, config: FrontEndConfig, max_tilt: float = 2.0,
                 ratio: float = 0.85, snap_px: float = 2.0) -> None:
        self.camera = camera
        self.max_tilt = float(max_tilt)
        self.snap_px = float(snap_px)
        # simulated views: tilts sqrt(2)^k up to max_tilt, rotations 72 / t degrees apart
        n_views = 1 + sum(len(np.arange(0.0, 180.0, 72.0 / t)) for t in self._tilts())
        # detect_features keeps the strongest max_features: allow that many per simulated view
        self.config = replace(config, max_features=config.max_features * n_views)
        self._frontend_config = config
        self.ratio = float(ratio)
        self._matcher = DescriptorMatcher(ratio, True, config.flann_trees, config.flann_checks)
        self._detector = None
        self._cache: dict[int, Features] = {}

    def _tilts(self) -> list[float]:
        out, t = [], np.sqrt(2.0)
        while t <= self.max_tilt + 1e-9:
            out.append(float(t))
            t *= np.sqrt(2.0)
        return out

    def features(self, frame_id: int, images: Callable[[int], np.ndarray]) -> Features:
        """Affine-simulated features of a frame's image (cached by frame id: ``images``,
        frame id -> image, is only called for a frame not seen yet; descriptors
        RootSIFT-normalised)."""
        f = self._cache.get(int(frame_id))
        if f is None:
            if self._detector is None:
                self._detector = affine_detector(self._frontend_config, self.max_tilt)
            f = detect_features(images(int(frame_id)), self.camera, self.config, self._detector)
            f = replace(f, descriptors=root_normalise(f.descriptors))
            self._cache[int(frame_id)] = f
        return f

    def clear(self) -> None:
        """Drop the cached features."""
        self._cache.clear()

    def match(self, ref_id: int, frame_id: int, images: Callable[[int], np.ndarray]) -> tuple[Array, Array, int]:
        """Epipolar-consistent affine matches ``(uv_ref, uv, n_matches)`` of two frames'
        images (``images``: frame id -> image)."""
        fa, fb = self.features(ref_id, images), self.features(frame_id, images)
        ia, ib = distinct_ratio_matches(self._matcher, fa, fb, self.ratio)
        n = int(len(ia))
        c = self._frontend_config
        _, inl = essential_ransac(fa.uv[ia], fb.uv[ib], self.camera.K, c.ransac_threshold_px,
                                  c.ransac_confidence, c.ransac_method)
        return fa.uv[ia[inl]], fb.uv[ib[inl]], n

    def relate(self, frontend, ref_id: int, frame_id: int, images: Callable[[int], np.ndarray]) -> WideMatch:
        """Match frame ``frame_id`` to frame ``ref_id`` (:meth:`match`) and join the tracks
        of the stored keypoints both ends of a match land on (``frontend``: a
        :class:`~eifslam.frontend.frontend.FrontEnd` holding both frames)."""
        uv_ref, uv, n = self.match(ref_id, frame_id, images)
        fr, fk = frontend.frame(ref_id), frontend.frame(frame_id)
        a = snap_to_keypoints(uv_ref, fr.uv, self.snap_px)
        b = snap_to_keypoints(uv, fk.uv, self.snap_px)
        both = (a >= 0) & (b >= 0)
        if both.any():
            # one pair per keypoint of the frame (the first match wins)
            _, first = np.unique(b[both], return_index=True)
            sel = np.flatnonzero(both)[np.sort(first)]
            frontend.join_tracks(frame_id, b[sel], fr.track_ids[a[sel]])
            joined = int(len(sel))
        else:
            joined = 0
        return WideMatch(int(ref_id), int(frame_id), uv_ref, uv, n, joined)
