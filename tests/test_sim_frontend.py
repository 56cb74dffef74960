"""The synthetic front end: the front end's interface over a synthetic scene, measurements
as :func:`simulate` draws them, deterministic, and the system's Algorithm 1 on top of it."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.errors import EstimatorError
from eifslam.frontend.results import Reason
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene, orbit_scene, simulate, true_relative
from eifslam.system.slam import Slam, TrackingState


def _fed(scene, frames=None, **kw) -> SyntheticFrontEnd:
    fe = SyntheticFrontEnd(scene, 5, **kw)
    for k in range(len(scene.positions) if frames is None else frames):
        fe.add_frame(k, k)
    return fe


def test_measurements_are_simulate_s_and_repeatable():
    sc = corridor_scene(6, np.random.default_rng(0))
    m = simulate(sc, 5)
    fe = _fed(sc, map_fraction=1.0)
    for k in range(6):
        ids, uv = fe.map_observations(k)
        np.testing.assert_array_equal(ids, m.frames[k].feature)
        np.testing.assert_array_equal(uv, m.frames[k].uv)
        ids2, uv2 = fe.map_observations(k)
        np.testing.assert_array_equal(uv2, uv)
    for k in range(1, 6):
        r = fe.relative_pose(k - 1, k)
        assert r.ok and r.reason == Reason.OK
        np.testing.assert_array_equal(r.measurement.q_ij, m.relative[k - 1].q_ij)
        np.testing.assert_array_equal(r.measurement.t_ij, m.relative[k - 1].t_ij)
        np.testing.assert_array_equal(r.measurement.cov, m.rel_cov)
    a, b = fe.relative_pose(0, 4), fe.relative_pose(0, 4)
    np.testing.assert_array_equal(a.measurement.t_ij, b.measurement.t_ij)
    q, t = true_relative(sc, 0, 4)
    assert 0 < np.linalg.norm(a.measurement.t_ij - t) < 0.02  # noisy, near the truth


def test_split_noise_free_parallax_and_failures():
    sc = orbit_scene(8, np.random.default_rng(1))
    fe = _fed(sc, map_fraction=0.5, noise=False)
    assert 0.4 < fe.in_map.mean() < 0.6
    ids, uv = fe.map_observations(3)
    assert fe.in_map[ids].all() and len(ids) > 100
    np.testing.assert_allclose(uv, sc.project(3, ids), atol=1e-9)  # exact
    ff = fe.frame(3)
    assert (~ff.in_map).sum() > 100  # the frame also holds its Ωp points
    r = fe.relative_pose(2, 5)
    q, t = true_relative(sc, 2, 5)
    np.testing.assert_allclose(r.measurement.t_ij, t, atol=1e-12)
    assert r.n_common == (~ff.in_map).sum() or r.n_common > 100
    assert r.parallax_deg == pytest.approx(3 * 120 / 7, rel=0.2)  # the orbit's step, seen from the centre
    assert fe.relative_pose(2, 2).reason == Reason.SAME_FRAME
    strict = _fed(sc, min_common=1000)
    assert strict.relative_pose(0, 1).reason == Reason.TOO_FEW_COMMON and strict.relative_pose(0, 1).measurement is None
    picky = _fed(sc, min_parallax_deg=50.0)
    assert picky.relative_pose(0, 1).reason == Reason.NO_PARALLAX and picky.relative_pose(0, 7).ok
    assert fe.reobserve(3, ids[:2], uv[:2], 15.0) == 0
    assert dict(fe.relocalise(7, [0, 7]))[7] == 0 and dict(fe.relocalise(7, [0, 7]))[0] > 0
    with pytest.raises(EstimatorError):
        fe.add_frame(1, 3)
    with pytest.raises(ValueError):
        fe.add_frame(np.zeros((4, 4)), 99)
    with pytest.raises(EstimatorError):
        fe.map_observations(42)


def test_slam_on_the_synthetic_front_end_recovers_the_truth():
    """Noise-free: the system's pose guesses, triangulation and fusion land on the truth;
    the frame ids map to any scene frames (every other frame here)."""
    sc = corridor_scene(16, np.random.default_rng(2))
    fe = SyntheticFrontEnd(sc, 2, noise=False, map_fraction=0.6)
    slam = Slam(sc.camera, fe.slam_config(tracking={"scale_distance": fe.true_distance(0, 2)}), frontend=fe)
    res = [slam.track(k, 0.1 * k) for k in range(0, 16, 2)]
    assert res[0].state is TrackingState.INITIALISING
    assert all(r.state is TrackingState.TRACKING for r in res[1:])
    t, P, Q = slam.trajectory()
    np.testing.assert_allclose(P, sc.positions[::2], atol=1e-8)
    np.testing.assert_allclose(t, 0.1 * np.arange(0, 16, 2))
    ids, X, _ = slam.map()
    assert len(ids) > 100 and fe.in_map[ids].all()
    np.testing.assert_allclose(X, sc.points[ids], atol=1e-8)
