"""Front-end configuration: one typed, frozen dataclass, validated on construction.

Pure Python (no OpenCV): the availability of a detector in the installed OpenCV is
checked when the detector is created (:mod:`eifslam.frontend.features`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Mapping

from ..errors import ConfigError
from ..estimation.options import Choice

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
RANSAC_METHODS = ("usac", "magsac", "ransac")


@dataclass(frozen=True)
class FrontEndConfig:
    """Parameters of the front end (features, split, matching, relative pose, uncertainty).

    Every value is checked in ``__post_init__``; a bad value raises
    :class:`~eifslam.errors.ConfigError` naming the key. Build from a mapping with
    :meth:`from_dict`, which also rejects unknown keys.

    Attributes
    ----------
    detector : Detector or {"sift", "orb", "akaze"}
        Feature detector/descriptor (stored as a :class:`Detector`). AKAZE needs an OpenCV build that ships it (the contrib wheel does).
    max_features : int
        Cap on keypoints per image (the strongest are kept). 2000: the system's choice,
        measured on the shared data sets (docs/system.md); 1000 already gives the same
        ZR/ZT accuracy on kitti-seq1 (1226x370) in less time, but fewer map features.
    sift_octave_layers : int
        SIFT scales per octave (3, OpenCV's default; 2 is ~10-25% faster with the same
        relative-pose accuracy on kitti-seq1 but tracks fewer features).
    sift_contrast_threshold : float > 0
        SIFT's contrast threshold (OpenCV's ``contrastThreshold``, 0.04 by default; OpenCV
        divides it by ``sift_octave_layers``): weaker extrema are dropped.
    detect_scale : float in (0, 1]
        Images are resized by this factor (``INTER_AREA``) before detection and the
        keypoints scaled back to full-resolution pixels (1: detect at full resolution).
        Colours and the Laplacian sign are taken from the full-resolution image.
    color_order : {"bgr", "rgb"}
        Channel order of 3-channel input images (OpenCV's ``imread`` gives BGR).
    map_fraction : float in [0, 1]
        Fraction of new tracks assigned to the map set ``Ωm``; the rest go to ``Ωp``
        (0.5, measured: docs/split_study.md; the paper kept 0.3).
    ratio : float in (0, 1]
        Lowe's ratio test threshold (best / second-best descriptor distance).
    mutual : bool
        Keep only mutual nearest neighbours.
    flann_trees : int >= 1
        Randomised k-d trees of the FLANN index (float descriptors: SIFT).
    flann_checks : int >= 1
        Leaves FLANN visits per query (more: closer to exact nearest neighbours, slower).
    match_window : int >= 1
        A new frame is matched against this many previous frames (1 = previous only; 3
        by default); older frames only see keypoints still unmatched, to recover tracks
        lost for a frame.
    ransac_threshold_px : float > 0
        Epipolar (Sampson) inlier threshold of the essential-matrix RANSAC, pixels.
    ransac_confidence : float in (0, 1)
        RANSAC confidence (0.9999). OpenCV sets the number of iterations from the best
        inlier ratio found so far: at 0.999 a wrong model with 90% inliers stopped USAC
        after about 8 samples on strecha-castle-p30's first pair (46° apart), where the
        right one has 99% (docs/frontend.md).
    ransac_method : {"usac", "magsac", "ransac"}
        OpenCV robust estimator: ``USAC_DEFAULT`` (with local optimisation; ~20x faster
        than the classic ``RANSAC`` here and finds more inliers), ``USAC_MAGSAC`` or
        ``RANSAC``.
    min_matches : int >= 5
        Fewer epipolar inliers than this between two frames: the pair is not used to
        extend tracks (``FrameResult.ok`` is False).
    min_inliers : int >= 5
        Minimum ``Ωp`` inliers for a relative-pose measurement.
    min_common : int >= 5
        Minimum ``Ωp`` tracks common to the two frames before trying a relative pose.
    min_parallax_deg : float >= 0
        Minimum median parallax, degrees: the angle between the bearings of frame *i* and
        the bearings of frame *j* rotated by the estimated ``R_ij`` (triangulation angle).
    min_rotation_residual_deg : float >= 0
        Pure-rotation test, degrees: the median angle left after the best pure-rotation
        fit of the bearings must exceed this (about the noise level for a pure rotation or
        a repeated frame); below it the pair has "no parallax" whatever the solver says.
    refine_iterations : int >= 1
        Gauss-Newton iterations of that refinement.
    sigma_px : float > 0
        Standard deviation of image-point noise per coordinate, pixels.
    prefetch : int >= 0
        How many frames ahead :func:`eifslam.system.runner.run_sequence` decodes and
        detects in a worker thread while the current frame is matched and fused (a
        pipelined front end; the results are those of the sequential order). 0: no
        worker thread, everything in the calling thread.
    seed : int or None
        Seed of OpenCV's random generator, set to ``seed + frame_id`` when each frame is
        added (FLANN's randomised k-d trees and the RANSAC samplers draw from it), so
        that a run is repeatable and a resumed session continues exactly as the
        uninterrupted run; None leaves it alone. A different seed is a different run: on long
        sequences the results of runs differ by more than small configuration changes do.
    """

    # features
    detector: Detector = Detector.SIFT
    max_features: int = 2000
    sift_octave_layers: int = 3
    sift_contrast_threshold: float = 0.04
    detect_scale: float = 1.0
    color_order: str = "bgr"
    # split of tracks between relative poses (Ωp) and the map (Ωm)
    map_fraction: float = 0.5
    # association
    ratio: float = 0.8
    mutual: bool = True
    flann_trees: int = 4
    flann_checks: int = 48
    match_window: int = 3
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.9999
    ransac_method: str = "usac"
    min_matches: int = 15
    # relative pose
    min_inliers: int = 15
    min_common: int = 20
    min_parallax_deg: float = 0.5
    min_rotation_residual_deg: float = 0.1
    refine_iterations: int = 3
    # uncertainty
    sigma_px: float = 1.0
    # pipelining (the runner)
    prefetch: int = 2
    # repeatability
    seed: int | None = 0

    def __post_init__(self) -> None:
        def bad(key: str, msg: str) -> ConfigError:
            return ConfigError(f"front-end config '{key}': {msg}, got {getattr(self, key)!r}")

        try:
            object.__setattr__(self, "detector", Detector(self.detector))
        except ValueError:
            raise bad("detector", f"must be one of {DETECTORS}") from None
        if self.ransac_method not in RANSAC_METHODS:
            raise bad("ransac_method", f"must be one of {RANSAC_METHODS}")
        if self.color_order not in COLOR_ORDERS:
            raise bad("color_order", f"must be one of {COLOR_ORDERS}")
        ints = {
            "max_features": 10,
            "sift_octave_layers": 1,
            "match_window": 1,
            "min_matches": 5,
            "min_inliers": 5,
            "min_common": 5,
            "refine_iterations": 1,
            "flann_trees": 1,
            "flann_checks": 1,
            "prefetch": 0,
        }
        for key, lo in ints.items():
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise bad(key, f"must be an integer >= {lo}")
        for key in ("mutual",):
            if not isinstance(getattr(self, key), bool):
                raise bad(key, "must be a bool")
        checks = {
            "map_fraction": lambda v: 0.0 <= v <= 1.0,
            "ratio": lambda v: 0.0 < v <= 1.0,
            "ransac_threshold_px": lambda v: 0.0 < v < 1e3,
            "ransac_confidence": lambda v: 0.0 < v < 1.0,
            "min_parallax_deg": lambda v: 0.0 <= v < 90.0,
            "min_rotation_residual_deg": lambda v: 0.0 <= v < 90.0,
            "sigma_px": lambda v: 0.0 < v < 1e3,
            "sift_contrast_threshold": lambda v: 0.0 < v < 1.0,
            "detect_scale": lambda v: 0.0 < v <= 1.0,
        }
        for key, ok in checks.items():
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not ok(float(v)):
                raise bad(key, "is out of range")

    @property
    def flann_search(self) -> bool:
        """Whether frames are matched with a FLANN index (approximate, built with OpenCV's
        seeded generator, serial): float descriptors; binary descriptors are searched
        exactly by brute force."""
        return self.detector.float_descriptors

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "FrontEndConfig":
        """Build a config from a mapping, rejecting unknown keys.

        Parameters
        ----------
        values : mapping
            Keys are attribute names of :class:`FrontEndConfig`.

        Raises
        ------
        ConfigError
            On an unknown key or an invalid value.
        """
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ConfigError(f"unknown front-end config key(s): {', '.join(unknown)}")
        return cls(**dict(values))
