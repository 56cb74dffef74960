"""Loop correction of the linearisation point (estimation/loop_correction.py): a path
whose heading drifted uniformly along the loop is put back on the true path, poses up
to the matched frame do not move, and features move with the last pose that saw them."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.errors import EstimatorError
from eifslam.estimation.loop_correction import distribute_correction
from eifslam.geometry.rotations import quat_exp, quat_multiply, quat_to_rotmat


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
