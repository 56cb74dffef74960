"""A fused loop can be taken back exactly, and the system takes back a loop the estimate
after it contradicts (synthetic corridor, loops forced into the filter)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eifslam.estimation.filter import InformationFilter
from eifslam.estimation.measurements import FeatureObservations
from eifslam.geometry.rotations import quat_multiply, quat_to_rotmat
from eifslam.sim import synthetic
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.system.loops import LoopClosure
from eifslam.system.slam import Slam

N_FRAMES = 12


def _run(n: int, recovery: str = "incremental", online: bool = True):
    """The system over the first ``n`` frames; ``online=False``: the filter without online
    relinearisation."""
    sc = synthetic.corridor_scene(N_FRAMES + 4, np.random.default_rng(3))
    fe = SyntheticFrontEnd(sc, 1)
    config = fe.slam_config(experimental={"recovery": recovery})
    filt = None if online else InformationFilter(
        sc.camera, dataclasses.replace(config.filter, relinearise_threshold=None), recovery=recovery)
    slam = Slam(sc.camera, config, frontend=fe, backend=filt)
    for k in range(n):
        slam.track(k)
    return sc, slam


def _loop(sc, slam, k: int, j: int, shift: float = 0.0, yaw: float = 0.0, seed: int = 5):
    """A loop of frame *k* to frame *j*: ``Zm`` of every map feature of frame *j* that frame *k*
    sees, drawn (1 px noise) from the true pose of *k* moved by ``shift`` metres sideways and
    turned by ``yaw`` radians (0, 0: a true loop; otherwise a perceptual alias)."""
    filt = slam.filter
    ids = np.intersect1d(slam.frontend.map_observations(j)[0], np.flatnonzero(sc.visible(k)))
    ids = ids[filt.layout.has_features(ids)]
    dq = np.array([np.cos(yaw / 2), 0.0, np.sin(yaw / 2), 0.0])
    q = quat_multiply(sc.quats[k], dq)
    p = sc.positions[k] + quat_to_rotmat(sc.quats[k]) @ np.array([shift, 0.0, 0.0])
    Xc = (sc.points[ids] - p) @ quat_to_rotmat(q)
    uv = sc.camera.project(Xc) + np.random.default_rng(seed).normal(0.0, 1.0, (len(ids), 2))
    obs = FeatureObservations.make(np.full(len(ids), k), ids, uv, 1.0)
    lc = LoopClosure(k, j, 1.0, len(ids), len(ids), 25, len(ids), 25, 0, 0.0, 0.0)
    return lc, obs, p, q


@pytest.mark.parametrize("recovery", ["incremental", "full"])
def test_removing_a_loop_restores_the_information_exactly(recovery):
    """Without online relinearisation the loop's fusion is all that changed ``I``, and
    subtracting it gives back ``I``, ``i`` and ``x`` (with it, the measurements the loop
    moved were relinearised, and removal relinearises everything at the estimate before
    the loop: the test below)."""
    sc, slam = _run(N_FRAMES, recovery, online=False)
    filt = slam.filter
    k = N_FRAMES - 1
    filt.complete_estimate()
    I0, i0, x0 = filt.information_matrix().toarray(), filt.information_vector(), filt.x.copy()
    n_zm = len(filt.store.all_features())
    lc, obs, p, q = _loop(sc, slam, k, k - 6)
    fused = slam.loops.fuse(lc, obs, p, q)
    assert len(fused) > 20 and slam.loop_closures == [lc]
    I1 = filt.information_matrix().toarray()
    assert np.abs(I1 - I0).max() > 1.0  # the loop added information
    assert slam.remove_loop(0) is lc
    I2, i2 = filt.information_matrix().toarray(), filt.information_vector()
    scale = np.abs(I0).max()
    np.testing.assert_allclose(I2, I0, rtol=0, atol=1e-9 * scale)
    np.testing.assert_allclose(i2, i0, rtol=0, atol=1e-9 * max(np.abs(i0).max(), 1.0))
    np.testing.assert_allclose(filt.x, x0, rtol=0, atol=1e-6)
    assert len(filt.store.all_features()) == n_zm  # smoothing does not bring it back
    assert slam.loop_closures == [] and [c for c, _, _ in slam.loops.removed] == [lc]
    with pytest.raises(KeyError):
        slam.remove_loop(lc)


def _position_error(sc, slam, frames) -> float:
    slam.filter.complete_estimate()
    return max(float(np.linalg.norm(slam.filter.pose(f)[0] - sc.positions[f])) for f in frames)


def test_the_system_takes_back_a_wrong_loop_and_keeps_a_true_one():
    sc, slam = _run(N_FRAMES)
    k = N_FRAMES - 1
    frames = list(range(k + 1))
    before = _position_error(sc, slam, frames)
    assert 0 < before < 0.05  # noisy, and near the truth
    lc, obs, p, q = _loop(sc, slam, k, k - 6, shift=0.8, yaw=0.3)
    slam.loops.fuse(lc, obs, p, q)
    assert _position_error(sc, slam, [k]) > 0.1  # the alias pulls the frame away
    # the check the loop closer runs right after a fusion: the estimate contradicts it
    assert not slam.loops.check(k, only=lc)
    assert [c for c, _, _ in slam.loops.removed] == [lc] and slam.loop_closures == []
    assert 0 < _position_error(sc, slam, frames) < 0.05  # back near the truth
    for f in range(k + 1, k + 4):
        slam.track(f)
    assert 0 < _position_error(sc, slam, range(k + 4)) < 0.05
    # a true loop, the same way, stays
    lc2, obs2, p2, q2 = _loop(sc, slam, k + 3, k - 3, seed=7)
    slam.loops.fuse(lc2, obs2, p2, q2)
    assert slam.loops.check(k + 3, only=lc2)
    slam.track(k + 4)  # the next keyframe's check keeps it too
    assert slam.loop_closures == [lc2] and len(slam.loops.removed) == 1
    assert 0 < _position_error(sc, slam, range(k + 5)) < 0.05


def test_a_true_loop_fused_away_from_the_optimum_is_kept():
    """The check tests a loop at the minimum of the cost: a true loop whose residuals are large
    only because the estimate is away from it (here the loop frame moved 0.3 m) is kept, and
    the estimate comes back to the truth."""
    sc, slam = _run(N_FRAMES)
    k = N_FRAMES - 1
    lc, obs, p, q = _loop(sc, slam, k, k - 6, seed=7)
    slam.loops.fuse(lc, obs, p, q)
    filt = slam.filter
    x = filt.complete_estimate().copy()
    x[filt.layout.pose_columns([k])[0, :3]] += np.array([0.3, 0.0, 0.0])
    filt.set_estimate(x)
    assert slam.loops._residual(slam.loops._fused[0].obs) > 10 * 2 * len(obs)  # far over any bound
    assert slam.loops.check(k, only=lc)
    assert slam.loop_closures == [lc] and slam.loops.removed == []
    assert 0 < _position_error(sc, slam, range(k + 1)) < 0.05


def test_a_saved_session_keeps_the_loops_taken_back(tmp_path):
    sc, slam = _run(N_FRAMES)
    k = N_FRAMES - 1
    lc, obs, p, q = _loop(sc, slam, k, k - 6, shift=0.8, yaw=0.3)
    slam.loops.fuse(lc, obs, p, q)
    assert not slam.loops.check(k, only=lc)
    state = slam.loops.state_dict()
    back = Slam(sc.camera, slam.config, frontend=slam.frontend)
    back.loops.load_state_dict(state)
    [(c, at, why)] = back.loops.removed
    assert (c.frame, c.matched_frame, at) == (k, k - 6, k) and why == slam.loops.removed[0][2]
    assert back.loop_closures == []
    from eifslam.errors import SessionError

    with pytest.raises(SessionError):
        back.loops.load_state_dict(dict(state, removed_why=[1]))

