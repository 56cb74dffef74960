"""A corpus of hostile inputs (issue 16), generated in tmp_path: every case ends with exit
0, or exit 1 and one line ``eifslam: error: ...`` naming the file or option; never a
traceback, a hang or lost estimates. Session files are covered by the session tests."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from eifslam.cli.main import main as cli_main
from eifslam.errors import OutputError
from eifslam.io import open_source, read_tum
from eifslam.io.files import atomic_path, atomic_write
from eifslam.io.trajectory import TumAppender

from hostile import Scene, assert_clean, png_claiming, poses_in, subprocess_env

IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(8)


@pytest.fixture
def data(scene, tmp_path) -> Path:
    """A good 4-image folder data set."""
    return scene.folder(tmp_path / "data", order=[0, 1, 2, 3])


def cli(capsys, *argv: str) -> tuple[int, str]:
    rc = cli_main([str(a) for a in argv])
    return rc, capsys.readouterr().err


# -- atomic and incremental writing -----------------------------------------------------------

def test_atomic_write_leaves_the_old_file_when_interrupted(tmp_path):
    target = tmp_path / "report.json"
    atomic_write(target, '{"old": 1}')
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text('{"new": ')
            raise KeyboardInterrupt
    assert target.read_text() == '{"old": 1}' and sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]
    with pytest.raises(OutputError, match="nowhere"):
        atomic_write(tmp_path / "nowhere" / "x", "data")


def test_tum_appender_skips_what_the_format_cannot_hold(tmp_path):
    log = TumAppender(tmp_path / "t.tum")
    q = np.array([1.0, 0, 0, 0])
    assert log.append(0.0, np.zeros(3), q) and log.append(1.0, np.ones(3), 2 * q)
    assert not log.append(1.0, np.ones(3), q)  # time not increasing
    assert not log.append(2.0, np.array([math.nan, 0, 0]), q)
    assert not log.append(3.0, np.zeros(3), np.zeros(4))
    log.close()
    traj = read_tum(tmp_path / "t.tum")
    assert list(traj.timestamps) == [0.0, 1.0] and np.allclose(traj.quats_wxyz[1], q)


