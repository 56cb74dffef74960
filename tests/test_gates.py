"""The ZR/ZT gate tests a relative pose against its innovation covariance: on the
synthetic corridor, where every measurement is correct, it refuses about as many as its
false-alarm rate says."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene
from eifslam.system import algorithm1
from eifslam.system.slam import Slam


@pytest.fixture(scope="module")
def corridor_gates():
    """The ZR/ZT gate's statistics over 30 frames of the corridor at the defaults."""
    stats: list[float] = []
    statistic = algorithm1.relative_gate_statistic
    mp = pytest.MonkeyPatch()

    def recording_statistic(*args):
        stats.append(statistic(*args))
        return stats[-1]

    mp.setattr(algorithm1, "relative_gate_statistic", recording_statistic)
    try:
        sc = corridor_scene(30, np.random.default_rng(3))
        fe = SyntheticFrontEnd(sc, 3, map_fraction=1.0)
        slam = Slam(sc.camera, fe.slam_config(), frontend=fe)
        for k in range(30):
            slam.track(k)
    finally:
        mp.undo()
    return np.array(stats), slam


def test_relative_gate_statistic_follows_chi2_5(corridor_gates):
    """Against ``Q + J P J^T`` the ZR/ZT statistic has the mean of a chi-square(5) and
    refuses few of the correct relative poses (against ``Q`` alone it refused half; the
    one left is the first step off the two-view map, linearised at features whose depth
    two views barely fix)."""
    stats, slam = corridor_gates
    assert len(stats) >= 15
    assert 3.0 < np.median(stats) < 8.0
    assert np.mean(stats > slam.config.experimental.relative_gate_chi2) <= 0.05


def test_relative_gate_statistic_without_pose_uncertainty_is_against_q(corridor_gates):
    """Without the new pose's uncertainty the statistic is the measurement's own normalised
    innovation squared; with it, never larger."""
    _, slam = corridor_gates
    f = slam.filter
    rp = f.store.relative[-1]
    _, _, W, innov = f.linearise_relative([rp])
    plain = algorithm1.relative_gate_statistic(f, rp)
    assert plain == pytest.approx(float(innov[0] @ W[0] @ innov[0]), rel=1e-12)
    ids, X = f.features()
    A = np.zeros((6, 3 * len(ids)))
    A[0, 0] = 1.0
    assert algorithm1.relative_gate_statistic(f, rp, (np.asarray(ids), A, 1e-4 * np.eye(6))) <= plain + 1e-9


def test_zm_gate_count_adds_up(corridor_gates):
    """The filter counts the ``Zm`` its gate was offered and refused: what it kept are the
    stored ``Zm`` (no loop fuses ungated ones on the corridor, none wait); it refuses some
    (each correct, on this simulation: features whose estimate is off), never most."""
    _, slam = corridor_gates
    g, filt = slam.filter.zm_gate, slam.filter
    assert slam.mapper.deferred == 0 and not slam.loops.closures
    assert g.offered - g.refused == len(filt.store.all_features())
    assert 0 < g.refused < 0.5 * g.offered
    assert g.rate == pytest.approx(g.refused / g.offered)


def test_zm_gate_count_survives_a_session(corridor_gates):
    """A saved and loaded filter keeps its gate count; a malformed one is refused."""
    from eifslam.errors import SessionError
    from eifslam.estimation.filter import InformationFilter

    _, slam = corridor_gates
    d = slam.filter.state_dict()
    f2 = InformationFilter(slam.filter.camera, slam.filter.config)
    f2.load_state_dict(d)
    assert (f2.zm_gate.offered, f2.zm_gate.refused) == (slam.filter.zm_gate.offered, slam.filter.zm_gate.refused)
    d["zm_gate"] = [1]
    with pytest.raises(SessionError, match="zm_gate"):
        InformationFilter(slam.filter.camera, slam.filter.config).load_state_dict(d)
