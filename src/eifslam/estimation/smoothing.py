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
from .calibration import FocalCheck, focal_check
from .filter import InformationFilter
from .gauss_newton import begin_pass, state_scale
from .measurements import FeatureObservations, RelativePose
from .noise import FeatureGate, residual_noise_scale, track_length_noise  # noqa: F401  (re-exported)
from .options import NoiseEstimate
from .scale import recover_scale, rescale  # noqa: F401  (re-exported)

#: a ``Zm`` gate: one normalised-innovation-squared bound, or one per feature
Gate = float | FeatureGate

#: the smallest Levenberg-Marquardt damping (fraction of ``diag(I)``) a pass uses; below it
#: the pass is plain Gauss-Newton
LAM_MIN = 1e-6


def _gate_of(gate: Gate, obs: FeatureObservations) -> float | np.ndarray:
    """The gate of each of ``obs`` (a float, or ``(N,)`` for a per-feature gate)."""
    return gate.of(obs.feature) if isinstance(gate, FeatureGate) else gate


@dataclass
class SmoothingReport:
    """What :func:`smooth` did.

    Attributes
    ----------
    passes : int
        Gauss-Newton passes run (all rounds).
    step_norms : list of float
        Largest change of a state entry in each pass (state units; 0 for an undone pass).
    dampings : list of float
        Levenberg-Marquardt ``lam`` of each pass's step (0: undamped Gauss-Newton; 1e4
        for a pass undone because even that raised the cost).
    costs : list of float
        Measurement cost (:func:`measurement_cost`, the current measurement set) at the
        start of each round and after each accepted pass.
    common_costs : list of float
        Cost on the common set: every measurement smoothing started with, each
        normalised innovation squared capped at its gate (:func:`measurement_cost` with
        ``feature_chi2``/``relative_chi2``; uncapped without gates). First at the filter's
        estimate, then after each round. What is returned is the estimate with the
        lowest value.
    kept : str
        ``"smoothed"``, ``"filter"`` (smoothing could not lower the common cost: the
        filter's estimate and information are returned unchanged) or ``"smoothed
        (rejection round N)"`` (the next round raised it and was undone).
    reason : str
        Why smoothing stopped, one line.
    noise_scale : float
        ``s`` of robust smoothing's noise estimate over every ``Zm``
        (:func:`~eifslam.estimation.noise.residual_noise_scale`): the ``Zm`` gate was
        ``feature_chi2 * s**2`` (1: the given gate), or per group of track lengths below.
    rejected_features : int
        ``Zm`` smoothing started with that the returned estimate was not smoothed on
        (refused by the gate at the returned round's estimate, or behind a camera).
    rejected_relative : int
        ``ZR``/``ZT`` pairs dropped over the rounds.
    noise_groups : list of NoiseGroup
        With the estimate by track length: each group's ``s`` (its features' gate is
        ``feature_chi2 * min(1, s)**2``).
    focal : FocalCheck or None
        The focal length the returned estimate's ``Zm`` support, tested against the
        camera's (:func:`~eifslam.estimation.calibration.focal_check`, at ``noise_scale``).
    """

    passes: int = 0
    step_norms: list[float] = field(default_factory=list)
    dampings: list[float] = field(default_factory=list)
    costs: list[float] = field(default_factory=list)
    converged: bool = False
    stopped_by_cost: bool = False
    rejected_features: int = 0
    rejected_relative: int = 0
    noise_scale: float = 1.0
    noise_groups: list = field(default_factory=list)
    common_costs: list[float] = field(default_factory=list)
    kept: str = "smoothed"
    reason: str = ""
    focal: FocalCheck | None = None


def relinearise(filt: InformationFilter) -> np.ndarray:
    """Rebuild ``I`` and ``i`` from zero with every stored measurement at the current ``x``
    (:meth:`InformationFilter.relinearise`); returns which stored ``Zm`` were fused."""
    return filt.relinearise()


