"""Whether two frames of a built-in scene see the same place, from the exact geometry.

A loop closure is true when its two frames see the same place. The rule: at least a
fifth of each view, taken at the depth of the scene it shows, lies inside the other view
at a like depth. Here a view is a regular grid of pixels (:data:`GRID`); each is lifted to
the world point the scene shows there (the nearest front-facing surface its ray meets,
as the renderer draws it). That point *lies inside the other view at a like depth* when

* it projects inside the other image, in front of the camera;
* the other view's own scene depth at that pixel agrees with the point's depth there to
  within :data:`DEPTH_TOLERANCE` (relative): the other camera sees that very point, not a
  wall in front of it;
* its depths in the two views differ by at most the factor :data:`DEPTH_RATIO`: the two
  cameras see it at a like scale, as descriptors can match it (a wall seen from its two
  ends, at grazing angles, is not the same place).

Pixels that show no surface count in neither the fraction's numerator nor its denominator.

Two walls that carry the same photograph are different places: their points lie at
different positions in the world, so a view of one does not contain the other, however
alike the images look.

Pure NumPy (no OpenCV): the depth comes from intersecting pixel rays with the scene's
planar :class:`~eifslam.sim.scene.layout.Surface` rectangles (ellipses for
``shape == "ellipse"``).

>>> from eifslam.sim.scene import make_scene
>>> s = make_scene(n_frames=54)
>>> same_place(s, 0, 1), same_place(s, 0, 27)
(True, False)
"""

from __future__ import annotations

import weakref

import numpy as np
from numpy.typing import NDArray

from ...errors import ConfigError
from .layout import BuiltinScene

Array = NDArray[np.float64]

__all__ = ["same_place", "view_overlap", "view_points", "scene_depth", "GRID", "MIN_FRACTION",
           "DEPTH_TOLERANCE", "DEPTH_RATIO"]

#: pixel grid (columns, rows) that stands for a view
GRID = (32, 24)
#: least fraction of each view that must lie in the other for the same place
MIN_FRACTION = 0.2
#: relative depth difference under which a point counts as seen by the other view
DEPTH_TOLERANCE = 0.1
#: largest ratio of a point's depths in the two views for a like depth
DEPTH_RATIO = 1.5
_NEAR = 0.01  # metres, as the renderer

# per scene (by identity, dropped with the scene): frame -> (world points, valid mask)
_VIEWS: "weakref.WeakKeyDictionary[BuiltinScene, dict[int, tuple[Array, NDArray[np.bool_]]]]" = \
    weakref.WeakKeyDictionary()


def _surface_arrays(scene: BuiltinScene) -> tuple[Array, Array, Array, Array, Array, NDArray[np.bool_]]:
    """Origins, normals, axes u and v ``(S, 3)``, sizes ``(S, 2)`` and ellipse flags ``(S,)``."""
    f = scene.surfaces
    return (np.array([s.origin for s in f], float).reshape(-1, 3),
            np.array([s.normal for s in f], float).reshape(-1, 3),
            np.array([s.axis_u for s in f], float).reshape(-1, 3),
            np.array([s.axis_v for s in f], float).reshape(-1, 3),
            np.array([(s.size_u, s.size_v) for s in f], float).reshape(-1, 2),
            np.array([s.shape == "ellipse" for s in f], bool))


def _check_frame(scene: BuiltinScene, k: int) -> int:
    if not 0 <= int(k) < scene.n_frames:
        raise ConfigError(f"frame index {k} out of range [0, {scene.n_frames})")
    return int(k)


