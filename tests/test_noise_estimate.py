"""The pixel noise estimated from the residuals (robust smoothing's gate).

Known answer: the synthetic front end draws ``Zm`` with a chosen pixel noise while the
system is told another; :func:`residual_noise_scale` must find the ratio, and robust
smoothing must then gate at the noise found.
"""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.estimation.measurements import FeatureObservations
from eifslam.estimation.noise import MIN_GROUP_ZM, FeatureGate, track_length_noise
from eifslam.estimation.smoothing import residual_noise_scale, smooth
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene
from eifslam.system.slam import Slam


def _run(true_px: float, stated_px: float, seed: int = 3, frames: int = 12):
    rng = np.random.default_rng(seed)
    sc = corridor_scene(frames, rng)
    fe = SyntheticFrontEnd(sc, seed, sigma_px=true_px, map_fraction=1.0)
    cfg = fe.slam_config(frontend={"sigma_px": stated_px}, mapping={"min_feature_parallax_deg": 3.0})
    slam = Slam(sc.camera, cfg, frontend=fe)
    for k in range(frames):
        slam.track(k)
    slam.filter.complete_estimate()
    return slam


@pytest.mark.parametrize("true_px, stated_px", [(0.3, 1.0), (1.0, 1.0), (0.5, 2.0)])
def test_the_noise_ratio_is_found_from_the_residuals(true_px, stated_px):
    """At the smoothed estimate ``s`` is the true over the stated noise, within 20%
    (both sides: a wrong degrees-of-freedom correction or a mean instead of a median
    would miss it)."""
    slam = _run(true_px, stated_px)
    smooth(slam.filter, max_passes=5)
    s = residual_noise_scale(slam.filter)
    want = true_px / stated_px
    assert 0.8 * want < s < 1.2 * want, (s, want)


def test_the_filter_estimate_gives_no_smaller_ratio_than_the_truth_allows():
    """At the filter's estimate (linearised once) the residuals are no smaller than the
    noise: ``s`` is at least 0.8 of the truth there too, so the gate it sets is not
    tighter than the noise."""
    slam = _run(0.3, 1.0)
    s = residual_noise_scale(slam.filter)
    assert 0.8 * 0.3 < s < 2.0 * 0.3, s


def test_robust_smoothing_gates_at_the_noise_found():
    slam = _run(0.3, 1.0)
    rep = smooth(slam.filter, max_passes=5, feature_chi2=9.21, estimate_noise="global")
    assert 0.8 * 0.3 < rep.noise_scale < 2.0 * 0.3 and rep.noise_groups == []
    # no Zm left above the scaled gate at the returned estimate
    obs = slam.filter.store.all_features()
    chi2 = slam.filter.linearise_features(obs, gate=False)[-1]
    assert np.all(chi2 <= 9.21 * rep.noise_scale**2 * (1 + 1e-6)) or rep.kept != "smoothed"


def test_the_gate_is_never_loosened():
    """Noise larger than stated leaves the gate as given (``noise_scale`` capped at 1)."""
    for how in ("global", "track_length"):
        slam = _run(2.0, 1.0)
        rep = smooth(slam.filter, max_passes=3, feature_chi2=9.21, estimate_noise=how)
        assert rep.noise_scale == 1.0
        assert all(g.scale is None or g.scale > 1.0 for g in rep.noise_groups)


