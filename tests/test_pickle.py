"""Filters pickle without outsiders blanking their fields."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from eifslam.estimation.filter import InformationFilter
from eifslam.estimation.recovery import factorize
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene
from eifslam.system.slam import Slam


def run(sc, seed: int, f: InformationFilter, n_frames: int | None = None) -> InformationFilter:
    """The system over the first ``n_frames`` frames of ``sc`` with back end ``f``."""
    fe = SyntheticFrontEnd(sc, seed, map_fraction=1.0)
    slam = Slam(sc.camera, fe.slam_config(), frontend=fe, backend=f)
    for k in range(len(sc.positions) if n_frames is None else n_frames):
        slam.track(k)
    return f


@pytest.mark.parametrize("recovery", ["incremental", "full"])
def test_pickle_round_trip_recovers_the_same_state(recovery):
    rng = np.random.default_rng(5)
    sc = corridor_scene(8, rng, points_per_metre=8.0)
    f = run(sc, 5, InformationFilter(sc.camera, recovery=recovery))
    f.factor()  # a cached SuperLU factorisation, which does not pickle
    g = pickle.loads(pickle.dumps(f))
    assert g.dim == f.dim and g.layout.order == f.layout.order
    assert np.array_equal(g.information_vector(), f.information_vector())
    assert (g.information_matrix() != f.information_matrix()).nnz == 0
    assert np.allclose(g.x, f.complete_estimate(), rtol=0, atol=1e-12)
    assert np.array_equal(g.recover(), f.recover())
    C, D = g.pose_covariance(3), f.pose_covariance(3)
    # the unpickled window is rebuilt (another elimination order of the same matrix): equal
    # to rounding, judged against the block's scale (a small off-diagonal entry differed by
    # 2e-9 of itself, 1e-13 of the block, once new features were refined on every view)
    assert np.allclose(C, D, rtol=1e-9, atol=1e-9 * np.abs(D).max())


def test_unpickled_incremental_recovery_rebuilds_and_continues():
    rng = np.random.default_rng(6)
    sc = corridor_scene(12, rng, points_per_metre=8.0)
    f = InformationFilter(sc.camera, recovery="incremental", window=1)
    run(sc, 6, f, n_frames=6)
    g = pickle.loads(pickle.dumps(f))
    assert not g.incremental.valid
    rebuilds = g.incremental.stats.rebuilds
    g.recover_active()
    assert g.incremental.valid and g.incremental.stats.rebuilds == rebuilds + 1
    g.complete_estimate()
    I, i = g.information_matrix(), g.information_vector()
    x = factorize(I, *g.index_sets()).solve(i)
    assert np.max(np.abs(g.x - x)) < 1e-8 * max(1.0, np.abs(x).max())
