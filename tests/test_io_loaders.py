"""Loaders on small synthetic layouts (good and broken) built in tmp_path."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from eifslam.geometry.camera import PinholeCamera
from eifslam.errors import CalibrationError, DatasetError, ImageError
from eifslam.geometry.rotations import quat_normalize, quat_to_rotmat, quat_wxyz_to_xyzw
from eifslam.io import open_source
from eifslam.io.cameras import write_camera_yaml
from eifslam.io.detect import detect_layout
from eifslam.io.trajectory import write_tum

W, H = 32, 24
CAM = PinholeCamera(30.0, 31.0, 15.5, 11.5, W, H)


def _images(folder: Path, n: int, names: list[str] | None = None, gray: bool = False) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    names = names or [f"{k:06d}.png" for k in range(n)]
    out = []
    for k, name in enumerate(names):
        img = np.full((H, W) if gray else (H, W, 3), 10 * k, np.uint8)
        img[0, 0] = 255
        assert cv2.imwrite(str(folder / name), img)
        out.append(folder / name)
    return out


def _poses(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    p = np.cumsum(rng.normal(size=(n, 3)), axis=0)
    q = quat_normalize(rng.normal(size=(n, 4)))
    return p, q


def _tum_lines(t, p, q) -> str:
    return "".join(
        f"{tt:.6f} {' '.join(map(str, pp))} {' '.join(map(str, quat_wxyz_to_xyzw(qq)))}\n"
        for tt, pp, qq in zip(t, p, q)
    )


def make_folder(root: Path, n: int = 4, times: bool = True, gt: bool = True) -> Path:
    _images(root / "images", n)
    write_camera_yaml(root / "camera.yaml", CAM)
    t = 0.1 * np.arange(n) + 5.0
    if times:
        (root / "times.txt").write_text("".join(f"{x:.6f}\n" for x in t))
    if gt:
        p, q = _poses(np.random.default_rng(0), n)
        write_tum(root / "groundtruth.tum", t if times else np.arange(n, dtype=float), p, q)
    return root


# --------------------------------------------------------------------------- folder


def test_folder_layout(tmp_path):
    seq = open_source(make_folder(tmp_path / "ds"))
    assert seq.kind == "folder" and len(seq) == 4 and seq.camera == CAM
    np.testing.assert_allclose(seq.timestamps, [5.0, 5.1, 5.2, 5.3])
    assert seq[2].path.name == "000002.png" and seq[2].index == 2
    img = seq.load(1)
    assert img.shape == (H, W, 3) and img.dtype == np.uint8 and img[5, 5, 0] == 10
    assert seq.load(1, grayscale=True).shape == (H, W)
    gt = seq.ground_truth()
    assert len(gt) == 4 and gt.positions.shape == (4, 3)
    np.testing.assert_allclose(gt.timestamps, seq.timestamps)
    assert [f.index for f, _ in seq.images()] == [0, 1, 2, 3]


def test_folder_without_times_and_gt(tmp_path):
    seq = open_source(make_folder(tmp_path / "ds", times=False, gt=False))
    np.testing.assert_array_equal(seq.timestamps, [0.0, 1.0, 2.0, 3.0])
    assert seq.ground_truth() is None and not seq.has_ground_truth


def test_folder_camera_override(tmp_path):
    root = make_folder(tmp_path / "ds")
    (root / "camera.yaml").unlink()
    with pytest.raises(DatasetError, match="camera"):
        open_source(root)
    other = PinholeCamera(40.0, 40.0, 16.0, 12.0, W, H)
    assert open_source(root, camera=other).camera == other
    write_camera_yaml(tmp_path / "cam.yaml", other)
    assert open_source(root, camera=tmp_path / "cam.yaml").camera == other


def test_folder_broken_files(tmp_path):
    root = make_folder(tmp_path / "ds")
    (root / "images" / "000002.png").write_bytes(b"not a png")
    seq = open_source(root)
    with pytest.raises(ImageError, match="000002.png"):
        seq.load(2)
    cv2.imwrite(str(root / "images" / "000003.png"), np.zeros((10, 10), np.uint8))
    with pytest.raises(ImageError, match="000003.png.*10x10"):
        seq.load(3)
    (root / "groundtruth.tum").write_text("0 1 2 3\n")
    with pytest.raises(DatasetError, match="groundtruth.tum"):
        open_source(root).ground_truth()
    (root / "times.txt").write_text("0\n1\n")
    with pytest.raises(DatasetError, match="times.txt.*2 timestamps.*4 images"):
        open_source(root)
    (root / "times.txt").write_text("0\n1\nabc\n3\n")
    with pytest.raises(DatasetError, match="times.txt:3"):
        open_source(root)
    (root / "times.txt").write_text("0\n1\n1\n3\n")
    with pytest.raises(DatasetError, match="increase"):
        open_source(root)
    (root / "camera.yaml").write_text("fx: -1\n")
    with pytest.raises(CalibrationError, match="camera.yaml"):
        open_source(root)


def test_detect_errors(tmp_path):
    with pytest.raises(DatasetError, match="no such"):
        open_source(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="unrecognised"):
        open_source(tmp_path / "empty")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DatasetError, match="notes.txt"):
        open_source(tmp_path / "notes.txt")


# --------------------------------------------------------------------------- KITTI


def _kitti(tmp_path: Path, n: int = 3, with_image_2: bool = False) -> tuple[Path, np.ndarray]:
    seq = tmp_path / "dataset" / "sequences" / "07"
    _images(seq / "image_0", n, gray=True)
    if with_image_2:
        _images(seq / "image_2", n)
    rows = [
        "P0: 30 0 15.5 0 0 31 11.5 0 0 0 1 0",
        "P1: 30 0 15.5 -16.2 0 31 11.5 0 0 0 1 0",
        "P2: 30 0 15.5 1.8 0 31 11.5 0.031 0 0 1 0.0027",
        "P3: 30 0 15.5 -14.4 0 31 11.5 0 0 0 1 0",
    ]
    (seq / "calib.txt").write_text("\n".join(rows) + "\n")
    (seq / "times.txt").write_text("".join(f"{0.1 * k:e}\n" for k in range(n)))
    rng = np.random.default_rng(3)
    p, q = _poses(rng, n)
    R = quat_to_rotmat(q)
    T = np.concatenate([R, p[:, :, None]], axis=2)
    (tmp_path / "dataset" / "poses").mkdir()
    (tmp_path / "dataset" / "poses" / "07.txt").write_text(
        "".join(" ".join(f"{v:.12e}" for v in M.ravel()) + "\n" for M in T)
    )
    return seq, T


def test_kitti(tmp_path):
    root, T = _kitti(tmp_path)
    assert detect_layout(root) == "kitti"
    seq = open_source(root)
    assert seq.kind == "kitti" and len(seq) == 3 and seq.camera == CAM
    assert seq.load(0).shape == (H, W)
    gt = seq.ground_truth()
    np.testing.assert_allclose(gt.positions, T[:, :, 3], atol=1e-9)
    np.testing.assert_allclose(gt.rotations, T[:, :, :3], atol=1e-9)
    np.testing.assert_allclose(gt.timestamps, [0.0, 0.1, 0.2])


def test_kitti_image_2_offsets_ground_truth(tmp_path):
    from eifslam.io.kitti import open_kitti

    root, T = _kitti(tmp_path, with_image_2=True)
    seq = open_kitti(root, camera_id=2)
    assert seq.load(0).shape == (H, W, 3)
    offset = -np.linalg.solve(CAM.K, [1.8, 0.031, 0.0027])  # camera 2 centre in camera 0
    expected = T[:, :, 3] + np.einsum("nij,j->ni", T[:, :, :3], offset)
    np.testing.assert_allclose(seq.ground_truth().positions, expected, atol=1e-9)


def test_kitti_broken(tmp_path):
    root, _ = _kitti(tmp_path)
    poses = tmp_path / "dataset" / "poses" / "07.txt"
    poses.write_text(poses.read_text().splitlines()[0] + "\n")
    with pytest.raises(DatasetError, match="07.txt.*1 poses.*3 images"):
        open_source(root).ground_truth()
    poses.write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(DatasetError, match="07.txt:1.*12 numbers"):
        open_source(root).ground_truth()
    (root / "calib.txt").write_text("P0: 30 0 15.5 0 0 31 11.5 0\n")
    with pytest.raises(CalibrationError, match="calib.txt"):
        open_source(root)


# --------------------------------------------------------------------------- TUM RGB-D


def test_tum_rgbd(tmp_path):
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    t_img = 1305031102.0 + np.array([0.0, 0.033, 0.066, 0.1])
    names = [f"{t:.6f}.png" for t in t_img]
    _images(root / "rgb", 4, names=names)
    (root / "rgb.txt").write_text(
        "# color images\n# file: 'x.bag'\n# timestamp filename\n"
        + "".join(f"{t:.6f} rgb/{n}\n" for t, n in zip(t_img, names))
    )
    t_gt = 1305031102.0 + np.arange(-0.0045, 0.08, 0.01)  # 100 Hz, ends before the last image
    p, q = _poses(np.random.default_rng(1), len(t_gt))
    (root / "groundtruth.txt").write_text("# ground truth\n" + _tum_lines(t_gt, p, q))
    seq = open_source(root, camera=CAM)
    assert seq.kind == "tum" and len(seq) == 4
    gt = seq.ground_truth()
    np.testing.assert_allclose(gt.timestamps, t_img[:3])  # the 4th is 0.0245 s from any pose
    nearest = [int(np.argmin(np.abs(t_gt - t))) for t in t_img[:3]]
    np.testing.assert_allclose(gt.positions, p[nearest])
    assert open_source(root).camera.fx == 517.3  # published freiburg1 calibration
    (root / "rgb.txt").write_text("1305031102.0\n")
    with pytest.raises(DatasetError, match="rgb.txt:1"):
        open_source(root, camera=CAM)
    (root / "rgb.txt").write_text("1305031102.0 rgb/missing.png\n")
    with pytest.raises(ImageError, match="missing.png"):
        open_source(root, camera=CAM).load(0)


# --------------------------------------------------------------------------- EuRoC

SENSOR = """%YAML:1.0
sensor_type: camera
T_BS:
  cols: 4
  rows: 4
  data: [0.0, -1.0, 0.0, 0.1,
         1.0, 0.0, 0.0, 0.2,
         0.0, 0.0, 1.0, 0.3,
         0.0, 0.0, 0.0, 1.0]
