"""ROS bags: bags written with ``rosbags`` itself (ROS 1 and ROS 2) read back frame for
frame, and run to the same trajectory as the folder they were made from; bad bags end in
one line."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402

from eifslam.cli.main import main as cli_main  # noqa: E402
from eifslam.errors import CalibrationError, DatasetError, ImageError  # noqa: E402
from eifslam.geometry.camera import PinholeCamera  # noqa: E402
from eifslam.io import detect_layout, load_camera, open_source, read_image, read_tum  # noqa: E402
from eifslam.io.folder import read_times  # noqa: E402
from eifslam.io.rosbag import camera_from_info, decode_image_message, find_bag, open_rosbag  # noqa: E402

from hostile import assert_clean  # noqa: E402

#: frames of kitti-seq1 put in the bags
N = 12
TOPIC = "/cam0/image_raw"
INFO = "/cam0/camera_info"


class BagWriter:
    """Writes one bag (ROS 1 file or ROS 2 folder) through rosbags' own writer."""

    def __init__(self, path: Path, ros2: bool) -> None:
        self.ros2 = ros2
        self.ts = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
        self.writer = Writer2(path, version=9) if ros2 else Writer1(path)
        self.conns: dict[str, object] = {}
        self.T = self.ts.types

    def __enter__(self) -> "BagWriter":
        self.writer.open()
        return self

    def __exit__(self, *exc) -> None:
        self.writer.close()

    def header(self, ns: int, frame_id: str):
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        extra = {} if self.ros2 else {"seq": 0}
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id, **extra)

    def write(self, topic: str, msg, record_ns: int) -> None:
        msgtype = msg.__msgtype__
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.ts)
        raw = self.ts.serialize_cdr(msg, msgtype) if self.ros2 else self.ts.serialize_ros1(msg, msgtype)
        self.writer.write(self.conns[topic], record_ns, raw)

    def image(self, topic: str, img: np.ndarray, ns: int, encoding: str | None = None,
              frame_id: str = "cam0", record_ns: int | None = None) -> None:
        if encoding is None:
            encoding = "mono8" if img.ndim == 2 else "bgr8"
        data = np.ascontiguousarray(img)
        if data.dtype == np.uint16:
            data = data.astype("<u2")
        h, w = img.shape[:2]
        step = data.strides[0]
        msg = self.T["sensor_msgs/msg/Image"](header=self.header(ns, frame_id), height=h, width=w,
                                              encoding=encoding, is_bigendian=0, step=step,
                                              data=np.frombuffer(data.tobytes(), np.uint8))
        self.write(topic, msg, ns + 1000 if record_ns is None else record_ns)

    def compressed(self, topic: str, img: np.ndarray, ns: int, ext: str = ".png", frame_id: str = "cam0") -> None:
        ok, buf = cv2.imencode(ext, img)
        assert ok
        msg = self.T["sensor_msgs/msg/CompressedImage"](header=self.header(ns, frame_id), format=ext[1:],
                                                        data=buf.reshape(-1))
        self.write(topic, msg, ns + 1000)

    def camera_info(self, topic: str, cam: PinholeCamera, ns: int = 0, frame_id: str = "cam0",
                    model: str = "plumb_bob", K: list[float] | None = None) -> None:
        K = [cam.fx, 0.0, cam.cx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 1.0] if K is None else K
        P = [cam.fx, 0.0, cam.cx, 0.0, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        k = "k" if self.ros2 else "K"
        fields = {k: np.array(K, float), k.replace("k", "d").replace("K", "D"): np.array(cam.distortion, float),
                  ("r" if self.ros2 else "R"): np.eye(3).reshape(-1), ("p" if self.ros2 else "P"): np.array(P, float)}
        msg = self.T["sensor_msgs/msg/CameraInfo"](header=self.header(ns, frame_id), height=cam.height,
                                                   width=cam.width, distortion_model=model, binning_x=0,
                                                   binning_y=0, roi=roi, **fields)
        self.write(topic, msg, ns + 1000)


def _kitti(root: Path) -> tuple[list[np.ndarray], list[int], PinholeCamera, np.ndarray]:
    files = sorted((root / "images").glob("*.png"))[:N]
    times = read_times(root / "times.txt")[:N]
    ns = [round(t * 1e9) for t in times]
    return [read_image(f) for f in files], ns, load_camera(root / "camera.yaml"), times


_BAGS: dict[str, Path] = {}


@pytest.fixture
def kitti(shared_dataset) -> Path:
    return shared_dataset("kitti-seq1")


@pytest.fixture
def bags(kitti, tmp_path_factory) -> dict[str, Path]:
    """``ros1`` (.bag), ``ros2`` (folder): the first N frames of kitti-seq1 as
    sensor_msgs/Image mono8 with a CameraInfo; ``compressed``: a ROS 2 bag of PNG
    CompressedImage with the CameraInfo; made once per session."""
    if not _BAGS:
        images, ns, cam, _ = _kitti(kitti)
        root = tmp_path_factory.mktemp("bags")
        for name, ros2, path in (("ros1", False, root / "kitti.bag"), ("ros2", True, root / "kitti_ros2"),
                                 ("compressed", True, root / "kitti_png")):
            with BagWriter(path, ros2) as w:
                w.camera_info(INFO, cam, ns[0])
                for img, t in zip(images, ns):
                    if name == "compressed":
                        w.compressed("/cam0/image_raw/compressed", img, t)
                    else:
                        w.image(TOPIC, img, t)
            _BAGS[name] = path
    return _BAGS


def cli(capsys, *argv) -> tuple[int, str]:
    rc = cli_main([str(a) for a in argv])
    return rc, capsys.readouterr().err


# -- reading back -----------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["ros1", "ros2", "compressed"])
def test_bag_reads_back_the_frames_times_and_camera(bags, kitti, kind):
    images, _, cam, times = _kitti(kitti)
    seq = open_source(bags[kind])
    assert seq.kind == "rosbag" and len(seq) == N
    assert seq.camera == cam
    np.testing.assert_array_equal(seq.timestamps, times)  # exactly the folder's times
    for k in (0, 5, N - 1):
        np.testing.assert_array_equal(seq.load(k), images[k])
    assert not seq.has_ground_truth and seq.ground_truth() is None


def test_loads_in_any_order_give_the_same_frames(bags, kitti):
    images = _kitti(kitti)[0]
    seq = open_rosbag(bags["ros1"], topic=TOPIC)
    for k in (3, 4, 5, 1, 11, 0, 7):  # back, forward, jumps
        np.testing.assert_array_equal(seq.load(k), images[k])
    assert seq.load(2, grayscale=True).shape == images[2].shape


def test_layout_detection(bags, tmp_path):
    assert detect_layout(bags["ros1"]) == "rosbag"
    assert detect_layout(bags["ros2"]) == "rosbag"
    db3 = next(bags["ros2"].glob("*.db3"))
    assert find_bag(db3) == bags["ros2"]  # a ROS 2 bag file stands for its folder
    assert find_bag(tmp_path) is None


def test_encodings_and_the_camera_file(tmp_path):
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    mono12 = rng.integers(0, 4096, (24, 32), dtype=np.uint16)
    yy, xx = np.mgrid[0:24, 0:32]
    smooth = np.dstack([xx * 8, yy * 10, xx * 4 + yy * 4]).astype(np.uint8)  # JPEG keeps it closely
    cam = PinholeCamera(fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=32, height=24)
    expect = {"/bgr": bgr, "/rgb": bgr, "/mono16": (mono12 >> 4).astype(np.uint8),
              "/jpeg": None}
    bag = tmp_path / "enc.bag"
    with BagWriter(bag, ros2=False) as w:
        for k in range(3):
            w.image("/bgr", bgr, k * 10**8 + 1)
            w.image("/rgb", bgr[..., ::-1], k * 10**8 + 1, encoding="rgb8")
            w.image("/mono16", mono12, k * 10**8 + 1, encoding="mono16")
            w.compressed("/jpeg", smooth, k * 10**8 + 1, ext=".jpg")
    (tmp_path / "cam.yaml").write_text("width: 32\nheight: 24\nfx: 30\nfy: 30\ncx: 16\ncy: 12\n")
    for topic, img in expect.items():
        seq = open_source(bag, camera=tmp_path / "cam.yaml", topic=topic)
        assert seq.camera == cam and len(seq) == 3
        np.testing.assert_allclose(seq.timestamps, [1e-9, 0.1 + 1e-9, 0.2 + 1e-9])
        out = seq.load(1)
        if img is None:  # JPEG: lossy
            assert out.shape == smooth.shape and np.abs(out.astype(int) - smooth).mean() < 3
        else:
            np.testing.assert_array_equal(out, img)
        assert seq.load(0, grayscale=True).shape == (24, 32)


def test_camera_info_of_the_images_frame_is_chosen(tmp_path):
    img = np.zeros((24, 32), np.uint8)
    left = PinholeCamera(fx=30.0, fy=31.0, cx=16.0, cy=12.0, width=32, height=24,
                         distortion=(0.1, -0.01, 0.001, 0.002, 0.0))
    right = PinholeCamera(fx=40.0, fy=41.0, cx=15.0, cy=11.0, width=32, height=24)
    bag = tmp_path / "stereo"
    with BagWriter(bag, ros2=True) as w:
        w.camera_info("/left/camera_info", left, frame_id="left")
        w.camera_info("/right/camera_info", right, frame_id="right")
        for k in range(2):
            w.image("/left/image", img, k + 1, frame_id="left")
            w.image("/right/image", img, k + 1, frame_id="right")
    assert open_rosbag(bag, topic="/right/image").camera == right
    assert open_rosbag(bag, topic="/left/image").camera == left
    with pytest.raises(DatasetError, match="2 image topics.*/left/image, /right/image"):
        open_rosbag(bag)


def test_header_stamps_all_zero_give_record_times(tmp_path):
    bag = tmp_path / "zero.bag"
    with BagWriter(bag, ros2=False) as w:
        for k in range(3):
            w.image("/im", np.zeros((4, 4), np.uint8), 0, record_ns=(k + 1) * 10**9)
    seq = open_rosbag(bag, camera=PinholeCamera(fx=4.0, fy=4.0, cx=2.0, cy=2.0, width=4, height=4))
    np.testing.assert_array_equal(seq.timestamps, [1.0, 2.0, 3.0])


def test_bad_camera_info_and_messages():
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="c")

    def info(K, D=(), model="plumb_bob", binning=0):
        return T["sensor_msgs/msg/CameraInfo"](header=header, height=24, width=32, distortion_model=model,
                                               d=np.array(D, float), k=np.array(K, float), r=np.eye(3).ravel(),
                                               p=np.zeros(12), binning_x=binning, binning_y=binning, roi=roi)

    K = [30.0, 0.0, 16.0, 0.0, 30.0, 12.0, 0.0, 0.0, 1.0]
    assert camera_from_info(info(K), "w").distortion == (0.0,) * 5
    with pytest.raises(CalibrationError, match="w: K is all zeros"):
        camera_from_info(info([0.0] * 9), "w")
    with pytest.raises(CalibrationError, match="'equidistant'"):
        camera_from_info(info(K, (0.1, 0.0, 0.0, 0.0), "equidistant"), "w")
    with pytest.raises(CalibrationError, match="binning"):
        camera_from_info(info(K, binning=2), "w")
    img = T["sensor_msgs/msg/Image"](header=header, height=4, width=4, encoding="mono8", is_bigendian=0, step=4,
                                     data=np.zeros(10, np.uint8))
    with pytest.raises(ImageError, match="w: a 4x4 mono8 image with step 4 needs 16 bytes, the message holds 10"):
        decode_image_message(img, "sensor_msgs/msg/Image", "w")
    bad = T["sensor_msgs/msg/CompressedImage"](header=header, format="jpeg", data=np.arange(50, dtype=np.uint8))
    with pytest.raises(ImageError, match="w: cannot decode"):
        decode_image_message(bad, "sensor_msgs/msg/CompressedImage", "w")


