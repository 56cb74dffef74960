"""The pose of one image from known map features (`estimation/localisation.py`)."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.stats import chi2

from eifslam.estimation.localisation import localise_pose, map_pose_covariance
from eifslam.geometry.rotations import quat_conjugate, quat_exp, quat_log, quat_multiply, quat_to_rotmat
from eifslam.sim.synthetic import default_camera

SIGMA = 0.5  # pixel noise of the synthetic observations, px


def facade(rng: np.random.Generator, n: int, p: np.ndarray, q: np.ndarray, depth: tuple[float, float]):
    """``n`` points in front of the camera ``(p, q)`` at ``depth`` (m) and their noisy pixels."""
    cam = default_camera()
    uv = rng.uniform([20, 20], [cam.width - 20, cam.height - 20], (n, 2))
    z = rng.uniform(*depth, n)
    Xc = np.c_[(uv[:, 0] - cam.cx) / cam.fx * z, (uv[:, 1] - cam.cy) / cam.fy * z, z]
    X = Xc @ quat_to_rotmat(q).T + p
    return X, uv + rng.normal(0.0, SIGMA, uv.shape)


def pose_nees(p: np.ndarray, q: np.ndarray, p_true: np.ndarray, q_true: np.ndarray, C: np.ndarray) -> float:
    """NEES of the estimate ``(p, q)`` in ``[dp, dtheta]`` (``R_true = R Exp(dtheta)``)."""
    d = np.r_[p_true - p, quat_log(quat_multiply(quat_conjugate(q), q_true))]
    return float(d @ np.linalg.solve(C, d))


def test_localisation_is_consistent_with_its_covariance():
    """From a start 0.3 m and 3 degrees off, the pose's errors over 40 scenes have the mean
    NEES of six degrees of freedom (two-sided 99% interval of the mean) against
    :func:`map_pose_covariance` at the pixel noise."""
    cam = default_camera()
    nees = []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        p_true, q_true = rng.normal(0.0, 1.0, 3), quat_exp(rng.normal(0.0, 0.3, 3))
        X, uv = facade(rng, 150, p_true, q_true, (6.0, 20.0))
        p0 = p_true + 0.3 * rng.normal(size=3) / np.sqrt(3)
        q0 = quat_multiply(q_true, quat_exp(np.radians(3.0) * rng.normal(size=3) / np.sqrt(3)))
        sol = localise_pose(cam, p0, q0, X, uv, iterations=20)
        assert sol is not None and sol[2].all()
        C = map_pose_covariance(cam, sol[0], sol[1], X, SIGMA)
        nees.append(pose_nees(sol[0], sol[1], p_true, q_true, C))
    n = len(nees)
    lo, hi = chi2.ppf([0.005, 0.995], 6 * n) / n
    assert lo < np.mean(nees) < hi


def test_wrong_points_close_to_the_camera_do_not_drag_the_pose():
    """A tenth of the map points are wrong and 1-3 m from the camera, among correct ones
    15-25 m away: their Jacobians are ten times the others', so under Huber's weight alone
    they pulled a pose that started at the truth far off (over these 20 scenes, a median
    NEES of about 2,000 before the χ² cut, and down to 76% of the correct points within
    4 px). With it, every pose stays within the χ²₆ 99.9% bound of its covariance, and
    the wrong points are not inliers."""
    cam = default_camera()
    bound = chi2.ppf(0.999, 6)
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        p_true, q_true = rng.normal(0.0, 1.0, 3), quat_exp(rng.normal(0.0, 0.3, 3))
        X, uv = facade(rng, 150, p_true, q_true, (15.0, 25.0))
        X_bad, _ = facade(rng, 15, p_true, q_true, (1.0, 3.0))
        uv_bad = rng.uniform([20, 20], [cam.width - 20, cam.height - 20], (15, 2))  # seen elsewhere
        sol = localise_pose(cam, p_true, q_true, np.r_[X, X_bad], np.r_[uv, uv_bad])
        assert sol is not None
        assert not sol[2][150:].any() and sol[2][:150].mean() > 0.95
        C = map_pose_covariance(cam, sol[0], sol[1], X, SIGMA)
        assert pose_nees(sol[0], sol[1], p_true, q_true, C) < bound


def test_a_point_within_its_own_uncertainty_keeps_its_weight():
    """A residual beyond the pixel bounds is cut unless the point's covariance, projected
    into the image, explains it: exact points fix the pose exactly, and one point 10 px
    off moves it only when that point is given a covariance of some 30 px."""
    cam = default_camera()
    rng = np.random.default_rng(7)
    p_true, q_true = np.zeros(3), quat_exp(np.array([0.02, -0.05, 0.01]))
    X, _ = facade(rng, 100, p_true, q_true, (4.0, 8.0))
    uv = cam.project((X - p_true) @ quat_to_rotmat(q_true))
    uv[0] += [10.0, 0.0]  # the map point's estimate is 10 px off where it is seen
    depth = ((X[0] - p_true) @ quat_to_rotmat(q_true))[2]
    P = np.full((100, 3, 3), np.nan)
    moved, sols = {}, {}
    for name, sd_m in (("none", None), ("certain", 0.001), ("uncertain", 30.0 / cam.fx * depth)):
        if sd_m is not None:
            P[0] = sd_m**2 * np.eye(3)
        sol = localise_pose(cam, p_true, q_true, X, uv, X_cov=None if sd_m is None else P, tol_px2=0.0)
        sols[name] = sol
        moved[name] = np.linalg.norm(sol[0] - p_true) + np.linalg.norm(quat_log(quat_multiply(quat_conjugate(q_true), sol[1])))
    assert moved["none"] < 1e-9 and moved["certain"] < 1e-9
    assert moved["uncertain"] > 1e-5
    # given on demand, the covariances are asked for the point beyond the pixel bounds only
    asked = []
    sol = localise_pose(cam, p_true, q_true, X, uv, X_cov=lambda idx: asked.append(idx) or P[idx], tol_px2=0.0)
    assert np.array_equal(np.unique(np.concatenate(asked)), [0])
    assert np.array_equal(sol[0], sols["uncertain"][0]) and np.array_equal(sol[1], sols["uncertain"][1])


def test_a_relative_pose_the_map_cannot_start_from_is_not_fused_where_it_points():
    """A relative pose turned half round (camera looking back) gives a guess from which no
    map point is in front: the localisation cannot start there, so the frame is
    localised from the nearest known pose, the map contradicts the relative pose, and
    that is not fused. Before, the frame was fused at the guess, 180 degrees off."""
    from eifslam.sim.frontend import SyntheticFrontEnd
    from eifslam.sim.synthetic import corridor_scene
    from eifslam.system.slam import Slam, TrackingState

    frames, bad = 10, 8
    sc = corridor_scene(frames, np.random.default_rng(3))
    fe = SyntheticFrontEnd(sc, 3, sigma_px=0.5)
    slam = Slam(sc.camera, fe.slam_config(smoothing={"mode": "filter"}, keyframes={"max_interval_s": 0.5}), frontend=fe)
    honest = fe.relative_pose

    def turned(i: int, j: int):
        r = honest(i, j)
        if j == bad and r.ok:
            rp = r.measurement
            q = quat_multiply(rp.q_ij, quat_exp(np.array([0.0, np.pi, 0.0])))
            return dataclasses.replace(r, measurement=dataclasses.replace(rp, q_ij=q))
        return r

    fe.relative_pose = turned
    for k in range(frames):
        assert slam.track(k, float(k)).state is TrackingState.TRACKING or k == 0
    assert any(rp.j == bad for rp in slam.tracker.rejected_relative)
    _, q = slam.filter.pose(bad)
    turn = np.degrees(np.linalg.norm(quat_log(quat_multiply(quat_conjugate(sc.quats[bad]), q))))
    assert turn < 1.0
