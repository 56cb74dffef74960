"""Descriptor matching (ratio test, mutual check) and the epipolar RANSAC check (OpenCV).

Paper III-F: descriptor matches are hypotheses; the epipolar constraint, checked inside
RANSAC with the five-point solver and the known intrinsics, keeps the consistent ones.
"""

from __future__ import annotations

import threading
import zlib
from dataclasses import dataclass

import cv2
import faiss
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree


Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["DescriptorIndex", "DescriptorMatcher", "ImageMotion", "essential_ransac", "guided_search",
           "homography_ransac", "image_motion", "lone_candidate_bound", "row_distances", "windowed_match"]

#: Neighbours searched in a prebuilt index of all rows to find the nearest free ones.
FREE_SEARCH = 8
#: Float descriptors are matched exactly, from the matrix of all their distances (one BLAS
#: product), while the pairs of free rows number at most this squared (two sides of this
#: many rows each); a FLANN k-d forest is built and searched only above it. ``benchmarks/matching.py`` (SIFT
#: on the shared sets, one thread): with every keypoint of two frames free (up to
#: 2000 x 2000) the exact match costs half to two thirds of FLANN's two searches of
#: prebuilt indices (14 against 22-26 ms), with half of them free (the older frames'
#: search) a fifth to a third (2-4 against 10-13 ms); the matrix of 2500 x 2500
#: distances takes 25 MB.
EXACT_ROWS = 2500

_EMPTY = (np.zeros(0, np.int64), np.zeros(0, np.int64))


def _claimed_once(i1: IntArray, i2: IntArray) -> tuple[IntArray, IntArray]:
    """The matches ``(i1, i2)`` with each train row ``i2`` claimed by its first match only
    (a train row can be claimed twice without the mutual check), in their order."""
    _, first = np.unique(i2, return_index=True)
    first = np.sort(first)
    return i1[first], i2[first]


#: Median distance of a descriptor to its second-nearest keypoint of a whole frame,
#: measured with tracked keypoints on a hand-held and a rendered sequence: SIFT (L2, the
#: descriptors' norm is 512) 300 on both; ORB (Hamming) 44 of its 256 bits, scaled here
#: by the bits of other binary descriptors.
SECOND_NEAREST_SIFT = 300.0
SECOND_NEAREST_BIT_FRACTION = 44.0 / 256.0

_POPCOUNT = np.array([bin(i).count("1") for i in range(256)], np.uint8)


def lone_candidate_bound(descriptors: NDArray, ratio: float) -> float:
    """The distance below which the nearest keypoint of a search window may be taken: ``ratio``
    times the median whole-frame second-nearest distance of descriptors of this kind
    (:data:`SECOND_NEAREST_SIFT` for float descriptors, :data:`SECOND_NEAREST_BIT_FRACTION`
    of the bits of binary ones). A candidate passes where a ratio test against a typical
    second-nearest keypoint of the frame would have passed it; alone in its window, this
    is its only test.

    Parameters
    ----------
    descriptors : (N, D) ndarray
        ``uint8`` binary or float descriptors (only the kind and width are used).
    ratio : float
        Lowe's ratio.
    """
    if descriptors.dtype == np.uint8:
        return float(ratio) * SECOND_NEAREST_BIT_FRACTION * 8 * descriptors.shape[1]
    return float(ratio) * SECOND_NEAREST_SIFT


def row_distances(a: NDArray, b: NDArray) -> Array:
    """Distances ``(P,)`` between the rows of ``a`` and ``b`` (both ``(P, D)``): Hamming for
    ``uint8`` binary descriptors, L2 for float ones."""
    if a.dtype == np.uint8:
        x = np.bitwise_xor(a, b)
        if hasattr(np, "bitwise_count") and x.shape[1] % 8 == 0:  # NumPy >= 2: eight bytes at a time
            bits = np.bitwise_count(np.ascontiguousarray(x).view(np.uint64))
            return bits.sum(axis=1, dtype=np.int64).astype(np.float64)
        return _POPCOUNT[x].sum(axis=1, dtype=np.int64).astype(np.float64)
    diff = np.asarray(a, np.float32) - np.asarray(b, np.float32)
    return np.sqrt(np.einsum("ij,ij->i", diff, diff, dtype=np.float64))