def _relative_chi2(filt: InformationFilter, rel: list[RelativePose]) -> np.ndarray:
    """Normalised innovation squared ``(N,)`` of each ``ZR``/``ZT`` pair (5 DOF) at ``x``."""
    _, _, W, innov = filt.linearise_relative(rel)
    return np.einsum("ni,nij,nj->n", innov, W, innov)


def model_cost(filt: InformationFilter, fused: np.ndarray) -> float:
    """The cost a relinearised information minimises, at ``x``: the squared normalised
    residuals of the ``Zm`` it fused (``fused``, from :func:`relinearise`; one that has
    moved behind its camera counts ``1e6``), of every ``ZR``/``ZT``, and of the priors and
    ``|q|^2 = 1`` pseudo-measurements (:meth:`InformationFilter.prior_terms`).

    Unlike :func:`measurement_cost` it leaves out the ``Zm`` the information does not hold
    (of features their views no longer constrain) and counts the priors, so that its
    change over a step is what the linear model predicts to first order: the test a
    Levenberg-Marquardt step must pass. (On strecha-fountain-p11 44 such ``Zm`` made every
    small step of a round look like a rise; on kitti-07 the first undamped pass lowered
    the measurement cost while it raised the priors' from 2 790 to 98 786.)
    """
    return _Costs.at(filt).model(fused)


@dataclass
class _Costs:
    """The parts of :func:`model_cost` and :func:`measurement_cost` at one ``x``, from one
    linearisation of every stored ``Zm``: each ``Zm``'s normalised innovation squared
    (``1e6`` where it cannot be linearised), the ``ZR``/``ZT`` and the priors' sums."""

    zm: np.ndarray
    relative: float
    priors: float

    @staticmethod
    def at(filt: InformationFilter) -> "_Costs":
        obs = filt.store.all_features()
        zm = np.zeros(0)
        if len(obs):
            chi2 = filt.linearise_features(obs, gate=False)[5]
            zm = np.where(np.isfinite(chi2), chi2, 1e6)
        rel = float(np.sum(_relative_chi2(filt, filt.store.relative))) if filt.store.relative else 0.0
        pri = sum(float(np.einsum("ni,nij,nj->", lin.innov, lin.W, lin.innov)) for lin in filt.prior_terms())
        return _Costs(zm, rel, pri)

    def model(self, fused: np.ndarray) -> float:
        """:func:`model_cost` with ``fused (N,)`` bool, the stored ``Zm`` the information holds."""
        return float(np.sum(self.zm[fused])) + self.relative + self.priors

    def measurement(self) -> float:
        """:func:`measurement_cost` without gates, of every stored measurement."""
        return float(np.sum(self.zm)) + self.relative


def measurement_cost(filt: InformationFilter, feature_chi2: Gate | None = None,
                     relative_chi2: float | None = None, features: FeatureObservations | None = None,
                     relative: list[RelativePose] | None = None) -> float:
    """Sum of squared normalised residuals of ``Zm`` and ``ZR``/``ZT`` at ``x``.

    Parameters
    ----------
    filt : InformationFilter
    feature_chi2, relative_chi2 : float or None (``feature_chi2`` also a FeatureGate)
        Cap each ``Zm``'s (``ZR``/``ZT`` pair's) normalised innovation squared at this
        value (a FeatureGate: each ``Zm`` at its feature's gate): the truncated
        least-squares cost that dropping the measurements above a gate minimises, so
        estimates that keep different subsets of one set compare on that whole set. ``None``: no cap, and a ``Zm`` behind the camera counts as
        ``1e6`` (it cannot be linearised; with a cap it counts as the cap).
    features, relative : optional
        The measurements to score (default: every stored one).
    """
    total = 0.0
    obs = filt.store.all_features() if features is None else features
    rel = filt.store.relative if relative is None else relative
    if len(obs):
        _, _, _, _, _, chi2 = filt.linearise_features(obs, gate=False)
        chi2 = np.where(np.isfinite(chi2), chi2, 1e6)
        total += float(np.sum(chi2 if feature_chi2 is None else np.minimum(chi2, _gate_of(feature_chi2, obs))))
    if rel:
        chi2 = _relative_chi2(filt, rel)
        total += float(np.sum(chi2 if relative_chi2 is None else np.minimum(chi2, relative_chi2)))
    return total


