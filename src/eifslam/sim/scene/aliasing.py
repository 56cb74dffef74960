"""The aliasing scene: one lap round a block whose walls repeat the same photographs.

A third built-in scene (``eifslam render --scene aliasing``), made to test that loop
closing refuses perceptual aliases. The camera walks once round a block, as in the loop
world (:mod:`eifslam.sim.scene.loop`), and a little past its start: until the last part
of the path no place is seen twice, so every loop closed before then is false; the last
part comes back to the start, the one true loop.

The block's walls are 2 m panels, each a *design*: a pebble-dash wall (texture offset and
tint), one poster (a cell of one of scikit-image's photographs, its size and place on the
panel) and, for some designs, a pillar in front at a fixed place. Panels of the same
design are identical, and the ground is one gravel tile repeated every 2 m in line with
the panels, so nothing near a repeated panel tells the copies apart. The designs along
the path (:data:`PANELS`, counter-clockwise from the start):

======  =============  =======================================
side    faces          panels (path order)
======  =============  =======================================
0       ``-y``         D, U2 | U1, A   (the path starts at ``|``)
1       ``+x``         B, C
2       ``+y``         A, B, D, A
3       ``-x``         B, C
======  =============  =======================================

So photograph A hangs on walls facing ``-y`` and ``+y`` and twice on the ``+y`` side
(6 m apart), B on walls facing three directions, and the block is the same under a
half-turn from the ``A|B`` corner of sides 0 and 1 to the ``A|B`` corner of sides 2 and 3
along the whole of sides 1 and 3: a view there matches its copy half a lap away over
several metres of path. The start (U1, U2) is unique, so the true loop is there to find.

World frame as the loop world: origin on the ground at the block centre, ``z`` up,
metres; camera poses camera-to-world. Pure NumPy; textures are made when rendering.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ...errors import ConfigError
from ...geometry.rotations import rotmat_to_quat
from .layout import BuiltinScene, Surface, scene_camera
from .loop import (CAMERA_HEIGHT, LAP_OFFSET, PILLAR_HEIGHT, PILLAR_OFFSET, PILLAR_SIZE, _poster,
                   _rect, _sides, _trajectory, path_length)

Array = NDArray[np.float64]

__all__ = ["AliasingScene", "make_aliasing_scene", "BLOCK_HALF", "BLOCK_HEIGHT", "PATH_DISTANCE",
           "REVISIT", "LEAD_IN", "PANELS", "PANEL_WIDTH", "POSTER_POOL"]

#: half sizes (x, y) of the block, metres (whole panels on every side)
BLOCK_HALF = (4.0, 2.0)
#: height of the block's walls, metres
BLOCK_HEIGHT = 4.0
#: distance of the path from the block's walls, metres
PATH_DISTANCE = 3.0
#: metres the path goes on past its start, the true loop
REVISIT = 5.0
#: metres before coming back to its start where the path's last part begins (the views
#: there may reach the first frames' views)
LEAD_IN = 3.5
#: width of a wall panel (one design each), metres
PANEL_WIDTH = 2.0
#: the designs of the panels of each side, in path order (see the module docstring)
PANELS: tuple[tuple[str, ...], ...] = (("D", "U2", "U1", "A"), ("B", "C"), ("A", "B", "D", "A"),
                                       ("B", "C"))
#: designs with a pillar in front, and where along the panel (from its centre, metres)
_PILLARS = {"A": 0.55, "C": -0.6, "U1": 0.3}
#: the poster cells the designs draw from (one per photograph): those where SIFT finds the
#: most features (several hundred to 1800 on a 300 px wide copy), so that an alias
#: matches as well as a true place would
POSTER_POOL: tuple[tuple[str, int], ...] = (
    ("immunohistochemistry", 0), ("page", 0), ("coins", 1), ("immunohistochemistry", 2),
    ("motorcycle_left", 1), ("chelsea", 0), ("astronaut", 2), ("camera", 3), ("text", 0),
    ("coins", 0), ("motorcycle_left", 0), ("hubble_deep_field", 1))
#: the far side of the street (a hedge), metres from the block, and its height
STREET_WIDTH = 6.0
HEDGE_HEIGHT = 8.0
_TEXEL_WALL = 0.004
_TEXEL_PILLAR = 0.003
_TEXEL_GROUND = 0.006
_TEXEL_HEDGE = 0.01


@dataclass(frozen=True, eq=False)
class AliasingScene(BuiltinScene):
    """The aliasing scene: a :class:`~eifslam.sim.scene.layout.BuiltinScene` that also says
    where the path's last part begins.

    Attributes
    ----------
    last_part_start : int
        First frame of the path's last part, ``LEAD_IN`` metres before the path comes back
        to its start. Before it no two frames see the same place unless they are close
        along the path (:func:`eifslam.sim.scene.places.same_place`).
    revisit_start : int
        First frame at or past the start of the path again (one lap walked).
    """

    last_part_start: int = 0
    revisit_start: int = 0

    @property
    def photo_walls(self) -> dict[str, list[str]]:
        """Poster material (``"poster:<image>:<cell>"``) -> names of the posters showing it."""
        out: dict[str, list[str]] = {}
        for f in self.surfaces:
            if f.kind == "poster":
                out.setdefault(f.material, []).append(f.name)
        return out


def _designs(rng: np.random.Generator, seed0: int) -> dict[str, dict]:
    """Every panel design: wall texture seed and tint, poster cell, width, shift and lift."""
    names = sorted({d for side in PANELS for d in side})
    cells: list[tuple[str, int]] = []
    for c in rng.permutation(len(POSTER_POOL)):  # one cell per photograph
        if POSTER_POOL[c][0] not in {img for img, _ in cells}:
            cells.append(POSTER_POOL[c])
    if len(cells) < len(names):
        raise ConfigError(f"{len(names)} designs need as many photographs, the pool has {len(cells)}")
    out = {}
    for i, name in enumerate(names):
        width = rng.uniform(0.9, 1.2)
        out[name] = {
            "seed": seed0 + 10 * i,
            "tint": (rng.uniform(0.45, 0.75), rng.uniform(0.55, 0.85), rng.uniform(0.8, 1.0)),
            "cell": cells[i],
            "width": width,
            "shift": rng.uniform(-0.5, 0.5) * (PANEL_WIDTH - width - 0.1),
            "lift": rng.uniform(0.5, 0.8),
            "pillar_tint": tuple(rng.uniform(0.8, 1.0, 3)),
        }
    return out


def _block_surfaces(designs: dict[str, dict]) -> list[Surface]:
    """The block's panels (wall, poster, pillar by design) in path order."""
    ez = np.array([0.0, 0.0, 1.0])
    out: list[Surface] = []
    for w, ((centre, n, length), side) in enumerate(zip(_sides(BLOCK_HALF), PANELS)):
        along = np.cross(ez, n)
        if abs(len(side) * PANEL_WIDTH - length) > 1e-9:
            raise ConfigError(f"side {w} is {length} m long, not {len(side)} panels")
        for i, name in enumerate(side):
            d = designs[name]
            mid = centre + (-0.5 * length + (i + 0.5) * PANEL_WIDTH) * along
            out.append(_rect(f"block{w}/{i}:{name}", "wall", mid + 0.5 * BLOCK_HEIGHT * ez, n, along,
                             PANEL_WIDTH, BLOCK_HEIGHT, _TEXEL_WALL, d["seed"], "tile:gravel",
                             d["tint"]))
            out.append(_poster(f"block{w}/{i}:{name}/poster", mid + d["shift"] * along, n, along,
                               d["width"], d["cell"], d["seed"] + 1, d["lift"]))
            if name in _PILLARS:
                base = mid + _PILLARS[name] * along + (PILLAR_OFFSET + 0.5 * PILLAR_SIZE) * n
                for f, pn in enumerate((n, along, -n, -along)):
                    out.append(_rect(f"pillar{w}.{i}:{name}/{f}", "pillar",
                                     base + 0.5 * PILLAR_SIZE * pn + 0.5 * PILLAR_HEIGHT * ez, pn,
                                     np.cross(ez, pn), PILLAR_SIZE, PILLAR_HEIGHT, _TEXEL_PILLAR,
                                     d["seed"] + 2 + f, "tile:gravel", d["pillar_tint"]))
    return out


