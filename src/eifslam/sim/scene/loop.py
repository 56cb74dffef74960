"""The loop world: a camera walks twice round a city block of textured walls.

A second built-in scene (``eifslam render --scene loop``), made for loop closure: the
camera travels the same closed path several times, so that the drift of the first lap is
seen when it comes back to the start, and the places of lap 1 are seen again on lap 2.

World frame (metres)
--------------------
* Origin on the ground at the centre of the block, ``z`` **up**; the ground is ``z = 0``.
* The block is the box ``|x| <= BLOCK_HALF[0]``, ``|y| <= BLOCK_HALF[1]``, ``BLOCK_HEIGHT``
  tall: walls of pebble-dash render (``skimage.data.gravel``, a different tint per 2 m
  panel) with one poster per panel (a cell of one of scikit-image's photographs, never
  shown twice) and pillars standing ``PILLAR_OFFSET`` in front of the walls. (Brick walls,
  ``skimage.data.brick``, were tried first: with ORB the repeated bricks along the
  horizontal epipolar lines of a sideways-moving camera gave wrong matches and the scale
  collapsed a hundredfold within 80 frames; ``WALL_MATERIAL`` switches back.)
* The ground is gravel (``skimage.data.gravel``) in 2 m tiles; the far side of the street
  is a hedge (``skimage.data.grass``) with posters, ``STREET_WIDTH`` from the block.
* Camera poses are camera-to-world, as in :mod:`eifslam.sim.scene.layout`.

The path is a rounded rectangle at ``PATH_DISTANCE`` from the block's walls, walked
counter-clockwise (seen from above) from the middle of the ``y = -BLOCK_HALF[1]`` side,
with the camera looking at the block, a little down. The distance to the walls swells by
up to ``LAP_OFFSET`` and back over the run (so lap 2 passes a place a little farther or
nearer than lap 1, and the last frame is back next to the first), with a small smooth
walking wobble of height, heading, pitch and roll.

This module is pure NumPy; the textures are made by :mod:`eifslam.sim.scene.photos` when
rendering.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from ...errors import ConfigError
from ...geometry.rotations import rotmat_to_quat
from .layout import BuiltinScene, Surface, look_at, scene_camera
from .photos import cell_size, poster_cells

Array = NDArray[np.float64]

__all__ = ["make_loop_scene", "path_length", "BLOCK_HALF", "BLOCK_HEIGHT", "PATH_DISTANCE",
           "LAP_OFFSET", "CAMERA_HEIGHT", "STREET_WIDTH"]

#: half sizes (x, y) of the block the camera walks round, metres
BLOCK_HALF = (4.0, 2.5)
#: height of the block's walls, metres
BLOCK_HEIGHT = 4.0
#: distance of the lap-1 path from the block's walls, metres
PATH_DISTANCE = 3.5
#: how much farther from the walls the path swells half way through the run, metres
LAP_OFFSET = 0.25
#: camera height above the ground, metres, and its downward pitch, degrees
CAMERA_HEIGHT = 1.5
PITCH_DEG = 8.0
#: the hedge on the far side of the street stands this far from the block, metres
STREET_WIDTH = 7.0
HEDGE_HEIGHT = 8.0
#: pillars: distance in front of the walls, side, height and spacing, metres
PILLAR_OFFSET = 1.0
PILLAR_SIZE = 0.3
PILLAR_HEIGHT = 3.0
PILLAR_SPACING = 2.6
_PANEL = 2.0  # target width of a wall panel (one poster each), metres
#: material of the block's walls (see :mod:`eifslam.sim.scene.photos`)
WALL_MATERIAL = "tile:gravel"
_TEXEL_WALL = 0.004
_TEXEL_PILLAR = 0.003
_TEXEL_GROUND = 0.006
_TEXEL_HEDGE = 0.01
_LIGHT = np.array([0.45, -0.3, 0.84])


def _shade(normal: Array, tint: tuple[float, float, float]) -> tuple[float, float, float]:
    """BGR factors: a fixed Lambertian light times ``tint``."""
    lam = 0.65 + 0.35 * max(0.0, float(normal @ _LIGHT / np.linalg.norm(_LIGHT)))
    return tuple(round(lam * c, 6) for c in tint)


def _rect(name: str, kind: str, centre: Array, normal: Array, axis_u: Array, size_u: float,
          size_v: float, texel: float, seed: int, material: str, tint=(1.0, 1.0, 1.0)) -> Surface:
    """A rectangle :class:`Surface` from its centre, visible normal and ``axis_u``."""
    n = np.asarray(normal, float)
    u = np.asarray(axis_u, float)
    v = np.cross(u, n)
    origin = np.asarray(centre, float) - 0.5 * size_u * u - 0.5 * size_v * v
    return Surface(name, kind, origin, u, v, float(size_u), float(size_v), float(texel), "rect",
                   int(seed), _shade(n, tint), material)


def _sides(half: tuple[float, float]) -> list[tuple[Array, Array, float]]:
    """The four sides of the rectangle ``|x| <= hx, |y| <= hy``: (centre, outward normal,
    length), counter-clockwise from the ``-y`` side."""
    hx, hy = half
    return [(np.array([0.0, -hy, 0.0]), np.array([0.0, -1.0, 0.0]), 2 * hx),
            (np.array([hx, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]), 2 * hy),
            (np.array([0.0, hy, 0.0]), np.array([0.0, 1.0, 0.0]), 2 * hx),
            (np.array([-hx, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0]), 2 * hy)]


def _poster(name: str, wall_point: Array, normal: Array, along: Array, width: float,
            cell: tuple[str, int], seed: int, lift: float) -> Surface:
    """A poster of photo cell ``cell``, ``width`` wide, its bottom ``lift`` above the ground,
    1 cm in front of the wall point ``wall_point`` (its centre along the wall)."""
    img, c = cell
    ch, cw = cell_size(img)
    height = width * ch / cw
    centre = wall_point + 0.01 * normal + np.array([0.0, 0.0, lift + 0.5 * height])
    return _rect(name, "poster", centre, normal, along, width, height, width / cw, seed,
                 f"poster:{img}:{c}")


def _block_surfaces(rng: np.random.Generator, cells: list[tuple[str, int]], seed0: int) -> list[Surface]:
    """The block's wall panels, a poster on each, and the pillars in front."""
    ez = np.array([0.0, 0.0, 1.0])
    out: list[Surface] = []
    seed = seed0
    for w, (centre, n, length) in enumerate(_sides(BLOCK_HALF)):
        along = np.cross(ez, n)
        n_pan = max(1, int(round(length / _PANEL)))
        pw = length / n_pan
        for i in range(n_pan):
            mid = centre + (-0.5 * length + (i + 0.5) * pw) * along
            tint = (rng.uniform(0.45, 0.75), rng.uniform(0.55, 0.85), rng.uniform(0.8, 1.0))
            out.append(_rect(f"block{w}/{i}", "wall", mid + 0.5 * BLOCK_HEIGHT * ez, n, along, pw,
                             BLOCK_HEIGHT, _TEXEL_WALL, seed, WALL_MATERIAL, tint))
            width = rng.uniform(0.9, 1.3)
            shift = rng.uniform(-0.5, 0.5) * (pw - width - 0.1)
            out.append(_poster(f"block{w}/{i}/poster", mid + shift * along, n, along, width,
                               cells.pop(), seed + 1, rng.uniform(0.5, 0.9)))
            seed += 2
        n_pil = max(1, int(np.floor(length / PILLAR_SPACING)))
        for i in range(n_pil):
            base = centre + (i - 0.5 * (n_pil - 1)) * PILLAR_SPACING * along \
                + (PILLAR_OFFSET + 0.5 * PILLAR_SIZE) * n
            tint = tuple(rng.uniform(0.8, 1.0, 3))
            for f, pn in enumerate((n, along, -n, -along)):
                out.append(_rect(f"pillar{w}.{i}/{f}", "pillar",
                                 base + 0.5 * PILLAR_SIZE * pn + 0.5 * PILLAR_HEIGHT * ez, pn,
                                 np.cross(ez, pn), PILLAR_SIZE, PILLAR_HEIGHT, _TEXEL_PILLAR, seed,
                                 "tile:gravel", tint))
                seed += 1
    return out


