"""Conformance of the back ends: ``Slam`` at the default settings on the EIF and on the
dense EKF, over a synthetic scene with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.baselines.ekf import DenseEKF
from eifslam.estimation.backend import Backend
from eifslam.estimation.filter import InformationFilter
from eifslam.sim import synthetic
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.system.slam import Slam, TrackingState

SCENES = {
    "corridor": lambda: synthetic.corridor_scene(12, np.random.default_rng(1)),
    "orbit": lambda: synthetic.orbit_scene(12, np.random.default_rng(1)),
}


def _run(scene, backend: str, **experimental):
    """``Slam`` with ``SlamConfig()`` matched to the simulation (pixel noise, true scale)
    over every frame, then its default finish (mode ``smooth``)."""
    fe = SyntheticFrontEnd(scene, 1)
    config = fe.slam_config(experimental=experimental)
    be = DenseEKF(scene.camera, config.filter) if backend == "ekf" else None
    slam = Slam(scene.camera, config, frontend=fe, backend=be)
    states = [slam.track(k).state for k in range(len(scene.positions))]
    fin = slam.finish()
    return slam, states, fin


@pytest.mark.parametrize("scene", sorted(SCENES))
@pytest.mark.parametrize("backend", ["eif", "ekf"])
def test_slam_runs_at_the_defaults_on_each_backend(backend, scene):
    sc = SCENES[scene]()
    slam, states, fin = _run(sc, backend)
    assert isinstance(slam.filter, Backend)
    assert isinstance(slam.filter, DenseEKF if backend == "ekf" else InformationFilter)
    assert states[0] is TrackingState.INITIALISING
    assert all(s is TrackingState.TRACKING for s in states[1:])
    assert fin.failures == [] and fin.smoothing is not None
    P = np.array([r.position for r in slam.results])
    assert P.shape == sc.positions.shape
    # the gauge is the first frame and the scale the true distance: positions compare with
    # the truth without alignment. One pixel of noise over 4-8 m of depth: millimetres to
    # centimetres; zero would mean the noise was not applied.
    ate = float(np.sqrt(np.mean(np.sum((P - sc.positions) ** 2, 1))))
    path = float(np.sum(np.linalg.norm(np.diff(sc.positions, axis=0), axis=1)))
    assert 1e-4 < ate < 0.01 * path


def test_both_backends_reach_the_same_smoothed_estimate():
    """Smoothing is a batch solve of the same stored measurements: the two back ends end
    within a fraction of their error of each other. The EIF recovers by the full solve here,
    which does not relinearise online: linearised as the EKF, its gate passes the same
    ``Zm`` (relinearised, it passes a few more, and the two smooth different sets)."""
    sc = SCENES["corridor"]()
    eif = np.array([r.position for r in _run(sc, "eif", recovery="full")[0].results])
    ekf = np.array([r.position for r in _run(sc, "ekf")[0].results])
    err = np.abs(eif - sc.positions).max()
    assert 0 < np.abs(eif - ekf).max() < 0.5 * err


def test_dense_ekf_takes_back_a_batch_step():
    """``information_form`` holds every state and stored measurement at the EKF's mean;
    ``set_from_information_form`` brings back its estimate and ``P = I^-1``."""
    sc = synthetic.corridor_scene(4, np.random.default_rng(2), points_per_metre=5)
    slam, _, _ = _run(sc, "ekf")
    ekf = slam.filter
    info = ekf.information_form()
    assert isinstance(info, InformationFilter) and info.layout.order == ekf.layout.order
    np.testing.assert_array_equal(info.x, ekf.x)
    assert len(info.store.all_features()) == len(ekf.store.all_features()) > 0
    x = info.x.copy()
    x[:3] += 0.01
    info.set_estimate(x)
    ekf.set_from_information_form(info)
    np.testing.assert_array_equal(ekf.x, x)
    I = info.information_matrix().toarray()
    np.testing.assert_allclose(ekf.P @ I, np.eye(ekf.dim), atol=1e-6)
    G = np.eye(3)
    tid = ekf.features()[0][0]
    np.testing.assert_allclose(ekf.feature_propagate([tid], G), ekf.feature_covariance(tid))
    eif = InformationFilter(sc.camera)
    assert eif.information_form() is eif
