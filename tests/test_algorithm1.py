"""Algorithm 1 as one function: the back end sees the paper's steps in the paper's order."""

from __future__ import annotations

import numpy as np

from eifslam.sim import synthetic
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.system.algorithm1 import OnMap, Placement, algorithm1
from eifslam.system.slam import Slam, TrackingState

STEPS = ("triangulate_new", "add_pose", "add_features", "fuse_relative", "fuse_features", "recover_active")


def _recorded_slam(n_frames: int = 8):
    """``Slam`` on a synthetic corridor with the back end's and the mapper's step calls
    recorded as ``(name, frame being placed, state dimension at the call)``."""
    sc = synthetic.corridor_scene(n_frames, np.random.default_rng(3))
    fe = SyntheticFrontEnd(sc, 1)
    slam = Slam(sc.camera, fe.slam_config(), frontend=fe)
    log: list[tuple[str, int, int]] = []
    current = {"k": -1}

    def record(obj, name):
        orig = getattr(obj, name)

        def wrapper(*args, **kwargs):
            log.append((name, current["k"], slam.filter.dim))
            return orig(*args, **kwargs)

        setattr(obj, name, wrapper)

    for name in STEPS[1:] + ("set_scale",):
        record(slam.filter, name)
    record(slam.mapper, "triangulate_new")
    states = []
    for k in range(n_frames):
        current["k"] = k
        states.append(slam.track(k).state)
    return slam, states, log


def test_each_keyframe_goes_through_the_five_steps_in_order():
    slam, states, log = _recorded_slam()
    assert states[0] is TrackingState.INITIALISING and all(s is TrackingState.TRACKING for s in states[1:])
    placed = sorted({k for name, k, _ in log if name == "triangulate_new"})
    assert placed and placed[0] == 1
    for k in placed:
        calls = [(name, dim) for name, kk, dim in log if kk == k]
        names = [n for n, _ in calls]
        first = [names.index(s) for s in STEPS if s in names]
        assert first == sorted(first), names  # step 3, 4 (pose, features), 5 (ZR/ZT, Zm), recovery
        assert {"triangulate_new", "add_pose", "add_features", "fuse_features", "recover_active"} <= set(names)
        # step 3 computes guesses only: nothing enters the state before step 4
        assert calls[names.index("triangulate_new")][1] == calls[names.index("add_pose")][1]
        # the scale is set once, on the first step, right after the pose enters
        if k == placed[0]:
            assert names[names.index("add_pose") + 1] == "set_scale"
        else:
            assert "set_scale" not in names
    # each keyframe's ZR/ZT is either fused or kept among the refused ones
    refused = {rp.j for rp in slam.tracker.rejected_relative}
    for k in placed:
        assert ("fuse_relative" in [n for n, kk, _ in log if kk == k]) != (k in refused)
    assert 1 not in refused


def test_algorithm1_reports_the_placement_and_its_timings():
    sc = synthetic.corridor_scene(4, np.random.default_rng(4))
    fe = SyntheticFrontEnd(sc, 1)
    slam = Slam(sc.camera, fe.slam_config(), frontend=fe)
    slam.track(0)
    fe.add_frame(1, 1)
    rp, _ = slam.tracker.find_reference(1, {}, relocalise=False)
    timings: dict[str, float] = {}
    placement = algorithm1(1, rp, slam.tracker, timings)
    assert isinstance(placement, Placement)
    assert placement.frame_id == 1 and placement.reference == 0 and placement.relative_fused
    assert placement.new_features == slam.filter.layout.n_features > 0
    assert set(timings) == {"init", "fuse", "recover"} and all(v >= 0 for v in timings.values())


def test_on_the_map_alone_without_a_map_nothing_changes():
    sc = synthetic.corridor_scene(4, np.random.default_rng(5))
    fe = SyntheticFrontEnd(sc, 1)
    slam = Slam(sc.camera, fe.slam_config(), frontend=fe)
    slam.track(0)
    fe.add_frame(1, 1)
    dim, timings = slam.filter.dim, {}
    assert algorithm1(1, OnMap(), slam.tracker, timings) is None
    assert slam.filter.dim == dim and timings == {}