def reject_outliers(filt: InformationFilter, feature_chi2: Gate | None, relative_chi2: float | None,
                    min_pose_features: int = 12,
                    candidates: FeatureObservations | None = None) -> tuple[int, int]:
    """Drop stored measurements that the current estimate contradicts (a robust step the
    paper does not take: its front end had no outliers left).

    Worst first, because one wrong ``ZR``/``ZT`` also raises the residuals of its
    neighbours: while some ``ZR``/``ZT`` pair's 5-DOF normalised innovation squared
    exceeds ``relative_chi2``, the pairs above both that gate and half the largest value
    go (only those whose two poses keep at least ``min_pose_features`` ``Zm``, so that no
    pose loses what places it), and no ``Zm``. Otherwise every ``Zm`` whose normalised
    innovation squared exceeds ``feature_chi2`` (a FeatureGate: its feature's gate), or
    whose feature is behind the camera, goes, except that each pose keeps its
    ``min(n, min_pose_features)`` best-fitting ``Zm`` in front of it (``n`` its own): a
    pose whose ``Zm`` all went would be placed along its ``ZT`` by nothing (7scenes seed
    7: two frames of the first second slid 1.35 and 2.04 m in the smoothing passes).

    With ``candidates`` (every ``Zm`` smoothing started with), the ``Zm`` kept are chosen
    again among all of them at the current estimate: one dropped in an earlier round, at
    a worse estimate, comes back when it fits this one. The set is then the inliers of
    the current estimate, as a robust estimator re-selects them at each iterate.

    Returns
    -------
    (features dropped, or with ``candidates`` whose membership changed; relative poses dropped)
    """
    obs = filt.store.all_features()
    if relative_chi2 is not None and filt.store.relative:
        rel = filt.store.relative
        chi2 = _relative_chi2(filt, rel)
        ids, counts = np.unique(obs.pose, return_counts=True)
        zm = dict(zip(ids.tolist(), counts.tolist()))
        placed = np.array([zm.get(r.i, 0) >= min_pose_features and zm.get(r.j, 0) >= min_pose_features for r in rel])
        bad = placed & (chi2 > relative_chi2)
        if bad.any():
            drop = bad & (chi2 >= 0.5 * chi2[bad].max())
            filt.store.relative = [r for r, d in zip(rel, drop) if not d]
            return 0, int(drop.sum())
    if candidates is not None and feature_chi2 is not None and len(candidates):
        keep = _fitting(filt, candidates, feature_chi2, min_pose_features)
        n_f = int(np.sum(keep != _stored(candidates, obs)))
        if n_f:
            filt.store.features = [candidates.subset(keep)]
        return n_f, 0
    if feature_chi2 is not None and len(obs):
        keep = _fitting(filt, obs, feature_chi2, min_pose_features)
        n_f = int(len(obs) - keep.sum())
        if n_f:
            filt.store.features = [obs.subset(keep)]
        return n_f, 0
    return 0, 0


def _fitting(filt: InformationFilter, obs: FeatureObservations, feature_chi2: Gate, n_min: int) -> np.ndarray:
    """Which ``Zm`` of ``obs (N,)`` pass their gate at the current estimate (one behind its
    camera, chi-square inf, never does), plus each pose's best up to
    ``min(n_pose, n_min)`` (:func:`_keep_poses_placed`)."""
    _, _, _, _, _, chi2 = filt.linearise_features(obs, gate=False)
    keep = np.isfinite(chi2) & (chi2 <= _gate_of(feature_chi2, obs))
    return _keep_poses_placed(obs.pose, chi2, keep, n_min)