def _street_surfaces(rng: np.random.Generator, cells: list[tuple[str, int]], seed0: int) -> list[Surface]:
    """Gravel ground tiles and the hedge (with posters) across the street, facing the block."""
    ez = np.array([0.0, 0.0, 1.0])
    ox, oy = BLOCK_HALF[0] + STREET_WIDTH, BLOCK_HALF[1] + STREET_WIDTH
    out: list[Surface] = []
    seed = seed0
    nx, ny = int(round(ox)), int(round(oy))  # tiles of about 2 m
    tx, ty = 2 * ox / nx, 2 * oy / ny
    for i in range(nx):
        for j in range(ny):
            c = np.array([-ox + (i + 0.5) * tx, -oy + (j + 0.5) * ty, 0.0])
            if abs(c[0]) + 0.5 * tx < BLOCK_HALF[0] and abs(c[1]) + 0.5 * ty < BLOCK_HALF[1]:
                continue  # under the block
            tint = tuple(rng.uniform(0.84, 0.9, 3))
            out.append(_rect(f"ground/{i}.{j}", "ground", c, ez, np.array([1.0, 0.0, 0.0]), tx, ty,
                             _TEXEL_GROUND, seed, "tile:gravel", tint))
            seed += 1
    for w, (centre, n, length) in enumerate(_sides((ox, oy))):
        along = np.cross(ez, -n)
        n_pan = max(1, int(round(length / _PANEL)))
        pw = length / n_pan
        for i in range(n_pan):
            mid = centre + (-0.5 * length + (i + 0.5) * pw) * along
            tint = (rng.uniform(0.35, 0.55), rng.uniform(0.75, 0.95), rng.uniform(0.45, 0.65))
            out.append(_rect(f"hedge{w}/{i}", "hedge", mid + 0.5 * HEDGE_HEIGHT * ez, -n, along, pw,
                             HEDGE_HEIGHT, _TEXEL_HEDGE, seed, "tile:grass", tint))
            if i % 2 == 0 and cells:
                out.append(_poster(f"hedge{w}/{i}/poster", mid, -n, along, 1.6, cells.pop(),
                                   seed + 1, rng.uniform(1.0, 2.5)))
            seed += 2
    return out


