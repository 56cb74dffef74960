"""Strecha multi-view data sets: images with one ``.camera`` file each.

::

    <root>/images/0000.jpg ...                (or the images directly in <root>)
    <root>/images/0000.jpg.camera ...         (or in <root>/gt_cameras/, or in <root>)
    <root>/times.txt                          optional; else the frame index

A ``.camera`` file holds K (3 rows), the radial distortion (1 row), ``R`` (3 rows,
camera-to-world), the centre ``C`` (1 row) and ``width height``; the projection is
``P = K [R^T | -R^T C]``. All views must share the intrinsics (one camera per sequence).
The first image must have a camera file (it gives the intrinsics); views without one
have no ground truth.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry.camera import PinholeCamera
from ..errors import DatasetError
from .cameras import _read_text, parse_strecha_camera
from .folder import read_times, resolve_camera
from .images import IMAGE_EXTENSIONS, list_images
from .sequence import Frame, Sequence
from .trajectory import Trajectory

__all__ = ["open_strecha", "find_strecha"]


def _image_dir(root: Path) -> Path:
    return root / "images" if (root / "images").is_dir() else root


def _camera_file(root: Path, image: Path) -> Path | None:
    name = image.name + ".camera"
    for folder in (image.parent, root / "gt_cameras", root / "cameras", root):
        if (folder / name).is_file():
            return folder / name
    return None


def find_strecha(root: Path) -> bool:
    """True when ``root`` holds images with Strecha ``.camera`` files."""
    folder = _image_dir(root)
    if not folder.is_dir():
        return False
    first = next(
        (p for p in sorted(folder.iterdir()) if p.suffix.lower() in IMAGE_EXTENSIONS), None
    )
    return first is not None and _camera_file(root, first) is not None


def open_strecha(root: str | Path, camera: PinholeCamera | str | Path | None = None) -> Sequence:
    """Open a Strecha data set (module docstring).

    Parameters
    ----------
    root : data set folder.
    camera : a camera or camera file overriding the ``.camera`` intrinsics.

    Returns
    -------
    Sequence of kind ``"strecha"``; ground truth from the ``.camera`` files.
    """
    root = Path(root)
    files = list_images(_image_dir(root))
    cam_files = [_camera_file(root, f) for f in files]
    if cam_files[0] is None:
        raise DatasetError(f"{files[0]}: no {files[0].name}.camera file found")
    parsed = {
        i: parse_strecha_camera(_read_text(cf), str(cf))
        for i, cf in enumerate(cam_files)
        if cf is not None
    }
    first = parsed[0]
    for i, sc in parsed.items():
        if not np.allclose(sc.camera.K, first.camera.K, rtol=1e-6):
            raise DatasetError(
                f"{cam_files[i]}: intrinsics differ from {cam_files[0]} (one camera per sequence)"
            )
    cam = first.camera if camera is None else resolve_camera(camera, None, files[0])
    times_file = root / "times.txt"
    if times_file.is_file():
        times = read_times(times_file, expected=len(files))
    else:
        times = np.arange(len(files), dtype=np.float64)
    frames = [Frame(i, float(t), path=p) for i, (t, p) in enumerate(zip(times, files))]

    def loader() -> Trajectory:
        idx = sorted(parsed)
        T = np.tile(np.eye(4), (len(idx), 1, 1))
        for k, i in enumerate(idx):
            T[k, :3, :3], T[k, :3, 3] = parsed[i].R_wc, parsed[i].C
        return Trajectory.from_poses(times[idx], T)

    return Sequence(root.name, root, cam, frames, "strecha", loader)
