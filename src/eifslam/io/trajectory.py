"""Camera trajectories and the TUM trajectory format (pure NumPy, no OpenCV).

A TUM trajectory file has one pose per line, ``timestamp tx ty tz qx qy qz qw``: the
camera-to-world pose (position of the camera centre in the world, orientation ``R_wc``)
with the quaternion **scalar last**. Inside eifslam quaternions are scalar first
(``[w, x, y, z]``, see :mod:`eifslam.geometry`); the conversion happens only here.
Lines starting with ``#`` and blank lines are skipped. This is the format ``evo`` reads;
:func:`write_tum` writes through evo's ``file_interface``.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
from numpy.typing import NDArray

from .files import atomic_path, read_text
from ..errors import DatasetError, OutputError
from ..geometry.rotations import quat_normalize, quat_to_rotmat, quat_wxyz_to_xyzw, quat_xyzw_to_wxyz

Array = NDArray[np.float64]

__all__ = ["Trajectory", "TumAppender", "read_tum", "write_tum", "parse_tum", "associate"]


@dataclass(frozen=True)
class Trajectory:
    """A timed sequence of camera-to-world poses.

    Attributes
    ----------
    timestamps : (N,) float64
        Seconds, strictly increasing.
    positions : (N, 3) float64
        Camera centres in the world frame (the data set's units).
    quats_wxyz : (N, 4) float64
        Unit quaternions ``[w, x, y, z]`` of ``R_wc`` (camera-to-world orientation).
    """

    timestamps: Array
    positions: Array
    quats_wxyz: Array

    def __post_init__(self) -> None:
        t = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        p = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(self.quats_wxyz, dtype=np.float64).reshape(-1, 4)
        if not (len(t) == len(p) == len(q)):
            raise DatasetError(
                f"trajectory arrays differ in length: {len(t)} timestamps, "
                f"{len(p)} positions, {len(q)} quaternions"
            )
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            raise DatasetError("trajectory contains NaN or infinite values")
        if len(t) > 1 and np.any(np.diff(t) <= 0):
            raise DatasetError("trajectory timestamps are not strictly increasing")
        norms = np.linalg.norm(q, axis=1)
        if np.any(norms < 1e-6):
            raise DatasetError("trajectory contains a zero quaternion")
        object.__setattr__(self, "timestamps", t)
        object.__setattr__(self, "positions", p)
        object.__setattr__(self, "quats_wxyz", quat_normalize(q))

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def rotations(self) -> Array:
        """(N, 3, 3) camera-to-world rotation matrices ``R_wc``."""
        return quat_to_rotmat(self.quats_wxyz).reshape(-1, 3, 3)

    @property
    def poses(self) -> Array:
        """(N, 4, 4) homogeneous camera-to-world transforms ``T_wc``."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = self.rotations
        T[:, :3, 3] = self.positions
        return T

    @property
    def path_length(self) -> float:
        """Sum of distances between consecutive camera centres (world units)."""
        if len(self) < 2:
            return 0.0
        return float(np.sum(np.linalg.norm(np.diff(self.positions, axis=0), axis=1)))

    def subset(self, indices: NDArray[np.intp]) -> "Trajectory":
        """The poses at ``indices`` (increasing), as a new trajectory."""
        idx = np.asarray(indices, dtype=np.intp)
        return Trajectory(self.timestamps[idx], self.positions[idx], self.quats_wxyz[idx])

    @classmethod
    def from_poses(cls, timestamps: Array, T_wc: Array) -> "Trajectory":
        """Build from ``(N,)`` timestamps and ``(N, 4, 4)`` or ``(N, 3, 4)`` camera-to-world poses."""
        from ..geometry.rotations import rotmat_to_quat

        T = np.asarray(T_wc, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] not in ((4, 4), (3, 4)):
            raise DatasetError(f"poses must have shape (N, 4, 4) or (N, 3, 4), got {T.shape}")
        if len(T) == 0:
            return cls.empty()
        return cls(np.asarray(timestamps, dtype=np.float64), T[:, :3, 3], rotmat_to_quat(T[:, :3, :3]))

    @classmethod
    def empty(cls) -> "Trajectory":
        """A trajectory with no poses (arrays of shape ``(0,)``, ``(0, 3)``, ``(0, 4)``)."""
        return cls(np.zeros(0), np.zeros((0, 3)), np.zeros((0, 4)))


def parse_tum(stream: TextIO, name: str = "<stream>") -> Trajectory:
    """Parse TUM trajectory text.

    Parameters
    ----------
    stream : text stream
        Lines ``timestamp tx ty tz qx qy qz qw`` (spaces or commas); ``#`` comments skipped.
    name : str
        File name used in error messages.

    Returns
    -------
    Trajectory

    Raises
    ------
    DatasetError
        A line without 8 numeric columns, a non-finite value, a zero quaternion or
        timestamps that do not increase; the message names the file and line.
    """
    rows: list[list[float]] = []
    for lineno, raw in enumerate(stream, start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        fields = line.replace(",", " ").split()
        if len(fields) != 8:
            raise DatasetError(
                f"{name}:{lineno}: expected 8 columns 'timestamp tx ty tz qx qy qz qw', "
                f"got {len(fields)}"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise DatasetError(f"{name}:{lineno}: non-numeric value in {line!r}") from None
        if not all(np.isfinite(values)):
            raise DatasetError(f"{name}:{lineno}: non-finite value in {line!r}")
        if np.linalg.norm(values[4:]) < 1e-6:
            raise DatasetError(f"{name}:{lineno}: zero quaternion")
        rows.append(values)
    if not rows:
        return Trajectory.empty()
    data = np.asarray(rows, dtype=np.float64)
    bad = np.nonzero(np.diff(data[:, 0]) <= 0)[0]
    if len(bad):
        raise DatasetError(
            f"{name}: timestamps must increase strictly (pose {bad[0] + 1} at "
            f"t={data[bad[0] + 1, 0]!r} follows t={data[bad[0], 0]!r})"
        )
    return Trajectory(data[:, 0], data[:, 1:4], quat_xyzw_to_wxyz(data[:, 4:8]))


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file (see :func:`parse_tum`).

    Raises
    ------
    DatasetError
        The file is missing, unreadable or malformed (message names the file).
    """
    path = Path(path)
    text = read_text(path, "trajectory file")
    return parse_tum(io.StringIO(text), name=str(path))


def write_tum(
    path: str | Path,
    timestamps: Array,
    positions: Array,
    quats_wxyz: Array,
    header: str | None = "timestamp tx ty tz qx qy qz qw  (camera-to-world)",
) -> None:
    """Write camera-to-world poses as a TUM trajectory file (atomically: a temporary file
    in the same folder renamed over ``path``, so a reader never sees half a file).

    Parameters
    ----------
    path : path of the file to (over)write.
    timestamps : (N,) seconds, strictly increasing.
    positions : (N, 3) camera centres in the world frame.
    quats_wxyz : (N, 4) orientations ``R_wc`` as ``[w, x, y, z]``; written as ``qx qy qz qw``.
    header : comment written as the first line (``None`` for none).

    The poses are written by evo (``file_interface.write_tum_trajectory_file``, full
    precision), the tool the files are meant for. Reading stays here: evo's reader checks
    the width of the first row only, refuses an empty file and names no line, where
    :func:`parse_tum` names the file and line of every problem.

    Raises
    ------
    DatasetError
        Arrays of mismatched shapes, non-finite values or non-increasing timestamps.
    """
    traj = Trajectory(timestamps, positions, quats_wxyz)
    with atomic_path(path) as tmp:  # a kill never leaves half a file
        with open(tmp, "w") as fh:
            if header is not None:
                fh.write(f"# {header}\n")
            if len(traj):
                from evo.core.trajectory import PoseTrajectory3D
                from evo.tools import file_interface

                file_interface.write_tum_trajectory_file(fh, PoseTrajectory3D(
                    positions_xyz=traj.positions, orientations_quat_wxyz=traj.quats_wxyz,
                    timestamps=traj.timestamps))

class TumAppender:
    """A TUM file written one pose at a time, each line flushed to the operating system.

    The trajectory of a run as it is tracked: a run killed by ``SIGKILL`` or a crash
    keeps every pose appended before (``flush`` hands the line to the kernel, which
    writes it even if the process dies; only a machine crash can lose the last lines).
    Non-finite poses and timestamps that do not increase are skipped, so the file always
    parses with :func:`read_tum`.

    Parameters
    ----------
    path : file to create (truncated if it exists).

    Raises
    ------
    OutputError
        The file cannot be created or written (names it).
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._last_t = -np.inf
        try:
            self._fh: TextIO | None = open(self.path, "w", encoding="ascii")
            self._fh.write("# timestamp tx ty tz qx qy qz qw  (camera-to-world, as tracked)\n")
            self._fh.flush()
        except OSError as exc:
            raise OutputError(f"{self.path}: cannot write ({exc.strerror or exc})") from None

    def append(self, timestamp: float, position: Array, quat_wxyz: Array) -> bool:
        """Append one pose (``position`` (3,) world frame, ``quat_wxyz`` (4,) of ``R_wc``);
        False when it was skipped (non-finite, zero quaternion, time not increasing)."""
        p = np.asarray(position, np.float64).reshape(3)
        q = np.asarray(quat_wxyz, np.float64).reshape(4)
        if (self._fh is None or not np.isfinite(timestamp) or timestamp <= self._last_t
                or not np.all(np.isfinite(p)) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-6):
            return False
        q = quat_wxyz_to_xyzw(q / np.linalg.norm(q))
        try:
            self._fh.write(f"{timestamp:.9f} " + " ".join(f"{v:.9f}" for v in (*p, *q)) + "\n")
            self._fh.flush()
        except OSError as exc:
            raise OutputError(f"{self.path}: cannot write ({exc.strerror or exc})") from None
        self._last_t = float(timestamp)
        return True

    def close(self) -> None:
        """Close the file (it stays on disk)."""
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def associate(
    first: Array, second: Array, max_difference: float = 0.02, offset: float = 0.0
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Match two lists of timestamps as the TUM RGB-D tools' ``associate.py`` does.

    Greedy on the time difference: candidate pairs with ``|a - (b + offset)| <
    max_difference`` are taken in increasing order of difference, each timestamp used once.

    Parameters
    ----------
    first, second : (N,), (M,) timestamps in seconds.
    max_difference : largest accepted difference in seconds.
    offset : time offset added to ``second``.

    Returns
    -------
    (K,) indices into ``first`` (increasing) and the matching (K,) indices into ``second``.
    """
    a = np.asarray(first, dtype=np.float64).reshape(-1)
    b = np.asarray(second, dtype=np.float64).reshape(-1) + offset
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    order = np.argsort(b)
    bs = b[order]
    cand: list[tuple[float, int, int]] = []
    # only neighbours inside the window can match: scan a window around each insertion point
    lo = np.searchsorted(bs, a - max_difference, side="left")
    hi = np.searchsorted(bs, a + max_difference, side="right")
    for i in range(len(a)):
        for k in range(lo[i], hi[i]):
            d = abs(a[i] - bs[k])
            if d < max_difference:
                cand.append((d, i, int(order[k])))
    cand.sort()
    used_a: set[int] = set()
    used_b: set[int] = set()
    pairs: list[tuple[int, int]] = []
    for _, i, j in cand:
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        pairs.append((i, j))
    pairs.sort()
    if not pairs:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    ia, ib = zip(*pairs)
    return np.asarray(ia, np.intp), np.asarray(ib, np.intp)