def path_length(distance: float = PATH_DISTANCE, half: tuple[float, float] = BLOCK_HALF) -> float:
    """Length of one lap (metres) of the rounded rectangle ``distance`` from a block of half
    sizes ``half`` (default: the loop world's block)."""
    return 4.0 * (half[0] + half[1]) + 2.0 * np.pi * distance


def _foot(station: Array, half: tuple[float, float] = BLOCK_HALF,
          distance: float = PATH_DISTANCE) -> tuple[Array, Array]:
    """Nearest block point ``(N, 3)`` and outward unit normal ``(N, 3)`` (world) of the
    rounded rectangle ``distance`` from the block ``|x| <= half[0], |y| <= half[1]``, at
    ``station`` metres along it (modulo one lap) from the middle of its ``-y`` side."""
    hx, hy = half
    arc = 0.5 * np.pi * distance
    # pieces in order: (length, start foot point, direction of the foot, start normal angle)
    pieces = [(hx, (0.0, -hy), (1.0, 0.0), -0.5 * np.pi), (arc, (hx, -hy), (0.0, 0.0), -0.5 * np.pi),
              (2 * hy, (hx, -hy), (0.0, 1.0), 0.0), (arc, (hx, hy), (0.0, 0.0), 0.0),
              (2 * hx, (hx, hy), (-1.0, 0.0), 0.5 * np.pi), (arc, (-hx, hy), (0.0, 0.0), 0.5 * np.pi),
              (2 * hy, (-hx, hy), (0.0, -1.0), np.pi), (arc, (-hx, -hy), (0.0, 0.0), np.pi),
              (hx, (-hx, -hy), (1.0, 0.0), 1.5 * np.pi)]
    s = np.mod(np.asarray(station, float), path_length(distance, half))
    foot = np.zeros((len(s), 3))
    ang = np.zeros(len(s))
    start = 0.0
    for length, f0, d, a0 in pieces:
        sel = (s >= start) & (s <= start + length)
        t = s[sel] - start
        is_arc = d == (0.0, 0.0)
        foot[sel, :2] = np.asarray(f0) + (0.0 if is_arc else 1.0) * t[:, None] * np.asarray(d)
        ang[sel] = a0 + (t / distance if is_arc else 0.0)
        start += length
    return foot, np.column_stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)])


