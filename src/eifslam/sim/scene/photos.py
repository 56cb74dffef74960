"""Textures made from real photographs that scikit-image ships (no download needed).

The loop world (:mod:`eifslam.sim.scene.loop`) covers its walls, pillars and ground with
these, so that features behave as in real images. A :class:`~eifslam.sim.scene.layout.Surface`
names its material:

``"tile:<image>"``
    The image (e.g. ``brick``, ``gravel``, ``grass``) repeated with mirrored copies (no
    seams) at one source pixel per texel, from an offset and a half-turn chosen by the
    face's seed (bricks are turned to lie in horizontal courses). Repetitive on purpose,
    like a real rendered wall, path or hedge.
``"poster:<image>:<cell>"``
    Cell ``cell`` of a grid cut over the image (:data:`POSTER_GRID`), stretched over the
    face. Distinct cells share no pixels, so two posters never show the same content and a
    place that looks alike on two laps is the same place.

Every texture is multiplied by the face's ``shade`` (BGR lighting and tint). Images come
from :mod:`skimage.data` functions whose files are inside the scikit-image package
(scikit-image is imported on first use, OpenCV only to make a texture).
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import NDArray

from ...errors import ConfigError

__all__ = ["POSTER_GRID", "poster_cells", "cell_size", "photo_texture", "source_image"]

#: images cut into posters, and their grid (rows, columns); every one is a photograph
#: bundled with scikit-image (the left view only of the stereo pair, one of the two cats)
POSTER_GRID: dict[str, tuple[int, int]] = {
    "astronaut": (2, 2), "coffee": (2, 2), "chelsea": (1, 2), "rocket": (2, 2),
    "hubble_deep_field": (2, 3), "immunohistochemistry": (2, 2), "motorcycle_left": (2, 2),
    "camera": (2, 2), "moon": (2, 2), "cell": (2, 2), "coins": (1, 2), "text": (1, 2),
    "page": (1, 2), "clock": (1, 1), "retina": (2, 2),
}
#: images used as repeating materials
TILE_IMAGES = ("brick", "gravel", "grass")


@functools.lru_cache(maxsize=32)
def source_image(name: str) -> NDArray[np.uint8]:
    """A scikit-image data image as ``(H, W, 3)`` uint8 BGR (grey images replicated).

    Raises
    ------
    ConfigError
        For a name that is not one of the bundled images used here.
    """
    if name not in POSTER_GRID and name not in TILE_IMAGES:
        raise ConfigError(f"unknown photo {name!r}")
    import skimage.data

    if name == "motorcycle_left":
        img = skimage.data.stereo_motorcycle()[0]
    else:
        img = getattr(skimage.data, name)()
    img = np.asarray(img)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    bgr = np.ascontiguousarray(img[:, :, 2::-1]).astype(np.uint8)
    bgr.flags.writeable = False
    return bgr


def poster_cells() -> list[tuple[str, int]]:
    """Every ``(image, cell)`` a poster can show, in a fixed order."""
    return [(name, c) for name, (r, k) in POSTER_GRID.items() for c in range(r * k)]


def cell_size(name: str) -> tuple[int, int]:
    """Nominal ``(height, width)`` in pixels of a poster cell of image ``name``: the
    (cropped) image size over the grid, rounded down (a cell may be a pixel larger)."""
    rows, cols = POSTER_GRID[name]
    h, w = _cropped(name).shape[:2]
    return h // rows, w // cols


def _cropped(name: str) -> NDArray[np.uint8]:
    """The part of image ``name`` that is cut into posters."""
    img = source_image(name)
    if name == "retina":  # the fundus photograph sits in a black disc: use its central square
        h, w = img.shape[:2]
        img = img[h // 5: h - h // 5, w // 5: w - w // 5]
    return img


def _cell(name: str, cell: int) -> NDArray[np.uint8]:
    """The pixels of grid cell ``cell`` (row-major) of image ``name``."""
    rows, cols = POSTER_GRID[name]
    if not 0 <= cell < rows * cols:
        raise ConfigError(f"poster cell {cell} out of range for {name!r}")
    img = _cropped(name)
    h, w = img.shape[:2]
    r, c = divmod(cell, cols)
    return img[r * h // rows:(r + 1) * h // rows, c * w // cols:(c + 1) * w // cols]


def _tiled(name: str, width: int, height: int, rng: np.random.Generator) -> NDArray[np.uint8]:
    """``(height, width, 3)`` texture repeating image ``name`` with mirrored copies."""
    img = source_image(name)
    if name == "brick":  # the photograph shows the courses upright
        img = np.rot90(img)
    if rng.random() < 0.5:
        img = np.rot90(img, 2)
    h, w = img.shape[:2]
    period = np.vstack([np.hstack([img, img[:, ::-1]]), np.hstack([img[::-1], img[::-1, ::-1]])])
    y0, x0 = int(rng.integers(2 * h)), int(rng.integers(2 * w))
    ny = (y0 + height) // (2 * h) + 1
    nx = (x0 + width) // (2 * w) + 1
    big = np.tile(period, (ny, nx, 1))
    return big[y0:y0 + height, x0:x0 + width]


def photo_texture(material: str, width: int, height: int, seed: int,
                  shade: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> NDArray[np.uint8]:
    """The texture of a face made of ``material``.

    Parameters
    ----------
    material : str
        ``"tile:<image>"`` or ``"poster:<image>:<cell>"`` (see the module docstring).
    width, height : int
        Texture size in texels (columns along the face's ``axis_u``, rows along ``axis_v``).
    seed : int
        Seed of the tile's offset and orientation (posters ignore it).
    shade : (3,) float
        BGR factors applied at the end.

    Returns
    -------
    (height, width, 3) uint8 BGR image.
    """
    import cv2

    kind, _, rest = material.partition(":")
    if kind == "tile" and rest in TILE_IMAGES:
        img = _tiled(rest, int(width), int(height), np.random.default_rng(seed))
    elif kind == "poster":
        name, _, cell = rest.partition(":")
        if name not in POSTER_GRID or not cell.isdigit():
            raise ConfigError(f"unknown material {material!r}")
        src = _cell(name, int(cell))
        shrink = width * height < src.shape[0] * src.shape[1]
        img = cv2.resize(src, (int(width), int(height)),
                         interpolation=cv2.INTER_AREA if shrink else cv2.INTER_CUBIC)
    else:
        raise ConfigError(f"unknown material {material!r}")
    out = img.astype(np.float32) * np.asarray(shade, np.float32)
    return np.clip(out, 0, 255).astype(np.uint8)
