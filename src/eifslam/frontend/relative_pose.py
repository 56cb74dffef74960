"""Relative pose ``ZR``, ``ZT`` between two frames from their ``Ωp`` correspondences.

Five-point essential matrix in RANSAC and the cheirality test (OpenCV), a
Gauss-Newton refinement on the inliers' Sampson error; on a wide pair whose inliers a
homography mostly explains, the homography's decompositions as further hypotheses (refined
by Levenberg-Marquardt; one replaces the essential matrix's pose only with significantly
more inliers, :func:`best_supported_pose`); the inliers that carry much of the pose's
information checked against the pose the others give (:func:`confirm_leveraged`); on a wide
pair, the inliers chosen again at the pair's own noise (:func:`tighten_to_noise`); a parallax
check on the pose that is kept; and the first-order covariance
(:mod:`eifslam.frontend.uncertainty`). A pixel pair given twice (SIFT's orientation twins) is
one correspondence.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.stats import binom

from ..geometry.camera import PinholeCamera
from ..geometry.rotations import rotmat_to_quat
from ..estimation.measurements import RelativePose
from .config import FrontEndConfig
from .matching import essential_ransac, homography_ransac
from .results import Reason, RelativePoseResult
from .twoview import (
    cheirality_mask,
    median_parallax_deg,
    pose_error,
    refine_pose,
    rotation_only_parallax_deg,
    sampson_jacobian,
    sampson_residuals,
)
from .uncertainty import first_order_covariance, is_valid_covariance

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["best_supported_pose", "confirm_leveraged", "estimate_relative_pose", "pose_from_essential",
           "tighten_to_noise"]

#: refinement of a homography's pose (:func:`best_supported_pose`): at most this many rounds of
#: re-classified inliers, of this many Levenberg-Marquardt steps each
_CANDIDATE_ROUNDS, _CANDIDATE_ITERATIONS = 3, 5
#: ... with Levenberg-Marquardt from this damping (the essential matrix's pose keeps the
#: undamped Gauss-Newton everything else was measured with)
_CANDIDATE_DAMPING = 1e-3
#: a refinement of the essential matrix's pose moving it further than this (degrees) is
#: rejected as diverged
_MAX_REFINE_STEP_DEG = 5.0
#: the homography's decompositions are tried on pairs with at least this median parallax
#: (degrees). On narrow pairs the count of inliers does not tell translation directions
#: apart: on kitti-seq1 with ORB (0.2-0.8 deg) decompositions 80 deg off the true direction
#: had significantly more inliers than the essential matrix's pose 2-4 deg off (the pair's
#: outliers, near-static image points, fit the wrong pose), and on kitti-07 with SIFT one
#: at 0.6 deg (47 deg off) replaced a 26-inlier pose 0.9 deg off. The twin poses this is
#: for come from wide pairs; with this bound every switch on the shared data sets (SIFT and
#: ORB) moves to a pose nearer the ground truth, and none happens on the video sequences.
_PLANE_PARALLAX_DEG = 5.0
#: level of the test that a homography's pose explains more correspondences (:func:`_significantly_more`)
_SWITCH_ALPHA = 0.05
#: an inlier whose leverage (its share of the pose's information, mean 5/n) is above this
#: many times the mean is checked against the pose of the others (:func:`confirm_leveraged`);
#: 2 is the usual flag for high leverage in regression diagnostics (Hoaglin & Welsch, 1978)
_LEVERAGE_FLAG = 2.0
#: on a wide pair, an inlier whose Sampson residual is beyond this many robust standard
#: deviations of the inliers' residuals (``1.4826 × median |r|``) is dropped
#: (:func:`tighten_to_noise`); 3 is the two-sided 99.7% bound of a Gaussian
_NOISE_SIGMAS = 3.0


def pose_from_essential(
    E: Array, uv_i: Array, uv_j: Array, K: Array, inliers: NDArray[np.bool_]
) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Decompose an OpenCV essential matrix with the cheirality test.

    Returns
    -------
    R_ij : (3, 3); t_ij : (3,) unit; inliers : (N,) bool (RANSAC and cheirality).
    """
    mask = inliers.astype(np.uint8).reshape(-1, 1).copy()
    _, R_cv, t_cv, mask = cv2.recoverPose(
        E, np.ascontiguousarray(uv_i, np.float64), np.ascontiguousarray(uv_j, np.float64),
        np.asarray(K, np.float64), mask=mask,
    )
    # OpenCV: x_j = R_cv x_i + t_cv  =>  R_ij = R_cv.T, t_ij ∝ -R_cv.T t_cv
    R = R_cv.T
    t = -R_cv.T @ t_cv.reshape(3)
    n = np.linalg.norm(t)
    t = t / n if n > 0 else np.array([0.0, 0.0, 1.0])
    return R, t, mask.reshape(-1) > 0


