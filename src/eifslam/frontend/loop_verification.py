"""Geometric verification of a place-recognition candidate (OpenCV).

A candidate loop (current frame *k*, old frame *j*) is accepted only when both hold:

1. **Map-feature PnP**: the current frame's descriptors, matched (ratio test, mutual) to
   the descriptors of old map features, give a camera pose by ``cv2.solvePnPRansac`` that
   fits at least :func:`min_inliers` of the matches within the chi-square reprojection
   radius ``sigma_px * sqrt(chi2_2(0.99))``.
2. **Five-point**: the two frames' keypoints, matched directly, fit one essential matrix
   (``essential_ransac``) with at least :func:`min_inliers` inliers under the epipolar
   version of the same argument, and its relative rotation agrees with the one the PnP
   pose and the old frame's estimated orientation imply. (The inlier count alone is not
   enough: on 300 shuffled matches USAC's optimised essential matrix gathered 25 inliers
   where the binomial bound asked for 23.)

The inlier counts are not tuned constants: :func:`min_inliers` is the smallest count that
wrong matches (uniform over the image) reach by chance with probability below ``alpha``
over every RANSAC hypothesis (a binomial tail), with a floor.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from ..geometry.rotations import rotmat_to_quat
from .matching import DescriptorMatcher, essential_ransac
from .twoview import rotation_only_parallax_deg

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["FivePoint", "PlaceCheck", "chi2_radius", "five_point", "match_to_frame", "match_to_map", "min_inliers",
           "verify_place"]

#: 99% quantile of chi-square with 2 degrees of freedom (a pixel residual).
CHI2_2DOF_99 = 9.21


def chi2_radius(sigma_px: float) -> float:
    """Reprojection radius (pixels) inside which 99% of correct ``sigma_px`` measurements fall."""
    return float(sigma_px) * float(np.sqrt(CHI2_2DOF_99))


def min_inliers(n_matches: int, p_chance: float, hypotheses: int, alpha: float, floor: int) -> int:
    """Smallest inlier count that chance does not explain.

    Parameters
    ----------
    n_matches : int
        Putative matches.
    p_chance : float
        Probability that a wrong match falls inside the inlier region of a wrong model
        (e.g. the area of the reprojection disc over the image area).
    hypotheses : int
        Models RANSAC tries (a union bound over all of them).
    alpha : float
        Accepted probability of a chance model reaching the count.
    floor : int
        Never fewer than this.

    Returns
    -------
    int
        ``max(floor, n)`` with ``hypotheses * P(Binomial(n_matches, p_chance) >= n) <= alpha``.
    """
    from scipy.stats import binom

    p = float(np.clip(p_chance, 0.0, 1.0))
    n = int(binom.isf(alpha / max(int(hypotheses), 1), int(n_matches), p)) + 1 if n_matches > 0 else 1
    return max(int(floor), n)


@dataclass(frozen=True)
class PlaceCheck:
    """The outcome of :func:`verify_place` (an expected failure is a value).

    Attributes
    ----------
    ok : bool
    reason : str, why it failed ("" when ok).
    matches : putative descriptor matches to the map features.
    inliers : PnP inliers.
    required : the inlier count required (:func:`min_inliers`) of the PnP.
    five_point_inliers, five_point_required : the same for the five-point check.
    p, q : (3,), (4,) camera centre and ``q_wc`` of the current frame from the PnP (in
        the old map's frame), or None.
    keypoints : (M,) indices of the current frame's keypoints that are PnP inliers (also
        when only the five-point check failed, so that a caller can choose another old
        frame for it).
    features : (M,) indices (into the given map features) they observe.
    """

    ok: bool
    reason: str = ""
    matches: int = 0
    inliers: int = 0
    required: int = 0
    five_point_inliers: int = 0
    five_point_required: int = 0
    p: Array | None = None
    q: Array | None = None
    keypoints: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    features: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))


def _map_required(camera: PinholeCamera, n: int, sigma_px: float, floor: int, alpha: float, iterations: int) -> int:
    r = chi2_radius(sigma_px)
    return min_inliers(n, np.pi * r * r / float(camera.width * camera.height), iterations, alpha, floor)


def match_to_map(camera: PinholeCamera, matcher: DescriptorMatcher, desc_k: NDArray, desc_X: NDArray,
                 sigma_px: float, floor: int = 25, alpha: float = 1e-6, iterations: int = 1000
                 ) -> tuple[IntArray, IntArray, int]:
    """Descriptor matches of the current frame to map features, and the PnP inlier count
    :func:`verify_place` will require of them.

    The first step of :func:`verify_place`, which needs no feature position: a caller can
    refuse a candidate with too few matches (``len(ia) < required``) before it has
    the positions.

    Returns
    -------
    ia, ib : (M,) indices into ``desc_k`` and ``desc_X``.
    required : int
    """
    return _matched(matcher, desc_k, desc_X, floor,
                    lambda n: _map_required(camera, n, sigma_px, floor, alpha, iterations))


def _matched(matcher: DescriptorMatcher, desc_k: NDArray, desc_o: NDArray, floor: int, required
             ) -> tuple[IntArray, IntArray, int]:
    """Matches of ``desc_k`` to ``desc_o`` and ``required(len(matches))`` (none, and the floor,
    with fewer than two descriptors on a side)."""
    if len(desc_k) < 2 or len(desc_o) < 2:
        z = np.zeros(0, np.int64)
        return z, z, max(int(floor), 1)
    ia, ib = matcher.match(desc_k, np.asarray(desc_o, desc_k.dtype))
    ia, ib = np.asarray(ia, np.int64), np.asarray(ib, np.int64)
    return ia, ib, required(len(ia))


def _frame_required(camera: PinholeCamera, n: int, sigma_px: float, floor: int, alpha: float, iterations: int) -> int:
    r = chi2_radius(sigma_px)
    p_band = 2.0 * r * float(np.hypot(camera.width, camera.height)) / float(camera.width * camera.height)
    return min_inliers(n, p_band, iterations, alpha, floor)


def match_to_frame(camera: PinholeCamera, matcher: DescriptorMatcher, desc_k: NDArray, desc_j: NDArray,
                   sigma_px: float, floor: int = 25, alpha: float = 1e-6, iterations: int = 1000
                   ) -> tuple[IntArray, IntArray, int]:
    """Direct descriptor matches of the current frame to the old frame, and the five-point
    inlier count :func:`verify_place` will require of them (an epipolar band of the
    chi-square radius, :func:`min_inliers`).

    Cheaper than :func:`match_to_map` (one frame's descriptors, not a place's): a caller
    can refuse a candidate with fewer matches than required before matching the map,
    which :func:`verify_place` would refuse all the same.

    Returns
    -------
    ja, jb : (M,) indices into ``desc_k`` and ``desc_j``.
    required : int
    """
    return _matched(matcher, desc_k, desc_j, floor,
                    lambda n: _frame_required(camera, n, sigma_px, floor, alpha, iterations))


@dataclass(frozen=True)
class FivePoint:
    """The five-point relation of the current frame *k* to an old frame *j* from their direct
    matches (:func:`five_point`).

    Attributes
    ----------
    inliers, required : int
        Essential-matrix inliers and the count chance does not explain (:func:`min_inliers`).
    R_kj : (3, 3) or None
        Rotation from camera *k*'s frame to camera *j*'s (``x_j = R_kj x_k``), when the
        inliers reach the count.
    parallax_deg : float
        Median angle, degrees, between the inliers' two rays once the rotation that aligns
        them best is taken out (a lower bound of the parallax): below a couple of degrees the
        essential matrix is degenerate and ``R_kj`` undetermined.
    """

    inliers: int
    required: int
    R_kj: Array | None = None
    parallax_deg: float = 0.0


def five_point(camera: PinholeCamera, uv_k: Array, uv_j: Array, direct: tuple[IntArray, IntArray], sigma_px: float,
               floor: int = 25, alpha: float = 1e-6, iterations: int = 1000) -> FivePoint:
    """The essential matrix of the direct matches ``direct`` (indices into ``uv_k`` and
    ``uv_j``, undistorted pixels (N, 2)) with the epipolar band of the chi-square radius, its
    inlier count against :func:`min_inliers`, and, when that is reached, the relative rotation
    and the inliers' parallax. Cheap next to the map match and the PnP of
    :func:`verify_place`, so a caller can test the rotation first."""
    ja, jb = (np.asarray(d, np.int64) for d in direct)
    need = _frame_required(camera, len(ja), sigma_px, floor, alpha, iterations)
    if len(ja) < need:
        return FivePoint(0, need)
    E, inl = essential_ransac(uv_k[ja], uv_j[jb], camera.K, chi2_radius(sigma_px), 0.9999)
    n = int(inl.sum()) if E is not None else 0
    if n < need:
        return FivePoint(n, need)
    _, R, _, _ = cv2.recoverPose(E[:3, :3], uv_k[ja][inl], uv_j[jb][inl], camera.K)
    # the parallax left by the rotation that best aligns the two rays of every inlier, not
    # by the essential matrix's own rotation: on a baseline near zero the essential matrix
    # is degenerate and its rotation, and the angles it leaves, arbitrary (the twisted pair
    # turns half a revolution)
    parallax = rotation_only_parallax_deg(camera.bearing(uv_k[ja][inl]), camera.bearing(uv_j[jb][inl]))
    return FivePoint(n, need, R, parallax)


def verify_place(camera: PinholeCamera, matcher: DescriptorMatcher, uv_k: Array, desc_k: NDArray,
                 X: Array, desc_X: NDArray, uv_j: Array, desc_j: NDArray, sigma_px: float, p_j: Array, R_wc_j: Array, *,
                 max_rot_deg: float = 2.0, min_parallax_deg: float = 2.0, floor: int = 25, alpha: float = 1e-6, iterations: int = 1000,
                 matches: tuple[IntArray, IntArray] | None = None,
                 direct: tuple[IntArray, IntArray] | None = None) -> PlaceCheck:
    """Verify that frame *k* sees the place of old map features and of old frame *j*.

    Parameters
    ----------
    camera : PinholeCamera
    matcher : DescriptorMatcher
        The front end's matcher (ratio test, mutual check).
    uv_k, desc_k : (N, 2) undistorted pixels and (N, D) descriptors of the current frame.
    X, desc_X : (F, 3) map feature positions and (F, D) descriptors (of an observation).
    uv_j, desc_j : keypoints and descriptors of the old frame (five-point check).
    sigma_px : float
        Standard deviation of a keypoint, pixels (the ``Zm`` sigma).
    p_j, R_wc_j : (3,), (3, 3)
        Centre and orientation of the old frame in the old map (the filter's estimate).
    max_rot_deg : float
        Largest angle between the relative rotation of the five-point model and the one
        the PnP pose and ``R_wc_j`` imply (a chance essential matrix fitted to wrong
        matches rotates anywhere).
    min_parallax_deg : float
        The rotation is compared only when the baseline between the two frames (PnP
        centre to ``p_j``) subtends at least this angle at the median depth of the PnP
        inliers: on a shorter baseline the essential matrix is degenerate and its
        rotation undetermined.
    floor, alpha, iterations : see :func:`min_inliers`; ``iterations`` is also the RANSAC
        budget of each model.
    matches : ((M,), (M,)) int arrays, optional
        The matches of ``desc_k`` to ``desc_X`` when the caller already has them
        (:func:`match_to_map`); rows of ``X`` that no match uses are then never read.
    direct : ((M,), (M,)) int arrays, optional
        The matches of ``desc_k`` to ``desc_j`` when the caller already has them
        (:func:`match_to_frame`).

    Returns
    -------
    PlaceCheck
    """
    r = chi2_radius(sigma_px)
    if len(desc_k) < 2 or len(desc_X) < 2:
        return PlaceCheck(False, "too few descriptors")
    ia, ib, need = match_to_map(camera, matcher, desc_k, desc_X, sigma_px, floor, alpha, iterations) \
        if matches is None else (*matches, _map_required(camera, len(matches[0]), sigma_px, floor, alpha, iterations))
    n = len(ia)
    if n < need:
        return PlaceCheck(False, "too few matches to the map", matches=n, required=need)
    K = camera.K
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        np.ascontiguousarray(X[ib], np.float64), np.ascontiguousarray(uv_k[ia], np.float64), K, None,
        iterationsCount=int(iterations), reprojectionError=r, confidence=0.9999, flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < 6:
        return PlaceCheck(False, "PnP failed", matches=n, required=need)
    inl = inl.reshape(-1)
    rvec, tvec = cv2.solvePnPRefineLM(X[ib][inl], uv_k[ia][inl], K, None, rvec, tvec)
    if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return PlaceCheck(False, "PnP failed", matches=n, required=need)
    R, _ = cv2.Rodrigues(rvec)
    Xc = X[ib] @ R.T + tvec.reshape(1, 3)
    z = Xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        h = np.stack([camera.fx * Xc[:, 0] / z + camera.cx, camera.fy * Xc[:, 1] / z + camera.cy], 1)
    good = (z > 0) & np.all(np.isfinite(h), 1) & (np.linalg.norm(h - uv_k[ia], axis=1) <= r)
    m = int(good.sum())
    p = (-R.T @ tvec.reshape(3)).astype(float)
    q = rotmat_to_quat(R.T)
    if m < need:
        return PlaceCheck(False, "too few PnP inliers", matches=n, inliers=m, required=need, p=p, q=q)
    ja, jb, need5 = match_to_frame(camera, matcher, desc_k, desc_j, sigma_px, floor, alpha, iterations) \
        if direct is None else (*direct, _frame_required(camera, len(direct[0]), sigma_px, floor, alpha, iterations))
    n5, rot = 0, 180.0
    if len(ja) >= need5:
        E, in5 = essential_ransac(uv_k[ja], uv_j[jb], K, r, 0.9999)
        n5 = int(in5.sum()) if E is not None else 0
        baseline = float(np.linalg.norm(p - np.asarray(p_j, float)))
        depth = float(np.median(z[good])) if good.any() else np.inf
        if n5 >= need5 and baseline < depth * np.tan(np.radians(min_parallax_deg)):
            rot = 0.0  # no parallax: the rotation of E is undetermined, not evidence either way
        elif n5 >= need5:
            _, R5, _, _ = cv2.recoverPose(E[:3, :3], uv_k[ja][in5], uv_j[jb][in5], K)
            R_pred = np.asarray(R_wc_j, float).T @ R.T  # camera k to camera j, from the PnP
            rot = float(np.degrees(np.arccos(np.clip((np.trace(R5.T @ R_pred) - 1.0) / 2.0, -1.0, 1.0))))
    common = dict(matches=n, inliers=m, required=need, five_point_inliers=n5, five_point_required=need5, p=p, q=q)
    if n5 < need5:
        return PlaceCheck(False, "too few five-point inliers", keypoints=ia[good].astype(np.int64),
                          features=ib[good].astype(np.int64), **common)
    if rot > max_rot_deg:
        return PlaceCheck(False, "five-point rotation disagrees with the PnP", **common)
    return PlaceCheck(True, "", keypoints=ia[good].astype(np.int64), features=ib[good].astype(np.int64), **common)
