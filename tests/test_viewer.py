"""The rerun viewer (``eifslam run --rerun-save``): a run recorded to an ``.rrd`` file and
read back through rerun's own API holds the final trajectory (one position per row of
``trajectory.tum``), the image, its classified keypoints, the map and the aligned ground
truth; the stream leaves the estimate unchanged; without rerun-sdk the command ends in
one line."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from eifslam.cli.main import main as cli_main

from hostile import Scene

rerun = pytest.importorskip("rerun")
from rerun.chunk import RrdReader  # noqa: E402


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    scene = Scene(12)
    scene.times = 0.1 * np.arange(12)  # the folder's frame times
    return scene.folder(tmp_path_factory.mktemp("viewer") / "data", gt=scene.tum_lines())


def _read(rrd) -> dict[str, list[tuple[int | None, dict]]]:
    """Per entity: ``(frame, row)`` of every logged row (``frame`` None when static)."""
    out: dict[str, list] = {}
    for chunk in RrdReader(rrd).store().stream():
        cols = chunk.to_record_batch().to_pydict()
        frames = cols.get("frame", [None] * chunk.num_rows)
        for i in range(chunk.num_rows):
            out.setdefault(chunk.entity_path, []).append((frames[i], {k: v[i] for k, v in cols.items()}))
    return out


def _latest(rows, column: str):
    timed = [(f, r[column]) for f, r in rows if f is not None and r.get(column) is not None]
    return max(timed, key=lambda fr: fr[0])[1]


def test_a_recorded_run_holds_the_final_trajectory_and_the_frames(data, tmp_path):
    out, rrd = tmp_path / "out", tmp_path / "run.rrd"
    assert cli_main(["run", str(data), "--out", str(out), "--rerun-save", str(rrd), "--no-html", "-q",
                     "--mode", "filter"]) == 0
    entities = _read(rrd)
    T = np.loadtxt(out / "trajectory.tum")
    strip = np.array(_latest(entities["/world/trajectory"], "LineStrips3D:strips")[0])
    assert strip.shape == (len(T), 3)  # one position per tracked frame
    np.testing.assert_allclose(strip, T[:, 1:4], atol=1e-5 * (1 + np.abs(T[:, 1:4]).max()))
    # every frame: the image and its keypoints, each in one of the four classes
    n = len(T)
    assert len(entities["/world/camera/image"]) == 12
    feats = [r["Points2D:class_ids"] for f, r in entities["/world/camera/image/features"] if f is not None]
    assert len(feats) == 12 and all(len(c) > 0 for c in feats)
    classes = {int(c) for cs in feats for c in cs}
    assert classes <= {0, 1, 2, 3} and 0 in classes and 2 in classes  # map features and new tracks
    assert len(_latest(entities["/world/map"], "Points3D:positions")) > 20
    # the ground truth, Sim(3)-aligned to the estimate: close to it
    G = np.array(_latest(entities["/world/ground_truth"], "LineStrips3D:strips")[0])
    assert G.shape == (12, 3)
    span = np.ptp(T[:, 1:4], axis=0).max()
    assert 0 < np.sqrt(np.mean(np.sum((G[:n] - T[:, 1:4]) ** 2, 1))) < 0.1 * span


def test_the_stream_leaves_the_estimate_unchanged(data, tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    assert cli_main(["run", str(data), "--out", str(a), "--no-html", "-q", "--mode", "filter"]) == 0
    assert cli_main(["run", str(data), "--out", str(b), "--no-html", "-q", "--mode", "filter",
                     "--rerun-save", str(tmp_path / "b.rrd")]) == 0
    np.testing.assert_array_equal(np.loadtxt(a / "trajectory.tum"), np.loadtxt(b / "trajectory.tum"))


def test_without_rerun_the_command_ends_in_one_line(data, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun raises ImportError
    out = tmp_path / "out"
    assert cli_main(["run", str(data), "--out", str(out), "--viewer", "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["eifslam: error: the viewer needs rerun-sdk: pip install 'eifslam[viewer]'"]
    assert not out.exists()  # checked before any work


def test_a_loop_closure_is_streamed_as_it_is_found(data, tmp_path):
    from eifslam.io import open_source
    from eifslam.system.config import SlamConfig
    from eifslam.system.loops import LoopClosure
    from eifslam.system.runner import run_sequence
    from eifslam.system.slam import Slam
    from eifslam.viz.viewer import RerunViewer

    seq = open_source(data)
    config = SlamConfig().replace(smoothing={"mode": "filter"})
    slam, rrd = Slam(seq.camera, config), tmp_path / "loop.rrd"
    viewer = RerunViewer(seq.camera, save=rrd, ground_truth=seq.ground_truth())
    run_sequence(viewer.watch(seq), config, quiet=True, on_frame=viewer.on_frame(slam), slam=slam)
    last = slam.results[-1]
    # a loop as the loop closer records it, from the last frame to the first keyframe after frame 0
    old = slam.filter.layout.pose_ids[1]
    slam.loops.closures.append(LoopClosure(
        frame=last.frame_id, matched_frame=old, score=0.5, matches=80, inliers=60, required=30,
        five_point_inliers=50, five_point_required=20, fused=60, correction_m=0.01, correction_deg=0.2))
    viewer.log_frame(slam, last)
    viewer.finish(slam)
    entities = _read(rrd)
    texts = [r["TextLog:text"][0] for _, r in entities["/loops"]]
    assert texts == [f"frame {last.frame_id} closed a loop with frame {old} (60 inliers, correction 0.01)"]
    segment = np.array(_latest(entities["/world/loops"], "LineStrips3D:strips")[0])
    ends = np.array([slam.T_wc(last.frame_id)[:3, 3], slam.T_wc(old)[:3, 3]])
    np.testing.assert_allclose(segment, ends, atol=1e-5)


def test_the_viewer_without_a_display_ends_in_one_line(data, tmp_path, monkeypatch, capsys):
    if not sys.platform.startswith("linux"):
        pytest.skip("the display check is Linux's")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert cli_main(["run", str(data), "--out", str(tmp_path / "out"), "--viewer", "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs a display" in err[0] and "--rerun-save" in err[0]


def test_a_recording_in_a_missing_folder_ends_in_one_line_before_any_work(data, tmp_path, capsys):
    out = tmp_path / "out"
    assert cli_main(["run", str(data), "--out", str(out), "--rerun-save", str(tmp_path / "no" / "r.rrd")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"eifslam: error: --rerun-save: {tmp_path / 'no'} is not a folder"] and not out.exists()
