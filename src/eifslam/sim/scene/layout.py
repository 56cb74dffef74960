"""Geometry and exact ground truth of the built-in scene (the paper's first experiment).

Section IV of Wang & Dissanayake (2010): three rectangular boxes of different sizes on an
oval table, not exactly aligned; a camera on a trolley moves once round the table and
takes 54 images of 1024 x 768 pixels with a 56 degree horizontal field of view. The top
face of one box (the one on the right in the paper's Figure 1(a)) has a width:length
ratio of 0.80:1.

World frame (metres)
--------------------
* Origin at the centre of the (elliptical) table top, ``z`` **up**, the table top is the
  plane ``z = 0``; the table's long axis is ``x``, its short axis ``y``.
* The floor is the plane ``z = -TABLE_HEIGHT``; four walls close a square room.
* Camera poses are camera-to-world: ``p`` is the camera centre in the world and
  ``q_wc`` (Hamilton, ``[w, x, y, z]``) rotates camera-frame vectors (x right, y down,
  z forward) into the world, as in :mod:`eifslam.geometry`.

Everything visible is a planar, textured, one-sided rectangle (:class:`Surface`); the
texture itself is made by :mod:`eifslam.sim.scene.textures` when rendering. This module is
pure NumPy: it imports neither OpenCV nor matplotlib.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ...geometry.camera import PinholeCamera
from ...errors import ConfigError
from ...geometry.rotations import quat_to_rotmat, rotmat_to_quat

Array = NDArray[np.float64]

__all__ = [
    "scene_camera",
    "Box",
    "Surface",
    "BuiltinScene",
    "make_scene",
    "box_corners",
    "look_at",
    "TABLE_SEMI_AXES",
    "TABLE_HEIGHT",
    "ROOM_HALF_SIZE",
    "WALL_HEIGHT",
]

#: semi-axes (a along x, b along y) of the elliptical table top, metres
TABLE_SEMI_AXES = (0.90, 0.60)
#: height of the table top above the floor, metres
TABLE_HEIGHT = 0.75
#: the room is the square ``[-ROOM_HALF_SIZE, ROOM_HALF_SIZE]^2`` around the table, metres
ROOM_HALF_SIZE = 4.0
#: height of the walls above the floor, metres
WALL_HEIGHT = 3.0
#: camera path: semi-axes of the ellipse the trolley follows, and the camera height above
#: the table top (metres)
PATH_SEMI_AXES = (1.70, 1.40)
CAMERA_HEIGHT = 0.62
#: the point every camera looks at (world, metres)
LOOK_AT = (0.0, 0.0, 0.08)

#: (name, centre x, centre y, yaw degrees, width, length, height); width along the box's
#: own x axis, length along its y axis, metres. The "right" box has a 0.80:1 top face.
_BOX_SPECS = (
    ("left", -0.36, -0.06, 4.0, 0.24, 0.40, 0.30),
    ("middle", 0.00, 0.16, -6.0, 0.32, 0.48, 0.13),
    ("right", 0.37, -0.10, 9.0, 0.28, 0.35, 0.20),
)
_RATIO_BOX = 2

# texel sizes (metres) of the generated textures
_TEXEL_BOX = 0.001
_TEXEL_TABLE = 0.002
_TEXEL_FLOOR = 0.004
_TEXEL_WALL = 0.005
_TILE = 2.0  # floor and wall tiles, metres
# BGR tint per kind of surface, so that boxes, table, floor and walls differ in tone
_TINT = {"box": (1.0, 1.0, 1.0), "table": (0.55, 0.75, 1.0), "floor": (0.55, 0.55, 0.55),
         "wall": (1.0, 0.9, 0.8)}


@dataclass(frozen=True, eq=False)
class Surface:
    """A one-sided textured planar rectangle.

    The point of texture coordinates ``(s, t)`` (metres, ``0 <= s <= size_u``,
    ``0 <= t <= size_v``) is ``origin + s * axis_u + t * axis_v``. Texture columns run
    along ``axis_u`` and rows along ``axis_v``; the face is visible from the side of
    ``normal = axis_v x axis_u`` (so its texture reads unmirrored from that side).

    Attributes
    ----------
    name : str
    kind : str
        ``"box"``, ``"table"``, ``"floor"`` or ``"wall"``.
    origin, axis_u, axis_v : (3,) float arrays
        World frame; ``axis_u`` and ``axis_v`` are orthonormal.
    size_u, size_v : float
        Extent in metres.
    texel : float
        Nominal texel size of the texture in metres.
    shape : str
        ``"rect"`` or ``"ellipse"`` (the ellipse inscribed in the rectangle).
    seed : int
        Seed of this face's texture (distinct per face).
    shade : (float, float, float)
        Constant BGR factors: a fixed Lambertian light times a tint per kind of surface
        (warm table, darker floor), each in ``(0, 1]``.
    material : str
        What the texture is made of: ``"procedural"`` (:func:`eifslam.sim.scene.textures.make_texture`,
        the box scene) or a photograph-based material of :mod:`eifslam.sim.scene.photos`
        (``"tile:<image>"``, ``"poster:<image>:<cell>"``; the loop world).
    """

    name: str
    kind: str
    origin: Array
    axis_u: Array
    axis_v: Array
    size_u: float
    size_v: float
    texel: float
    shape: str
    seed: int
    shade: tuple[float, float, float]
    material: str = "procedural"

    @property
    def normal(self) -> Array:
        """(3,) unit normal of the visible side, world frame."""
        return np.cross(self.axis_v, self.axis_u)

    @property
    def corners(self) -> Array:
        """(4, 3) world corners at ``(s, t) = (0,0), (U,0), (U,V), (0,V)``."""
        o, u, v = self.origin, self.axis_u * self.size_u, self.axis_v * self.size_v
        return np.stack([o, o + u, o + u + v, o + v])


@dataclass(frozen=True, eq=False)
class Box:
    """A rectangular box standing on the table.

    Attributes
    ----------
    name : str
    corners : (8, 3) float array
        World frame, metres: the 4 bottom corners then the 4 top corners, each counter-
        clockwise seen from above, starting at the box's local ``(-w/2, -l/2)``.
    size : (float, float, float)
        ``(w, l, h)``: width along the box's own x axis, length along its y axis, height.
    center : (3,) float array
        Centre of the box (world, metres).
    yaw : float
        Rotation about the world ``z`` axis, radians.
    """

    name: str
    corners: Array
    size: tuple[float, float, float]
    center: Array
    yaw: float

    @property
    def rotation(self) -> Array:
        """(3, 3) ``R_wb``: box-frame axes (columns) in the world."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    @property
    def top_z(self) -> float:
        """Height of the top face, world ``z`` (metres)."""
        return float(self.center[2] + 0.5 * self.size[2])

    @property
    def top_ratio(self) -> float:
        """Width:length ratio of the top face (shorter side over longer side)."""
        w, l = self.size[:2]
        return float(min(w, l) / max(w, l))