def test_passes_stop_when_damped_steps_only_crawl(monkeypatch):
    """A pass whose undamped step raises the cost and whose damped step lowers it by less
    than 1% ends the passes (another would crawl the same way); a damped step that lowers
    it by more goes on, the next pass trying a tenth of its damping (Marquardt's schedule,
    down to ``LAM_MIN``, then undamped); an undamped one below 1% is convergence."""
    from types import SimpleNamespace

    from eifslam.estimation import smoothing as sm

    def run(costs_by_lam: dict[float, list[float]], max_passes: int = 5) -> tuple[sm.SmoothingReport, list[float]]:
        seq = {lam: list(v) for lam, v in costs_by_lam.items()}
        filt = SimpleNamespace(x=np.zeros(3), dim=3, priors=SimpleNamespace(scale=None), current_lam=0.0,
                               started=False, tried=[], relinearise=lambda: None)

        def costs_at(f):  # the model cost: 100 at the start, then after each step by its damping
            v = seq[f.current_lam].pop(0) if f.started else 100.0
            f.started = True
            return SimpleNamespace(model=lambda fused: v, measurement=lambda: 0.0)

        def solve(f, x0, lam):
            f.current_lam = float(f"{lam:.3g}")  # 1e-4 / 10 is 1.0000000000000001e-05
            f.tried.append(f.current_lam)
            return x0 + 1.0

        monkeypatch.setattr(sm._Costs, "at", staticmethod(costs_at))
        monkeypatch.setattr(sm, "_damped_solve", solve)
        rep = sm.SmoothingReport()
        sm._passes(filt, max_passes, 1e-12, rep)
        return rep, filt.tried  # the dampings tried, in order

    crawl, _ = run({0.0: [101.0] * 5, 1e-3: [100.5] * 5, 1e-2: [99.6, 99.3, 99.0, 98.7, 98.4]})
    assert crawl.passes == 1 and not crawl.converged and crawl.reason.startswith("stopped: the last pass, damped")
    assert crawl.dampings == [1e-2]
    useful, tried = run({0.0: [101.0, 69.95], 1e-3: [100.5, 85.0], 1e-2: [90.0], 1e-4: [80.0], 1e-5: [75.0],
                         1e-6: [70.0]}, max_passes=8)
    assert useful.passes == 6 and useful.converged and "undamped" in useful.reason
    assert tried == [0.0, 1e-3, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 0.0]
    assert [float(f"{d:.3g}") for d in useful.dampings] == [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 0.0]  # the steps taken


def _track_lengths(filt):
    obs = filt.store.all_features()
    ids, inv, counts = np.unique(obs.feature, return_inverse=True, return_counts=True)
    return obs, counts[inv]


def test_every_track_length_group_finds_the_same_noise():
    """Noise 0.3 px stated as 1: at the smoothed estimate each group's ``s`` is 0.3
    within 25% (both sides: the per-group correction for its fitted parameters is what
    keeps the short tracks' ``s`` from being far too small)."""
    slam = _run(0.3, 1.0, frames=16)
    smooth(slam.filter, max_passes=5)
    noise = track_length_noise(slam.filter)
    told = [g for g in noise.groups if g.scale is not None]
    assert len(told) >= 3, noise.groups
    assert all(g.zm >= MIN_GROUP_ZM for g in noise.groups)  # the 4 Zm of 2-view tracks joined 3-4
    for g in told:
        assert 0.75 * 0.3 < g.scale < 1.25 * 0.3, g
    assert 0.8 * 0.3 < noise.overall < 1.2 * 0.3


def test_long_tracks_noisier_than_short_ones_get_their_own_gate():
    """Known answer: the ``Zm`` of features with 9 or more views carry 0.6 px of noise,
    the others 0.3 px (stated: 1 px). Refitted, the groups of long tracks find 0.6 and
    those of short ones 0.3 (within 25%), and the gate of each feature follows its
    group: ``9.21 s**2``, never above 9.21."""
    slam = _run(0.3, 1.0, frames=16)
    filt = slam.filter
    obs, m = _track_lengths(filt)
    long_ = m >= 9
    assert 0.2 < long_.mean() < 0.8
    rng = np.random.default_rng(5)
    uv = obs.uv + np.where(long_[:, None], rng.normal(0.0, np.sqrt(0.6**2 - 0.3**2), obs.uv.shape), 0.0)
    filt.store.features = [FeatureObservations.make(obs.pose, obs.feature, uv, obs.sigma_px)]
    smooth(filt, max_passes=5)
    noise = track_length_noise(filt)
    for g in noise.groups:
        if g.scale is None:
            continue
        want = 0.6 if g.shortest >= 9 else 0.3
        assert g.longest < 9 or g.shortest >= 9  # groups double in length: 9-16 is one
        assert 0.75 * want < g.scale < 1.25 * want, (g, want)
    assert 0.3 < noise.overall < 0.6
    assert all(g.zm >= MIN_GROUP_ZM for g in noise.groups)
    gate = noise.gate(9.21)
    per_zm = gate.of(obs.feature)
    assert np.all(per_zm <= 9.21)
    assert 0.75**2 * 0.36 * 9.21 < np.median(per_zm[long_]) < 1.25**2 * 0.36 * 9.21
    assert 0.75**2 * 0.09 * 9.21 < np.median(per_zm[~long_]) < 1.25**2 * 0.09 * 9.21


