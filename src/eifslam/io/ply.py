"""Point clouds as PLY files (ASCII or binary little-endian), readable by MeshLab,
CloudCompare, Open3D, ...

The PLY format is the `plyfile <https://github.com/dranjan/python-plyfile>`_ library's
job; this module checks what goes in and what comes out. Vertices have ``float x, y, z``
(``double`` on request) and optionally ``uchar red, green, blue``. :func:`read_ply` reads
the vertices of any PLY file back (any of the three encodings, any property order; other
elements such as faces are ignored), and turns every way a file can be broken into one
:class:`~eifslam.errors.DatasetError` naming it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import DatasetError
from .files import atomic_path

__all__ = ["write_ply", "read_ply"]

def write_ply(
    path: str | Path,
    points: NDArray[np.floating],
    colors: NDArray[np.uint8] | None = None,
    binary: bool = True,
    double: bool = False,
) -> None:
    """Write a coloured point cloud.

    Parameters
    ----------
    path : output file.
    points : (N, 3) positions (world frame, any units); N may be 0.
    colors : (N, 3) uint8 RGB (note: *RGB*, not OpenCV's BGR), optional.
    binary : binary little-endian (default) or ASCII.
    double : store coordinates as ``double`` instead of ``float``.

    Raises
    ------
    DatasetError
        Wrong shapes, non-finite points or colours outside 0..255.
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise DatasetError(f"{path}: points must have shape (N, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise DatasetError(f"{path}: points contain NaN or infinite values")
    fields = [("x", "f8" if double else "f4"), ("y", "f8" if double else "f4"), ("z", "f8" if double else "f4")]
    if colors is not None:
        col = np.asarray(colors)
        if col.shape != pts.shape:
            raise DatasetError(f"{path}: colors must have shape {pts.shape}, got {col.shape}")
        if np.any(col < 0) or np.any(col > 255):
            raise DatasetError(f"{path}: colors must lie in 0..255")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    dtype = np.dtype([(n, "<" + t) for n, t in fields])
    data = np.empty(len(pts), dtype=dtype)
    data["x"], data["y"], data["z"] = pts.T
    if colors is not None:
        data["red"], data["green"], data["blue"] = col.astype(np.uint8).T
    from plyfile import PlyData, PlyElement

    ply = PlyData([PlyElement.describe(data, "vertex")], text=not binary, byte_order="<",
                  comments=["written by eifslam"])
    try:
        with atomic_path(path) as tmp:  # a kill never leaves half a file
            ply.write(str(tmp))
    except OSError as exc:
        raise DatasetError(f"{path}: cannot write PLY file ({exc})") from None


def read_ply(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.uint8] | None]:
    """Read the vertices of a PLY point cloud.

    Returns
    -------
    points : (N, 3) float64.
    colors : (N, 3) uint8 RGB, or ``None`` when the file has no colours.

    Raises
    ------
    DatasetError
        Missing file, not a PLY file, truncated data, no ``x, y, z`` vertex properties,
        list or non-finite coordinates (one line naming the file).
    """
    from plyfile import PlyData, PlyParseError

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: PLY file not found")
    try:
        with open(path, "rb") as fh:
            ply = PlyData.read(fh, mmap=False)
        vertex = ply["vertex"].data if "vertex" in ply else None
    except (PlyParseError, ValueError, TypeError, IndexError, KeyError, EOFError, OSError, MemoryError,
            OverflowError, UnicodeDecodeError) as exc:
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise DatasetError(f"{path}: not a readable PLY file ({msg})") from None
    if vertex is None:
        raise DatasetError(f"{path}: PLY file has no vertex element")
    names = set(vertex.dtype.names or ())
    if not {"x", "y", "z"} <= names:
        raise DatasetError(f"{path}: vertex properties x, y, z missing")
    try:
        pts = np.stack([vertex["x"], vertex["y"], vertex["z"]], -1).astype(np.float64).reshape(-1, 3)
        colors = None
        if {"red", "green", "blue"} <= names:
            colors = np.stack([vertex["red"], vertex["green"], vertex["blue"]], -1).astype(np.uint8).reshape(-1, 3)
    except (TypeError, ValueError) as exc:  # list properties
        raise DatasetError(f"{path}: unsupported vertex properties ({exc})") from None
    if not np.all(np.isfinite(pts)):
        raise DatasetError(f"{path}: vertex coordinates contain NaN or infinite values")
    return pts, colors
