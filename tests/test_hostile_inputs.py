"""A corpus of hostile inputs, generated in tmp_path: every case ends with exit
0, or exit 1 and one line ``eifslam: error: ...`` naming the file or option; never a
traceback, a hang or lost estimates. Session files are covered by the session tests."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from eifslam.cli.main import main as cli_main
from eifslam.errors import OutputError
from eifslam.io import open_source, read_tum
from eifslam.io.files import atomic_path, atomic_write
from eifslam.io.image_header import MAX_IMAGE_PIXELS, header_size
from eifslam.io.trajectory import TumAppender

from hostile import Scene, assert_clean, png_claiming, poses_in, subprocess_env

IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(8)


@pytest.fixture
def data(scene, tmp_path) -> Path:
    """A good 4-image folder data set."""
    return scene.folder(tmp_path / "data", order=[0, 1, 2, 3])


def cli(capsys, *argv: str) -> tuple[int, str]:
    rc = cli_main([str(a) for a in argv])
    return rc, capsys.readouterr().err


# -- the output folder, checked before any work ----------------------------------------

def test_output_folder_that_is_a_file(data, tmp_path, capsys):
    out = tmp_path / "out.txt"
    out.write_text("keep me")
    rc, err = cli(capsys, "run", data, "--out", out, "--no-html")
    assert rc == 1 and out.read_text() == "keep me"
    assert_clean(rc, err, str(out))
    assert "is a file" in err


def test_output_folder_whose_parent_is_a_file(data, tmp_path, capsys):
    (tmp_path / "f").write_text("")
    out = tmp_path / "f" / "out"
    rc, err = cli(capsys, "run", data, "--out", out, "--no-html")
    assert rc == 1
    assert_clean(rc, err, str(out))


@pytest.mark.skipif(IS_ROOT or os.name != "posix", reason="root writes anywhere")
def test_output_folder_read_only(data, tmp_path, capsys):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        for out in (ro, ro / "sub"):
            rc, err = cli(capsys, "run", data, "--out", out, "--no-html")
            assert rc == 1
            assert_clean(rc, err, str(out))
    finally:
        ro.chmod(0o700)


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="no /proc")
def test_output_folder_on_a_pseudo_file_system(data, capsys):
    for out in ("/proc/eifslam-out", "/proc/self/eifslam-out", "/sys/eifslam-out"):
        rc, err = cli(capsys, "run", data, "--out", out, "--no-html")
        assert rc == 1
        assert_clean(rc, err, out)


def test_output_path_longer_than_the_os_allows(data, tmp_path, capsys):
    for out in (tmp_path / ("x" * 300), tmp_path.joinpath(*["y" * 200] * 30)):
        rc, err = cli(capsys, "run", data, "--out", out, "--no-html")
        assert rc == 1
        assert_clean(rc, err, str(out))


def test_demo_and_render_check_their_output_folder_first(tmp_path, capsys):
    (tmp_path / "f").write_text("")
    for cmd in (["demo", "--frames", "3"], ["render", "--frames", "3"]):
        rc, err = cli(capsys, *cmd, "--out", tmp_path / "f")
        assert rc == 1
        assert_clean(rc, err, str(tmp_path / "f"))


def test_an_output_name_taken_by_a_folder_costs_only_that_file(data, tmp_path, capsys):
    out = tmp_path / "out"
    (out / "map.ply").mkdir(parents=True)
    rc, err = cli(capsys, "run", data, "--out", out, "--no-html")
    assert rc == 1
    assert_clean(rc, err, "map.ply")
    rep = json.loads((out / "report.json").read_text())
    assert "map.ply" in rep["write_errors"][0]
    assert poses_in(out / "trajectory.tum") == rep["frames_tracked"] >= 3
    assert poses_in(out / "trajectory.partial.tum") >= 3  # kept: the run did not end cleanly


def test_no_decodable_image_is_one_line_with_outputs(scene, tmp_path, capsys):
    d = scene.folder(tmp_path / "data", order=[0, 1, 2])
    for p in (d / "images").iterdir():
        p.write_bytes(b"\x89PNG\r\n\x1a\n broken")
    out = tmp_path / "out"
    rc, err = cli(capsys, "run", d, "--out", out, "--no-html")
    assert rc == 1 and "no frame" in err
    assert_clean(rc, err, str(d))
    assert json.loads((out / "report.json").read_text())["frames"] == 0


# -- arguments ---------------------------------------------------------------------------

@pytest.mark.parametrize("scale", [
    ("pose", "0", "sphere", "3", "1.0"),
    ("pose", "zero", "pose", "3", "1.0"),
    ("pose", "0", "pose", "1.5", "1.0"),
    ("pose", "0", "pose", "3", "-2"),
    ("pose", "0", "pose", "3", "0"),
    ("pose", "0", "pose", "3", "nan"),
    ("pose", "0", "pose", "3", "inf"),
    ("pose", "0", "pose", "0", "1.0"),
])
def test_bad_scale_distance_is_refused_before_any_work(data, tmp_path, capsys, scale):
    out = tmp_path / "out"
    rc, err = cli(capsys, "run", data, "--out", out, "--scale-distance", *scale)
    assert rc == 1 and not out.exists()
    assert_clean(rc, err, "--scale-distance")


@pytest.mark.parametrize("argv, names", [
    (["run", "DATA", "--max-frames", "0"], "--max-frames"),
    (["run", "DATA", "--map-fraction", "nan"], "--map-fraction"),
    (["render", "--width", "100000"], "100000"),
    (["render", "--noise", "nan"], "--noise"),
    (["render", "--frames", "100000000"], "--frames"),
    (["demo", "--frames", "1"], "--frames"),
    (["demo", "--blur", "-1"], "--blur"),
])
def test_bad_numbers_are_one_line(data, tmp_path, capsys, argv, names):
    out = tmp_path / "out"
    rc, err = cli(capsys, *[data if a == "DATA" else a for a in argv], "--out", out)
    assert rc == 1 and not out.exists()
    assert_clean(rc, err, names)


# -- images over the memory budget --------------------------------------------------------

def test_header_size_agrees_with_opencv(tmp_path):
    img = np.random.default_rng(0).integers(0, 255, (37, 53, 3), np.uint8)
    for ext in (".png", ".jpg", ".bmp", ".tif", ".ppm", ".webp"):
        path = tmp_path / f"i{ext}"
        assert cv2.imwrite(str(path), img if ext != ".pgm" else img[..., 0])
        decoded = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        assert header_size(path) == (decoded.shape[1], decoded.shape[0]), ext
    (tmp_path / "claims.png").write_bytes(png_claiming(100_000, 90_000))
    assert header_size(tmp_path / "claims.png") == (100_000, 90_000)
    (tmp_path / "short.png").write_bytes(b"\x89PNG\r\n")
    assert header_size(tmp_path / "short.png") is None


def test_png_claiming_a_huge_size_is_skipped_not_decoded(scene, tmp_path, capsys):
    d = scene.folder(tmp_path / "data", order=[0, 1, 2, 3])
    (d / "images" / "000002.png").write_bytes(png_claiming(100_000, 100_000))
    out = tmp_path / "out"
    rc, err = cli(capsys, "run", d, "--out", out, "--no-html")
    assert_clean(rc, err)
    assert rc == 0 and "000002.png" in err and "megapixels" in err
    assert json.loads((out / "report.json").read_text())["frames"] == 3


def test_an_8000x8000_image_and_camera_are_refused(scene, tmp_path, capsys):
    assert 8000 * 8000 > MAX_IMAGE_PIXELS
    d = scene.folder(tmp_path / "data", order=[0, 1, 2])
    assert cv2.imwrite(str(d / "images" / "000001.png"), np.zeros((8000, 8000), np.uint8))
    rc, err = cli(capsys, "run", d, "--out", tmp_path / "o1", "--no-html")
    assert_clean(rc, err)
    assert "000001.png" in err and "8000x8000" in err
    (d / "camera.yaml").write_text(scene.camera_yaml().replace("width: 320", "width: 8000")
                                   .replace("height: 240", "height: 8000"))
    rc, err = cli(capsys, "run", d, "--out", tmp_path / "o2", "--no-html")
    assert rc == 1
    assert_clean(rc, err, str(d))


# -- camera YAML --------------------------------------------------------------------------

def _billion_laughs() -> str:
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for k in range(1, 10):
        lines.append(f"a{k}: &a{k} [" + ",".join([f"*a{k - 1}"] * 9) + "]")
    return "\n".join(lines) + "\nfx: *a9\nfy: 1\ncx: 1\ncy: 1\n"


@pytest.mark.parametrize("content", [
    _billion_laughs(),
    "fx: " + "[" * 5000 + "]" * 5000 + "\n",
    "fx: 1\n" + "".join(f"k{k}: {k}\n" for k in range(120_000)),  # 1.5 MB
    "fx: [" + ",".join(["1"] * 20_000) + "]\n",
    "fx: 1" + "0" * 5000 + "\nfy: 1\ncx: 1\ncy: 1\nwidth: 320\nheight: 240\n",
    "\x00\xff\xfe binary",
])
def test_hostile_camera_yaml_is_one_line(scene, tmp_path, capsys, content):
    d = scene.folder(tmp_path / "data", order=[0, 1])
    (d / "camera.yaml").write_bytes(content.encode("latin-1"))
    t0 = time.perf_counter()
    rc, err = cli(capsys, "run", d, "--out", tmp_path / "out")
    assert rc == 1 and time.perf_counter() - t0 < 20  # generous: refused, not expanded
    assert_clean(rc, err, "camera.yaml")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs")
def test_camera_file_that_is_a_fifo_does_not_hang(scene, tmp_path, capsys):
    d = scene.folder(tmp_path / "data", order=[0, 1])
    (d / "camera.yaml").unlink()
    os.mkfifo(d / "camera.yaml")
    rc, err = cli(capsys, "run", d, "--out", tmp_path / "out")
    assert rc == 1
    assert_clean(rc, err, "camera.yaml")


# -- ground truth is for scoring only ------------------------------------------------------

BAD_GT = {
    "folder": ("groundtruth.tum", "0.0 nan 0 0 0 0 0 1\n"),
    "tum": ("groundtruth.txt", "this is not a trajectory\n"),
    "euroc": ("data.csv", "#timestamp,x,y,z,qw,qx,qy,qz\n100000000000,nan,0,0,1,0,0,0\n"),
    "kitti": ("poses.txt", "1 2 3\n"),
    "video": ("clip.tum", "0 0 0 0 0 0 0 0\n"),
}


@pytest.mark.parametrize("layout", sorted(BAD_GT))
def test_bad_ground_truth_skips_evaluation_and_keeps_every_estimate(scene, tmp_path, capsys, layout):
    name, content = BAD_GT[layout]
    sub = Scene.__new__(Scene)  # the first 4 images
    sub.__dict__.update(scene.__dict__, images=scene.images[:4], times=scene.times[:4])
    d = sub.folder(tmp_path / "d", gt=content) if layout == "folder" else getattr(sub, layout)(tmp_path / "d", content)
    out = tmp_path / "out"
    rc, err = cli(capsys, "run", d, "--out", out)
    assert_clean(rc, err)
    assert rc == 0 and "warning" in err and name in err
    rep = json.loads((out / "report.json").read_text())
    assert name in rep["evaluation_skipped"] and "ate_rmse" not in rep
    assert poses_in(out / "trajectory.tum") == rep["frames_tracked"] >= 3
    assert (out / "map.ply").stat().st_size > 0 and (out / "report.html").is_file()
    assert not (out / "trajectory.partial.tum").exists()


def test_good_ground_truth_is_scored(scene, tmp_path, capsys):
    # the same run with a well-formed file: evaluation is not skipped (the test above
    # would pass trivially if it always were)
    d = scene.folder(tmp_path / "d", order=[0, 1, 2, 3])
    sub_times = np.round(0.1 * np.arange(4), 3)
    q = scene.tum_lines().splitlines()[:4]
    (d / "groundtruth.tum").write_text("".join(f"{t:.3f} " + ln.split(" ", 1)[1] + "\n" for t, ln in zip(sub_times, q)))
    rc, err = cli(capsys, "run", d, "--out", tmp_path / "out", "--no-html")
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    assert rc == 0 and "evaluation_skipped" not in rep and 0 < rep["ate_rmse"] < 0.05


# -- arguments only wrong once the run ends ---------------------------------------------

def test_scale_naming_a_state_not_in_the_map_warns_and_writes_unscaled(data, tmp_path, capsys):
    out = tmp_path / "out"
    rc, err = cli(capsys, "run", data, "--out", out, "--no-html", "--scale-distance", "pose", "0", "pose", "999", "2")
    assert_clean(rc, err)
    assert rc == 0 and "warning" in err and "999" in err
    rep = json.loads((out / "report.json").read_text())
    assert "999" in rep["scale_skipped"]
    assert poses_in(out / "trajectory.tum") == rep["frames_tracked"] >= 3


def test_scale_naming_existing_states_is_applied(data, tmp_path, capsys):
    # the reference: the written trajectory itself, read back
    out = tmp_path / "out"
    rc, err = cli(capsys, "run", data, "--out", out, "--no-html", "--scale-distance", "pose", "0", "pose", "3", "2.5")
    assert rc == 0 and "scale_skipped" not in json.loads((out / "report.json").read_text())
    traj = read_tum(out / "trajectory.tum")
    assert 2.499 < np.linalg.norm(traj.positions[3] - traj.positions[0]) < 2.501


# -- video whose middle is corrupt ----------------------------------------------------------

def test_video_with_a_corrupt_middle_keeps_every_decodable_frame(tmp_path):
    path = tmp_path / "clip.mp4"
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, (160, 120))
    if not w.isOpened():
        pytest.skip("no mp4v encoder in this OpenCV")
    for k in range(40):
        img = np.full((120, 160, 3), 5 * k, np.uint8)
        cv2.putText(img, str(k), (40, 80), 0, 2, (255, 255, 255), 3)
        w.write(img)
    w.release()
    raw = bytearray(path.read_bytes())
    a = len(raw) // 2
    raw[a:a + 2000] = np.random.default_rng(1).integers(0, 256, 2000, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(raw))
    (tmp_path / "clip.yaml").write_text("fx: 150\nfy: 150\ncx: 80\ncy: 60\n")
    # reference: OpenCV reading the file straight through, going on after a failed frame
    cap = cv2.VideoCapture(str(path))
    reference = [int(img.mean()) for ok, img in (cap.read() for _ in range(80)) if ok]
    cap.release()
    seq = open_source(path)
    kept = []
    for k in range(len(seq)):
        try:
            kept.append(int(seq.load(k).mean()))
        except Exception as exc:  # an ImageError naming the file, nothing else
            assert "clip.mp4" in str(exc) and type(exc).__name__ == "ImageError"
    assert 20 < len(reference) < 40  # the corruption costs frames, but not all after it
    assert kept == reference


# -- eval -------------------------------------------------------------------------------------

def test_eval_json_at_a_folder_and_unknown_plot_format_before_any_work(tmp_path, capsys):
    missing = tmp_path / "missing.tum"  # never read: the checks come first
    rc, err = cli(capsys, "eval", missing, missing, "--json", tmp_path)
    assert rc == 1 and "--json" in err
    assert_clean(rc, err, str(tmp_path))
    for plot in ("plot.xyz", "plot"):
        rc, err = cli(capsys, "eval", missing, missing, "--plot", tmp_path / plot)
        assert rc == 1 and "format" in err
        assert_clean(rc, err, plot)
    rc, err = cli(capsys, "eval", missing, missing, "--json", tmp_path / "no" / "r.json")
    assert_clean(rc, err, "r.json")
    rc, err = cli(capsys, "eval", missing, missing, "--max-diff", "nan")
    assert_clean(rc, err, "--max-diff")


@pytest.mark.parametrize("estimate", ["", "5 0 0 0 0 0 0 1\n", "0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n",
                                      "0 nan 0 0 0 0 0 1\n", "0 0 0 0 0 0 0 0\n", "1 0 0 0 0 0 0 1\n0 0 0 0 0 0 0 1\n"])
def test_eval_of_an_unusable_estimate_names_it(tmp_path, capsys, estimate):
    (tmp_path / "gt.tum").write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n2 1 1 0 0 0 0 1\n3 0 1 1 0 0 0 1\n")
    (tmp_path / "est.tum").write_text(estimate)
    rc, err = cli(capsys, "eval", tmp_path / "est.tum", tmp_path / "gt.tum")
    assert rc == 1
    assert_clean(rc, err, "est.tum")


# -- the Python API's readers: a DatasetError naming the file, nothing else -------------------

@pytest.mark.parametrize("body", [
    b"ply\nformat ascii 1.0\nelement vertex many\nend_header\n",
    b"ply\nformat ascii 1.0\nelement vertex\nend_header\n",
    b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 x\n",
    b"ply\nformat binary_little_endian 1.0\nelement vertex -5\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
    b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999999\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
    b"ply\nend_header",
    b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n\xff\xfe\n",
])
def test_malformed_ply_is_a_dataset_error(tmp_path, body):
    from eifslam.errors import DatasetError
    from eifslam.io import read_ply

    (tmp_path / "m.ply").write_bytes(body)
    with pytest.raises(DatasetError, match="m.ply"):
        read_ply(tmp_path / "m.ply")


_SEEDS = {
    "t.tum": "0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n",
    "times.txt": "0.0\n0.1\n",
    "rgb.txt": "# x\n0.0 rgb/a.png\n",
    "data.csv": "#t,f\n100,a.png\n",
    "poses.txt": "1 0 0 0 0 1 0 0 0 0 1 0\n",
    "camera.yaml": "model: pinhole\nwidth: 10\nheight: 10\nfx: 5\nfy: 5\ncx: 5\ncy: 5\ndistortion: [0,0,0,0,0]\n",
    "cv.yaml": "%YAML:1.0\nCamera.fx: 5\nCamera.fy: 5\nCamera.cx: 1\nCamera.cy: 1\nCamera.width: 10\nCamera.height: 10\n",
    "calib.txt": "P0: 5 0 5 0 0 5 5 0 0 0 1 0\n",
    "sensor.yaml": ("camera_model: pinhole\nintrinsics: [5,5,5,5]\nresolution: [10,10]\n"
                    "distortion_coefficients: [0,0,0,0]\nT_BS:\n  data: [1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1]\n"),
    "x.camera": "5 0 5\n0 5 5\n0 0 1\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n10 10\n",
}
_TOKENS = ["nan", "inf", "-1", "0", "1e400", "1" * 50, "[", "]", "{", "}", ":", "&a", "*a", "!!python/object:os.system",
           "\x00", "\xff", ",", " ", "\n", "-", "e", "'", '"', "!!binary", "~", "null", "true", "[1,2]", "{a: 1}", "? ", "|"]


@pytest.mark.parametrize("name", sorted(_SEEDS))
def test_mutated_text_files_raise_only_eifslam_errors(tmp_path, name):
    """A fixed-seed mutation of each text format eifslam reads: every outcome is a value
    or an EifslamError (which the CLI prints in one line), never another exception."""
    from eifslam.errors import EifslamError
    from eifslam.io import load_camera
    from eifslam.io.cameras import read_euroc_sensor
    from eifslam.io.euroc import read_euroc_csv
    from eifslam.io.folder import read_times
    from eifslam.io.kitti import read_kitti_poses
    from eifslam.io.tum_rgbd import read_file_list

    read = {"t.tum": read_tum, "times.txt": read_times, "rgb.txt": read_file_list,
            "data.csv": lambda p: read_euroc_csv(p, 2), "poses.txt": read_kitti_poses,
            "camera.yaml": load_camera, "cv.yaml": load_camera, "x.camera": load_camera,
            "calib.txt": lambda p: load_camera(p, image_size=(10, 10)), "sensor.yaml": read_euroc_sensor}[name]
    rng = np.random.default_rng(sorted(_SEEDS).index(name))
    path = tmp_path / name
    errors = 0
    for _ in range(150):
        text = list(_SEEDS[name])
        for _ in range(rng.integers(1, 6)):
            k = int(rng.integers(0, len(text) + 1))
            op = rng.integers(0, 3)
            if op == 0 and text:
                del text[min(k, len(text) - 1)]
            elif op == 1:
                text.insert(k, _TOKENS[rng.integers(len(_TOKENS))])
            else:
                text.insert(k, chr(rng.integers(32, 127)))
        path.write_bytes("".join(text).encode("utf-8", "surrogateescape"))
        try:
            read(path)
        except EifslamError as exc:
            errors += 1
            assert name in str(exc) and "\n" not in str(exc)
    assert errors > 10  # the mutations do break the files


# -- atomic and incremental writing -----------------------------------------------------------

def test_atomic_write_leaves_the_old_file_when_interrupted(tmp_path):
    target = tmp_path / "report.json"
    atomic_write(target, '{"old": 1}')
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text('{"new": ')
            raise KeyboardInterrupt
    assert target.read_text() == '{"old": 1}' and sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]
    with pytest.raises(OutputError, match="nowhere"):
        atomic_write(tmp_path / "nowhere" / "x", "data")


def test_tum_appender_skips_what_the_format_cannot_hold(tmp_path):
    log = TumAppender(tmp_path / "t.tum")
    q = np.array([1.0, 0, 0, 0])
    assert log.append(0.0, np.zeros(3), q) and log.append(1.0, np.ones(3), 2 * q)
    assert not log.append(1.0, np.ones(3), q)  # time not increasing
    assert not log.append(2.0, np.array([math.nan, 0, 0]), q)
    assert not log.append(3.0, np.zeros(3), np.zeros(4))
    log.close()
    traj = read_tum(tmp_path / "t.tum")
    assert list(traj.timestamps) == [0.0, 1.0] and np.allclose(traj.quats_wxyz[1], q)


# -- interruptions: signals in a subprocess ---------------------------------------------------

@pytest.fixture(scope="module")
def long_run(scene, tmp_path_factory) -> Path:
    """80 images going back and forth over the 8 rendered ones (a few seconds of tracking)."""
    order = (list(range(8)) + list(range(6, 0, -1))) * 6
    return scene.folder(tmp_path_factory.mktemp("long") / "data", order=order[:80])


def _start(data: Path, out: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "eifslam.cli.main", "run", str(data), "--out", str(out), "--no-html"],
                            env=subprocess_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for_poses(proc: subprocess.Popen, path: Path, n: int, timeout: float = 60.0) -> int:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        k = poses_in(path)
        if k >= n:
            return k
        if proc.poll() is not None:
            pytest.fail(f"the run ended before {n} poses: {proc.communicate()[1][-2000:]}")
        time.sleep(0.02)
    proc.kill()
    pytest.fail("no poses written in time")


@pytest.mark.parametrize("signame", ["SIGTERM", "SIGHUP", "SIGINT"])
def test_sigterm_and_sighup_write_what_was_estimated(long_run, tmp_path, signame):
    if not hasattr(signal, signame):
        pytest.skip(f"no {signame} here")
    out = tmp_path / "out"
    proc = _start(long_run, out)
    seen = _wait_for_poses(proc, out / "trajectory.partial.tum", 4)
    proc.send_signal(getattr(signal, signame))
    _, err = proc.communicate(timeout=120)
    assert_clean(proc.returncode, err)
    assert proc.returncode == 0 and "interrupted" in err
    rep = json.loads((out / "report.json").read_text())
    assert signame in rep["stopped"] and rep["frames"] < 80
    assert rep["frames_tracked"] >= seen and poses_in(out / "trajectory.tum") == rep["frames_tracked"]
    assert (out / "map.ply").is_file() and not (out / "trajectory.partial.tum").exists()


def test_sigkill_keeps_the_poses_tracked_before(long_run, tmp_path):
    out = tmp_path / "out"
    proc = _start(long_run, out)
    partial = out / "trajectory.partial.tum"
    _wait_for_poses(proc, partial, 4)
    before = read_tum(partial)
    proc.kill()
    proc.communicate(timeout=60)
    after = read_tum(partial)  # parses: no half line
    assert len(after) >= len(before) >= 4
    np.testing.assert_array_equal(after.timestamps[: len(before)], before.timestamps)
    assert not (out / "report.json").exists()
