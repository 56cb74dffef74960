"""The SLAM system end to end: configuration, degenerate input, sessions, the built-in scene,
real data, and the command line's handling of bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from eifslam.cli.main import main as cli_main
from eifslam.system.config import SlamConfig
from eifslam.errors import ConfigError, ImageError
from eifslam.system.slam import Slam, TrackingState



def test_config_rejects_unknown_keys_and_bad_values():
    with pytest.raises(ConfigError, match="tracking.nonsense"):
        SlamConfig.from_dict({"tracking": {"nonsense": 1}})
    with pytest.raises(ConfigError, match="smoothing.mode"):
        SlamConfig.from_dict({"smoothing": {"mode": "fast"}})
    with pytest.raises(ConfigError, match="frontend.map_fraction"):
        SlamConfig.from_dict({"frontend": {"map_fraction": 1.5}})
    with pytest.raises(ConfigError, match="section"):
        SlamConfig.from_dict({"backend": {}})
    cfg = SlamConfig.from_dict({"smoothing": {"mode": "filter"}})
    assert cfg.smoothing.mode == "filter" and SlamConfig().mapping.feature_parallax_deg == 2.0


@pytest.fixture(scope="module")
def scene_run():
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54)
    slam = Slam(scene.camera)
    idx = list(range(0, 10))
    results = [slam.track(render_frame(scene, k), float(scene.timestamps[k])) for k in idx]
    return scene, slam, idx, results


def test_builtin_scene_tracks_every_frame_with_small_error(scene_run):
    from eifslam.evaluation.metrics import evaluate
    from eifslam.io import Trajectory

    scene, slam, idx, results = scene_run
    assert all(r.position is not None for r in results)
    assert results[0].state is TrackingState.INITIALISING
    assert all(r.state is TrackingState.TRACKING for r in results[1:])
    for r in results[1:]:
        assert r.covariance.shape == (6, 6) and np.all(np.linalg.eigvalsh(r.covariance) > 0)
    t, P, Q = slam.trajectory()
    gt = Trajectory(scene.timestamps[idx], scene.positions[idx], scene.quats_wxyz[idx])
    ate = evaluate(Trajectory(t, P, Q), gt).ate_rmse
    assert 1e-6 < ate < 0.01  # metres; the path is ~1 m long
    ids, X, cols = slam.map()
    assert len(ids) > 200 and X.shape == (len(ids), 3) and cols.dtype == np.uint8


def test_black_frame_is_lost_not_a_crash_and_tracking_resumes(scene_run, tmp_path):
    from eifslam.sim.scene import render_frame

    scene, slam, idx, _ = scene_run
    r = slam.track(np.zeros((scene.camera.height, scene.camera.width, 3), np.uint8), 99.0)
    assert r.state is TrackingState.LOST and r.position is None and r.reason
    assert np.all(np.isfinite(slam.filter.x))
    r2 = slam.track(render_frame(scene, 10), float(scene.timestamps[10]))
    assert r2.state is TrackingState.TRACKING
    # sessions: save and load give the same estimate and keep tracking
    path = tmp_path / "session.pkl"
    slam.save(path)
    back = Slam.load(path)
    np.testing.assert_array_equal(back.filter.x, slam.filter.x)
    r3 = back.track(render_frame(scene, 11), float(scene.timestamps[11]))
    assert r3.state is TrackingState.TRACKING


def test_bad_image_raises_image_error():
    from eifslam.geometry.camera import PinholeCamera

    slam = Slam(PinholeCamera(500, 500, 319.5, 239.5, 640, 480))
    with pytest.raises(ImageError):
        slam.track(np.zeros((10, 10)), 0.0)


def test_repeated_frame_is_not_fused_as_a_baseline(scene_run):
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54)
    slam = Slam(scene.camera)
    img = render_frame(scene, 0)
    slam.track(img, 0.0)
    r = slam.track(img.copy(), 1.0)
    assert r.state is TrackingState.INITIALISING and "parallax" in r.reason
    assert slam.filter.layout.n_poses == 1


def test_frames_that_wait_for_a_baseline_are_localised_once_the_map_exists():
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54)
    slam = Slam(scene.camera)
    img0 = render_frame(scene, 0)
    slam.track(img0, 0.0)
    waiting = slam.track(img0.copy(), 0.5)  # the same view again: no baseline yet
    assert waiting.state is TrackingState.INITIALISING and waiting.position is None
    for k in range(1, 4):
        slam.track(render_frame(scene, k), float(scene.timestamps[k]) + 1.0)
    late = slam.results[1]
    assert late.state is TrackingState.TRACKING and late.position is not None and "waited" in late.reason
    t, P, _ = slam.trajectory()
    assert 0.5 in t.tolist()
    step = np.linalg.norm(P[t == scene.timestamps[3] + 1.0] - P[0])
    assert 0 < np.linalg.norm(P[t == 0.5] - P[0]) < 0.05 * step  # it sits where frame 0 is
    assert slam.retry_lost() == 0  # nothing left to retry


def test_session_saves_after_the_recovery_window_was_rebuilt(scene_run, tmp_path):
    from eifslam.sim.scene import render_frame

    scene, slam, idx, _ = scene_run
    slam.filter.incremental.on_invalidate()  # the next frame rebuilds the window (factorisations)
    slam.track(render_frame(scene, 12), float(scene.timestamps[12]))
    slam.save(tmp_path / "s.pkl")
    back = Slam.load(tmp_path / "s.pkl")
    np.testing.assert_allclose(back.filter.x, slam.filter.x, atol=1e-12)
    assert back.track(render_frame(scene, 13), float(scene.timestamps[13])).state is TrackingState.TRACKING


@pytest.mark.data
def test_kitti_first_frames_against_ground_truth(shared_dataset):
    from eifslam.evaluation.metrics import evaluate
    from eifslam.io import Trajectory, open_source

    seq = open_source(shared_dataset("kitti-seq1"))
    slam = Slam(seq.camera)
    n = 12
    res = [slam.track(seq.load(k), seq.frames[k].timestamp) for k in range(n)]
    assert sum(r.position is not None for r in res) == n
    slam.smooth()
    t, P, Q = slam.trajectory()
    ev = evaluate(Trajectory(t, P, Q), seq.ground_truth())
    assert 1e-4 < ev.ate_rmse < 0.1  # metres over ~13 m of road
    assert ev.tracked_fraction > 0.2


def _tiny_folder(tmp_path: Path, n: int = 3) -> Path:
    import cv2
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54, width=320, height=240)
    d = tmp_path / "data"
    (d / "images").mkdir(parents=True)
    for k in range(n):
        cv2.imwrite(str(d / "images" / f"{k:06d}.png"), render_frame(scene, k))
    c = scene.camera
    (d / "camera.yaml").write_text(
        f"model: pinhole\nwidth: {c.width}\nheight: {c.height}\nfx: {c.fx}\nfy: {c.fy}\ncx: {c.cx}\ncy: {c.cy}\n"
        "distortion: [0, 0, 0, 0, 0]\n")
    return d


def test_cli_run_writes_outputs_and_survives_a_corrupt_image(tmp_path, capsys):
    d = _tiny_folder(tmp_path, 4)
    (d / "images" / "000002.png").write_bytes(b"not a png")
    out = tmp_path / "out"
    rc = cli_main(["run", str(d), "--out", str(out), "--no-html"])
    assert rc == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames"] == 3 and rep["frames_tracked"] >= 1
    assert (out / "trajectory.tum").exists() and (out / "map.ply").exists()
    assert "000002.png" in capsys.readouterr().err


def test_cli_bad_calibration_is_one_line(tmp_path, capsys):
    d = _tiny_folder(tmp_path, 1)
    (d / "camera.yaml").write_text("model: pinhole\nwidth: 320\nheight: 240\nfx: -5\nfy: 1\ncx: 1\ncy: 1\n")
    rc = cli_main(["run", str(d), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and len(err) == 1 and "camera.yaml" in err[0]
    rc = cli_main(["run", str(tmp_path / "missing"), "--out", str(tmp_path / "o")])
    assert rc == 1


def test_runs_repeat_with_the_same_seed_and_bad_settings_are_named():
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54)
    images = [render_frame(scene, k) for k in range(4)]

    def run() -> np.ndarray:
        slam = Slam(scene.camera, SlamConfig.from_dict({"frontend": {"seed": 3}}))
        for k, im in enumerate(images):
            slam.track(im, float(scene.timestamps[k]))
        return slam.trajectory()[1]

    np.testing.assert_array_equal(run(), run())
    with pytest.raises(ConfigError, match="reobserve_radius_px"):
        SlamConfig.from_dict({"experimental": {"reobserve_radius_px": -1}})


def test_one_set_of_defaults_and_string_enums():
    import argparse

    from eifslam.cli.run import make_config
    from eifslam.frontend.config import Detector, FrontEndConfig
    from eifslam.system.config import Mode

    args = argparse.Namespace(map_fraction=None, features=None, max_features=None, mode=None)
    assert make_config(args) == SlamConfig()  # `eifslam run` without options
    assert SlamConfig().frontend == FrontEndConfig() and SlamConfig().filter.gate_chi2 == 9.21
    cfg = SlamConfig.from_dict({"smoothing": {"mode": "ba"}, "frontend": {"detector": "orb"}})
    assert cfg.smoothing.mode is Mode.BA and cfg.smoothing.mode == "ba" and f"{cfg.smoothing.mode}" == "ba"
    assert cfg.frontend.detector is Detector.ORB and not cfg.float_descriptors
    with pytest.raises(ConfigError, match="tracking.scale_distance"):
        SlamConfig.from_dict({"tracking": {"scale_distance": 0.0}})
    with pytest.raises(ConfigError, match="experimental.window"):
        SlamConfig.from_dict({"experimental": {"window": 0}})


def test_finish_follows_the_mode_and_old_sessions_are_refused(tmp_path):
    import pickle

    from eifslam.errors import EifslamError
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54)
    slam = Slam(scene.camera, SlamConfig().replace(smoothing={"mode": "smooth"}))
    for k in range(4):
        slam.track(render_frame(scene, k), float(scene.timestamps[k]))
    fin = slam.finish()
    assert fin.failures == [] and fin.smoothing is not None and slam.smoothing is fin.smoothing
    assert fin.ba is None
    from eifslam.evaluation.outputs import write_outputs

    sm = write_outputs(slam, tmp_path / "out", 1.0, None, html=False)["smoothing"]  # one damping per pass
    assert sm["passes"] == len(sm["step_norms"]) == len(sm["dampings"]) >= 1
    assert all(d >= 0.0 for d in sm["dampings"])
    import json

    rows = json.loads((tmp_path / "out" / "frames.json").read_text())["frames"]
    c = [r["features"] for r in rows]  # what became of each frame's keypoints
    assert len(c) == 4 and c[0]["matched"] == 0 and all(x["matched"] > 0 for x in c[1:])
    assert all(x["detected"] == x["omega_p"] + x["omega_m"] >= x["matched"] for x in c)
    assert all(x["omega_m"] >= x["in_map"] >= x["zm_fused"] >= 0 for x in c)
    assert sum(x["zm_fused"] for x in c) == len(slam.filter.store.all_features().pose)
    assert sum(x["relative"] for x in c) == len(slam.filter.store.relative)
    old = tmp_path / "old.pkl"
    old.write_bytes(pickle.dumps({"version": 1, "slam": slam.config}))
    with pytest.raises(EifslamError, match="pickled sessions"):
        Slam.load(old)


def test_every_state_is_the_full_solve_after_each_frame():
    """After every frame the whole state (not only the recovery window) equals the full
    sparse solve of the information so far: the front end reads old map features and
    poses (localisation on the map, re-observation, triangulation), so they must be the
    current estimate, not the values they had when they left the window."""
    import scipy.sparse.linalg as spla

    from eifslam.sim.frontend import SyntheticFrontEnd
    from eifslam.sim.synthetic import corridor_scene

    sc = corridor_scene(30, np.random.default_rng(4), step=0.3, points_per_metre=20.0)
    fe = SyntheticFrontEnd(sc, 4, map_fraction=0.6)
    slam = Slam(sc.camera, fe.slam_config(smoothing={"mode": "filter"}, experimental={"window": 2}), frontend=fe)
    worst = 0.0
    for k in range(30):
        slam.track(k, 0.1 * k)
        f = slam.filter
        if f.layout.n_poses < 3:
            continue
        x_full = spla.spsolve(f.information_matrix().tocsc(), f.information_vector())
        worst = max(worst, float(np.max(np.abs(f.x - x_full)) / np.max(np.abs(x_full))))
    stats = slam.filter.incremental.stats
    assert stats.marginalised_poses + stats.marginalised_features > 0  # states did leave the window
    assert worst < 1e-3  # numerically 5e-5 (gauge priors of 1e-6 m); 1.5e-2 without the back-substitution
