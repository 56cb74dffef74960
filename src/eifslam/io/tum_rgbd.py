"""TUM RGB-D sequences (only the colour images are used).

::

    <root>/rgb.txt          '# timestamp filename' lines, e.g. '1305031102.175304 rgb/...png'
    <root>/rgb/...png
    <root>/groundtruth.txt  optional: TUM trajectory (optical centre of the colour camera,
                            camera-to-world), at ~100 Hz
    <root>/camera.yaml      optional: intrinsics; else the published calibration of the
                            freiburg1/2/3 sensor named in the folder name

Ground truth is associated with the image times as the TUM tools do (``associate.py``:
nearest, one-to-one, within 0.02 s).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry.camera import PinholeCamera
from .files import read_text
from ..errors import DatasetError
from .folder import ground_truth_at_frames, resolve_camera
from .sequence import Frame, Sequence
from .trajectory import Trajectory, read_tum

__all__ = ["open_tum_rgbd", "read_file_list", "TUM_CAMERAS"]

#: published colour-camera calibrations of the TUM RGB-D sensors (640x480)
TUM_CAMERAS = {
    "freiburg1": PinholeCamera(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": PinholeCamera(520.9, 521.0, 325.1, 249.7, 640, 480, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": PinholeCamera(535.4, 539.2, 320.1, 247.6, 640, 480, (0.0, 0.0, 0.0, 0.0, 0.0)),
}


def read_file_list(path: str | Path) -> list[tuple[float, str]]:
    """Read a TUM ``rgb.txt``-style list: ``timestamp filename`` per line.

    Raises
    ------
    DatasetError
        Missing file or a malformed line (names the file and line).
    """
    path = Path(path)
    text = read_text(path, "file list")
    out: list[tuple[float, str]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) < 2:
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp filename', got {line!r}")
        try:
            t = float(fields[0])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: non-numeric timestamp {fields[0]!r}") from None
        if not np.isfinite(t):
            raise DatasetError(f"{path}:{lineno}: non-finite timestamp")
        out.append((t, fields[1]))
    if not out:
        raise DatasetError(f"{path}: lists no images")
    return out


def _default_camera(root: Path) -> PinholeCamera | None:
    for key, cam in TUM_CAMERAS.items():
        if key in root.resolve().name:
            return cam
    return None


def open_tum_rgbd(
    root: str | Path,
    camera: PinholeCamera | str | Path | None = None,
    max_difference: float = 0.02,
) -> Sequence:
    """Open a TUM RGB-D sequence folder (module docstring).

    Parameters
    ----------
    root : folder holding ``rgb.txt``.
    camera : a camera or camera file; default ``root/camera.yaml``, else the published
        calibration of the sensor named in the folder name (``freiburg1`` ...).
    max_difference : association window for the ground truth, seconds.

    Returns
    -------
    Sequence of kind ``"tum"``.
    """
    root = Path(root)
    entries = read_file_list(root / "rgb.txt")
    files = [root / name for _, name in entries]
    times = np.array([t for t, _ in entries])
    if camera is None and not (root / "camera.yaml").is_file():
        camera = _default_camera(root)
        if camera is None:
            raise DatasetError(
                f"{root}: no camera.yaml and the folder name names no TUM sensor "
                "(freiburg1/2/3); pass a camera file"
            )
    cam = resolve_camera(camera, root / "camera.yaml", files[0])
    frames = [Frame(i, float(t), path=p) for i, (t, p) in enumerate(zip(times, files))]
    gt_file = root / "groundtruth.txt"
    loader = None
    if gt_file.is_file():
        def loader() -> Trajectory:
            return ground_truth_at_frames(read_tum(gt_file), times, max_difference)
    return Sequence(root.name, root, cam, frames, "tum", loader)