def _trajectory(n_frames: int, n_laps: float, rng: np.random.Generator,
                half: tuple[float, float] = BLOCK_HALF, distance: float = PATH_DISTANCE,
                lap_offset: float = LAP_OFFSET) -> tuple[Array, Array]:
    """Camera centres ``(N, 3)`` and ``R_wc`` ``(N, 3, 3)`` of ``n_laps`` laps (a fraction
    of a lap allowed) round the block of half sizes ``half``, ``distance`` from its walls,
    swelling by up to ``lap_offset`` half way through the run."""
    L = path_length(distance, half)
    station = n_laps * L * np.arange(n_frames) / n_frames
    u = station / (n_laps * L)  # run fraction
    foot, n = _foot(station, half, distance)
    dist = distance + lap_offset * 0.5 * (1.0 - np.cos(2.0 * np.pi * u))
    ph = rng.uniform(0.0, 2.0 * np.pi, size=5)
    w = station / L * 2.0 * np.pi  # one radian per lap / 2 pi
    p = foot + dist[:, None] * n
    p[:, 2] = CAMERA_HEIGHT + 0.04 * np.sin(2.7 * w + ph[0]) + 0.015 * np.sin(23.0 * w + ph[1])
    yaw = np.radians(3.0) * np.sin(3.3 * w + ph[2])
    pitch = np.radians(PITCH_DEG + 1.5 * np.sin(4.1 * w + ph[3]))
    roll = np.radians(1.0) * np.sin(5.3 * w + ph[4])
    cy, sy = np.cos(yaw), np.sin(yaw)
    look = -n  # horizontal, towards the block; turn by yaw about z, then pitch down
    look = np.column_stack([cy * look[:, 0] - sy * look[:, 1], sy * look[:, 0] + cy * look[:, 1],
                            np.zeros(n_frames)])
    fwd = np.cos(pitch)[:, None] * look - np.sin(pitch)[:, None] * np.array([0.0, 0.0, 1.0])
    R = np.stack([look_at(p[k], p[k] + fwd[k]) for k in range(n_frames)])
    cr, sr = np.cos(roll), np.sin(roll)
    Rroll = np.zeros((n_frames, 3, 3))
    Rroll[:, 0, 0], Rroll[:, 0, 1], Rroll[:, 1, 0], Rroll[:, 1, 1] = cr, -sr, sr, cr
    Rroll[:, 2, 2] = 1.0
    return p, R @ Rroll


def make_loop_scene(n_frames: int = 1040, n_laps: int = 2, width: int = 640, height: int = 480,
                    hfov_deg: float = 60.0, seed: int = 0, frame_interval: float = 0.1) -> BuiltinScene:
    """Build the loop world (geometry and exact ground truth; no pixels).

    Parameters
    ----------
    n_frames : int
        Number of images over the whole run (default 1040: 520 per lap, about 9 cm apart).
    n_laps : int
        Laps of the path; frame ``n_frames`` (one past the last) would be back at the start.
    width, height : int
        Image size in pixels.
    hfov_deg : float
        Horizontal field of view in degrees; square pixels, principal point at the centre.
    seed : int
        Seed of the tints, poster choice and placement, tile offsets and walking wobble.
    frame_interval : float
        Seconds between frames (default 0.1: walking at about 0.9 m/s, 10 images/s).

    Returns
    -------
    BuiltinScene
        With no boxes (``ratio_box_index = -1``); :func:`~eifslam.sim.scene.render.render_scene`
        writes it in the shared data layout.

    Examples
    --------
    >>> s = make_loop_scene()
    >>> s.n_frames, s.camera.width, round(s.camera.hfov_deg, 6)
    (1040, 640, 60.0)
    """
    if int(n_laps) < 1:
        raise ConfigError(f"n_laps must be at least 1, got {n_laps}")
    cam = scene_camera(n_frames, width, height, hfov_deg, frame_interval)
    rng = np.random.default_rng(seed)
    cells = poster_cells()
    cells = [cells[i] for i in rng.permutation(len(cells))]
    surfaces = _block_surfaces(rng, cells, 100_000 * int(seed))
    surfaces += _street_surfaces(rng, cells, 100_000 * int(seed) + 50_000)
    p, R = _trajectory(int(n_frames), int(n_laps), rng)
    desc = (f"Rendered by `eifslam render --scene loop`: the loop world, {int(n_laps)} laps of a "
            f"camera walking round a {2 * BLOCK_HALF[0]:g} x {2 * BLOCK_HALF[1]:g} m block of "
            "rendered walls with posters and pillars (textures: photographs bundled with "
            "scikit-image).\n"
            "World frame: origin on the ground at the block centre, z up, metres. Poses are "
            "camera-to-world (camera x right, y down, z forward). Exact ground truth.")
    return BuiltinScene(
        camera=cam,
        timestamps=frame_interval * np.arange(int(n_frames), dtype=float),
        positions=p,
        quats_wxyz=rotmat_to_quat(R),
        boxes=[],
        surfaces=surfaces,
        ratio_box_index=-1,
        seed=int(seed),
        description=desc,
        world_frame="block centre on the ground, z up, m",
    )
