"""How large the ``Zm`` noise is, from the residuals: robust smoothing's gate.

The stated ``sigma_px`` is a guess made before any image is seen. At an estimate fitted to
the measurements, the normalised innovations squared of the ``Zm`` show the real noise:
:func:`residual_noise_scale` gives one ratio ``s`` for all of them,
:func:`track_length_noise` one per group of features with about the same number of
``Zm`` (track lengths ``2``, ``3-4``, ``5-8``, ``9-16``, ...: ``ceil(log2 m)``).

Why by track length: a keypoint drifts along a long track (its position is re-detected
at other scales and viewpoints), so long tracks' residuals are larger than short ones'
(kitti-seq1, seed 0: ``s`` 0.19, 0.20, 0.21, 0.31, 0.31 for the groups from 3-4 ``Zm``
up). A single ``s`` is set by the many short tracks, and a gate at ``3 s`` then drops
about 18% of the far, long-tracked features' ``Zm`` where Gaussian noise would drop 1%.
Pure NumPy.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from .filter import InformationFilter
from .measurements import FeatureObservations

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["MIN_GROUP_ZM", "FeatureGate", "NoiseGroup", "TrackLengthNoise", "residual_noise_scale", "track_length_noise"]

#: the median of a chi-square with 2 degrees of freedom
_MEDIAN_CHI2_2 = 2.0 * np.log(2.0)

#: ``Zm`` a group of track lengths needs for a scale of its own: the median of ``N``
#: chi-square(2) values estimates ``s**2`` with a relative standard error of
#: ``1 / (ln 2 sqrt(N))``, so ``s`` to 10% (one standard error) takes ``N >= 53``;
#: a smaller group joins the next shorter one (the shortest: the next longer one)
MIN_GROUP_ZM = int(np.ceil((1.0 / (np.log(2.0) * 2 * 0.10)) ** 2))


def _scale(chi2: Array, fitted: float) -> float | None:
    """``s`` from the finite ``chi2 (N,)`` of ``N`` ``Zm`` to which ``fitted`` parameters
    were fitted: ``sqrt(median(chi2) / median(chi2_2) * n / (n - p))``, ``n = 2 N``;
    None when ``n <= 2 p`` (too few residuals to tell)."""
    n = 2 * len(chi2)
    if n <= 2 * fitted or not len(chi2):
        return None
    s2 = float(np.median(chi2)) / _MEDIAN_CHI2_2 * n / (n - fitted)
    return float(np.sqrt(s2)) if np.isfinite(s2) and s2 > 0 else None


def _chi2(filt: InformationFilter, features: FeatureObservations | None) -> tuple[FeatureObservations, Array]:
    obs = filt.store.all_features() if features is None else features
    if not len(obs):
        return obs, np.zeros(0)
    return obs, filt.linearise_features(obs, gate=False)[5]


def residual_noise_scale(filt: InformationFilter, features: FeatureObservations | None = None) -> float:
    """How large the ``Zm`` noise is against the stated one, from the residuals at ``x``.

    ``s = sigma_hat / sigma`` with ``sigma_hat**2 = median(chi2) / median(chi2_2) *
    n / (n - p)``: the median of the normalised innovations squared (2 DOF each) against
    the median of a chi-square with 2 DOF (``2 ln 2``), a robust variance estimate that
    outliers barely move, corrected for the parameters the residuals were fitted with
    (``n = 2 N`` residuals of ``N`` measurements; ``p`` = 3 per observed feature and 6
    per observing pose). Only meaningful at an estimate fitted to these measurements (the
    filter's, or smoothed).

    Parameters
    ----------
    filt : InformationFilter
    features : FeatureObservations, optional
        The measurements (default: every stored ``Zm``).

    Returns
    -------
    float
        ``s > 0``; 1.0 when there are too few measurements to tell (``n <= 2 p``).
    """
    return _overall(*_chi2(filt, features))


def _overall(obs: FeatureObservations, chi2: Array) -> float:
    """:func:`residual_noise_scale` of ``obs`` from their ``chi2 (N,)``."""
    ok = np.isfinite(chi2)
    if not ok.any():
        return 1.0
    p = 3 * len(np.unique(obs.feature)) + 6 * len(np.unique(obs.pose))
    s = _scale(chi2[ok], p)
    return 1.0 if s is None else s


@dataclass(frozen=True)
class FeatureGate:
    """A ``Zm`` gate (normalised innovation squared) per map feature.

    Attributes
    ----------
    ids : (F,) int64, sorted
        Track ids of the features with a gate of their own.
    gates : (F,) float
        Their gates.
    default : float
        The gate of every other feature.
    """

    ids: IntArray
    gates: Array
    default: float

    def of(self, features: IntArray) -> Array:
        """The gate ``(N,)`` of each of ``features (N,)`` (track ids)."""
        features = np.asarray(features, np.int64)
        out = np.full(len(features), float(self.default))
        if len(self.ids) and len(features):
            at = np.minimum(np.searchsorted(self.ids, features), len(self.ids) - 1)
            hit = self.ids[at] == features
            out[hit] = self.gates[at[hit]]
        return out


@dataclass(frozen=True)
class NoiseGroup:
    """Features with ``shortest`` to ``longest`` stored ``Zm``, and their noise scale.

    ``scale`` is None when the group has too few residuals to tell (its features then
    take the overall scale); ``zm`` counts the group's ``Zm``."""

    shortest: int
    longest: int
    zm: int
    scale: float | None

    def to_dict(self) -> dict:
        return dict(track_length=[self.shortest, self.longest], zm=self.zm,
                    scale=None if self.scale is None else round(self.scale, 6))


@dataclass
class TrackLengthNoise:
    """:func:`track_length_noise`'s answer.

    Attributes
    ----------
    overall : float
        :func:`residual_noise_scale` of every ``Zm``.
    groups : list of NoiseGroup
        Shortest tracks first.
    feature_ids : (F,) int64, sorted
        Every feature with a ``Zm``.
    feature_scale : (F,) float
        The scale of each one's group (``overall`` where the group has none).
    """

    overall: float
    groups: list[NoiseGroup] = field(default_factory=list)
    feature_ids: IntArray = field(default_factory=lambda: np.zeros(0, np.int64))
    feature_scale: Array = field(default_factory=lambda: np.zeros(0))

    def gate(self, chi2_gate: float) -> FeatureGate:
        """``chi2_gate * min(1, s)**2`` per feature, ``s`` its group's scale: never looser
        than ``chi2_gate`` (more noise than stated does not open the gate)."""
        return FeatureGate(self.feature_ids, chi2_gate * np.minimum(1.0, self.feature_scale) ** 2,
                           chi2_gate * min(1.0, self.overall) ** 2)


def track_length_noise(filt: InformationFilter, features: FeatureObservations | None = None) -> TrackLengthNoise:
    """The ``Zm`` noise scale (as :func:`residual_noise_scale`) per group of track lengths.

    A feature with ``m`` stored ``Zm`` is in group ``ceil(log2 m)`` (2; 3-4; 5-8; 9-16;
    ...): groups double in length, as a keypoint's drift grows with how far it was
    followed. A group with fewer than :data:`MIN_GROUP_ZM` ``Zm`` joins the next shorter
    group (the shortest: the next longer one), so that no few features set their own
    gate. Each group's scale is corrected for its own fitted parameters: 3 per
    feature, and the poses' ``6 P`` shared in proportion to the group's ``Zm``.

    Parameters
    ----------
    filt : InformationFilter
        At an estimate fitted to the measurements.
    features : FeatureObservations, optional
        The measurements (default: every stored ``Zm``).
    """
    obs, chi2 = _chi2(filt, features)
    overall = _overall(obs, chi2)  # the residuals once, for the overall and the groups
    if not len(obs):
        return TrackLengthNoise(overall)
    ids, inv, counts = np.unique(obs.feature, return_inverse=True, return_counts=True)
    group = np.ceil(np.log2(np.maximum(counts, 1))).astype(np.int64)  # per feature
    levels = np.unique(group)
    zm_per_level = np.array([counts[group == g].sum() for g in levels])
    for a in range(len(levels) - 1, 0, -1):  # the longest tracks first: too few Zm, join the shorter
        if zm_per_level[a] < MIN_GROUP_ZM:
            group[group == levels[a]] = levels[a - 1]
            zm_per_level[a - 1] += zm_per_level[a]
            zm_per_level[a] = 0
    rest = np.flatnonzero(zm_per_level[1:]) + 1
    if zm_per_level[0] < MIN_GROUP_ZM and len(rest):  # the shortest: join the next longer
        group[group == levels[0]] = levels[rest[0]]
    zm_group = group[inv]
    ok = np.isfinite(chi2)
    pose_params = 6.0 * len(np.unique(obs.pose))
    scale = np.full(len(ids), overall)
    groups = []
    for g in np.unique(group):
        sel = ok & (zm_group == g)
        members = group == g
        s = _scale(chi2[sel], 3.0 * members.sum() + pose_params * sel.sum() / max(ok.sum(), 1))
        if s is not None:
            scale[members] = s
        c = counts[members]
        groups.append(NoiseGroup(int(c.min()), int(c.max()), int((zm_group == g).sum()), s))
    return TrackLengthNoise(overall, groups, ids.astype(np.int64), scale)
