"""The folder layout of eifslam's evaluation data sets.

::

    <root>/images/         frames, in sorted file-name order
    <root>/camera.yaml     intrinsics (any format :func:`~.cameras.load_camera` reads)
    <root>/times.txt       optional: one timestamp (s) per image; else the frame index
    <root>/groundtruth.tum optional: camera-to-world poses, TUM format (scoring only)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from .files import read_text
from ..errors import DatasetError
from .cameras import load_camera
from .images import image_size, list_images
from .sequence import Frame, Sequence
from .trajectory import Trajectory, associate, read_tum

__all__ = ["open_folder", "read_times", "resolve_camera", "ground_truth_at_frames"]


def read_times(path: str | Path, expected: int | None = None) -> NDArray[np.float64]:
    """Read a ``times.txt``: one timestamp in seconds per line (``#`` comments skipped).

    Parameters
    ----------
    path : file.
    expected : number of frames the file must list, if known.

    Returns
    -------
    (N,) float64 seconds, strictly increasing.

    Raises
    ------
    DatasetError
        Missing file, a line that is not one finite number, a count that differs from
        ``expected``, or timestamps that do not increase (names the file and line).
    """
    path = Path(path)
    text = read_text(path, "timestamps", missing="timestamps file not found")
    vals: list[float] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.split()
        try:
            if len(fields) != 1:
                raise ValueError
            v = float(fields[0])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: expected one number, got {line!r}") from None
        if not np.isfinite(v):
            raise DatasetError(f"{path}:{lineno}: non-finite timestamp")
        vals.append(v)
    t = np.asarray(vals, dtype=np.float64)
    if expected is not None and len(t) != expected:
        raise DatasetError(f"{path}: lists {len(t)} timestamps but there are {expected} images")
    bad = np.nonzero(np.diff(t) <= 0)[0]
    if len(bad):
        raise DatasetError(f"{path}: timestamps must increase strictly (entry {bad[0] + 2})")
    return t


def resolve_camera(
    camera: PinholeCamera | str | Path | None,
    default_file: Path | None,
    first_image: Path | None,
    **kwargs,
) -> PinholeCamera:
    """The camera given by the caller (object or file), else read from ``default_file``.

    ``first_image`` supplies the image size for formats that lack it.
    """
    if isinstance(camera, PinholeCamera):
        return camera
    size = (lambda: image_size(first_image)) if first_image is not None else None
    if camera is not None:
        return load_camera(camera, image_size=size, **kwargs)
    if default_file is None:
        raise DatasetError("no camera given and the layout has no default camera file")
    if not default_file.is_file():
        raise DatasetError(f"{default_file}: camera file not found (pass a camera file explicitly)")
    return load_camera(default_file, image_size=size, **kwargs)


def ground_truth_at_frames(
    gt: Trajectory, frame_times: NDArray[np.float64], max_difference: float = 0.02
) -> Trajectory:
    """Ground-truth poses re-stamped at the frame times they are associated with.

    Each frame time is matched to the nearest ground-truth time within
    ``max_difference`` seconds (greedy, one-to-one, as TUM's ``associate.py``); frames
    without a match are left out.

    Returns
    -------
    Trajectory with timestamps a subset of ``frame_times``.
    """
    ia, ib = associate(frame_times, gt.timestamps, max_difference)
    if len(ia) == 0:
        return Trajectory.empty()
    return Trajectory(np.asarray(frame_times)[ia], gt.positions[ib], gt.quats_wxyz[ib])


def open_folder(
    root: str | Path,
    camera: PinholeCamera | str | Path | None = None,
    images_dir: str = "images",
) -> Sequence:
    """Open a data set in the folder layout (module docstring).

    Parameters
    ----------
    root : the data set folder.
    camera : a camera or camera file to use instead of ``root/camera.yaml``.
    images_dir : name of the image sub-folder (``"."`` for images in ``root`` itself).

    Returns
    -------
    Sequence of kind ``"folder"``; ground truth from ``groundtruth.tum`` when present,
    associated with the frame times (max difference 0.02 s).
    """
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f"{root}: data set folder not found")
    files = list_images(root / images_dir)
    cam = resolve_camera(camera, root / "camera.yaml", files[0])
    times_file = root / "times.txt"
    if times_file.is_file():
        times = read_times(times_file, expected=len(files))
    else:
        times = np.arange(len(files), dtype=np.float64)
    frames = [Frame(i, float(t), path=p) for i, (t, p) in enumerate(zip(times, files))]
    gt_file = root / "groundtruth.tum"
    loader = None
    if gt_file.is_file():
        def loader() -> Trajectory:
            return ground_truth_at_frames(read_tum(gt_file), times)
    return Sequence(root.name, root, cam, frames, "folder", loader)
