"""The dense EKF agrees with the EIF when both see the same measurements, linearised alike."""

from __future__ import annotations

import dataclasses

import numpy as np

from eifslam.baselines.ekf import DenseEKF
from eifslam.estimation.filter import InformationFilter
from eifslam.sim import synthetic
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.system.slam import Slam


def run(sc, seed: int, ekf: bool, **kw):
    """The system over every frame of ``sc`` with the EIF (its default back end) or the
    dense EKF, on the same simulated measurements; the filter at its complete estimate."""
    fe = SyntheticFrontEnd(sc, seed, map_fraction=1.0, **kw)
    config = fe.slam_config()
    # linearised alike: the EKF never relinearises, so the EIF's online relinearisation is off
    backend = DenseEKF(sc.camera, config.filter) if ekf else \
        InformationFilter(sc.camera, dataclasses.replace(config.filter, relinearise_threshold=None))
    slam = Slam(sc.camera, config, frontend=fe, backend=backend)
    for k in range(len(sc.positions)):
        slam.track(k)
    slam.filter.complete_estimate()
    return slam.filter


def test_ekf_estimate_and_covariance_agree_with_eif():
    rng = np.random.default_rng(1)
    sc = synthetic.corridor_scene(8, rng, points_per_metre=10)
    eif = run(sc, 1, ekf=False, sigma_px=0.5)
    ekf = run(sc, 1, ekf=True, sigma_px=0.5)
    assert ekf.dim == eif.dim > 200
    _, P1, Q1 = eif.poses()
    _, P2, Q2 = ekf.poses()
    err_truth = np.abs(P1 - sc.positions).max()
    assert 1e-3 < err_truth < 0.1  # noise was applied
    assert np.abs(P1 - P2).max() < 1e-2 * err_truth
    assert np.abs(Q1 - Q2).max() < 1e-5
    assert np.abs(eif.features()[1] - ekf.features()[1]).max() < 1e-2
    C1, C2 = eif.pose_covariance(7), ekf.pose_covariance(7)
    assert np.allclose(np.diag(C1), np.diag(C2), rtol=1e-2)
    ids = ekf.features()[0][:4]
    F = ekf.feature_covariances(ids + [ids[0], -5])  # a repeat and an unknown id
    assert np.array_equal(F[:4], np.stack([ekf.feature_covariance(t) for t in ids]))
    assert np.array_equal(F[4], F[0]) and np.isnan(F[5]).all()


def test_ekf_update_reduces_only_the_touched_uncertainty():
    rng = np.random.default_rng(2)
    sc = synthetic.corridor_scene(3, rng, points_per_metre=5)
    ekf = run(sc, 2, ekf=True, noise=False)
    assert np.allclose(ekf.P, ekf.P.T)
    assert np.all(np.linalg.eigvalsh(ekf.P) > -1e-9 * np.abs(ekf.P).max())
    _, P, _ = ekf.poses()
    assert np.abs(P - sc.positions).max() < 1e-6


def test_both_back_ends_satisfy_the_protocol_without_inheritance():
    from eifslam.estimation.backend import Backend

    rng = np.random.default_rng(3)
    sc = synthetic.corridor_scene(2, rng, points_per_metre=5)
    assert not issubclass(DenseEKF, InformationFilter)
    assert isinstance(DenseEKF(sc.camera), Backend)
    assert isinstance(InformationFilter(sc.camera), Backend)
