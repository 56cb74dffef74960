"""Conformance of the front ends: ``Slam`` at the default settings on the OpenCV front end
(the first rendered frames of the built-in scene) and on the synthetic one."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from eifslam.baselines.ekf import DenseEKF
from eifslam.sim import synthetic
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.system.frontend_protocol import FrontEndProtocol, LoopFrontEnd
from eifslam.system.slam import Slam, TrackingState

N_RENDERED = 8


@pytest.fixture(scope="module")
def rendered():
    """The built-in scene and its first frames, rendered once."""
    pytest.importorskip("cv2")
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54)
    return scene, [render_frame(scene, k) for k in range(N_RENDERED)]


def _ate(slam: Slam, positions: np.ndarray, timestamps: np.ndarray, quats: np.ndarray) -> float:
    from eifslam.evaluation.metrics import evaluate
    from eifslam.io import Trajectory

    t, P, Q = slam.trajectory()
    return evaluate(Trajectory(t, P, Q), Trajectory(timestamps, positions, quats)).ate_rmse


def test_the_protocol_module_does_not_import_opencv():
    code = ("import sys; import eifslam.system.frontend_protocol; "
            "sys.exit(int('cv2' in sys.modules or 'eifslam.frontend.frontend' in sys.modules))")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_slam_runs_at_the_defaults_on_the_opencv_frontend(rendered):
    scene, images = rendered
    slam = Slam(scene.camera)
    assert isinstance(slam.frontend, LoopFrontEnd) and isinstance(slam.frontend, FrontEndProtocol)
    states = [slam.track(im, float(scene.timestamps[k])).state for k, im in enumerate(images)]
    assert states[0] is TrackingState.INITIALISING
    assert all(s is TrackingState.TRACKING for s in states[1:])
    fin = slam.finish()
    assert fin.failures == []
    idx = np.arange(N_RENDERED)
    ate = _ate(slam, scene.positions[idx], scene.timestamps[idx], scene.quats_wxyz[idx])
    # noise-free renders, sub-pixel keypoints, a path of about a metre: well under a centimetre,
    # and not zero (the estimate is not the truth copied)
    assert 1e-6 < ate < 0.01


def test_opencv_frontend_with_the_dense_ekf(rendered):
    """The OpenCV front end's tracks (frames between keyframes, map features outside the
    window) on the dense EKF: fewer features keep ``P`` small."""
    scene, images = rendered
    from eifslam.system.config import SlamConfig

    config = SlamConfig().replace(frontend={"max_features": 400})
    slam = Slam(scene.camera, config, backend=DenseEKF(scene.camera, config.filter))
    states = [slam.track(im, float(scene.timestamps[k])).state for k, im in enumerate(images)]
    assert all(s is TrackingState.TRACKING for s in states[1:])
    assert slam.finish().failures == []
    idx = np.arange(N_RENDERED)
    assert 1e-6 < _ate(slam, scene.positions[idx], scene.timestamps[idx], scene.quats_wxyz[idx]) < 0.02


def test_slam_runs_at_the_defaults_on_the_synthetic_frontend():
    sc = synthetic.orbit_scene(10, np.random.default_rng(4))
    fe = SyntheticFrontEnd(sc, 4)
    assert isinstance(fe, FrontEndProtocol) and not isinstance(fe, LoopFrontEnd)
    slam = Slam(sc.camera, fe.slam_config(), frontend=fe)
    assert not slam.loops.enabled  # no descriptors: no loop closing
    states = [slam.track(k).state for k in range(len(sc.positions))]
    assert all(s is TrackingState.TRACKING for s in states[1:])
    assert slam.finish().failures == []
    P = np.array([r.position for r in slam.results])
    ate = float(np.sqrt(np.mean(np.sum((P - sc.positions) ** 2, 1))))
    assert 1e-4 < ate < 0.05  # one pixel of noise, 4 m from the cloud; the truth's scale
