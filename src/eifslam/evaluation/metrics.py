"""Trajectory accuracy against ground truth (pure NumPy / SciPy / evo core).

The measures every run is scored by:

* **ATE**: RMSE of camera-centre errors after a Sim(3) (Umeyama, 7-DoF) alignment of the
  estimate to the ground truth, as ``evo_ape tum groundtruth.tum estimate.tum -as``
  computes it; also as a percentage of the ground-truth path length.
* **Tracked fraction**: ground-truth frames that have an estimate / ground-truth frames.
* **RPE** per consecutive pair of associated frames: rotation error (degrees) and the angle
  between estimated and true translation directions (degrees), the quantities the paper's
  ``ZR`` and ``ZT`` measure. Both are invariant to the Sim(3) alignment.

The Sim(3) is returned so that callers can bring map points into the ground-truth frame.
This module imports neither OpenCV nor matplotlib (see :mod:`eifslam.evaluation.plots_eval`).

>>> import numpy as np
>>> from eifslam.io.trajectory import Trajectory
>>> rng = np.random.default_rng(0)
>>> t = np.arange(20.0)
>>> p = np.cumsum(rng.normal(size=(20, 3)), axis=0)
>>> q = np.tile([1.0, 0.0, 0.0, 0.0], (20, 1))
>>> res = evaluate(Trajectory(t, 2.0 * p + 1.0, q), Trajectory(t, p, q))
>>> round(res.ate_rmse, 9), round(res.sim3.scale, 6)
(0.0, 0.5)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from evo.core import metrics as evo_metrics
from evo.core import sync
from evo.core.geometry import GeometryException, umeyama_alignment
from evo.core.trajectory import PoseTrajectory3D
from numpy.typing import NDArray

from ..errors import EifslamError
from ..io.trajectory import Trajectory

Array = NDArray[np.float64]

__all__ = ["DATASET_UNITS", "GT_UNITS", "EvaluationError", "Sim3", "EvaluationResult", "align_sim3", "evaluate", "to_evo"]


class EvaluationError(EifslamError):
    """The estimate cannot be scored (too few associated poses, degenerate geometry)."""


@dataclass(frozen=True)
class Sim3:
    """Similarity transform ``x -> scale * rotation @ x + translation``.

    Maps the estimate's world frame into the ground truth's world frame.

    Attributes
    ----------
    scale : float
        Positive, unitless.
    rotation : (3, 3) float64
    translation : (3,) float64, ground-truth units.
    """

    scale: float
    rotation: Array
    translation: Array

    @property
    def matrix(self) -> Array:
        """(4, 4) homogeneous matrix ``[[s R, t], [0, 1]]``."""
        M = np.eye(4)
        M[:3, :3] = self.scale * self.rotation
        M[:3, 3] = self.translation
        return M

    def apply(self, points: Array) -> Array:
        """Transform points ``(..., 3)`` (e.g. map points) into the ground-truth frame."""
        P = np.asarray(points, dtype=np.float64)
        return self.scale * P @ self.rotation.T + self.translation

    def apply_rotations(self, R_wc: Array) -> Array:
        """Transform camera-to-world rotations ``(..., 3, 3)``: ``R @ R_wc``."""
        return self.rotation @ np.asarray(R_wc, dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly dictionary (lists of floats)."""
        return {
            "scale": float(self.scale),
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
        }


#: The name of a length in the ground truth's unit when the unit is not known.
GT_UNITS = "ground-truth units"
#: The unit of the ground truth of every data set eifslam reads (KITTI, TUM RGB-D,
#: EuRoC, Strecha, the built-in scene): metres.
DATASET_UNITS = "m"


def _stats(x: Array) -> dict[str, float | None]:
    if len(x) == 0:
        return {"rmse": None, "mean": None, "median": None, "max": None}
    return {
        "rmse": float(np.sqrt(np.mean(x**2))),
        "mean": float(np.mean(x)),
        "median": float(np.median(x)),
        "max": float(np.max(x)),
    }


