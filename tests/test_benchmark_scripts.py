"""Fast tests of the benchmarks package: its shared helpers, and the benchmarks run as modules.

The pure parts (row building, table formatting, data set discovery, the provenance header)
are tested on fake report dicts; the smoke runs start ``python -m benchmarks.<name>`` from
the repository's root, as a user does, on a tiny rendered scene (4 frames of 320x240).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import _common as common
from benchmarks import run_all

ROOT = Path(__file__).resolve().parents[1]


def run_module(name: str, *args: str) -> subprocess.CompletedProcess:
    """``python -m benchmarks.<name> args`` from the repository's root (the environment's
    ``PYTHONPATH`` passed on, so the same eifslam is imported)."""
    return subprocess.run([sys.executable, "-m", f"benchmarks.{name}", *args], cwd=ROOT, capture_output=True,
                          text=True, env=dict(os.environ), timeout=600)


def fake_report(**over) -> dict:
    """A report.json dict as run_to_folder returns it."""
    rep = dict(frames=10, frames_tracked=8, frames_lost=2, map_features=123, mode="filter", detector="sift",
               stage_ms_median=dict(detect=20.0, match=5.0, relative_pose=3.0, covariance=1.0, init=2.0,
                                    fuse=0.5, recover=1.5, total=33.0),
               total_seconds=4.0, fps=2.5, ate_rmse=0.048, ate_percent=0.5)
    rep.update(over)
    return rep


# -- pure parts ---------------------------------------------------------------------------
def test_build_row_from_report():
    row = common.build_row("kitti-seq1", "filter", "sift", fake_report())
    assert row["tracked_pct"] == pytest.approx(80.0)
    assert row["colmap_ate"] == 0.024
    assert row["ate_ratio_colmap"] == pytest.approx(2.0)
    assert row["ms_fuse"] == 0.5 and row["ms_total"] == 33.0
    assert row["ms_backend"] == pytest.approx(2.0)  # fuse + recover medians when not given
    assert row["error"] is None and row["box_ratio_estimated"] is None and row["ba"] is None
    json.dumps(row)  # JSON-ready


def test_build_row_failure_and_missing_figures():
    row = common.build_row("mine", "ba", "orb", None, error="DatasetError: no images")
    assert row["error"] == "DatasetError: no images"
    assert row["frames"] is None and row["ate_rmse"] is None and row["colmap_ate"] is None
    row = common.build_row("builtin", "ba", "orb", fake_report(ate_rmse=None, ba={"seconds": 1.0},
                                                             box_ratio_estimated=0.81, box_ratio_true=0.8),
                           ms_backend=7.0)
    assert row["ate_ratio_colmap"] is None and row["ba"] == {"seconds": 1.0}
    assert row["box_ratio_estimated"] == 0.81 and row["ms_backend"] == 7.0


def test_fmt_and_markdown_table():
    assert common.fmt(None) == "–" and common.fmt(12) == "12" and common.fmt(0.0) == "0"
    assert common.fmt(0.0123456) == "0.0123" and common.fmt(12345.6) == "12346"
    assert common.fmt(float("nan")) == "nan"
    t = common.markdown_table(["a", "b"], [["1", "x|y"]])
    assert t.splitlines() == ["| a | b |", "|---|---|", "| 1 | x\\|y |"]


def test_format_table_columns():
    rows = [common.build_row("kitti-seq1", "filter", "sift", fake_report()),
            common.build_row("builtin", "smooth", "orb", fake_report(box_ratio_estimated=0.79, box_ratio_true=0.8)),
            common.build_row("x", "ba", "sift", None, error="RuntimeError: boom\nmore")]
    lines = run_all.format_table(rows).strip().splitlines()
    assert len(lines) == 2 + len(rows)
    n_cols = len(run_all.HEADERS)
    assert all(line.count(" | ") == n_cols - 1 for line in lines if not line.startswith("|---"))
    assert "COLMAP ATE" in lines[0] and "ratio to COLMAP" in lines[0]
    assert "2×" in lines[2] and "8/10 (80%)" in lines[2]
    assert "0.790 (true 0.80)" in lines[3]
    assert "RuntimeError: boom" in lines[4] and "more" not in lines[4]


def test_discover_and_select(tmp_path):
    for name in ("b-set", "a-set", ".hidden"):
        (tmp_path / name / "images").mkdir(parents=True)
    (tmp_path / "no-images").mkdir()
    (tmp_path / "file.txt").write_text("x")
    assert [p.name for p in common.discover_datasets(tmp_path)] == ["a-set", "b-set"]
    assert common.discover_datasets(tmp_path / "missing") == []
    sel, missing = run_all.select_datasets(tmp_path, None)
    assert [n for n, _ in sel] == ["a-set", "b-set", "builtin"] and sel[-1][1] is None
    sel, missing = run_all.select_datasets(tmp_path, ["builtin", "b-set", "zzz"])
    assert [n for n, _ in sel] == ["b-set", "builtin"] and missing == ["zzz"]


def test_split_list():
    assert common.split_list(" filter, smooth,,ba ") == ["filter", "smooth", "ba"]
    assert common.split_list(None) == [] and common.split_list("") == []


def test_backend_ms_median(tmp_path):
    f = tmp_path / "frames.json"
    f.write_text(json.dumps({"frames": [{"ms": {"detect": 1}}, {"ms": {"fuse": 1.0, "recover": 2.0}},
                                        {"ms": {"fuse": 3.0}}, {"ms": {"recover": 10.0, "fuse": 0.0}}]}))
    assert common.backend_ms_median(f) == pytest.approx(3.0)
    assert common.backend_ms_median(tmp_path / "missing.json") is None


def test_command_line_and_markdown_header():
    """Every generated Markdown page opens with the date, the machine, the commit and the
    command that reproduces it (``python -m benchmarks.<name> ...``)."""
    command = common.command_line("benchmarks.run_all", ["--out", "a b"])
    assert command == "python -m benchmarks.run_all --out 'a b'"
    info = dict(date_utc="Mon 00:00 UTC", platform="Linux", cpu_count=4, cpus_usable=2, python="3.11",
                numpy="2", scipy="1", opencv="4", eifslam_commit="abc1234")
    md = common.markdown_header("Results", command, info)
    lines = md.splitlines()
    assert lines[0] == "# Results"
    assert "- Date: Mon 00:00 UTC" in lines and "- Machine: Linux, 4 CPUs (2 usable)" in lines
    assert "- Commit: abc1234" in lines and f"- Command: `{command}`" in lines
    assert "- Commit: unknown" in common.markdown_header("R", command, dict(info, eifslam_commit=None))
    live = common.machine_info()
    assert live["cpu_count"] >= 1 and live["platform"] and live["date_utc"].endswith("UTC")


# -- smoke run on a tiny rendered scene -----------------------------------------------------
def _tiny_dataset(root: Path, n: int = 4) -> Path:
    """Render the first ``n`` frames of a small built-in scene into a data folder."""
    import cv2

    from eifslam.io import write_camera_yaml, write_tum
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54, width=320, height=240)
    (root / "images").mkdir(parents=True)
    for k in range(n):
        assert cv2.imwrite(str(root / "images" / f"{k:06d}.png"), render_frame(scene, k))
    write_camera_yaml(root / "camera.yaml", scene.camera)
    (root / "times.txt").write_text("".join(f"{t:.6f}\n" for t in scene.timestamps[:n]))
    write_tum(root / "groundtruth.tum", scene.timestamps[:n], scene.positions[:n], scene.quats_wxyz[:n])
    return root


def test_run_all_smoke(tmp_path):
    """``python -m benchmarks.run_all`` on one tiny data set: the row, the run's folder,
    and both Markdown pages under their provenance header."""
    data = tmp_path / "data"
    _tiny_dataset(data / "tiny")
    (data / "empty").mkdir()  # no images/: not a data set
    out = tmp_path / "out"
    docs = tmp_path / "docs" / "results.md"
    cfg = tmp_path / "c.yaml"  # --config: every run takes these settings (mode and detector from the options)
    cfg.write_text("smoothing:\n  mode: smooth\n")
    r = run_module("run_all", "--data", str(data), "--out", str(out), "--modes", "filter", "--detectors", "sift",
                   "--only", "tiny", "--docs", str(docs), "--config", str(cfg))
    rows = json.loads((out / "results.json").read_text())
    assert len(rows) == 1
    row = rows[0]
    assert row["error"] is None, row["error"]
    assert r.returncode == 0, r.stderr
    assert (row["dataset"], row["mode"], row["detector"], row["frames"]) == ("tiny", "filter", "sift", 4)
    assert row["frames_tracked"] >= 3 and row["ate_rmse"] is not None and np.isfinite(row["ate_rmse"])
    assert row["ms_total"] > 0
    rep = json.loads((out / "tiny-filter-sift" / "report.json").read_text())
    assert rep["config"]["smoothing"]["mode"] == "filter"
    assert not (out / "tiny-filter-sift" / "report.html").exists()
    for page in (out / "results.md", docs):
        text = page.read_text()
        assert text.startswith("# ") and "- Date: " in text and "- Machine: " in text and "- Commit: " in text
        assert "Command: `python -m benchmarks.run_all --data" in text and "--only tiny" in text
        assert "| tiny | filter | sift |" in text
    assert "| tiny | filter | sift |" in r.stdout


def test_run_all_refuses_a_bad_config_file(tmp_path, capsys):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("mapping:\n  no_such_setting: 1\n")
    rc = run_all.main(["--data", str(tmp_path), "--out", str(tmp_path / "out"), "--only", "builtin",
                       "--config", str(cfg)])
    assert rc == 2 and not (tmp_path / "out" / "results.json").exists()
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "no_such_setting" in err


def test_run_all_records_failures(tmp_path):
    data = tmp_path / "data"
    (data / "broken" / "images").mkdir(parents=True)  # no camera, no images: open_source fails
    rc = run_all.main(["--data", str(data), "--out", str(tmp_path / "out"), "--modes", "filter,smooth",
                       "--detectors", "orb", "--only", "broken"])
    rows = json.loads((tmp_path / "out" / "results.json").read_text())
    assert rc == 1 and len(rows) == 2 and all(r["error"] for r in rows)
    assert run_all.main(["--data", str(data), "--out", str(tmp_path / "o2"), "--only", "nothing"]) == 2


def test_batch_speedup_picks_the_smallest_sets(tmp_path):
    from benchmarks import batch_speedup

    for name, n in (("big", 5), ("small", 2), ("mid", 3), ("other", 3)):
        (tmp_path / name / "images").mkdir(parents=True)
        for k in range(n):
            (tmp_path / name / "images" / f"{k:03d}.png").write_bytes(b"")
        (tmp_path / name / "images" / "notes.txt").write_text("not an image")
    assert batch_speedup.smallest_datasets(tmp_path, 3) == [("small", 2), ("mid", 3), ("other", 3)]
    assert batch_speedup.smallest_datasets(tmp_path / "missing", 4) == []


def test_consistency_benchmark_writes_its_json(tmp_path):
    """``python -m benchmarks.consistency`` on 2 tiny runs: the JSON and the PNG, and the
    interval of the mean NEES (50 runs of 6 DOF: 5.08-7.00)."""
    from benchmarks import consistency

    lo, hi = consistency.interval(50)
    assert lo == pytest.approx(5.08, abs=0.01) and hi == pytest.approx(7.00, abs=0.01)
    assert consistency.parse_sets(["experimental.zm_gate_chi2=none", "mapping.min_feature_parallax_deg=4"]) == \
        {"experimental": {"zm_gate_chi2": None}, "mapping": {"min_feature_parallax_deg": 4}}
    r = run_module("consistency", "--out", str(tmp_path), "--runs", "2", "--frames", "6", "--every", "3")
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "consistency.json").read_text())
    for mode in ("filter", "smooth"):
        assert set(res[mode]) >= {"mean_nees", "lo", "hi", "runs", "frames"}
        assert res[mode]["runs"] == 2 and res[mode]["frames"] == 6
        assert 0 < res[mode]["mean_nees"] < 1e3
        assert f"{mode}: mean NEES" in r.stdout
    assert res["per_frame"]["frame"] == [2, 5]
    assert all(1.0 <= c < 1.5 for c in res["per_frame"]["cost_ratio"])  # the filter's cost, never below the smoothed
    assert res["command"].startswith("python -m benchmarks.consistency --out") and res["machine"]["cpu_count"]
    assert (tmp_path / "consistency.png").stat().st_size > 0


def test_consistency_benchmark_scores_frames_between_keyframes(tmp_path):
    """A short corridor step leaves frames between keyframes: their reported covariance is
    scored too."""
    r = run_module("consistency", "--out", str(tmp_path), "--runs", "1", "--frames", "12", "--every", "6",
                   "--step", "0.1", "--fps", "10")
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "consistency.json").read_text())
    assert res["between"]["runs"] == 1 and 0 < res["between"]["mean_nees"] < 1e3
    assert res["settings"]["step"] == 0.1 and len(res["per_frame"]["between"]) == 2


def test_consistency_jobs_give_the_same_figures(tmp_path):
    """``--jobs 2`` gives the same figures as one process."""
    args = ["--runs", "2", "--frames", "6", "--every", "6"]
    for d, extra in (("one", []), ("two", ["--jobs", "2"])):
        r = run_module("consistency", "--out", str(tmp_path / d), *args, *extra)
        assert r.returncode == 0, r.stderr
    one, two = (json.loads((tmp_path / d / "consistency.json").read_text()) for d in ("one", "two"))
    assert one["filter"] == two["filter"] and one["smooth"] == two["smooth"]


def test_frontend_benchmark_smoke(tmp_path):
    """``python -m benchmarks.frontend`` on five rendered frames: per-detector timings and
    relative-pose errors in the JSON, one table row per detector on stdout."""
    data = _tiny_dataset(tmp_path / "tiny", 5)
    r = run_module("frontend", "--data", str(data), "--out", str(tmp_path / "out"), "--detectors", "sift")
    assert r.returncode == 0, r.stderr
    res = json.loads((tmp_path / "out" / "frontend.json").read_text())
    sift = res["detectors"]["sift"]
    assert sift["ms_median"] > 0 and sift["pairs"] == 4 and set(sift["stages_ms_median"]) >= {"detect", "match"}
    assert res["command"].startswith("python -m benchmarks.frontend") and res["machine"]["platform"]
    assert "| sift |" in r.stdout


def test_every_benchmark_runs_as_a_module():
    """Each benchmark answers ``--help`` when run as ``python -m benchmarks.<name>``."""
    names = sorted(p.stem for p in (ROOT / "benchmarks").glob("*.py") if not p.stem.startswith("_"))
    assert {"run_all", "realtime", "consistency", "loop_closure", "frontend", "backend_scaling"} <= set(names)
    for name in names:
        r = run_module(name, "--help")
        assert r.returncode == 0 and "usage" in r.stdout, (name, r.stderr)


def test_loop_scoring_view_overlap_and_same_place():
    """``view_overlap`` (the smaller share of one view, at its scene depth, that the other
    camera sees at a like depth) is 1 for one camera, 0 for two looking apart or at scenes
    of unlike depths, and about a half for a sideways shift of half the view's width at the
    depth; ``same_place`` asks a fifth."""
    from benchmarks import loop_closure as lc
    from eifslam.geometry.camera import PinholeCamera

    cam = PinholeCamera(fx=320.0, fy=320.0, cx=319.5, cy=239.5, width=640, height=480)
    eye = np.eye(3)
    here = (np.zeros(3), eye)
    depth = 2.0
    width_at_depth = depth * cam.width / cam.fx  # 4 m
    assert lc.view_overlap(cam, here, here, depth) == 1.0 and lc.same_place(cam, here, here, depth)
    assert lc.view_overlap(cam, here, here, depth, 5 * depth) == 0.0  # the same ray, another scene depth
    away = (np.zeros(3), np.diag([-1.0, 1.0, -1.0]))  # looking the other way
    assert lc.view_overlap(cam, here, away, depth) == 0.0 and not lc.same_place(cam, here, away, depth)
    half = (np.array([0.5 * width_at_depth, 0.0, 0.0]), eye)
    assert 0.4 <= lc.view_overlap(cam, here, half, depth) <= 0.6 and lc.same_place(cam, here, half, depth)
    far = (np.array([0.9 * width_at_depth, 0.0, 0.0]), eye)  # a tenth of each view shared
    assert not lc.same_place(cam, here, far, depth) and 0.0 < lc.view_overlap(cam, here, far, depth) < 0.2


def test_posterior_samples_have_the_inverse_information_as_covariance():
    """``benchmarks._posterior.posterior_samples`` (the spread backend_scaling reads the online
    estimate against): draws whose sample covariance matches the dense ``I^-1`` of the
    information the last relinearisation built, two-sided; ``ate_between`` ignores a
    similarity transform."""
    from eifslam.sim import synthetic
    from eifslam.sim.frontend import SyntheticFrontEnd
    from eifslam.system.slam import Slam

    from benchmarks import _posterior as post
    rng = np.random.default_rng(2)
    sc = synthetic.corridor_scene(6, rng, points_per_metre=6)
    fe = SyntheticFrontEnd(sc, 2, map_fraction=1.0)
    slam = Slam(sc.camera, fe.slam_config(), frontend=fe)
    for k in range(len(sc.positions)):
        slam.track(k)
    f = slam.filter
    f.complete_estimate()
    for _ in range(3):  # to convergence, so that x is the last linearisation point
        fused = f.relinearise()
        f.recover()
    fused = f.relinearise()
    Iinv = np.linalg.inv(f.information_matrix().toarray())
    cols = f.layout.pose_columns(f.layout.pose_ids)[1:, :3].ravel()  # positions, the fixed first pose left out
    Y = np.array(post.posterior_samples(f, fused, 800, np.random.default_rng(0)))[:, cols]
    ratio = Y.var(axis=0) / np.diag(Iinv)[cols]
    assert 0.75 < np.median(ratio) < 1.3 and 0.6 < ratio.min() and ratio.max() < 1.6
    P = post.positions(f, f.x)
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    assert post.ate_between(2.5 * P @ R.T + 1.0, P) < 1e-9
    assert post.ate_between(P + rng.normal(0, 0.1, P.shape), P) > 0.01


def test_backend_scaling_checks_survive_untimed_fusion():
    """``checks`` on a run too short to time any fusion (every ``fuse_ms`` 0 at first):
    the constant-fusion check fails with a NaN ratio instead of dividing by zero, and a
    flat run passes it."""
    from benchmarks import backend_scaling as bs
    rows = [dict(state_dim=7 * (k + 1), fuse_ms=0.0 if k < 5 else 0.6, recover_ms=0.1 * (k + 1),
                 nnz=49 * (k + 1)) for k in range(20)]
    out = bs.checks(rows)["fuse_constant"]
    assert np.isnan(out["ratio"]) and not out["passed"]
    flat = [dict(r, fuse_ms=0.5) for r in rows]
    out = bs.checks(flat)["fuse_constant"]
    assert out["ratio"] == pytest.approx(1.0) and out["passed"]