@dataclass(frozen=True, eq=False)
class BuiltinScene:
    """The built-in scene: camera, trajectory, boxes and textured surfaces.

    Attributes
    ----------
    camera : PinholeCamera
    timestamps : (N,) float array, seconds
    positions : (N, 3) float array
        Camera centres ``p`` (world, metres).
    quats_wxyz : (N, 4) float array
        ``q_wc`` of every frame (camera-to-world).
    boxes : list of Box
    surfaces : list of Surface
        Everything the renderer draws.
    ratio_box_index : int
        Index into ``boxes`` of the box whose top face is 0.80:1.
    seed : int
        Seed of the textures and of the trolley's small wobble.
    description : str
        The body of the rendered folder's ``README.md`` (scene, world frame, files).
    world_frame : str
        Short description of the world frame (the ``groundtruth.tum`` header).
    """

    camera: PinholeCamera
    timestamps: Array
    positions: Array
    quats_wxyz: Array
    boxes: list[Box]
    surfaces: list[Surface]
    ratio_box_index: int
    seed: int
    description: str = (
        "Rendered by `eifslam render` (the paper's first experiment: three boxes on an oval table, "
        "a camera moving once round it).\nWorld frame: origin at the table-top centre, z up, "
        "metres. Poses are camera-to-world (camera x right, y down, z forward). Exact ground "
        "truth; `boxes.json` gives the box corners and which box has the 0.80:1 top face.")
    world_frame: str = "table centre, z up, m"

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        return int(self.positions.shape[0])

    @property
    def box_ratio_true(self) -> float:
        """True width:length ratio of the top face of the ratio box (0.80)."""
        return self.boxes[self.ratio_box_index].top_ratio

    def rotation_wc(self, k: int) -> Array:
        """(3, 3) ``R_wc`` of frame ``k``."""
        return quat_to_rotmat(self.quats_wxyz[k])

    def project(self, k: int, points_w: Array) -> tuple[Array, Array]:
        """Project world points into frame ``k``.

        Parameters
        ----------
        k : int
        points_w : (M, 3) world points, metres.

        Returns
        -------
        uv : (M, 2) pixels; depth : (M,) camera-frame ``z`` in metres.
        """
        X_c = (np.asarray(points_w, float) - self.positions[k]) @ self.rotation_wc(k)
        return self.camera.project(X_c), X_c[:, 2]


