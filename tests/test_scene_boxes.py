"""Known-answer tests of the box-ratio estimator on synthetic samples."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.errors import ConfigError
from eifslam.sim.scene import estimate_box_ratio, fit_rectangle, make_scene, top_face_mask


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def _top_samples(box, n, rng, noise=0.0):
    w, l, h = box.size
    q = rng.uniform([-w / 2, -l / 2], [w / 2, l / 2], size=(n, 2))
    q = np.column_stack([q, np.full(n, h / 2)])
    return q @ box.rotation.T + box.center + rng.normal(0.0, noise, size=(n, 3))


def test_dense_uniform_samples_give_080_within_1_percent(scene):
    rng = np.random.default_rng(0)
    box = scene.boxes[scene.ratio_box_index]
    ratio, n = estimate_box_ratio(_top_samples(box, 20000, rng), scene)
    assert n == 20000
    assert 0.792 < ratio < 0.808


@pytest.mark.parametrize("percentile", [0.0, 1.0, 5.0])
def test_ratio_does_not_depend_on_trimming_for_uniform_samples(scene, percentile):
    rng = np.random.default_rng(1)
    box = scene.boxes[scene.ratio_box_index]
    ratio, _ = estimate_box_ratio(_top_samples(box, 20000, rng), scene, percentile=percentile)
    assert 0.792 < ratio < 0.808


def test_sparse_samples_scatter_but_stay_unbiased(scene):
    rng = np.random.default_rng(2)
    box = scene.boxes[scene.ratio_box_index]
    r = np.array([estimate_box_ratio(_top_samples(box, 200, rng), scene)[0] for _ in range(40)])
    assert 0.78 < r.mean() < 0.82
    assert 0.003 < r.std() < 0.04


def test_noise_outliers_and_other_boxes(scene):
    rng = np.random.default_rng(3)
    box = scene.boxes[scene.ratio_box_index]
    good = _top_samples(box, 3000, rng, noise=0.003)
    elsewhere = rng.uniform([-1, -1, -0.1], [1, 1, 0.5], size=(3000, 3))
    elsewhere = elsewhere[~top_face_mask(elsewhere, box, 0.02)]
    others = np.vstack([_top_samples(b, 500, rng) for i, b in enumerate(scene.boxes)
                        if i != scene.ratio_box_index])
    ratio, n = estimate_box_ratio(np.vstack([good, elsewhere, others]), scene)
    assert n == 3000
    assert 0.79 < ratio < 0.81
    for i, b in enumerate(scene.boxes):
        if i != scene.ratio_box_index:
            r_i, n_i = estimate_box_ratio(others, scene, box_index=i)
            assert n_i == 500
            assert abs(r_i - b.top_ratio) < 0.03


def test_too_few_points_is_a_value_not_an_exception(scene):
    ratio, n = estimate_box_ratio(np.zeros((0, 3)), scene)
    assert n == 0 and np.isnan(ratio)


def test_fit_rectangle_recovers_pose_and_size():
    rng = np.random.default_rng(4)
    th = np.radians(33.0)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    pts = rng.uniform([-1.0, -0.3], [1.0, 0.3], size=(20000, 2)) @ R.T + [5.0, -2.0]
    fit = fit_rectangle(pts, percentile=1.0)
    assert fit.length == pytest.approx(2.0, rel=0.01)
    assert fit.width == pytest.approx(0.6, rel=0.01)
    assert fit.angle == pytest.approx(th, abs=np.radians(0.5))
    assert np.allclose(fit.center, [5.0, -2.0], atol=0.01)
    assert fit.n_points == 20000


@pytest.mark.parametrize("bad", [np.zeros((2, 2)), np.zeros((5, 3)), np.full((5, 2), np.nan)])
def test_fit_rectangle_rejects_bad_input(bad):
    with pytest.raises(ConfigError):
        fit_rectangle(bad)


def test_estimate_box_ratio_rejects_bad_arguments(scene):
    with pytest.raises(ConfigError):
        estimate_box_ratio(np.zeros((5, 3)), scene, tol=0.0)
    with pytest.raises(ConfigError):
        estimate_box_ratio(np.zeros((5, 3)), scene, box_index=7)
