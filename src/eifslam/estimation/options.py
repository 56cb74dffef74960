"""Typed options of the estimation layer: :class:`FilterConfig`, :class:`ZtForm`, :class:`Recovery`,
:class:`FirstEstimates`.

The enums are ``str``-valued: they accept and compare equal to the plain strings of
configuration files (``ZtForm("auto") == "auto"``).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from ..errors import ConfigError


class Choice(str, Enum):
    """A ``str``-valued enum that prints as its value: the base of every option with a
    fixed set of values (:class:`ZtForm`, :class:`Recovery`, the front end's
    ``Detector``, the system's ``Mode``), so that configs given as plain strings work."""

    def __str__(self) -> str:
        return str(self.value)

    @classmethod
    def parse(cls, value: "str | Choice", what: str):
        """The member whose value is ``value``; :class:`ConfigError` naming ``what`` otherwise."""
        try:
            return cls(value)
        except ValueError:
            allowed = ", ".join(m.value for m in cls)
            raise ConfigError(f"{what} must be one of {allowed}, got {value!r}") from None


class ZtForm(Choice):
    """Model of the translation-direction measurement ``ZT``.

    ``PAPER``: the paper's ``[x/z, y/z]``; ``BEARING``: the non-singular bearing form;
    ``AUTO``: the paper's form within ``zt_paper_max_angle_deg`` of the optical axis,
    the bearing form otherwise.
    """

    AUTO = "auto"
    PAPER = "paper"
    BEARING = "bearing"


class Recovery(Choice):
    """Per-frame state recovery of :class:`~eifslam.estimation.filter.InformationFilter`.

    ``INCREMENTAL``: exact over an active window, the rest marginalised
    (:mod:`eifslam.estimation.incremental`); ``FULL``: the full sparse solve.
    """

    INCREMENTAL = "incremental"
    FULL = "full"


class FirstEstimates(Choice):
    """Which states' Jacobians a new measurement takes at their *first* estimates
    (``FilterConfig.first_estimate_jacobians``).

    ``OFF``: every Jacobian at the current estimate; ``FEATURES``: the map features' at
    their first estimates (the multi-view point they entered with), the poses' at the
    current estimate; ``ALL``: every state's at its first estimate.
    """

    OFF = "off"
    FEATURES = "features"
    ALL = "all"

    @classmethod
    def parse(cls, value: "str | bool | Choice", what: str):
        """As :meth:`Choice.parse`; ``True`` is ``ALL`` and ``False`` ``OFF`` (the option
        was a bool before ``FEATURES``)."""
        if isinstance(value, (bool, np.bool_)):
            return cls.ALL if value else cls.OFF
        return super().parse(value, what)

    def points(self, x: np.ndarray, first: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Where a ``Zm``'s Jacobian is taken: the vectors its pose entries and its feature
        entries are read from (``x`` the current estimate, ``first`` the first estimates);
        None for ``OFF`` (at ``x``, with the innovation)."""
        if self == FirstEstimates.OFF:
            return None
        return (x if self == FirstEstimates.FEATURES else first), first


class NoiseEstimate(Choice):
    """How robust smoothing sets its ``Zm`` gate from the residuals
    (``SystemConfig.smoothing_noise_estimate``; :mod:`eifslam.estimation.noise`).

    ``OFF``: at the stated ``sigma_px``; ``GLOBAL``: scaled by one noise ratio from every
    ``Zm``; ``TRACK_LENGTH``: by one ratio per group of track lengths (2; 3-4; 5-8; ...).
    """

    OFF = "off"
    GLOBAL = "global"
    TRACK_LENGTH = "track_length"

    @classmethod
    def parse(cls, value: "str | bool | Choice", what: str):
        """As :meth:`Choice.parse`; ``True`` is ``TRACK_LENGTH`` (the estimate on) and
        ``False`` ``OFF`` (the option was a bool before ``TRACK_LENGTH``)."""
        if isinstance(value, (bool, np.bool_)):
            return cls.TRACK_LENGTH if value else cls.OFF
        return super().parse(value, what)


@dataclass(frozen=True)
class FilterConfig:
    """Settings of the information filter.

    Attributes
    ----------
    prior_sigma : float
        Standard deviation of the first-pose prior (position units, and quaternion units).
    scale_prior_sigma : float
        Relative standard deviation of the scale prior (fraction of the prior distance).
    quat_norm_sigma : float
        Standard deviation of the ``|q|^2 = 1`` pseudo-measurement.
    zt_form : ZtForm or {"auto", "paper", "bearing"}
        ``ZT`` model: the paper's ``[x/z, y/z]``, the non-singular bearing form, or the
        paper's form when the measured direction is within ``zt_paper_max_angle_deg`` of
        the optical axis and the bearing form otherwise.
    zt_paper_max_angle_deg : float
        Largest angle between the translation direction and the optical axis for which
        ``auto`` uses the paper's form.
    gate_chi2 : float or None
        Reject a ``Zm`` whose normalised innovation squared exceeds this (2 DOF); ``None``
        fuses everything.
    min_depth : float
        Reject a ``Zm`` whose predicted depth is below this (state units).
    weak_prior_sigma : float
        Standard deviation of a weak prior put on every new pose position and feature at
        its initial guess, so that a state whose measurements were all rejected (gate,
        depth) never makes ``I`` singular. Its information, ``1e-6`` by default, is
        negligible next to any measurement's; it touches diagonal blocks only.
    gate_feature_uncertainty : bool
        Test a ``Zm`` against its innovation covariance ``R + J_f P_f J_f^T`` (``P_f`` the
        feature's marginal covariance, where the incremental window has it:
        :meth:`InformationFilter.feature_covariances`) instead of ``R`` alone. With ``R``
        alone, an observation of a feature whose estimate is off (e.g. triangulated with
        little parallax) is refused for disagreeing with that estimate, which is then
        never corrected: on the synthetic corridor (every measurement correct) the gate
        refused about 10% of the ``Zm`` with ``R`` alone (``docs/estimator.md``, Consistency).
        Off by default: on real images it also admits wrong matches of uncertain features
        (smoothed ATE, seed 0, SIFT: middlebury-templering 0.00203 -> 0.0036 m,
        strecha-fountain-p11 0.00308 -> 0.00353 m; kitti-seq1 0.0195 -> 0.0177 m and
        strecha-herzjesu-p25 0.00954 -> 0.00858 m improved); measured again in session 38,
        kitti-07's scale collapses with it (filter ATE 20.9 m).
    first_estimate_jacobians : FirstEstimates or {"off", "features", "all"} or bool
        Linearise every new ``Zm`` (and, with ``"all"``, ``ZR``/``ZT``) with the Jacobians
        of some states at their *first* estimates (the value they entered the state with;
        smoothing's relinearisation makes the smoothed estimate the new first one), the
        innovation at the current estimate (first-estimates Jacobians, Huang, Mourikis &
        Roumeliotis 2008). The filter never relinearises what it fused, so Jacobians of
        one state at different points give it information in directions the
        measurements cannot observe, and it grows overconfident as a run goes on.
        ``"features"`` takes the map features' Jacobians at their first estimates (the
        point refined on every view they entered with) and the poses' at the current
        estimate: a feature is measured from many frames, a pose almost only in the frame
        it enters, so this is where the inconsistency comes from (synthetic corridor, 50
        runs x 50 frames, filter's mean NEES 30.8 off, 13.6 ``"features"``; the poses' first
        estimates, guesses from a relative pose and the last step length, only add
        linearisation error: middlebury-templering's filter ATE 0.00159 m ``"features"``,
        0.00202 m ``"all"``). ``True`` is ``"all"`` and ``False`` ``"off"``. Off by default:
        on kitti-07 the filter then lands at the cost's minimum, whose scale drifts
        (filter ATE 0.24 m off, 0.42-0.44 m ``"features"``, seeds 0-2), which outweighs
        middlebury-templering's gain (smoothed ATE 20% lower) when chosen
        leave-one-set-out (``docs/estimator.md``, Consistency).
    relinearise_threshold : float or None
        Online relinearisation (incremental recovery only,
        :mod:`eifslam.estimation.relinearisation`): before each recovery, a stored ``Zm``
        or ``ZR``/``ZT`` whose states are all in the active window is relinearised at
        the current estimate (its Jacobian where ``first_estimate_jacobians`` takes it)
        when its linearisation error exceeds this many standard
        deviations of the measurement. ``None``: measurements stay linearised where
        they were fused (the default: on a slow walk with small parallax, 0.1 made the
        filter diverge; on the corridor 0.1 brings the estimate to within 0.05% of the
        batch optimum's cost; ``docs/backend.md``).
    relinearise_budget : int
        At most this many measurements relinearised per frame (largest error first;
        at most 8 times as many evaluated).
    """

    prior_sigma: float = 1e-6
    scale_prior_sigma: float = 1e-6
    quat_norm_sigma: float = 1e-3
    zt_form: ZtForm = ZtForm.AUTO
    zt_paper_max_angle_deg: float = 60.0
    gate_chi2: float | None = None
    min_depth: float = 1e-6
    weak_prior_sigma: float = 1e3
    gate_feature_uncertainty: bool = False
    first_estimate_jacobians: FirstEstimates = FirstEstimates.OFF
    relinearise_threshold: float | None = None
    relinearise_budget: int = 50

    def __post_init__(self) -> None:
        for key in ("prior_sigma", "scale_prior_sigma", "quat_norm_sigma", "min_depth", "weak_prior_sigma"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"filter.{key} must be a positive number, got {v!r}")
        object.__setattr__(self, "zt_form", ZtForm.parse(self.zt_form, "filter.zt_form"))
        object.__setattr__(self, "first_estimate_jacobians",
                           FirstEstimates.parse(self.first_estimate_jacobians, "filter.first_estimate_jacobians"))
        if not 0.0 < self.zt_paper_max_angle_deg < 90.0:
            raise ConfigError("filter.zt_paper_max_angle_deg must lie in (0, 90)")
        if self.gate_chi2 is not None and not self.gate_chi2 > 0:
            raise ConfigError("filter.gate_chi2 must be positive or None")
        t = self.relinearise_threshold
        if t is not None and not (isinstance(t, (int, float)) and np.isfinite(t) and t > 0):
            raise ConfigError(f"filter.relinearise_threshold must be a positive number or None, got {t!r}")
        b = self.relinearise_budget
        if not (isinstance(b, (int, np.integer)) and not isinstance(b, bool) and b >= 1):
            raise ConfigError(f"filter.relinearise_budget must be an integer >= 1, got {b!r}")


__all__ = ["FilterConfig", "FirstEstimates", "Recovery", "ZtForm"]
