"""Fast tests of ``benchmarks.realtime``: its statistics on known numbers, and one smoke
run of ``python -m benchmarks.realtime`` on a tiny rendered scene (5 frames of 320x240,
SIFT, filter mode)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_benchmark_scripts import _tiny_dataset, run_module

from benchmarks import realtime


def test_statistics_on_known_numbers():
    st = realtime.percentile_stats(list(range(1, 101)))  # 1..100
    assert st["median"] == pytest.approx(50.5) and st["n"] == 100
    assert st["p95"] == pytest.approx(95.05)  # linear interpolation: 1 + 0.95 * 99
    assert realtime.percentile_stats([]) == {"median": None, "p95": None, "n": 0}
    frames = [{"frame": k, "ms": {"total": 10.0 + k, "detect": 5.0}} for k in range(20)]
    frames[3]["ms"]["recover"] = 7.0
    s = realtime.stage_stats(frames)
    assert set(s) == {"total", "detect", "recover"}
    assert s["recover"] == {"median": 7.0, "p95": 7.0, "n": 1}
    f = realtime.flatness(frames)  # first 2 frames: 10, 11; last 2: 28, 29
    assert f["first10_ms"] == pytest.approx(10.5) and f["last10_ms"] == pytest.approx(28.5)
    assert f["last_over_first"] == pytest.approx(28.5 / 10.5)
    assert realtime.flatness(frames[:5])["last_over_first"] is None
    assert realtime.camera_rate_hz([0.0, 0.1, 0.2, 0.3]) == pytest.approx(10.0)
    assert realtime.camera_rate_hz([1.0]) is None


def test_parse_settings():
    assert realtime.parse_settings(["max_features=1000", "map_fraction=0.5", "seed=null", "color_order=rgb"]) \
        == {"max_features": 1000, "map_fraction": 0.5, "seed": None, "color_order": "rgb"}
    with pytest.raises(ValueError):
        realtime.parse_settings(["nokey"])


def test_realtime_smoke(tmp_path):
    data = tmp_path / "data"
    _tiny_dataset(data / "tiny", 5)
    out = tmp_path / "out"
    r = run_module("realtime", "--data", str(data), "--out", str(out), "--only", "tiny,nope", "--detectors", "sift",
                   "--smooth", "--set", "max_features=500", "--tag", "t")
    summary = json.loads((out / "realtime.json").read_text())
    assert len(summary["rows"]) == 1
    row = summary["rows"][0]
    assert row["error"] is None, row["error"]
    assert r.returncode == 0, r.stderr
    assert (row["dataset"], row["detector"], row["frames"], row["settings"]) == ("tiny", "sift", 5, {"max_features": 500})
    assert row["frames_tracked"] >= 4 and np.isfinite(row["ate_filter"]) and np.isfinite(row["ate_smooth"])
    assert row["cpu_seconds"] > 0 and row["cpu_ms_per_frame"] > 0
    assert row["fps"] > 0 and row["camera_hz"] == pytest.approx(2.0)  # the scene: a frame every 0.5 s
    for s in ("detect", "match", "total", "wait"):
        assert row["stages"][s]["n"] >= 4 and row["stages"][s]["p95"] >= row["stages"][s]["median"] > 0
    assert summary["command"].startswith("python -m benchmarks.realtime ") and "--only tiny,nope" in summary["command"]
    assert summary["machine"]["opencv"]
    run = out / "tiny-sift-t"
    frames = json.loads((run / "frames.json").read_text())["frames"]
    assert [f["frame"] for f in frames] == list(range(5)) and all(f["ms"]["total"] > 0 for f in frames)
    assert (run / "frames.png").stat().st_size > 1000 and (run / "report.json").exists()
    assert "| tiny [t] | sift | 5 |" in r.stdout
    page = (out / "realtime.md").read_text()
    assert page.startswith("# ") and "- Commit: " in page and "Command: `python -m benchmarks.realtime" in page
    assert "| tiny [t] | sift | 5 |" in page
    assert realtime.main(["--data", str(data), "--out", str(tmp_path / "o2"), "--only", "nothing"]) == 2


def test_peak_memory_reset_forgets_what_an_earlier_run_freed():
    """The peak of a run starts from what the process holds once the runs before handed
    their freed memory back, not from their peak."""
    if realtime.peak_rss_mb() is None or not realtime.reset_peak_rss():
        pytest.skip("no /proc peak to read or reset here")
    before = realtime.peak_rss_mb()
    a = np.ones(200_000_000 // 8)  # 200 MB, touched
    assert realtime.peak_rss_mb() > before + 150
    del a
    assert realtime.reset_peak_rss()
    assert realtime.peak_rss_mb() < before + 50