def _keep_poses_placed(pose: np.ndarray, chi2: np.ndarray, keep: np.ndarray, n_min: int) -> np.ndarray:
    """``keep (N,)`` with, for every pose keeping fewer than ``min(n_pose, n_min)`` of its
    ``Zm``, its lowest finite ``chi2`` ones added back up to that number (``pose``,
    ``chi2``: ``(N,)`` of each ``Zm``)."""
    keep = keep.copy()
    ids, inv, total = np.unique(np.asarray(pose), return_inverse=True, return_counts=True)
    need = np.minimum(total, n_min) - np.bincount(inv, weights=keep, minlength=len(ids)).astype(int)
    if not np.any(need > 0):
        return keep
    spare = np.flatnonzero(~keep & np.isfinite(chi2) & (need[inv] > 0))
    spare = spare[np.lexsort((chi2[spare], inv[spare]))]  # by pose, best first
    first = np.searchsorted(inv[spare], inv[spare])  # where each pose's run starts
    rank = np.arange(len(spare)) - first
    keep[spare[rank < need[inv[spare]]]] = True
    return keep


def _stored(candidates: FeatureObservations, obs: FeatureObservations) -> np.ndarray:
    """Which of ``candidates (N,)`` are among ``obs`` (a ``Zm`` is its pose and feature:
    a feature is measured once per pose)."""
    span = int(max(candidates.feature.max(initial=0), obs.feature.max(initial=0))) + 1

    def key(o: FeatureObservations) -> np.ndarray:
        return o.pose.astype(np.int64) * span + o.feature

    return np.isin(key(candidates), key(obs))


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
           feature_chi2: float | None = None, relative_chi2: float | None = None, max_rounds: int = 4,
           estimate_noise: NoiseEstimate | str | bool = NoiseEstimate.OFF) -> SmoothingReport:
    """Relinearise and recover until the update is small (paper III-E); never worse than
    the filter's estimate by the cost.

    Each pass relinearises every stored measurement at the current estimate, from zero
    information, and recovers: one Gauss-Newton step, as in the paper. A safeguard the
    paper does not need (its filter answer was close to the optimum): if a pass raises the
    measurement cost (:func:`measurement_cost`), the step is damped Levenberg-Marquardt
    style (``I + lam diag(I)``, ``lam`` grown tenfold up to 1e4) and, if still no better,
    smoothing stops at the previous estimate (``report.reason`` says so). After a damped
    pass the next one starts from a tenth of its ``lam`` (Marquardt's schedule), down to
    :data:`LAM_MIN`, below which the passes are undamped again.

    Robust smoothing (``feature_chi2`` or ``relative_chi2`` given): after the passes,
    :func:`reject_outliers` drops the measurements the smoothed estimate contradicts,
    worst first, and the passes run again; at most ``max_rounds`` such rounds. The ``Zm``
    of each round are chosen among every ``Zm`` smoothing started with, so one dropped at
    an earlier, worse estimate comes back when the new one agrees with it; the rounds end
    when the set no longer changes.

    Rounds drop measurements, so their costs are not comparable with each other or with
    the filter's. Every estimate (the filter's, and each round's) is therefore also scored
    on one common set, the measurements smoothing started with, each capped at its gate
    (``report.common_costs``: the truncated least-squares cost the rejection minimises;
    without gates, the plain cost of every measurement). The estimate with the lowest
    common cost is returned, with the measurement set it was smoothed on and its
    information relinearised there; if none is below the filter's, the filter's estimate
    and information are returned unchanged (``report.kept``, ``report.reason``). A round
    that raises the common cost does not end the rounds: the next rejection may remove
    what pulled it away (e.g. one wrong ``ZR``/``ZT`` averaged in before it is dropped).

    Parameters
    ----------
    filt : InformationFilter
        Filter whose measurements are stored (changed in place), at its complete estimate.
    max_passes : int
        At most this many passes per round (default 5).
    tol : float
        Stop when the largest change of any state entry, relative to the scale of the
        map (``max(1, scale prior length)``), is below ``tol``, or when a pass lowers the
        cost by less than 1% (undamped: converged; damped: the undamped step left the
        region where the model is linear and the damped ones only crawl).
    feature_chi2, relative_chi2 : float or None
        Gates of :func:`reject_outliers` (``None``: keep every measurement of that kind).
    max_rounds : int
        Robust smoothing: at most this many rejection rounds.
    estimate_noise : NoiseEstimate or {"off", "global", "track_length"} or bool
        Robust smoothing: scale the ``Zm`` gate to the noise the measurements show,
        ``feature_chi2 * min(1, s**2)`` with ``s`` estimated at the filter's estimate
        (:mod:`eifslam.estimation.noise`; never looser than the gate given;
        ``report.noise_scale``, ``report.noise_groups``): one ``s`` for every ``Zm``
        (``"global"``) or one per group of track lengths (``"track_length"``, ``True``).
        The stated pixel noise is a prior guess; a gate set on it passes, on precise
        images, matches many standard deviations off.
    """
    if max_passes < 1:
        raise EstimatorError("smoothing needs at least one pass")
    rep = SmoothingReport()
    robust = feature_chi2 is not None or relative_chi2 is not None
    estimate_noise = NoiseEstimate.parse(estimate_noise, "estimate_noise")
    if estimate_noise == NoiseEstimate.GLOBAL and feature_chi2 is not None:
        rep.noise_scale = min(1.0, residual_noise_scale(filt))
        feature_chi2 = feature_chi2 * rep.noise_scale**2
    elif estimate_noise == NoiseEstimate.TRACK_LENGTH and feature_chi2 is not None:
        noise = track_length_noise(filt)
        rep.noise_scale, rep.noise_groups = min(1.0, noise.overall), noise.groups
        feature_chi2 = noise.gate(feature_chi2)
    obs0, rel0 = filt.store.all_features(), list(filt.store.relative)
    feats0 = list(filt.store.features)
    x0, I0, i0 = filt.x.copy(), filt.info.matrix().copy(), filt.info.vector.copy()

    def common() -> float:
        return measurement_cost(filt, feature_chi2, relative_chi2, obs0, rel0)

    rep.common_costs.append(common())
    best = (rep.common_costs[0], "filter", None)  # (cost, label, (x, features, relative) or None)
    if robust:  # Zm that cannot be linearised (behind a camera) only distort the cost
        reject_outliers(filt, np.inf, None)
    rises: list[str] = []
    for rnd in range(max_rounds + 1):
        if rnd > 0:  # the Zm inliers of this estimate among all (a dropped one may come back)
            n_f, n_r = reject_outliers(filt, feature_chi2, relative_chi2, candidates=obs0)
            rep.rejected_relative += n_r
            if n_f == 0 and n_r == 0:
                rep.reason += "; no measurement left above the gates (the inliers no longer change)"
                break
        _passes(filt, max_passes, tol, rep)
        c = common()
        rep.common_costs.append(c)
        current = "smoothed" if rnd == 0 else f"smoothed (rejection round {rnd})"
        if c <= best[0]:
            best = (c, current, (filt.x.copy(), list(filt.store.features), list(filt.store.relative)))
        else:  # kept going: the next rejection may remove what pulled this estimate away
            rises.append(f"{current} raised the common cost from {best[0]:.6g} to {c:.6g}")
        if not robust:
            break
    else:
        rep.reason += f"; stopped after {max_rounds} rejection rounds"
    undone = best[1] != current
    if undone:
        rep.reason += (f"; {', '.join(rises)} (a linearisation that pulls the estimate towards measurements "
                       f"the gates then drop, or away from ones capped at the gates); kept the "
                       f"{best[1]} estimate")
    rep.kept = best[1]
    if best[2] is None:  # the filter's own answer, as it was
        filt.store.features, filt.store.relative = feats0, rel0
        filt.info.set(I0, i0)
        filt.set_estimate(x0)
    elif undone:  # a later round was undone: back to the best one, information at its estimate
        x, filt.store.features, filt.store.relative = best[2]
        filt.set_estimate(x)
        filt.relinearise()
    rep.rejected_features = len(obs0) - len(filt.store.all_features())
    filt.invalidate()  # covariances: refactorise the undamped information on demand
    rep.focal = focal_check(filt, rep.noise_scale)
    return rep


