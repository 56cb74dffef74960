"""Analytic Jacobians of every observation model against central differences."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.geometry import models
from eifslam.geometry.rotations import quat_exp, quat_multiply, quat_normalize, quat_to_rotmat

RTOL = 1e-6


def numeric_jacobian(f, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central-difference Jacobian of ``f: (n,) -> (m,)`` at ``x``."""
    cols = []
    for k in range(len(x)):
        e = np.zeros_like(x)
        e[k] = eps
        cols.append((f(x + e) - f(x - e)) / (2 * eps))
    return np.stack(cols, -1)


def rel_err(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.linalg.norm(A - B) / max(np.linalg.norm(B), 1e-12))


def random_quat(rng, scale=1.0):
    q = rng.normal(size=4)
    return scale * q / np.linalg.norm(q)


@pytest.mark.parametrize("seed", range(20))
def test_feature_model_jacobian(seed):
    rng = np.random.default_rng(seed)
    q = random_quat(rng, scale=rng.uniform(0.7, 1.3))  # deliberately not unit
    p = rng.normal(size=3)
    R = quat_to_rotmat(q)
    X = p + R @ np.array([rng.normal(), rng.normal(), rng.uniform(0.5, 5)])
    K = (500.0, 480.0, 320.0, 240.0)

    def f(v):
        h, *_ = models.feature_model(v[None, :3], v[None, 3:7], v[None, 7:], *K)
        return h[0]

    x0 = np.concatenate([p, q, X])
    h, Jp, Jf, z = models.feature_model(p[None], q[None], X[None], *K)
    assert z[0] > 0
    J = np.concatenate([Jp[0], Jf[0]], 1)
    assert rel_err(J, numeric_jacobian(f, x0)) < RTOL


@pytest.mark.parametrize("seed", range(5))
def test_feature_model_of_one_pose_is_the_feature_model(seed):
    """Many points from one (non-unit) pose: the same predictions, depths and Jacobians
    as the element-wise model, and a Jacobian that finite differences confirm."""
    rng = np.random.default_rng(seed)
    q = random_quat(rng, scale=rng.uniform(0.7, 1.3))
    p = rng.normal(size=3)
    X = p + (quat_to_rotmat(q) @ np.column_stack([rng.normal(size=40), rng.normal(size=40),
                                                    rng.uniform(0.5, 5, 40)]).T).T
    K = (500.0, 480.0, 320.0, 240.0)
    one = models.feature_model_one_pose(p, q, X, *K)
    each = models.feature_model(np.tile(p, (40, 1)), np.tile(q, (40, 1)), X, *K)
    for a, b in zip(one, each):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12 * max(1.0, float(np.abs(b).max())))

    def f(v):
        return models.feature_model_one_pose(v[:3], v[3:7], v[None, 7:], *K)[0][0]

    J = np.concatenate([one[1][7], one[2][7]], 1)
    assert rel_err(J, numeric_jacobian(f, np.concatenate([p, q, X[7]]))) < RTOL


def test_feature_model_prediction_matches_pinhole():
    rng = np.random.default_rng(1)
    q = quat_normalize(random_quat(rng))
    p = rng.normal(size=3)
    Xc = np.array([0.3, -0.2, 2.0])
    X = p + quat_to_rotmat(q) @ Xc
    h, *_ = models.feature_model(p[None], q[None], X[None], 500, 500, 320, 240)
    np.testing.assert_allclose(h[0], [500 * 0.15 + 320, -500 * 0.1 + 240], atol=1e-9)


@pytest.mark.parametrize("seed", range(20))
@pytest.mark.parametrize("kind", ["translation", "bearing"])
def test_translation_models_jacobian(seed, kind):
    rng = np.random.default_rng(seed)
    qi = random_quat(rng, scale=rng.uniform(0.7, 1.3))
    pi = rng.normal(size=3)
    # direction in frame i: forward-ish for the paper model, anything for the bearing one
    d = np.array([rng.normal(), rng.normal(), rng.uniform(0.5, 2.0)]) if kind == "translation" else rng.normal(size=3)
    pj = pi + quat_to_rotmat(qi) @ d
    qj = random_quat(rng)
    t_meas = d / np.linalg.norm(d) + 0.01 * rng.normal(size=3)
    t_meas /= np.linalg.norm(t_meas)

    def model(v):
        a, b = v[:7], v[7:]
        if kind == "translation":
            return models.translation_model(a[None, :3], a[None, 3:], b[None, :3])
        return models.bearing_model(a[None, :3], a[None, 3:], b[None, :3], t_meas[None])

    x0 = np.concatenate([pi, qi, pj, qj])
    h, Ji, Jj = model(x0)
    J = np.concatenate([Ji[0], Jj[0]], 1)
    assert rel_err(J, numeric_jacobian(lambda v: model(v)[0][0], x0)) < RTOL


