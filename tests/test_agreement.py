"""The loop-closure agreement tests (estimation/agreement.py): Jacobians against central
differences, and the statistic's distribution on poses drawn from the stated covariances."""

from __future__ import annotations

import numpy as np

from eifslam.estimation.agreement import (
    chi2_quantile, pose_agreement, relative_pose_innovation, relative_pose_jacobians, rotation_agreement,
)
from eifslam.geometry.rotations import quat_exp, quat_multiply, quat_normalize, quat_to_rotmat


def _perturb(p, q, d):
    """Pose ``(p, q)`` moved by the tangent error ``d = [dp, dtheta]`` (right-multiplied rotation)."""
    return p + d[:3], quat_normalize(quat_multiply(q, quat_exp(d[3:])))


def _relative(p_j, q_j, p_k, q_k):
    R_j = quat_to_rotmat(q_j)
    return R_j.T @ (p_k - p_j), R_j.T @ quat_to_rotmat(q_k)


def test_relative_pose_jacobians_match_central_differences():
    rng = np.random.default_rng(3)
    p_j, p_k = rng.normal(size=3), rng.normal(size=3) * 4
    q_j = quat_normalize(rng.normal(size=4))
    q_k = quat_normalize(rng.normal(size=4))
    J_j, J_k = relative_pose_jacobians(p_j, q_j, p_k, q_k)
    t0, R0 = _relative(p_j, q_j, p_k, q_k)
    h = 1e-6
    for J, which in ((J_j, 0), (J_k, 1)):
        num = np.zeros((6, 6))
        for c in range(6):
            out = []
            for s in (h, -h):
                d = np.zeros(6)
                d[c] = s
                pj, qj = _perturb(p_j, q_j, d) if which == 0 else (p_j, q_j)
                pk, qk = _perturb(p_k, q_k, d) if which == 1 else (p_k, q_k)
                t, R = _relative(pj, qj, pk, qk)
                dR = R0.T @ R  # right error of the relative rotation
                phi = np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0], dR[1, 0] - dR[0, 1]]) / 2
                out.append(np.concatenate([t - t0, phi]))
            num[:, c] = (out[0] - out[1]) / (2 * h)
        np.testing.assert_allclose(J, num, atol=1e-6)


def test_innovation_is_zero_for_the_estimate_itself_and_the_rotation_vector_of_a_known_turn():
    p_j, q_j = np.zeros(3), np.array([1.0, 0, 0, 0])
    p_k, q_k = np.array([1.0, 2.0, 3.0]), quat_exp(np.array([0.0, 0.2, 0.0]))
    np.testing.assert_allclose(relative_pose_innovation(p_j, q_j, p_k, q_k, p_k, q_k), 0, atol=1e-12)
    q_m = quat_multiply(q_k, quat_exp(np.array([0.0, 0.0, 0.05])))
    v = relative_pose_innovation(p_j, q_j, p_k, q_k, p_k + [0.1, 0, 0], q_m)
    np.testing.assert_allclose(v, [0.1, 0, 0, 0, 0, 0.05], atol=1e-12)


def test_the_statistics_are_chi_square_on_poses_drawn_from_their_covariances():
    rng = np.random.default_rng(7)
    p_j, q_j = np.array([0.5, -0.2, 0.1]), quat_normalize(np.array([1.0, 0.1, -0.2, 0.05]))
    p_k, q_k = np.array([3.0, 1.0, -0.5]), quat_normalize(np.array([0.9, -0.1, 0.3, 0.2]))
    A = rng.normal(size=(12, 12)) * 0.02
    C_jk = A @ A.T + 1e-4 * np.eye(12)
    C_m = np.diag([1e-3, 2e-3, 1e-3, 1e-4, 1e-4, 2e-4])
    L, Lm = np.linalg.cholesky(C_jk), np.linalg.cholesky(C_m)
    nis, nis_rot = [], []
    for _ in range(2000):
        e = L @ rng.normal(size=12)  # the estimate's error: truth = estimate moved by -e
        pj, qj = _perturb(p_j, q_j, -e[:6])
        pk, qk = _perturb(p_k, q_k, -e[6:])
        # the measurement: the true pose of k relative to j, placed on the estimate of j
        t, R = _relative(pj, qj, pk, qk)
        pm0 = p_j + quat_to_rotmat(q_j) @ t
        from eifslam.geometry.rotations import rotmat_to_quat
        qm0 = rotmat_to_quat(quat_to_rotmat(q_j) @ R)
        pm, qm = _perturb(pm0, qm0, Lm @ rng.normal(size=6))
        nis.append(pose_agreement(p_j, q_j, p_k, q_k, C_jk, pm, qm, C_m)[0])
    mean = float(np.mean(nis))
    assert 5.6 < mean < 6.4  # chi-square, 6 DOF (mean 6, sd of the mean 0.077)
    rate = float(np.mean(np.array(nis) > chi2_quantile(6, 0.05)))
    assert 0.035 < rate < 0.065
    # rotation alone: a rotation error drawn from C_k + C_m
    C_k = C_jk[9:, 9:]
    Lr = np.linalg.cholesky(C_k + C_m[3:, 3:])
    for _ in range(2000):
        qm = quat_multiply(q_k, quat_exp(Lr @ rng.normal(size=3)))
        nis_rot.append(rotation_agreement(q_k, qm, C_k, C_m[3:, 3:]))
    assert 2.8 < float(np.mean(nis_rot)) < 3.2


def test_a_half_turn_alias_is_refused_at_any_sensible_rate():
    q_k = np.array([1.0, 0, 0, 0])
    q_m = quat_exp(np.array([0.0, np.radians(178.0), 0.0]))
    C = np.eye(3) * np.radians(2.0) ** 2  # a generous 2 degree drift
    assert rotation_agreement(q_k, q_m, C, C) > chi2_quantile(3, 1e-9)
    assert rotation_agreement(q_k, q_k, C, C) == 0.0
