"""KITTI odometry sequences.

::

    <dataset>/sequences/NN/image_0/000000.png ...   left grey camera (P0)
    <dataset>/sequences/NN/image_2/000000.png ...   left colour camera (P2)
    <dataset>/sequences/NN/calib.txt                 P0..P3 (and Tr) rows, 3x4 row-major
    <dataset>/sequences/NN/times.txt                 seconds, one per image
    <dataset>/poses/NN.txt                           optional: 3x4 T_w0 per line

The poses are those of camera 0 (left grey) in the frame of its first pose. For
``image_2`` the camera-2 poses ``T_w2 = T_w0 @ T_02`` are returned, with the offset
``T_02`` (pure translation ``-K^-1 P2[:, 3]``) read from ``calib.txt``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from .files import read_text
from ..errors import DatasetError
from .cameras import _read_text, parse_kitti_calib
from .folder import read_times, resolve_camera
from .images import image_size, list_images
from .sequence import Frame, Sequence
from .trajectory import Trajectory

__all__ = ["open_kitti", "read_kitti_poses", "is_kitti"]


def is_kitti(root: Path) -> bool:
    """True when ``root`` looks like a KITTI odometry sequence folder."""
    return (root / "calib.txt").is_file() and any(
        (root / f"image_{k}").is_dir() for k in (0, 2)
    )


def read_kitti_poses(path: str | Path) -> NDArray[np.float64]:
    """Read a KITTI poses file: one row-major 3x4 camera-to-world matrix per line.

    Returns
    -------
    (N, 4, 4) float64 ``T_wc``.

    Raises
    ------
    DatasetError
        Missing file, a line without 12 numbers, non-finite values or a non-rotation.
    """
    path = Path(path)
    text = read_text(path, "poses", missing="poses file not found")
    mats = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        if len(fields) != 12:
            raise DatasetError(f"{path}:{lineno}: expected 12 numbers (3x4 pose), got {len(fields)}")
        try:
            M = np.array([float(f) for f in fields]).reshape(3, 4)
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: non-numeric value") from None
        if not np.all(np.isfinite(M)):
            raise DatasetError(f"{path}:{lineno}: non-finite value")
        R = M[:, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
            raise DatasetError(f"{path}:{lineno}: the 3x3 part is not a rotation matrix")
        T = np.eye(4)
        T[:3] = M
        mats.append(T)
    return np.asarray(mats).reshape(-1, 4, 4)


def _find_poses(root: Path) -> Path | None:
    for cand in (root.parent.parent / "poses" / f"{root.name}.txt", root / "poses.txt"):
        if cand.is_file():
            return cand
    return None


def open_kitti(
    root: str | Path,
    camera: PinholeCamera | str | Path | None = None,
    camera_id: int | None = None,
    poses: str | Path | None = None,
) -> Sequence:
    """Open a KITTI odometry sequence folder (``.../sequences/NN``).

    Parameters
    ----------
    root : the sequence folder.
    camera : a camera or camera file overriding ``calib.txt``.
    camera_id : 0 (``image_0``, grey) or 2 (``image_2``, colour); default: 0 if present.
    poses : ground-truth poses file; default ``../../poses/NN.txt`` or ``root/poses.txt``.

    Returns
    -------
    Sequence of kind ``"kitti"``.
    """
    root = Path(root)
    if camera_id is None:
        camera_id = 0 if (root / "image_0").is_dir() else 2
    if camera_id not in (0, 2):
        raise DatasetError(f"{root}: KITTI camera_id must be 0 or 2, got {camera_id}")
    files = list_images(root / f"image_{camera_id}")
    calib = root / "calib.txt"
    row = f"P{camera_id}"
    if camera is not None:
        cam = resolve_camera(camera, None, files[0], kitti_row=row)
    else:
        cam = parse_kitti_calib(
            _read_text(calib), str(calib), row, image_size=lambda: image_size(files[0])
        )[0]
    times_file = root / "times.txt"
    if times_file.is_file():
        times = read_times(times_file, expected=len(files))
    else:
        times = np.arange(len(files), dtype=np.float64)
    frames = [Frame(i, float(t), path=p) for i, (t, p) in enumerate(zip(times, files))]
    pose_file = Path(poses) if poses is not None else _find_poses(root)
    loader = None
    if pose_file is not None:
        def loader() -> Trajectory:
            T = read_kitti_poses(pose_file)
            if len(T) != len(files):
                raise DatasetError(
                    f"{pose_file}: has {len(T)} poses but there are {len(files)} images"
                )
            if camera_id != 0 and calib.is_file():
                P = parse_kitti_calib(_read_text(calib), str(calib), row, (1, 1))[1]
                T_0c = np.eye(4)
                T_0c[:3, 3] = -np.linalg.solve(P[:, :3], P[:, 3])
                T = T @ T_0c
            return Trajectory.from_poses(times, T)
    return Sequence(root.name, root, cam, frames, "kitti", loader)