def box_corners(center_xy: tuple[float, float], yaw: float, size: tuple[float, float, float]) -> Array:
    """(8, 3) corners of a box standing on ``z = 0`` (order as in :class:`Box`)."""
    w, l, h = size
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s], [s, c]])
    local = np.array([[-w, -l], [w, -l], [w, l], [-w, l]]) * 0.5
    xy = local @ R.T + np.asarray(center_xy, float)
    bottom = np.column_stack([xy, np.zeros(4)])
    top = np.column_stack([xy, np.full(4, h)])
    return np.vstack([bottom, top])


def _face(name: str, kind: str, center: Array, normal: Array, axis_u: Array,
          size_u: float, size_v: float, texel: float, seed: int, shape: str = "rect") -> Surface:
    """A :class:`Surface` from its centre, visible normal and ``axis_u``."""
    n = np.asarray(normal, float)
    u = np.asarray(axis_u, float)
    v = np.cross(u, n)  # so that cross(v, u) == n
    light = np.array([0.3, -0.5, 0.81])
    lambert = 0.7 + 0.3 * max(0.0, float(n @ light / np.linalg.norm(light)))
    shade = tuple(round(lambert * c, 6) for c in _TINT[kind])
    origin = np.asarray(center, float) - 0.5 * size_u * u - 0.5 * size_v * v
    return Surface(name, kind, origin, u, v, float(size_u), float(size_v), texel, shape, seed, shade)


def _box_surfaces(box: Box, seed0: int) -> list[Surface]:
    """The 5 visible faces (not the bottom) of a box."""
    R = box.rotation
    ex, ey, ez = R[:, 0], R[:, 1], R[:, 2]
    w, l, h = box.size
    c = box.center
    faces = [_face(f"{box.name}/top", "box", c + 0.5 * h * ez, ez, ex, w, l, _TEXEL_BOX, seed0)]
    for i, (n, half, side) in enumerate(((ex, w, l), (-ex, w, l), (ey, l, w), (-ey, l, w))):
        faces.append(_face(f"{box.name}/side{i}", "box", c + 0.5 * half * n, n,
                           np.cross(ez, n), side, h, _TEXEL_BOX, seed0 + 1 + i))
    return faces


def _room_surfaces(seed0: int) -> list[Surface]:
    """Table top, floor tiles and wall tiles."""
    a, b = TABLE_SEMI_AXES
    ex, ey, ez = np.eye(3)
    out = [_face("table", "table", np.zeros(3), ez, ex, 2 * a, 2 * b, _TEXEL_TABLE, seed0, "ellipse")]
    L, n_t = ROOM_HALF_SIZE, int(round(2 * ROOM_HALF_SIZE / _TILE))
    centres = -L + _TILE * (np.arange(n_t) + 0.5)
    seed = seed0 + 1
    for i, x in enumerate(centres):
        for j, y in enumerate(centres):
            out.append(_face(f"floor/{i}{j}", "floor", np.array([x, y, -TABLE_HEIGHT]), ez, ex,
                             _TILE, _TILE, _TEXEL_FLOOR, seed))
            seed += 1
    zc = -TABLE_HEIGHT + 0.5 * WALL_HEIGHT
    for w, n in enumerate((-ex, ex, -ey, ey)):  # inward normals of the walls at +x, -x, +y, -y
        along = np.cross(ez, n)
        for i, s in enumerate(centres):
            centre = -L * n + s * along + zc * ez
            out.append(_face(f"wall{w}/{i}", "wall", centre, n, along, _TILE, WALL_HEIGHT,
                             _TEXEL_WALL, seed))
            seed += 1
    return out


