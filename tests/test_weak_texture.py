"""Weak texture: a run whose first image is weakly textured detects SIFT at the contrast
threshold its noise allows (:func:`~eifslam.frontend.features.run_contrast_threshold`)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from eifslam.frontend import FrontEnd, FrontEndConfig
from eifslam.frontend.features import (QUANTISATION_NOISE, detect_features, image_noise, make_detector,
                                       run_contrast_threshold)
from eifslam.geometry.camera import PinholeCamera

CAM = PinholeCamera(500.0, 500.0, 319.5, 239.5, 640, 480)


@pytest.fixture(scope="module")
def texture() -> np.ndarray:
    """A textured 640x480 grayscale image over the whole range (scikit-image's bricks, tiled)."""
    from skimage import data

    img = np.tile(data.brick(), (2, 2))[:480, :640]
    return cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def _faint(texture: np.ndarray, seed: int) -> np.ndarray:
    """The texture at 12% of its contrast with 1 grey level of sensor noise."""
    rng = np.random.default_rng(seed)
    faint = np.clip(128.0 + 0.12 * (texture - 128.0) + rng.normal(0.0, 1.0, texture.shape), 0, 255)
    return faint.round().astype(np.uint8)


def test_image_noise_measures_white_noise_and_ignores_smooth_shading():
    rng = np.random.default_rng(0)
    for sigma in (1.0, 3.0, 8.0):
        img = np.clip(128.0 + rng.normal(0.0, sigma, (480, 640)), 0, 255).round().astype(np.uint8)
        assert 0.85 * sigma <= image_noise(img) <= 1.15 * sigma
    y, x = np.mgrid[0:480, 0:640]
    shading = (60.0 + 0.2 * x + 0.1 * y + 1e-4 * (x - 320.0) ** 2).astype(np.uint8)
    assert 0.0 <= image_noise(shading) < 0.3
    assert image_noise(np.zeros((2, 2), np.uint8)) == 0.0
    # a flat image: the threshold stops at the 8-bit rounding's noise
    cfg = FrontEndConfig(detector="sift")
    flat = run_contrast_threshold(np.full((480, 640), 7, np.uint8), 0, CAM, cfg)
    assert flat == pytest.approx(0.5 * cfg.sift_octave_layers * QUANTISATION_NOISE / 255.0)


def test_a_weakly_textured_run_keeps_the_lower_threshold_and_a_rich_one_the_default(texture):
    """At 12% of the contrast, OpenCV's default threshold keeps a few keypoints; a run that
    starts there detects many times more, on every later image too. A run that starts on a
    rich image keeps exactly the default's keypoints, also on a faint image later."""
    cfg = FrontEndConfig(detector="sift")
    faint = _faint(texture, 1)
    n_default = len(detect_features(faint, CAM, cfg, make_detector(cfg)))
    weak = FrontEnd(CAM, cfg)
    assert n_default < 200 and len(weak.detect(faint)) >= 3 * n_default
    later = _faint(texture, 2)
    assert len(weak.detect(later)) >= 3 * len(detect_features(later, CAM, cfg, make_detector(cfg)))
    rich = FrontEnd(CAM, cfg)
    a, b = rich.detect(texture), detect_features(texture, CAM, cfg, make_detector(cfg))
    np.testing.assert_array_equal(a.uv_raw, b.uv_raw)
    assert len(rich.detect(faint)) == n_default
    # the run's threshold survives a session
    back = FrontEnd(CAM, cfg)
    back.load_state_dict(weak.state_dict())
    np.testing.assert_array_equal(back.detect(later).uv_raw, weak.detect(later).uv_raw)


@pytest.mark.data
def test_the_world_frame_moves_on_when_its_tracks_end_before_a_baseline(shared_dataset):
    """ICL-NUIM's living room with 150 keypoints an image: the first frame's few tracks end
    before the camera has moved enough for a first baseline. The world frame moves on to the
    frame that lost them (the filter starts again) until a pair initialises the map, and the
    frames before are placed on it; with the first frame kept as the world frame for ever,
    one frame of the 200 is placed."""
    from eifslam.evaluation.metrics import evaluate
    from eifslam.io import Trajectory, open_source
    from eifslam.system.config import SlamConfig
    from eifslam.system.slam import Slam

    seq = open_source(shared_dataset("icl-nuim-lr-kt3"))
    cfg = SlamConfig().replace(frontend={"max_features": 150}, smoothing={"mode": "filter"})
    slam = Slam(seq.camera, cfg)
    for k in range(len(seq)):
        slam.track(seq.load(k), seq.frames[k].timestamp)
    world = slam.filter.layout.pose_ids[0]
    assert world > 0 and np.allclose(slam.filter.pose(world)[0], 0.0)  # frame 0 lost its role to a later one
    slam.finish()
    placed = [r for r in slam.results if r.position is not None]
    assert len(placed) >= 0.7 * len(seq)
    t, P, Q = slam.trajectory()
    ev = evaluate(Trajectory(t, P, Q), seq.ground_truth())
    assert 1e-4 < ev.ate_rmse < 0.06  # metres, over a 1.5 m walk; 0.022 when measured
