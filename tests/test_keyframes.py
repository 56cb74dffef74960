"""Keyframes: only keyframes enter the filter; the frames between are localised on the map."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.errors import ConfigError
from eifslam.evaluation.metrics import align_sim3
from eifslam.estimation.localisation import map_pose_covariance, map_pose_sensitivity
from eifslam.geometry.rotations import quat_exp, quat_multiply, quat_to_rotmat
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene, default_camera
from eifslam.system.config import KeyframeConfig, SlamConfig
from eifslam.system.keyframes import MapPose, median_parallax_deg
from eifslam.system.slam import Slam, TrackingState


def test_map_pose_covariance_matches_finite_differences():
    cam = default_camera()
    rng = np.random.default_rng(0)
    X = rng.uniform([-2, -2, 4], [2, 2, 8], (40, 3))
    p, q = np.array([0.1, -0.2, 0.3]), quat_exp(np.array([0.05, -0.1, 0.02]))
    sigma = 0.7
    C = map_pose_covariance(cam, p, q, X, sigma)

    def h(d):  # pixels at [p + dp, q ⊗ Exp(dtheta)]
        Xc = (X - (p + d[:3])) @ quat_to_rotmat(quat_multiply(q, quat_exp(d[3:])))
        return cam.project(Xc).ravel()

    J = np.zeros((2 * len(X), 6))
    for i in range(6):
        d = np.zeros(6)
        d[i] = 1e-6
        J[:, i] = (h(d) - h(-d)) / 2e-6
    ref = np.linalg.inv(J.T @ J) * sigma**2
    assert np.max(np.abs(C - ref)) < 1e-6 * np.max(np.abs(ref))
    assert map_pose_covariance(cam, p, q, X[:2], sigma) is None  # too few points

    # with the map's uncertainty: the pose moves by A dX, A = -(J^T J)^-1 J^T dh/dX
    def hx(dX):
        Xc = (X + dX.reshape(-1, 3) - p) @ quat_to_rotmat(q)
        return cam.project(Xc).ravel()

    H = np.zeros((2 * len(X), 3 * len(X)))
    for i in range(3 * len(X)):
        d = np.zeros(3 * len(X))
        d[i] = 1e-6
        H[:, i] = (hx(d) - hx(-d)) / 2e-6
    A = -np.linalg.solve(J.T @ J, J.T @ H)
    L = rng.normal(size=(3 * len(X), 3 * len(X))) * 0.01
    P = L @ L.T + 0.02**2 * np.kron(np.ones((len(X), len(X))), np.eye(3))  # noise + a common shift
    Cm = map_pose_covariance(cam, p, q, X, sigma, lambda G: G @ P @ G.T)
    ref_m = ref + A @ P @ A.T
    assert np.max(np.abs(Cm - ref_m)) < 1e-5 * np.max(np.abs(ref_m))
    assert np.all(np.linalg.eigvalsh(Cm - C) > -1e-12)  # never smaller than given the map
    # the sensitivity itself, sign included (the joint ZR/ZT gate uses its cross terms)
    Cs, As = map_pose_sensitivity(cam, p, q, X, sigma)
    np.testing.assert_allclose(Cs, ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())
    np.testing.assert_allclose(As, A, rtol=1e-5, atol=1e-6 * np.abs(A).max())
    shift = np.tile([0.01, -0.02, 0.005], len(X))  # the whole map moves: the pose moves with it
    np.testing.assert_allclose((As @ shift)[:3], shift[:3], rtol=1e-4, atol=1e-7)


def test_median_parallax():
    X = np.array([[0.0, 0.0, 10.0], [1.0, 0.0, 10.0], [-1.0, 0.0, 10.0]])
    a = median_parallax_deg(X, np.zeros(3), np.array([1.0, 0.0, 0.0]))
    assert a == pytest.approx(np.degrees(np.arctan(0.1)), rel=0.02)
    assert median_parallax_deg(np.zeros((0, 3)), np.zeros(3), np.ones(3)) == 0.0


def aligned_errors(P: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Position errors ``(N,)`` after a Sim(3) alignment (monocular: scale is free)."""
    return np.linalg.norm(align_sim3(P, truth).apply(P) - truth, axis=1)