def guided_search(q: NDArray, uv_predicted: Array, t: NDArray, uv: Array, radius_px: float, ratio: float,
                  lone_bound: float, mutual: bool = False) -> tuple[IntArray, IntArray, Array]:
    """Search by projection: each query descriptor among the keypoints near its prediction.

    The candidates of query ``i`` are the keypoints within ``radius_px`` of
    ``uv_predicted[i]`` (a k-d tree of the keypoints); descriptor distances are computed to
    those only. The nearest candidate is kept when its distance is below ``lone_bound``
    (:func:`lone_candidate_bound`) and, when the window holds others, it passes Lowe's
    ratio test against the second nearest inside the window.

    Parameters
    ----------
    q : (M, D) query descriptors.
    uv_predicted : (M, 2) pixels where each query is expected.
    t : (N, D) the keypoints' descriptors, of the same kind as ``q``.
    uv : (N, 2) the keypoints' pixels.
    radius_px : float
        Search radius, pixels.
    ratio : float
        Keep when ``d1 < ratio * d2`` (best and second-best candidates of the window).
    lone_bound : float
        Keep only when ``d1 < lone_bound`` (the only test of a lone candidate).
    mutual : bool
        Also require the query to be the nearest of the keypoint's own candidates (the
        queries whose windows hold it).

    Returns
    -------
    rows : (K,) int64 query rows that found a keypoint, ascending.
    kp : (K,) int64 their keypoints (a keypoint may be the nearest of several queries).
    dist : (K,) float64 their descriptor distances.
    """
    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if len(q) == 0 or len(t) == 0:
        return empty
    pairs = cKDTree(np.asarray(uv_predicted, float)).sparse_distance_matrix(
        cKDTree(np.asarray(uv, float)), float(radius_px), output_type="ndarray")
    if len(pairs) == 0:
        return empty
    qi, kj = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
    d = row_distances(q[qi], t[kj])
    order = np.lexsort((kj, d, qi))  # by query, then distance (ties: lower keypoint)
    qi, kj, d = qi[order], kj[order], d[order]
    rows, first, count = np.unique(qi, return_index=True, return_counts=True)
    d1 = d[first]
    d2 = np.where(count > 1, d[np.minimum(first + 1, len(d) - 1)], np.inf)
    ok = (d1 < lone_bound) & (d1 < ratio * d2)  # d2 is inf for a lone candidate
    if mutual:
        back = np.lexsort((qi, d, kj))  # by keypoint, then distance (ties: lower query)
        kp, kfirst = np.unique(kj[back], return_index=True)
        nearest = np.full(len(t), -1, np.int64)
        nearest[kp] = qi[back][kfirst]
        ok &= nearest[kj[first]] == rows
    return rows[ok], kj[first[ok]], d1[ok]


@dataclass(frozen=True)
class ImageMotion:
    """How a frame's keypoints moved since the frame before, to predict where they are next.

    Attributes
    ----------
    flow : (N, 2) float64
        Image velocity of each keypoint, pixels per frame: its displacement from its match
        in the frame before (an epipolar inlier); a keypoint without one takes the median
        of its nearest matched neighbours' (``FLOW_NEIGHBOURS``).
    radius_px : float
        Search radius for the next frame, pixels: the ``PREDICTION_QUANTILE`` of this
        frame's prediction errors (how far its matches landed from where the frame before
        predicted them), at least ``MIN_RADIUS_PX``; ``inf`` (search the whole next frame)
        when there was no prediction or that quantile exceeds ``MAX_RADIUS_PX`` (still
        images, a jolt): a window is searched only once the prediction has been seen to
        hold. A windowed search sees only the errors inside its window, so the radius
        shrinks while the prediction holds; when it stops holding, the window finds fewer
        matches than its ``reference`` and the whole frame is searched again.
    reference : int
        Epipolar inliers of the last whole-frame search: a window that finds fewer than a
        fraction of them has missed and the whole frame is searched again.
    """

    flow: Array
    radius_px: float
    reference: int


#: Matched neighbours whose median flow a keypoint without a match takes.
FLOW_NEIGHBOURS = 5
#: Quantile of the prediction errors the search window covers, and its bounds (pixels:
#: the keypoints' localisation noise below, a fast turn's image motion above).
PREDICTION_QUANTILE = 0.99
MIN_RADIUS_PX, MAX_RADIUS_PX = 8.0, 64.0


