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
a fixed distance in metres. ``e`` is second order in ``x - x0``; it is evaluated only
where the first-order change ``J0 (x - x0)`` (whitened, from the stored Jacobian, no
model evaluation) exceeds the threshold.

A measurement on its last step in the window (its feature, or one of its poses, not
measured for ``window - 1`` steps: unless measured again in this frame, the step's
marginalisation makes its linearisation final) is relinearised at the current estimate
whatever its error: the last estimate it can take is the best one it will have.

Only measurements whose states are all in the incremental recovery's active window are
candidates (``live``: a ``Zm`` while its feature was measured within the feature window,
a ``ZR``/``ZT`` while both poses were measured within the pose window); once one of their
states is marginalised their linearisation is final (the elimination used it). So the
work per frame is bounded by the window, not the map, and every candidate over the
threshold is relinearised in the frame it goes over (a budget per frame, largest error
first, left the filter's NEES on the synthetic corridor as without relinearisation:
``docs/estimator.md``, Consistency). ``Zm`` and ``ZR``/``ZT`` are
relinearised; priors and the quaternion-norm pseudo-measurements are not. Measurements
fused before ``I`` was replaced wholesale (smoothing, rescaling) are no longer tracked;
sessions keep the candidates.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigError
from . import factors
from .gauss_newton import information_terms
from .measurements import (FeatureObservations, RelativePose, pack_features, pack_relative, unpack_features,
                           unpack_relative)