rate_hz: 20
resolution: [32, 24]
camera_model: pinhole
intrinsics: [30.0, 31.0, 15.5, 11.5]
distortion_model: radial-tangential
distortion_coefficients: [-0.28, 0.07, 0.0002, 0.00002]
"""


def test_euroc(tmp_path):
    cam0 = tmp_path / "MH_01_easy" / "mav0" / "cam0"
    ns = 1403636579763555584 + 50_000_000 * np.arange(3, dtype=np.int64)
    names = [f"{t}.png" for t in ns]
    _images(cam0 / "data", 3, names=names, gray=True)
    (cam0 / "data.csv").write_text(
        "#timestamp [ns],filename\n" + "".join(f"{t},{n}\n" for t, n in zip(ns, names))
    )
    (cam0 / "sensor.yaml").write_text(SENSOR)
    gt_ns = ns[0] - 3_000_000 + 5_000_000 * np.arange(40, dtype=np.int64)  # 200 Hz
    p, q = _poses(np.random.default_rng(2), len(gt_ns))
    gt_dir = cam0.parent / "state_groundtruth_estimate0"
    gt_dir.mkdir()
    (gt_dir / "data.csv").write_text(
        "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], "
        "q_RS_z [], v_RS_R_x [m s^-1], v_RS_R_y, v_RS_R_z, b_w_x, b_w_y, b_w_z, b_a_x, b_a_y, b_a_z\n"
        + "".join(
            f"{t}," + ",".join(map(str, [*pp, *qq])) + ",0,0,0,0,0,0,0,0,0\n"
            for t, pp, qq in zip(gt_ns, p, q)
        )
    )
    root = tmp_path / "MH_01_easy"
    assert detect_layout(root) == "euroc" and detect_layout(root / "mav0") == "euroc"
    seq = open_source(root)
    assert seq.kind == "euroc" and len(seq) == 3 and seq.camera.fx == 30.0
    assert seq.camera.distortion[0] == -0.28
    np.testing.assert_allclose(np.diff(seq.timestamps), 0.05, atol=1e-6)
    gt = seq.ground_truth()
    assert len(gt) == 3
    k = [int(np.argmin(np.abs(gt_ns - t))) for t in ns]  # 3 ms before each image: gt k+1? nearest
    R_wb = quat_to_rotmat(q[k])
    expected = p[k] + R_wb @ np.array([0.1, 0.2, 0.3])  # T_WC = T_WB T_BS
    np.testing.assert_allclose(gt.positions, expected, atol=1e-9)
    R_bs = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(gt.rotations, R_wb @ R_bs, atol=1e-9)
    (cam0 / "data.csv").write_text("#timestamp [ns],filename\nabc,x.png\n")
    with pytest.raises(DatasetError, match="data.csv:2"):
        open_source(root)


# --------------------------------------------------------------------------- Strecha

STRECHA_CAM = """30 0 15.5
0 31 11.5
0 0 1
0 0 0
{R}
{C}
32 24
"""


def test_strecha(tmp_path):
    root = tmp_path / "fountain"
    files = _images(root / "images", 3, names=["0000.jpg", "0001.jpg", "0002.jpg"])
    p, q = _poses(np.random.default_rng(4), 3)
    for f, pp, qq in zip(files, p, q):
        R = quat_to_rotmat(qq)
        text = STRECHA_CAM.format(
            R="\n".join(" ".join(f"{v:.15g}" for v in row) for row in R),
            C=" ".join(f"{v:.15g}" for v in pp),
        )
        (f.parent / (f.name + ".camera")).write_text(text)
    seq = open_source(root)
    assert seq.kind == "strecha" and len(seq) == 3 and seq.camera == CAM
    gt = seq.ground_truth()
    np.testing.assert_allclose(gt.positions, p, atol=1e-12)
    np.testing.assert_allclose(gt.quats_wxyz, q, atol=1e-9)
    assert seq.load(0).shape == (H, W, 3)
    bad = root / "images" / "0001.jpg.camera"
    bad.write_text(bad.read_text().replace("30 0 15.5", "35 0 15.5"))
    with pytest.raises(DatasetError, match="0001.jpg.camera.*intrinsics differ"):
        open_source(root)
    bad.write_text("1 2 3\n")
    with pytest.raises(CalibrationError, match="0001.jpg.camera"):
        open_source(root)


# --------------------------------------------------------------------------- video


def test_video(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (W, H))
    if not writer.isOpened():
        pytest.skip("this OpenCV build cannot write MJPG video")
    for k in range(5):
        writer.write(np.full((H, W, 3), 40 * k, np.uint8))
    writer.release()
    with pytest.raises(DatasetError, match="clip.avi.*camera"):
        open_source(path)
    write_camera_yaml(tmp_path / "clip.yaml", CAM)
    seq = open_source(path)
    assert seq.kind == "video" and len(seq) == 5 and seq.camera == CAM
    np.testing.assert_allclose(seq.timestamps, 0.1 * np.arange(5))
    assert seq[3].path is None and seq[3].video_index == 3
    levels = [int(img.mean()) for _, img in seq.images()]
    assert all(abs(a - 40 * k) <= 3 for k, a in enumerate(levels))
    assert abs(int(seq.load(1, grayscale=True).mean()) - 40) <= 3  # a seek backwards
    assert seq.ground_truth() is None
    seq.close()
    (tmp_path / "broken.mp4").write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="broken.mp4"):
        open_source(tmp_path / "broken.mp4", camera=CAM)


@pytest.mark.parametrize("bits", [10, 12, 14, 16])
def test_sixteen_bit_files_keep_the_bits_their_data_uses(tmp_path, bits):
    """A 10/12/14-bit camera's frames in 16-bit PNGs keep their 8 highest bits (OpenCV's own
    conversion kept the top 8 of 16: 16 grey levels of a 12-bit image); colour and
    grayscale reads alike."""
    import cv2

    from eifslam.io.images import read_image, sensor_bits

    rng = np.random.default_rng(bits)
    top = (1 << bits) - 1
    img = rng.integers(0, top + 1, size=(48, 64), dtype=np.uint16)
    img[0, 0] = top
    path = tmp_path / f"b{bits}.png"
    assert cv2.imwrite(str(path), img)
    assert sensor_bits(top) == bits
    assert [sensor_bits(v) for v in (0, 255, 256, 1023, 1024, 4095, 4096, 16384, 65535)] == \
        [8, 8, 10, 10, 12, 12, 14, 16, 16]
    for grey in (True, False):
        out = read_image(path, grayscale=grey)
        assert out.dtype == np.uint8 and out.shape[:2] == (48, 64)
        plane = out if out.ndim == 2 else out[..., 0]
        np.testing.assert_array_equal(plane, (img >> (bits - 8)).astype(np.uint8))
        assert len(np.unique(plane)) == 256
    eight = tmp_path / "eight.png"
    cv2.imwrite(str(eight), (img >> (bits - 8)).astype(np.uint8))
    np.testing.assert_array_equal(read_image(eight, grayscale=True), (img >> (bits - 8)).astype(np.uint8))
