"""Point clouds as PLY files (ASCII or binary little-endian), readable by MeshLab,
CloudCompare, Open3D, ...

Vertices have ``float x, y, z`` (``double`` on request) and optionally ``uchar red,
green, blue``. :func:`read_ply` reads such vertex-only files back (any of the three PLY
encodings, any vertex property order).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..errors import DatasetError
from .files import atomic_path

__all__ = ["write_ply", "read_ply"]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def write_ply(
    path: str | Path,
    points: NDArray[np.floating],
    colors: NDArray[np.uint8] | None = None,
    binary: bool = True,
    double: bool = False,
) -> None:
    """Write a coloured point cloud (atomically: see :func:`~.files.atomic_path`).

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
    ptype = "double" if double else "float"
    header = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        "comment written by eifslam",
        f"element vertex {len(pts)}",
        f"property {ptype} x",
        f"property {ptype} y",
        f"property {ptype} z",
    ]
    if colors is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:  # a kill never leaves half a file
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            fh.write(data.tobytes())
        else:
            fmt = "%.9g %.9g %.9g" + (" %d %d %d" if colors is not None else "")
            rows = pts if colors is None else np.hstack([pts, col.astype(np.float64)])
            if len(rows):
                np.savetxt(fh, rows, fmt=fmt)


def read_ply(path: str | Path) -> tuple[NDArray[np.float64], NDArray[np.uint8] | None]:
    """Read a vertex-only PLY point cloud.

    Returns
    -------
    points : (N, 3) float64.
    colors : (N, 3) uint8 RGB, or ``None`` when the file has no colours.

    Raises
    ------
    DatasetError
        Missing file, bad header, list properties, or truncated data.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise DatasetError(f"{path}: PLY file not found") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read PLY file ({exc.strerror or exc})") from None
    try:
        return _parse_ply(raw, path)
    except (ValueError, IndexError, UnicodeDecodeError) as exc:  # a malformed header or body
        raise DatasetError(f"{path}: malformed PLY file ({exc})") from None


def _parse_ply(raw: bytes, path: Path) -> tuple[NDArray[np.float64], NDArray[np.uint8] | None]:
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise DatasetError(f"{path}: not a PLY file (no 'ply' magic or 'end_header')")
    body_start = raw.index(b"\n", end) + 1
    header = raw[:end].decode("ascii", errors="replace").splitlines()
    fmt, n_vertex, props, element = None, 0, [], None
    for line in header[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            element = tok[1]
            if element == "vertex":
                n_vertex = int(tok[2])
                if n_vertex < 0:
                    raise DatasetError(f"{path}: negative vertex count {n_vertex}")
            elif int(tok[2]) > 0:
                raise DatasetError(f"{path}: only vertex elements are supported, found {tok[1]}")
        elif tok[0] == "property" and element == "vertex":
            if tok[1] == "list" or tok[1] not in _PLY_TYPES:
                raise DatasetError(f"{path}: unsupported vertex property {line.strip()!r}")
            props.append((tok[2], _PLY_TYPES[tok[1]]))
    names = [n for n, _ in props]
    if not {"x", "y", "z"} <= set(names):
        raise DatasetError(f"{path}: vertex properties x, y, z missing")
    if fmt == "ascii":
        text = raw[body_start:].decode("ascii").split()
        vals = np.array(text[: n_vertex * len(props)], dtype=np.float64)
        if vals.size != n_vertex * len(props):
            raise DatasetError(f"{path}: truncated data ({vals.size} values)")
        table = vals.reshape(n_vertex, len(props))
        col = {n: table[:, k] for k, n in enumerate(names)}
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        if len(raw) - body_start < dtype.itemsize * n_vertex:
            raise DatasetError(f"{path}: truncated data")
        arr = np.frombuffer(raw, dtype=dtype, count=n_vertex, offset=body_start)
        col = {n: arr[n] for n in names}
    else:
        raise DatasetError(f"{path}: unknown PLY format {fmt!r}")
    pts = np.stack([col["x"], col["y"], col["z"]], -1).astype(np.float64).reshape(-1, 3)
    colors = None
    if {"red", "green", "blue"} <= set(names):
        colors = np.stack([col["red"], col["green"], col["blue"]], -1).astype(np.uint8).reshape(-1, 3)
    return pts, colors