@dataclass(frozen=True)
class EvaluationResult:
    """Accuracy of an estimated trajectory.

    Attributes
    ----------
    ate_rmse : float
        ATE, RMSE of aligned camera-centre errors (ground-truth units).
    ate_mean, ate_median, ate_max : float
        Other statistics of the same errors.
    ate_percent : float
        ``100 * ate_rmse / gt_path_length`` (``inf`` if the path length is zero).
    gt_path_length : float
        Ground-truth path length over the associated frames (ground-truth units).
    tracked_fraction : float
        ``n_matched / n_ground_truth`` in [0, 1].
    n_ground_truth, n_estimate, n_matched : int
        Poses in the ground truth, in the estimate, and associated by timestamp.
    sim3 : Sim3
        Alignment estimate → ground truth.
    timestamps : (M,) float64
        Ground-truth timestamps of the associated poses (seconds).
    gt_positions, aligned_positions : (M, 3) float64
        True and aligned estimated camera centres.
    gt_rotations : (M, 3, 3) float64
        True camera-to-world rotations ``R_wc`` of the associated poses.
    ate_errors : (M,) float64
        Per-pose position errors after alignment.
    rpe_rot_deg : (M - 1,) float64
        Rotation error of each consecutive associated pair, degrees.
    rpe_dir_deg : (K,) float64
        Translation-direction error of each pair with non-zero motion, degrees.
    units : str
        Name of the ground truth's length unit, printed after every length ("m" for the
        data sets eifslam reads, whose ground truth is in metres; "ground-truth units"
        when it is not known).
    """

    ate_rmse: float
    ate_mean: float
    ate_median: float
    ate_max: float
    ate_percent: float
    gt_path_length: float
    tracked_fraction: float
    n_ground_truth: int
    n_estimate: int
    n_matched: int
    sim3: Sim3
    timestamps: Array = field(repr=False)
    gt_positions: Array = field(repr=False)
    aligned_positions: Array = field(repr=False)
    gt_rotations: Array = field(repr=False)
    ate_errors: Array = field(repr=False)
    rpe_rot_deg: Array = field(repr=False)
    rpe_dir_deg: Array = field(repr=False)
    units: str = GT_UNITS

    @property
    def rpe_rot(self) -> dict[str, float | None]:
        """RMSE / mean / median / max of :attr:`rpe_rot_deg` (``None`` if no pair)."""
        return _stats(self.rpe_rot_deg)

    @property
    def rpe_dir(self) -> dict[str, float | None]:
        """RMSE / mean / median / max of :attr:`rpe_dir_deg` (``None`` if no pair)."""
        return _stats(self.rpe_dir_deg)

    def to_dict(self, arrays: bool = False) -> dict[str, Any]:
        """JSON-friendly dictionary of the figures; with ``arrays`` also per-pose data."""
        d: dict[str, Any] = {
            "units": self.units,
            "ate_rmse": self.ate_rmse,
            "ate_mean": self.ate_mean,
            "ate_median": self.ate_median,
            "ate_max": self.ate_max,
            "ate_percent": self.ate_percent if np.isfinite(self.ate_percent) else None,
            "gt_path_length": self.gt_path_length,
            "tracked_fraction": self.tracked_fraction,
            "n_ground_truth": self.n_ground_truth,
            "n_estimate": self.n_estimate,
            "n_matched": self.n_matched,
            "rpe_rot_deg": self.rpe_rot,
            "rpe_dir_deg": self.rpe_dir,
            "sim3": self.sim3.to_dict(),
        }
        if arrays:
            d["timestamps"] = self.timestamps.tolist()
            d["gt_positions"] = self.gt_positions.tolist()
            d["aligned_positions"] = self.aligned_positions.tolist()
            d["ate_errors"] = self.ate_errors.tolist()
        return d

    def summary(self) -> str:
        """Human-readable multi-line summary."""
        rr, rd = self.rpe_rot, self.rpe_dir

        def fmt(v: float | None) -> str:
            return "n/a" if v is None else f"{v:.3f}"

        pct = f"{self.ate_percent:.3f} %" if np.isfinite(self.ate_percent) else "n/a"
        u = self.units
        return "\n".join(
            [
                f"matched poses     {self.n_matched} (estimate {self.n_estimate}, "
                f"ground truth {self.n_ground_truth})",
                f"tracked fraction  {self.tracked_fraction:.3f}",
                f"ATE RMSE (Sim3)   {self.ate_rmse:.6g} {u}  ({pct} of {self.gt_path_length:.4g} {u} path)",
                f"ATE mean/median/max {self.ate_mean:.6g} / {self.ate_median:.6g} / {self.ate_max:.6g} {u}",
                f"RPE rotation deg  rmse {fmt(rr['rmse'])}  mean {fmt(rr['mean'])}  "
                f"median {fmt(rr['median'])}  max {fmt(rr['max'])}",
                f"RPE direction deg rmse {fmt(rd['rmse'])}  mean {fmt(rd['mean'])}  "
                f"median {fmt(rd['median'])}  max {fmt(rd['max'])}",
                f"Sim3 scale        {self.sim3.scale:.6g}",
            ]
        )