# -- the same trajectory as the folder ------------------------------------------------------

@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_bag_runs_to_the_folders_trajectory(bags, kitti, kind, tmp_path, capsys):
    common = ["--mode", "filter", "--max-frames", N, "--no-html", "-q"]
    rc, err = cli(capsys, "run", kitti, "--out", tmp_path / "folder", *common)
    assert rc == 0, err
    rc, err = cli(capsys, "run", bags[kind], "--topic", TOPIC, "--out", tmp_path / "bag", *common)
    assert rc == 0, err
    a, b = read_tum(tmp_path / "folder" / "trajectory.tum"), read_tum(tmp_path / "bag" / "trajectory.tum")
    assert len(a.timestamps) > N // 2
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    np.testing.assert_array_equal(a.positions, b.positions)
    np.testing.assert_array_equal(a.quats_wxyz, b.quats_wxyz)


# -- bad bags: one line, exit 1, no traceback ----------------------------------------------

def _run_bad(capsys, tmp_path, source, *extra) -> str:
    rc, err = cli(capsys, "run", source, "--out", tmp_path / "out", "--no-html", "-q", *extra)
    assert_clean(rc, err, str(source))
    assert rc == 1
    return err


def test_missing_topic_lists_the_image_topics(bags, tmp_path, capsys):
    err = _run_bad(capsys, tmp_path, bags["ros1"], "--topic", "/cam1/image_raw")
    assert "no topic /cam1/image_raw" in err and "image topics: /cam0/image_raw" in err
    err = _run_bad(capsys, tmp_path, bags["ros2"], "--topic", INFO)
    assert "CameraInfo, not images" in err


