"""TUM trajectory files and timestamp association."""

from __future__ import annotations

import io

import numpy as np
import pytest

from eifslam.errors import DatasetError
from eifslam.geometry.rotations import quat_normalize, rotmat_to_quat
from eifslam.io.trajectory import Trajectory, associate, parse_tum, read_tum, write_tum


def _random_traj(rng: np.random.Generator, n: int = 10) -> Trajectory:
    t = np.cumsum(rng.uniform(0.01, 0.1, n)) + 1.3e9
    p = rng.normal(size=(n, 3))
    q = quat_normalize(rng.normal(size=(n, 4)))
    return Trajectory(t, p, q)


def test_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    tr = _random_traj(rng)
    f = tmp_path / "traj.tum"
    write_tum(f, tr.timestamps, tr.positions, tr.quats_wxyz)
    back = read_tum(f)
    assert len(back) == len(tr)
    np.testing.assert_allclose(back.timestamps, tr.timestamps, atol=1e-6)
    np.testing.assert_allclose(back.positions, tr.positions, atol=1e-8)
    np.testing.assert_allclose(back.quats_wxyz, tr.quats_wxyz, atol=1e-8)


def test_column_order_is_xyzw():
    tr = parse_tum(io.StringIO("# comment\n\n0.0 1 2 3 0 0 0 1\n1.0 1 2 3 1 0 0 0\n"))
    np.testing.assert_allclose(tr.quats_wxyz, [[1, 0, 0, 0], [0, 1, 0, 0]])
    np.testing.assert_allclose(tr.positions[0], [1, 2, 3])
    np.testing.assert_allclose(tr.poses[1][:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)


def test_from_poses_matches_quaternions():
    rng = np.random.default_rng(1)
    tr = _random_traj(rng, 5)
    back = Trajectory.from_poses(tr.timestamps, tr.poses)
    np.testing.assert_allclose(back.quats_wxyz, tr.quats_wxyz, atol=1e-12)
    np.testing.assert_allclose(rotmat_to_quat(tr.rotations), tr.quats_wxyz, atol=1e-12)


def test_empty_file_keeps_shapes():
    tr = parse_tum(io.StringIO("# nothing\n"))
    assert tr.positions.shape == (0, 3) and tr.quats_wxyz.shape == (0, 4)


@pytest.mark.parametrize(
    "text, words",
    [
        ("0 1 2 3 0 0 0\n", "8 columns"),
        ("0 1 2 3 0 0 0 1 5\n", "8 columns"),
        ("0 1 2 x 0 0 0 1\n", "non-numeric"),
        ("0 1 2 nan 0 0 0 1\n", "non-finite"),
        ("0 1 2 3 0 0 0 0\n", "zero quaternion"),
        ("1 1 2 3 0 0 0 1\n0.5 1 2 3 0 0 0 1\n", "increase"),
    ],
)
def test_malformed_lines(text, words):
    with pytest.raises(DatasetError, match=words) as exc:
        parse_tum(io.StringIO(text), name="bad.tum")
    assert "bad.tum" in str(exc.value)


def test_read_missing_names_file(tmp_path):
    with pytest.raises(DatasetError, match="nope.tum"):
        read_tum(tmp_path / "nope.tum")


def test_write_rejects_bad_arrays(tmp_path):
    with pytest.raises(DatasetError):
        write_tum(tmp_path / "a.tum", [0.0, 1.0], np.zeros((3, 3)), np.tile([1.0, 0, 0, 0], (2, 1)))
    with pytest.raises(DatasetError):
        write_tum(tmp_path / "a.tum", [0.0, 1.0], np.full((2, 3), np.inf), np.tile([1.0, 0, 0, 0], (2, 1)))


def test_associate_like_tum_tools():
    a = np.array([0.0, 0.1, 0.2, 0.3, 5.0])
    b = np.array([0.005, 0.012, 0.098, 0.25, 0.31])
    ia, ib = associate(a, b, max_difference=0.02)
    # 0.0 takes 0.005 (not 0.012); 0.2 has nothing within 0.02; 0.3 takes 0.31
    assert ia.tolist() == [0, 1, 3]
    assert ib.tolist() == [0, 2, 4]
    ia, ib = associate(a, b - 1.0, max_difference=0.02, offset=1.0)
    assert ia.tolist() == [0, 1, 3]
    e0, e1 = associate(np.zeros(0), b)
    assert e0.shape == (0,) and e1.shape == (0,)
