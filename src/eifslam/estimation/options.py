"""Typed options of the estimation layer: :class:`FilterConfig`, :class:`Recovery`,
:class:`NoiseEstimate`.

The enums are ``str``-valued: they accept and compare equal to the plain strings of
configuration files (``Recovery("full") == "full"``).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np

from ..errors import ConfigError


class Choice(str, Enum):
    """A ``str``-valued enum that prints as its value: the base of every option with a
    fixed set of values (:class:`Recovery`, the front end's
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


#: Steps without a measurement before a state leaves the incremental recovery's active
#: window: more than the front end's matching window, so that a track that reappears
#: rarely touches a marginalised feature.
WINDOW = 5


class Recovery(Choice):
    """Per-frame state recovery of :class:`~eifslam.estimation.filter.InformationFilter`.

    ``INCREMENTAL``: exact over an active window, the rest marginalised
    (:mod:`eifslam.estimation.incremental`); ``FULL``: the full sparse solve.
    """

    INCREMENTAL = "incremental"
    FULL = "full"


class NoiseEstimate(Choice):
    """How robust smoothing sets its ``Zm`` gate from the residuals
    (``SlamConfig.experimental.noise_estimate``; :mod:`eifslam.estimation.noise`).

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
    relinearise_threshold : float or None
        Online relinearisation (incremental recovery only,
        :mod:`eifslam.estimation.relinearisation`): before each recovery, a stored ``Zm``
        or ``ZR``/``ZT`` whose states are all in the active window is relinearised at
        the current estimate when its linearisation error exceeds this many standard
        deviations of the measurement (0.3: at most a twentieth of a 2-DOF measurement's
        expected cost is linearisation). Without it the filter's estimate drifts from the
        cost's minimum and its NEES grows along a run (synthetic corridor, 10 runs x 100
        frames: 86.9 without, 9.8 at 0.3, 9.1 at 0.1, 9.9 at 1.0; ``docs/estimator.md``,
        Consistency). ``None``: measurements stay linearised where they were fused (as
        the dense EKF baseline, which is compared with the filter linearised alike).
    """

    prior_sigma: float = 1e-6
    scale_prior_sigma: float = 1e-6
    quat_norm_sigma: float = 1e-3
    gate_chi2: float | None = None
    min_depth: float = 1e-6
    weak_prior_sigma: float = 1e3
    relinearise_threshold: float | None = 0.3

    def __post_init__(self) -> None:
        for key in ("prior_sigma", "scale_prior_sigma", "quat_norm_sigma", "min_depth", "weak_prior_sigma"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v > 0):
                raise ConfigError(f"filter.{key} must be a positive number, got {v!r}")
        if self.gate_chi2 is not None and not self.gate_chi2 > 0:
            raise ConfigError("filter.gate_chi2 must be positive or None")
        t = self.relinearise_threshold
        if t is not None and not (isinstance(t, (int, float)) and np.isfinite(t) and t > 0):
            raise ConfigError(f"filter.relinearise_threshold must be a positive number or None, got {t!r}")


__all__ = ["FilterConfig", "NoiseEstimate", "Recovery", "WINDOW"]
