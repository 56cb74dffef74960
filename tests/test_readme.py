"""The README's Python example runs as written."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def _python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(encoding="utf-8"), flags=re.S)


def test_the_readme_example_runs_as_written(tmp_path, monkeypatch, capsys):
    blocks = [b for b in _python_blocks() if "from eifslam import" in b]
    assert len(blocks) == 1, "the README has one Python example using the package"
    code = blocks[0]
    assert 'DATA = "out/scene"' in code
    monkeypatch.chdir(tmp_path)
    # the data folder the example names: the first 5 of the built-in scene's 54 views, small
    import cv2
    from eifslam.sim.scene import make_scene, render_frame

    scene = make_scene(n_frames=54, width=320, height=240)
    d = tmp_path / "out" / "scene"
    (d / "images").mkdir(parents=True)
    for k in range(5):
        cv2.imwrite(str(d / "images" / f"{k:06d}.png"), render_frame(scene, k))
    c = scene.camera
    (d / "camera.yaml").write_text(
        f"model: pinhole\nwidth: {c.width}\nheight: {c.height}\nfx: {c.fx}\nfy: {c.fy}\ncx: {c.cx}\ncy: {c.cy}\n")
    ns: dict = {}
    exec(compile(code, str(README), "exec"), ns)  # the block, unchanged
    printed = capsys.readouterr().out.strip().splitlines()
    assert len(printed) == 5 and printed[0].startswith("0 initialising")
    assert sum(line.split()[1] == "tracking" for line in printed) >= 3
    P, T = ns["P"], ns["T_wc"]
    assert T.shape == (4, 4) and np.allclose(T[3], [0, 0, 0, 1])
    np.testing.assert_allclose(T[:3, 3], P[1], atol=1e-12)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
    assert len(ns["ids"]) > 20 and ns["colours"].dtype == np.uint8
    assert (tmp_path / "session.npz").is_file()
    # the last result's 4x4 agrees with its position and quaternion
    from eifslam.geometry.rotations import quat_to_rotmat

    r = ns["r"]
    np.testing.assert_allclose(r.T_wc[:3, :3], quat_to_rotmat(r.quat_wxyz))
    np.testing.assert_allclose(r.T_wc[:3, 3], r.position)


def test_import_eifslam_gives_the_entry_points_without_opencv():
    import subprocess
    import sys

    code = ("import sys, eifslam; assert 'cv2' not in sys.modules, 'cv2 imported'; "
            "from eifslam import Slam, SlamConfig, load_camera, open_source; "
            "assert Slam.__name__ == 'Slam' and callable(load_camera) and callable(open_source); "
            "assert SlamConfig().smoothing.mode == 'smooth'")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-500:]
