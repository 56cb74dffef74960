"""Descriptor matching (ratio test, mutual check) and the epipolar RANSAC check (OpenCV).

Paper III-F: descriptor matches are hypotheses; the epipolar constraint, checked inside
RANSAC with the five-point solver and the known intrinsics, keeps the consistent ones.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["DescriptorMatcher", "essential_ransac"]

_EMPTY = (np.zeros(0, np.int64), np.zeros(0, np.int64))


class DescriptorMatcher:
    """Nearest-neighbour descriptor matching with Lowe's ratio test and a mutual check.

    Float descriptors (SIFT, SURF) use a FLANN k-d forest; binary ones (ORB, AKAZE) a
    brute-force Hamming matcher.

    Parameters
    ----------
    ratio : float
        Keep a match when ``d1 < ratio * d2`` (best and second-best distances).
    mutual : bool
        Also require the query to be the train point's nearest neighbour.
    trees : int
        Randomised k-d trees of the FLANN index (float descriptors).
    checks : int
        Leaves visited per FLANN query.
    """

    def __init__(self, ratio: float = 0.8, mutual: bool = True, trees: int = 4, checks: int = 48) -> None:
        self.ratio = float(ratio)
        self.mutual = bool(mutual)
        self._flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": int(trees)}, {"checks": int(checks)})
        self._hamming = cv2.BFMatcher(cv2.NORM_HAMMING)

    def knn(self, q: NDArray, t: NDArray, k: int) -> list:
        """The ``k`` nearest descriptors of ``t (N2, D)`` for each of ``q (N1, D)``:
        OpenCV ``DMatch`` lists (Hamming for ``uint8`` binary descriptors, FLANN k-d
        trees for float ones)."""
        if q.dtype == np.uint8:
            return self._hamming.knnMatch(q, t, k=k)
        return self._flann.knnMatch(np.asarray(q, np.float32), np.asarray(t, np.float32), k=k)

    def match(self, d1: NDArray, d2: NDArray) -> tuple[IntArray, IntArray]:
        """Match descriptors ``d1 (N1, D)`` to ``d2 (N2, D)``.

        Returns
        -------
        (idx1, idx2) : two (M,) int64 arrays of matched rows, each row used at most once.
        """
        if len(d1) < 2 or len(d2) < 2:
            return _EMPTY
        knn = self.knn(d1, d2, 2)
        q, tr = [], []
        for m in knn:
            if len(m) == 2 and m[0].distance < self.ratio * m[1].distance:
                q.append(m[0].queryIdx)
                tr.append(m[0].trainIdx)
        i1 = np.asarray(q, np.int64)
        i2 = np.asarray(tr, np.int64)
        if len(i1) == 0:
            return _EMPTY
        if self.mutual:
            cand = np.unique(i2)
            back = self.knn(d2[cand], d1, 1)
            best = np.full(len(d2), -1, np.int64)
            best[cand] = [m[0].trainIdx if len(m) else -1 for m in back]
            keep = best[i2] == i1
            i1, i2 = i1[keep], i2[keep]
        # a train row must not be claimed twice (possible without the mutual check)
        _, first = np.unique(i2, return_index=True)
        first = np.sort(first)
        return i1[first], i2[first]


_METHODS = {"usac": cv2.USAC_DEFAULT, "magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC}


def essential_ransac(
    uv1: Array, uv2: Array, K: Array, threshold_px: float, confidence: float, method: str = "usac"
) -> tuple[Array | None, NDArray[np.bool_]]:
    """Five-point essential matrix in RANSAC (OpenCV) between undistorted pixels.

    Parameters
    ----------
    uv1, uv2 : (N, 2) corresponding undistorted pixels in images 1 and 2.
    K : (3, 3) intrinsics.
    threshold_px : float
        Inlier threshold on the epipolar distance, pixels.
    confidence : float
    method : {"usac", "magsac", "ransac"}

    Returns
    -------
    E : (3, 3) OpenCV essential matrix (``x2.T E x1 = 0``) or None when it failed.
    inliers : (N,) bool
    """
    n = len(uv1)
    none = np.zeros(n, bool)
    if n < 5:
        return None, none
    try:
        E, mask = cv2.findEssentialMat(
            np.ascontiguousarray(uv1, np.float64),
            np.ascontiguousarray(uv2, np.float64),
            np.asarray(K, np.float64),
            method=_METHODS[method],
            prob=confidence,
            threshold=threshold_px,
        )
    except cv2.error:
        return None, none
    if E is None or mask is None or E.shape[0] < 3 or not np.all(np.isfinite(E[:3])):
        return None, none
    return np.asarray(E[:3], np.float64), mask.reshape(-1).astype(bool)
