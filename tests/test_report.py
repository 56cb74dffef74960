"""HTML report of a run folder: figures, tables, ground-truth ATE, missing/empty inputs."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from eifslam.errors import DatasetError
from eifslam.geometry.rotations import quat_normalize, rotmat_to_quat
from eifslam.io.ply import write_ply
from eifslam.io.trajectory import Trajectory, write_tum
from eifslam.evaluation.report import parse_frames, read_frames, write_report

FIGURES = ("map_top.png", "map_top_close.png", "map_3d.png", "information_sparsity.png", "timing.png")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _trajectory(rng: np.random.Generator, n: int = 30) -> Trajectory:
    t = 0.1 * np.arange(n)
    p = np.c_[np.cos(0.1 * np.arange(n)), 0.05 * rng.normal(size=n), np.sin(0.1 * np.arange(n))]
    q = quat_normalize(np.c_[np.ones(n), 0.05 * rng.normal(size=(n, 3))])
    return Trajectory(t, p, q)


def _spd(rng: np.random.Generator, n: int) -> sp.csr_array:
    """Random sparse symmetric positive definite matrix (diagonally dominant)."""
    A = sp.random_array((n, n), density=0.05, rng=rng)
    A = A + A.T
    return sp.csr_array(A + sp.diags_array(np.abs(A).sum(axis=1) + 1.0))


def _frames(n: int) -> dict:
    frames = []
    for k in range(n):
        rec = {"frame": k, "timestamp": 0.1 * k, "state": "initialising" if k < 2 else "tracking",
               "ms": {"detect": 5.0 + k % 3, "match": 2.0, "relative_pose": 1.0,
                      "covariance": 0.5, "fuse": 0.2 * k, "recover": 0.1 * k, "total": 12.0 + 0.4 * k},
               "state_dim": 6 * k + 30, "map_features": 10 * k, "nnz": 100 * k}
        if k == 3:  # tolerate missing keys and null values
            del rec["ms"]["recover"], rec["state_dim"]
            rec["ms"]["fuse"] = None
        if k == 4:
            del rec["ms"]
        frames.append(rec)
    frames[-1]["state"] = "lost"
    return {"frames": frames}


def _make_run(tmp_path: Path, rng: np.random.Generator, n_points: int = 500, n_poses: int = 30) -> Trajectory:
    traj = _trajectory(rng, n_poses)
    write_tum(tmp_path / "trajectory.tum", traj.timestamps, traj.positions, traj.quats_wxyz)
    pts = rng.normal(size=(n_points, 3)) * [2.0, 0.5, 2.0]
    write_ply(tmp_path / "map.ply", pts, rng.integers(0, 256, size=(n_points, 3), dtype=np.uint8))
    sp.save_npz(tmp_path / "information.npz", _spd(rng, 120))
    (tmp_path / "frames.json").write_text(json.dumps(_frames(n_poses)))
    (tmp_path / "report.json").write_text(json.dumps(
        {"ate_rmse": 0.123456789, "frames": n_poses, "lost": 1, "timing_ms": {"total": 15.5},
         "sequence": "fake <seq>"}))
    return traj


def _assert_png(path: Path, min_bytes: int = 5000) -> None:
    assert path.is_file(), path
    data = path.read_bytes()
    assert data.startswith(PNG_MAGIC)
    assert len(data) > min_bytes, (path, len(data))


def _img_sources(text: str) -> list[str]:
    return re.findall(r'<img src="([^"]+)"', text)


def test_full_report(tmp_path):
    import matplotlib
    import matplotlib.pyplot as plt

    rng = np.random.default_rng(0)
    _make_run(tmp_path, rng)
    backend, figures = matplotlib.get_backend(), plt.get_fignums()
    out = write_report(tmp_path, title="fake run")
    assert (matplotlib.get_backend(), plt.get_fignums()) == (backend, figures)  # no pyplot state
    assert out == tmp_path / "report.html"
    text = out.read_text()
    assert "<title>fake run</title>" in text
    assert sorted(_img_sources(text)) == sorted(f"figures/{f}" for f in FIGURES)
    for f in FIGURES:
        _assert_png(tmp_path / "figures" / f)
    # report.json figures, nested keys flattened, HTML escaped
    # readable labels with units, 4 significant digits, the exact value and the key beside
    assert re.search(r'<th>ATE RMSE \(ground-truth units\)</th><td data-value="0.123456789">0.1235</td>'
                     r'<td class="key">ate_rmse</td>', text)
    assert '<th>timing ms: total</th><td data-value="15.5">15.5</td>' in text
    assert "fake &lt;seq&gt;" in text
    # no ground truth: no evaluation
    assert 'id="ate-rmse"' not in text and "ground_truth.png" not in text
    assert "Figure left out" not in text
    assert "2 initialising, 27 tracking, 1 lost" in text


def test_ground_truth_ate_is_zero(tmp_path):
    rng = np.random.default_rng(1)
    traj = _make_run(tmp_path, rng)
    R = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    s, t = 2.5, np.array([4.0, -1.0, 0.5])
    gt = Trajectory(traj.timestamps, s * traj.positions @ R.T + t, rotmat_to_quat(R @ traj.rotations))
    text = write_report(tmp_path, ground_truth=gt).read_text()
    ate = float(re.search(r'<span id="ate-rmse"[^>]*>([^<]+)</span>', text).group(1))
    assert 0.0 <= ate < 1e-6
    scale = float(re.search(r'<th>Sim\(3\) scale</th><td data-value="([^"]+)">', text).group(1))
    assert scale == pytest.approx(s, rel=1e-6)
    assert "figures/ground_truth.png" in _img_sources(text)
    _assert_png(tmp_path / "figures" / "ground_truth.png")


def test_ground_truth_without_overlap_is_a_note(tmp_path):
    rng = np.random.default_rng(2)
    traj = _make_run(tmp_path, rng)
    gt = Trajectory(traj.timestamps + 100.0, traj.positions, traj.quats_wxyz)
    text = write_report(tmp_path, ground_truth=gt).read_text()
    assert "Evaluation impossible" in text
    assert "ground_truth.png" not in text


def test_empty_map(tmp_path):
    rng = np.random.default_rng(3)
    _make_run(tmp_path, rng, n_points=0)
    text = write_report(tmp_path).read_text()
    assert "The map has no features" in text
    for f in FIGURES:
        _assert_png(tmp_path / "figures" / f)


def test_one_pose_no_map_no_frames_no_information(tmp_path):
    rng = np.random.default_rng(4)
    _make_run(tmp_path, rng, n_points=0, n_poses=1)
    (tmp_path / "frames.json").unlink()
    sp.save_npz(tmp_path / "information.npz", sp.csr_array((0, 0)))
    text = write_report(tmp_path).read_text()
    assert _img_sources(text) == []
    assert "Nothing to draw: 1 camera pose(s)" in text
    assert "frames.json not found" in text
    assert "information matrix is empty" in text


def test_empty_folder_and_bad_files(tmp_path):
    text = write_report(tmp_path).read_text()
    assert _img_sources(text) == []
    for name in ("trajectory.tum", "map.ply", "information.npz", "frames.json", "report.json"):
        assert f"{name} not found" in text
    (tmp_path / "trajectory.tum").write_text("0 1 2\n")
    (tmp_path / "information.npz").write_bytes(b"not a zip")
    (tmp_path / "frames.json").write_text("{")
    (tmp_path / "report.json").write_text("[1, 2]")
    text = write_report(tmp_path).read_text()
    assert text.count("could not be read") == 4
    assert "expected 8 columns" in text


def test_missing_folder_raises(tmp_path):
    with pytest.raises(DatasetError, match="not found"):
        write_report(tmp_path / "nope")


def test_read_frames_tolerant(tmp_path):
    log = parse_frames(_frames(6))
    assert len(log) == 6 and log.frame.tolist() == list(range(6))
    assert np.isnan(log.stage_ms["recover"][3]) and np.isnan(log.stage_ms["fuse"][3])
    assert np.isnan(log.stage_ms["detect"][4]) and np.isnan(log.state_dim[3])
    assert log.state[-1] == "lost"
    bare = parse_frames([{"state": "tracking"}, "junk", {"ms": {"total": 3}}])
    assert bare.frame.tolist() == [0, 1] and bare.stage_ms["total"][1] == 3.0
    assert len(parse_frames({})) == 0
    with pytest.raises(DatasetError, match="not found"):
        read_frames(tmp_path / "frames.json")


def test_sparsity_plot_counts_nonzeros_and_image_fallback():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from eifslam.evaluation.plots import plot_information_sparsity

    rng = np.random.default_rng(5)
    A = _spd(rng, 80)
    A.data[0] = 0.0  # a stored zero is not a non-zero
    for max_markers, image_size, note in ((10**6, 1000, ""), (10, 1000, " (binned: a black cell holds a non-zero "
                                                                     "among 1 × 1 entries)"),
                                          (10, 20, " (binned: a black cell holds a non-zero among 4 × 4 entries)")):
        fig, ax = plt.subplots()
        plot_information_sparsity(ax, A, max_markers=max_markers, image_size=image_size)
        assert ax.get_title() == f"nz = {A.count_nonzero()}{note}"
        plt.close(fig)


def test_top_view_draws_camera_wedges_and_honours_limits():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from eifslam.evaluation.plots import plot_map_top

    t = np.linspace(0, 2 * np.pi, 30, endpoint=False)
    C = np.c_[np.cos(t), np.zeros(30), np.sin(t)]
    # cameras looking at the centre, y down: R_wc columns (x, y, z) with z = -C
    z = -C
    y = np.tile([0.0, 1.0, 0.0], (30, 1))
    R = np.stack([np.cross(y, z), y, z], axis=2)
    P = np.r_[np.random.default_rng(0).normal(scale=0.1, size=(200, 3)), 50 * np.eye(3)]
    fig, (a, b) = plt.subplots(1, 2)
    plot_map_top(a, C, P, R_wc=R, frusta=10)
    assert len(a.patches) == 10 and a.get_xlabel() == "x (map units)"
    tip = a.patches[0].get_xy()
    ahead = 0.5 * (tip[1] + tip[2]) - tip[0]
    assert ahead @ -C[0, [0, 2]] > 0.9 * np.linalg.norm(ahead)  # the wedge opens where camera 0 looks
    plot_map_top(b, C, P, R_wc=R, limits=(np.full(3, -1.5), np.full(3, 1.5)), frusta=0, units="m")
    assert b.get_xlim() == (-1.5, 1.5) and len(b.patches) == 0 and b.get_ylabel() == "z (m)"
    plt.close(fig)


def test_stage_times_and_subsample():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from eifslam.evaluation.plots import plot_stage_times, subsample_indices

    x = np.array([3.0, 1.0, np.nan, 2.0])
    stages = {"match": np.array([1.0, np.nan, 2.0, 3.0]), "detect": np.ones(4), "total": np.ones(4)}
    fig, (a, b) = plt.subplots(1, 2)
    plot_stage_times(a, x, stages, total_ms=np.full(4, 10.0), stacked=True)
    labels = [t.get_text() for t in a.get_legend().get_texts()]
    assert labels == ["detect", "match", "other", "total"]  # pipeline order, no 'total' stage
    plot_stage_times(b, x, stages, stacked=False)
    assert [len(line.get_xdata()) for line in b.get_lines()] == [3, 2]  # NaN left out
    plt.close(fig)
    idx = subsample_indices(30_000, 20_000, np.random.default_rng(0))
    assert len(idx) == 20_000 and len(np.unique(idx)) == 20_000 and np.all(np.diff(idx) > 0)


def test_headlines_and_readable_tables(tmp_path):
    rng = np.random.default_rng(3)
    _make_run(tmp_path, rng)
    rep = json.loads((tmp_path / "report.json").read_text())
    rep.update(box_ratio_true=0.8, box_ratio_estimated=0.7912, config={"smoothing": {"mode": "smooth"}},
               ate_units="m", stage_ms_median={"detect": 12.3456})
    (tmp_path / "report.json").write_text(json.dumps(rep))
    text = write_report(tmp_path, title="eifslam demo").read_text()
    assert '<p class="headline">Box width:length <span id="box-ratio">0.791</span> (true 0.80)</p>' in text
    assert "<th>Median time per frame, detect (ms)</th>" in text and ">12.35</td>" in text
    assert "<th>ATE RMSE (m)</th>" in text
    # the configuration is a table of its own, folded away
    at = text.index('id="config-smoothing.mode"')
    assert text.rfind("<details>", 0, at) > text.rfind("</details>", 0, at)
    assert 'id="summary-config' not in text


def test_sparsity_marks_pose_and_feature_blocks(tmp_path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from eifslam.evaluation.plots import plot_information_sparsity

    rng = np.random.default_rng(6)
    isf = np.repeat(np.array([False, True, True, False, True]), [7, 3, 3, 7, 3])
    fig, ax = plt.subplots()
    plot_information_sparsity(ax, _spd(rng, len(isf)), is_feature=isf)
    labels = sorted(t.get_text() for t in ax.get_legend().get_texts())
    assert labels == ["feature entries (9)", "pose entries (14)"]
    spans = {c.get_label(): c for c in ax.collections if c.get_label().endswith(")")}
    assert len(spans["pose entries (14)"].get_paths()) == 2 and len(spans["feature entries (9)"].get_paths()) == 2
    plt.close(fig)
    # the report reads the layout beside information.npz; a layout of another size is a note
    _make_run(tmp_path, rng)  # information.npz of 120 entries
    (tmp_path / "state_layout.json").write_text(json.dumps({"kinds": "p" * 6 + "f" * 26}))
    text = write_report(tmp_path).read_text()
    assert "figures/information_sparsity.png" in text and "not marked" not in text
    (tmp_path / "state_layout.json").write_text(json.dumps({"kinds": "p" * 6}))
    assert "describes 42 entries, the matrix has 120" in write_report(tmp_path).read_text()
    (tmp_path / "state_layout.json").write_text("[1, 2]")
    assert "state_layout.json could not be read" in write_report(tmp_path).read_text()


def test_the_page_leads_with_the_trajectory_and_five_numbers(tmp_path):
    rng = np.random.default_rng(4)
    traj = _make_run(tmp_path, rng)
    rep = json.loads((tmp_path / "report.json").read_text())
    rep.update(frames=30, frames_tracked=29, fps=12.345, keyframes=11, loop_closures=[{"frame": 20}],
               evaluation={"ate_rmse": 0.5, "units": "m"}, config={"smoothing": {"mode": "smooth"}})
    (tmp_path / "report.json").write_text(json.dumps(rep))
    text = write_report(tmp_path, ground_truth=traj).read_text()
    numbers = {k: re.search(rf'<span id="{k}"[^>]*>([^<]+)</span>', text).group(1)
               for k in ("frames-tracked", "ate-rmse", "fps", "loops-closed", "keyframes")}
    assert numbers["frames-tracked"] == "29" and numbers["fps"] == "12.3"
    assert numbers["loops-closed"] == "1" and numbers["keyframes"] == "11" and float(numbers["ate-rmse"]) < 1e-6
    sources = _img_sources(text)
    assert sources[0] == "figures/ground_truth.png" and len(sources) == len(set(sources))  # each figure once
    first = text.index('<div class="first">')
    assert max(text.index(f'id="{k}"') for k in numbers) < first < text.index("figures/ground_truth.png")
    # the tables last, folded; the evaluation once (the one computed from the ground truth)
    assert text.index("<details>") > text.index(sources[-1])
    assert text.count("Sim(3) scale") == 1 and 'id="summary-evaluation' not in text