def run(keyframes: bool, frames: int = 40, seed: int = 2):
    """A slow walk down the corridor (5 cm per frame, 10 frames per second); without
    ``keyframes`` every frame is one (the longest interval between keyframes is shorter
    than the frames')."""
    sc = corridor_scene(frames, np.random.default_rng(seed), step=0.05, points_per_metre=30.0)
    fe = SyntheticFrontEnd(sc, seed, map_fraction=0.6)
    # the whole triangulation parallax between keyframes (2 deg), so that the walk has
    # frames between keyframes to test (the default, a quarter of it, keeps more)
    every = {} if keyframes else {"max_interval_s": 0.05}
    slam = Slam(sc.camera, fe.slam_config(smoothing={"mode": "filter"}, experimental={"keyframe_parallax_deg": 2.0},
                                          keyframes=every), frontend=fe)
    for k in range(frames):
        slam.track(k, 0.1 * k)
    slam.finish()
    return sc, slam


def test_only_keyframes_enter_the_filter_and_every_frame_is_tracked():
    sc, slam = run(keyframes=True)
    res = slam.results
    assert all(r.state is TrackingState.TRACKING for r in res[1:])
    kf = [r.frame_id for r in res if r.keyframe]
    between = [r.frame_id for r in res if not r.keyframe]
    assert 4 <= len(kf) <= 30 and len(between) >= 10  # the slow walk needs few keyframes
    assert sorted(slam.filter.layout.pose_ids) == kf  # keyframes, and only they, are states
    t, P, Q = slam.trajectory()
    assert len(t) == 40 and np.all(np.diff(t) > 0)
    err = aligned_errors(P, sc.positions)
    assert 1e-5 < err[between].max() < 0.05  # localised on the map, noisy but close
    for j in between:  # a covariance given the map, as large as the error it admits
        r = res[j]
        assert r.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(r.covariance) > 0)
        assert r.reference in kf and r.reference < j
    # every keyframe says why it is one, but the first two poses (the first baseline) and
    # the frames that waited for them
    base = [r.frame_id for r in res if r.keyframe and r.reason == ""]
    assert all(r.reason.startswith("keyframe:") or "waited for a baseline" in r.reason or r.frame_id in base
               for r in res[1:] if r.keyframe)
    assert len(base) == 1


def test_keyframes_cost_no_accuracy_against_every_frame_in_the_filter():
    sc, slam_kf = run(keyframes=True)
    _, slam_all = run(keyframes=False)
    assert all(r.keyframe for r in slam_all.results)
    assert slam_kf.filter.dim < 0.8 * slam_all.filter.dim
    e_kf = aligned_errors(slam_kf.trajectory()[1], sc.positions)
    e_all = aligned_errors(slam_all.trajectory()[1], sc.positions)
    ate_kf, ate_all = np.sqrt(np.mean(e_kf**2)), np.sqrt(np.mean(e_all**2))
    # the simulated pixel noise is independent from frame to frame, so the frames left out
    # of the filter take real information with them (a few times less than sqrt(40 / 9) of
    # the map's accuracy here); on images, where consecutive frames' errors are correlated,
    # benchmarks/realtime.py measures the cost. Both runs must still be accurate.
    assert 1e-4 < ate_all and 0.5 * ate_all < ate_kf < 5.0 * ate_all and ate_kf < 0.03