def image_motion(uv: Array, uv_previous: Array, rows: IntArray, rows_previous: IntArray,
                 previous: ImageMotion | None, whole_frame: bool) -> ImageMotion | None:
    """The :class:`ImageMotion` of a frame from its matches with the frame before.

    Parameters
    ----------
    uv : (N, 2) the frame's keypoints, pixels.
    uv_previous : (N2, 2) the previous frame's keypoints, pixels.
    rows, rows_previous : (M,) int64 matched rows of the two (epipolar inliers).
    previous : ImageMotion or None
        The previous frame's motion (the prediction the matches are compared with).
    whole_frame : bool
        Whether the matches come from a search of the whole frame (they then set the
        reference) or of the previous motion's windows (which keep it).

    Returns
    -------
    ImageMotion or None
        None with fewer than ``FLOW_NEIGHBOURS`` matches (nothing to predict from).
    """
    rows, rows_previous = np.asarray(rows, np.int64), np.asarray(rows_previous, np.int64)
    if len(rows) < FLOW_NEIGHBOURS:
        return None
    flow = np.empty((len(uv), 2))
    step = uv[rows] - uv_previous[rows_previous]
    flow[rows] = step
    lone = np.ones(len(uv), bool)
    lone[rows] = False
    if lone.any():
        _, nn = cKDTree(uv[rows]).query(uv[lone], k=FLOW_NEIGHBOURS)
        flow[lone] = np.median(step[nn], axis=1)
    radius = np.inf
    if previous is not None:
        radius = max(float(np.quantile(np.linalg.norm(step - previous.flow[rows_previous], axis=1),
                                       PREDICTION_QUANTILE)), MIN_RADIUS_PX)
    reference = previous.reference if previous is not None and not whole_frame else int(len(rows))
    return ImageMotion(flow, radius if radius <= MAX_RADIUS_PX else np.inf, reference)


def windowed_match(d_new: NDArray, uv_new: Array, d_old: NDArray, uv_old_predicted: Array, radius_px: float,
                   ratio: float, free_new: NDArray[np.bool_] | None = None,
                   free_old: NDArray[np.bool_] | None = None) -> tuple[IntArray, IntArray]:
    """Match a new frame's keypoints to an older frame's near where those are predicted.

    Each free new keypoint is compared only with the free old keypoints predicted within
    ``radius_px`` of it (:func:`guided_search`: Lowe's ratio test inside the window, and
    the bound of :func:`lone_candidate_bound` for the nearest) and must be the nearest of
    all new keypoints whose windows hold the old one (the mutual check, which also leaves
    each old keypoint to one new one).

    Parameters
    ----------
    d_new, d_old : (N1, D), (N2, D) descriptors of one kind (float for L2, ``uint8`` binary
        for Hamming).
    uv_new : (N1, 2) the new keypoints, pixels.
    uv_old_predicted : (N2, 2) where the old keypoints are predicted in the new frame.
    radius_px : float
    ratio : float
    free_new, free_old : (N1,), (N2,) bool, optional
        Only these rows may be matched (default: all).

    Returns
    -------
    (idx_new, idx_old) : two (M,) int64 arrays of matched rows, ascending in ``idx_new``,
        each row used at most once.
    """
    rn = np.flatnonzero(np.ones(len(d_new), bool) if free_new is None else free_new)
    ro = np.flatnonzero(np.ones(len(d_old), bool) if free_old is None else free_old)
    if len(rn) == 0 or len(ro) == 0:
        return _EMPTY
    rows, kp, _ = guided_search(d_new[rn], uv_new[rn], d_old[ro], uv_old_predicted[ro], radius_px, ratio,
                                lone_candidate_bound(d_old, ratio), mutual=True)
    return rn[rows], ro[kp]  # the mutual check leaves each old keypoint to one new one