def test_feature_gate_lookup():
    gate = FeatureGate(np.array([2, 5, 9]), np.array([1.0, 2.0, 3.0]), default=7.0)
    assert gate.of(np.array([9, 1, 5, 2, 10, 5])).tolist() == [3.0, 7.0, 2.0, 1.0, 7.0, 2.0]
    assert gate.of(np.zeros(0, np.int64)).shape == (0,)
    assert FeatureGate(np.zeros(0, np.int64), np.zeros(0), 4.0).of(np.array([3])).tolist() == [4.0]


@pytest.mark.parametrize("given, want", [(True, "track_length"), (False, "off"), ("global", "global"),
                                         ("track_length", "track_length"), ("off", "off")])
def test_the_option_reads_old_bools_and_its_names(given, want):
    from eifslam.system.config import SlamConfig

    cfg = SlamConfig.from_dict({"experimental": {"noise_estimate": given}})
    assert str(cfg.experimental.noise_estimate) == want
    assert SlamConfig.from_dict(cfg.to_dict()).experimental.noise_estimate == cfg.experimental.noise_estimate


def test_a_bad_value_is_refused():
    from eifslam.errors import ConfigError
    from eifslam.system.config import SlamConfig

    with pytest.raises(ConfigError, match="experimental.noise_estimate must be one of off, global, track_length"):
        SlamConfig.from_dict({"experimental": {"noise_estimate": "per_octave"}})


def test_small_groups_join_their_neighbours():
    """Track lengths 2 (10 Zm), 3-4 (630), 5-8 (640), 17-32 (20 Zm, one feature): the
    one long feature joins 5-8 and the 2-view tracks join 3-4, so every group has at
    least ``MIN_GROUP_ZM`` ``Zm``, and the long group's noise shows in its scale."""
    from types import SimpleNamespace

    lengths = [2] * 5 + [3] * 10 + [4] * 150 + [8] * 80 + [20]
    feature = np.repeat(np.arange(len(lengths)), lengths)
    pose = np.concatenate([np.arange(m) for m in lengths])
    obs = FeatureObservations.make(pose, feature, np.zeros((len(feature), 2)), 1.0)
    rng = np.random.default_rng(0)
    scale_of = np.where(np.array(lengths) >= 8, 0.5, 0.25)[feature]
    chi2 = rng.chisquare(2, len(feature)) * scale_of**2

    filt = SimpleNamespace(store=SimpleNamespace(all_features=lambda: obs),
                           linearise_features=lambda o, gate=False: (None,) * 5 + (chi2,))
    noise = track_length_noise(filt)
    assert [(g.shortest, g.longest, g.zm) for g in noise.groups] == [(2, 4, 640), (8, 20, 660)]
    assert 1.6 < noise.groups[1].scale / noise.groups[0].scale < 2.5
    gate = noise.gate(9.21).of(np.array([0, 5, 100, 200, 245]))  # tracks of 2, 3, 4, 8 and 20 views
    assert gate[0] == gate[1] == gate[2] < gate[3] == gate[4] <= 9.21


def test_a_zm_dropped_at_a_worse_estimate_comes_back_when_it_fits():
    """Rejection re-selects the ``Zm`` among every candidate at the current estimate:
    the ``Zm`` of a pose dropped while its estimate was 0.5 m off come back once it is
    back, the ones that still fail stay out, and the count is of changed memberships."""
    from eifslam.estimation.smoothing import reject_outliers

    slam = _run(1.0, 1.0)
    filt = slam.filter
    obs0 = filt.store.all_features()
    x_good = filt.x.copy()
    k = int(np.bincount(obs0.pose).argmax())
    at = filt.layout.pose_offset(k)
    filt.x[at:at + 3] += 0.5
    n_drop, _ = reject_outliers(filt, 9.21, None)
    assert n_drop >= 0.9 * np.sum(obs0.pose == k)
    filt.x[:] = x_good
    assert reject_outliers(filt, 9.21, None)[0] < 0.05 * len(obs0)  # without candidates: nothing returns
    kept_before = filt.store.all_features()
    n_back, _ = reject_outliers(filt, 9.21, None, candidates=obs0)
    now = filt.store.all_features()
    chi2 = filt.linearise_features(obs0, gate=False)[5]
    assert len(now) == int(np.sum(chi2 <= 9.21))  # exactly the inliers of this estimate
    assert np.sum(now.pose == k) >= 0.9 * np.sum(obs0.pose == k)
    assert n_back == len(now) - len(kept_before)  # only returns here: no inlier left
