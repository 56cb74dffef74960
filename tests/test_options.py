"""Typed options and state keys of the estimation layer accept the plain strings."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.errors import ConfigError, EstimatorError
from eifslam.estimation.filter import InformationFilter
from eifslam.estimation.options import Recovery
from eifslam.estimation.state import StateKey, StateKind, StateLayout
from eifslam.geometry.camera import PinholeCamera


def test_recovery_is_chosen_by_a_string_enum_or_given_as_an_object():
    from eifslam.estimation.recovery_modes import FullRecovery, RecoveryMode, WindowRecovery

    cam = PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480)
    for how in ("full", Recovery.FULL):
        f = InformationFilter(cam, recovery=how)
        assert isinstance(f.recovery, FullRecovery) and f.incremental is None
    f = InformationFilter(cam)
    assert isinstance(f.recovery, WindowRecovery) and isinstance(f.recovery, RecoveryMode) and f.incremental is not None
    given = FullRecovery()
    assert InformationFilter(cam, recovery=given).recovery is given
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


@pytest.mark.parametrize("far", [50, 10**9])
def test_feature_lookups_agree_with_the_layout_dicts(far):
    """has_features/feature_offsets (vectorised through a track-id array, or the dict
    when the ids are too sparse for one) give what the per-id queries give, as the layout grows."""
    rng = np.random.default_rng(1)
    lay = StateLayout()
    ids = [int(v) for v in rng.permutation(40)[:25]] + [far]
    for n, t in enumerate(ids):
        lay.add_feature(t)
        if n % 3 == 0:
            lay.add_pose(n)
        ask = np.concatenate([rng.integers(-3, 45, 30), [far, far + 1]])
        expect = np.array([lay.has_feature(int(a)) for a in ask])
        np.testing.assert_array_equal(lay.has_features(ask), expect)
        np.testing.assert_array_equal(lay.has_features(ask.tolist()), expect)
        big = np.tile(ask, 20)  # enough ids for the sorted lookup when the ids are sparse
        np.testing.assert_array_equal(lay.has_features(big), np.tile(expect, 20))
        known = ask[expect]
        np.testing.assert_array_equal(lay.feature_offsets(known), [lay.feature_offset(int(a)) for a in known])
        np.testing.assert_array_equal(lay.feature_offsets(np.tile(known, 40)),
                                      [lay.feature_offset(int(a)) for a in np.tile(known, 40)])
    assert lay.feature_ids == ids and lay.pose_ids == [n for n in range(len(ids)) if n % 3 == 0]
    missing = next(a for a in range(-3, 45) if not lay.has_feature(a))
    with pytest.raises(EstimatorError, match=f"feature {missing} is not in the state"):
        lay.feature_offsets([ids[0], missing])
    assert lay.has_features([]).shape == (0,) and lay.feature_offsets([]).shape == (0,)
