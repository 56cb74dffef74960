"""Plots of a SLAM run: trajectory and map, information-matrix sparsity, per-frame timing.

Every function draws on a matplotlib ``ax`` it is given and takes arrays (scikit-image
style); none reads or writes files or creates figures. :mod:`eifslam.evaluation.report` lays the
figures out and saves them. Plots against ground truth are in :mod:`eifslam.evaluation.plots_eval`.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from .metrics import EvaluationResult
from .plots_eval import plot_evaluation, top_view_axes

Array = NDArray[np.float64]

#: The length unit of an estimate's own frame (its scale is set between the first two poses).
MAP_UNITS = "map units"

__all__ = [
    "STAGES",
    "subsample_indices",
    "robust_limits",
    "plot_map_top",
    "plot_map_3d",
    "plot_information_sparsity",
    "plot_stage_times",
    "plot_aligned_map",
]

#: Per-frame timing stages in pipeline order (keys of ``frames.json`` ``"ms"``).
STAGES = ("detect", "match", "relative_pose", "covariance", "fuse", "recover")

_AXIS_NAMES = "xyz"
_TRAJ_COLOR = "tab:blue"
_MAP_GREY = "0.45"


def subsample_indices(n: int, max_count: int, rng: np.random.Generator | None = None) -> NDArray[np.intp]:
    """Sorted indices of at most ``max_count`` of ``n`` items, drawn without replacement.

    Parameters
    ----------
    n : number of items.
    max_count : largest number kept; all ``n`` when ``n <= max_count``.
    rng : random generator; default ``np.random.default_rng(0)`` (reproducible figures).

    >>> subsample_indices(5, 10).tolist()
    [0, 1, 2, 3, 4]
    >>> len(subsample_indices(50_000, 20_000))
    20000
    """
    if n <= max_count:
        return np.arange(n, dtype=np.intp)
    rng = np.random.default_rng(0) if rng is None else rng
    return np.sort(rng.choice(n, size=max(int(max_count), 0), replace=False)).astype(np.intp)


def robust_limits(*point_sets: Array, quantile: float = 0.01, margin: float = 0.05) -> tuple[Array, Array]:
    """Axis-aligned box holding the sets' central points (ignores far outliers).

    Monocular map features far from the cameras (low parallax) would otherwise squeeze
    the trajectory into a corner of the plot.

    Parameters
    ----------
    *point_sets : (N_i, 3) arrays; empty ones are ignored. The first set (the camera
        centres) is always contained entirely; the others from ``quantile`` to
        ``1 - quantile`` on each axis.
    quantile : fraction cut from each end of the other sets.
    margin : fraction of the box size added on each side.

    Returns
    -------
    lo, hi : (3,) corners; a degenerate extent is widened to 1 (or to 10 % of the
        largest extent).
    """
    parts = []
    for k, P in enumerate(point_sets):
        P = np.asarray(P, dtype=np.float64).reshape(-1, 3)
        P = P[np.all(np.isfinite(P), axis=1)]
        if len(P) == 0:
            continue
        if k == 0 or len(P) < 10:
            parts.append(np.stack([P.min(0), P.max(0)]))
        else:
            parts.append(np.quantile(P, [quantile, 1.0 - quantile], axis=0))
    if not parts:
        return -np.ones(3), np.ones(3)
    box = np.concatenate(parts)
    lo, hi = box.min(0), box.max(0)
    size = hi - lo
    floor = 0.1 * size.max() if size.max() > 0 else 1.0
    pad = np.maximum(size, floor)
    centre = 0.5 * (lo + hi)
    half = 0.5 * pad * (1.0 + 2.0 * margin)
    return centre - half, centre + half


def _point_colors(colors: NDArray[np.uint8] | None, idx: NDArray[np.intp]) -> Any:
    """Matplotlib colour argument: (M, 3) floats in [0, 1] or one grey."""
    if colors is None:
        return _MAP_GREY
    return np.asarray(colors, dtype=np.float64).reshape(-1, 3)[idx] / 255.0


def plot_map_top(
    ax: Any,
    positions: Array,
    points: Array,
    colors: NDArray[np.uint8] | None = None,
    R_wc: Array | None = None,
    axes: tuple[int, int] | None = None,
    max_points: int = 20_000,
    point_size: float = 2.0,
    rng: np.random.Generator | None = None,
    units: str = MAP_UNITS,
    limits: tuple[Array, Array] | None = None,
    frusta: int = 24,
) -> None:
    """Top view of the camera trajectory over the map.

    Parameters
    ----------
    ax : matplotlib Axes (2-D).
    positions : (N, 3) camera centres, world frame; N may be 0.
    points : (M, 3) map features, same frame; M may be 0.
    colors : (M, 3) uint8 RGB of the features, or ``None`` (grey).
    R_wc : (N, 3, 3) camera-to-world rotations; they choose the view direction
        (see :func:`eifslam.evaluation.plots_eval.top_view_axes`).
    axes : the two world axes shown, overriding the automatic choice.
    max_points : features drawn at most (random subset beyond that).
    point_size : marker area of the features (points²).
    rng : generator for the subset (see :func:`subsample_indices`).
    units : name of the length unit of the positions, on the axes (default: the map's own
        unit, fixed by ``tracking.scale_distance`` between the first two poses).
    limits : ``(lo, hi)`` (3,) corners of the region shown; default :func:`robust_limits`.
    frusta : with ``R_wc``, draw the viewing wedge (optical axis and a 60-degree field of
        view, cut at 6 % of the view's width) of this many evenly spaced cameras.
    """
    C = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    a, b = axes if axes is not None else top_view_axes(C if len(C) else P, R_wc)
    idx = subsample_indices(len(P), max_points, rng)
    if len(idx):
        ax.scatter(P[idx, a], P[idx, b], s=point_size, c=_point_colors(colors, idx),
                   linewidths=0, zorder=1, label=f"map ({len(P)} features)")
    if len(C):
        ax.plot(C[:, a], C[:, b], ".-", color=_TRAJ_COLOR, lw=1.0, ms=2, zorder=3,
                label=f"cameras ({len(C)})")
        ax.plot(C[0, a], C[0, b], "o", color="k", ms=5, zorder=4, label="start")
    lo, hi = robust_limits(C, P) if limits is None else (np.asarray(limits[0]), np.asarray(limits[1]))
    if R_wc is not None and len(C) and frusta > 0:
        _draw_frusta(ax, C, np.asarray(R_wc, float).reshape(-1, 3, 3), (a, b), 0.06 * max(hi[a] - lo[a], hi[b] - lo[b]),
                     frusta)
    ax.set_xlim(lo[a], hi[a])
    ax.set_ylim(lo[b], hi[b])
    ax.set_xlabel(f"{_AXIS_NAMES[a]} ({units})")
    ax.set_ylabel(f"{_AXIS_NAMES[b]} ({units})")
    ax.set_aspect("equal", adjustable="box")
    if len(C) or len(idx):
        ax.legend(loc="best", fontsize="small", markerscale=2)


def _vertical_axis(R_wc: Array | None) -> tuple[int, float]:
    """World axis closest to 'up' and its sign: minus the mean camera ``y`` (down) axis."""
    if R_wc is not None and len(R_wc):
        down = np.asarray(R_wc, dtype=np.float64).reshape(-1, 3, 3)[:, :, 1].mean(0)
        if np.linalg.norm(down) > 0.3:
            k = int(np.argmax(np.abs(down)))
            return k, -float(np.sign(down[k]))
    return 2, 1.0


def _draw_frusta(ax: Any, C: Array, R: Array, axes: tuple[int, int], size: float, count: int) -> None:
    """Viewing wedges of ``count`` evenly spaced cameras (centres ``C``, rotations ``R_wc``)
    in the top view ``axes``: the camera-frame rays ``(±tan 30°, 0, 1)`` scaled to ``size``."""
    a, b = axes
    idx = np.unique(np.linspace(0, len(C) - 1, min(count, len(C))).round().astype(int))
    rays = np.array([[-np.tan(np.radians(30)), 0.0, 1.0], [np.tan(np.radians(30)), 0.0, 1.0]]) * size
    for k in idx:
        left, right = C[k] + R[k] @ rays[0], C[k] + R[k] @ rays[1]
        ax.fill([C[k, a], left[a], right[a]], [C[k, b], left[b], right[b]], color=_TRAJ_COLOR, alpha=0.25,
                lw=0.6, zorder=2)


def plot_map_3d(
    ax: Any,
    positions: Array,
    points: Array,
    colors: NDArray[np.uint8] | None = None,
    R_wc: Array | None = None,
    max_points: int = 20_000,
    point_size: float = 1.0,
    rng: np.random.Generator | None = None,
    units: str = MAP_UNITS,
) -> None:
    """Perspective view of the trajectory and the map.

    Parameters
    ----------
    ax : matplotlib 3-D Axes (``fig.add_subplot(projection="3d")``).
    positions, points, colors, max_points, point_size, rng, units
        As in :func:`plot_map_top`.
    R_wc : (N, 3, 3) camera-to-world rotations. When given, the world axis along the
        mean camera ``-y`` (up in the images) is drawn upwards; otherwise ``z`` is.

    Features outside the box of :func:`robust_limits` are left out (3-D axes do not clip).
    """
    C = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    up, sign = _vertical_axis(R_wc)
    h0, h1 = [k for k in range(3) if k != up]
    flip = np.array([1.0, 1.0, sign])
    if np.linalg.det(np.eye(3)[[h0, h1, up]] * flip[:, None]) < 0:
        h0, h1 = h1, h0  # keep the drawn frame right-handed (no mirror image)
    order = [h0, h1, up]
    lo, hi = robust_limits(C, P)
    P = P[np.all((P >= lo) & (P <= hi), axis=1)]  # 3-D axes do not clip: drop outliers
    idx = subsample_indices(len(P), max_points, rng)
    ax.computed_zorder = False  # keep the trajectory above the map
    if len(idx):
        Q = P[idx][:, order] * flip
        ax.scatter(Q[:, 0], Q[:, 1], Q[:, 2], s=point_size, c=_point_colors(colors, idx),
                   linewidths=0, depthshade=False)
    if len(C):
        D = C[:, order] * flip
        ax.plot(D[:, 0], D[:, 1], D[:, 2], "-", color=_TRAJ_COLOR, lw=1.5, zorder=3)
        ax.scatter(D[:1, 0], D[:1, 1], D[:1, 2], color="k", s=15, zorder=4)
    lo, hi = lo[order] * flip, hi[order] * flip
    lo, hi = np.minimum(lo, hi), np.maximum(lo, hi)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(hi - lo), zoom=0.85)
    ax.set_xlabel(f"{_AXIS_NAMES[h0]} ({units})")
    ax.set_ylabel(f"{_AXIS_NAMES[h1]} ({units})")
    ax.set_zlabel(f"{'' if sign > 0 else '-'}{_AXIS_NAMES[up]} ({units})")


def plot_information_sparsity(
    ax: Any,
    information: sp.spmatrix | sp.sparray | Array,
    markersize: float | None = None,
    max_markers: int = 1_000_000,
    image_size: int = 1000,
    is_feature: NDArray[np.bool_] | None = None,
) -> None:
    """Sparsity pattern of the information matrix, as the paper's Figs. 1b and 3c.

    Parameters
    ----------
    ax : matplotlib Axes.
    information : (n, n) sparse or dense matrix; a stored entry equal to zero counts as zero.
    markersize : marker size of ``ax.spy``; default shrinks with ``n``.
    max_markers : above this many non-zeros the pattern is drawn as an image of
        ``image_size`` × ``image_size`` cells (a cell is black when it holds a non-zero)
        instead of one marker per entry.
    image_size : cells per side of that image.
    is_feature : (n,) bool, optional
        Whether each entry of the state belongs to a map feature (else to a pose); the
        pose and feature blocks are then marked by a strip under the pattern.

    The title is ``nz = <number of non-zeros>``, followed by the cell size when the
    pattern is binned.
    """
    A = sp.coo_array(information)
    A.eliminate_zeros()
    n_rows, n_cols = A.shape
    nnz = int(A.nnz)
    if nnz > max_markers:
        cell = max(1, int(np.ceil(max(n_rows, n_cols) / image_size)))
        img = np.zeros((-(-n_rows // cell), -(-n_cols // cell)), dtype=bool)
        img[A.row // cell, A.col // cell] = True
        ax.imshow(img, cmap="Greys", interpolation="nearest", aspect="equal",
                  extent=(-0.5, n_cols - 0.5, n_rows - 0.5, -0.5), vmin=0, vmax=1)
        ax.xaxis.tick_top()
    elif nnz == 0:
        ax.set_xlim(-0.5, n_cols - 0.5)
        ax.set_ylim(n_rows - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.xaxis.tick_top()
    else:
        if markersize is None:
            markersize = float(np.clip(200.0 / max(n_rows, n_cols, 1), 0.05, 3.0))
        ax.spy(A, markersize=markersize, color="k")
    if is_feature is not None and len(is_feature) == n_cols and n_cols:
        _mark_blocks(ax, np.asarray(is_feature, bool))
    title = f"nz = {nnz}"
    if nnz > max_markers:
        title += f" (binned: a black cell holds a non-zero among {cell} × {cell} entries)"
    ax.set_title(title)


def _mark_blocks(ax: Any, is_feature: NDArray[np.bool_]) -> None:
    """A strip under a sparsity pattern: pose entries blue, feature entries orange."""
    from matplotlib.transforms import blended_transform_factory

    edges = np.flatnonzero(np.diff(is_feature.astype(np.int8))) + 1
    starts, ends = np.r_[0, edges], np.r_[edges, len(is_feature)]
    under = blended_transform_factory(ax.transData, ax.transAxes)
    for feat, colour, what in ((False, "tab:blue", "pose"), (True, "tab:orange", "feature")):
        sel = is_feature[starts] == feat
        if sel.any():
            ax.broken_barh(list(zip(starts[sel] - 0.5, ends[sel] - starts[sel])), (-0.04, 0.03), transform=under,
                           color=colour, clip_on=False,
                           label=f"{what} entries ({int((is_feature == feat).sum())})")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.05), ncol=2, fontsize="small", frameon=False)


def _stage_matrix(stage_ms: Mapping[str, Array], n: int) -> tuple[list[str], Array]:
    """Stage names (pipeline order first) and an (S, n) matrix of times (NaN if missing)."""
    names = [s for s in STAGES if s in stage_ms] + sorted(
        s for s in stage_ms if s not in STAGES and s != "total"
    )
    if not names:
        return [], np.zeros((0, n))
    Y = np.stack([np.asarray(stage_ms[s], dtype=np.float64).reshape(n) for s in names])
    return names, np.where(np.isfinite(Y), Y, np.nan)


def plot_stage_times(
    ax: Any,
    x: Array,
    stage_ms: Mapping[str, Array],
    total_ms: Array | None = None,
    stacked: bool = True,
    xlabel: str = "frame",
) -> None:
    """Time per frame and stage.

    Parameters
    ----------
    ax : matplotlib Axes.
    x : (N,) abscissa of each frame: the frame number, or the size of the state vector
        (``state_dim``, the paper's measure of map size). NaN entries are left out.
    stage_ms : stage name -> (N,) milliseconds, NaN where a frame lacks that stage
        (drawn as 0 when stacked, left out otherwise); frames with no time at all are
        left out. Stages of :data:`STAGES` come first,
        in pipeline order; a ``"total"`` key is ignored (use ``total_ms``).
    total_ms : (N,) measured total per frame, optional; drawn as a black line/points, and
        when stacked the part not covered by the stages is shown as ``other``.
    stacked : stacked areas over ``x`` sorted (suits ``x`` = frame) or one point series
        per stage (suits ``x`` = map size, where several frames share a value).
    xlabel : label of the abscissa.
    """
    xs = np.asarray(x, dtype=np.float64).reshape(-1)
    n = len(xs)
    names, Y = _stage_matrix(stage_ms, n)
    tot = None if total_ms is None else np.asarray(total_ms, dtype=np.float64).reshape(n)
    timed = np.any(np.isfinite(Y), axis=0) | (np.zeros(n, bool) if tot is None else np.isfinite(tot))
    keep = np.isfinite(xs) & timed  # frames without any time are left out, not drawn as 0
    order = np.argsort(xs[keep], kind="stable")
    xs, Y = xs[keep][order], Y[:, keep][:, order]
    tot = None if tot is None else tot[keep][order]
    if stacked:
        Y = np.nan_to_num(Y, nan=0.0)
        if tot is not None and np.any(np.isfinite(tot)):
            other = np.clip(np.where(np.isfinite(tot), tot, 0.0) - Y.sum(0), 0.0, None)
            if np.any(other > 0):
                names, Y = names + ["other"], np.vstack([Y, other])
        if len(names) and len(xs):
            ax.stackplot(xs, Y, labels=names, linewidth=0)
        if tot is not None:
            ax.plot(xs, tot, "-", color="k", lw=0.6, label="total")
    else:
        for name, y in zip(names, Y):
            ok = np.isfinite(y)
            ax.plot(xs[ok], y[ok], ".", ms=3, label=name)
        if tot is not None:
            ok = np.isfinite(tot)
            ax.plot(xs[ok], tot[ok], "+", color="k", ms=4, label="total")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("time per frame (ms)")
    ax.set_ylim(bottom=0)
    if names or tot is not None:
        ax.legend(loc="upper left", fontsize="small", ncol=2)


def plot_aligned_map(
    ax: Any,
    result: EvaluationResult,
    points: Array,
    colors: NDArray[np.uint8] | None = None,
    axes: tuple[int, int] | None = None,
    max_points: int = 20_000,
    point_size: float = 2.0,
    rng: np.random.Generator | None = None,
) -> None:
    """Top view of the Sim(3)-aligned estimate against ground truth, with the map.

    Parameters
    ----------
    ax : matplotlib Axes.
    result : evaluation of the estimated trajectory; its ``sim3`` maps the estimate's
        world frame into the ground truth's.
    points : (M, 3) map features in the *estimate's* frame; transformed here by
        ``result.sim3``. M may be 0.
    colors, max_points, point_size, rng : as in :func:`plot_map_top`.
    axes : the two world axes shown; default from the ground-truth poses.

    The title gives the ATE (see :func:`eifslam.evaluation.plots_eval.plot_evaluation`).
    """
    if axes is None:
        axes = top_view_axes(result.gt_positions, result.gt_rotations)
    a, b = axes
    P = result.sim3.apply(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    idx = subsample_indices(len(P), max_points, rng)
    if len(idx):
        ax.scatter(P[idx, a], P[idx, b], s=point_size, c=_point_colors(colors, idx),
                   linewidths=0, zorder=0)
    plot_evaluation(ax, result, axes)
    lo, hi = robust_limits(np.vstack([result.gt_positions, result.aligned_positions]), P)
    ax.set_xlim(lo[a], hi[a])
    ax.set_ylim(lo[b], hi[b])
    ax.set_aspect("equal", adjustable="box")