def scene_depth(scene: BuiltinScene, k: int, uv: Array) -> Array:
    """Depth (camera ``z``, metres) the scene shows at pixels ``uv`` of frame ``k``.

    Parameters
    ----------
    scene : BuiltinScene
    k : int
        Frame index.
    uv : (M, 2) float array
        Pixels (centres at integer coordinates).

    Returns
    -------
    (M,) float array
        The depth of the nearest front-facing surface each pixel's ray meets; ``inf`` where
        it meets none.
    """
    k = _check_frame(scene, k)
    uv = np.asarray(uv, float).reshape(-1, 2)
    cam = scene.camera
    rays_c = np.column_stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy,
                              np.ones(len(uv))])  # z = 1: the ray parameter is the depth
    R_wc = scene.rotation_wc(k)
    p = scene.positions[k]
    rays_w = rays_c @ R_wc.T
    o, n, au, av, size, ellipse = _surface_arrays(scene)
    # keep the faces whose visible side faces the camera and that reach in front of it
    front = np.einsum("sj,sj->s", n, p - o) > 1e-9
    corners = np.stack([o, o + au * size[:, :1], o + au * size[:, :1] + av * size[:, 1:],
                        o + av * size[:, 1:]], axis=1)  # (S, 4, 3)
    ahead = ((corners - p) @ R_wc[:, 2]).max(axis=1) > _NEAR
    keep = front & ahead
    if not keep.any() or len(uv) == 0:
        return np.full(len(uv), np.inf)
    o, n, au, av, size, ellipse = o[keep], n[keep], au[keep], av[keep], size[keep], ellipse[keep]
    denom = rays_w @ n.T  # (M, S)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.einsum("sj,sj->s", n, o - p)[None, :] / denom
    t = np.where(np.isfinite(t) & (t > _NEAR), t, np.inf)
    tf = np.where(np.isfinite(t), t, 0.0)
    # texture coordinates of the hit, over the face's size: (p - o + t ray) . axis / size
    s_ = (np.einsum("sj,sj->s", p - o, au)[None, :] + tf * (rays_w @ au.T)) / size[None, :, 0]
    t_ = (np.einsum("sj,sj->s", p - o, av)[None, :] + tf * (rays_w @ av.T)) / size[None, :, 1]
    inside = (s_ >= 0) & (s_ <= 1) & (t_ >= 0) & (t_ <= 1)
    round_ = (s_ - 0.5) ** 2 + (t_ - 0.5) ** 2 <= 0.25
    inside &= np.where(ellipse[None, :], round_, True)
    t = np.where(inside, t, np.inf)
    return t.min(axis=1)


def _grid(scene: BuiltinScene) -> Array:
    """(M, 2) pixel centres of the :data:`GRID` cells."""
    cam = scene.camera
    cols, rows = GRID
    u = (np.arange(cols) + 0.5) * cam.width / cols - 0.5
    v = (np.arange(rows) + 0.5) * cam.height / rows - 0.5
    uu, vv = np.meshgrid(u, v)
    return np.column_stack([uu.ravel(), vv.ravel()])


def view_points(scene: BuiltinScene, k: int) -> tuple[Array, NDArray[np.bool_]]:
    """The view of frame ``k``: the world points its :data:`GRID` pixels show.

    Returns
    -------
    points_w : (M, 3) float array
        World points, metres (``M = GRID[0] * GRID[1]``; zeros where ``valid`` is false).
    valid : (M,) bool array
        Pixels that show a surface.
    """
    k = _check_frame(scene, k)
    views = _VIEWS.setdefault(scene, {})
    if k not in views:
        uv = _grid(scene)
        depth = scene_depth(scene, k, uv)
        valid = np.isfinite(depth)
        cam = scene.camera
        X_c = np.column_stack([(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy,
                               np.ones(len(uv))]) * np.where(valid, depth, 0.0)[:, None]
        views[k] = (X_c @ scene.rotation_wc(k).T + scene.positions[k], valid)
    return views[k]


def view_overlap(scene: BuiltinScene, i: int, j: int) -> float:
    """Fraction of frame ``i``'s view that lies inside frame ``j``'s view at a like depth.

    Returns
    -------
    float
        In ``[0, 1]``; 0 when frame ``i`` shows no surface.
    """
    j = _check_frame(scene, j)
    X, valid = view_points(scene, i)
    if not valid.any():
        return 0.0
    z_i = (X[valid] - scene.positions[i]) @ scene.rotation_wc(i)[:, 2]
    uv, z = scene.project(j, X[valid])
    cam = scene.camera
    ins = (z > _NEAR) & (np.maximum(z, z_i) <= DEPTH_RATIO * np.minimum(z, z_i)) & (uv[:, 0] >= -0.5) & (uv[:, 0] <= cam.width - 0.5) \
        & (uv[:, 1] >= -0.5) & (uv[:, 1] <= cam.height - 0.5)
    seen = np.zeros(len(z), bool)
    if ins.any():
        d = scene_depth(scene, j, uv[ins])
        seen[ins] = np.abs(d - z[ins]) <= DEPTH_TOLERANCE * z[ins]
    return float(seen.sum() / valid.sum())


def same_place(scene: BuiltinScene, i: int, j: int) -> bool:
    """Whether frames ``i`` and ``j`` see the same place.

    True when at least :data:`MIN_FRACTION` of each view lies inside the other at a like
    depth (:func:`view_overlap` both ways; see the module docstring).

    Parameters
    ----------
    scene : BuiltinScene
        Any built-in scene (the boxes, the loop world, the aliasing scene).
    i, j : int
        Frame indices.

    Returns
    -------
    bool
    """
    return (view_overlap(scene, i, j) >= MIN_FRACTION
            and view_overlap(scene, j, i) >= MIN_FRACTION)
