"""The focal-length check finds a focal length given wrong, and accepts the right one
(synthetic orbit: the camera turns round the scene, so the focal length is observable)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from eifslam.sim import synthetic
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.system.slam import Slam


def _focal(stated_over_true: float):
    sc = synthetic.orbit_scene(12, np.random.default_rng(1))
    fe = SyntheticFrontEnd(sc, 1)
    cam = dataclasses.replace(sc.camera, fx=sc.camera.fx * stated_over_true, fy=sc.camera.fy * stated_over_true)
    slam = Slam(cam, fe.slam_config(), frontend=fe)
    for k in range(len(sc.positions)):
        slam.track(k)
    return slam.smooth().focal


@pytest.mark.parametrize("stated_over_true", [1.0, 1.03])
def test_the_focal_check_finds_the_true_focal_length(stated_over_true):
    check = _focal(stated_over_true)
    truth = 1.0 / stated_over_true  # the factor that takes the stated focal length to the true one
    assert 0 < check.sigma < 0.01
    assert abs(check.scale - truth) < 4 * check.sigma + 0.002
    if stated_over_true == 1.0:
        assert check.chi2 < 10.8  # chi-square 1 DOF, 0.1%
    else:
        assert check.chi2 > 50 and abs(check.scale - 1.0) > 10 * check.sigma
