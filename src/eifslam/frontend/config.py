"""Front-end configuration: the ``frontend`` section of the settings, and the front end's
tuning constants.

Pure Python (no OpenCV): the availability of a detector in the installed OpenCV is
checked when the detector is created (:mod:`eifslam.frontend.features`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Mapping

from ..estimation.options import Choice
from ..settings import Int, OneOf, Real, build_section, check_section, setting

__all__ = ["FrontEndConfig", "Detector", "DETECTORS"]


class Detector(Choice):
    """Feature detector/descriptor (a ``str`` enum: ``"sift"`` and ``Detector.SIFT`` are equal)."""

    SIFT = "sift"
    ORB = "orb"
    AKAZE = "akaze"

    @property
    def float_descriptors(self) -> bool:
        """Whether its descriptors are floats (SIFT) rather than binary (ORB, AKAZE)."""
        return self is Detector.SIFT


DETECTORS = tuple(d.value for d in Detector)
COLOR_ORDERS = ("bgr", "rgb")


@dataclass(frozen=True)
class FrontEndConfig:
    """Settings of the front end (section ``frontend``): features, the split of tracks,
    the matching window, the pixel noise, repeatability.

    Each field declares its help and its check (:func:`~eifslam.settings.setting`); a bad
    value raises :class:`~eifslam.errors.ConfigError` naming ``frontend.key``. The class
    attributes below the fields are tuning constants, not settings.
    """

    detector: Detector = setting(Detector.SIFT, "feature detector and descriptor: sift, orb or akaze",
                                 OneOf(Detector))
    max_features: int = setting(2000, "keypoints kept per image, the strongest", Int(10))
    map_fraction: float = setting(0.5, "fraction of new tracks that become map features (the paper's Ωm; "
                                       "the rest give relative poses)", Real(0.0, 1.0))
    sigma_px: float = setting(1.0, "standard deviation of a keypoint's position per coordinate, pixels "
                                   "(relative poses' covariance and Zm noise)", Real(0.0, 1e3, lo_open=True))
    color_order: str = setting("bgr", "channel order of 3-channel images: bgr (OpenCV's imread) or rgb",
                               OneOf(COLOR_ORDERS))
    match_window: int = setting(3, "previous frames a new frame is matched against (older ones only for "
                                   "keypoints still unmatched)", Int(1))
    seed: int | None = setting(0, "seed of OpenCV's random draws, seed + frame id per frame (null: left alone)",
                               Int(-2**31, 2**31 - 1, none=True))

    # -- tuning constants (not settings) ----------------------------------------------
    #: SIFT scales per octave: OpenCV's default (2 is faster but tracks fewer features).
    sift_octave_layers: ClassVar[int] = 3
    #: SIFT's contrast threshold: OpenCV's default.
    sift_contrast_threshold: ClassVar[float] = 0.04
    #: Lowe's ratio test (best / second-best descriptor distance): Lowe's own choice.
    ratio: ClassVar[float] = 0.8
    #: Keep only mutual nearest neighbours (fewer wrong matches for little cost).
    mutual: ClassVar[bool] = True
    #: Randomised k-d trees of the FLANN index of float descriptors (the sets too large
    #: for an exact match, ``frontend.matching.EXACT_ROWS``).
    flann_trees: ClassVar[int] = 4
    #: Leaves FLANN visits per query: close to exact neighbours at a fraction of the cost.
    flann_checks: ClassVar[int] = 48
    #: Epipolar (Sampson) inlier threshold of the essential-matrix RANSAC, pixels: about
    #: the keypoint noise.
    ransac_threshold_px: ClassVar[float] = 1.0
    #: RANSAC confidence: at 0.999 USAC stopped on a wrong model with 90% inliers on a
    #: wide pair where the right one has 99%.
    ransac_confidence: ClassVar[float] = 0.9999
    #: OpenCV's robust estimator: USAC (with local optimisation) is much faster than the
    #: classic RANSAC here and finds more inliers.
    ransac_method: ClassVar[str] = "usac"
    #: Fewer epipolar inliers between two frames: the pair does not extend tracks.
    min_matches: ClassVar[int] = 15
    #: Fewest Ωp inliers of a relative-pose measurement.
    min_inliers: ClassVar[int] = 15
    #: Fewest Ωp tracks common to two frames before a relative pose is tried.
    min_common: ClassVar[int] = 20
    #: Least median parallax of a relative pose, degrees (triangulation angle).
    min_parallax_deg: ClassVar[float] = 0.5
    #: Pure-rotation test, degrees: about the noise level of a pure rotation.
    min_rotation_residual_deg: ClassVar[float] = 0.1
    #: Gauss-Newton iterations of the relative pose's refinement on the Sampson error.
    refine_iterations: ClassVar[int] = 3

    def __post_init__(self) -> None:
        check_section(self, "frontend")

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "FrontEndConfig":
        """Build from a mapping of field names, rejecting unknown keys
        (:class:`~eifslam.errors.ConfigError`)."""
        return build_section(cls, values, "frontend")
