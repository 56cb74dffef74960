"""Plots of evaluation results (matplotlib; functions take an ``ax`` and never save)."""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from .evaluation import EvaluationResult

__all__ = ["top_view_axes", "plot_trajectories", "plot_evaluation"]

_AXIS_NAMES = "xyz"


def top_view_axes(positions: NDArray[np.float64]) -> tuple[int, int]:
    """The two world axes with the largest extent of ``positions`` (N, 3), in index order.

    For camera-to-world ground truth with ``y`` down (KITTI, the shared data sets) this
    is ``(0, 2)``, the x-z ground plane.
    """
    P = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    extent = P.max(0) - P.min(0) if len(P) else np.ones(3)
    drop = int(np.argmin(extent))
    keep = [k for k in range(3) if k != drop]
    return keep[0], keep[1]


def plot_trajectories(
    ax: Any,
    gt_positions: NDArray[np.float64],
    est_positions: NDArray[np.float64],
    axes: tuple[int, int] | None = None,
    labels: tuple[str, str] = ("ground truth", "estimate (Sim(3)-aligned)"),
    connect: bool = True,
) -> None:
    """Draw a top view of two trajectories on ``ax``.

    Parameters
    ----------
    ax : matplotlib Axes.
    gt_positions, est_positions : (N, 3), (M, 3) camera centres in the same frame.
    axes : the two world axes to show; default :func:`top_view_axes` of the ground truth.
    labels : legend labels.
    connect : draw thin lines between associated poses (needs N == M).
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
    ax.set_xlabel(_AXIS_NAMES[a])
    ax.set_ylabel(_AXIS_NAMES[b])
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize="small")


def plot_evaluation(ax: Any, result: EvaluationResult, axes: tuple[int, int] | None = None) -> None:
    """Top view of an :class:`EvaluationResult` with its ATE in the title."""
    plot_trajectories(ax, result.gt_positions, result.aligned_positions, axes)
    ax.set_title(
        f"ATE {result.ate_rmse:.4g} ({result.ate_percent:.2f} % of path), "
        f"tracked {100 * result.tracked_fraction:.0f} %",
        fontsize="medium",
    )