class DescriptorIndex:
    """The descriptors of one keypoint set, prepared once for nearest-neighbour queries.

    Float descriptors (SIFT) get a FLANN k-d forest, built once (:meth:`build`, or
    on the first query) and kept, so a frame's index serves every query against it (as the
    train set of the next frames' matches and in the mutual checks); :meth:`DescriptorMatcher.match`
    uses it only for more than ``EXACT_ROWS`` rows and matches fewer exactly. Binary
    descriptors (ORB, AKAZE) are searched exactly by brute force (Hamming) with FAISS's
    flat binary index, which counts bits with the processor's own instruction: on 7-Scenes
    frames of 2000 ORB keypoints a 2-nearest search of one frame in another takes 3.8 ms
    against OpenCV's 18.8 ms (``cv2.batchDistance``, the same neighbours and distances).
    FAISS runs single-threaded here (``faiss.omp_set_num_threads(1)``): the front end's
    threads are the parallelism.

    With a ``seed``, the forest's random trees are drawn from OpenCV's generator set to
    ``seed`` plus a checksum of the descriptors: the same descriptors give the same index,
    and so the same neighbours, in whichever thread and at whatever time it is built.
    Queries may come from several threads (they take turns).

    Parameters
    ----------
    descriptors : (N, D) ndarray
        ``uint8`` binary or float descriptors.
    trees, checks : int
        FLANN randomised k-d trees (float descriptors) and leaves visited per query.
    seed : int, optional
        See above; None draws from the building thread's generator as it is.
    """

    def __init__(self, descriptors: NDArray, trees: int = 4, checks: int = 48, seed: int | None = None) -> None:
        self.binary = descriptors.dtype == np.uint8
        self.descriptors = np.ascontiguousarray(descriptors if self.binary else np.asarray(descriptors, np.float32))
        self._trees, self._checks = int(trees), int(checks)
        self._seed = None if seed is None else int(seed)
        self._flann = None
        self._binary_index = None
        self._lock = threading.Lock()

    @property
    def prebuilt(self) -> bool:
        """Whether the index has a structure worth keeping (FLANN: float descriptors, more
        than ``EXACT_ROWS`` of them), rather than an exact search."""
        return not self.binary and len(self.descriptors) > EXACT_ROWS

    def __len__(self) -> int:
        return len(self.descriptors)

    def build(self) -> None:
        """Build the FLANN index now when it is worth keeping (:attr:`prebuilt`; else a
        FLANN query builds it first). Its random trees are drawn from OpenCV's generator
        (``cv2.setRNGSeed``; seeded from the descriptors when the index has a ``seed``)."""
        if self.prebuilt:
            self._build()

    def _build(self) -> None:
        with self._lock:
            if self._flann is None and not self.binary and len(self.descriptors):
                if self._seed is not None:
                    cv2.setRNGSeed((self._seed + zlib.crc32(self.descriptors)) % 2**31)
                self._flann = cv2.flann_Index(self.descriptors, {"algorithm": 1, "trees": self._trees})

    def _hamming_index(self) -> "faiss.IndexBinaryFlat":
        """The exact Hamming index of binary descriptors, made on the first query."""
        with self._lock:
            if self._binary_index is None:
                faiss.omp_set_num_threads(1)
                index = faiss.IndexBinaryFlat(8 * self.descriptors.shape[1])
                index.add(self.descriptors)
                self._binary_index = index
            return self._binary_index

    def knn(self, q: NDArray, k: int) -> tuple[IntArray, Array]:
        """The ``k`` nearest indexed descriptors of each query row.

        Parameters
        ----------
        q : (M, D) descriptors of the same kind.
        k : int >= 1

        Returns
        -------
        idx : (M, k) int64 rows of the indexed descriptors, nearest first; -1 where there
            are fewer than ``k`` (or FLANN found fewer).
        dist : (M, k) float64 distances (L2 for float, Hamming for binary); inf where ``idx`` is -1.
        """
        m, n = len(q), len(self.descriptors)
        idx = np.full((m, k), -1, np.int64)
        dist = np.full((m, k), np.inf)
        kk = min(int(k), n)
        if m == 0 or kk == 0:
            return idx, dist
        if self.binary:
            d, i = self._hamming_index().search(np.ascontiguousarray(q, np.uint8), kk)
            d = d.astype(np.float64)
        else:
            self._build()
            with self._lock:
                i, d = self._flann.knnSearch(np.ascontiguousarray(q, np.float32), kk, params={"checks": self._checks})
            d = np.sqrt(np.maximum(d.astype(np.float64), 0.0))  # FLANN returns squared L2
        i = np.asarray(i, np.int64).reshape(m, kk)
        d = np.asarray(d, np.float64).reshape(m, kk)
        bad = (i < 0) | (i >= n)
        i[bad], d[bad] = -1, np.inf
        idx[:, :kk], dist[:, :kk] = i, d
        return idx, dist


