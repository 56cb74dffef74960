"""Dark images: the gain normalisation before detection
(:func:`~eifslam.frontend.features.normalise_gain`).

Detection thresholds are absolute intensities, so without it a darker exposure of the same
scene loses most keypoints; a sparse ring of views of a dark object places 1 view.
"""

from __future__ import annotations


import cv2
import numpy as np
import pytest

from eifslam.frontend import FrontEndConfig
from eifslam.frontend.features import detect_features, make_detector, normalise_gain
from eifslam.geometry.camera import PinholeCamera

CAM = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)


@pytest.fixture(scope="module")
def image() -> np.ndarray:
    """A textured 640x480 image using the whole intensity range (scikit-image's brick
    photograph, tiled)."""
    from skimage import data

    tile = data.brick()
    img = np.tile(tile, (2, 2))[:480, :640]
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _dark(img: np.ndarray, factor: float) -> np.ndarray:
    return np.round(img.astype(np.float64) * factor).astype(np.uint8)


def test_normalise_gain_restores_a_darkened_image(image):
    """A darker exposure (brightest pixels below half the range) normalises to the bright
    image scaled to full range (up to the dark image's quantisation, amplified by the gain)."""
    ref = normalise_gain(image, min_gain=1.0).astype(float)
    for factor in (0.45, 0.3, 0.15):
        out = normalise_gain(_dark(image, factor))
        assert np.percentile(out, 99.99) >= 250
        err = np.abs(out.astype(float) - ref)
        assert 0.0 < np.mean(err) <= 0.5 / factor + 1.0


def test_normalise_gain_leaves_bright_and_black_images_alone(image):
    bright = image.copy()
    bright[:10, :] = 255  # more than 0.5% of the pixels at 255
    assert normalise_gain(bright) is bright
    dim = _dark(image, 0.6)  # within one stop of full range: kept exactly
    assert normalise_gain(dim) is dim
    assert normalise_gain(dim, min_gain=1.0) is not dim
    black = np.zeros((480, 640), np.uint8)
    assert normalise_gain(black) is black
    hot = _dark(image, 0.3)
    hot[0, :20] = 255  # a few hot pixels (under 0.01%) do not set the gain
    assert np.percentile(normalise_gain(hot), 99.99) >= 250


@pytest.mark.parametrize("detector,factor", [("sift", 0.25), ("orb", 0.15)])
def test_a_dark_exposure_keeps_the_keypoints_of_the_bright_one(image, detector, factor):
    """SIFT at 25% of the exposure found 226 keypoints of 1170 without the normalisation,
    ORB (which keeps its 2000 strongest) at 15% 739 of 2000; with it, as many as the
    bright image gives."""
    on = FrontEndConfig(detector=detector)
    n_bright = len(detect_features(image, CAM, on, make_detector(on)))
    dark = _dark(image, factor)
    gray = cv2.cvtColor(dark, cv2.COLOR_BGR2GRAY) if dark.ndim == 3 else dark
    n_dark_off = len(make_detector(on).detect(gray, None))  # OpenCV on the dark image as it is
    n_dark_on = len(detect_features(dark, CAM, on, make_detector(on)))
    assert n_bright >= 1000
    assert n_dark_off < 0.6 * n_bright  # what detection without the normalisation loses
    assert 0.85 * n_bright <= n_dark_on <= 1.15 * n_bright


@pytest.mark.data
def test_sparse_ring_of_a_dark_object_is_placed(tmp_path, shared_dataset):
    """Every third view of middlebury-templering (about 23 degrees apart), darkened to 30%:
    8 of 11 views are placed with the gain normalised (the same as the bright images;
    without it, 1: no map features)."""
    from eifslam.evaluation.outputs import write_outputs
    from eifslam.io import open_source
    from eifslam.system.config import SlamConfig
    from eifslam.system.runner import run_sequence

    src = shared_dataset("middlebury-templering")
    dst = tmp_path / "dark-ring"
    (dst / "images").mkdir(parents=True)
    (dst / "camera.yaml").write_text((src / "camera.yaml").read_text())
    gt = [line for line in (src / "groundtruth.tum").read_text().splitlines() if not line.startswith("#")]
    keep = list(range(0, 31, 3))
    lines = []
    for n, k in enumerate(keep):
        img = cv2.imread(str(src / "images" / f"{k:04d}.png"))
        cv2.imwrite(str(dst / "images" / f"{n:04d}.png"), _dark(img, 0.3))
        lines.append(" ".join([f"{n:.6f}"] + gt[k].split()[1:]))
    (dst / "groundtruth.tum").write_text("\n".join(lines) + "\n")
    (dst / "times.txt").write_text("".join(f"{n:.6f}\n" for n in range(len(keep))))

    config = SlamConfig().replace(smoothing={"mode": "filter"})
    seq = open_source(dst)
    run = run_sequence(seq, config, quiet=True)
    rep = write_outputs(run.slam, tmp_path / "out", run.seconds, seq.ground_truth(), html=False)
    assert rep["frames_tracked"] >= 7
    # placed where they are, not just placed: ATE within about 1% of the views' extent
    # (1.46 units), and not zero
    assert 1e-5 < rep["ate_rmse"] < 0.016
