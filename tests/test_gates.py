"""The gates test a measurement against its innovation covariance: on the synthetic
corridor, where every measurement is correct, they refuse about as many as their
false-alarm rate says."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from eifslam.estimation.filter import InformationFilter
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene
from eifslam.system import algorithm1
from eifslam.system.slam import Slam


@pytest.fixture(scope="module")
def corridor_gates():
    """Zm offered and refused by the filter's gate, and the ZR/ZT gate's statistics, over
    30 frames of the corridor at the defaults."""
    counts = {"zm": 0, "refused": 0}
    stats: list[float] = []
    fuse, statistic = InformationFilter.fuse_features, algorithm1.relative_gate_statistic
    mp = pytest.MonkeyPatch()

    def counting_fuse(self, obs, store=True, gate=True):
        out = fuse(self, obs, store, gate)
        if gate and len(obs):
            usable = self.linearise_features(obs, gate=False)[0]
            counts["zm"] += int(usable.sum())
            counts["refused"] += int(usable.sum()) - len(out)
        return out

    def recording_statistic(*args):
        stats.append(statistic(*args))
        return stats[-1]

    mp.setattr(InformationFilter, "fuse_features", counting_fuse)
    mp.setattr(algorithm1, "relative_gate_statistic", recording_statistic)
    try:
        sc = corridor_scene(30, np.random.default_rng(3))
        fe = SyntheticFrontEnd(sc, 3, map_fraction=1.0)
        slam = Slam(sc.camera, fe.slam_config(), frontend=fe)
        for k in range(30):
            slam.track(k)
    finally:
        mp.undo()
    return counts, np.array(stats), slam


def test_zm_gate_refuses_correct_measurements_at_most_at_its_false_alarm_rate(corridor_gates):
    counts, _, slam = corridor_gates
    gate = slam.filter.config.gate_chi2
    alpha = float(chi2.sf(gate, 2))  # 1% at the default 9.21
    assert counts["zm"] > 1000
    assert counts["refused"] / counts["zm"] <= 1.5 * alpha


def test_relative_gate_statistic_follows_chi2_5(corridor_gates):
    """Against ``Q + J P J^T`` the ZR/ZT statistic has the mean of a chi-square(5) and
    refuses few of the correct relative poses (against ``Q`` alone it refused half; the
    one left is the first step off the two-view map, linearised at features whose depth
    two views barely fix)."""
    _, stats, slam = corridor_gates
    assert len(stats) >= 15
    assert 3.0 < np.median(stats) < 8.0
    assert np.mean(stats > slam.config.experimental.relative_gate_chi2) <= 0.05


def test_relative_gate_statistic_without_pose_uncertainty_is_against_q(corridor_gates):
    """Without the new pose's uncertainty the statistic is the measurement's own normalised
    innovation squared; with it, never larger."""
    _, _, slam = corridor_gates
    f = slam.filter
    rp = f.store.relative[-1]
    _, _, W, innov = f.linearise_relative([rp])
    plain = algorithm1.relative_gate_statistic(f, rp)
    assert plain == pytest.approx(float(innov[0] @ W[0] @ innov[0]), rel=1e-12)
    ids, X = f.features()
    A = np.zeros((6, 3 * len(ids)))
    A[0, 0] = 1.0
    assert algorithm1.relative_gate_statistic(f, rp, (np.asarray(ids), A, 1e-4 * np.eye(6))) <= plain + 1e-9


def test_innovation_chi2_only_lowers_the_tested_entries(corridor_gates):
    _, _, slam = corridor_gates
    f = slam.filter
    obs = f.store.all_features()
    obs = obs.subset(np.arange(len(obs)) >= len(obs) - 200)
    ok, idx, J, _, innov, c = f.linearise_features(obs, gate=False)
    test = ok & (np.arange(len(obs)) % 2 == 0)
    out = f.innovation_chi2(obs, test, idx, J, innov, c)
    assert np.array_equal(out[~test], c[~test])
    assert np.all(out[test] <= c[test] + 1e-9)