def _street_surfaces(seed0: int) -> list[Surface]:
    """Ground of identical 2 m gravel tiles (edges in line with the panels) and a hedge."""
    ez = np.array([0.0, 0.0, 1.0])
    ox, oy = BLOCK_HALF[0] + STREET_WIDTH, BLOCK_HALF[1] + STREET_WIDTH
    out: list[Surface] = []
    nx, ny = int(round(ox / PANEL_WIDTH)), int(round(oy / PANEL_WIDTH))
    for i in range(-nx, nx):
        for j in range(-ny, ny):
            c = np.array([(i + 0.5) * PANEL_WIDTH, (j + 0.5) * PANEL_WIDTH, 0.0])
            if abs(c[0]) < BLOCK_HALF[0] and abs(c[1]) < BLOCK_HALF[1]:
                continue  # under the block
            out.append(_rect(f"ground/{i}.{j}", "ground", c, ez, np.array([1.0, 0.0, 0.0]),
                             PANEL_WIDTH, PANEL_WIDTH, _TEXEL_GROUND, seed0, "tile:gravel",
                             (0.87, 0.87, 0.87)))
    seed = seed0 + 1
    for w, (centre, n, length) in enumerate(_sides((ox, oy))):
        along = np.cross(ez, -n)
        n_pan = max(1, int(round(length / PANEL_WIDTH)))
        pw = length / n_pan
        for i in range(n_pan):
            mid = centre + (-0.5 * length + (i + 0.5) * pw) * along
            out.append(_rect(f"hedge{w}/{i}", "hedge", mid + 0.5 * HEDGE_HEIGHT * ez, -n, along, pw,
                             HEDGE_HEIGHT, _TEXEL_HEDGE, seed, "tile:grass", (0.45, 0.85, 0.55)))
            seed += 1
    return out


