"""``eifslam batch``: the task list, the task function, skipping complete
folders, failures as rows, the missing-Dask hint, an unreachable scheduler, two runs
through a real local Dask cluster of processes (one of them with a worker killed by
SIGKILL) and one on an existing (threaded) cluster through ``--scheduler``.

The runs are on 4 frames of the built-in scene rendered at 320x240 (a fraction of a
second each); the two cluster tests start worker processes (a few seconds each).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

from eifslam.cli.main import main
from eifslam.errors import EifslamError
from eifslam.evaluation.batch import (
    ROW_KEYS, dataset_names, is_complete, make_tasks, results_markdown, run_serial, run_task, skipped_row, write_results,
)
from eifslam.system.config import SlamConfig


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """``tinyA`` and ``tinyB`` (4 frames each, with ground truth) and ``broken`` (no images)."""
    import cv2

    from eifslam.io import write_camera_yaml, write_tum
    from eifslam.sim.scene import make_scene, render_frame

    root = tmp_path_factory.mktemp("batch-data")
    scene = make_scene(n_frames=54, width=320, height=240)
    for name, first in (("tinyA", 0), ("tinyB", 10)):
        d = root / name
        (d / "images").mkdir(parents=True)
        ks = range(first, first + 4)
        for k in ks:
            assert cv2.imwrite(str(d / "images" / f"{k:06d}.png"), render_frame(scene, k))
        write_camera_yaml(d / "camera.yaml", scene.camera)
        (d / "times.txt").write_text("".join(f"{scene.timestamps[k]:.6f}\n" for k in ks))
        write_tum(d / "groundtruth.tum", scene.timestamps[first:first + 4], scene.positions[first:first + 4],
                  scene.quats_wxyz[first:first + 4])
    (root / "broken" / "images").mkdir(parents=True)
    return root


def _filter(detector: str = "sift") -> SlamConfig:
    return SlamConfig().replace(smoothing={"mode": "filter"}, frontend={"detector": detector})


def test_task_list_names_are_unique(tmp_path):
    assert dataset_names(["a/seq", "b/seq", "c/seq", "clip.mp4"]) == ["seq", "seq-2", "seq-3", "clip"]
    tasks = make_tasks(["a/seq", "b/seq"], [_filter(), _filter("orb")], tmp_path, max_frames=3)
    names = [t.name for t in tasks]
    assert names == ["seq-filter-sift", "seq-filter-orb", "seq-2-filter-sift", "seq-2-filter-orb"]
    assert len({t.out_dir for t in tasks}) == 4 and all(t.max_frames == 3 for t in tasks)
    assert SlamConfig.from_dict(tasks[1].config).frontend.detector == "orb"
    with pytest.raises(EifslamError, match="share a folder"):
        make_tasks(["a"], [_filter(), _filter()], tmp_path)


def test_tasks_run_fail_as_rows_and_skip_when_complete(data, tmp_path):
    tasks = make_tasks([data / "tinyA", data / "broken"], [_filter()], tmp_path, html=False)
    seen = []
    rows = run_serial(tasks, on_row=lambda k, r: seen.append(k))
    assert seen == [0, 1]
    ok, bad = rows
    assert tuple(ok) == ROW_KEYS and tuple(bad) == ROW_KEYS
    assert (ok["dataset"], ok["mode"], ok["features"], ok["status"], ok["error"]) == ("tinyA", "filter", "sift",
                                                                                      "done", None)
    assert ok["frames"] == 4 and 3 <= ok["tracked"] <= 4 and ok["ate_units"] == "m"
    assert 0 < ok["ate_rmse"] < 0.05 and math.isfinite(ok["ate_rmse"])  # the box scene is metres wide
    assert ok["seconds"] > 0 and is_complete(tasks[0].out_dir)
    report = json.loads((Path(tasks[0].out_dir) / "report.json").read_text())
    assert report["frames_tracked"] == ok["tracked"]
    assert bad["status"] == "failed" and "broken" in bad["error"] and "\n" not in bad["error"]
    assert bad["frames"] is None and not is_complete(tasks[1].out_dir)
    # a re-run skips the complete folder and tries the failed one again; --force redoes both
    again = run_serial(tasks)
    assert [r["status"] for r in again] == ["skipped", "failed"]
    assert again[0]["ate_rmse"] == ok["ate_rmse"] and again[0]["tracked"] == ok["tracked"]
    assert [r["status"] for r in run_serial(tasks, force=True)] == ["done", "failed"]
    write_results(tmp_path, rows)
    assert json.loads((tmp_path / "results.json").read_text()) == rows
    md = (tmp_path / "results.md").read_text()
    assert "2 tasks, 1 failed" in md and "| tinyA | filter | sift | done |" in md


def test_an_interrupted_run_is_not_complete(data, tmp_path):
    task = make_tasks([data / "tinyA"], [_filter()], tmp_path, html=False)[0]
    out = Path(task.out_dir)
    out.mkdir()
    (out / "report.json").write_text("{not json")
    assert not is_complete(out)
    (out / "report.json").write_text(json.dumps({"frames": 4, "stopped": "interrupted (SIGTERM)"}))
    assert not is_complete(out)
    (out / "report.json").write_text(json.dumps({"frames": 4, "frames_tracked": 0}))
    assert is_complete(out)
    row = skipped_row(task)  # complete, but as `eifslam run` says: a failure
    assert row["status"] == "skipped" and row["error"] == "no frame could be tracked (4 read)"
    assert "no frame could be tracked" in results_markdown([row])
    row = run_task(task)
    assert row["status"] == "done" and row["tracked"] >= 3  # the stale report was replaced


def test_without_dask_the_command_says_how_to_install_it(data, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    rc = main(["batch", str(data / "tinyA"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert 'pip install "eifslam[batch]"' in err and 'pip install -e ".[batch]"' in err
    assert not (tmp_path / "out").exists()  # checked before any work


def test_batch_command_on_a_local_cluster(data, tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["batch", str(data / "tinyA"), str(data / "broken"), "--out", str(out), "--mode", "filter",
            "--workers", "1", "--no-html", "-q"]
    assert main(argv) == 1  # one task failed; every row is written
    rows = json.loads((out / "results.json").read_text())
    assert [(r["dataset"], r["status"]) for r in rows] == [("tinyA", "done"), ("broken", "failed")]
    assert rows[0]["error"] is None and 0 < rows[0]["ate_rmse"] < 0.05
    assert (out / "tinyA-filter-sift" / "trajectory.tum").is_file()
    assert "| tinyA | filter | sift | done |" in (out / "results.md").read_text()
    report = json.loads((out / "tinyA-filter-sift" / "report.json").read_text())
    assert report["command"].startswith("eifslam batch") and report["config"]["smoothing"]["mode"] == "filter"
    assert "broken filter sift:" in capsys.readouterr().err
    # complete: skipped without starting a cluster
    assert main(["batch", str(data / "tinyA"), "--out", str(out), "--mode", "filter", "-q"]) == 0
    assert [r["status"] for r in json.loads((out / "results.json").read_text())] == ["skipped"]


def test_a_killed_worker_gives_a_row_and_the_others_finish(data, tmp_path):
    from eifslam.cli.cluster import run_on_dask

    def task_function(task):  # defined here: Dask sends it to the workers by value
        import os
        import signal

        from eifslam.evaluation.batch import run_task

        if task.dataset == "tinyB":
            os.kill(os.getpid(), signal.SIGKILL)
        return run_task(task)

    tasks = make_tasks([data / "tinyB", data / "tinyA", data / "broken"], [_filter()], tmp_path, html=False)
    arrived = []
    rows = run_on_dask(tasks, workers=2, progress=False, task_function=task_function,
                       on_row=lambda k, r: arrived.append(k))
    assert sorted(arrived) == [0, 1, 2]
    killed, ok, bad = rows
    assert killed["status"] == "failed" and "KilledWorker" in killed["error"] and "\n" not in killed["error"]
    assert ok["status"] == "done" and ok["error"] is None and ok["tracked"] >= 3
    assert bad["status"] == "failed" and "no image" in bad["error"]


def test_batch_on_an_existing_scheduler(data, tmp_path):
    import cv2
    from distributed import LocalCluster

    threads = cv2.getNumThreads()  # the task sets OpenCV's threads of this process (workers are threads here)
    out = tmp_path / "out"
    try:
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
            rc = main(["batch", str(data / "tinyB"), "--out", str(out), "--mode", "filter", "--no-html", "-q",
                       "--scheduler", cluster.scheduler_address])
    finally:
        cv2.setNumThreads(threads)
    rows = json.loads((out / "results.json").read_text())
    assert rc == 0 and [(r["dataset"], r["status"]) for r in rows] == [("tinyB", "done")]
    assert rows[0]["tracked"] >= 3 and 0 < rows[0]["ate_rmse"] < 0.05


def test_an_unreachable_scheduler_is_one_line(data, tmp_path, capsys, monkeypatch):
    import distributed

    from eifslam.cli import cluster

    def refuse(address, timeout=None):  # what Client says after its timeout, without the wait
        raise OSError(f"Timed out trying to connect to {address} after 15 s")

    monkeypatch.setattr(distributed, "Client", refuse)
    rc = main(["batch", str(data / "tinyA"), "--out", str(tmp_path / "out"), "-q", "--scheduler", "tcp://127.0.0.1:9"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and err == ["eifslam: error: tcp://127.0.0.1:9: cannot connect to the Dask scheduler "
                               "(OSError: Timed out trying to connect to tcp://127.0.0.1:9 after 15 s)"]
    rows = json.loads((tmp_path / "out" / "results.json").read_text())
    assert rows[0]["status"] == "failed" and "cannot connect" in rows[0]["error"]
    assert cluster.INSTALL_HINT.startswith("eifslam batch needs Dask")
