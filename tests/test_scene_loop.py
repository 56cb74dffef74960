"""The loop world (``eifslam render --scene loop``): exact ground truth, a closed path of
two laps, places that look alike on both laps and unlike elsewhere, a loadable folder."""

from __future__ import annotations

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")
pytest.importorskip("skimage")

from eifslam.cli.main import main  # noqa: E402
from eifslam.errors import ConfigError  # noqa: E402
from eifslam.io import open_source  # noqa: E402
from eifslam.sim.scene.loop import PATH_DISTANCE, make_loop_scene, path_length  # noqa: E402
from eifslam.sim.scene.photos import photo_texture, poster_cells  # noqa: E402
from eifslam.sim.scene.render import render_frame  # noqa: E402


@pytest.fixture(scope="module")
def small():
    """The default path and world at 320 x 240 pixels."""
    return make_loop_scene(width=320, height=240)


def _sift(img):
    grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return cv2.SIFT_create(1500).detectAndCompute(grey, None)


def _matches(a, b):
    (ka, da), (kb, db) = a, b
    good = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.75 * n.distance]
    xa = np.float32([ka[m.queryIdx].pt for m in good]).reshape(-1, 2)
    xb = np.float32([kb[m.trainIdx].pt for m in good]).reshape(-1, 2)
    return xa, xb


def _inliers(fa, fb):
    """Matches of two frames consistent with one epipolar geometry (RANSAC, 1 px)."""
    xa, xb = _matches(fa, fb)
    if len(xa) < 8:
        return 0
    _, mask = cv2.findFundamentalMat(xa, xb, cv2.FM_RANSAC, 1.0, 0.999)
    return 0 if mask is None else int(mask.sum())


def test_default_path_is_closed_with_two_laps_at_walking_speed():
    s = make_loop_scene()
    assert s.n_frames >= 1000 and s.camera.width == 640 and s.camera.height == 480
    step = np.linalg.norm(np.diff(s.positions, axis=0), axis=1)
    assert 0.06 < step.min() and step.max() < 0.13  # metres per frame
    # laps: the bearing of the camera seen from the block centre turns twice round
    bearing = np.unwrap(np.arctan2(s.positions[:, 1], s.positions[:, 0]))
    turns = (bearing[-1] - bearing[0] + (bearing[1] - bearing[0])) / (2 * np.pi)
    assert 1.98 < turns < 2.02
    # closed: one step past the last frame is the first one
    assert np.linalg.norm(s.positions[-1] - s.positions[0]) < 1.5 * step.max()
    # lap 2 passes each place within LAP_OFFSET (and the wobble) of lap 1
    half = s.n_frames // 2
    gap = np.linalg.norm(s.positions[:half] - s.positions[half:2 * half], axis=1)
    assert 0.0 < gap.max() < 0.4
    assert path_length() == pytest.approx(4 * (4.0 + 2.5) + 2 * np.pi * PATH_DISTANCE)
    # the camera always looks at the block (the optical axis points inwards)
    z_axis = np.stack([s.rotation_wc(k)[:, 2] for k in range(0, s.n_frames, 37)])
    inward = -s.positions[::37, :2] / np.linalg.norm(s.positions[::37, :2], axis=1, keepdims=True)
    assert np.all(np.sum(z_axis[:, :2] * inward, 1) > 0.3)


def _polygon_mask(scene, k, corners_w, shape):
    """Pixels inside the ground-truth projection of a planar quadrilateral."""
    uv, depth = scene.project(k, corners_w)
    assert np.all(depth > 0)
    mask = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(uv * 16).astype(np.int32), 1, cv2.LINE_8, 4)
    return mask.astype(bool)


