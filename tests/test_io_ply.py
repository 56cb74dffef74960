"""PLY point clouds: round trips and header layout."""

from __future__ import annotations

import numpy as np
import pytest

from eifslam.errors import DatasetError
from eifslam.io.ply import read_ply, write_ply


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("with_colors", [True, False])
def test_round_trip(tmp_path, binary, with_colors):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3)) * 10
    cols = rng.integers(0, 256, size=(50, 3), dtype=np.uint8) if with_colors else None
    f = tmp_path / "cloud.ply"
    write_ply(f, pts, cols, binary=binary)
    back, bcols = read_ply(f)
    np.testing.assert_allclose(back, pts, rtol=1e-6, atol=1e-5)  # float32 storage
    if with_colors:
        np.testing.assert_array_equal(bcols, cols)
    else:
        assert bcols is None


def test_header_is_standard(tmp_path):
    f = tmp_path / "c.ply"
    write_ply(f, np.zeros((2, 3)), np.zeros((2, 3), np.uint8), binary=True)
    raw = f.read_bytes()
    header = raw[: raw.index(b"end_header")].decode().splitlines()
    assert header[0] == "ply"
    assert header[1] == "format binary_little_endian 1.0"
    assert "element vertex 2" in header
    assert header[-3:] == ["property uchar red", "property uchar green", "property uchar blue"]
    assert len(raw) - raw.index(b"end_header\n") - len(b"end_header\n") == 2 * (12 + 3)


def test_double_and_empty(tmp_path):
    f = tmp_path / "d.ply"
    pts = np.array([[1.0 + 1e-12, 2.0, 3.0]])
    write_ply(f, pts, double=True)
    np.testing.assert_array_equal(read_ply(f)[0], pts)
    write_ply(f, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), binary=False)
    back, cols = read_ply(f)
    assert back.shape == (0, 3) and cols.shape == (0, 3)


def test_bad_input(tmp_path):
    with pytest.raises(DatasetError, match="shape"):
        write_ply(tmp_path / "x.ply", np.zeros((3, 2)))
    with pytest.raises(DatasetError, match="NaN"):
        write_ply(tmp_path / "x.ply", np.full((1, 3), np.nan))
    with pytest.raises(DatasetError, match="colors"):
        write_ply(tmp_path / "x.ply", np.zeros((2, 3)), np.zeros((3, 3), np.uint8))
    (tmp_path / "bad.ply").write_text("hello\n")
    with pytest.raises(DatasetError, match="bad.ply"):
        read_ply(tmp_path / "bad.ply")


def test_broken_files_are_one_line_errors_naming_the_file(tmp_path):
    good = tmp_path / "good.ply"
    write_ply(good, np.ones((20, 3)), np.zeros((20, 3), np.uint8))
    raw = good.read_bytes()
    head = raw[: raw.index(b"end_header")]
    cases = {
        "truncated.ply": raw[: len(raw) - 7],
        "huge.ply": head.replace(b"element vertex 20", b"element vertex 99999999999") + b"end_header\n" + b"\0" * 30,
        "garbage.ply": b"ply\nformat nonsense 1.0\nend_header\n",
        "noxyz.ply": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n",
        "list.ply": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\nproperty float y\n"
                    b"property float z\nend_header\n2 1 1 1 1\n",
        "nan.ply": b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                   b"property float z\nend_header\nnan 1 1\n",
    }
    for name, data in cases.items():
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(DatasetError) as err:
            read_ply(p)
        assert name in str(err.value) and "\n" not in str(err.value), name


def test_plyfile_reads_what_we_write(tmp_path):
    from plyfile import PlyData

    f = tmp_path / "m.ply"
    pts = np.arange(12, dtype=float).reshape(4, 3)
    write_ply(f, pts, np.full((4, 3), 7, np.uint8))
    v = PlyData.read(str(f))["vertex"]
    np.testing.assert_array_equal(np.c_[v["x"], v["y"], v["z"]], pts)
    assert v["red"].tolist() == [7] * 4
