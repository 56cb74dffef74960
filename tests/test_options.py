"""Typed options and state keys of the estimation layer accept the plain strings (issue 11)."""

from __future__ import annotations

import pytest

from eifslam.errors import ConfigError, EstimatorError
from eifslam.estimation.filter import FilterConfig, InformationFilter
from eifslam.estimation.options import Recovery, ZtForm
from eifslam.estimation.state import StateKey, StateKind, StateLayout
from eifslam.geometry.camera import PinholeCamera


def test_zt_form_and_recovery_are_string_enums():
    cfg = FilterConfig(zt_form="bearing")
    assert cfg.zt_form is ZtForm.BEARING and cfg.zt_form == "bearing" and str(cfg.zt_form) == "bearing"
    assert FilterConfig().zt_form == "auto"
    with pytest.raises(ConfigError):
        FilterConfig(zt_form="sideways")
    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    f = InformationFilter(cam, recovery="full")
    assert f.recovery is Recovery.FULL and f.recovery == "full" and f.incremental is None
    assert InformationFilter(cam).recovery == Recovery.INCREMENTAL
    with pytest.raises(ConfigError):
        InformationFilter(cam, recovery="sometimes")


def test_state_keys_are_tuples():
    lay = StateLayout()
    lay.add_pose(3)
    lay.add_feature(7)
    assert lay.order == (("pose", 3), ("feature", 7))
    assert lay.order[0] == StateKey(StateKind.POSE, 3) and lay.order[1].kind is StateKind.FEATURE
    assert {("pose", 3): 1}[lay.order[0]] == 1
    assert StateKey.of(("feature", "7")) == (StateKind.FEATURE, 7)
    with pytest.raises(EstimatorError):
        StateKey.of(("landmark", 1))
    assert lay.keys_since(1) == [("feature", 7)] and lay.n_states == 2
