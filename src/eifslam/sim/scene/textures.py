"""Procedural, feature-rich textures for the built-in scene (uses OpenCV for drawing).

Every face gets its own texture from its own seed, so no two faces look alike and feature
matching is unambiguous. A texture superimposes, from coarse to fine:

1. colour value noise at several octaves (smooth gradients, large blobs);
2. filled random shapes (ellipses, rectangles, triangles) at geometrically spaced sizes
   from a quarter of the texture down to a few texels, each layer covering a fixed fraction
   of the area so coarse layers stay visible;
3. random strings of letters and digits in several font sizes;
4. a little fine grain.

This gives corner- and blob-like structures at every scale that SIFT, ORB and AKAZE pick
up, and none of the periodic patterns that make matching ambiguous.
"""

from __future__ import annotations

import string

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["make_texture", "ellipse_alpha"]

_FONTS = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_COMPLEX,
          cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_PLAIN)
_CHARS = np.array(list(string.ascii_uppercase + string.digits + "#&%@"))


def _colours(rng: np.random.Generator, n: int) -> NDArray[np.int64]:
    """(n, 3) random saturated-ish BGR colours: one channel pushed dark or bright."""
    c = rng.uniform(0, 255, size=(n, 3))
    extreme = np.where(rng.random(n) < 0.5, rng.uniform(0, 60, n), rng.uniform(195, 255, n))
    c[np.arange(n), rng.integers(3, size=n)] = extreme
    return c.astype(np.int64)


def _value_noise(h: int, w: int, rng: np.random.Generator) -> NDArray[np.float32]:
    """(h, w, 3) float32 colour noise in [0, 255] summed over octaves."""
    out = np.zeros((h, w, 3), np.float32)
    total = 0.0
    cells = 3
    amp = 1.0
    while cells <= max(h, w) / 4:
        ch = max(2, int(round(cells * h / max(h, w))))
        cw = max(2, int(round(cells * w / max(h, w))))
        small = rng.uniform(0, 255, size=(ch, cw, 3)).astype(np.float32)
        out += amp * cv2.resize(small, (w, h), interpolation=cv2.INTER_CUBIC)
        total += amp
        cells *= 2
        amp *= 0.6
    return out / max(total, 1e-9)


def _shapes(img: NDArray[np.uint8], rng: np.random.Generator, min_size: float, coverage: float) -> None:
    """Draw filled shapes at geometrically spaced sizes (largest first), in place."""
    h, w = img.shape[:2]
    size = max(h, w) / 4.0
    while size >= min_size:
        n = int(np.ceil(coverage * h * w / (size * size)))
        centres = rng.uniform(0, 1, size=(n, 2)) * [w, h]
        sizes = size * rng.uniform(0.5, 1.0, n)
        cols = _colours(rng, n)
        kinds = rng.integers(3, size=n)
        angles = rng.uniform(0, np.pi, n)
        aspect = rng.uniform(0.3, 1.0, n)
        tri = rng.uniform(-0.5, 0.5, size=(n, 3, 2))
        for i in range(n):
            (cx, cy), s, col = centres[i], sizes[i], tuple(int(c) for c in cols[i])
            if kinds[i] == 0:
                axes = (max(1, int(s / 2)), max(1, int(s / 2 * aspect[i])))
                cv2.ellipse(img, (int(cx), int(cy)), axes, float(np.degrees(angles[i])), 0, 360,
                            col, -1, cv2.LINE_AA)
                continue
            if kinds[i] == 1:
                ca, sa = np.cos(angles[i]), np.sin(angles[i])
                half = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]]) * s
                half[:, 1] *= aspect[i]
                pts = half @ np.array([[ca, sa], [-sa, ca]]) + [cx, cy]
            else:
                pts = tri[i] * s + [cx, cy]
            cv2.fillConvexPoly(img, pts.astype(np.int32), col, cv2.LINE_AA)
        size /= 2.0


def _text(img: NDArray[np.uint8], rng: np.random.Generator, min_height: float) -> None:
    """Draw random strings at several font sizes, in place."""
    h, w = img.shape[:2]
    height = max(h, w) / 8.0
    while height >= min_height:
        n = int(np.ceil(0.04 * h * w / (height * height * 4)))
        for _ in range(n):
            txt = "".join(rng.choice(_CHARS, size=int(rng.integers(2, 7))))
            font = int(rng.choice(_FONTS))
            scale = cv2.getFontScaleFromHeight(font, int(height), 1)
            thick = max(1, int(height / 10 * rng.uniform(0.7, 1.5)))
            org = (int(rng.uniform(-0.1 * w, w)), int(rng.uniform(0, h + height)))
            col = tuple(int(c) for c in _colours(rng, 1)[0])
            cv2.putText(img, txt, org, font, scale, col, thick, cv2.LINE_AA)
        height /= 2.0


def make_texture(width: int, height: int, seed: int,
                 shade: float | tuple[float, float, float] = 1.0) -> NDArray[np.uint8]:
    """A distinctive multi-scale texture.

    Parameters
    ----------
    width, height : int
        Texture size in texels.
    seed : int
        Seed of a fresh :class:`numpy.random.Generator`; the same seed gives the same image.
    shade : float or (3,) BGR factors
        Brightness factor(s) applied at the end (constant face lighting and tint).

    Returns
    -------
    (height, width, 3) uint8 BGR image.
    """
    rng = np.random.default_rng(seed)
    img = _value_noise(height, width, rng)
    # stretch the noise contrast so that the smooth layer carries structure too
    img = (img - img.mean()) * 1.8 + rng.uniform(90, 165, size=3).astype(np.float32)
    img = np.clip(img, 0, 255).astype(np.uint8)
    _shapes(img, rng, min_size=4.0, coverage=0.12)
    _text(img, rng, min_height=7.0)
    grain = rng.standard_normal(size=img.shape, dtype=np.float32) * np.float32(6.0)
    img = cv2.GaussianBlur(img.astype(np.float32) + grain, (0, 0), 0.6)
    return np.clip(img * np.asarray(shade, np.float32), 0, 255).astype(np.uint8)


def ellipse_alpha(width: int, height: int) -> NDArray[np.uint8]:
    """(height, width) uint8 mask, 255 inside the ellipse inscribed in the texture.

    Texel ``(i, j)`` is centred at ``((i + 0.5) / width, (j + 0.5) / height)`` in
    normalised texture coordinates; the ellipse is the unit-disc of ``2 * (x - 0.5)``.
    """
    x = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    y = (np.arange(height) + 0.5) / height * 2.0 - 1.0
    inside = x[None, :] ** 2 + y[:, None] ** 2 <= 1.0
    return (inside * 255).astype(np.uint8)
