"""Loop correction of the linearisation point (estimation/loop_correction.py): a path
whose heading drifted uniformly along the loop is put back on the true path, poses up
to the matched frame do not move, and features move with the last pose that saw them."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.errors import EstimatorError
from eifslam.estimation.loop_correction import distribute_correction
from eifslam.geometry.rotations import quat_exp, quat_log, quat_multiply, quat_to_rotmat


def _circle(n: int, drift_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """``n`` poses on a unit circle (heading along the path); each step's heading error
    grows uniformly to ``drift_deg`` at the last pose (yaw about z)."""
    th = np.linspace(0.0, 1.5 * np.pi, n)
    P_true = np.column_stack([np.cos(th), np.sin(th), np.zeros(n)])
    Q_true = quat_exp(np.column_stack([np.zeros(n), np.zeros(n), th]))
    a = np.radians(drift_deg) * np.arange(n) / (n - 1)
    dq = quat_exp(np.column_stack([np.zeros(n), np.zeros(n), a]))
    steps = np.einsum("nij,nj->ni", quat_to_rotmat(dq[1:]), np.diff(P_true, axis=0))
    P = np.vstack([P_true[:1], P_true[0] + np.cumsum(steps, axis=0)])
    return P_true, Q_true, P, quat_multiply(dq, Q_true)


def test_a_uniform_heading_drift_is_undone():
    P_true, Q_true, P, Q = _circle(101, 30.0)
    ids = np.arange(101) * 2  # frame ids need not be consecutive
    P2, Q2 = distribute_correction(ids, P, Q, 0, 200, P_true[-1], Q_true[-1])
    # the drifted path is 1-3 m off at its end; the correction puts every pose back to
    # within the error of spreading by distance travelled (steps vary little)
    assert np.max(np.linalg.norm(P - P_true, axis=1)) > 0.3
    assert np.max(np.linalg.norm(P2 - P_true, axis=1)) < 0.02
    ang = np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(Q2 * Q_true, 1)), 0, 1)))
    assert ang.max() < 0.5
    np.testing.assert_allclose(P2[-1], P_true[-1], atol=1e-12)


def test_poses_up_to_the_matched_frame_do_not_move_and_bad_input_is_refused():
    P_true, Q_true, P, Q = _circle(50, 20.0)
    ids = np.arange(50)
    P2, Q2 = distribute_correction(ids, P, Q, 10, 49, P_true[-1], Q_true[-1])
    np.testing.assert_array_equal(P2[:11], P[:11])
    np.testing.assert_array_equal(Q2[:11], Q[:11])
    assert np.linalg.norm(P2[30] - P[30]) > 1e-3
    with pytest.raises(EstimatorError):
        distribute_correction(ids, P, Q, 49, 10, P_true[-1], Q_true[-1])
    with pytest.raises(EstimatorError):
        distribute_correction(ids, P, Q, 10, 49, np.array([np.nan, 0, 0]), Q_true[-1])


def test_correct_loop_moves_features_with_the_last_pose_that_saw_them():
    from eifslam.estimation.filter import InformationFilter
    from eifslam.estimation.loop_correction import correct_loop
    from eifslam.estimation.measurements import FeatureObservations
    from eifslam.geometry.camera import PinholeCamera

    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    filt = InformationFilter(cam, recovery="full")
    one = np.array([1.0, 0.0, 0.0, 0.0])
    for fid, x in ((0, 0.0), (5, 1.0), (10, 2.0)):
        filt.add_pose(fid, np.array([x, 0.0, 0.0]), one)
    filt.add_features([1, 2, 3], np.array([[0.0, 0.0, 5.0], [1.0, 0.5, 5.0], [2.0, -0.5, 4.0]]))
    # feature 1 last seen by pose 0, feature 2 by pose 5, feature 3 by pose 10
    filt.store.features.append(FeatureObservations.make([0, 0, 5, 10, 5], [1, 2, 2, 3, 3], np.zeros((5, 2)) + 300))
    q10 = quat_exp(np.array([0.0, np.radians(10.0), 0.0]))
    p10 = np.array([2.0, 0.0, 0.5])
    X0 = {t: filt.x[filt.layout.feature_slice(t)].copy() for t in (1, 2, 3)}
    rep = correct_loop(filt, 0, 10, p10, q10)
    assert rep.poses == 2 and rep.features == 2 and abs(rep.rotation_deg - 10.0) < 1e-9
    np.testing.assert_array_equal(filt.pose(0)[0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(filt.pose(10)[0], p10, atol=1e-12)
    np.testing.assert_allclose(np.abs(filt.pose(10)[1] @ q10), 1.0, atol=1e-12)
    np.testing.assert_array_equal(filt.x[filt.layout.feature_slice(1)], X0[1])
    # feature 3 keeps its place in camera 10's frame
    R10 = quat_to_rotmat(q10)
    np.testing.assert_allclose(filt.x[filt.layout.feature_slice(3)], R10 @ (X0[3] - [2.0, 0.0, 0.0]) + p10, atol=1e-12)
    # pose 5 got half the rotation (half the distance travelled)
    ang = np.degrees(np.linalg.norm(quat_log(filt.pose(5)[1])))
    assert abs(ang - 5.0) < 1e-6


def test_relinearising_keeps_a_feature_collapsed_onto_its_camera_on_its_weak_prior_only():
    """At a new estimate a feature can end up behind or on one of its cameras: its views
    then no longer constrain it, and fusing the one left would make its block singular.
    relinearise() keeps its weak prior only; a well-seen feature keeps its views."""
    from eifslam.estimation.factors import constrained_features, features as lin_features
    from eifslam.estimation.filter import InformationFilter
    from eifslam.estimation.measurements import FeatureObservations
    from eifslam.geometry.camera import PinholeCamera

    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    filt = InformationFilter(cam, recovery="full")
    one = np.array([1.0, 0.0, 0.0, 0.0])
    filt.add_pose(0, np.zeros(3), one)
    filt.add_pose(1, np.array([1.0, 0.0, 0.0]), one)
    filt.fix_pose(0)
    filt.set_scale(0, 1, 1.0)
    good, bad = np.array([0.5, 0.2, 5.0]), np.array([0.3, -0.1, 4.0])
    filt.add_features([7, 8], np.vstack([good, bad]))
    uv = lambda X, c: np.array([500 * (X[0] - c) / X[2] + 320, 500 * X[1] / X[2] + 240])  # noqa: E731
    obs = FeatureObservations.make([0, 1, 0, 1], [7, 7, 8, 8],
                                   np.vstack([uv(good, 0), uv(good, 1), uv(bad, 0), uv(bad, 1)]))
    filt.fuse_features(obs, gate=False)
    filt.recover()
    # the estimate moves feature 8 onto camera 1's centre and slightly behind it
    x = filt.x.copy()
    x[filt.layout.feature_slice(8)] = [1.0, 0.0, -1e-9]
    filt.set_estimate(x)
    ok, idx, J, W, innov, _ = lin_features(filt.layout, filt.x, cam, filt.config, obs, False)
    keep = constrained_features(obs.feature, ok, J[:, :, 7:], W, filt.config.weak_prior_sigma**-2)
    assert keep.tolist() == [True, True, False, False]
    filt.relinearise()
    filt.recover()  # factorises: feature 8's block is its weak prior
    np.testing.assert_allclose(filt.x[filt.layout.feature_slice(7)], good, atol=1e-6)
    I = filt.information_matrix().toarray()
    c8 = filt.layout.feature_columns([8])[0]
    np.testing.assert_allclose(I[np.ix_(c8, c8)], np.eye(3) * filt.config.weak_prior_sigma**-2)
