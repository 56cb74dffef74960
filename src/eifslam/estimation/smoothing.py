"""Smoothing (paper III-E), pure NumPy / SciPy.

Smoothing starts from zero information, relinearises every stored measurement (and the
gauge priors and quaternion-norm pseudo-measurements) at the latest estimate, fuses them
by eq. 8 and recovers the state; this is repeated until the update is small. It is
Gauss-Newton started at the filter's answer.

Scale recovery (:func:`rescale`, :func:`recover_scale`) lives in
:mod:`eifslam.estimation.scale` and is re-exported here.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..errors import EstimatorError
from .filter import InformationFilter
from .scale import recover_scale, rescale  # noqa: F401  (re-exported)


@dataclass
class SmoothingReport:
    """What :func:`smooth` did: the update norms (state units) and the measurement cost
    (sum of squared normalised residuals) before the first and after each pass."""

    passes: int = 0
    step_norms: list[float] = field(default_factory=list)
    costs: list[float] = field(default_factory=list)
    converged: bool = False
    stopped_by_cost: bool = False
    rejected_features: int = 0
    rejected_relative: int = 0


def relinearise(filt: InformationFilter) -> None:
    """Rebuild ``I`` and ``i`` from zero with every stored measurement at the current ``x``
    (:meth:`InformationFilter.relinearise`)."""
    filt.relinearise()


def measurement_cost(filt: InformationFilter) -> float:
    """Sum of squared normalised residuals of every stored ``Zm``, ``ZR``/``ZT`` at ``x``.

    A ``Zm`` behind the camera counts as ``1e6`` (it cannot be linearised).
    """
    total = 0.0
    obs = filt.store.all_features()
    if len(obs):
        _, _, _, _, _, chi2 = filt.linearise_features(obs, gate=False)
        total += float(np.sum(np.where(np.isfinite(chi2), chi2, 1e6)))
    if filt.store.relative:
        _, _, W, innov = filt.linearise_relative(filt.store.relative)
        total += float(np.einsum("ni,nij,nj->", innov, W, innov))
    return total


def reject_outliers(filt: InformationFilter, feature_chi2: float | None, relative_chi2: float | None,
                    min_pose_features: int = 12) -> tuple[int, int]:
    """Drop stored measurements that the current estimate contradicts (a robust step the
    paper does not take: its front end had no outliers left).

    Worst first, because one wrong ``ZR``/``ZT`` also raises the residuals of its
    neighbours: while some ``ZR``/``ZT`` pair's 5-DOF normalised innovation squared
    exceeds ``relative_chi2``, the pairs above both that gate and half the largest value
    go (only those whose two poses keep at least ``min_pose_features`` ``Zm``, so that no
    pose loses what places it), and no ``Zm``. Otherwise every ``Zm`` whose normalised
    innovation squared exceeds ``feature_chi2``, or whose feature is behind the camera, goes.

    Returns
    -------
    (features dropped, relative poses dropped)
    """
    obs = filt.store.all_features()
    if relative_chi2 is not None and filt.store.relative:
        rel = filt.store.relative
        _, _, W, innov = filt.linearise_relative(rel)
        chi2 = np.einsum("ni,nij,nj->n", innov, W, innov)
        ids, counts = np.unique(obs.pose, return_counts=True)
        zm = dict(zip(ids.tolist(), counts.tolist()))
        placed = np.array([zm.get(r.i, 0) >= min_pose_features and zm.get(r.j, 0) >= min_pose_features for r in rel])
        bad = placed & (chi2 > relative_chi2)
        if bad.any():
            drop = bad & (chi2 >= 0.5 * chi2[bad].max())
            filt.store.relative = [r for r, d in zip(rel, drop) if not d]
            return 0, int(drop.sum())
    if feature_chi2 is not None and len(obs):
        _, _, _, _, _, chi2 = filt.linearise_features(obs, gate=False)
        keep = np.isfinite(chi2) & (chi2 <= feature_chi2)  # behind a camera (inf) fails too
        n_f = int(len(obs) - keep.sum())
        if n_f:
            filt.store.features = [obs.subset(keep)]
        return n_f, 0
    return 0, 0


def _damped_solve(filt: InformationFilter, x0: np.ndarray, lam: float) -> np.ndarray:
    """``x`` of ``(I + lam diag(I)) x = i + lam diag(I) x0``: the Levenberg-Marquardt step
    from ``x0`` in information form (``lam = 0`` is the paper's Gauss-Newton recovery)."""
    if lam == 0.0:
        return filt.factor().solve(filt.info.vector)
    I = filt.info.matrix()
    d = lam * I.diagonal()
    F = filt.factorize(I + sp.diags(d))
    return F.solve(filt.info.vector + d * x0)


def smooth(filt: InformationFilter, max_passes: int = 5, tol: float = 1e-8,
           feature_chi2: float | None = None, relative_chi2: float | None = None,
           max_rounds: int = 4) -> SmoothingReport:
    """Relinearise and recover until the update is small (paper III-E).

    Each pass relinearises every stored measurement at the current estimate, from zero
    information, and recovers: one Gauss-Newton step, as in the paper. A safeguard the
    paper does not need (its filter answer was close to the optimum): if a pass raises the
    measurement cost (:func:`measurement_cost`), the step is damped Levenberg-Marquardt
    style (``I + lam diag(I)``, ``lam`` grown tenfold up to 1e4) and, if still no better,
    smoothing stops at the previous estimate.

    Robust smoothing (``feature_chi2`` or ``relative_chi2`` given): after the passes,
    :func:`reject_outliers` drops the measurements the smoothed estimate contradicts,
    worst first, and the passes run again; at most ``max_rounds`` such rounds.

    Parameters
    ----------
    filt : InformationFilter
        Filter whose measurements are stored (changed in place).
    max_passes : int
        At most this many passes per round (default 5).
    tol : float
        Stop when the largest change of any state entry, relative to the scale of the
        map (``max(1, scale prior length)``), is below ``tol``, or when an undamped pass
        lowers the cost by less than 1%.
    feature_chi2, relative_chi2 : float or None
        Gates of :func:`reject_outliers` (``None``: keep every measurement of that kind).
    max_rounds : int
        Robust smoothing: at most this many rejection rounds.
    """
    if max_passes < 1:
        raise EstimatorError("smoothing needs at least one pass")
    rep = SmoothingReport()
    robust = feature_chi2 is not None or relative_chi2 is not None
    if robust:  # Zm that cannot be linearised (behind a camera) only distort the cost
        rep.rejected_features += reject_outliers(filt, np.inf, None)[0]
    _passes(filt, max_passes, tol, rep)
    if robust:
        for _ in range(max_rounds):
            n_f, n_r = reject_outliers(filt, feature_chi2, relative_chi2)
            rep.rejected_features += n_f
            rep.rejected_relative += n_r
            if n_f == 0 and n_r == 0:
                break
            _passes(filt, max_passes, tol, rep)
    filt.invalidate()  # covariances: refactorise the undamped information on demand
    return rep


def _passes(filt: InformationFilter, max_passes: int, tol: float, rep: SmoothingReport,
            cost_tol: float = 1e-2) -> None:
    """Gauss-Newton passes with the Levenberg-Marquardt safeguard (see :func:`smooth`)."""
    ref = 1.0 if filt.priors.scale is None else max(1.0, filt.priors.scale[2])
    cost = measurement_cost(filt)
    rep.costs.append(cost)
    rep.converged = rep.stopped_by_cost = False
    lam = 0.0
    for _ in range(max_passes):
        before = filt.x.copy()
        relinearise(filt)
        while True:
            try:
                filt.x[:] = _damped_solve(filt, before, lam)
                new_cost = measurement_cost(filt) if np.all(np.isfinite(filt.x)) else np.inf
            except EstimatorError:  # e.g. a feature left without information: damp harder
                filt.x[:] = before
                new_cost = np.inf
            if new_cost <= cost or lam >= 1e4:
                break
            lam = 1e-3 if lam == 0.0 else 10.0 * lam
        rep.passes += 1
        if new_cost > cost:
            filt.x[:] = before
            rep.step_norms.append(0.0)
            rep.stopped_by_cost = True
            break
        lam = lam / 10.0 if lam > 1e-3 else 0.0
        cost = new_cost
        rep.costs.append(cost)
        norm = float(np.max(np.abs(filt.x - before))) if filt.dim else 0.0
        rep.step_norms.append(norm)
        if norm <= tol * ref or (lam == 0.0 and rep.costs[-2] - cost <= cost_tol * rep.costs[-2]):
            rep.converged = True
            break


__all__ = ["SmoothingReport", "measurement_cost", "recover_scale", "reject_outliers", "relinearise", "rescale",
           "smooth"]
