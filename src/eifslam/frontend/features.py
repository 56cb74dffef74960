"""Keypoint detection and description with OpenCV, undistortion, colours, Laplacian sign.

The image is checked (:func:`check_image`), converted to grayscale, and the configured
detector (SIFT by default; ORB, AKAZE) finds at
most ``max_features`` keypoints. Keypoints leave this module undistorted (``uv``) and raw
(``uv_raw``, for colours).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from typing import Iterator

import cv2
import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from ..errors import ConfigError, ImageError
from .config import FrontEndConfig
from .matching import DescriptorIndex, ImageMotion
from .split import laplacian_sign

Array = NDArray[np.float64]

__all__ = ["AheadMatch", "Features", "check_image", "make_detector", "detect_features", "undistort_pixels",
           "image_noise", "run_contrast_threshold", "set_opencv_threads", "opencv_threads", "normalise_gain"]


@dataclass(frozen=True)
class AheadMatch:
    """Descriptor matches of a frame with the frame detected before it, computed ahead
    (in the prefetch worker) because they depend on the two frames' descriptors alone.

    Attributes
    ----------
    previous : (N2, D) ndarray
        The previous frame's descriptors (the very array: the front end uses the matches
        only when its previous frame holds this object).
    idx_new, idx_previous : (M,) int64
        Matched rows of this frame's and of the previous frame's descriptors
        (:meth:`~eifslam.frontend.matching.DescriptorMatcher.match`, all rows free).
    ms : float
        Time the matching (and its RANSAC) took, milliseconds.
    inliers : (M,) bool or None
        Which matches pass the epipolar RANSAC of the front end's config; None when it
        was not run (fewer matches than ``min_matches``).
    motion_previous : ImageMotion or None
        The previous frame's motion that predicted where to search (the very object: the
        front end uses the matches only when it holds this one for its previous frame).
    """

    previous: NDArray
    idx_new: NDArray[np.int64]
    idx_previous: NDArray[np.int64]
    ms: float = 0.0
    inliers: NDArray[np.bool_] | None = None
    motion_previous: ImageMotion | None = None


@dataclass(frozen=True)
class Features:
    """Keypoints of one image.

    Attributes
    ----------
    uv : (N, 2) float64
        Undistorted pixel coordinates.
    uv_raw : (N, 2) float64
        Pixel coordinates as detected (with the lens distortion).
    descriptors : (N, D) uint8 or float32
        Descriptors (binary for ORB/AKAZE, float for SIFT).
    scale_px : (N,) float64
        Keypoint scale (approximate Gaussian sigma), pixels.
    response : (N,) float64
        Detector response (larger is stronger).
    sign : (N,) int8
        Sign of the Laplacian at the keypoint scale (see :mod:`eifslam.frontend.split`).
    colors : (N, 3) uint8
        RGB colour at the raw keypoint.
    detect_ms : float
        Wall time of the detection and description, milliseconds (reported as the
        ``detect`` stage wherever the detection ran, e.g. in the runner's worker thread).
    ahead : AheadMatch or None
        Descriptor matches with the previous frame computed where the features were
        detected (:meth:`~eifslam.frontend.frontend.FrontEnd.match_ahead`), or None.
    index : DescriptorIndex or None
        The search index of ``descriptors`` built where the features were detected
        (:meth:`~eifslam.frontend.frontend.FrontEnd.match_ahead`), or None.
    motion : ImageMotion or None
        How the keypoints moved since the frame before (set when they are matched with it:
        :meth:`~eifslam.frontend.frontend.FrontEnd.match_ahead` or ``add_features``), to
        predict where they are in the next frames; None before.
    """

    uv: Array
    uv_raw: Array
    descriptors: NDArray
    scale_px: Array
    response: Array
    sign: NDArray[np.int8]
    colors: NDArray[np.uint8]
    detect_ms: float = 0.0
    ahead: AheadMatch | None = None
    index: DescriptorIndex | None = None
    motion: ImageMotion | None = None

    def __len__(self) -> int:
        return int(len(self.uv))


def check_image(image: object, camera: PinholeCamera) -> np.ndarray:
    """Validate an image and return it as a C-contiguous ``uint8`` array.

    Accepts ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` or ``(H, W, 4)`` arrays of ``uint8``,
    ``uint16`` (scaled by 1/257) or float in ``[0, 1]``, with ``H, W`` the camera's size.

    Raises
    ------
    ImageError
        On ``None``, a non-array, a wrong dtype, shape or size, or non-finite values.
    """
    if image is None:
        raise ImageError("image is None (unreadable file?)")
    if not isinstance(image, np.ndarray):
        raise ImageError(f"image must be a numpy array, got {type(image).__name__}")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise ImageError(f"image must be HxW or HxWx{{1,3,4}}, got shape {image.shape}")
    if image.shape[:2] != (camera.height, camera.width):
        raise ImageError(
            f"image is {image.shape[1]}x{image.shape[0]} but the camera is "
            f"{camera.width}x{camera.height}"
        )
    if image.dtype == np.uint8:
        out = image
    elif image.dtype == np.uint16:
        out = (image // 257).astype(np.uint8)
    elif np.issubdtype(image.dtype, np.floating):
        if not np.all(np.isfinite(image)):
            raise ImageError("image has non-finite values")
        out = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    else:
        raise ImageError(f"image dtype must be uint8, uint16 or float, got {image.dtype}")
    return np.ascontiguousarray(out)


def akaze_factory():
    """OpenCV's AKAZE constructor: ``cv2.AKAZE_create`` (OpenCV 4) or
    ``cv2.xfeatures2d.AKAZE_create`` (OpenCV 5's contrib wheel); None when neither exists."""
    factory = getattr(cv2, "AKAZE_create", None)
    return factory if factory is not None else getattr(getattr(cv2, "xfeatures2d", None), "AKAZE_create", None)


def make_detector(config: FrontEndConfig) -> "cv2.Feature2D":
    """The OpenCV detector/descriptor named by ``config.detector``.

    Raises
    ------
    ConfigError
        When the installed OpenCV does not provide it (AKAZE is absent from OpenCV 5's
        main wheel; the contrib wheel, ``opencv-contrib-python-headless``, has it).
    """
    n = config.max_features
    name = config.detector
    if name == "sift":
        return cv2.SIFT_create(nfeatures=n, nOctaveLayers=config.sift_octave_layers,
                               contrastThreshold=float(config.sift_contrast_threshold))
    if name == "orb":
        return cv2.ORB_create(nfeatures=n, fastThreshold=10)
    factory = akaze_factory()
    if factory is None:
        raise ConfigError(
            f"detector 'akaze' is not available in the installed OpenCV {cv2.__version__} "
            "(install opencv-contrib-python-headless, which has it)"
        )
    return factory(threshold=1e-4)


def undistort_pixels(uv_raw: Array, camera: PinholeCamera) -> Array:
    """Remove lens distortion from pixels ``(N, 2)``; returns undistorted pixels ``(N, 2)``."""
    uv_raw = np.asarray(uv_raw, np.float64).reshape(-1, 2)
    if not camera.has_distortion or len(uv_raw) == 0:
        return uv_raw.copy()
    K = camera.K
    dist = np.asarray(camera.distortion, np.float64)
    out = cv2.undistortPoints(uv_raw.reshape(-1, 1, 2), K, dist, P=K)
    return out.reshape(-1, 2).astype(np.float64)


def _gray_and_rgb(image: np.ndarray, color_order: str) -> tuple[np.ndarray, np.ndarray]:
    if image.ndim == 2 or image.shape[2] == 1:
        gray = image.reshape(image.shape[:2])
        return gray, gray[..., None]
    rgb = image[..., :3]
    if color_order == "bgr":
        rgb = rgb[..., ::-1]
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), rgb


GAIN_PERCENTILE = 99.99
"""Percentile of the grayscale image that :func:`normalise_gain` maps to 255."""

GAIN_MIN = 2.0
"""Smallest gain :func:`normalise_gain` applies: images whose brightest pixels reach half
the range (exposed within one stop of full) are left as they are."""


def normalise_gain(gray: np.ndarray, percentile: float = GAIN_PERCENTILE, min_gain: float = GAIN_MIN) -> np.ndarray:
    """Scale a dark ``uint8`` grayscale image so that its ``percentile`` becomes 255.

    Detection thresholds are absolute intensities (SIFT's contrast threshold on the
    image in ``[0, 1]``, FAST's intensity step), while a camera's gain or exposure
    scales every intensity: normalising the gain gives a dark image the keypoints of the
    same image well exposed. The percentile rather than the maximum, so that a few
    specular or hot pixels do not set the gain. Descriptors (SIFT's normalised
    gradients, ORB's comparisons) are unaffected by a gain.

    Only a gain of at least ``min_gain`` is applied: a normally exposed image keeps its
    pixels (and its keypoints) exactly; docs/frontend.md, "Dark images", measures why.

    Parameters
    ----------
    gray : (H, W) uint8
    percentile : float in (0, 100]
    min_gain : float >= 1

    Returns
    -------
    (H, W) uint8
        ``gray`` itself when the gain ``g = 255 / P`` is below ``min_gain`` (or the
        image is black), else ``round(gray * g)`` saturated at 255.
    """
    hist = np.bincount(gray.reshape(-1), minlength=256)
    level = int(np.searchsorted(np.cumsum(hist), percentile / 100.0 * gray.size))
    if level <= 0 or 255.0 / level < min_gain:
        return gray
    return cv2.convertScaleAbs(gray, alpha=255.0 / level)


def image_noise(gray: np.ndarray) -> float:
    """Standard deviation of the image noise, grey levels (Immerkaer 1996).

    The image is filtered with the difference of two Laplacians, which cancels every
    smooth structure up to second order; the mean absolute response of white noise of
    standard deviation ``s`` is ``6 s sqrt(2 / pi)``. Texture adds to it, so the figure is
    an upper bound of the noise on a textured image.

    Parameters
    ----------
    gray : (H, W) uint8, H, W >= 3.

    Returns
    -------
    float
        The estimated standard deviation, grey levels (0 for a smaller image).
    """
    if gray.shape[0] < 3 or gray.shape[1] < 3:
        return 0.0
    r = cv2.filter2D(gray.astype(np.float32), cv2.CV_32F, _NOISE_KERNEL)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2.0) / 6.0 * np.mean(np.abs(r)))


_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)

WEAK_TEXTURE_FRACTION = 0.25
"""A run whose first image gives SIFT fewer than this fraction of ``max_features`` at the
default contrast threshold is weakly textured (:func:`run_contrast_threshold`)."""


def run_contrast_threshold(image: np.ndarray, n_keypoints: int, camera: PinholeCamera,
                           config: FrontEndConfig) -> float:
    """SIFT's contrast threshold (OpenCV's ``contrastThreshold``, image in ``[0, 1]``) for a
    whole run, from its first image and the keypoints the default threshold found there.

    OpenCV's default (0.04: 3.4 grey levels per scale of the difference of Gaussians)
    throws away the extrema of a weakly textured scene (a living room of white walls keeps
    about 300 of 2000). When the first image keeps fewer than
    :data:`WEAK_TEXTURE_FRACTION` of ``max_features``, the threshold is lowered to where
    the per-scale threshold (the threshold over ``sift_octave_layers``) is half the image
    noise's standard deviation (:func:`image_noise`, at least the 8-bit rounding's
    :data:`QUANTISATION_NOISE`): the difference of Gaussians averages
    white noise down about twentyfold, so such an extremum still stands well out of the
    noise. The run keeps one threshold: deciding per image lowers it on the few blurred
    frames of a textured run and costs accuracy there (the weak keypoints of one frame are
    not found again in the next).

    Parameters
    ----------
    image : ndarray
        The run's first image (as for :func:`detect_features`).
    n_keypoints : int
        Keypoints the default threshold found on it.
    camera : PinholeCamera
    config : FrontEndConfig

    Returns
    -------
    float
        ``config.sift_contrast_threshold``, or the lower threshold from the noise.
    """
    default = float(config.sift_contrast_threshold)
    if n_keypoints >= WEAK_TEXTURE_FRACTION * config.max_features:
        return default
    gray = normalise_gain(_gray_and_rgb(check_image(image, camera), config.color_order)[0])
    noise = max(image_noise(gray), QUANTISATION_NOISE)
    return float(min(default, 0.5 * config.sift_octave_layers * noise / 255.0))


QUANTISATION_NOISE = 1.0 / np.sqrt(12.0)
"""Standard deviation of the rounding to 8 bits, grey levels: the noise floor of every image
(a rendered image without sensor noise still has it)."""


def detect_features(
    image: np.ndarray, camera: PinholeCamera, config: FrontEndConfig, detector: "cv2.Feature2D",
    contrast: float | None = None,
) -> Features:
    """Detect and describe keypoints of one image.

    Parameters
    ----------
    image : ndarray
        ``(H, W)`` grayscale or ``(H, W, 3|4)`` colour image (channel order per
        ``config.color_order``); see :func:`check_image`.
    camera : PinholeCamera
    config : FrontEndConfig
    detector : cv2.Feature2D
        From :func:`make_detector`.
    contrast : float, optional
        SIFT's contrast threshold to detect with (:func:`run_contrast_threshold`; default:
        the detector's own).

    Returns
    -------
    Features
        At most ``config.max_features`` keypoints (possibly zero, e.g. for a black image).

    Notes
    -----
    Pure apart from the detector object: the same image, camera and config give the same
    features. One OpenCV detector object should not be used by two threads at once
    (:meth:`eifslam.frontend.FrontEnd.detect` keeps one per thread).
    """
    t0 = time.perf_counter()
    img = check_image(image, camera)
    gray, rgb = _gray_and_rgb(img, config.color_order)
    gray = normalise_gain(gray)
    if contrast is not None and detector.getContrastThreshold() != contrast:
        detector.setContrastThreshold(float(contrast))
    kps, desc = detector.detectAndCompute(gray, None)
    if desc is None or len(kps) == 0:
        d = {"orb": 32, "akaze": 61}.get(str(config.detector), 128)
        dtype = np.uint8 if config.detector in ("orb", "akaze") else np.float32
        return Features(
            np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, d), dtype), np.zeros(0),
            np.zeros(0), np.zeros(0, np.int8), np.zeros((0, 3), np.uint8),
            (time.perf_counter() - t0) * 1e3,
        )
    uv_raw = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
    size = np.array([k.size for k in kps], np.float64)
    response = np.array([k.response for k in kps], np.float64)
    if len(kps) > config.max_features:  # AKAZE has no cap of its own
        keep = np.argsort(-response, kind="stable")[: config.max_features]
        uv_raw, size, response, desc = uv_raw[keep], size[keep], response[keep], desc[keep]
    scale = 0.5 * size  # OpenCV's size is a diameter of about 2 sigma (SIFT)
    sign = laplacian_sign(cv2.integral(gray, sdepth=cv2.CV_64F), uv_raw, scale)
    x = np.clip(np.rint(uv_raw[:, 0]).astype(int), 0, camera.width - 1)
    y = np.clip(np.rint(uv_raw[:, 1]).astype(int), 0, camera.height - 1)
    colors = rgb[y, x]
    if colors.shape[1] == 1:
        colors = np.repeat(colors, 3, axis=1)
    return Features(
        # without distortion the two are one array (neither is ever changed in place):
        # 16 bytes a keypoint of every stored frame
        uv=undistort_pixels(uv_raw, camera) if camera.has_distortion else uv_raw,
        uv_raw=uv_raw,
        descriptors=desc,
        scale_px=scale,
        response=response,
        sign=sign,
        colors=np.ascontiguousarray(colors, dtype=np.uint8),
        detect_ms=(time.perf_counter() - t0) * 1e3,
    )


def set_opencv_threads(n: int) -> None:
    """Set OpenCV's worker threads (``cv2.setNumThreads``); a process-wide setting."""
    cv2.setNumThreads(int(n))


@contextlib.contextmanager
def opencv_threads(n: int | None) -> Iterator[None]:
    """Hold OpenCV to ``n`` worker threads inside the block, then restore its setting
    (``None``: leave it as it is). Process-wide, like :func:`set_opencv_threads`."""
    if n is None:
        yield
        return
    before = cv2.getNumThreads()
    cv2.setNumThreads(int(n))
    try:
        yield
    finally:
        cv2.setNumThreads(before)