def _refine(R, t, ui, uj, bi, bj, inl, K, config: FrontEndConfig, max_step_deg: float = _MAX_REFINE_STEP_DEG,
            rounds: int = 2, iterations: int | None = None, damping: float = 0.0):
    """Gauss-Newton (Levenberg-Marquardt with ``damping``, :func:`refine_pose`) on the
    inliers, re-classify every correspondence by its Sampson residual and cheirality at the
    refined pose, refine again on the new inlier set, for at most ``rounds`` rounds of
    ``iterations`` (default ``config.refine_iterations``) steps.
    A refinement moving the pose by more than ``max_step_deg`` is not taken (diverged: on a
    low-parallax pair the cost is flat along the direction, and a far pose with a few more
    inliers is not a better one)."""
    for _ in range(rounds):
        R2, t2, _ = refine_pose(R, t, ui[inl], uj[inl], K, iterations or config.refine_iterations, damping)
        if np.degrees(np.linalg.norm(pose_error(R, t, R2, t2))) > max_step_deg:
            break  # diverged: keep the pose it started from
        r = sampson_residuals(R2, t2, ui, uj, K)
        new = (np.abs(r) < config.ransac_threshold_px) & cheirality_mask(R2, t2, bi, bj)
        R, t = R2, t2
        if np.array_equal(new, inl) or new.sum() < config.min_inliers:
            break
        inl = new
    return R, t, inl


def _homography_poses(ui: Array, uj: Array, K: Array, threshold_px: float, n_inliers: int
                      ) -> list[tuple[Array, Array]]:
    """Relative poses ``(R_ij, t_ij)`` (``t`` unit) from the decomposition of a homography
    fitted to the correspondences in RANSAC (OpenCV), when it holds most of the essential
    matrix's ``n_inliers``; empty otherwise.

    When most correspondences lie on one plane (a facade), five-point samples are near
    degenerate and RANSAC can stop at the plane's twin pose, which explains the plane and
    not the points off it; the homography's decompositions are then the other hypotheses
    worth scoring."""
    H, mask = homography_ransac(ui, uj, 2.0 * threshold_px)
    if H is None or 2 * int(mask.sum()) < n_inliers:
        return []
    out = []
    for R_cv, t_cv in zip(*cv2.decomposeHomographyMat(H, np.asarray(K, np.float64))[1:3]):
        t = -R_cv.T @ np.asarray(t_cv, np.float64).reshape(3)  # as in pose_from_essential
        n = np.linalg.norm(t)
        if n > 1e-9:
            out.append((np.asarray(R_cv.T, np.float64), t / n))
    return out


