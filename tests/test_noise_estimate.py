"""The pixel noise estimated from the residuals (robust smoothing's gate, issue 14).

Known answer: the synthetic front end draws ``Zm`` with a chosen pixel noise while the
system is told another; :func:`residual_noise_scale` must find the ratio, and robust
smoothing must then gate at the noise found.
"""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.estimation.smoothing import residual_noise_scale, smooth
from eifslam.sim.frontend import SyntheticFrontEnd
from eifslam.sim.synthetic import corridor_scene
from eifslam.system.slam import Slam


def _run(true_px: float, stated_px: float, seed: int = 3, frames: int = 12):
    rng = np.random.default_rng(seed)
    sc = corridor_scene(frames, rng)
    fe = SyntheticFrontEnd(sc, seed, sigma_px=true_px, map_fraction=1.0)
    cfg = fe.slam_config(system={"sigma_px": stated_px, "min_feature_parallax_deg": 3.0})
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
    rep = smooth(slam.filter, max_passes=5, feature_chi2=9.21, estimate_noise=True)
    assert 0.8 * 0.3 < rep.noise_scale < 2.0 * 0.3
    # no Zm left above the scaled gate at the returned estimate
    obs = slam.filter.store.all_features()
    chi2 = slam.filter.linearise_features(obs, gate=False)[-1]
    assert np.all(chi2 <= 9.21 * rep.noise_scale**2 * (1 + 1e-6)) or rep.kept != "smoothed"


def test_the_gate_is_never_loosened():
    """Noise larger than stated leaves the gate as given (``noise_scale`` capped at 1)."""
    slam = _run(2.0, 1.0)
    rep = smooth(slam.filter, max_passes=3, feature_chi2=9.21, estimate_noise=True)
    assert rep.noise_scale == 1.0


def test_passes_stop_when_damped_steps_only_crawl(monkeypatch):
    """A pass whose undamped step raises the cost and whose damped step lowers it by less
    than 1% ends the passes (another would crawl the same way); a damped step that lowers
    it by more goes on; an undamped one below 1% is convergence."""
    from types import SimpleNamespace

    from eifslam.estimation import smoothing as sm

    def run(costs_by_lam: dict[float, list[float]], max_passes: int = 5) -> sm.SmoothingReport:
        seq = {lam: list(v) for lam, v in costs_by_lam.items()}
        filt = SimpleNamespace(x=np.zeros(3), dim=3, priors=SimpleNamespace(scale=None), current_lam=0.0,
                               at=100.0, relinearised=False)

        def cost(f, *a, **k):  # the model cost: at the linearisation point, or after a step
            if f.relinearised:
                f.relinearised = False
                return f.at
            f.at = seq[f.current_lam].pop(0)
            return f.at

        def relin(f):
            f.relinearised = True
            return None

        def solve(f, x0, lam):
            f.current_lam = lam
            return x0 + 1.0

        monkeypatch.setattr(sm, "model_cost", cost)
        monkeypatch.setattr(sm, "measurement_cost", lambda f, *a, **k: 0.0)
        monkeypatch.setattr(sm, "relinearise", relin)
        monkeypatch.setattr(sm, "_damped_solve", solve)
        rep = sm.SmoothingReport()
        sm._passes(filt, max_passes, 1e-12, rep)
        return rep

    crawl = run({0.0: [101.0] * 5, 1e-3: [100.5] * 5, 1e-2: [99.6, 99.3, 99.0, 98.7, 98.4]})
    assert crawl.passes == 1 and not crawl.converged and crawl.reason.startswith("stopped: the last pass, damped")
    useful = run({0.0: [101.0, 84.95], 1e-3: [100.5, 85.0], 1e-2: [90.0]})
    assert useful.passes == 3 and useful.converged and "undamped" in useful.reason