def to_evo(traj: Trajectory) -> PoseTrajectory3D:
    """The same poses as an ``evo`` ``PoseTrajectory3D`` (quaternions stay ``wxyz``)."""
    return PoseTrajectory3D(
        positions_xyz=traj.positions.copy(),
        orientations_quat_wxyz=traj.quats_wxyz.copy(),
        timestamps=traj.timestamps.copy(),
    )


def align_sim3(source: Array, target: Array) -> Sim3:
    """Least-squares Sim(3) with ``target ≈ s R source + t`` (Umeyama 1991).

    Parameters
    ----------
    source, target : (N, 3) corresponding points, N >= 3.

    Raises
    ------
    EvaluationError
        Fewer than 3 points, or degenerate (collinear / coincident) points.
    """
    x = np.asarray(source, dtype=np.float64)
    y = np.asarray(target, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise EvaluationError(f"point sets must both be (N, 3), got {x.shape} and {y.shape}")
    if len(x) < 3:
        raise EvaluationError(f"Sim(3) alignment needs at least 3 poses, got {len(x)}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise EvaluationError("positions contain NaN or infinite values")
    if np.max(np.linalg.norm(x - x.mean(0), axis=1)) <= 1e-12 * (1.0 + np.abs(x).max()):
        raise EvaluationError("estimated positions all coincide: Sim(3) alignment impossible")
    try:
        R, t, s = umeyama_alignment(x.T, y.T, with_scale=True)
    except GeometryException as exc:
        raise EvaluationError(f"Sim(3) alignment impossible: {exc}") from None
    if not (np.isfinite(s) and s > 0):
        raise EvaluationError(f"Sim(3) alignment gave scale {s!r}")
    return Sim3(float(s), np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64))


def _relative_errors(R_gt: Array, p_gt: Array, R_est: Array, p_est: Array) -> tuple[Array, Array]:
    """Rotation and translation-direction errors (degrees) of consecutive pairs."""
    if len(p_gt) < 2:
        return np.zeros(0), np.zeros(0)
    Rg = np.swapaxes(R_gt[:-1], 1, 2) @ R_gt[1:]  # R_ij, true
    Re = np.swapaxes(R_est[:-1], 1, 2) @ R_est[1:]
    dR = np.swapaxes(Rg, 1, 2) @ Re
    # angle = atan2(|vee(dR - dR^T)| / 2, (trace - 1) / 2): accurate near 0 (arccos is not)
    w = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]], -1)
    rot = np.degrees(np.arctan2(0.5 * np.linalg.norm(w, axis=1), 0.5 * (np.trace(dR, axis1=1, axis2=2) - 1.0)))
    tg = np.einsum("nji,nj->ni", R_gt[:-1], p_gt[1:] - p_gt[:-1])  # R_i^T (p_j - p_i)
    te = np.einsum("nji,nj->ni", R_est[:-1], p_est[1:] - p_est[:-1])
    ng, ne = np.linalg.norm(tg, axis=1), np.linalg.norm(te, axis=1)
    scale_g = 1e-12 * (1.0 + np.abs(p_gt).max())
    scale_e = 1e-12 * (1.0 + np.abs(p_est).max())
    ok = (ng > scale_g) & (ne > scale_e)
    dot = np.einsum("ni,ni->n", tg[ok], te[ok])
    cross = np.linalg.norm(np.cross(tg[ok], te[ok]), axis=1)
    return rot, np.degrees(np.arctan2(cross, dot))