def best_supported_pose(
    R: Array, t: Array, inl: NDArray[np.bool_], ui: Array, uj: Array, bi: Array, bj: Array, K: Array,
    config: FrontEndConfig,
) -> tuple[Array, Array, NDArray[np.bool_]]:
    """The refined essential matrix's pose, or, on a wide pair (median parallax at least
    :data:`_PLANE_PARALLAX_DEG`) whose inliers a homography mostly holds, a decomposition's
    (:func:`_homography_poses`) that has significantly more inliers (:func:`_significantly_more`),
    or, when neither has, a lower robust cost (:func:`_msac_cost`: the twin poses of a
    facade can hold the same correspondences within the inlier threshold, 61 of 62 each on
    strecha-castle-p30's first pair, and the residuals then tell the true pose, 1.4° from
    the ground truth, from its twins, 6° and 14°).

    Inliers are RANSAC's own criterion: Sampson residual below ``ransac_threshold_px`` and
    in front of both cameras. On a dominant plane RANSAC can stop at the plane's twin pose;
    the decompositions are the hypotheses its sampler missed.

    Parameters
    ----------
    R : (3, 3) ``R_ij``; t : (3,) unit ``t_ij``
        The pose from the essential matrix.
    inl : (N,) bool
        Its inliers.
    ui, uj : (N, 2)
        Undistorted pixels in images *i* and *j*.
    bi, bj : (N, 3)
        Their unit bearings, camera frames *i* and *j*.
    K : (3, 3)
    config : FrontEndConfig
        Uses ``refine_iterations``, ``ransac_threshold_px``, ``min_inliers``.

    Returns
    -------
    R : (3, 3); t : (3,) unit; inliers : (N,) bool
    """
    best = _refine(R, t, ui, uj, bi, bj, inl, K, config)
    if median_parallax_deg(best[0], bi[best[2]], bj[best[2]]) < _PLANE_PARALLAX_DEG:
        return best  # a narrow pair: inlier counts do not tell directions apart
    for Rh, th in _homography_poses(ui, uj, K, config.ransac_threshold_px, int(best[2].sum())):
        if np.degrees(np.linalg.norm(pose_error(best[0], best[1], Rh, th))) < 1.0:
            continue  # the pose already found
        inl_h = (np.abs(sampson_residuals(Rh, th, ui, uj, K)) < config.ransac_threshold_px) & \
            cheirality_mask(Rh, th, bi, bj)
        if inl_h.sum() < config.min_inliers:
            continue
        # a decomposition is only near the pose it stands for (the homography fits the plane
        # alone, and along the plane's ambiguity the cost is flat and ill-conditioned: the
        # points off the plane join the inliers a few at a time): damped steps, more rounds,
        # no step bound, and the test judges
        cand = _refine(Rh, th, ui, uj, bi, bj, inl_h, K, config, np.inf, _CANDIDATE_ROUNDS,
                       _CANDIDATE_ITERATIONS, _CANDIDATE_DAMPING)
        if _significantly_more(cand[2], best[2]) or (
                not _significantly_more(best[2], cand[2])
                and _msac_cost(cand, ui, uj, K, config) < _msac_cost(best, ui, uj, K, config)):
            best = cand
    return best


def _msac_cost(pose: tuple[Array, Array, NDArray[np.bool_]], ui: Array, uj: Array, K: Array,
               config: FrontEndConfig) -> float:
    """MSAC's cost of a pose ``(R, t, inliers)`` (Torr & Zisserman, 2000): the squared Sampson
    residuals of its inliers, pixels², and the squared threshold ``ransac_threshold_px`` for
    every other correspondence."""
    r2 = np.asarray(sampson_residuals(pose[0], pose[1], ui, uj, K), float) ** 2
    return float(np.where(pose[2], np.minimum(r2, config.ransac_threshold_px ** 2),
                          config.ransac_threshold_px ** 2).sum())


