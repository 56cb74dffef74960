"""Sessions: a saved and loaded system continues as the uninterrupted run, and a
file that is not an eifslam session (a pickle, random bytes, another zip, a crafted or
truncated npz) is refused in one line naming it, without running anything in it."""

from __future__ import annotations

import io
import json
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest

from eifslam.errors import EifslamError, SessionError
from eifslam.system.config import SlamConfig
from eifslam.system.slam import Slam, TrackingState


@pytest.fixture(scope="module")
def scene_images():
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54)
    return scene, [render_frame(scene, k) for k in range(9)]


def _run(scene, images, cfg: SlamConfig, frames: range, slam: Slam | None = None) -> Slam:
    slam = slam or Slam(scene.camera, cfg)
    for k in frames:
        slam.track(images[k], float(scene.timestamps[k]))
    return slam


def _poses(slam: Slam) -> np.ndarray:
    return np.array([np.concatenate([r.position, r.quat_wxyz]) for r in slam.results])


@pytest.mark.parametrize("recovery", ["full", "incremental"])
def test_a_loaded_session_continues_as_the_uninterrupted_run(scene_images, tmp_path, recovery):
    scene, images = scene_images
    cfg = SlamConfig().replace(experimental={"recovery": recovery,  # keyframe state saved too
                                             "keyframe_parallax_deg": 2.0,  # (frames between keyframes)
                                             "loop_train_frames": 3, "loop_learn_lag": 5})  # a learnt place index
    whole = _run(scene, images, cfg, range(9))
    first = _run(scene, images, cfg, range(6))
    path = tmp_path / "six.npz"
    first.save(path)
    assert zipfile.is_zipfile(path)
    back = Slam.load(path)
    # what was saved comes back
    assert back.config == cfg and back.camera == scene.camera and back.n_frames == 6
    assert len(first.keyframes) >= 1 and not first.results[5].keyframe  # a frame between keyframes
    assert [r.keyframe for r in back.results] == [r.keyframe for r in first.results]
    ka, kb = first.keyframes.poses(), back.keyframes.poses()
    assert ka[0] == kb[0] and np.array_equal(ka[1], kb[1]) and back.keyframes.last == first.keyframes.last
    np.testing.assert_array_equal(back.T_wc(5), first.T_wc(5))
    assert [r.state for r in back.results] == [r.state for r in first.results]
    np.testing.assert_array_equal(_poses(back), _poses(first))
    np.testing.assert_array_equal(back.results[3].covariance, first.results[3].covariance)
    assert back.filter.layout.order == first.filter.layout.order
    assert (back.filter.information_matrix() != first.filter.information_matrix()).nnz == 0
    np.testing.assert_array_equal(back.map()[2], first.map()[2])
    assert back.frontend.frame_ids == first.frontend.frame_ids
    fa, fb = first.frontend.state_dict(), back.frontend.state_dict()
    assert fa["descriptors_float32"] and fb["descriptors"].dtype == np.uint8  # SIFT's floats, kept as bytes
    for key in ("descriptors", "uv", "raw_ids", "last_frame"):
        np.testing.assert_array_equal(fa[key], fb[key])
    np.testing.assert_array_equal(back.frontend.frame(2).track_ids, first.frontend.frame(2).track_ids)
    # ... and tracking continues on it as it would have without the interruption
    _run(scene, images, cfg, range(6, 9), back)
    assert all(r.state is TrackingState.TRACKING for r in back.results[1:])
    assert back.filter.layout.n_features == whole.filter.layout.n_features
    step = np.linalg.norm(_poses(whole)[8, :3] - _poses(whole)[4, :3])
    assert step > 1e-3  # the frames after the save moved the camera (the comparison means something)
    if recovery == "full":
        np.testing.assert_array_equal(_poses(back), _poses(whole))
    else:  # the loaded recovery rebuilds its window: the same solution up to round-off, which
        # can tip a measurement's gate the other way (then the poses differ by far less than a step)
        d = np.abs(_poses(back) - _poses(whole)).max()
        assert d < 1e-3 * step


