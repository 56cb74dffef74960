"""EuRoC MAV sequences (ASL format), left camera ``cam0``.

::

    <root>/mav0/cam0/data.csv      '#timestamp [ns],filename'
    <root>/mav0/cam0/data/<ns>.png
    <root>/mav0/cam0/sensor.yaml   intrinsics, radial-tangential distortion, T_BS
    <root>/mav0/state_groundtruth_estimate0/data.csv   optional: body pose per line
        '#timestamp, p_RS_R_x, p_RS_R_y, p_RS_R_z, q_RS_w, q_RS_x, q_RS_y, q_RS_z, ...'

Timestamps are nanoseconds in the files and seconds in the returned sequence. The
ground truth is the body (IMU) pose ``T_WB``; the camera pose is ``T_WC = T_WB @ T_BS``
with ``T_BS`` (camera to body) from ``sensor.yaml``. It is associated with the image
times (nearest within 0.02 s, one-to-one).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from .files import read_text
from ..errors import DatasetError
from ..geometry.rotations import quat_to_rotmat
from .cameras import read_euroc_sensor
from .folder import ground_truth_at_frames, resolve_camera
from .sequence import Frame, Sequence
from .trajectory import Trajectory

__all__ = ["open_euroc", "find_mav0", "read_euroc_csv"]


def find_mav0(root: Path) -> Path | None:
    """The ``mav0`` folder of a EuRoC sequence at ``root`` (``root`` itself or a child)."""
    for cand in (root / "mav0", root):
        if (cand / "cam0" / "data.csv").is_file():
            return cand
    return None


def read_euroc_csv(path: str | Path, min_columns: int) -> tuple[NDArray[np.int64], list[list[str]]]:
    """Read an ASL csv file: the ns timestamps (N,) int64 and the other columns as text.

    Raises
    ------
    DatasetError
        Missing file or a line with too few columns or a bad timestamp.
    """
    path = Path(path)
    text = read_text(path, "")
    stamps: list[int] = []
    rest: list[list[str]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) < min_columns:
            raise DatasetError(f"{path}:{lineno}: expected {min_columns} columns, got {len(fields)}")
        try:
            stamps.append(int(fields[0]))
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: timestamp {fields[0][:40]!r} is not integer ns") from None
        if not 0 <= stamps[-1] < 2**63:
            raise DatasetError(f"{path}:{lineno}: timestamp out of range (0 .. 2^63 ns)")
        rest.append(fields[1:])
    if not stamps:
        raise DatasetError(f"{path}: no data lines")
    return np.asarray(stamps, dtype=np.int64), rest


def _read_body_poses(path: Path, T_BS: NDArray[np.float64]) -> Trajectory:
    ns, rest = read_euroc_csv(path, 8)
    try:
        vals = np.array([[float(x) for x in r[:7]] for r in rest])
    except ValueError:
        raise DatasetError(f"{path}: non-numeric pose value") from None
    if not np.all(np.isfinite(vals)):
        raise DatasetError(f"{path}: non-finite pose value")
    T_WB = np.tile(np.eye(4), (len(ns), 1, 1))
    T_WB[:, :3, :3] = quat_to_rotmat(vals[:, 3:7]).reshape(-1, 3, 3)
    T_WB[:, :3, 3] = vals[:, :3]
    t = (ns - ns[0]).astype(np.float64) * 1e-9 + ns[0] * 1e-9
    try:
        return Trajectory.from_poses(t, T_WB @ T_BS)
    except DatasetError as exc:
        raise DatasetError(f"{path}: {exc}") from None


def open_euroc(
    root: str | Path,
    camera: PinholeCamera | str | Path | None = None,
    max_difference: float = 0.02,
) -> Sequence:
    """Open a EuRoC MAV sequence (the folder holding ``mav0`` or ``mav0`` itself).

    Parameters
    ----------
    root : sequence folder.
    camera : a camera or camera file overriding ``cam0/sensor.yaml``.
    max_difference : association window for the ground truth, seconds.

    Returns
    -------
    Sequence of kind ``"euroc"``; timestamps in seconds (ns / 1e9).
    """
    root = Path(root)
    mav0 = find_mav0(root)
    if mav0 is None:
        raise DatasetError(f"{root}: not a EuRoC sequence (no mav0/cam0/data.csv)")
    cam_dir = mav0 / "cam0"
    ns, rest = read_euroc_csv(cam_dir / "data.csv", 2)
    files = [cam_dir / "data" / r[0] for r in rest]
    sensor_cam, T_BS = read_euroc_sensor(cam_dir / "sensor.yaml")
    cam = sensor_cam if camera is None else resolve_camera(camera, None, files[0])
    times = (ns - ns[0]).astype(np.float64) * 1e-9 + ns[0] * 1e-9
    frames = [Frame(i, float(t), path=p) for i, (t, p) in enumerate(zip(times, files))]
    gt_file = mav0 / "state_groundtruth_estimate0" / "data.csv"
    loader = None
    if gt_file.is_file():
        def loader() -> Trajectory:
            return ground_truth_at_frames(_read_body_poses(gt_file, T_BS), times, max_difference)
    name = root.name if root != mav0 else mav0.parent.name
    return Sequence(name, root, cam, frames, "euroc", loader)