from .statedict import check_index, sub, take, take_int

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
    evaluated : measurements whose linearisation error was evaluated (their first-order
        change exceeded the threshold, or they were on their last step in the window),
        summed over frames.
    relinearised : measurements relinearised, summed over frames.
    """

    steps: int = 0
    evaluated: int = 0
    relinearised: int = 0


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
    return information_terms(J, W, innov + np.einsum("nmk,nk->nm", J, x0))


@dataclass
class OnlineRelinearisation:
    """Relinearises, each frame, the live measurements whose linearisation error exceeds
    ``threshold`` standard deviations (see the module).

    Parameters
    ----------
    threshold : float
        Whitened linearisation error (standard deviations of the measurement) above
        which a measurement is relinearised (> 0).
    """

    threshold: float
    stats: RelinearisationStats = field(default_factory=RelinearisationStats)
    features: LiveBatch | None = None
    relative: LiveBatch | None = None

    def __post_init__(self) -> None:
        if not (np.isfinite(self.threshold) and self.threshold > 0):
            raise ConfigError(f"relinearisation threshold must be positive, got {self.threshold!r}")

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

    @staticmethod
    def _in_window(inc, name: str, idx: IntArray, less: int = 0) -> NDArray[np.bool_]:
        """Which measurements ``idx (N, k)`` are still candidates: a ``Zm`` while its feature
        was measured within ``feature_window`` steps (the window keeps such a feature, and
        every pose coupled to it), a ``ZR``/``ZT`` while both poses were measured within
        ``pose_window`` steps. Decided from the steps of the last measurements only (not the
        window's current make-up, which a rebuild changes), so a loaded session prunes as
        the uninterrupted run does. ``less``: within that many steps fewer (1: which will
        still be candidates after this step's marginalisation, unless measured again)."""
        if name == "features":
            return inc.measured_within(idx[:, 7], inc.feature_window - less)
        w = inc.pose_window - less
        return inc.measured_within(idx[:, 0], w) & inc.measured_within(idx[:, 7], w)

    # -- sessions -----------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """The candidates and their linearisations, and the counters (arrays and JSON values)."""
        out: dict = {"stats": dataclasses.asdict(self.stats)}
        for name, pack in (("features", pack_features), ("relative", pack_relative)):
            live = getattr(self, name)
            out[name] = None if live is None or len(live) == 0 else dict(
                meas=pack(live.meas), **{k: getattr(live, k).copy() for k in ("idx", "J", "W", "innov", "x0")})
        return out

    def load_state_dict(self, d: Mapping[str, Any], dim: int) -> None:
        """Restore :meth:`state_dict` into a filter of ``dim`` entries.

        Raises
        ------
        SessionError
            On a malformed entry.
        """
        st = sub(d, "stats")
        self.stats = RelinearisationStats(**{f.name: take_int(st, f.name, 0)
                                             for f in dataclasses.fields(RelinearisationStats)})
        for name, unpack, k, m in (("features", unpack_features, 10, 2), ("relative", unpack_relative, 14, 5)):
            if d.get(name) is None:
                setattr(self, name, None)
                continue
            e = sub(d, name)
            meas = unpack(sub(e, "meas"))
            n = len(meas)
            idx = take(e, "idx", np.int64, (n, k))
            check_index(idx, dim, "array 'idx'")
            setattr(self, name, LiveBatch(meas, idx.copy(), take(e, "J", np.float64, (n, m, k)).copy(),
                                          take(e, "W", np.float64, (n, m, m)).copy(),
                                          take(e, "innov", np.float64, (n, m)).copy(),
                                          take(e, "x0", np.float64, (n, k)).copy()))

    # -- the step -----------------------------------------------------------------------------
    def step(self, filt: "InformationFilter") -> int:
        """Relinearise the live measurements over the threshold, and those on their last
        step in the window, at ``filt.x``; return how many. Call before the frame's
        recovery."""
        inc = filt.incremental
        self.stats.steps += 1
        if inc is None:
            return 0
        x, t2 = filt.x, self.threshold**2
        done = 0
        for name in ("features", "relative"):
            live = getattr(self, name)
            if live is None or len(live) == 0:
                continue
            live = live.subset(self._in_window(inc, name, live.idx))
            setattr(self, name, live)
            if len(live) == 0:
                continue
            # the linearisation error is second order in the change of the states, so it is
            # below the first-order change J0 dx (whitened) unless the model curves by more
            # than the change itself: only the measurements whose first-order change exceeds
            # the threshold are evaluated
            dx = x[live.idx] - live.x0
            d = np.einsum("nmk,nk->nm", live.J, dx)
            f2 = np.einsum("ni,nij,nj->n", d, live.W, d)
            # on their last step in the window: evaluated whatever their change
            last = ~self._in_window(inc, name, live.idx, less=1)
            cand = np.flatnonzero((f2 > t2) | last)
            self.stats.evaluated += len(cand)
            if len(cand) == 0:
                continue
            i = live.idx[cand]
            if name == "features":  # factors.features on the stored indices (no layout look-ups)
                h, J, depth = factors.feature_model_at(i, x, filt.camera)
                innov = live.meas.uv[cand] - h
                ok = depth > filt.config.min_depth
            else:
                _, J, _, innov = filt.linearise_relative([live.meas[j] for j in cand])
                ok = np.ones(len(cand), bool)
            e = live.innov[cand] - d[cand] - innov
            err2 = np.einsum("ni,nij,nj->n", e, live.W[cand], e)
            ok &= np.isfinite(err2) & np.all(np.isfinite(J), axis=(1, 2)) & np.all(np.isfinite(innov), axis=1)
            o = np.flatnonzero(ok & ((err2 > t2) | last[cand]))
            if not len(o):
                continue
            sel = cand[o]
            idx = live.idx[sel]
            Lam0, eta0 = contribution(idx, live.J[sel], live.W[sel], live.innov[sel], live.x0[sel])
            x1 = x[idx]
            Lam1, eta1 = contribution(idx, J[o], live.W[sel], innov[o], x1)
            filt.add_information(idx, Lam1 - Lam0, eta1 - eta0, measurement=False)
            live.J[sel], live.innov[sel], live.x0[sel] = J[o], innov[o], x1
            done += len(sel)
        self.stats.relinearised += done
        return done


__all__ = ["LiveBatch", "OnlineRelinearisation", "RelinearisationStats", "contribution"]
