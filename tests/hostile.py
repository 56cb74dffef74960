"""Builders of the hostile-input corpus of tests/test_hostile_inputs.py: small data sets in
the folder, TUM RGB-D, EuRoC and KITTI layouts (rendered from the built-in scene), files
that lie about their size, and the check every case ends with."""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from eifslam.geometry.rotations import quat_wxyz_to_xyzw

#: the checkout's src/, for subprocesses (CI's editable install and a worktree alike)
SRC = Path(__file__).resolve().parents[1] / "src"
W, H = 320, 240


def subprocess_env() -> dict[str, str]:
    """The environment of a ``python -m eifslam.cli.main`` subprocess of this checkout."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(SRC) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def assert_clean(rc: int, err: str, names: str | None = None) -> None:
    """Every hostile case ends with exit 0, or exit 1 and one line ``eifslam: error: ...``
    naming ``names`` (a file or option); never a traceback."""
    assert "Traceback" not in err, err
    assert rc in (0, 1), (rc, err)
    errors = [ln for ln in err.splitlines() if "error" in ln.lower() and "eifslam" in ln]
    if rc == 1:
        assert len(errors) == 1 and errors[0].startswith("eifslam: error: "), err
        if names is not None:
            assert names in errors[0], (names, errors[0])


class Scene:
    """The first ``n`` images of the built-in scene at 320x240, their times and poses."""

    def __init__(self, n: int) -> None:
        from eifslam.sim.scene import make_scene, render_frame

        s = make_scene(n_frames=54, width=W, height=H)
        self.camera = s.camera
        self.images = [render_frame(s, k) for k in range(n)]
        self.times = np.asarray(s.timestamps[:n], float)
        self.positions = np.asarray(s.positions[:n], float)
        self.quats = np.asarray(s.quats_wxyz[:n], float)

    def camera_yaml(self) -> str:
        c = self.camera
        return (f"model: pinhole\nwidth: {c.width}\nheight: {c.height}\nfx: {c.fx}\nfy: {c.fy}\n"
                f"cx: {c.cx}\ncy: {c.cy}\ndistortion: [0, 0, 0, 0, 0]\n")

    def tum_lines(self) -> str:
        q = quat_wxyz_to_xyzw(self.quats)
        return "".join(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*p, *qq)) + "\n"
                       for t, p, qq in zip(self.times, self.positions, q))

    def folder(self, root: Path, order: list[int] | None = None, gt: str | None = None) -> Path:
        """Folder layout; ``order`` picks images (repeats allowed) at times 0.1 s apart."""
        order = list(range(len(self.images))) if order is None else order
        (root / "images").mkdir(parents=True)
        for j, k in enumerate(order):
            assert cv2.imwrite(str(root / "images" / f"{j:06d}.png"), self.images[k])
        (root / "camera.yaml").write_text(self.camera_yaml())
        (root / "times.txt").write_text("".join(f"{0.1 * j:.3f}\n" for j in range(len(order))))
        if gt is not None:
            (root / "groundtruth.tum").write_text(gt)
        return root

    def tum(self, root: Path, gt: str) -> Path:
        (root / "rgb").mkdir(parents=True)
        lines = []
        for t, im in zip(self.times, self.images):
            cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), im)
            lines.append(f"{t:.6f} rgb/{t:.6f}.png\n")
        (root / "rgb.txt").write_text("# timestamp filename\n" + "".join(lines))
        (root / "camera.yaml").write_text(self.camera_yaml())
        (root / "groundtruth.txt").write_text(gt)
        return root

    def euroc(self, root: Path, gt: str) -> Path:
        cam = root / "mav0" / "cam0"
        (cam / "data").mkdir(parents=True)
        lines = []
        for t, im in zip(self.times, self.images):
            ns = int(round((100.0 + t) * 1e9))
            cv2.imwrite(str(cam / "data" / f"{ns}.png"), im)
            lines.append(f"{ns},{ns}.png\n")
        (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(lines))
        c = self.camera
        (cam / "sensor.yaml").write_text(
            f"camera_model: pinhole\nintrinsics: [{c.fx}, {c.fy}, {c.cx}, {c.cy}]\n"
            f"resolution: [{c.width}, {c.height}]\ndistortion_model: radial-tangential\n"
            "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n"
            "T_BS:\n  cols: 4\n  rows: 4\n  data: [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]\n")
        (root / "mav0" / "state_groundtruth_estimate0").mkdir()
        (root / "mav0" / "state_groundtruth_estimate0" / "data.csv").write_text(gt)
        return root

    def video(self, root: Path, gt: str) -> Path:
        """``root/clip.avi`` (MJPG: every frame a key frame) with ``clip.yaml`` and ``clip.tum``."""
        root.mkdir(parents=True)
        w = cv2.VideoWriter(str(root / "clip.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, (W, H))
        for im in self.images:
            w.write(im)
        w.release()
        (root / "clip.yaml").write_text(self.camera_yaml())
        (root / "clip.tum").write_text(gt)
        return root / "clip.avi"

    def kitti(self, root: Path, poses: str) -> Path:
        (root / "image_0").mkdir(parents=True)
        for k, im in enumerate(self.images):
            cv2.imwrite(str(root / "image_0" / f"{k:06d}.png"), cv2.cvtColor(im, cv2.COLOR_BGR2GRAY))
        c = self.camera
        (root / "calib.txt").write_text(f"P0: {c.fx} 0 {c.cx} 0 0 {c.fy} {c.cy} 0 0 0 1 0\n")
        (root / "times.txt").write_text("".join(f"{t:.6f}\n" for t in self.times))
        (root / "poses.txt").write_text(poses)
        return root


def png_claiming(width: int, height: int) -> bytes:
    """A small PNG file whose header claims ``width`` x ``height`` grey pixels (its data
    is a few bytes of a zlib stream: decoding it would allocate the claimed size first)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64))
            + chunk(b"IEND", b""))


def poses_in(path: Path) -> int:
    """Poses in a TUM file (0 when it does not exist)."""
    if not path.is_file():
        return 0
    return sum(1 for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#"))