def test_wrong_encoding(tmp_path, capsys):
    bag = tmp_path / "bayer.bag"
    with BagWriter(bag, ros2=False) as w:
        w.image("/im", np.zeros((4, 4), np.uint8), 1, encoding="bayer_rggb8")
    err = _run_bad(capsys, tmp_path, bag, "--topic", "/im")
    assert "encoding 'bayer_rggb8' is not supported (mono8, bgr8, rgb8, mono16)" in err


def test_truncated_bags(bags, tmp_path, capsys):
    data = bags["ros1"].read_bytes()
    half = tmp_path / "half.bag"
    half.write_bytes(data[: len(data) // 2])
    err = _run_bad(capsys, tmp_path, half, "--topic", TOPIC)
    assert "cannot read ROS bag" in err
    folder = tmp_path / "half_ros2"
    folder.mkdir()
    for f in bags["ros2"].iterdir():
        body = f.read_bytes()
        (folder / f.name).write_bytes(body[: len(body) // 2] if f.suffix == ".db3" else body)
    err = _run_bad(capsys, tmp_path, folder, "--topic", TOPIC)
    assert "cannot read ROS bag" in err


def test_no_camera_info_and_no_camera_file(kitti, tmp_path, capsys):
    images, ns, cam, _ = _kitti(kitti)
    bag = tmp_path / "nocam.bag"
    with BagWriter(bag, ros2=False) as w:
        for img, t in zip(images[:3], ns[:3]):
            w.image(TOPIC, img, t)
    err = _run_bad(capsys, tmp_path, bag)
    assert "no camera" in err and "CameraInfo" in err
    seq = open_source(bag, camera=kitti / "camera.yaml")  # the camera file does it
    assert seq.camera == cam and len(seq) == 3


def test_topic_for_a_source_that_is_not_a_bag(kitti, tmp_path, capsys):
    err = _run_bad(capsys, tmp_path, kitti, "--topic", TOPIC)
    assert "applies to ROS bags only" in err