class DescriptorMatcher:
    """Nearest-neighbour descriptor matching with Lowe's ratio test and a mutual check.

    Float descriptors (SIFT) use a FLANN k-d forest; binary ones (ORB, AKAZE) a
    brute-force Hamming search (:class:`DescriptorIndex`).

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
        self.trees, self.checks = int(trees), int(checks)
        self._flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": self.trees}, {"checks": self.checks})
        self._hamming = cv2.BFMatcher(cv2.NORM_HAMMING)

    def index(self, descriptors: NDArray, seed: int | None = None) -> DescriptorIndex:
        """A :class:`DescriptorIndex` of ``descriptors (N, D)`` with this matcher's FLANN
        settings (and ``seed``, see there)."""
        return DescriptorIndex(descriptors, self.trees, self.checks, seed)

    def knn(self, q: NDArray, t: NDArray, k: int) -> list:
        """The ``k`` nearest descriptors of ``t (N2, D)`` for each of ``q (N1, D)``:
        OpenCV ``DMatch`` lists (Hamming for ``uint8`` binary descriptors, FLANN k-d
        trees for float ones)."""
        if q.dtype == np.uint8:
            return self._hamming.knnMatch(q, t, k=k)
        return self._flann.knnMatch(np.asarray(q, np.float32), np.asarray(t, np.float32), k=k)

    def match(self, d1: NDArray, d2: NDArray, free1: NDArray[np.bool_] | None = None,
              free2: NDArray[np.bool_] | None = None, index1: DescriptorIndex | None = None,
              index2: DescriptorIndex | None = None) -> tuple[IntArray, IntArray]:
        """Match descriptors ``d1 (N1, D)`` to ``d2 (N2, D)``.

        Parameters
        ----------
        d1, d2 : (N1, D), (N2, D) descriptors.
        free1, free2 : (N1,), (N2,) bool, optional
            Only these rows may be matched (default: all).
        index1, index2 : DescriptorIndex, optional
            Prebuilt indices of all of ``d1`` / ``d2``, used by the FLANN search of float
            descriptors (more free rows than ``EXACT_ROWS`` squared pairs): the nearest
            free rows are taken from a search of all rows (``_search``); without one the
            search runs on the free rows only, the same matches up to FLANN's
            approximation. Fewer pairs of float descriptors are matched exactly
            (:meth:`_exact`), and binary ones by brute force on the free rows (a search of
            the free rows costs less than one of all); neither uses the indices.

        Returns
        -------
        (idx1, idx2) : two (M,) int64 arrays of matched rows, each row used at most once.
        """
        f1 = np.ones(len(d1), bool) if free1 is None else np.asarray(free1, bool)
        f2 = np.ones(len(d2), bool) if free2 is None else np.asarray(free2, bool)
        if f1.sum() < 2 or f2.sum() < 2:
            return _EMPTY
        rows1 = np.flatnonzero(f1)
        if d1.dtype != np.uint8 and len(rows1) * int(f2.sum()) <= EXACT_ROWS ** 2:
            return self._exact(d1[rows1], d2[f2], rows1, np.flatnonzero(f2))
        nn, dd = self._search(d1[rows1], d2, f2, index2, 2)
        ok = (nn[:, 0] >= 0) & np.isfinite(dd[:, 1]) & (dd[:, 0] < self.ratio * dd[:, 1])
        i1, i2 = rows1[ok], nn[ok, 0]
        if len(i1) == 0:
            return _EMPTY
        if self.mutual:
            cand = np.unique(i2)
            back, _ = self._search(d2[cand], d1, f1, index1, 1)
            best = np.full(len(d2), -1, np.int64)
            best[cand] = back[:, 0]
            keep = best[i2] == i1
            i1, i2 = i1[keep], i2[keep]
        return _claimed_once(i1, i2)

    def _exact(self, a: NDArray, b: NDArray, rows_a: IntArray, rows_b: IntArray) -> tuple[IntArray, IntArray]:
        """:meth:`match` of float descriptors ``a (N1, D)`` and ``b (N2, D)`` (N1, N2 >= 2)
        from the matrix of their squared L2 distances: each row's two nearest columns for
        the ratio test and each column's nearest row for the mutual check. Returns the
        matches as rows of ``rows_a`` and ``rows_b``."""
        a, b = np.asarray(a, np.float32), np.asarray(b, np.float32)
        D = np.einsum("ij,ij->i", a, a)[:, None] + np.einsum("ij,ij->i", b, b)[None, :]
        D -= 2.0 * (a @ b.T)
        rows = np.arange(len(a))
        nearest = D.argmin(axis=1)
        d1 = D[rows, nearest]  # (a copy) the nearest; the second nearest with it set aside
        D[rows, nearest] = np.inf
        d2 = np.maximum(D.min(axis=1), 0.0)
        D[rows, nearest] = d1
        i1 = np.flatnonzero(d1 < self.ratio ** 2 * d2)  # squared distances: the ratio squared
        i2 = nearest[i1]
        if self.mutual:
            keep = D[:, i2].argmin(axis=0) == i1  # each column's nearest row
            i1, i2 = i1[keep], i2[keep]
        i1, i2 = _claimed_once(i1, i2)
        return rows_a[i1], rows_b[i2]

    def _search(self, q: NDArray, t: NDArray, free: NDArray[np.bool_], index: DescriptorIndex | None,
                k: int) -> tuple[IntArray, Array]:
        """The ``k`` nearest free rows of ``t`` for each row of ``q``, in ``t``'s numbering.

        With a prebuilt ``index`` of all of ``t``, the ``FREE_SEARCH`` nearest rows of all
        are searched and the first ``k`` free ones kept: the free rows' own nearest
        neighbours unless more than ``FREE_SEARCH - k`` taken rows are nearer. A free
        neighbour not among them gets -1 and, as its distance, the farthest one searched
        (a lower bound of its distance, so a ratio test against it is passed only when
        the true one would be). Without an index the free rows are searched alone.
        Missing neighbours (fewer rows): -1 and inf.
        """
        if index is not None and index.prebuilt and len(index) == len(t):
            if free.all():
                return index.knn(q, k)
            nn, dd = index.knn(q, max(FREE_SEARCH, k))
            ok = (nn >= 0) & free[np.maximum(nn, 0)]
            rank = np.cumsum(ok, axis=1)
            out_n = np.full((len(q), k), -1, np.int64)
            out_d = np.full((len(q), k), np.inf)
            bound = dd[:, -1] if len(t) > nn.shape[1] else np.full(len(q), np.inf)  # all searched: none left
            for j in range(k):
                hit = ok & (rank == j + 1)
                row, col = np.nonzero(hit)
                out_n[row, j], out_d[row, j] = nn[row, col], dd[row, col]
                miss = ~hit.any(axis=1)
                out_d[miss, j] = bound[miss]
            return out_n, out_d
        rows = np.flatnonzero(free)
        sub = t if len(rows) == len(t) else t[rows]
        nn, dd = self.index(sub).knn(q, k)
        return np.where(nn >= 0, rows[np.maximum(nn, 0)], -1), dd


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


def homography_ransac(uv1: Array, uv2: Array, threshold_px: float, confidence: float = 0.995,
                      method: str = "usac") -> tuple[Array | None, NDArray[np.bool_]]:
    """Homography in RANSAC (OpenCV) between undistorted pixels, ``uv2 ~ H uv1``.

    Two uses: the decompositions of a dominant plane's homography are relative-pose
    hypotheses (:func:`~eifslam.frontend.relative_pose.best_supported_pose`), and its
    inliers check descriptor matches where the epipolar check cannot be made. Without
    parallax (a camera standing still, or only rotating) every essential matrix ``[t]x R``
    with the right ``R`` fits every correspondence whatever ``t``: five-point samples are
    degenerate and :func:`essential_ransac` may find no model at all (an identical frame
    twice). The image motion is then a homography (``K R K^-1``), which still tells right
    matches from wrong ones.

    Parameters
    ----------
    uv1, uv2 : (N, 2) corresponding undistorted pixels.
    threshold_px : float
        Transfer-error threshold, pixels.
    confidence : float
        (OpenCV's default 0.995.)
    method : {"usac", "magsac", "ransac"}

    Returns
    -------
    H : (3, 3) or None when no homography was found (fewer than 4 points, or OpenCV failed).
    inliers : (N,) bool, all False without ``H``.
    """
    n = len(uv1)
    none = np.zeros(n, bool)
    if n < 4:
        return None, none
    try:
        H, mask = cv2.findHomography(np.ascontiguousarray(uv1, np.float64), np.ascontiguousarray(uv2, np.float64),
                                     _METHODS[method], float(threshold_px), confidence=float(confidence))
    except cv2.error:
        return None, none
    if H is None or mask is None or not np.all(np.isfinite(H)):
        return None, none
    return np.asarray(H, np.float64), mask.reshape(-1).astype(bool)
