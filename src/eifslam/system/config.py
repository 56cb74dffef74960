"""Typed configuration of the whole system, with key and range checking.

``SlamConfig`` groups the front end's, the filter's and the system's settings. Build it
from a nested mapping with :meth:`SlamConfig.from_dict`; an unknown key or an
out-of-range value raises :class:`~eifslam.errors.ConfigError` naming it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Mapping

from ..errors import ConfigError
from ..estimation.options import Choice, FilterConfig, NoiseEstimate, Recovery
from ..frontend import FrontEndConfig


class Mode(Choice):
    """What a run does after the last image (:meth:`Slam.finish <eifslam.system.slam.Slam.finish>`).

    A ``str`` enum: ``Mode("smooth")``, ``Mode.SMOOTH == "smooth"`` and configs given as
    plain strings all work.
    """

    FILTER = "filter"  #: the filter's estimate
    SMOOTH = "smooth"  #: relinearise every stored measurement and smooth (paper III-E)
    BA = "ba"  #: full bundle adjustment of every track


@dataclass(frozen=True)
class SystemConfig:
    """Settings of the SLAM system (paper III-C, III-D, III-E).

    Attributes
    ----------
    mode : Mode or {"filter", "smooth", "ba"}
        Filter only, or filter + relinearise + smooth at the end of a run, or filter +
        full bundle adjustment of every track (:mod:`eifslam.baselines.bundle_adjustment`);
        :meth:`Slam.finish` does it. Stored as a :class:`Mode`.
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
    smoothing_noise_estimate : NoiseEstimate or {"track_length", "global", "off"} or bool
        Robust smoothing gates ``Zm`` against the pixel noise the measurements show rather
        than the stated ``sigma_px``: the gate is scaled by ``min(1, s**2)``, ``s`` the
        robust, degrees-of-freedom-corrected ratio of the residuals at the filter's
        estimate to ``sigma_px`` (:mod:`eifslam.estimation.noise`). On the shared sets
        ``s`` is 0.11-0.7 (the SIFT keypoints are far better than 1 px), and the 3-sigma
        gate at 1 px kept matches 10-20 true standard deviations off (docs/estimator.md,
        "Noise from the residuals"). ``"track_length"`` (default; ``true``): one ``s``
        per group of features with about as many ``Zm`` (2; 3-4; 5-8; ...), since long
        tracks drift more; ``"global"``: one ``s`` for every ``Zm``; ``"off"``
        (``false``): the gate at the stated noise.
    reobserve_radius_px : float or None
        Map features that frame-to-frame tracking lost are searched for again in each
        new frame within this many pixels of where the pose guess projects them
        (descriptor ratio test; 0 turns it off). This keeps map features alive across
        occlusions and revisits, which holds the scale. None (default): 15 px for float
        descriptors (SIFT, SURF), off for binary ones (ORB, AKAZE), whose ratio test let
        wrong re-observations in on kitti-seq1 (ATE 5.7 m with, 0.034 m without). See
        :meth:`SlamConfig.reobserve_px`.
    recovery : Recovery or {"incremental", "full"}
        Per-frame state recovery: exact over an active window with the rest marginalised
        (paper III-G, :mod:`eifslam.incremental`), or the full sparse solve.
    window : int
        Incremental recovery: frames without a measurement before a state leaves the
        window (larger than the front end's matching window, so that a track that
        reappears rarely touches a marginalised feature).
    relocalise_top : int
        When tracking is lost, the relative pose is tried with at most this many of the
        older poses that share the most descriptor matches with the frame.
    min_map_features : int
        Known map features a frame must see before its pose is localised on (or refined
        against) the map alone.
    agree_rotation_deg : float
        A map-refined pose agrees with the relative-pose guess when they differ by at
        most this rotation, degrees, ...
    agree_direction_deg : float
        ... their step directions from the reference pose by at most this angle, degrees,
        and at least half of the known features fit the refined pose.
    map_inlier_fraction : float in (0, 1]
        A map-refined pose with at least this fraction of inliers is a trusted
        linearisation point (and the ``ZR``/``ZT`` is gated against it).
    contradiction_ratio : float >= 1
        The map contradicts a relative pose when the refined pose's inlier fraction
        exceeds this multiple of the relative-pose guess's; the ``ZR``/``ZT`` is then
        not fused.
    inlier_radius_px : float
        A known feature fits the relative-pose guess when it projects within this many
        pixels of its measurement (for ``contradiction_ratio``).
    keyframe_parallax_deg : float or None
        A frame becomes a keyframe once the median parallax of the map features it shares
        with the last keyframe reaches this angle, degrees. None (default): a quarter of
        the parallax a new map feature needs (``min_feature_parallax_deg``), so that a
        feature has been seen from about four keyframes by the time it can be
        triangulated. With the whole triangulation parallax between keyframes (2 deg) the
        map is built from too few views: kitti-07's filter ATE rose to 0.363 m and
        kitti-seq1's to 0.064 m (0.293 m and 0.030 m with a quarter).
    keyframe_min_tracked : float in (0, 1]
        ... or once it sees fewer than this fraction of the map features the last keyframe
        saw (the view is changing; the map must follow it). 0.5 was chosen on the first
        150 frames of 7scenes-redkitchen-a (52 keyframes, filter ATE 0.0196 m against
        0.0191 m with every frame a keyframe; 0.7 made 121 keyframes for 0.0190 m) and
        checked on the other shared sets (docs/realtime.md).
    keyframe_max_interval_s : float
        ... or once this many seconds have passed since the last keyframe (timestamps as
        given to :meth:`Slam.track`; frame indices when none are given, so that every
        frame is then a keyframe).
    loop_closure : bool
        Place recognition on the filter's frames, geometric verification and fusion of
        the loop's ``Zm`` (:mod:`eifslam.system.loops`); ``--loop-closure`` sets it True,
        ``--no-loop-closure`` False. On by default (docs/loop_closure.md): over the whole
        loop world it takes the ATE from 0.659 m to 0.014 m and on 7scenes-redkitchen-a
        (SIFT, smooth, seeds 0-4) to 0.039-0.042 m, and without a loop the estimate is
        exactly the one without it; the place queries cost a few ms a frame, a loop the
        estimate does not predict relinearises every stored measurement (1-2 s on
        7scenes, 10-20 s at the loop world's end).
    loop_words : int
        Visual words of the vocabulary learnt from the run's first frames.
    loop_train_frames : int
        Frames whose descriptors train the vocabulary (no loop is sought before).
    loop_learn_lag : int
        The vocabulary's k-means runs in a background thread while this many more filter
        frames arrive, and is joined then (no loop is sought before). The vocabulary and
        the frame it is joined at depend on the frames alone, never on the thread's
        timing. 20 (about 2 s of k-means under load) keeps the join from waiting on it;
        at 5 the join waited 1.5 s on 7scenes-redkitchen-a with ORB.
    loop_min_inliers : int
        Floor of the inlier counts the PnP and five-point checks require (the count itself
        comes from a binomial chance argument, :func:`~eifslam.frontend.loop_verification.min_inliers`).
    loop_false_alarm : float in (0, 1)
        Probability that wrong matches reach the required inlier count by chance, over
        every RANSAC hypothesis.
    loop_consistency : int
        A candidate place must come back in this many consecutive queries (DBoW/ORB-SLAM's
        temporal consistency) before it is verified.
    loop_smooth_passes : int
        A loop whose ``Zm`` the estimate does not predict (median normalised innovation
        above the 99% bound) is fused after moving the estimate along the loop
        (:func:`~eifslam.estimation.loop_correction.correct_loop`, the correction spread
        by distance travelled, as a pose graph would) and then relinearising every stored
        measurement there: at most this many Gauss-Newton passes
        (:func:`~eifslam.estimation.loop_correction.relinearise_all`). 0: every loop's
        ``Zm`` are fused at the current linearisation point (on the loop world this left
        1.4 deg of the 3.8 deg error and bent the old map).
    wide_baseline : bool
        After the run, match the frames still without a pose to their nearest known
        frames with affine-simulated features (ASIFT, ``cv2.AffineFeature``; seconds per
        frame, so offline only) and place them from those matches
        (:mod:`eifslam.frontend.wide`, docs/frontend.md). Needs the images again (the
        runner passes its sequence's). Off by default.
    wide_baseline_max_tilt : float in [1, 8]
        Largest tilt ASIFT simulates (2: slants up to 60 degrees, 10 views).
    wide_baseline_references : int >= 1
        Known frames, nearest in frame order, each lost frame is matched against.
    wide_baseline_min_map_features : int >= 4
        A frame placed by wide-baseline matching needs at least this many known map
        features on its joined tracks (it is localised on them, starting from the
        relative pose of the matches).
    blas_threads : int >= 1 or None
        Threads of the BLAS library (NumPy and SciPy's dense algebra) while
        :func:`~eifslam.system.runner.run_sequence` runs (1; None: the library's own
        setting). The dense algebra of a frame is small, and OpenBLAS's extra threads spin
        on the core the prefetch worker needs: on a 2-core machine 7scenes-redkitchen-a
        (SIFT, filter) took 64 s with OpenBLAS's default and 42 s with 1 thread, kitti-seq1
        13.9 s and 11.2 s (docs/realtime.md).
    opencv_threads : int >= 1, "auto" or None
        OpenCV's worker threads while :func:`~eifslam.system.runner.run_sequence` runs
        (None: OpenCV's own setting, one per core). ``"auto"``: 1 when detection runs in
        the prefetch worker and the tracking thread's descriptor search is FLANN's (float
        descriptors), which is serial: OpenCV's pool then
        only adds threads to the detection, which already has a core of its own, and they
        compete with the tracking thread (kitti-seq1, SIFT, filter: 7.6 s against 8.3 s,
        medians of 4 runs; 7scenes-redkitchen-a 33.0 s against 34.3 s). OpenCV's own
        setting otherwise: the brute-force Hamming search of ORB/AKAZE is parallel and is
        the tracking thread's largest stage (7scenes-redkitchen-a, ORB: 35.3 s with
        OpenCV's setting, 45.2 s with 1 thread). docs/realtime.md.
    """

    mode: Mode = Mode.SMOOTH
    smooth_passes: int = 5
    reference_candidates: int = 4
    relocalise_candidates: int = 30
    min_feature_parallax_deg: float = 2.0
    init_parallax_deg: float = 0.5
    scale_distance: float = 1.0
    recovery: Recovery = Recovery.INCREMENTAL
    window: int = 5
    relative_gate_chi2: float | None = 50.0
    robust_smoothing: bool = True
    smoothing_noise_estimate: NoiseEstimate = NoiseEstimate.TRACK_LENGTH
    reobserve_radius_px: float | None = None
    relocalise_top: int = 5
    min_map_features: int = 12
    agree_rotation_deg: float = 2.0
    agree_direction_deg: float = 10.0
    map_inlier_fraction: float = 0.7
    contradiction_ratio: float = 1.5
    inlier_radius_px: float = 4.0
    keyframe_parallax_deg: float | None = None
    keyframe_min_tracked: float = 0.5
    keyframe_max_interval_s: float = 1.0
    loop_closure: bool = True
    loop_words: int = 256
    loop_train_frames: int = 20
    loop_learn_lag: int = 20
    loop_min_inliers: int = 25
    loop_false_alarm: float = 1e-6
    loop_consistency: int = 3
    loop_smooth_passes: int = 2
    wide_baseline: bool = False
    wide_baseline_max_tilt: float = 2.0
    wide_baseline_references: int = 2
    wide_baseline_min_map_features: int = 6
    blas_threads: int | None = 1
    opencv_threads: int | str | None = "auto"

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "mode", Mode(self.mode))
        except ValueError:
            raise ConfigError(f"system.mode must be 'filter', 'smooth' or 'ba', got {self.mode!r}") from None
        for key in ("relocalise_top", "min_map_features"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"system.{key} must be an integer >= 1, got {v!r}")
        if not isinstance(self.loop_closure, bool):
            raise ConfigError(f"system.loop_closure must be true or false, got {self.loop_closure!r}")
        for key, lo in (("loop_words", 2), ("loop_train_frames", 1), ("loop_learn_lag", 0),
                        ("loop_min_inliers", 6), ("loop_consistency", 1), ("loop_smooth_passes", 0)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ConfigError(f"system.{key} must be an integer >= {lo}, got {v!r}")
        v = self.loop_false_alarm
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 < v < 1.0:
            raise ConfigError(f"system.loop_false_alarm must lie in (0, 1), got {v!r}")
        if not isinstance(self.wide_baseline, bool):
            raise ConfigError(f"system.wide_baseline must be true or false, got {self.wide_baseline!r}")
        v = self.wide_baseline_max_tilt
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 1.0 <= v <= 8.0:
            raise ConfigError(f"system.wide_baseline_max_tilt must lie in [1, 8], got {v!r}")
        v = self.wide_baseline_references
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ConfigError(f"system.wide_baseline_references must be an integer >= 1, got {v!r}")
        v = self.wide_baseline_min_map_features
        if isinstance(v, bool) or not isinstance(v, int) or v < 4:
            raise ConfigError(f"system.wide_baseline_min_map_features must be an integer >= 4, got {v!r}")
        v = self.blas_threads
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ConfigError(f"system.blas_threads must be an integer >= 1 or null, got {v!r}")
        v = self.opencv_threads
        if v is not None and v != "auto" and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ConfigError(f"system.opencv_threads must be an integer >= 1, 'auto' or null, got {v!r}")
        if self.keyframe_parallax_deg is not None:
            v = self.keyframe_parallax_deg
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 < v < 90.0:
                raise ConfigError(f"system.keyframe_parallax_deg must lie in (0, 90) or be None, got {v!r}")
        for key, lo, hi in (("agree_rotation_deg", 0.0, 180.0), ("agree_direction_deg", 0.0, 180.0),
                            ("map_inlier_fraction", 0.0, 1.0), ("inlier_radius_px", 0.0, 1e3),
                            ("keyframe_min_tracked", 0.0, 1.0), ("keyframe_max_interval_s", 0.0, 1e6)):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo < v <= hi:
                raise ConfigError(f"system.{key} must lie in ({lo:g}, {hi:g}], got {v!r}")
        v = self.contradiction_ratio
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 1.0 <= v < 1e3:
            raise ConfigError(f"system.contradiction_ratio must be >= 1, got {v!r}")
        for key in ("smooth_passes", "reference_candidates"):
            if int(getattr(self, key)) < 1:
                raise ConfigError(f"system.{key} must be at least 1")
        if self.relative_gate_chi2 is not None and not self.relative_gate_chi2 > 0:
            raise ConfigError("system.relative_gate_chi2 must be positive or None")
        object.__setattr__(self, "recovery", Recovery.parse(self.recovery, "system.recovery"))
        object.__setattr__(self, "smoothing_noise_estimate",
                           NoiseEstimate.parse(self.smoothing_noise_estimate, "system.smoothing_noise_estimate"))
        if int(self.window) < 1:
            raise ConfigError("system.window must be at least 1")
        if self.relocalise_candidates < 0:
            raise ConfigError("system.relocalise_candidates must be >= 0")
        if not 0.0 <= self.init_parallax_deg < 90.0:
            raise ConfigError("system.init_parallax_deg must be in [0, 90)")
        if self.reobserve_radius_px is not None and not self.reobserve_radius_px >= 0:
            raise ConfigError("system.reobserve_radius_px must be >= 0")
        for key in ("min_feature_parallax_deg", "scale_distance"):
            v = getattr(self, key)
            if not (isinstance(v, (int, float)) and v > 0):
                raise ConfigError(f"system.{key} must be a positive number, got {v!r}")


    @property
    def keyframe_parallax(self) -> float:
        """The parallax that makes a keyframe, degrees (``keyframe_parallax_deg`` or, by
        default, a quarter of ``min_feature_parallax_deg``)."""
        v = self.keyframe_parallax_deg
        return float(self.min_feature_parallax_deg / KEYFRAMES_PER_TRIANGULATION if v is None else v)

    @property
    def feature_parallax_deg(self) -> float:
        """The parallax a new map feature needs, degrees."""
        return float(self.min_feature_parallax_deg)


#: Keyframes per triangulation parallax (``SystemConfig.keyframe_parallax`` by default).
KEYFRAMES_PER_TRIANGULATION = 4

#: The ``Zm`` gate the system runs with (``SlamConfig().filter.gate_chi2``).
SYSTEM_GATE_CHI2 = 9.21


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
    """Front end, filter and system settings: ``SlamConfig()`` is what ``eifslam run``
    uses without options.

    The defaults are those of the three dataclasses, with one system choice:
    ``filter.gate_chi2`` is :data:`SYSTEM_GATE_CHI2` (9.21) here, where a bare
    :class:`~eifslam.estimation.filter.FilterConfig` does not gate.
    """

    frontend: FrontEndConfig = field(default_factory=FrontEndConfig)
    # the system gates Zm (the filter alone does not): 99% of chi-square with 2 DOF at
    # sigma_px (docs/system.md); FilterConfig's own default belongs to the estimation layer
    filter: FilterConfig = field(default_factory=lambda: FilterConfig(gate_chi2=SYSTEM_GATE_CHI2))
    system: SystemConfig = field(default_factory=SystemConfig)

    @property
    def float_descriptors(self) -> bool:
        """Whether the detector gives float descriptors (SIFT, SURF) rather than binary ones."""
        return self.frontend.detector.float_descriptors

    @property
    def zm_sigma_px(self) -> float:
        """Standard deviation of ``Zm``, pixels: the front end's keypoint noise
        ``frontend.sigma_px`` (the one its relative poses' covariances are computed with)."""
        return float(self.frontend.sigma_px)

    @property
    def reobserve_px(self) -> float:
        """Re-observation radius, pixels (0: off): ``system.reobserve_radius_px``, or by
        default 15 px for float descriptors (SIFT, SURF) and off for binary ones."""
        if self.system.reobserve_radius_px is not None:
            return float(self.system.reobserve_radius_px)
        return 15.0 if self.float_descriptors else 0.0

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Every setting as plain values (enums as their strings): what :meth:`from_dict`
        takes back, and safe to write as JSON or YAML."""
        def plain(v: Any) -> Any:
            return v.value if isinstance(v, Enum) else list(v) if isinstance(v, tuple) else v

        return {sec: {k: plain(v) for k, v in dataclasses.asdict(getattr(self, sec)).items()}
                for sec in ("frontend", "filter", "system")}

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
