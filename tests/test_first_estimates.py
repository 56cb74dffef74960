"""The consistency changes: first-estimates Jacobians (off, for the features only, for every
state), the multi-view first estimate of new features, and the ZR/ZT gate statistic with
the poses' uncertainty."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.errors import ConfigError
from eifslam.estimation import factors
from eifslam.estimation.filter import InformationFilter
from eifslam.estimation.initialisation import refine_points, triangulate
from eifslam.estimation.measurements import FeatureObservations, RelativePose
from eifslam.estimation.options import FilterConfig, FirstEstimates
from eifslam.estimation.scale import rescale
from eifslam.geometry.rotations import quat_exp, quat_to_rotmat
from eifslam.sim.synthetic import corridor_scene


def _two_poses_one_point(first: bool | str) -> tuple[InformationFilter, np.ndarray]:
    """A filter with poses 0, 1 and feature 7 at their initial guesses (no measurement)."""
    sc = corridor_scene(3, np.random.default_rng(0))
    f = InformationFilter(sc.camera, FilterConfig(first_estimate_jacobians=first), recovery="full")
    f.add_pose(0, sc.positions[0], sc.quats[0])
    f.add_pose(1, sc.positions[1], sc.quats[1])
    X = sc.points[np.flatnonzero(sc.visible(1))[0]]
    f.add_features([7], X[None])
    return f, X


@pytest.mark.parametrize("first", [True, False, "off", "features", "all"])
def test_zm_jacobian_at_first_estimates_innovation_at_current(first):
    f, X = _two_poses_one_point(first)
    mode = FirstEstimates.parse(first, "first")
    fe = f.first_estimates.copy()
    np.testing.assert_array_equal(fe, f.x)
    # the estimate moves (as a recovery would move it); the first estimates stay
    fcols = f.layout.feature_columns([7])[0]
    f.x[fcols] += [0.05, -0.03, 0.2]
    f.x[f.layout.pose_columns([1])[0][:3]] += [0.01, 0.0, -0.02]
    np.testing.assert_array_equal(f.first_estimates, fe)
    obs = FeatureObservations.make(np.array([1]), np.array([7]), np.array([[300.0, 200.0]]), 1.0)
    ok, idx, J, W, innov, chi2 = f.linearise_features(obs, gate=False)
    at_x = factors.features(f.layout, f.x, f.camera, f.config, obs, False)
    at_fe = factors.features(f.layout, fe, f.camera, f.config, obs, False)
    mixed = f.x.copy()
    mixed[fcols] = fe[fcols]  # the feature at its first estimate, the poses where they are
    at_mixed = factors.features(f.layout, mixed, f.camera, f.config, obs, False)
    np.testing.assert_array_equal(innov, at_x[4])  # innovation always at the current estimate
    np.testing.assert_array_equal(chi2, at_x[5])
    expected = {FirstEstimates.OFF: at_x, FirstEstimates.FEATURES: at_mixed, FirstEstimates.ALL: at_fe}[mode]
    np.testing.assert_array_equal(J, expected[2])
    # the three points give three different Jacobians (so the test can tell them apart)
    assert np.abs(at_fe[2] - at_x[2]).max() > 1e-3
    assert np.abs(at_mixed[2] - at_x[2]).max() > 1e-3 and np.abs(at_mixed[2] - at_fe[2]).max() > 1e-3


@pytest.mark.parametrize("first", ["off", "features", "all"])
def test_relative_jacobian_at_the_poses_first_estimates_only_with_all(first):
    f, _ = _two_poses_one_point(first)
    fe = f.first_estimates.copy()
    f.x[f.layout.pose_columns([1])[0][:3]] += [0.03, 0.01, -0.05]
    rp = RelativePose(0, 1, np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.1, 0.0, 1.0]), np.eye(5) * 1e-4)
    idx, J, W, innov = f.linearise_relative([rp])
    at_x = factors.relative(f.layout, f.x, f.config, [rp])
    at_fe = factors.relative(f.layout, fe, f.config, [rp])
    np.testing.assert_array_equal(innov, at_x[3])
    np.testing.assert_array_equal(J, (at_fe if first == "all" else at_x)[1])
    assert np.abs(at_fe[1] - at_x[1]).max() > 1e-4


def test_first_estimates_option_reads_bools_and_names():
    assert FilterConfig().first_estimate_jacobians == FirstEstimates.OFF
    assert FilterConfig(first_estimate_jacobians=True).first_estimate_jacobians == FirstEstimates.ALL
    assert FilterConfig(first_estimate_jacobians=False).first_estimate_jacobians == FirstEstimates.OFF
    assert FilterConfig(first_estimate_jacobians="features").first_estimate_jacobians == "features"
    with pytest.raises(ConfigError, match="first_estimate_jacobians"):
        FilterConfig(first_estimate_jacobians="poses")


def test_relinearise_rescale_and_sessions_carry_the_first_estimates():
    f, _ = _two_poses_one_point(True)
    f.x[:] += 0.01
    f.relinearise()  # smoothing: every Jacobian now at x, which becomes the first estimate
    np.testing.assert_array_equal(f.first_estimates, f.x)
    fe = f.first_estimates.copy()
    f.x[:] += 0.01
    rescale(f, 2.0)
    pos = f.layout.position_mask()
    np.testing.assert_allclose(f.first_estimates[pos], 2.0 * fe[pos])
    np.testing.assert_array_equal(f.first_estimates[~pos], fe[~pos])
    g = InformationFilter(f.camera, f.config, recovery="full")
    g.load_state_dict(f.state_dict())
    np.testing.assert_array_equal(g.first_estimates, f.first_estimates)
    d = f.state_dict()
    del d["x_first"]  # a session saved before first estimates were kept: they start at x
    h = InformationFilter(f.camera, f.config, recovery="full")
    h.load_state_dict(d)
    np.testing.assert_array_equal(h.first_estimates, h.x)


def test_refine_points_recovers_points_from_many_views():
    """Noise-free views from 8 poses: refinement from a perturbed start lands on the true
    point; with pixel noise it fits every view better than the two-view midpoint."""
    rng = np.random.default_rng(3)
    sc = corridor_scene(8, rng)
    vis = np.flatnonzero(np.all([sc.visible(k) for k in range(8)], 0))[:40]
    P, Q = sc.positions.copy(), sc.quats.copy()
    feature = np.repeat(np.arange(len(vis)), 8)
    k = np.tile(np.arange(8), len(vis))
    uv = np.concatenate([sc.project(kk, vis[[i]]) for i, kk in zip(feature, k)])
    X0, _, ok = triangulate(P[0], Q[0], sc.project(0, vis), P[7], Q[7], sc.project(7, vis), sc.camera)
    assert ok.all()
    X, front = refine_points(X0 + rng.normal(0, 0.05, X0.shape), feature, P[k], Q[k], uv, sc.camera)
    assert front.all()
    np.testing.assert_allclose(X, sc.points[vis], atol=1e-7)
    # with pixel noise: the refined points fit every view at least as well as the midpoints
    uvn = uv + rng.normal(0, 1.0, uv.shape)
    Xm, _, _ = triangulate(P[0], Q[0], uvn[k == 0], P[7], Q[7], uvn[k == 7], sc.camera)
    Xr, _ = refine_points(Xm, feature, P[k], Q[k], uvn, sc.camera)

    def cost(Xs):
        h = np.concatenate([sc.camera.project((Xs[[i]] - P[kk]) @ quat_to_rotmat(Q[kk])) for i, kk in zip(feature, k)])
        return np.sum((h - uvn) ** 2)

    assert cost(Xr) < cost(Xm)
    assert np.median(np.linalg.norm(Xr - sc.points[vis], axis=1)) < np.median(np.linalg.norm(Xm - sc.points[vis], axis=1))


def test_perturbed_pose_first_estimate_is_kept_by_add_pose():
    f, _ = _two_poses_one_point(True)
    q = quat_exp(np.array([0.0, 0.01, 0.0]))
    f.add_pose(2, np.array([0.1, 0.0, 1.2]), q)
    cols = f.layout.pose_columns([2])[0]
    np.testing.assert_allclose(f.first_estimates[cols], np.concatenate([[0.1, 0.0, 1.2], q]))


def _tracked(frames: int, seed: int):
    """The system's filter and synthetic front end after ``frames`` frames of the corridor."""
    from eifslam.sim.frontend import SyntheticFrontEnd
    from eifslam.system.slam import Slam

    sc = corridor_scene(frames, np.random.default_rng(seed))
    fe = SyntheticFrontEnd(sc, seed, map_fraction=1.0)
    slam = Slam(sc.camera, fe.slam_config(), frontend=fe)
    for k in range(frames):
        slam.track(k)
    return slam.filter, fe


@pytest.mark.parametrize("text, mode", [("off", "off"), ("false", "off"), ("'off'", "off"), ("true", "all"),
                                        ("features", "features"), ("all", "all")])
def test_first_estimates_option_from_a_configuration_file(tmp_path, text, mode):
    """YAML reads a bare ``off`` as False and ``true`` as True: both still name the mode."""
    from eifslam.cli.config import read_config

    path = tmp_path / "c.yaml"
    path.write_text(f"experimental:\n  first_estimate_jacobians: {text}\n")
    assert read_config(path).filter.first_estimate_jacobians == mode