def evaluate(estimate: Trajectory, ground_truth: Trajectory, max_diff: float = 0.01,
             units: str = GT_UNITS) -> EvaluationResult:
    """Score an estimated trajectory against ground truth.

    Poses are associated by nearest timestamp within ``max_diff`` seconds (evo's
    ``associate_trajectories``, as ``evo_ape`` does by default), the estimate is aligned
    with a Sim(3) (``align(correct_scale=True)``), then ATE and RPE are computed.

    Parameters
    ----------
    estimate : camera-to-world poses, any world frame and scale.
    ground_truth : camera-to-world poses.
    max_diff : association window in seconds.
    units : name of the ground truth's length unit (for printing; nothing is converted).

    Returns
    -------
    EvaluationResult

    Raises
    ------
    EvaluationError
        Fewer than 3 associated poses, or degenerate geometry.
    """
    n_gt, n_est = len(ground_truth), len(estimate)
    if n_gt == 0 or n_est == 0:
        raise EvaluationError(f"empty trajectory (estimate {n_est} poses, ground truth {n_gt})")
    try:
        gt_s, est_s = sync.associate_trajectories(
            to_evo(ground_truth), to_evo(estimate), max_diff=max_diff
        )
    except sync.SyncException as exc:
        raise EvaluationError(f"no estimated pose matches a ground-truth timestamp: {exc}") from None
    m = gt_s.num_poses
    if m < 3:
        raise EvaluationError(
            f"only {m} estimated poses match ground-truth timestamps within {max_diff} s (need 3)"
        )
    p_gt, p_est = gt_s.positions_xyz, est_s.positions_xyz
    sim3 = align_sim3(p_est, p_gt)
    aligned = sim3.apply(p_est)
    # ATE statistics: evo's APE on the translation part, as evo_ape computes them
    ape = evo_metrics.APE(evo_metrics.PoseRelation.translation_part)
    ape.process_data((gt_s, PoseTrajectory3D(positions_xyz=aligned, orientations_quat_wxyz=gt_s.orientations_quat_wxyz,
                                             timestamps=gt_s.timestamps)))
    err = np.asarray(ape.error, dtype=np.float64)
    stats = ape.get_all_statistics()
    path = float(np.sum(np.linalg.norm(np.diff(p_gt, axis=0), axis=1)))
    R_gt = np.asarray(gt_s.poses_se3)[:, :3, :3]
    R_est = np.asarray(est_s.poses_se3)[:, :3, :3]
    rot, dirs = _relative_errors(R_gt, p_gt, R_est, p_est)
    rmse = float(stats["rmse"])
    return EvaluationResult(
        ate_rmse=rmse,
        ate_mean=float(stats["mean"]),
        ate_median=float(stats["median"]),
        ate_max=float(stats["max"]),
        ate_percent=100.0 * rmse / path if path > 0 else float("inf"),
        gt_path_length=path,
        tracked_fraction=m / n_gt,
        n_ground_truth=n_gt,
        n_estimate=n_est,
        n_matched=m,
        sim3=sim3,
        timestamps=np.asarray(gt_s.timestamps, dtype=np.float64),
        gt_positions=np.asarray(p_gt, dtype=np.float64),
        aligned_positions=aligned,
        gt_rotations=R_gt,
        ate_errors=err,
        rpe_rot_deg=rot,
        rpe_dir_deg=dirs,
        units=str(units),
    )
