"""Rendering the built-in scene: images agree with the ground truth; the folder is loadable."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from eifslam.cli.main import main  # noqa: E402
from eifslam.errors import ConfigError  # noqa: E402
from eifslam.sim.scene import make_scene, render_frame, render_scene, top_face_mask  # noqa: E402
from eifslam.sim.scene import render as render_module  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    return make_scene()


@pytest.fixture(scope="module")
def frames(scene):
    """Frames 0, 1 and the loop-closing pair (53, 0), with render times."""
    out, times = {}, []
    for k in (0, 1, 27, 28, 53):
        t0 = time.perf_counter()
        out[k] = render_frame(scene, k)
        times.append(time.perf_counter() - t0)
    print(f"\nrender_frame: {np.median(times[1:]) * 1e3:.0f} ms per 1024x768 frame (median)")
    return out


def _sift_matches(a, b):
    sift = cv2.SIFT_create()
    ka, da = sift.detectAndCompute(cv2.cvtColor(a, cv2.COLOR_BGR2GRAY), None)
    kb, db = sift.detectAndCompute(cv2.cvtColor(b, cv2.COLOR_BGR2GRAY), None)
    pairs = cv2.BFMatcher().knnMatch(da, db, k=2)
    good = [m for m, n in pairs if m.distance < 0.7 * n.distance]
    xa = np.array([ka[m.queryIdx].pt for m in good])
    xb = np.array([kb[m.trainIdx].pt for m in good])
    return len(ka), len(kb), xa, xb


def _relative(scene, i, j):
    """``R, t`` with ``X_j = R X_i + t`` (camera frames of frames i and j)."""
    Ri, Rj = scene.rotation_wc(i), scene.rotation_wc(j)
    return Rj.T @ Ri, Rj.T @ (scene.positions[i] - scene.positions[j])


def _epipolar_errors(scene, i, j, xi, xj):
    R, t = _relative(scene, i, j)
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    Ki = np.linalg.inv(scene.camera.K)
    F = Ki.T @ tx @ R @ Ki
    hi = np.column_stack([xi, np.ones(len(xi))])
    hj = np.column_stack([xj, np.ones(len(xj))])
    lines = hi @ F.T
    return np.abs(np.sum(lines * hj, 1)) / np.hypot(lines[:, 0], lines[:, 1])


def _distance_to_surfaces(scene, X):
    """(N,) distance of world points to the nearest textured face (inf if over none)."""
    best = np.full(len(X), np.inf)
    for f in scene.surfaces:
        d = X - f.origin
        s, t, h = d @ f.axis_u, d @ f.axis_v, np.abs(d @ f.normal)
        inside = (s > -0.002) & (s < f.size_u + 0.002) & (t > -0.002) & (t < f.size_v + 0.002)
        best = np.where(inside, np.minimum(best, h), best)
    return best


def test_frame_shape_dtype_and_determinism(scene, frames):
    img = frames[0]
    assert img.shape == (768, 1024, 3) and img.dtype == np.uint8
    assert np.array_equal(render_frame(scene, 0), img)
    assert img.std() > 30  # textured, not flat


def test_every_pixel_is_covered(scene, monkeypatch):
    monkeypatch.setattr(render_module, "BACKGROUND_BGR", (1, 254, 3))
    for k in (0, 20, 40):
        img = render_frame(scene, k)
        assert not np.any(np.all(img == (1, 254, 3), axis=2))


@pytest.mark.parametrize("pair", [(0, 1), (27, 28), (53, 0)])
def test_sift_matches_satisfy_ground_truth_epipolar_geometry(scene, frames, pair):
    i, j = pair
    na, nb, xi, xj = _sift_matches(frames[i], frames[j])
    assert min(na, nb) > 1500
    assert len(xi) > 500
    err = _epipolar_errors(scene, i, j, xi, xj)
    print(f"\nframes {i}->{j}: {na} keypoints, {len(xi)} matches, "
          f"median epipolar error {np.median(err):.3f} px")
    assert np.median(err) < 0.5
    assert np.mean(err < 1.0) > 0.9


def test_triangulated_matches_lie_on_the_scene_surfaces(scene, frames):
    _, _, x0, x1 = _sift_matches(frames[0], frames[1])
    K = scene.camera.K
    P = [K @ np.column_stack([scene.rotation_wc(k).T, -scene.rotation_wc(k).T @ scene.positions[k]])
         for k in (0, 1)]
    Xh = cv2.triangulatePoints(P[0], P[1], x0.T, x1.T)
    X = (Xh[:3] / Xh[3]).T
    near = np.linalg.norm(X - scene.positions[0], axis=1) < 2.5  # table and boxes
    err = _epipolar_errors(scene, 0, 1, x0, x1)
    X = X[near & (err < 1.0)]
    dist = _distance_to_surfaces(scene, X)
    assert len(X) > 300
    assert np.median(dist) < 0.003  # metres
    box = scene.boxes[scene.ratio_box_index]
    assert top_face_mask(X, box, 0.01).sum() >= 10  # features on the 0.80:1 top face


def test_noise_and_blur(scene, frames):
    clean = frames[0].astype(float)
    noisy = render_frame(scene, 0, noise_sigma=4.0, rng=np.random.default_rng(0)).astype(float)
    assert 3.5 < (noisy - clean).std() < 4.5
    blurred = render_frame(scene, 0, blur_sigma=1.5).astype(float)
    grad = lambda im: np.abs(np.diff(im, axis=1)).mean()  # noqa: E731
    assert grad(blurred) < 0.7 * grad(clean)
    with pytest.raises(ConfigError):
        render_frame(scene, 0, noise_sigma=-1.0)
    with pytest.raises(ConfigError):
        render_frame(scene, 54)


def test_render_scene_writes_a_loadable_folder(tmp_path):
    small = make_scene(n_frames=3, width=320, height=240)
    out = render_scene(small, tmp_path / "builtin")
    assert sorted(p.name for p in (out / "images").iterdir()) == ["000000.png", "000001.png",
                                                                  "000002.png"]
    img = cv2.imread(str(out / "images" / "000001.png"))
    assert img.shape == (240, 320, 3)
    from eifslam.io.folder import open_folder

    seq = open_folder(out)
    assert (seq.camera.width, seq.camera.height) == (320, 240)
    assert seq.camera.fx == pytest.approx(small.camera.fx)
    gt = seq.ground_truth()
    assert np.allclose(gt.positions, small.positions, atol=1e-8)
    assert np.allclose(np.abs(np.sum(gt.quats_wxyz * small.quats_wxyz, 1)), 1.0, atol=1e-8)
    assert np.allclose(gt.timestamps, small.timestamps)
    boxes = json.loads((out / "boxes.json").read_text())
    assert boxes["ratio_box_index"] == small.ratio_box_index
    assert np.allclose(boxes["boxes"][2]["corners"], small.boxes[2].corners)
    assert boxes["top_face_ratio"] == pytest.approx(0.8)


def test_render_command(tmp_path, capsys):
    rc = main(["render", "--out", str(tmp_path / "r"), "--frames", "2", "--width", "160",
               "--height", "120", "--noise", "1"])
    assert rc == 0
    assert len(list((tmp_path / "r" / "images").glob("*.png"))) == 2
    assert main(["render", "--out", str(tmp_path / "r"), "--blur", "-1"]) == 1
