"""Relative pose ``ZR``, ``ZT`` between two frames from their ``Ωp`` correspondences.

Five-point essential matrix in RANSAC and the cheirality test (OpenCV), a parallax check,
an optional Gauss-Newton refinement on the inliers' Sampson error, and the covariance
(first order or unscented transform, :mod:`eifslam.frontend.uncertainty`).
"""

from __future__ import annotations

import time

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from ..geometry.rotations import rotmat_to_quat
from ..estimation.measurements import RelativePose
from .config import FrontEndConfig
from .matching import essential_ransac
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
from .uncertainty import first_order_covariance, is_valid_covariance, unscented_covariance

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["estimate_relative_pose", "pose_from_essential"]

#: a refinement moving the pose further than this (degrees) is rejected as diverged
_MAX_REFINE_STEP_DEG = 5.0


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


def _refine(R, t, ui, uj, bi, bj, inl, K, config: FrontEndConfig):
    """Gauss-Newton on the inliers, re-classify every correspondence by its Sampson
    residual and cheirality at the refined pose, refine again on the new inlier set."""
    for _ in range(2):
        R2, t2, _ = refine_pose(R, t, ui[inl], uj[inl], K, config.refine_iterations)
        if np.degrees(np.linalg.norm(pose_error(R, t, R2, t2))) > _MAX_REFINE_STEP_DEG:
            break  # diverged: keep the RANSAC answer
        r = sampson_residuals(R2, t2, ui, uj, K)
        new = (np.abs(r) < config.ransac_threshold_px) & cheirality_mask(R2, t2, bi, bj)
        R, t = R2, t2
        if np.array_equal(new, inl) or new.sum() < config.min_inliers:
            break
        inl = new
    return R, t, inl


def _fail(reason: str, n_common: int, t0: float, **kw) -> RelativePoseResult:
    ms = {"relative_pose": (time.perf_counter() - t0) * 1e3, "covariance": 0.0}
    return RelativePoseResult(ok=False, reason=reason, measurement=None, n_common=n_common,
                              timings_ms=ms, **kw)


def _covariance(R, t, ui, uj, K, J, config: FrontEndConfig) -> Array:
    if config.covariance == "fast":
        return first_order_covariance(J, config.sigma_px)
    n = len(ui)
    m = min(n, config.ut_max_points)
    sel = np.linspace(0, n - 1, m).round().astype(int)
    P = unscented_covariance(R, t, ui[sel], uj[sel], K, config.sigma_px)
    return P * (m / n)


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
        Uses ``min_common, min_inliers, min_parallax_deg, ransac_*, refine*, sigma_px,
        covariance, ut_max_points``.
    i, j : int
        Frame ids stored in the measurement.
    track_ids : (N,) int64, optional
        Ids of the correspondences, to report the inliers.

    Returns
    -------
    RelativePoseResult
        ``ok`` with a :class:`~eifslam.measurements.RelativePose`, or a reason.
    """
    t0 = time.perf_counter()
    ui = np.asarray(uv_i, np.float64).reshape(-1, 2)
    uj = np.asarray(uv_j, np.float64).reshape(-1, 2)
    ids = np.asarray(track_ids if track_ids is not None else np.zeros(0), np.int64)
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
    parallax = median_parallax_deg(R, bi_all[inl], bj_all[inl])
    if parallax < config.min_parallax_deg:
        return _fail(Reason.NO_PARALLAX, n, t0, n_inliers=int(inl.sum()), parallax_deg=parallax)
    if config.refine:
        R, t, inl = _refine(R, t, ui, uj, bi_all, bj_all, inl, K, config)
    n_in = int(inl.sum())
    if n_in < config.min_inliers:
        return _fail(Reason.TOO_FEW_INLIERS, n, t0, n_inliers=n_in, parallax_deg=parallax)
    ui, uj = ui[inl], uj[inl]
    J = sampson_jacobian(R, t, ui, uj, K)[1]
    t1 = time.perf_counter()
    P = _covariance(R, t, ui, uj, K, J, config)
    t2 = time.perf_counter()
    timings = {"relative_pose": (t1 - t0) * 1e3, "covariance": (t2 - t1) * 1e3}
    kw = dict(n_common=n, n_inliers=n_in, parallax_deg=parallax, timings_ms=timings,
              inlier_track_ids=ids[inl] if len(ids) == len(inl) else np.zeros(0, np.int64))
    if not (is_valid_covariance(P) and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return RelativePoseResult(ok=False, reason=Reason.DEGENERATE, measurement=None, **kw)
    meas = RelativePose(i=int(i), j=int(j), q_ij=rotmat_to_quat(R), t_ij=t, cov=P, n_inliers=n_in)
    return RelativePoseResult(ok=True, reason=Reason.OK, measurement=meas, **kw)