def look_at(p: Array, target: Array) -> Array:
    """(3, 3) ``R_wc`` of a camera at ``p`` (world, m) looking at ``target`` with zero roll (world z up)."""
    z = target - p
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.array([0.0, 0.0, 1.0]))
    x = x / np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def _trajectory(n_frames: int, rng: np.random.Generator) -> tuple[Array, Array]:
    """Camera centres ``(N, 3)`` and ``R_wc`` ``(N, 3, 3)`` of one loop round the table.

    The trolley moves counter-clockwise (seen from above) along an ellipse at a nearly
    constant height, with a small smooth wobble (a few millimetres / a fraction of a degree)
    whose phases come from ``rng``.
    """
    th = 2.0 * np.pi * np.arange(n_frames) / n_frames - 0.5 * np.pi
    ph = rng.uniform(0.0, 2.0 * np.pi, size=4)
    A, B = PATH_SEMI_AXES
    r = 1.0 + 0.02 * np.sin(3 * th + ph[0])
    p = np.column_stack([A * r * np.cos(th), B * r * np.sin(th),
                         CAMERA_HEIGHT + 0.01 * np.sin(2 * th + ph[1])])
    target = np.asarray(LOOK_AT) + np.column_stack(
        [0.04 * np.sin(2 * th + ph[2]), 0.04 * np.cos(3 * th + ph[3]), np.zeros_like(th)])
    R = np.stack([look_at(p[k], target[k]) for k in range(n_frames)])
    return p, R


def scene_camera(n_frames: int, width: int, height: int, hfov_deg: float, frame_interval: float) -> PinholeCamera:
    """The pinhole camera of a built-in scene (square pixels, principal point at the image
    centre), after checking the scene's size settings.

    Raises
    ------
    ConfigError
        Fewer than 2 frames, an image under 16x16, a field of view outside [10, 150]
        degrees or a non-positive frame interval (s).
    """
    if int(n_frames) < 2:
        raise ConfigError(f"n_frames must be at least 2, got {n_frames}")
    if int(width) < 16 or int(height) < 16:
        raise ConfigError(f"image size must be at least 16x16, got {width}x{height}")
    if not 10.0 <= float(hfov_deg) <= 150.0:
        raise ConfigError(f"hfov_deg must be in [10, 150], got {hfov_deg}")
    if not frame_interval > 0:
        raise ConfigError(f"frame_interval must be positive, got {frame_interval}")
    f = 0.5 * width / np.tan(np.radians(0.5 * hfov_deg))
    cam = PinholeCamera(float(f), float(f), 0.5 * (width - 1), 0.5 * (height - 1), int(width), int(height))
    return cam


def make_scene(n_frames: int = 54, width: int = 1024, height: int = 768,
               hfov_deg: float = 56.0, seed: int = 0, frame_interval: float = 0.5) -> BuiltinScene:
    """Build the built-in scene (geometry and exact ground truth; no pixels).

    Parameters
    ----------
    n_frames : int
        Number of images along one loop round the table (paper: 54).
    width, height : int
        Image size in pixels (paper: 1024 x 768).
    hfov_deg : float
        Horizontal field of view in degrees (paper: 56); ``fx = fy = (width/2)/tan(hfov/2)``,
        principal point at the image centre ``((width-1)/2, (height-1)/2)``.
    seed : int
        Seed of the textures and of the trolley's wobble.
    frame_interval : float
        Seconds between frames (timestamps start at 0).

    Returns
    -------
    BuiltinScene

    Examples
    --------
    >>> s = make_scene()
    >>> s.n_frames, round(s.camera.hfov_deg, 6), round(s.box_ratio_true, 6)
    (54, 56.0, 0.8)
    """
    cam = scene_camera(n_frames, width, height, hfov_deg, frame_interval)
    boxes = []
    for name, x, y, yaw_deg, w, l, h in _BOX_SPECS:
        yaw = float(np.radians(yaw_deg))
        boxes.append(Box(name, box_corners((x, y), yaw, (w, l, h)), (w, l, h),
                         np.array([x, y, 0.5 * h]), yaw))
    surfaces: list[Surface] = []
    for i, box in enumerate(boxes):
        surfaces += _box_surfaces(box, 1000 * seed + 10 * i)
    surfaces += _room_surfaces(1000 * seed + 100)
    rng = np.random.default_rng(seed)
    p, R = _trajectory(int(n_frames), rng)
    return BuiltinScene(
        camera=cam,
        timestamps=frame_interval * np.arange(int(n_frames), dtype=float),
        positions=p,
        quats_wxyz=rotmat_to_quat(R),
        boxes=boxes,
        surfaces=surfaces,
        ratio_box_index=_RATIO_BOX,
        seed=int(seed),
    )