def _significantly_more(a: NDArray[np.bool_], b: NDArray[np.bool_]) -> bool:
    """Whether inlier set *a* holds significantly more of the correspondences than *b*:
    McNemar's exact test on the correspondences the two classify differently (under "as
    good as each other" each is *a*'s alone with probability 1/2), one-sided, level
    :data:`_SWITCH_ALPHA`. Two poses that explain different halves of a low-parallax pair
    (kitti-seq1 with ORB: 244 against 243 inliers, 9 of them each one's alone, directions
    84 deg apart) are not told apart by one inlier."""
    only_a, only_b = int(np.sum(a & ~b)), int(np.sum(b & ~a))
    return only_a > only_b and float(binom.sf(only_a - 1, only_a + only_b, 0.5)) < _SWITCH_ALPHA


def _fail(reason: str, n_common: int, t0: float, **kw) -> RelativePoseResult:
    ms = {"relative_pose": (time.perf_counter() - t0) * 1e3, "covariance": 0.0}
    return RelativePoseResult(ok=False, reason=reason, measurement=None, n_common=n_common,
                              timings_ms=ms, **kw)


def confirm_leveraged(
    R: Array, t: Array, inl: NDArray[np.bool_], ui: Array, uj: Array, bi: Array, bj: Array, K: Array,
    config: FrontEndConfig,
) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Inliers of high leverage kept only if the pose of the other inliers agrees with them.

    A correspondence with a large share of the pose's information (its leverage
    ``h = J_k (JᵀJ)⁻¹ J_kᵀ``, which sums to 5 over the inliers) pulls the pose towards itself,
    so its own residual is small even when it is wrong: a few mismatches together, alone in
    a part of the image, can pass the inlier test at the pose they bend and shrink the
    covariance severalfold (strecha-herzjesu-p25's pair 19-20: three wrong matches with
    leverage 0.3 each, docs/frontend.md). Inliers with leverage above
    :data:`_LEVERAGE_FLAG` times the mean are classified again, by the same residual and
    cheirality test, at the pose refined on the others; those that fail are dropped and the
    pose is refined on the rest. Only on wide pairs (median parallax at least
    :data:`_PLANE_PARALLAX_DEG`): on a narrow one the high-leverage inliers are what fixes
    the translation's direction, and the others' pose can be anywhere along it.

    Parameters
    ----------
    R, t, inl, ui, uj, bi, bj, K
        As :func:`best_supported_pose`, with ``R, t`` the refined pose and ``inl`` its inliers.
    config : FrontEndConfig
        Uses ``refine_iterations``, ``ransac_threshold_px``, ``min_inliers``.

    Returns
    -------
    R : (3, 3); t : (3,) unit; inliers : (N,) bool
        Unchanged when every flagged inlier agrees, on a narrow pair, or when too few are
        left to test them.
    """
    idx = np.flatnonzero(inl)
    n = len(idx)
    if n < 2 * config.min_inliers or median_parallax_deg(R, bi[idx], bj[idx]) < _PLANE_PARALLAX_DEG:
        return R, t, inl  # a narrow pair: the others alone do not fix the translation's direction
    J = sampson_jacobian(R, t, ui[idx], uj[idx], K)[1]
    H = J.T @ J
    if not np.all(np.isfinite(H)) or np.linalg.cond(H) > 1e12:
        return R, t, inl
    h = np.einsum("ij,jk,ik->i", J, np.linalg.inv(H), J)
    flag = h > _LEVERAGE_FLAG * 5.0 / n
    if not flag.any() or n - flag.sum() < config.min_inliers:
        return R, t, inl
    R2, t2, _ = refine_pose(R, t, ui[idx[~flag]], uj[idx[~flag]], K, config.refine_iterations)
    if np.degrees(np.linalg.norm(pose_error(R, t, R2, t2))) > _MAX_REFINE_STEP_DEG:
        return R, t, inl  # diverged without them: they cannot be checked
    test = idx[flag]
    agree = (np.abs(sampson_residuals(R2, t2, ui[test], uj[test], K)) < config.ransac_threshold_px) \
        & cheirality_mask(R2, t2, bi[test], bj[test])
    if agree.all():
        return R, t, inl
    kept = inl.copy()
    kept[test[~agree]] = False
    R3, t3, _ = refine_pose(R2, t2, ui[kept], uj[kept], K, config.refine_iterations)
    return R3, t3, kept


def tighten_to_noise(
    R: Array, t: Array, inl: NDArray[np.bool_], ui: Array, uj: Array, bi: Array, bj: Array, K: Array,
    config: FrontEndConfig,
) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Inliers of a wide pair chosen again at the pair's own noise, and the pose refined on them.

    RANSAC's threshold (``config.ransac_threshold_px``, 1 px) must hold on every image, but
    SIFT's keypoints are good to 0.1-0.3 px on still images, so at 1 px a wide pair admits
    matches several real standard deviations off, and they bend the pose: on the Strecha
    sets the accepted relative poses were 3-6 times further from the ground truth than the
    map's own residuals make their stated covariance (docs/frontend.md). Here the threshold
    becomes ``min(ransac_threshold_px, 3 σ̂)``, with ``σ̂ = 1.4826 median |r|`` the robust
    standard deviation of the inliers' Sampson residuals at the refined pose (0.24-0.40 px
    on the SIFT sets), and the pose is refined on the inliers within it. Only on wide
    pairs (median parallax at least :data:`_PLANE_PARALLAX_DEG`): on narrow ones the
    residuals do not tell a wrong direction apart (applied to every pair, it sends kitti-07
    to its far minimum on every seed); and only when at least half of the inliers, and
    ``config.min_inliers``, are kept.

    Parameters
    ----------
    R, t, inl, ui, uj, bi, bj, K
        As :func:`confirm_leveraged`.
    config : FrontEndConfig
        Uses ``ransac_threshold_px``, ``min_inliers``, ``refine_iterations``.

    Returns
    -------
    R : (3, 3); t : (3,) unit; inliers : (N,) bool
        Unchanged on a narrow pair, when every inlier is within the bound, or when too few are.
    """
    idx = np.flatnonzero(inl)
    if len(idx) < config.min_inliers or median_parallax_deg(R, bi[idx], bj[idx]) < _PLANE_PARALLAX_DEG:
        return R, t, inl
    r = np.abs(sampson_residuals(R, t, ui, uj, K))
    tau = min(config.ransac_threshold_px, _NOISE_SIGMAS * 1.4826 * float(np.median(r[idx])))
    kept = inl & (r < tau)
    n_kept = int(kept.sum())
    if n_kept == len(idx) or n_kept < max(config.min_inliers, 0.5 * len(idx)):
        return R, t, inl
    R2, t2, _ = refine_pose(R, t, ui[kept], uj[kept], K, config.refine_iterations)
    return R2, t2, kept