def test_ground_truth_projects_a_poster_where_it_is_drawn():
    """Where a poster changes the image (rendered with and without it) is where the ground
    truth projects its four corners, to a pixel; the pose of another frame does not fit."""
    import dataclasses

    scene = make_loop_scene()  # 640 x 480
    k = 0
    face = next(f for f in scene.surfaces if f.name == "block0/2/poster")  # ahead at frame 0
    without = dataclasses.replace(scene, surfaces=[f for f in scene.surfaces if f is not face])
    drawn = np.any(render_frame(scene, k) != render_frame(without, k), axis=2)
    drawn = cv2.morphologyEx(drawn.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8)) > 0
    shape = drawn.shape
    assert drawn.sum() > 2000  # the poster is in view
    inside = _polygon_mask(scene, k, face.corners, shape)
    grown = cv2.dilate(inside.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    shrunk = cv2.erode(inside.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    assert np.mean(grown[drawn]) > 0.999  # drawn only where projected (within a pixel)
    assert 0.85 < np.mean(drawn[shrunk]) <= 1.0  # and all of it bar what a pillar hides
    moved = _polygon_mask(scene, k + 3, face.corners, shape)
    assert np.mean(moved[drawn]) < 0.9


def test_places_look_alike_on_both_laps_and_unlike_elsewhere(small):
    half = small.n_frames // 2
    feats = {k: _sift(render_frame(small, k)) for k in (40, 40 + half, 170, 300)}
    same = _inliers(feats[40], feats[40 + half])
    other = max(_inliers(feats[40], feats[170]), _inliers(feats[40], feats[300]))
    assert same > 150
    assert other < 0.3 * same


def test_posters_show_each_photo_cell_once(small):
    shown = [f.material for f in small.surfaces if f.material.startswith("poster:")]
    assert len(shown) == len(set(shown)) >= 12
    assert set(shown) <= {f"poster:{n}:{c}" for n, c in poster_cells()}
    with pytest.raises(ConfigError):
        photo_texture("poster:nothing:0", 8, 8, 0)


def test_render_loop_command_writes_a_loadable_folder(tmp_path):
    out = tmp_path / "loop"
    rc = main(["render", "--scene", "loop", "--frames", "5", "--width", "160", "--height", "120",
               "--noise", "1", "--out", str(out)])
    assert rc == 0
    seq = open_source(out)
    assert len(seq) == 5 and (seq.camera.width, seq.camera.height) == (160, 120)
    assert seq.load(4).shape[:2] == (120, 160)
    gt = seq.ground_truth()
    ref = make_loop_scene(n_frames=5, width=160, height=120)
    assert np.allclose(gt.positions, ref.positions, atol=1e-8)
    assert not (out / "boxes.json").exists()
    assert "loop world" in (out / "README.md").read_text()
    # --laps belongs to the loop scene only
    assert main(["render", "--laps", "3", "--out", str(tmp_path / "b")]) == 1


def test_loop_world_benchmark_drift_figures(tmp_path):
    """benchmarks.loop_world scores drift: none for the truth, the right amount for an
    estimate whose scale shrinks along the run (known answer)."""
    from benchmarks import loop_world as bench
    from eifslam.io.trajectory import write_tum

    s = make_loop_scene(n_frames=400)
    write_tum(tmp_path / "gt.tum", s.timestamps, s.positions, s.quats_wxyz)
    write_tum(tmp_path / "same.tum", s.timestamps, s.positions, s.quats_wxyz)
    d = bench.drift_figures(tmp_path / "same.tum", tmp_path / "gt.tum")
    assert d["end_lap1_error_m"] < 1e-6 and d["end_lap2_error_m"] < 1e-6
    np.testing.assert_allclose(d["lap_gap"], d["lap_gap_true"], atol=1e-6)
    # each step 0.1% shorter than the last: positions drift towards where the run started
    steps = np.diff(s.positions, axis=0) * (0.999 ** np.arange(399))[:, None]
    P = np.vstack([s.positions[:1], s.positions[0] + np.cumsum(steps, axis=0)])
    write_tum(tmp_path / "drift.tum", s.timestamps, P, s.quats_wxyz)
    d = bench.drift_figures(tmp_path / "drift.tum", tmp_path / "gt.tum")
    assert 0.5 < d["end_lap1_error_m"] < d["end_lap2_error_m"] < 5.0
    assert d["lap_gap_median_m"] > 2 * d["lap_gap_true_max_m"]