@pytest.mark.parametrize("seed", range(20))
def test_rotation_model_jacobian(seed):
    rng = np.random.default_rng(seed)
    qi = random_quat(rng, scale=rng.uniform(0.7, 1.3))
    qj = random_quat(rng, scale=rng.uniform(0.7, 1.3))
    q_true = quat_multiply(quat_normalize(qi) * [1, -1, -1, -1], quat_normalize(qj))
    q_meas = quat_normalize(quat_multiply(q_true, quat_exp(0.05 * rng.normal(size=3))))

    def f(v):
        return models.rotation_model(v[None, :4], v[None, 4:], q_meas[None])[0][0]

    x0 = np.concatenate([qi, qj])
    h, Ji, Jj = models.rotation_model(qi[None], qj[None], q_meas[None])
    assert rel_err(np.concatenate([Ji[0], Jj[0]], 1), numeric_jacobian(f, x0)) < RTOL


def test_rotation_model_is_dtheta_to_first_order():
    rng = np.random.default_rng(3)
    qi = quat_normalize(random_quat(rng))
    q_meas = quat_normalize(random_quat(rng))
    dtheta = 1e-4 * rng.normal(size=3)
    qj = quat_multiply(qi, quat_multiply(q_meas, quat_exp(dtheta)))
    h, *_ = models.rotation_model(qi[None], qj[None], q_meas[None])
    np.testing.assert_allclose(h[0], dtheta, rtol=1e-3, atol=1e-10)


@pytest.mark.parametrize("angle_deg", [89.0, 89.9, 89.999])
def test_bearing_model_near_sideways(angle_deg):
    """Near-singular for the paper's form (z -> 0): the bearing model stays exact and bounded."""
    rng = np.random.default_rng(7)
    a = np.radians(angle_deg)
    d = np.array([np.sin(a), 0.0, np.cos(a)])
    qi = np.array([1.0, 0, 0, 0])
    pi = np.zeros(3)
    pj = d * 2.0
    t_meas = d

    def f(v):
        return models.bearing_model(v[None, :3], v[None, 3:7], v[None, 7:10], t_meas[None])[0][0]

    x0 = np.concatenate([pi, qi, pj])
    h, Ji, Jj = models.bearing_model(pi[None], qi[None], pj[None], t_meas[None])
    assert np.all(np.isfinite(Ji)) and np.abs(Ji).max() < 10
    J = np.concatenate([Ji[0], Jj[0][:, :3]], 1)
    assert rel_err(J, numeric_jacobian(f, x0)) < RTOL
    np.testing.assert_allclose(h[0], 0.0, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_distance_and_norm_models(seed):
    rng = np.random.default_rng(seed)
    a, b, q = rng.normal(size=3), rng.normal(size=3), rng.normal(size=4)
    h, Ja, Jb = models.distance_model(a[None], b[None])
    J = np.concatenate([Ja[0], Jb[0]], 1)
    fd = numeric_jacobian(lambda v: models.distance_model(v[None, :3], v[None, 3:])[0], np.concatenate([a, b]))
    assert rel_err(J, fd) < RTOL
    h, Jq = models.quat_norm_model(q[None])
    assert rel_err(Jq[0], numeric_jacobian(lambda v: models.quat_norm_model(v[None])[0], q)) < RTOL


def test_zt_paper_covariance_matches_linearisation():
    rng = np.random.default_rng(0)
    t = np.array([0.2, -0.1, 1.0])
    t /= np.linalg.norm(t)
    from eifslam.geometry.rotations import tangent_basis

    B = tangent_basis(t)

    def f(dt):
        v = t + B @ dt
        v /= np.linalg.norm(v)
        return v[:2] / v[2]

    z, G = models.zt_paper_covariance(t[None])
    np.testing.assert_allclose(z[0], t[:2] / t[2])
    assert rel_err(G[0], numeric_jacobian(f, np.zeros(2))) < RTOL
