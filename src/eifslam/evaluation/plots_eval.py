"""Plots of evaluation results (matplotlib; functions take an ``ax`` and never save)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .metrics import EvaluationResult

__all__ = ["top_view_axes", "plot_trajectories", "plot_evaluation"]

_AXIS_NAMES = "xyz"


def top_view_axes(
    positions: NDArray[np.float64], R_wc: NDArray[np.float64] | None = None
) -> tuple[int, int]:
    """The two world axes of a top view, in index order.

    Parameters
    ----------
    positions : (N, 3) camera centres.
    R_wc : (N, 3, 3) camera-to-world rotations, optional. When given and the cameras
        agree on a down direction (mean camera ``y`` axis of length > 0.7), the world axis
        most aligned with it is left out (KITTI, a hand-held camera: ``(0, 2)``).
        Otherwise the world axis closest to the normal of the best-fit plane of
        ``positions`` is left out (a camera circling an object: the ring's axis).
    """
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    if R_wc is not None and len(R_wc):
        down = np.asarray(R_wc, dtype=np.float64).reshape(-1, 3, 3)[:, :, 1].mean(0)
        if np.linalg.norm(down) > 0.7:
            drop = int(np.argmax(np.abs(down)))
            keep = [k for k in range(3) if k != drop]
            return keep[0], keep[1]
    if len(P) >= 3:
        C = P - P.mean(0)
        normal = np.linalg.eigh(C.T @ C)[1][:, 0]
        drop = int(np.argmax(np.abs(normal)))
    else:
        drop = 1
    keep = [k for k in range(3) if k != drop]
    return keep[0], keep[1]


def plot_trajectories(
    ax: Any,
    gt_positions: NDArray[np.float64],
    est_positions: NDArray[np.float64],
    axes: tuple[int, int] | None = None,
    labels: tuple[str, str] = ("ground truth", "estimate (Sim(3)-aligned)"),
    connect: bool = True,
    units: str = "ground-truth units",
) -> None:
    """Draw a top view of two trajectories on ``ax``.

    Parameters
    ----------
    ax : matplotlib Axes.
    gt_positions, est_positions : (N, 3), (M, 3) camera centres in the same frame.
    axes : the two world axes to show; default :func:`top_view_axes` of the ground truth.
    labels : legend labels.
    connect : draw thin lines between associated poses (needs N == M).
    units : name of the length unit of the positions, on the axes.
    """
    G = np.asarray(gt_positions, dtype=np.float64).reshape(-1, 3)
    E = np.asarray(est_positions, dtype=np.float64).reshape(-1, 3)
    a, b = axes if axes is not None else top_view_axes(G)
    if connect and len(G) == len(E) and len(G):
        segs_x = np.stack([G[:, a], E[:, a], np.full(len(G), np.nan)], 1).ravel()
        segs_y = np.stack([G[:, b], E[:, b], np.full(len(G), np.nan)], 1).ravel()
        ax.plot(segs_x, segs_y, "-", color="0.7", lw=0.5, zorder=1)
    ax.plot(G[:, a], G[:, b], "-", color="k", lw=1.5, label=labels[0], zorder=2)
    ax.plot(E[:, a], E[:, b], ".-", color="tab:blue", lw=1.0, ms=3, label=labels[1], zorder=3)
    if len(G):
        ax.plot(G[0, a], G[0, b], "o", color="k", ms=5, zorder=4)
    ax.set_xlabel(f"{_AXIS_NAMES[a]} ({units})")
    ax.set_ylabel(f"{_AXIS_NAMES[b]} ({units})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize="small")


def plot_evaluation(ax: Any, result: EvaluationResult, axes: tuple[int, int] | None = None) -> None:
    """Top view of an :class:`EvaluationResult` with its ATE in the title.

    The view direction is the mean camera ``y`` (down) axis of the ground truth unless
    ``axes`` is given (see :func:`top_view_axes`).
    """
    if axes is None:
        axes = top_view_axes(result.gt_positions, result.gt_rotations)
    plot_trajectories(ax, result.gt_positions, result.aligned_positions, axes, units=result.units)
    ax.set_title(
        f"ATE RMSE {result.ate_rmse:.4g} {result.units} ({result.ate_percent:.2f} % of path), "
        f"tracked {100 * result.tracked_fraction:.0f} %",
        fontsize="medium",
    )
