"""Evaluation: Sim(3)-aligned ATE, RPE, tracked fraction; evo cross-checks; eval command."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from eifslam.evaluation.metrics import EvaluationError, Sim3, align_sim3, evaluate, to_evo
from eifslam.geometry.rotations import quat_normalize, rotmat_to_quat, rotvec_exp
from eifslam.io.trajectory import Trajectory, read_tum, write_tum



def _gt(rng: np.random.Generator, n: int = 200) -> Trajectory:
    t = 0.05 * np.arange(n)
    p = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    q = quat_normalize(rng.normal(size=(n, 4)))
    return Trajectory(t, p, q)


def _transform(tr: Trajectory, s: float, R: np.ndarray, t: np.ndarray, noise: np.ndarray | None = None):
    """The trajectory in another world frame: x' = s R x + t, R_wc' = R R_wc."""
    p = tr.positions if noise is None else tr.positions + noise
    return Trajectory(tr.timestamps, s * p @ R.T + t, rotmat_to_quat(R @ tr.rotations))


def test_imports_neither_cv2_nor_matplotlib():
    code = (
        "import sys, eifslam.evaluation.metrics\n"
        "bad = [m for m in ('cv2', 'matplotlib') if m in sys.modules]\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_exact_sim3_copy_gives_zero_error():
    rng = np.random.default_rng(0)
    gt = _gt(rng)
    R = Rotation.random(random_state=1).as_matrix()
    est = _transform(gt, 0.2, R, np.array([3.0, -1.0, 7.0]))
    res = evaluate(est, gt)
    assert res.ate_rmse < 1e-9 and res.ate_max < 1e-9
    assert res.sim3.scale == pytest.approx(5.0)
    np.testing.assert_allclose(res.sim3.rotation, R.T, atol=1e-9)
    np.testing.assert_allclose(res.sim3.apply(est.positions), gt.positions, atol=1e-8)
    np.testing.assert_allclose(res.aligned_positions, gt.positions, atol=1e-8)
    assert res.tracked_fraction == 1.0 and res.n_matched == len(gt)
    assert np.max(res.rpe_rot_deg) < 1e-6 and np.max(res.rpe_dir_deg) < 1e-5
    assert res.gt_path_length == pytest.approx(gt.path_length)
    M = res.sim3.matrix
    np.testing.assert_allclose(M[:3, :3] @ est.positions[0] + M[:3, 3], gt.positions[0], atol=1e-8)


def test_known_noise_gives_ate_in_band():
    rng = np.random.default_rng(2)
    gt = _gt(rng, 1000)
    sigma = 0.05
    noise = rng.normal(scale=sigma, size=gt.positions.shape)
    R = Rotation.random(random_state=3).as_matrix()
    res = evaluate(_transform(gt, 3.0, R, np.array([1.0, 2.0, 3.0]), noise), gt)
    expected = sigma * np.sqrt(3.0)  # RMS of a 3-D isotropic error
    assert 0.9 * expected < res.ate_rmse < 1.1 * expected
    assert res.ate_percent == pytest.approx(100 * res.ate_rmse / gt.path_length)


def test_tracked_fraction_and_time_offsets():
    rng = np.random.default_rng(4)
    gt = _gt(rng, 100)
    keep = np.sort(rng.choice(100, size=60, replace=False))
    est = gt.subset(keep)
    est = Trajectory(est.timestamps + 0.004, est.positions, est.quats_wxyz)  # within 0.01 s
    res = evaluate(est, gt)
    assert res.n_matched == 60 and res.tracked_fraction == pytest.approx(0.6)
    np.testing.assert_allclose(res.timestamps, gt.timestamps[keep])
    assert res.ate_rmse < 1e-9
    late = Trajectory(est.timestamps + 0.02, est.positions, est.quats_wxyz)
    with pytest.raises(EvaluationError, match="timestamp"):
        evaluate(late, gt)


def test_rpe_known_rotation_and_direction_errors():
    n = 10
    t = np.arange(n, dtype=float)
    gt = Trajectory(t, np.c_[t, np.zeros(n), 0.1 * t**2], np.tile([1.0, 0, 0, 0], (n, 1)))
    # rotation error: frame 4 turned by 2 degrees -> pairs (3, 4) and (4, 5) off by 2 degrees
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    q[4] = rotmat_to_quat(rotvec_exp(np.radians([0.0, 2.0, 0.0])))
    res = evaluate(Trajectory(t, gt.positions, q), gt)
    expected = np.zeros(n - 1)
    expected[[3, 4]] = 2.0
    np.testing.assert_allclose(res.rpe_rot_deg, expected, atol=1e-9)
    # direction error: every step turned by 10 degrees about the y axis (camera frames fixed)
    Ry = rotvec_exp(np.radians([0.0, 10.0, 0.0]))
    steps = np.diff(gt.positions, axis=0) @ Ry.T
    p_est = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)]) * 0.5
    res = evaluate(Trajectory(t, p_est, gt.quats_wxyz), gt)
    np.testing.assert_allclose(res.rpe_dir_deg, 10.0, atol=1e-9)
    assert res.rpe_dir["median"] == pytest.approx(10.0)


def test_degenerate_inputs_raise():
    rng = np.random.default_rng(5)
    gt = _gt(rng, 10)
    with pytest.raises(EvaluationError, match="need 3"):
        evaluate(gt.subset(np.array([0, 5])), gt)
    still = Trajectory(gt.timestamps, np.zeros((10, 3)), gt.quats_wxyz)
    with pytest.raises(EvaluationError, match="coincide"):
        evaluate(still, gt)
    with pytest.raises(EvaluationError):
        align_sim3(np.zeros((2, 3)), np.zeros((2, 3)))


def test_to_dict_is_json_ready():
    rng = np.random.default_rng(6)
    gt = _gt(rng, 20)
    d = evaluate(gt, gt).to_dict(arrays=True)
    text = json.dumps(d)
    assert json.loads(text)["n_matched"] == 20
    assert set(d["rpe_rot_deg"]) == {"rmse", "mean", "median", "max"}
    assert len(d["aligned_positions"]) == 20
    assert Sim3(1.0, np.eye(3), np.zeros(3)).to_dict()["scale"] == 1.0


@pytest.mark.data
def test_matches_evo_on_shared_ground_truth(shared_dataset):
    from evo.core import metrics, sync

    path = shared_dataset("7scenes-redkitchen-a/groundtruth.tum")
    gt = read_tum(path)
    rng = np.random.default_rng(7)
    R = Rotation.random(random_state=8).as_matrix()
    est = _transform(gt, 0.7, R, np.array([0.3, 0.1, -2.0]), rng.normal(scale=0.02, size=gt.positions.shape))
    # orientation noise too, so that the RPE comparison is not trivial
    dR = rotvec_exp(rng.normal(scale=0.01, size=(len(gt), 3)))
    est = Trajectory(est.timestamps, est.positions, rotmat_to_quat(est.rotations @ dR))
    keep = np.sort(rng.choice(len(gt), size=400, replace=False))
    est = est.subset(keep)
    res = evaluate(est, gt)
    # what 'evo_ape tum groundtruth.tum estimate.tum -as' does
    ref, e = sync.associate_trajectories(to_evo(gt), to_evo(est), max_diff=0.01)
    e.align(ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, e))
    assert res.ate_rmse == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-9)
    assert 0.02 < res.ate_rmse < 0.05  # the noise was applied
    rpe = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta=1, all_pairs=False)
    rpe.process_data((ref, e))
    np.testing.assert_allclose(np.sort(res.rpe_rot_deg), np.sort(rpe.error), atol=1e-6)
    assert res.tracked_fraction == pytest.approx(400 / 500)


def test_top_view_axes():
    from eifslam.evaluation.plots_eval import top_view_axes

    n = 20
    t = np.linspace(0, 2 * np.pi, n)
    ring_xz = np.c_[np.cos(t), 0.01 * np.sin(3 * t), np.sin(t)]
    assert top_view_axes(ring_xz) == (0, 2)
    # cameras with y down along world -z (Strecha-like): drop z
    R = np.tile(np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]), (n, 1, 1))
    assert top_view_axes(ring_xz, R) == (0, 1)


def test_eval_command(tmp_path):
    from eifslam.cli.main import main

    rng = np.random.default_rng(9)
    gt = _gt(rng, 30)
    est = _transform(gt, 2.0, np.eye(3), np.zeros(3), rng.normal(scale=0.01, size=(30, 3)))
    write_tum(tmp_path / "gt.tum", gt.timestamps, gt.positions, gt.quats_wxyz)
    write_tum(tmp_path / "est.tum", est.timestamps, est.positions, est.quats_wxyz)
    rc = main(["eval", str(tmp_path / "gt.tum"), str(tmp_path / "est.tum"),
               "--json", str(tmp_path / "r.json"), "--plot", str(tmp_path / "p.png")])
    assert rc == 0
    d = json.loads((tmp_path / "r.json").read_text())
    assert 0.005 < d["ate_rmse"] < 0.03 and d["tracked_fraction"] == 1.0
    assert d["units"] == "ground-truth units"
    assert abs(d["sim3"]["scale"] - 0.5) < 0.01  # est = 2 x gt: evo's order aligns the estimate onto gt
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    assert main(["eval", str(tmp_path / "gt.tum"), str(tmp_path / "nope.tum")]) == 1
    # swapped, the figures change (the order matters and is evo's)
    rc = main(["eval", str(tmp_path / "est.tum"), str(tmp_path / "gt.tum"), "--json", str(tmp_path / "s.json"),
               "--units", "m"])
    s = json.loads((tmp_path / "s.json").read_text())
    assert rc == 0 and abs(s["sim3"]["scale"] - 2.0) < 0.04 and s["units"] == "m"
    assert s["ate_rmse"] > 1.5 * d["ate_rmse"]