def test_save_refuses_a_synthetic_front_end(tmp_path):
    from eifslam.sim.frontend import SyntheticFrontEnd
    from eifslam.sim.synthetic import corridor_scene

    sc = corridor_scene(4, np.random.default_rng(0), points_per_metre=4.0)
    fe = SyntheticFrontEnd(sc, 0)
    slam = Slam(sc.camera, fe.slam_config(), frontend=fe)
    slam.track(0)
    with pytest.raises(EifslamError, match="SyntheticFrontEnd does not save"):
        slam.save(tmp_path / "s.npz")
    assert not (tmp_path / "s.npz").exists()


# -- hostile files ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def session_members(tmp_path_factory) -> dict[str, np.ndarray]:
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54)
    slam = Slam(scene.camera)
    for k in range(3):
        slam.track(render_frame(scene, k), float(scene.timestamps[k]))
    path = tmp_path_factory.mktemp("valid") / "s.npz"
    slam.save(path)
    with np.load(path, allow_pickle=False) as z:
        return {name: z[name] for name in z.files}


def _doc(members) -> dict:
    return json.loads(members["session.json"].tobytes())


def _with_doc(members, doc) -> dict:
    return {**members, "session.json": np.frombuffer(json.dumps(doc).encode(), np.uint8)}


def _npz_bytes(members) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **members)
    return buf.getvalue()