def make_aliasing_scene(n_frames: int = 400, width: int = 640, height: int = 480,
                        hfov_deg: float = 60.0, seed: int = 0,
                        frame_interval: float = 0.1) -> AliasingScene:
    """Build the aliasing scene (geometry and exact ground truth; no pixels).

    Parameters
    ----------
    n_frames : int
        Number of images over the whole path (default 400: one lap of
        ``path_length(PATH_DISTANCE, BLOCK_HALF)`` = 42.8 m plus ``REVISIT`` = 5 m, about
        12 cm apart).
    width, height : int
        Image size in pixels.
    hfov_deg : float
        Horizontal field of view in degrees; square pixels, principal point at the centre.
    seed : int
        Seed of the designs (photographs, tints, texture offsets, poster places) and of
        the walking wobble.
    frame_interval : float
        Seconds between frames (default 0.1: about 1.2 m/s, 10 images/s).

    Returns
    -------
    AliasingScene
        :func:`~eifslam.sim.scene.render.render_scene` writes it in the shared data layout.

    Examples
    --------
    >>> s = make_aliasing_scene()
    >>> s.n_frames, s.camera.width, s.last_part_start < s.revisit_start < s.n_frames
    (400, 640, True)
    """
    cam = scene_camera(n_frames, width, height, hfov_deg, frame_interval)
    n_frames = int(n_frames)
    rng = np.random.default_rng(seed)
    designs = _designs(rng, 100_000 * int(seed))
    surfaces = _block_surfaces(designs) + _street_surfaces(100_000 * int(seed) + 50_000)
    lap = path_length(PATH_DISTANCE, BLOCK_HALF)
    run = lap + REVISIT
    p, R = _trajectory(n_frames, run / lap, rng, BLOCK_HALF, PATH_DISTANCE, LAP_OFFSET)
    station = run * np.arange(n_frames) / n_frames
    last = int(np.searchsorted(station, lap - LEAD_IN))
    back = int(np.searchsorted(station, lap))
    photos = {name: f"{d['cell'][0]} (cell {d['cell'][1]})" for name, d in designs.items()}
    desc = (f"Rendered by `eifslam render --scene aliasing`: the aliasing scene, one lap and "
            f"{REVISIT:g} m of a camera walking round a {2 * BLOCK_HALF[0]:g} x "
            f"{2 * BLOCK_HALF[1]:g} m block whose wall panels repeat the same photographs "
            "(textures: photographs bundled with scikit-image).\n"
            "Panels in path order, side by side (sides face -y, +x, +y, -x; the path starts "
            "between U2 and U1): " + " / ".join(" ".join(side) for side in PANELS) + ".\n"
            "Photographs: " + ", ".join(f"{k} {v}" for k, v in sorted(photos.items())) + ".\n"
            f"The path comes back to no place it has passed before frame {last} (its last "
            f"part); frames from {back} on pass the start again (the one true loop). Every loop "
            "closed before the last part is false.\n"
            "World frame: origin on the ground at the block centre, z up, metres. Poses are "
            "camera-to-world (camera x right, y down, z forward). Exact ground truth.")
    return AliasingScene(
        camera=cam,
        timestamps=frame_interval * np.arange(n_frames, dtype=float),
        positions=p,
        quats_wxyz=rotmat_to_quat(R),
        boxes=[],
        surfaces=surfaces,
        ratio_box_index=-1,
        seed=int(seed),
        description=desc,
        world_frame="block centre on the ground, z up, m",
        last_part_start=last,
        revisit_start=back,
    )