def estimate_relative_pose(
    uv_i: Array,
    uv_j: Array,
    camera: PinholeCamera,
    config: FrontEndConfig,
    i: int = 0,
    j: int = 1,
    track_ids: IntArray | None = None,
) -> RelativePoseResult:
    """Relative pose of camera *j* seen from camera *i*, with its 5x5 covariance.

    Parameters
    ----------
    uv_i, uv_j : (N, 2)
        Corresponding undistorted pixels of ``Ωp`` tracks in images *i* and *j*.
    camera : PinholeCamera
    config : FrontEndConfig
        Uses ``min_common, min_inliers, min_parallax_deg, ransac_*, refine_iterations,
        sigma_px``.
    i, j : int
        Frame ids stored in the measurement.
    track_ids : (N,) int64, optional
        Ids of the correspondences, to report the inliers.

    Returns
    -------
    RelativePoseResult
        ``ok`` with a :class:`~eifslam.estimation.measurements.RelativePose`, or a reason.
    """
    t0 = time.perf_counter()
    ui = np.asarray(uv_i, np.float64).reshape(-1, 2)
    uj = np.asarray(uv_j, np.float64).reshape(-1, 2)
    ids = np.asarray(track_ids if track_ids is not None else np.zeros(0), np.int64)
    # a pixel pair given twice is one correspondence, not two: SIFT gives a keypoint one copy
    # per dominant orientation, and both copies become tracks with the same pixels
    # (docs/frontend.md, "SIFT's orientation twins"); counted twice, it would double its
    # weight in RANSAC's consensus and its information in the covariance
    _, first = np.unique(np.c_[ui, uj], axis=0, return_index=True)
    if len(first) < len(ui):
        first.sort()
        if len(ids) == len(ui):
            ids = ids[first]
        ui, uj = ui[first], uj[first]
    n = len(ui)
    if n < max(config.min_common, 5):
        return _fail(Reason.TOO_FEW_COMMON, n, t0)
    K = camera.K
    bi_all, bj_all = camera.bearing(ui), camera.bearing(uj)
    # pure rotation / repeated frame: decided before any solver (which may fail or pick an
    # arbitrary baseline on such input), and again on the RANSAC inliers below
    residual = rotation_only_parallax_deg(bi_all, bj_all)
    if residual < config.min_rotation_residual_deg:
        return _fail(Reason.NO_PARALLAX, n, t0, parallax_deg=residual)
    E, inl = essential_ransac(ui, uj, K, config.ransac_threshold_px, config.ransac_confidence,
                              config.ransac_method)
    if E is None or inl.sum() < config.min_inliers:
        return _fail(Reason.ESSENTIAL_FAILED if E is None else Reason.TOO_FEW_INLIERS, n, t0,
                     n_inliers=int(inl.sum()))
    residual = rotation_only_parallax_deg(bi_all[inl], bj_all[inl])
    if residual < config.min_rotation_residual_deg:
        return _fail(Reason.NO_PARALLAX, n, t0, n_inliers=int(inl.sum()), parallax_deg=residual)
    R, t, inl = pose_from_essential(E, ui, uj, K, inl)
    if inl.sum() < config.min_inliers:
        return _fail(Reason.TOO_FEW_INLIERS, n, t0, n_inliers=int(inl.sum()), parallax_deg=residual)
    R, t, inl = best_supported_pose(R, t, inl, ui, uj, bi_all, bj_all, K, config)
    R, t, inl = confirm_leveraged(R, t, inl, ui, uj, bi_all, bj_all, K, config)
    R, t, inl = tighten_to_noise(R, t, inl, ui, uj, bi_all, bj_all, K, config)
    parallax = median_parallax_deg(R, bi_all[inl], bj_all[inl])
    if parallax < config.min_parallax_deg:
        return _fail(Reason.NO_PARALLAX, n, t0, n_inliers=int(inl.sum()), parallax_deg=parallax)
    n_in = int(inl.sum())
    if n_in < config.min_inliers:
        return _fail(Reason.TOO_FEW_INLIERS, n, t0, n_inliers=n_in, parallax_deg=parallax)
    ui, uj = ui[inl], uj[inl]
    J = sampson_jacobian(R, t, ui, uj, K)[1]
    t1 = time.perf_counter()
    P = first_order_covariance(J, config.sigma_px)
    t2 = time.perf_counter()
    timings = {"relative_pose": (t1 - t0) * 1e3, "covariance": (t2 - t1) * 1e3}
    kw = dict(n_common=n, n_inliers=n_in, parallax_deg=parallax, timings_ms=timings,
              inlier_track_ids=ids[inl] if len(ids) == len(inl) else np.zeros(0, np.int64))
    if not (is_valid_covariance(P) and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return RelativePoseResult(ok=False, reason=Reason.DEGENERATE, measurement=None, **kw)
    meas = RelativePose(i=int(i), j=int(j), q_ij=rotmat_to_quat(R), t_ij=t, cov=P, n_inliers=n_in)
    return RelativePoseResult(ok=True, reason=Reason.OK, measurement=meas, **kw)
