"""Typed configuration of the whole system: :class:`SlamConfig` and its sections.

``SlamConfig`` holds one section per part of the system: ``frontend``
(:class:`~eifslam.frontend.config.FrontEndConfig`), ``tracking``, ``mapping``,
``keyframes``, ``loops``, ``smoothing``, ``runtime``, and ``experimental``, the few
alternatives still measured. Every field is declared with one line of help and its check
(:func:`~eifslam.settings.setting`); a bad value or an unknown key raises
:class:`~eifslam.errors.ConfigError` naming ``section.key``. Build it from a nested mapping
with :meth:`SlamConfig.from_dict`. The class attributes of a section below its fields are
tuning constants of the code that reads them, not settings.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping

from ..errors import ConfigError
from ..estimation.options import WINDOW, Choice, FilterConfig, NoiseEstimate, Recovery
from ..frontend import FrontEndConfig
from ..settings import Flag, Int, OneOf, Real, build_section, check_section, plain, setting


class Mode(Choice):
    """What a run does after the last image (:meth:`Slam.finish <eifslam.system.slam.Slam.finish>`).

    A ``str`` enum: ``Mode("smooth")``, ``Mode.SMOOTH == "smooth"`` and configs given as
    plain strings all work.
    """

    FILTER = "filter"  #: the filter's estimate
    SMOOTH = "smooth"  #: relinearise every stored measurement and smooth (paper III-E)
    BA = "ba"  #: full bundle adjustment of every track


_POSITIVE = Real(0.0, 1e9, lo_open=True)


@dataclass(frozen=True)
class TrackingConfig:
    """Settings of tracking (section ``tracking``): placing each frame (paper III-C, III-D)."""

    scale_distance: float = setting(1.0, "length given to the distance between the first two poses "
                                         "(the scale gauge), map units", _POSITIVE)

    # -- tuning constants (not settings) ----------------------------------------------
    #: Most recent known poses tried as the reference of a new image.
    reference_candidates: ClassVar[int] = 4
    #: Older poses tried when the recent ones fail (tracking lost).
    relocalise_candidates: ClassVar[int] = 30
    #: When lost, a relative pose is tried with at most this many of the older poses that
    #: share the most descriptor matches with the frame.
    relocalise_top: ClassVar[int] = 5
    #: Known map features a frame must see before it is localised on the map alone.
    min_map_features: ClassVar[int] = 12
    #: A map-refined pose agrees with the relative-pose guess within this rotation, degrees ...
    agree_rotation_deg: ClassVar[float] = 2.0
    #: ... and this angle between their step directions, degrees.
    agree_direction_deg: ClassVar[float] = 10.0
    #: A map-refined pose with this fraction of inliers is a trusted linearisation point.
    map_inlier_fraction: ClassVar[float] = 0.7
    #: The map contradicts a relative pose when the refined pose's inlier fraction exceeds
    #: this multiple of the relative-pose guess's (its ZR/ZT is then not fused).
    contradiction_ratio: ClassVar[float] = 1.5
    #: A known feature fits a pose when it projects within this many pixels of its measurement.
    inlier_radius_px: ClassVar[float] = 4.0

    def __post_init__(self) -> None:
        check_section(self, "tracking")


@dataclass(frozen=True)
class MappingConfig:
    """Settings of mapping (section ``mapping``): the map features."""

    min_feature_parallax_deg: float = setting(2.0, "angle two rays of a track must span before it becomes a "
                                                   "map feature, degrees", Real(0.0, 90.0, lo_open=True,
                                                                                hi_open=True))

    def __post_init__(self) -> None:
        check_section(self, "mapping")

    @property
    def feature_parallax_deg(self) -> float:
        """The parallax a new map feature needs, degrees."""
        return float(self.min_feature_parallax_deg)


@dataclass(frozen=True)
class KeyframeConfig:
    """Settings of keyframe selection (section ``keyframes``): only keyframes become states
    of the filter; the frames between are localised on the map (:mod:`eifslam.system.keyframes`)."""

    max_interval_s: float = setting(1.0, "a frame becomes a keyframe once this long has passed since the last "
                                         "one, seconds (frame indices without timestamps)",
                                    Real(0.0, 1e6, lo_open=True))

    # -- tuning constants (not settings) ----------------------------------------------
    #: ... or once it sees fewer than this fraction of the map features the last keyframe
    #: saw (chosen on the first 150 frames of 7scenes-redkitchen-a, checked on the others).
    min_tracked: ClassVar[float] = 0.5
    #: Keyframes per triangulation parallax: the keyframe parallax is at least the map
    #: feature's divided by this, so that a feature is seen from about four keyframes when
    #: it is made.
    per_triangulation: ClassVar[int] = 4
    #: Map features that fix a frame's pose: a frame localised on more of them needs
    #: proportionally more parallax to become a keyframe, up to the whole triangulation
    #: parallax (:meth:`SlamConfig.keyframe_parallax`). Chosen so that the shared real sets
    #: (30-230 map features per frame) keep their keyframes; checked on the loop world
    #: (about 800 per frame, where it halves the keyframes).
    redundant_features: ClassVar[int] = 150

    def __post_init__(self) -> None:
        check_section(self, "keyframes")


@dataclass(frozen=True)
class LoopConfig:
    """Settings of loop closure (section ``loops``, :mod:`eifslam.system.loops`)."""

    enabled: bool = setting(True, "place recognition, geometric verification and fusion of loops", Flag())

    # -- tuning constants (not settings) ----------------------------------------------
    #: Visual words of the vocabulary learnt from the run's first frames.
    words: ClassVar[int] = 256
    #: Floor of the inlier counts the PnP and five-point checks require.
    min_inliers: ClassVar[int] = 25
    #: Probability that wrong matches reach the required inlier count by chance.
    false_alarm: ClassVar[float] = 1e-6
    #: Consecutive queries a candidate place must come back in before it is verified.
    consistency: ClassVar[int] = 3
    #: Gauss-Newton passes over every stored measurement after a loop the estimate does not
    #: predict (0 left a third of the loop world's error and bent the old map).
    smooth_passes: ClassVar[int] = 2

    def __post_init__(self) -> None:
        check_section(self, "loops")


@dataclass(frozen=True)
class SmoothingConfig:
    """Settings of what a run does after the last image (section ``smoothing``)."""

    mode: Mode = setting(Mode.SMOOTH, "after the last image: filter (the filter's estimate), smooth "
                                      "(relinearise and smooth, paper III-E) or ba (bundle adjustment)",
                         OneOf(Mode))

    def __post_init__(self) -> None:
        check_section(self, "smoothing")


def _threads(value: Any) -> Any:
    if value is None or value == "auto" or (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        return value
    raise ValueError("must be an integer >= 1, auto or null")


@dataclass(frozen=True)
class RuntimeConfig:
    """Settings of how a run uses the machine (section ``runtime``,
    :func:`~eifslam.system.runner.run_sequence`); they never change an estimate."""

    prefetch: int = setting(2, "frames decoded and detected ahead in worker threads (0: none)", Int(0))
    blas_threads: int | None = setting(1, "threads of the BLAS library during a run (null: the library's "
                                          "setting); more only spin on the worker's core", Int(1, none=True))
    opencv_threads: int | str | None = setting("auto", "OpenCV's threads during a run: a number, auto (1 when "
                                                       "detection runs in the worker and descriptors are floats) or "
                                                       "null (OpenCV's setting)", _threads)

    def __post_init__(self) -> None:
        check_section(self, "runtime")


@dataclass(frozen=True)
class ExperimentalConfig:
    """Alternatives still measured, and the gates and counts studies vary (section
    ``experimental``). The defaults are the system's choices."""

    recovery: Recovery = setting(Recovery.INCREMENTAL, "per-frame state recovery: incremental (exact over an "
                                                       "active window, paper III-G) or full (sparse solve)",
                                 OneOf(Recovery))
    window: int = setting(WINDOW, "incremental recovery: frames without a measurement before a state leaves the "
                             "active window", Int(1))
    zm_gate_chi2: float | None = setting(9.21, "a Zm whose normalised innovation squared (2 DOF) exceeds this "
                                               "is not fused (null: every Zm)", Real(0.0, 1e9, lo_open=True,
                                                                                    none=True))
    relative_gate_chi2: float | None = setting(50.0, "a ZR/ZT whose normalised innovation squared (5 DOF) "
                                                     "exceeds this is not fused (null: every one)",
                                               Real(0.0, 1e9, lo_open=True, none=True))
    init_map_features: int | None = setting(
        None, "map features the first baseline must give the map (null: tracking's min_map_features; 0: the "
              "first relative pose that passes, as simulations whose scale is the distance of frames 0 and 1 "
              "need)", Int(0, none=True))
    reobserve_radius_px: float | None = setting(
        None, "lost map features are searched again within this radius of their projection, pixels (0: off; "
              "null: 15 for SIFT, off for binary descriptors)", Real(0.0, 1e4, none=True))
    keyframe_parallax_deg: float | None = setting(
        None, "median parallax to the last keyframe that makes a keyframe, degrees (null: a quarter of "
              "mapping.min_feature_parallax_deg, more for a frame localised on over 150 map features, at most "
              "the whole of it)", Real(0.0, 90.0, lo_open=True, hi_open=True, none=True))
    loop_train_frames: int = setting(20, "frames whose descriptors train the place vocabulary", Int(1))
    loop_learn_lag: int = setting(20, "frames the vocabulary's k-means runs in the background before it is "
                                      "joined", Int(0))
    smooth_passes: int = setting(5, "relinearisation passes of smoothing at most", Int(1))
    robust_smoothing: bool = setting(True, "smoothing drops the measurements that fail the gates at the "
                                           "smoothed estimate and smooths again", Flag())
    noise_estimate: NoiseEstimate = setting(
        NoiseEstimate.TRACK_LENGTH, "robust smoothing's Zm gate at the noise the residuals show: track_length, "
                                    "global or off", OneOf(NoiseEstimate))
    wide_baseline: bool = setting(False, "after the run, place the frames still lost with affine-simulated "
                                         "features (ASIFT; seconds per frame)", Flag())

    # -- tuning constants (not settings) ----------------------------------------------
    #: Largest tilt ASIFT simulates (2: slants up to 60 degrees, 10 views).
    wide_baseline_max_tilt: ClassVar[float] = 2.0
    #: Known frames, nearest in frame order, each lost frame is matched against.
    wide_baseline_references: ClassVar[int] = 2
    #: Known map features a wide-baseline frame needs on its joined tracks to be localised.
    wide_baseline_min_map_features: ClassVar[int] = 6

    def __post_init__(self) -> None:
        check_section(self, "experimental")


