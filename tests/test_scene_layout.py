"""Geometry and ground truth of the built-in scene (pure, no OpenCV)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from eifslam.errors import ConfigError
from eifslam.geometry.rotations import quat_to_rotmat
from eifslam.sim.scene import make_scene
from eifslam.sim.scene.layout import TABLE_SEMI_AXES


@pytest.fixture(scope="module")
def scene():
    return make_scene(n_frames=54, width=1024, height=768, hfov_deg=56.0, seed=0)


def test_pure_modules_do_not_import_cv2_or_matplotlib():
    code = (
        "import sys\n"
        "import eifslam.sim.scene, eifslam.sim.scene.layout, eifslam.sim.scene.boxes\n"
        "s = eifslam.sim.scene.make_scene()\n"
        "bad = [m for m in ('cv2', 'matplotlib') if m in sys.modules]\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_trajectory_shapes_and_timestamps(scene):
    assert scene.n_frames == 54
    assert scene.positions.shape == (54, 3)
    assert scene.quats_wxyz.shape == (54, 4)
    assert scene.timestamps.shape == (54,)
    assert np.all(np.diff(scene.timestamps) > 0)
    assert np.allclose(np.linalg.norm(scene.quats_wxyz, axis=1), 1.0)


def test_intrinsics_match_56_degree_hfov(scene):
    cam = scene.camera
    assert (cam.width, cam.height) == (1024, 768)
    assert cam.fx == pytest.approx(512.0 / np.tan(np.radians(28.0)), rel=1e-12)
    assert cam.fy == pytest.approx(cam.fx)
    assert cam.hfov_deg == pytest.approx(56.0, abs=1e-9)
    assert (cam.cx, cam.cy) == (511.5, 383.5)
    assert not cam.has_distortion


def test_ratio_box_is_080_and_others_are_not(scene):
    assert scene.box_ratio_true == pytest.approx(0.80, abs=1e-12)
    assert len(scene.boxes) == 3
    others = [b.top_ratio for i, b in enumerate(scene.boxes) if i != scene.ratio_box_index]
    assert all(abs(r - 0.8) > 0.05 for r in others)
    sizes = {b.size for b in scene.boxes}
    assert len(sizes) == 3  # different sizes
    yaws = [b.yaw for b in scene.boxes]
    assert len(set(np.round(np.degrees(yaws), 3))) == 3  # not exactly aligned


def test_box_corners_match_sizes_and_stand_on_the_table(scene):
    a, b = TABLE_SEMI_AXES
    for box in scene.boxes:
        c = box.corners
        w, l, h = box.size
        assert np.linalg.norm(c[1] - c[0]) == pytest.approx(w)
        assert np.linalg.norm(c[3] - c[0]) == pytest.approx(l)
        assert np.allclose(c[4:] - c[:4], [0, 0, h])
        assert np.allclose(c[:4, 2], 0.0)
        assert np.all((c[:, 0] / a) ** 2 + (c[:, 1] / b) ** 2 < 0.9)
        assert np.allclose(c.mean(0), box.center)


def _separated(p: np.ndarray, q: np.ndarray) -> bool:
    """Separating-axis test for two convex 2-D polygons."""
    for poly in (p, q):
        for i in range(len(poly)):
            e = poly[(i + 1) % len(poly)] - poly[i]
            n = np.array([-e[1], e[0]])
            if (p @ n).max() < (q @ n).min() or (q @ n).max() < (p @ n).min():
                return True
    return False


def test_boxes_do_not_overlap(scene):
    fp = [b.corners[:4, :2] for b in scene.boxes]
    for i in range(3):
        for j in range(i + 1, 3):
            assert _separated(fp[i], fp[j])


def test_all_boxes_in_view_in_every_frame(scene):
    corners = np.vstack([b.corners for b in scene.boxes])
    cam = scene.camera
    inside = []
    for k in range(scene.n_frames):
        uv, z = scene.project(k, corners)
        assert np.all(z > 0.5)
        inside.append(np.all((uv >= 0) & (uv <= [cam.width - 1, cam.height - 1])))
    assert np.mean(inside) >= 0.9


def test_camera_loops_round_the_table_looking_inward_and_down(scene):
    p = scene.positions
    assert np.ptp(p[:, 2]) < 0.05  # roughly constant height
    ang = np.unwrap(np.arctan2(p[:, 1], p[:, 0]))
    assert np.all(np.diff(ang) > 0)
    assert ang[-1] - ang[0] == pytest.approx(2 * np.pi * 53 / 54, abs=0.1)
    step = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert np.linalg.norm(p[-1] - p[0]) < 1.5 * step.max()  # the loop closes
    R = quat_to_rotmat(scene.quats_wxyz)
    fwd = R[:, :, 2]
    assert np.all(np.einsum("ij,ij->i", fwd[:, :2], -p[:, :2]) > 0)  # looking inward
    pitch = np.degrees(np.arcsin(-fwd[:, 2]))
    assert np.all((pitch > 10) & (pitch < 35))  # slightly downward
    assert np.allclose(R[:, 2, 0], 0.0, atol=1e-9)  # no roll: camera x stays horizontal


def test_surfaces_are_orthonormal_and_box_faces_face_outward(scene):
    for f in scene.surfaces:
        assert f.axis_u @ f.axis_v == pytest.approx(0.0, abs=1e-12)
        assert np.linalg.norm(f.normal) == pytest.approx(1.0)
    for box in scene.boxes:
        faces = [f for f in scene.surfaces if f.name.startswith(box.name + "/")]
        assert len(faces) == 5
        for f in faces:
            centre = f.corners.mean(0)
            assert f.normal @ (centre - box.center) > 0
    assert len({f.seed for f in scene.surfaces}) == len(scene.surfaces)  # distinct textures


def test_seed_changes_wobble_not_layout():
    a, b = make_scene(seed=0), make_scene(seed=1)
    assert np.allclose(a.boxes[0].corners, b.boxes[0].corners)
    assert not np.allclose(a.positions, b.positions)
    assert np.allclose(a.positions, make_scene(seed=0).positions)


@pytest.mark.parametrize("kw", [{"n_frames": 1}, {"width": 4}, {"hfov_deg": 200.0},
                                {"frame_interval": 0.0}])
def test_bad_arguments_raise(kw):
    with pytest.raises(ConfigError):
        make_scene(**kw)
