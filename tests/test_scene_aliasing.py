"""The aliasing scene (``eifslam render --scene aliasing``): a loadable folder with exact
ground truth, a path that comes back to no place before its last part, the same
photograph on several walls, and ``same_place`` telling a wall from its copies."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.sim.scene.aliasing import PANELS, AliasingScene, make_aliasing_scene
from eifslam.sim.scene.places import same_place, view_overlap


@pytest.fixture(scope="module")
def scene() -> AliasingScene:
    return make_aliasing_scene()


def _facing(scene, name, last=None):
    """The frame that sees surface ``name``'s centre nearest the image centre, from in
    front (optical axis within 25 degrees of the surface's normal), among the frames
    before ``last`` (default: all)."""
    face = next(f for f in scene.surfaces if f.name == name)
    centre = face.corners.mean(axis=0)
    best, best_d = -1, np.inf
    for k in range(scene.n_frames if last is None else last):
        uv, z = scene.project(k, centre[None])
        if z[0] > 0 and scene.rotation_wc(k)[:, 2] @ face.normal < -np.cos(np.radians(25)):
            d = np.hypot(uv[0, 0] - scene.camera.cx, uv[0, 1] - scene.camera.cy)
            if d < best_d:
                best, best_d = k, d
    return best


def test_default_run_is_one_lap_and_a_little_more_at_walking_speed(scene):
    assert scene.n_frames == 400 and (scene.camera.width, scene.camera.height) == (640, 480)
    assert len(scene.positions) == len(scene.quats_wxyz) == len(scene.timestamps) == 400
    np.testing.assert_allclose(np.diff(scene.timestamps), 0.1)
    step = np.linalg.norm(np.diff(scene.positions, axis=0), axis=1)
    assert 0.08 < step.min() and step.max() < 0.15  # metres per frame
    bearing = np.unwrap(np.arctan2(scene.positions[:, 1], scene.positions[:, 0]))
    turns = (bearing[-1] - bearing[0]) / (2 * np.pi)
    assert 1.05 < turns < 1.2
    assert 0 < scene.last_part_start < scene.revisit_start < scene.n_frames
    assert 0.7 * scene.n_frames < scene.last_part_start


def test_path_comes_back_to_no_place_before_its_last_part(scene):
    P = scene.positions
    last = scene.last_part_start
    step = np.linalg.norm(np.diff(P, axis=0), axis=1).mean()
    dist = np.linalg.norm(P[:last, None] - P[None, :last], axis=2)
    along = np.abs(np.arange(last)[:, None] - np.arange(last)[None]) * step  # metres of path
    assert dist[along > 8.0].min() > 3.0
    # ... and the last part does come back: from revisit_start on, every frame passes
    # within 0.3 m of one of the first frames
    back = np.linalg.norm(P[scene.revisit_start:, None] - P[None, :60], axis=2).min(axis=1)
    assert back.max() < 0.3
    # by the same-place rule: before the last part, views meet only along one side of the
    # block (its corners); the last part meets the start
    frames = range(0, scene.n_frames, 8)
    meet = [(i, j) for i in frames for j in frames if i < j and same_place(scene, i, j)]
    early = [j - i for i, j in meet if j < last]
    assert max(early) * step < 11.0
    assert any(i < 40 and j >= last for i, j in meet)


def test_the_same_photograph_hangs_on_walls_facing_different_ways_and_the_same_way(scene):
    walls = scene.photo_walls
    faces = {f.name: f for f in scene.surfaces}
    n_designs = len({d for side in PANELS for d in side})
    assert len(walls) == n_designs  # one photograph per design, none shared by two designs
    most = max(walls.values(), key=len)
    assert len(most) >= 3
    normals = np.array([faces[n].normal for n in most])
    centres = np.array([faces[n].corners.mean(axis=0) for n in most])
    assert len({tuple(np.round(v, 6)) for v in normals}) >= 2  # facing different ways
    same_way = [(a, b) for a in range(len(most)) for b in range(a + 1, len(most))
                if normals[a] @ normals[b] > 0.999]
    assert any(np.linalg.norm(centres[a] - centres[b]) > 4.0 for a, b in same_way)
    # the panels around the copies are identical too (wall texture and tint)
    wall_of = {n: faces[n.rsplit("/", 1)[0]] for n in most}
    assert len({(w.seed, w.shade[0] / max(w.shade)) for w in wall_of.values()}) >= 1
    assert len({w.seed for w in wall_of.values()}) == 1
    # photographs of the unique start panels hang once
    assert sum(len(v) == 1 for v in walls.values()) >= 2


def test_same_place_tells_a_wall_from_its_copies(scene):
    copies = [f.name for f in scene.surfaces
              if f.kind == "poster" and f.name.endswith(":A/poster")]
    assert len(copies) == 3
    views = [_facing(scene, n, scene.last_part_start) for n in copies]
    assert len(set(views)) == 3
    for a in range(3):
        k = views[a]
        assert same_place(scene, k, k + 3)  # the same wall, a step later
        assert not same_place(scene, k, k + 60)  # a wall farther on
        for b in range(a + 1, 3):
            assert not same_place(scene, k, views[b])
            assert view_overlap(scene, k, views[b]) < 0.1  # a little ground past a corner
    # the start and its revisit see the same place
    start = _facing(scene, next(f.name for f in scene.surfaces if f.name.endswith(":U1/poster")))
    lap = int(np.argmin(np.linalg.norm(scene.positions[scene.revisit_start:] - scene.positions[start],
                                       axis=1))) + scene.revisit_start
    assert same_place(scene, start, lap) and same_place(scene, lap, start)


def test_copies_look_alike_to_sift():
    """The aliases are hard: copies of panel A pass the epipolar check with a good share of
    the inliers of the true loop (the start and its revisit), other places with few."""
    cv2 = pytest.importorskip("cv2")
    pytest.importorskip("skimage")
    from eifslam.sim.scene.render import render_frame

    s = make_aliasing_scene(width=320, height=240)
    copies = [f.name for f in s.surfaces if f.kind == "poster" and f.name.endswith(":A/poster")]
    k0, k1, k2 = (_facing(s, n, s.last_part_start) for n in copies)
    start = _facing(s, next(f.name for f in s.surfaces if f.name.endswith(":U1/poster")), 60)
    lap = start + int(np.argmin(np.linalg.norm(s.positions[start + 1:] - s.positions[start], axis=1))) + 1
    assert lap >= s.revisit_start
    sift = cv2.SIFT_create(1500)

    def feats(k):
        return sift.detectAndCompute(cv2.cvtColor(render_frame(s, k), cv2.COLOR_BGR2GRAY), None)

    def inliers(a, b):
        (ka, da), (kb, db) = a, b
        good = [m for m, n in cv2.BFMatcher().knnMatch(da, db, k=2) if m.distance < 0.75 * n.distance]
        if len(good) < 8:
            return 0
        xa = np.float32([ka[m.queryIdx].pt for m in good])
        xb = np.float32([kb[m.trainIdx].pt for m in good])
        _, mask = cv2.findFundamentalMat(xa, xb, cv2.FM_RANSAC, 1.0, 0.999)
        return 0 if mask is None else int(mask.sum())

    f = {k: feats(k) for k in (start, lap, k0, k1, k2, k0 + 40)}
    true_loop = inliers(f[start], f[lap])
    alias_same_way = inliers(f[k1], f[k2])  # both copies on the +y side
    alias_turned = inliers(f[k0], f[k1])  # -y side against +y side
    other = inliers(f[k0], f[k0 + 40])
    assert true_loop > 300
    assert alias_same_way > 0.25 * true_loop and alias_turned > 0.25 * true_loop
    assert other < 0.3 * min(alias_same_way, alias_turned)


def test_render_aliasing_command_writes_a_loadable_folder(tmp_path):
    pytest.importorskip("cv2")
    pytest.importorskip("skimage")
    from eifslam.cli.main import main
    from eifslam.io import open_source

    out = tmp_path / "aliasing"
    rc = main(["render", "--scene", "aliasing", "--frames", "6", "--width", "160", "--height", "120",
               "--out", str(out)])
    assert rc == 0
    for name in ("camera.yaml", "groundtruth.tum", "times.txt", "README.md"):
        assert (out / name).is_file()
    assert not (out / "boxes.json").exists()
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"{k:06d}.png" for k in range(6)]
    seq = open_source(out)
    assert len(seq) == 6 and (seq.camera.width, seq.camera.height) == (160, 120)
    assert seq.load(5).shape[:2] == (120, 160)
    gt = seq.ground_truth()
    ref = make_aliasing_scene(n_frames=6, width=160, height=120)
    assert len(gt.positions) == 6
    np.testing.assert_allclose(gt.positions, ref.positions, atol=1e-8)
    readme = (out / "README.md").read_text()
    assert "aliasing scene" in readme and "last part" in readme
    assert main(["render", "--scene", "aliasing", "--laps", "2", "--out", str(tmp_path / "b")]) == 1


def test_same_place_in_the_loop_world_needs_a_like_depth():
    """Lap 2 sees the places of lap 1; a frame at the next corner sees all of the first
    frame's wall from three times as far, which is not the same place."""
    from eifslam.errors import ConfigError
    from eifslam.sim.scene.loop import make_loop_scene

    s = make_loop_scene()
    half = s.n_frames // 2
    assert same_place(s, 0, half) and same_place(s, 300, 300 + half)
    assert view_overlap(s, 0, 100) < 0.2 and not same_place(s, 0, 100)
    assert not same_place(s, 0, 260)
    with pytest.raises(ConfigError):
        same_place(s, 0, s.n_frames)