class _Payload:
    """A pickle that writes a file when unpickled."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.write_text, (self.marker, "pwned"))


def _npy_header_only(shape: tuple, dtype: str = "<f8") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": shape})
    return buf.getvalue() + b"\0" * 16


def _hostile(members, marker: Path) -> dict[str, bytes]:
    doc = _doc(members)
    good = _npz_bytes(members)
    zbuf = io.BytesIO()
    with zipfile.ZipFile(zbuf, "w") as zf:
        zf.writestr("readme.txt", "hello")
    huge = io.BytesIO()
    with zipfile.ZipFile(huge, "w") as zf:
        zf.writestr("session.json.npy", _npy_header_only((10**12,), "|u1"))
    obj = io.BytesIO()
    np.save(obj, np.array([_Payload(marker)], dtype=object), allow_pickle=True)
    with_obj = io.BytesIO()
    with zipfile.ZipFile(with_obj, "w") as zf:
        zf.writestr("session.json.npy", obj.getvalue())
    deep = json.dumps({**doc, "results": "DEEP"}).replace('"DEEP"', "[" * 5000 + "]" * 5000)
    return {
        "pickle": pickle.dumps({"version": 3, "slam": _Payload(marker)}),
        "empty": b"",
        "random": np.random.default_rng(0).integers(0, 256, 5000).astype(np.uint8).tobytes(),
        "truncated": good[: len(good) // 2],
        "foreign zip": zbuf.getvalue(),
        "no document": _npz_bytes({k: v for k, v in members.items() if k != "session.json"}),
        "huge declared shape": huge.getvalue(),
        "object array": with_obj.getvalue(),
        "not json": _npz_bytes({**members, "session.json": np.frombuffer(b"\xff{", np.uint8)}),
        "other format": _npz_bytes(_with_doc(members, {**doc, "format": "something"})),
        "other version": _npz_bytes(_with_doc(members, {**doc, "version": 2})),
        "missing array": _npz_bytes({k: v for k, v in members.items() if k != "filter.x"}),
        "wrong dtype": _npz_bytes({**members, "filter.x": members["filter.x"].astype(np.int64)}),
        "wrong shape": _npz_bytes({**members, "filter.x": members["filter.x"][:-1]}),
        "nan": _npz_bytes({**members, "filter.x": np.full_like(members["filter.x"], np.nan)}),
        "index out of range": _npz_bytes({**members, "frontend.raw_ids": members["frontend.raw_ids"] + 10**9}),
        "huge length": _npz_bytes({**members, "frontend.n_keypoints": members["frontend.n_keypoints"] * 10**12}),
        "track cycle": _npz_bytes({**members, "frontend.tracks.parent": members["frontend.tracks.parent"][::-1].copy()}),
        "unknown setting": _npz_bytes(_with_doc(members, {**doc, "config": {"tracking": {"nonsense": 1}}})),
        "bad camera": _npz_bytes(_with_doc(members, {**doc, "camera": {**doc["camera"], "fx": -1.0}})),
        "deep nesting": _npz_bytes({**members, "session.json": np.frombuffer(deep.encode(), np.uint8)}),
        "frame ids": _npz_bytes({**members, "results.frame_id": members["results.frame_id"] + 1}),
    }


def test_hostile_files_are_refused_in_one_line_and_never_run(session_members, tmp_path):
    marker = tmp_path / "pwned"
    files = _hostile(session_members, marker)
    for name, data in files.items():
        path = tmp_path / f"{name.replace(' ', '_')}.npz"
        path.write_bytes(data)
        with pytest.raises(SessionError) as err:
            Slam.load(path)
        msg = str(err.value)
        assert str(path) in msg and "\n" not in msg, (name, msg)
        assert not marker.exists(), name
    # the untouched members do load (the corpus is refused for what was changed)
    good = tmp_path / "good.npz"
    good.write_bytes(_npz_bytes(session_members))
    assert Slam.load(good).n_frames == 3


def test_cli_style_error_for_a_missing_session(tmp_path):
    with pytest.raises(SessionError, match="no such file"):
        Slam.load(tmp_path / "absent.npz")


# -- the command line -------------------------------------------------------------------------
def _folder(tmp_path: Path, n: int) -> Path:
    import cv2
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54, width=320, height=240)
    d = tmp_path / "data"
    (d / "images").mkdir(parents=True)
    for k in range(n):
        cv2.imwrite(str(d / "images" / f"{k:06d}.png"), render_frame(scene, k))
    c = scene.camera
    (d / "camera.yaml").write_text(
        f"model: pinhole\nwidth: {c.width}\nheight: {c.height}\nfx: {c.fx}\nfy: {c.fy}\ncx: {c.cx}\ncy: {c.cy}\n")
    return d


def test_cli_resume_continues_a_saved_run_on_the_later_frames(tmp_path, capsys):
    from eifslam.cli.main import main as cli_main
    from eifslam.io import read_tum

    d = _folder(tmp_path, 6)
    common = ["--no-html", "--mode", "filter"]
    assert cli_main(["run", str(d), "--out", str(tmp_path / "whole"), *common]) == 0
    sess = tmp_path / "first.npz"
    assert cli_main(["run", str(d), "--out", str(tmp_path / "first"), "--max-frames", "3",
                     "--save-session", str(sess), *common]) == 0
    assert Slam.load(sess).n_frames == 3
    assert cli_main(["run", str(d), "--out", str(tmp_path / "rest"), "--resume", str(sess), "--no-html"]) == 0
    rep = json.loads((tmp_path / "rest" / "report.json").read_text())
    whole = json.loads((tmp_path / "whole" / "report.json").read_text())
    assert rep["frames"] == 6 and rep["frames_tracked"] == whole["frames_tracked"] >= 5
    a, b = read_tum(tmp_path / "whole" / "trajectory.tum"), read_tum(tmp_path / "rest" / "trajectory.tum")
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    assert np.abs(a.positions - b.positions).max() < 1e-6
    assert np.linalg.norm(a.positions[-1] - a.positions[0]) > 1e-2
    # a configuration option cannot change a resumed session's configuration
    capsys.readouterr()
    assert cli_main(["run", str(d), "--out", str(tmp_path / "x"), "--resume", str(sess), "--features", "orb"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--features" in err[0]
    # a file that is not a session is one line naming it
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"junk")
    assert cli_main(["run", str(d), "--out", str(tmp_path / "y"), "--resume", str(bad)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("eifslam: error:") and str(bad) in err[0]