def _passes(filt: InformationFilter, max_passes: int, tol: float, rep: SmoothingReport,
            cost_tol: float = 1e-2) -> None:
    """Gauss-Newton passes with the Levenberg-Marquardt safeguard (see :func:`smooth`).

    A pass is kept only when it lowers :func:`model_cost`, the cost of the terms its
    relinearised information holds (the measurement cost alone can fall while the priors'
    part rises, and counts ``Zm`` the information leaves out). Both costs at one estimate
    come from one linearisation (:class:`_Costs`), which the next pass reuses as its
    starting cost: ``x`` does not change between them."""
    ref = state_scale(filt)
    here = _Costs.at(filt)
    rep.costs.append(here.measurement())
    rep.converged = rep.stopped_by_cost = False
    lam = 0.0
    for _ in range(max_passes):
        p = begin_pass(filt)
        before, fused = p.before, p.fused
        cost = here.model(fused)
        while True:
            try:
                filt.x[:] = _damped_solve(filt, before, lam)
                there = _Costs.at(filt) if np.all(np.isfinite(filt.x)) else None
            except EstimatorError:  # e.g. a feature left without information: damp harder
                filt.x[:] = before
                there = None
            new_cost = there.model(fused) if there is not None else np.inf
            if new_cost <= cost or lam >= 1e4:
                break
            lam = 1e-3 if lam == 0.0 else 10.0 * lam
        rep.passes += 1
        rep.dampings.append(lam)
        if new_cost > cost:
            filt.x[:] = before
            rep.step_norms.append(0.0)
            rep.stopped_by_cost = True
            rep.reason = (f"pass {rep.passes} raised the cost from {cost:.6g} to {new_cost:.6g} even damped "
                          f"(lam up to 1e4): the linearised step leaves the region where the model is "
                          f"linear; kept the estimate before it")
            break
        here = there
        # Marquardt's schedule: the next pass tries a tenth of the damping that worked;
        # below LAM_MIN it is dropped (Gauss-Newton). Dropping it at once after a damped
        # pass made the next undamped step fail again on kitti-07 (two factorisations a pass)
        lam = lam / 10.0 if lam >= 10.0 * LAM_MIN else 0.0
        rep.costs.append(here.measurement())
        norm = p.change(filt)
        rep.step_norms.append(norm)
        small = cost - new_cost <= cost_tol * cost
        if norm <= tol * ref or (lam == 0.0 and small):
            rep.converged = True
            rep.reason = (f"converged: the last pass changed no state entry by more than {tol:g} of the scale"
                          if norm <= tol * ref else
                          f"converged: the last undamped pass lowered the cost by less than {cost_tol:.0%}")
            break
        if small:  # damped: crawling where the undamped step leaves the linear region
            rep.reason = (f"stopped: the last pass, damped (lam {lam * 10:g}), lowered the cost by less "
                          f"than {cost_tol:.0%}")
            break
    else:
        rep.reason = f"stopped after {max_passes} passes"


__all__ = ["SmoothingReport", "measurement_cost", "model_cost", "recover_scale", "reject_outliers", "relinearise",
           "rescale", "smooth"]