def test_keyframe_rules():
    sc, slam = run(keyframes=True, frames=12)
    kfs = slam.keyframes
    mp = MapPose(99, kfs.last, np.zeros(3), np.array([1.0, 0, 0, 0]), np.eye(6), np.zeros(0, np.int64),
                 np.zeros((0, 2)), inlier_fraction=1.0, parallax_deg=0.1, tracked_fraction=1.0)
    t_last = slam.results[kfs.last].timestamp
    assert kfs.keyframe_reason(mp, t_last + 0.05) is None
    assert "s since" in kfs.keyframe_reason(mp, t_last + 5.0)
    mp.parallax_deg = 2.5
    assert "parallax" in kfs.keyframe_reason(mp, t_last + 0.05)
    mp.parallax_deg, mp.tracked_fraction = 0.1, 0.2
    assert "sees" in kfs.keyframe_reason(mp, t_last + 0.05)
    mp.tracked_fraction, mp.inlier_fraction = 1.0, 0.3
    assert "fits the map poorly" in kfs.keyframe_reason(mp, t_last + 0.05)


def test_keyframe_settings_are_checked():
    for bad in ({"experimental": {"keyframe_parallax_deg": -1.0}}, {"keyframes": {"max_interval_s": 0.0}},
                {"keyframes": {"min_tracked": 0.5}}):
        with pytest.raises(ConfigError):
            SlamConfig.from_dict(bad)


