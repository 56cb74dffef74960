"""report.html in a real headless browser (``benchmarks/report_screenshot.py``): its first
1000 pixels of height show the trajectory figure and the five numbers. Skipped without
Playwright or a Chromium to drive."""

from __future__ import annotations

import json

import numpy as np
import pytest

from eifslam.evaluation.report import write_report

from benchmarks.report_screenshot import NoBrowser, first_screen
from test_report import PNG_MAGIC, _make_run

pytest.importorskip("playwright")


@pytest.mark.parametrize("with_ground_truth", [True, False])
def test_the_first_screen_shows_the_trajectory_and_five_numbers(tmp_path, with_ground_truth):
    traj = _make_run(tmp_path, np.random.default_rng(5), n_points=2000)
    rep = json.loads((tmp_path / "report.json").read_text())
    rep.update(frames=30, frames_tracked=29, fps=8.5, keyframes=12, loop_closures=[],
               config={"smoothing": {"mode": "smooth"}, "frontend": {f"k{i}": i for i in range(60)}})
    (tmp_path / "report.json").write_text(json.dumps(rep))
    report = write_report(tmp_path, ground_truth=traj if with_ground_truth else None)
    png = tmp_path / "first.png"
    try:
        checks = first_screen(report, png)
    except NoBrowser as exc:
        pytest.skip(str(exc))
    assert [name for name, _, _ in checks] == ["number frames-tracked", "number ate-rmse", "number fps",
                                               "number loops-closed", "number keyframes", "trajectory figure"]
    assert all(ok for _, ok, _ in checks), checks
    figure = checks[-1][2]
    assert figure.startswith("figures/ground_truth.png" if with_ground_truth else "figures/map_top.png")
    assert png.read_bytes().startswith(PNG_MAGIC)