#: The sections of :class:`SlamConfig`, in the order they are printed, and their classes.
SECTIONS: dict[str, type] = {"frontend": FrontEndConfig, "tracking": TrackingConfig, "mapping": MappingConfig,
                             "keyframes": KeyframeConfig, "loops": LoopConfig, "smoothing": SmoothingConfig,
                             "runtime": RuntimeConfig, "experimental": ExperimentalConfig}


@dataclass(frozen=True)
class SlamConfig:
    """Every setting of a run, by part of the system: ``SlamConfig()`` is what
    ``eifslam run`` uses without options.

    The filter's options (:class:`~eifslam.estimation.options.FilterConfig`) are built
    from it (:attr:`filter`).
    """

    frontend: FrontEndConfig = field(default_factory=FrontEndConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    loops: LoopConfig = field(default_factory=LoopConfig)
    smoothing: SmoothingConfig = field(default_factory=SmoothingConfig)
    runtime: RuntimeConfig = field(default_factory=RuntimeConfig)
    experimental: ExperimentalConfig = field(default_factory=ExperimentalConfig)

    def __post_init__(self) -> None:
        for name, cls in SECTIONS.items():
            if not isinstance(getattr(self, name), cls):
                raise ConfigError(f"configuration section {name} must be a {cls.__name__}")

    @functools.cached_property
    def filter(self) -> FilterConfig:
        """The information filter's options: its ``Zm`` gate from ``experimental``, the
        estimation layer's defaults otherwise."""
        ex = self.experimental
        return FilterConfig(gate_chi2=ex.zm_gate_chi2)

    @property
    def float_descriptors(self) -> bool:
        """Whether the detector gives float descriptors (SIFT) rather than binary ones."""
        return self.frontend.detector.float_descriptors

    @property
    def zm_sigma_px(self) -> float:
        """Standard deviation of ``Zm``, pixels: the front end's keypoint noise
        ``frontend.sigma_px`` (the one its relative poses' covariances are computed with)."""
        return float(self.frontend.sigma_px)

    @property
    def reobserve_px(self) -> float:
        """Re-observation radius, pixels (0: off): ``experimental.reobserve_radius_px``, or by
        default 15 px for float descriptors (SIFT) and off for binary ones, whose ratio
        test lets wrong re-observations in."""
        v = self.experimental.reobserve_radius_px
        if v is not None:
            return float(v)
        return 15.0 if self.float_descriptors else 0.0

    def keyframe_parallax(self, n_map_features: int = 0) -> float:
        """The parallax that makes a keyframe of a frame localised on ``n_map_features`` map
        features, degrees: ``experimental.keyframe_parallax_deg`` when set; by default
        ``mapping.min_feature_parallax_deg / KeyframeConfig.per_triangulation`` times
        ``n_map_features / KeyframeConfig.redundant_features``, that factor clipped to
        ``[1, per_triangulation]``.

        Why it grows with the map features: a frame's pose error comes from its pixel
        noise and from its features' own error, each divided by about the number of
        features; a feature's error grows with the spacing of the keyframes that measured
        it. With many features the map fixes the frame's pose well even from features seen
        by fewer keyframes, so the keyframes can be spaced in proportion (on the loop world,
        about 800 map features per frame, every second frame is a keyframe instead of
        every frame, and its ATE does not change). The spacing never exceeds the
        triangulation parallax itself, so that a track first seen at one keyframe can be
        triangulated at the next."""
        v = self.experimental.keyframe_parallax_deg
        if v is not None:
            return float(v)
        k = KeyframeConfig
        factor = min(max(n_map_features / k.redundant_features, 1.0), float(k.per_triangulation))
        return float(self.mapping.min_feature_parallax_deg / k.per_triangulation * factor)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Every setting as plain values (enums as their strings): what :meth:`from_dict`
        takes back, and safe to write as JSON or YAML."""
        return {name: {f.name: plain(getattr(getattr(self, name), f.name)) for f in dataclasses.fields(cls)}
                for name, cls in SECTIONS.items()}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "SlamConfig":
        """Build from ``{"frontend": {...}, "tracking": {...}, ...}``: any subset of the
        sections and of their keys; the rest keeps its default."""
        unknown = sorted(set(values) - set(SECTIONS))
        if unknown:
            raise ConfigError(f"unknown configuration section {unknown[0]!r} (known: {', '.join(SECTIONS)})")
        out = {}
        for name, section in SECTIONS.items():
            given = values.get(name) or {}
            if not isinstance(given, Mapping):
                raise ConfigError(f"configuration section {name} must map keys to values, got {given!r}")
            out[name] = build_section(section, given, name)
        return cls(**out)

    def replace(self, **sections: Mapping[str, Any]) -> "SlamConfig":
        """A copy with some keys of some sections changed, e.g. ``replace(smoothing={"mode": "filter"})``."""
        d = self.to_dict()
        for name, vals in sections.items():
            if name not in d:
                raise ConfigError(f"unknown configuration section {name!r} (known: {', '.join(SECTIONS)})")
            d[name] = d[name] | dict(vals)
        return SlamConfig.from_dict(d)

    def help_lines(self) -> dict[str, dict[str, str]]:
        """One line of help per setting, by section: meaning, unit and default."""
        from ..settings import help_line

        return {name: {f.name: help_line(f) for f in dataclasses.fields(cls)} for name, cls in SECTIONS.items()}


def setting_count() -> tuple[int, int]:
    """How many settings :class:`SlamConfig` has: (all, outside ``experimental``)."""
    n = {name: len(dataclasses.fields(cls)) for name, cls in SECTIONS.items()}
    return sum(n.values()), sum(v for k, v in n.items() if k != "experimental")


__all__ = ["SlamConfig", "Mode", "SECTIONS", "TrackingConfig", "MappingConfig", "KeyframeConfig", "LoopConfig",
           "SmoothingConfig", "RuntimeConfig", "ExperimentalConfig", "setting_count"]