def test_keyframe_parallax_grows_with_the_map_features_up_to_the_triangulation_parallax():
    cfg = SlamConfig()
    tri, n_ref = cfg.mapping.min_feature_parallax_deg, KeyframeConfig.redundant_features
    quarter = tri / KeyframeConfig.per_triangulation
    assert cfg.keyframe_parallax() == cfg.keyframe_parallax(n_ref // 2) == quarter
    assert cfg.keyframe_parallax(2 * n_ref) == pytest.approx(2 * quarter)
    assert cfg.keyframe_parallax(100 * n_ref) == pytest.approx(tri)
    fixed = cfg.replace(experimental={"keyframe_parallax_deg": 1.3})
    assert fixed.keyframe_parallax(0) == fixed.keyframe_parallax(100 * n_ref) == 1.3


def test_a_frame_on_many_map_features_needs_more_parallax():
    sc, slam = run(keyframes=True, frames=12)
    kfs = slam.keyframes
    n = 4 * KeyframeConfig.redundant_features
    mp = MapPose(99, kfs.last, np.zeros(3), np.array([1.0, 0, 0, 0]), np.eye(6), np.arange(n),
                 np.zeros((n, 2)), inlier_fraction=1.0, parallax_deg=1.0, tracked_fraction=1.0)
    t_last = slam.results[kfs.last].timestamp
    assert kfs.keyframe_reason(mp, t_last + 0.05) is None  # 1 deg: a keyframe on few features
    mp.parallax_deg = slam.config.mapping.min_feature_parallax_deg
    assert "parallax" in kfs.keyframe_reason(mp, t_last + 0.05)


def test_frames_between_keyframes_follow_their_keyframe_when_the_map_moves():
    """After the whole map moves (a rigid motion of every state, as smoothing or a loop
    closure can cause), a frame between keyframes is placed from its reference keyframe's
    new pose, not re-localised from its stale pose in the old gauge."""
    from eifslam.geometry.rotations import quat_exp, quat_multiply, quat_to_rotmat

    sc, slam = run(keyframes=True, frames=30)
    filt = slam.filter
    between = [r.frame_id for r in slam.results if not r.keyframe]
    before = {j: (slam.results[j].position.copy(), slam.results[j].quat_wxyz.copy()) for j in between}
    dq = quat_exp(np.radians([0.0, 35.0, 10.0]))
    R, t = quat_to_rotmat(dq), np.array([12.0, -3.0, 8.0])  # far beyond the map's extent
    x = filt.x.copy()
    for f in filt.layout.pose_ids:
        s = filt.layout.pose_slice(f)
        x[s][:3] = R @ x[s][:3] + t
        x[s.start + 3:s.stop] = quat_multiply(dq, x[s.start + 3:s.stop])
    for tr in filt.layout.feature_ids:
        s = filt.layout.feature_slice(tr)
        x[s] = R @ x[s] + t
    filt.set_estimate(x)
    slam.refine_between_keyframes()
    for j in between:
        p_old, q_old = before[j]
        p_new = slam.results[j].position
        # the same pose carried by the rigid motion, up to the re-localisation's noise
        assert np.linalg.norm(p_new - (R @ p_old + t)) < 0.02
        assert np.linalg.norm(p_new - p_old) > 5.0


def test_frames_between_keyframes_are_refined_on_every_map_feature_they_observe():
    """At the end a frame between keyframes is re-localised on all its observations of the
    final map's features, including those that later keyframes triangulated from its
    tracks, not only those it was localised on while tracked: its covariance is the one
    of all of them, and its pose is nearer the truth than one from the first ones alone."""
    from eifslam.estimation.localisation import localise_pose

    sc, slam = run(keyframes=True, frames=30)
    filt, cfg = slam.filter, slam.config
    grown = []
    for r in slam.results:
        mp = slam.keyframes.get(r.frame_id)
        if mp is None:
            continue
        ids, _ = slam.frontend.map_observations(r.frame_id)
        known = np.asarray(ids)[filt.layout.has_features(ids)]
        first = mp.track_ids[filt.layout.has_features(mp.track_ids)]
        assert set(first) <= set(known)
        if len(known) > 1.2 * len(first):
            grown.append((r.frame_id, mp, first))
    assert grown  # later keyframes added map features that these frames observe
    stamps, P, _ = slam.trajectory()
    sim = align_sim3(P, sc.positions[np.rint(stamps / 0.1).astype(int)])  # frame k at 0.1 k s
    errs_all, errs_first = [], []
    for j, mp, first in grown:
        c_all = np.trace(slam.results[j].covariance[:3, :3])
        uv = dict(zip(*slam.frontend.map_observations(j)))
        X = filt.x[filt.layout.feature_columns(first)]
        p0, q0 = slam.keyframes.composed(mp)
        sol = localise_pose(sc.camera, p0, q0, X, np.array([uv[t] for t in first]),
                            min_inliers=cfg.tracking.min_map_features, inlier_px=cfg.tracking.inlier_radius_px)
        assert sol is not None
        ids = first[sol[2]]
        c_first = np.trace(map_pose_covariance(sc.camera, sol[0], sol[1], X[sol[2]], cfg.zm_sigma_px,
                                               lambda G: filt.feature_propagate(ids, G))[:3, :3])
        assert c_all < c_first
        errs_all.append(np.linalg.norm(sim.apply(slam.results[j].position[None])[0] - sc.positions[j]))
        errs_first.append(np.linalg.norm(sim.apply(sol[0][None])[0] - sc.positions[j]))
    assert np.median(errs_all) < np.median(errs_first)


def test_smoothing_a_finished_filter_run_moves_the_frames_between_keyframes_too():
    """``Slam.smooth()`` called on a run finished in filter mode gives every frame the
    trajectory a smooth-mode run gives: the frames between keyframes are re-localised on
    the smoothed map (before, they kept their filter-mode poses; on kitti-07 that gave ATE
    2.19 m against the smooth mode's 0.446 m for the same smoothed keyframes)."""
    sc, slam = run(keyframes=True, frames=30)
    between = [r.frame_id for r in slam.results if not r.keyframe]
    assert between
    before = {j: slam.results[j].position.copy() for j in between}
    slam.smooth()
    moved = max(np.linalg.norm(slam.results[j].position - before[j]) for j in between)
    assert moved > 1e-6  # the smoothed map moved them
    t, P, Q = slam.trajectory()
    # a smooth-mode run of the same frames: the same trajectory for every frame
    sc2 = corridor_scene(30, np.random.default_rng(2), step=0.05, points_per_metre=30.0)
    fe = SyntheticFrontEnd(sc2, 2, map_fraction=0.6)
    ref = Slam(sc2.camera, fe.slam_config(smoothing={"mode": "smooth"}, experimental={"keyframe_parallax_deg": 2.0}), frontend=fe)
    for k in range(30):
        ref.track(k, 0.1 * k)
    ref.finish()
    np.testing.assert_allclose(P, ref.trajectory()[1], atol=1e-6)
