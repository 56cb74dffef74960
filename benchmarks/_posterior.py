"""How far apart two trajectory estimates are, against the posterior's own spread.

``backend_scaling.py`` compares the filter's final estimate with Gauss-Newton run to
convergence on the same measurements. On a monocular corridor without a loop both lie in
a long, nearly flat valley of the cost (the scale drift), so their ATE against the ground
truth can differ a lot while their costs agree to 1e-3. This module measures that
difference in the posterior's own units:

* :func:`ate_between`: RMSE of one trajectory's positions after a Sim(3) alignment to the
  other's (the ATE with the second estimate in the place of the ground truth);
* :func:`posterior_samples`: draws ``y ~ N(0, I^-1)`` of the state around the batch
  optimum, ``I`` the information the last Gauss-Newton pass built, by perturbing every
  term of ``I`` (``y = I^-1 sum_k J_k^T L_k z_k`` with ``W_k = L_k L_k^T`` and
  ``z_k ~ N(0, 1)``, whose covariance is ``I^-1 (sum_k J_k^T W_k J_k) I^-1 = I^-1``):
  one sparse solve a sample, no dense square root.

The ATE between the batch optimum and its samples is how far a trajectory the data cannot
tell from the optimum lies from it; the ATE between the online estimate and the batch
optimum is then read against that distribution. Ground truth is not used here.
"""

from __future__ import annotations

import time

import numpy as np
from numpy.typing import NDArray

from eifslam.estimation.factors import Linearised
from eifslam.estimation.filter import InformationFilter
from eifslam.evaluation.metrics import align_sim3

Array = NDArray[np.float64]

__all__ = ["ate_between", "posterior_samples", "posterior_spread", "positions"]


def positions(filt: InformationFilter, x: Array) -> Array:
    """Pose positions ``(P, 3)`` of state vector ``x`` ``(dim,)``, in pose order."""
    cols = filt.layout.pose_columns(filt.layout.pose_ids)[:, :3]
    return x[cols]


def ate_between(p: Array, ref: Array) -> float:
    """RMSE of positions ``p (P, 3)`` after the Sim(3) that best aligns them to ``ref (P, 3)``."""
    e = align_sim3(p, ref).apply(p) - ref
    return float(np.sqrt(np.mean(np.sum(e**2, axis=1))))


def posterior_samples(filt: InformationFilter, fused: NDArray[np.bool_], n: int,
                      rng: np.random.Generator) -> list[Array]:
    """``n`` draws ``(dim,)`` of ``N(0, I^-1)``, ``I`` the filter's information as
    :meth:`InformationFilter.relinearise` last built it (``fused``: which stored ``Zm`` it
    took, as it returned); the terms are linearised again at ``x``, so ``x`` must be the
    point of that relinearisation or, after convergence, indistinguishable from it."""
    terms = list(filt.prior_terms())
    obs = filt.store.all_features()
    if len(obs):
        _, idx, J, W, innov, _ = filt.linearise_features(obs, gate=False)
        terms.append(Linearised(idx[fused], J[fused], W[fused], innov[fused]))
    if filt.store.relative:
        idx, J, W, innov = filt.linearise_relative(filt.store.relative)
        terms.append(Linearised(idx, J, W, innov))
    roots = [np.linalg.cholesky(t.W) for t in terms]
    factor = filt.factor()
    out = []
    for _ in range(int(n)):
        r = np.zeros(filt.dim)
        for t, L in zip(terms, roots):
            z = rng.standard_normal(t.innov.shape)
            v = np.einsum("nmk,nm->nk", t.J, np.einsum("nij,nj->ni", L, z))
            np.add.at(r, t.idx.ravel(), v.ravel())
        out.append(factor.solve(r))
    return out


def posterior_spread(online: InformationFilter, batch: InformationFilter, fused, n: int = 32) -> dict:
    """The online estimate's distance from the batch optimum (ATE after Sim(3), the batch
    in the place of the ground truth) against that of ``n`` draws of the batch posterior
    (:func:`posterior_samples`; ``fused`` as the batch's last relinearisation returned):
    how much of the ATE gap the data can tell apart."""
    xb = batch.x
    pb = positions(batch, xb)
    t0 = time.perf_counter()
    samples = posterior_samples(batch, fused, n, np.random.default_rng(0))
    draws = [ate_between(positions(batch, xb + y), pb) for y in samples]
    out = dict(online_to_batch_ate=ate_between(positions(online, online.x), pb), draws=n,
               posterior_to_batch_ate=draws, posterior_to_batch_ate_median=float(np.median(draws)),
               seconds=time.perf_counter() - t0)
    print(f"  online vs batch optimum (ATE, batch as reference) {out['online_to_batch_ate']:.3f} m; posterior "
          f"draws vs batch median {out['posterior_to_batch_ate_median']:.3f} m [{min(draws):.3f}, "
          f"{max(draws):.3f}] ({n} draws, {out['seconds']:.0f} s)", flush=True)
    return out
