"""Online relinearisation of stored measurements (the EIF analogue of iSAM2's fluid
relinearisation; pure NumPy).

The information form is a sum over measurements: a measurement linearised at ``x0``
contributed ``J0^T W J0`` to ``I`` and ``J0^T W (r0 + J0 x0[idx])`` to ``i`` (paper eq. 8,
``r0`` its innovation at ``x0``). When its states have moved since, that contribution
can be taken out and put back at the current estimate, touching only its own rows, and
the incremental window absorbs the difference like any fusion (the states involved are
active, so nothing is re-activated and the window stays exact).

Which measurements: those whose *linearisation error* at the current estimate ``x``,

    e = h(x) - (h(x0) + J0 (x - x0)) = r0 - J0 (x - x0) - r(x),

exceeds ``threshold`` standard deviations (``sqrt(e^T W e)``, the whitened distance
between the measurement's prediction and its linearised prediction): a threshold on
what the linearisation costs the measurement's residual, in its own units, rather than
a fixed distance in metres. At most ``budget`` per frame, largest error first.

Only measurements whose states are all in the incremental recovery's active window are
candidates (``live``); once one of their states is marginalised their linearisation is
final (the elimination used it). So the work per frame is bounded by the window, not
the map. ``Zm`` and ``ZR``/``ZT`` are relinearised; priors and the quaternion-norm
pseudo-measurements are not. Measurements fused before ``I`` was replaced wholesale
(smoothing, rescaling, a loaded session) are no longer tracked.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigError
from .measurements import FeatureObservations, RelativePose

if TYPE_CHECKING:  # the filter owns this object; no import at run time
    from .filter import InformationFilter

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass
class RelinearisationStats:
    """Counters of :class:`OnlineRelinearisation`.

    Attributes
    ----------
    steps : frames processed.
    evaluated : measurements whose linearisation error was evaluated, summed over frames.
    relinearised : measurements relinearised, summed over frames.
    over_budget : measurements above the threshold left for a later frame (budget).
    """

    steps: int = 0
    evaluated: int = 0
    relinearised: int = 0
    over_budget: int = 0


@dataclass
class LiveBatch:
    """Stored measurements of one kind whose states are all active, with the
    linearisation each contributed to ``I``.

    Attributes
    ----------
    meas : the measurements (``FeatureObservations`` of ``N``, or a list of ``N``
        ``RelativePose``).
    idx : (N, k) state indices; J : (N, m, k) Jacobians; W : (N, m, m) information;
    innov : (N, m) innovation at the linearisation point; x0 : (N, k) that point.
    """

    meas: Any
    idx: IntArray
    J: Array
    W: Array
    innov: Array
    x0: Array

    def __len__(self) -> int:
        return int(len(self.idx))

    def subset(self, keep: NDArray[np.bool_]) -> "LiveBatch":
        meas = self.meas.subset(keep) if isinstance(self.meas, FeatureObservations) \
            else [r for r, k in zip(self.meas, keep) if k]
        return LiveBatch(meas, self.idx[keep], self.J[keep], self.W[keep], self.innov[keep], self.x0[keep])

    @staticmethod
    def join(a: "LiveBatch | None", b: "LiveBatch") -> "LiveBatch":
        if a is None or len(a) == 0:
            return b
        meas = FeatureObservations.concatenate([a.meas, b.meas]) if isinstance(b.meas, FeatureObservations) \
            else a.meas + b.meas
        return LiveBatch(meas, *(np.concatenate([getattr(a, k), getattr(b, k)])
                                 for k in ("idx", "J", "W", "innov", "x0")))


def contribution(idx: IntArray, J: Array, W: Array, innov: Array, x0: Array) -> tuple[Array, Array]:
    """``(J^T W J (N, k, k), J^T W (innov + J x0) (N, k))``: eq. 8's terms of ``N``
    measurements linearised at their own points ``x0 (N, k)``."""
    JtW = np.swapaxes(J, 1, 2) @ W
    return JtW @ J, np.einsum("nkm,nm->nk", JtW, innov + np.einsum("nmk,nk->nm", J, x0))


@dataclass
class OnlineRelinearisation:
    """Relinearises, each frame, the live measurements whose linearisation error exceeds
    ``threshold`` standard deviations (see the module).

    Parameters
    ----------
    threshold : float
        Whitened linearisation error (standard deviations of the measurement) above
        which a measurement is relinearised (> 0).
    budget : int
        At most this many measurements relinearised per frame (>= 1).
    """

    threshold: float
    budget: int
    stats: RelinearisationStats = field(default_factory=RelinearisationStats)
    features: LiveBatch | None = None
    relative: LiveBatch | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.threshold) and self.threshold > 0):
            raise ConfigError(f"relinearisation threshold must be positive, got {self.threshold!r}")
        if not (isinstance(self.budget, (int, np.integer)) and self.budget >= 1):
            raise ConfigError(f"relinearisation budget must be an integer >= 1, got {self.budget!r}")

    # -- recording (the filter calls these when it fuses and stores) -----------------------
    def record_features(self, obs: FeatureObservations, idx: IntArray, J: Array, W: Array, innov: Array,
                        x: Array) -> None:
        """``Zm`` just fused at ``x (n,)``: ``idx (N, 10)``, ``J (N, 2, 10)``, ``W``, ``innov``."""
        if len(obs):
            self.features = LiveBatch.join(self.features, LiveBatch(obs, idx, J, W, innov, x[idx]))

    def record_relative(self, rps: list[RelativePose], idx: IntArray, J: Array, W: Array, innov: Array,
                        x: Array) -> None:
        """``ZR``/``ZT`` just fused at ``x (n,)``: ``idx (N, 14)``, ``J (N, 5, 14)``, ``W``, ``innov``."""
        if len(rps):
            self.relative = LiveBatch.join(self.relative, LiveBatch(list(rps), idx, J, W, innov, x[idx]))

    # -- information-store listener -----------------------------------------------------------
    def on_add(self, idx: IntArray, Lam: Array, eta: Array) -> None:
        """Fusions need no bookkeeping here (recording is explicit)."""

    def on_invalidate(self) -> None:
        """``I`` was replaced wholesale: the recorded linearisations are not in it any more."""
        self.features = self.relative = None

    # -- the step -----------------------------------------------------------------------------
    def step(self, filt: "InformationFilter") -> int:
        """Relinearise the live measurements over the threshold (at most ``budget``) at
        ``filt.x``; return how many. Call before the frame's recovery."""
        inc = filt.incremental
        self.stats.steps += 1
        if inc is None or not inc.valid:
            return 0
        x = filt.x
        parts = []
        for name, lin in (("features", filt.linearise_features), ("relative", filt.linearise_relative)):
            live = getattr(self, name)
            if live is None or len(live) == 0:
                continue
            live = live.subset(inc.active_mask(live.idx).all(axis=1))
            setattr(self, name, live)
            if len(live) == 0:
                continue
            if name == "features":
                ok, _, J, _, innov, _ = lin(live.meas, gate=False)
            else:
                _, J, _, innov = lin(live.meas)
                ok = np.ones(len(live), bool)
            e = live.innov - np.einsum("nmk,nk->nm", live.J, x[live.idx] - live.x0) - innov
            err2 = np.einsum("ni,nij,nj->n", e, live.W, e)
            ok &= np.isfinite(err2) & np.all(np.isfinite(J), axis=(1, 2)) & np.all(np.isfinite(innov), axis=1)
            parts.append((name, live, np.where(ok, err2, -1.0), J, innov))
            self.stats.evaluated += len(live)
        over = [(name, np.flatnonzero(e2 > self.threshold**2), e2) for name, _, e2, _, _ in parts]
        n_over = sum(len(o) for _, o, _ in over)
        if n_over == 0:
            return 0
        cut = -np.inf
        if n_over > self.budget:
            cut = np.sort(np.concatenate([e2[o] for _, o, e2 in over]))[-self.budget]
            self.stats.over_budget += n_over - self.budget
        done = 0
        for (name, live, e2, J, innov), (_, o, _) in zip(parts, over):
            sel = o[e2[o] >= cut][: self.budget - done]
            if not len(sel):
                continue
            idx = live.idx[sel]
            Lam0, eta0 = contribution(idx, live.J[sel], live.W[sel], live.innov[sel], live.x0[sel])
            x1 = x[idx]
            Lam1, eta1 = contribution(idx, J[sel], live.W[sel], innov[sel], x1)
            filt.add_information(idx, Lam1 - Lam0, eta1 - eta0)
            live.J[sel], live.innov[sel], live.x0[sel] = J[sel], innov[sel], x1
            done += len(sel)
        self.stats.relinearised += done
        return done


__all__ = ["LiveBatch", "OnlineRelinearisation", "RelinearisationStats", "contribution"]
