"""Box-shape measurement from a point cloud: the paper's width:length check (pure NumPy).

Section IV of the paper judges the map by the shape of the boxes: the top face of one box
is 0.80:1 and the estimate gives about 0.83:1. :func:`estimate_box_ratio` makes the same
measurement on a map that the caller has already aligned (Sim(3)) into the scene's world
frame:

1. keep the map points within ``tol`` of the box's top plane and inside its footprint grown
   by ``tol`` (the ground-truth box only *selects* points; it does not shape the fit);
2. fit an oriented rectangle to their horizontal coordinates (:func:`fit_rectangle`): for
   every orientation the extent along each axis is the spread between the ``percentile``
   and ``100 - percentile`` quantiles, divided by ``1 - 2 percentile / 100`` (the exact
   correction for a uniform density); the orientation of least area wins (a robust version
   of the rotating-calipers minimum-area rectangle);
3. the ratio is shorter extent / longer extent.

Behaviour: on dense uniform samples of the true face the ratio is exact to well under 1%.
The trimming and its correction scale both extents alike, so the ratio does not depend on
the percentile for uniform samples. With sparse points (tens) the extreme points decide
the extents: ``n`` uniform points span on average ``(n - 1)/(n + 1)`` of each side, again
the same for both axes, so the ratio stays nearly unbiased but scatters (standard
deviation about 0.4% at 2000 points, 1.6% at 200, 4% at 50, 10% at 20). Real feature maps are not uniform: the ratio
is only as good as the features near the face's edges and corners; a face with no feature
near one edge looks shorter along that axis, and points of the side faces within ``tol`` of
the top edge lengthen it by up to ``tol``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ...errors import ConfigError

if TYPE_CHECKING:  # pragma: no cover
    from .layout import Box, BuiltinScene

Array = NDArray[np.float64]

__all__ = ["RectangleFit", "fit_rectangle", "top_face_mask", "estimate_box_ratio"]


@dataclass(frozen=True)
class RectangleFit:
    """An oriented rectangle fitted to 2-D points.

    Attributes
    ----------
    width, length : float
        Shorter and longer side (units of the points).
    angle : float
        Direction of the ``length`` side, radians in ``[0, pi)``, from the 2-D ``x`` axis.
    center : (2,) float array
        Centre of the robust extents.
    n_points : int
    """

    width: float
    length: float
    angle: float
    center: Array
    n_points: int

    @property
    def ratio(self) -> float:
        """``width / length`` (<= 1)."""
        return float(self.width / self.length) if self.length > 0 else float("nan")


def _extents(xy: Array, angles: Array, percentile: float) -> tuple[Array, Array, Array]:
    """Robust extents along the axes of every angle: ``(ext_a, ext_b, mid)``."""
    c, s = np.cos(angles), np.sin(angles)
    a = xy[:, :1] * c + xy[:, 1:] * s  # (N, A) coordinate along the axis at angle
    b = -xy[:, :1] * s + xy[:, 1:] * c
    q = [percentile, 100.0 - percentile]
    qa = np.percentile(a, q, axis=0)
    qb = np.percentile(b, q, axis=0)
    k = 1.0 / (1.0 - 2.0 * percentile / 100.0)
    mid = np.stack([0.5 * (qa[0] + qa[1]), 0.5 * (qb[0] + qb[1])], -1)
    return k * (qa[1] - qa[0]), k * (qb[1] - qb[0]), mid


def fit_rectangle(xy: Array, percentile: float = 1.0) -> RectangleFit:
    """Robust minimum-area oriented rectangle of 2-D points.

    Parameters
    ----------
    xy : (N, 2) float array, ``N >= 3``.
    percentile : float
        Trimmed fraction per side in percent, ``0 <= percentile < 25``; 0 gives the exact
        minimum-area bounding rectangle (up to the 0.02 degree angle search).

    Returns
    -------
    RectangleFit

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> pts = rng.uniform([-0.4, -0.5], [0.4, 0.5], size=(20000, 2))
    >>> round(fit_rectangle(pts).ratio, 2)
    0.8
    """
    xy = np.asarray(xy, dtype=float)
    if xy.ndim != 2 or xy.shape[1] != 2 or len(xy) < 3:
        raise ConfigError(f"fit_rectangle needs (N>=3, 2) points, got shape {xy.shape}")
    if not np.all(np.isfinite(xy)):
        raise ConfigError("fit_rectangle: points must be finite")
    if not 0.0 <= percentile < 25.0:
        raise ConfigError(f"percentile must be in [0, 25), got {percentile}")
    origin = xy.mean(0)
    xy = xy - origin
    coarse = np.radians(np.arange(0.0, 90.0, 1.0))
    ea, eb, _ = _extents(xy, coarse, percentile)
    best = coarse[np.argmin(ea * eb)]
    fine = best + np.radians(np.arange(-1.0, 1.0001, 0.02))
    ea, eb, mid = _extents(xy, fine, percentile)
    i = int(np.argmin(ea * eb))
    th = fine[i]
    c, s = np.cos(th), np.sin(th)
    center = origin + mid[i, 0] * np.array([c, s]) + mid[i, 1] * np.array([-s, c])
    if ea[i] >= eb[i]:
        length, width, angle = ea[i], eb[i], th
    else:
        length, width, angle = eb[i], ea[i], th + 0.5 * np.pi
    return RectangleFit(float(width), float(length), float(np.mod(angle, np.pi)), center, len(xy))


def top_face_mask(points_world: Array, box: "Box", tol: float) -> NDArray[np.bool_]:
    """Which points lie near the top face of ``box``.

    Parameters
    ----------
    points_world : (N, 3) float array, world frame, metres.
    box : Box
    tol : float
        Distance to the top plane, and growth of the footprint, in metres.

    Returns
    -------
    (N,) bool array.
    """
    P = np.asarray(points_world, dtype=float).reshape(-1, 3)
    q = (P - box.center) @ box.rotation  # box-frame coordinates
    w, l, h = box.size
    ok = np.all(np.isfinite(q), axis=1)
    return (ok & (np.abs(q[:, 2] - 0.5 * h) <= tol) & (np.abs(q[:, 0]) <= 0.5 * w + tol)
            & (np.abs(q[:, 1]) <= 0.5 * l + tol))


def estimate_box_ratio(points_world: Array, scene: "BuiltinScene", box_index: int | None = None,
                       tol: float = 0.02, percentile: float = 1.0) -> tuple[float, int]:
    """Width:length ratio of a box's top face as seen in a map.

    Parameters
    ----------
    points_world : (N, 3) float array
        Map points already aligned into the scene's world frame (metres).
    scene : BuiltinScene
    box_index : int, optional
        Index into ``scene.boxes``; default ``scene.ratio_box_index`` (the 0.80:1 box).
    tol : float
        Selection tolerance in metres (see :func:`top_face_mask`).
    percentile : float
        Trimming of :func:`fit_rectangle`, percent per side.

    Returns
    -------
    ratio : float
        Shorter / longer side of the fitted rectangle; ``nan`` when fewer than 4 points
        were selected (an expected failure: check ``n_points``).
    n_points : int
        Number of points selected on the top face.
    """
    if not np.isfinite(tol) or tol <= 0:
        raise ConfigError(f"tol must be positive, got {tol}")
    idx = scene.ratio_box_index if box_index is None else int(box_index)
    if not 0 <= idx < len(scene.boxes):
        raise ConfigError(f"box_index {idx} out of range [0, {len(scene.boxes)})")
    P = np.asarray(points_world, dtype=float).reshape(-1, 3)
    sel = P[top_face_mask(P, scene.boxes[idx], tol)]
    if len(sel) < 4:
        return float("nan"), int(len(sel))
    return fit_rectangle(sel[:, :2], percentile).ratio, int(len(sel))
