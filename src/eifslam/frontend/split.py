"""The split of feature tracks between relative poses (``Ωp``) and the map (``Ωm``).

Pure NumPy. Every track is assigned once, when it is created, and keeps its set for ever
(:class:`eifslam.frontend.tracks.TrackStore` stores the flag per track id, and merges only
tracks of the same set), so the same raw measurement never feeds both a relative pose and
a map feature.

The rule (the paper's SURF criterion, computed for any detector):

1. The sign of the Laplacian of the image at the keypoint, at the keypoint's scale, is
   computed by :func:`laplacian_sign` as a box difference of means (surround minus centre),
   the box approximation of a difference of Gaussians that SURF itself uses. ``+1`` is a
   dark blob on a brighter background, ``-1`` a bright blob (or a flat patch).
2. Among the tracks created from one image, :func:`assign_to_map` puts into ``Ωm`` the
   strongest (by detector response) keypoints of positive sign, as many as
   ``round(map_fraction * n_new)``; if the positive class is too small, the strongest
   negative ones complete it. All other new tracks go to ``Ωp``. The sign therefore
   decides the partition, the response only trims the map class to the requested
   fraction, and the map gets the most repeatable keypoints.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["integral_image", "box_mean", "laplacian_sign", "assign_to_map"]


def integral_image(gray: NDArray) -> Array:
    """Summed-area table with a zero first row and column, shape ``(H + 1, W + 1)``."""
    g = np.asarray(gray, dtype=np.float64)
    S = np.zeros((g.shape[0] + 1, g.shape[1] + 1))
    np.cumsum(np.cumsum(g, 0), 1, out=S[1:, 1:])
    return S


def box_mean(S: Array, x: NDArray, y: NDArray, r: NDArray) -> Array:
    """Mean of the image over ``[x - r, x + r] x [y - r, y + r]`` (clipped to the image).

    Parameters
    ----------
    S : (H + 1, W + 1) integral image from :func:`integral_image`.
    x, y : (N,) integer pixel centres (column, row).
    r : (N,) integer half-widths.

    Returns
    -------
    (N,) means.
    """
    H, W = S.shape[0] - 1, S.shape[1] - 1
    x0 = np.clip(x - r, 0, W - 1)
    x1 = np.clip(x + r, 0, W - 1) + 1
    y0 = np.clip(y - r, 0, H - 1)
    y1 = np.clip(y + r, 0, H - 1) + 1
    total = S[y1, x1] - S[y0, x1] - S[y1, x0] + S[y0, x0]
    return total / ((x1 - x0) * (y1 - y0))


def laplacian_sign(S: Array, uv_raw: Array, scale_px: Array) -> NDArray[np.int8]:
    """Sign of the scale-normalised Laplacian at keypoints.

    Parameters
    ----------
    S : (H + 1, W + 1) integral image of the grayscale image.
    uv_raw : (N, 2) keypoint positions in the (distorted) image, pixels.
    scale_px : (N,) keypoint scale (Gaussian sigma), pixels.

    Returns
    -------
    (N,) int8 in {-1, +1}; +1 where the surround is brighter than the centre.
    """
    uv = np.asarray(uv_raw, float).reshape(-1, 2)
    if len(uv) == 0:
        return np.zeros(0, np.int8)
    x = np.rint(uv[:, 0]).astype(np.int64)
    y = np.rint(uv[:, 1]).astype(np.int64)
    r1 = np.maximum(1, np.rint(np.asarray(scale_px, float))).astype(np.int64)
    lap = box_mean(S, x, y, 2 * r1) - box_mean(S, x, y, r1)
    return np.where(lap > 0, 1, -1).astype(np.int8)


def assign_to_map(sign: NDArray, response: Array, map_fraction: float) -> NDArray[np.bool_]:
    """Choose which new tracks go to the map set ``Ωm``.

    Parameters
    ----------
    sign : (N,) Laplacian signs of the keypoints that start new tracks.
    response : (N,) detector responses (larger is stronger).
    map_fraction : float in [0, 1]

    Returns
    -------
    (N,) bool, True for ``Ωm``; exactly ``round(map_fraction * N)`` are True.

    Examples
    --------
    >>> assign_to_map(np.array([1, -1, 1, 1]), np.array([3.0, 9.0, 1.0, 2.0]), 0.5)
    array([ True, False, False,  True])
    """
    sign = np.asarray(sign).reshape(-1)
    response = np.asarray(response, float).reshape(-1)
    n = len(sign)
    k = int(round(map_fraction * n))
    # positive sign first, then by decreasing response; stable for ties
    order = np.lexsort((-response, -(sign > 0).astype(np.int64)))
    out = np.zeros(n, bool)
    out[order[:k]] = True
    return out
