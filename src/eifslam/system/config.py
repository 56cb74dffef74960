"""Typed configuration of the whole system, with key and range checking.

``SlamConfig`` groups the front end's, the filter's and the system's settings. Build it
from a nested mapping with :meth:`SlamConfig.from_dict`; an unknown key or an
out-of-range value raises :class:`~eifslam.errors.ConfigError` naming it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Mapping

from ..errors import ConfigError
from ..estimation.filter import FilterConfig
from ..frontend import FrontEndConfig


@dataclass(frozen=True)
class SystemConfig:
    """Settings of the SLAM system (paper III-C, III-D, III-E).

    Attributes
    ----------
    mode : {"filter", "smooth", "ba"}
        Filter only, or filter + relinearise + smooth at the end of a run, or filter +
        full bundle adjustment of every track (:mod:`eifslam.bundle_adjustment`).
    smooth_passes : int
        At most this many relinearisation passes when smoothing (paper: one is enough).
    reference_candidates : int
        How many of the most recent known poses to try as the reference of a new image.
    relocalise_candidates : int
        How many older poses to try when the recent ones fail (tracking lost).
    min_feature_parallax_deg : float
        A map feature is created once two of its rays differ by this angle (2 degrees:
        lower lets poorly triangulated features in, which the EIF never relinearises;
        higher starves slow sequences of map features; measured in docs/system.md).
    init_parallax_deg : float
        The pair that initialises the map (III-C: the first frame and the first later
        frame related to it) needs at least this median parallax, degrees; until then
        frames wait, and are localised on the map once it exists. Set it above the front
        end's ``min_parallax_deg`` (the default equals it) for a better triangulated first
        map.
    sigma_px : float or None
        Standard deviation of a map feature's pixel measurement ``Zm``; None (default):
        1 px for float-descriptor detectors (SIFT, SURF), 2 px for binary ones (ORB,
        AKAZE), whose keypoints come from coarser pyramid levels (on kitti-seq1 ORB lost
        the map at 1 px with the 3-px gate). See :meth:`SlamConfig.zm_sigma_px`.
    scale_distance : float
        Length given to the distance between the first two poses (the scale gauge).
    relative_gate_chi2 : float or None
        A ``ZR``/``ZT`` pair whose normalised innovation squared (5 DOF) at the pose the
        known map supports exceeds this is not fused (a wrong five-point solution or an
        overconfident covariance); ``None`` fuses every pair.
    robust_smoothing : bool
        After its passes, smoothing drops the ``ZR``/``ZT`` that fail
        ``relative_gate_chi2`` (worst first), then the ``Zm`` that fail the filter's
        ``gate_chi2``, at the smoothed estimate, and smooths again
        (:func:`eifslam.smoothing.reject_outliers`); False relinearises every fused one.
    reobserve_radius_px : float or None
        Map features that frame-to-frame tracking lost are searched for again in each
        new frame within this many pixels of where the pose guess projects them
        (descriptor ratio test; 0 turns it off). This keeps map features alive across
        occlusions and revisits, which holds the scale. None (default): 15 px for float
        descriptors (SIFT, SURF), off for binary ones (ORB, AKAZE), whose ratio test let
        wrong re-observations in on kitti-seq1 (ATE 5.7 m with, 0.034 m without). See
        :meth:`SlamConfig.reobserve_px`.
    recovery : {"incremental", "full"}
        Per-frame state recovery: exact over an active window with the rest marginalised
        (paper III-G, :mod:`eifslam.incremental`), or the full sparse solve.
    window : int
        Incremental recovery: frames without a measurement before a state leaves the
        window (larger than the front end's matching window, so that a track that
        reappears rarely touches a marginalised feature).
    """

    mode: str = "smooth"
    smooth_passes: int = 5
    reference_candidates: int = 4
    relocalise_candidates: int = 30
    min_feature_parallax_deg: float = 2.0
    init_parallax_deg: float = 0.5
    sigma_px: float | None = None
    scale_distance: float = 1.0
    recovery: str = "incremental"
    window: int = 5
    relative_gate_chi2: float | None = 50.0
    robust_smoothing: bool = True
    reobserve_radius_px: float | None = None

    def __post_init__(self) -> None:
        if self.mode not in ("filter", "smooth", "ba"):
            raise ConfigError(f"system.mode must be 'filter', 'smooth' or 'ba', got {self.mode!r}")
        for key in ("smooth_passes", "reference_candidates"):
            if int(getattr(self, key)) < 1:
                raise ConfigError(f"system.{key} must be at least 1")
        if self.relative_gate_chi2 is not None and not self.relative_gate_chi2 > 0:
            raise ConfigError("system.relative_gate_chi2 must be positive or None")
        if self.recovery not in ("incremental", "full"):
            raise ConfigError(f"system.recovery must be 'incremental' or 'full', got {self.recovery!r}")
        if int(self.window) < 1:
            raise ConfigError("system.window must be at least 1")
        if self.relocalise_candidates < 0:
            raise ConfigError("system.relocalise_candidates must be >= 0")
        if not 0.0 <= self.init_parallax_deg < 90.0:
            raise ConfigError("system.init_parallax_deg must be in [0, 90)")
        if self.reobserve_radius_px is not None and not self.reobserve_radius_px >= 0:
            raise ConfigError("system.reobserve_radius_px must be >= 0")
        for key in ("min_feature_parallax_deg", "sigma_px", "scale_distance"):
            v = getattr(self, key)
            if key == "sigma_px" and v is None:
                continue
            if not (isinstance(v, (int, float)) and v > 0):
                raise ConfigError(f"system.{key} must be a positive number, got {v!r}")


    @property
    def feature_parallax_deg(self) -> float:
        """The parallax a new map feature needs, degrees."""
        return float(self.min_feature_parallax_deg)


def _build(cls: type, values: Mapping[str, Any], prefix: str):
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f"unknown configuration key {prefix}.{unknown[0]} (known: {', '.join(sorted(names))})")
    try:
        return cls(**values)
    except TypeError as exc:
        raise ConfigError(f"bad value in {prefix}: {exc}") from exc


@dataclass(frozen=True)
class SlamConfig:
    """Front end, filter and system settings."""

    # the system's front-end defaults (measured on the shared data sets, docs/system.md):
    # more features, SIFT's 3 layers per octave, tracks matched over the last 3 frames, and
    # half of the new tracks kept in the map (docs/split_study.md)
    frontend: FrontEndConfig = field(
        default_factory=lambda: FrontEndConfig(max_features=2000, sift_octave_layers=3, match_window=3,
                                               map_fraction=0.5))
    # Zm gate: 99% of chi-square with 2 DOF at sigma_px (docs/system.md)
    filter: FilterConfig = field(default_factory=lambda: FilterConfig(gate_chi2=9.21))
    system: SystemConfig = field(default_factory=SystemConfig)

    @property
    def float_descriptors(self) -> bool:
        """Whether the detector gives float descriptors (SIFT, SURF) rather than binary ones."""
        return self.frontend.detector in ("sift", "surf")

    @property
    def zm_sigma_px(self) -> float:
        """Standard deviation of ``Zm``, pixels: ``system.sigma_px``, or by default 1 px for
        float descriptors (SIFT, SURF) and 2 px for binary ones (ORB, AKAZE)."""
        if self.system.sigma_px is not None:
            return float(self.system.sigma_px)
        return 1.0 if self.float_descriptors else 2.0

    @property
    def reobserve_px(self) -> float:
        """Re-observation radius, pixels (0: off): ``system.reobserve_radius_px``, or by
        default 15 px for float descriptors (SIFT, SURF) and off for binary ones."""
        if self.system.reobserve_radius_px is not None:
            return float(self.system.reobserve_radius_px)
        return 15.0 if self.float_descriptors else 0.0

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "SlamConfig":
        """Build from ``{"frontend": {...}, "filter": {...}, "system": {...}}``."""
        unknown = sorted(set(values) - {"frontend", "filter", "system"})
        if unknown:
            raise ConfigError(f"unknown configuration section {unknown[0]!r} (known: frontend, filter, system)")
        base = cls()
        fe = dataclasses.asdict(base.frontend) | dict(values.get("frontend", {}))
        fi = dataclasses.asdict(base.filter) | dict(values.get("filter", {}))
        sy = dataclasses.asdict(base.system) | dict(values.get("system", {}))
        return cls(
            frontend=_build(FrontEndConfig, fe, "frontend"),
            filter=_build(FilterConfig, fi, "filter"),
            system=_build(SystemConfig, sy, "system"),
        )

    def replace(self, **sections: Mapping[str, Any]) -> "SlamConfig":
        """A copy with some keys of some sections changed, e.g. ``replace(system={"mode": "filter"})``."""
        d = {k: dataclasses.asdict(getattr(self, k)) for k in ("frontend", "filter", "system")}
        for sec, vals in sections.items():
            if sec not in d:
                raise ConfigError(f"unknown configuration section {sec!r}")
            d[sec] = d[sec] | dict(vals)
        return SlamConfig.from_dict(d)
