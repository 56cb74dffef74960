"""ROS bags: a ROS 1 ``.bag`` file or a ROS 2 bag folder, read with ``rosbags``.

``rosbags`` is pure Python and needs no ROS install (the ``ros`` extra:
``pip install "eifslam[ros]"``). Nothing in a bag is unpickled or executed: messages are
decoded by their type definitions only.

* **Frames**: the messages of one image topic, ``sensor_msgs/Image`` (encodings
  :data:`ENCODINGS`) or ``sensor_msgs/CompressedImage`` (JPEG, PNG), in the order of their
  header stamps. The topic is the one asked for, else the bag's only image topic.
* **Timestamps**: the header stamps, in seconds; when every header stamp of the topic is
  zero (a driver that leaves them unset), the times the bag recorded the messages.
* **Camera**: the ``camera`` argument (a camera or camera file) when given; else a
  ``sensor_msgs/CameraInfo`` topic of the bag: the one whose header ``frame_id`` is the
  images', else the bag's only one. Its ``K``, image size and ``plumb_bob`` (or
  ``rational_polynomial``) distortion give the :class:`PinholeCamera`.
* **Ground truth** (optional, scoring only): ``<stem>.tum`` or ``groundtruth.tum`` beside
  a ``.bag`` file; ``groundtruth.tum`` inside a ROS 2 bag folder or ``<folder>.tum``
  beside it; associated with the frame times as for the other layouts.

A bag is scanned once when opened (every message of the topic is read, not decoded):
a missing topic, an unsupported encoding, a truncated or corrupt file and a missing
camera are found before any work and raise a one-line :class:`DatasetError` or
:class:`CalibrationError` naming the bag. Images are decoded by :meth:`Sequence.load`.
"""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import CalibrationError, DatasetError, EifslamError, ImageError
from ..geometry.camera import PinholeCamera
from .cameras import load_camera
from .folder import ground_truth_at_frames
from .image_header import check_image_size, encoded_size
from .images import decode_image, eight_bit
from .sequence import Frame, Sequence
from .trajectory import Trajectory, read_tum

__all__ = ["open_rosbag", "find_bag", "BagSequence", "camera_from_info", "decode_image_message",
           "IMAGE_TYPES", "ENCODINGS"]

#: message types read as frames
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
#: ``sensor_msgs/Image`` encodings read: (channels, bytes per channel)
ENCODINGS = {"mono8": (1, 1), "bgr8": (3, 1), "rgb8": (3, 1), "mono16": (1, 2)}
#: CameraInfo distortion models whose coefficients are OpenCV's (k1, k2, p1, p2[, k3[, k4, k5, k6]])
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")
#: files of a ROS 2 bag (inside its folder, beside ``metadata.yaml``)
ROS2_FILE_SUFFIXES = (".db3", ".mcap")


def find_bag(path: str | Path) -> Path | None:
    """The bag at ``path``: a ``.bag`` file, a ROS 2 bag folder (``metadata.yaml``), or the
    folder of a ROS 2 bag file (``.db3``, ``.mcap``) given directly; ``None`` otherwise."""
    p = Path(path)
    if p.is_file() and p.suffix.lower() == ".bag":
        return p
    if p.is_dir() and _is_ros2_folder(p):
        return p
    if p.is_file() and p.suffix.lower() in ROS2_FILE_SUFFIXES and _is_ros2_folder(p.parent):
        return p.parent
    return None


def _is_ros2_folder(p: Path) -> bool:
    meta = p / "metadata.yaml"
    try:
        return meta.is_file() and b"rosbag2_bagfile_information" in meta.read_bytes()[:4096]
    except OSError:
        return False


def _reason(exc: BaseException) -> str:
    """The reason of a reader's exception in one line: its message (arguments nested in
    tuples flattened), prefixed with the exception's type unless it is the reader's own."""

    def flat(args: Any) -> list[str]:
        return [t for a in args for t in (flat(a) if isinstance(a, tuple) else [str(a)])]

    text = " ".join(" ".join(flat(exc.args)).split()) or type(exc).__name__
    return text if type(exc).__name__.endswith("ReaderError") else f"{type(exc).__name__}: {text}"


@contextlib.contextmanager
def _reading(where: str, error: type[EifslamError] = DatasetError) -> Iterator[None]:
    """Turn what the bag reader raises into one ``error`` naming ``where``. ``rosbags``
    raises its own errors on a damaged bag, but a crafted one can reach any of Python's
    (``struct.error``, ``KeyError``, ``AssertionError``, ...): all of them mean the same
    to the user, an unreadable bag."""
    try:
        yield
    except (EifslamError, MemoryError, KeyboardInterrupt):
        raise
    except Exception as exc:  # noqa: BLE001 (see the docstring)
        raise error(f"{where}: cannot read ROS bag ({_reason(exc)})") from None


def _any_reader(bag: Path) -> Any:
    """An (unopened) ``rosbags.highlevel.AnyReader`` of ``bag``. ROS 2 bags written
    without type definitions are decoded with ROS 2 Humble's (the sensor_msgs types
    read here are the same in every ROS 2 release)."""
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise DatasetError(f"{bag}: reading ROS bags needs the 'rosbags' package "
                           "(pip install \"eifslam[ros]\")") from None
    return AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE))


def _stamp_ns(msg: Any) -> int:
    stamp = msg.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _field(msg: Any, name: str) -> Any:
    """A CameraInfo field by its ROS 2 name (``k``) or its ROS 1 name (``K``)."""
    return getattr(msg, name) if hasattr(msg, name) else getattr(msg, name.upper())


def camera_from_info(msg: Any, where: str, image_size: tuple[int, int] | None = None) -> PinholeCamera:
    """The camera of a ``sensor_msgs/CameraInfo`` message (ROS 1 or ROS 2 field names).

    Parameters
    ----------
    msg : the decoded message.
    where : names it in errors (the bag and topic).
    image_size : ``(width, height)`` of the images, used when the message has none (0).

    Raises
    ------
    CalibrationError
        ``K`` not a calibration (zeros, skew), a distortion model other than
        :data:`DISTORTION_MODELS` with non-zero coefficients, binning or a region of
        interest (the intrinsics would not be those of the images).
    """
    K = np.asarray(_field(msg, "k"), dtype=np.float64).reshape(-1)
    if K.size != 9 or not np.all(np.isfinite(K)):
        raise CalibrationError(f"{where}: K must hold 9 finite numbers")
    if not np.any(K):
        raise CalibrationError(f"{where}: K is all zeros (an uncalibrated camera); pass a camera file")
    if K[1] != 0.0 or K[3] != 0.0 or K[6] != 0.0 or K[7] != 0.0 or K[8] != 1.0:
        raise CalibrationError(f"{where}: K is not a pinhole matrix without skew ({K.tolist()})")
    D = tuple(float(d) for d in np.asarray(_field(msg, "d"), dtype=np.float64).reshape(-1))
    model = str(msg.distortion_model)
    if not any(D):
        D = (0.0,) * 5
    elif model not in DISTORTION_MODELS or len(D) not in (4, 5, 8):
        raise CalibrationError(f"{where}: distortion model {model!r} with {len(D)} coefficients is not "
                               f"supported ({', '.join(DISTORTION_MODELS)}); pass a camera file")
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1:
        raise CalibrationError(f"{where}: binning {msg.binning_x}x{msg.binning_y} is not supported; "
                               "pass a camera file")
    roi = msg.roi
    width, height = int(msg.width), int(msg.height)
    if (width == 0 or height == 0) and image_size is not None:
        width, height = image_size
    if int(roi.x_offset) or int(roi.y_offset) or (int(roi.width) and (int(roi.width), int(roi.height))
                                                  != (width, height)):
        raise CalibrationError(f"{where}: a region of interest is not supported; pass a camera file")
    try:
        return PinholeCamera(fx=float(K[0]), fy=float(K[4]), cx=float(K[2]), cy=float(K[5]),
                             width=width, height=height, distortion=D)
    except EifslamError as exc:
        raise CalibrationError(f"{where}: {exc}") from None


def decode_image_message(msg: Any, msgtype: str, where: str, grayscale: bool = False) -> NDArray[np.uint8]:
    """The image of a ``sensor_msgs/Image`` or ``sensor_msgs/CompressedImage`` message.

    Returns
    -------
    (H, W) uint8 grey or (H, W, 3) uint8 BGR, as :func:`~.images.read_image`: ``rgb8`` is
    turned to BGR, ``mono16`` keeps the 8 highest bits its data uses.

    Raises
    ------
    ImageError
        An encoding not in :data:`ENCODINGS`, data shorter than the size and step say,
        a size over the memory budget, or compressed data that does not decode
        (``where`` starts the message).
    """
    if msgtype.endswith("CompressedImage"):
        fmt = str(msg.format)
        if "compresseddepth" in fmt.lower():
            raise ImageError(f"{where}: compressed depth images ({fmt!r}) are not supported")
        return decode_image(np.asarray(msg.data, dtype=np.uint8), where, grayscale)
    enc = str(msg.encoding)
    if enc not in ENCODINGS:
        raise ImageError(f"{where}: image encoding {enc!r} is not supported ({', '.join(ENCODINGS)})")
    channels, depth = ENCODINGS[enc]
    w, h, step = int(msg.width), int(msg.height), int(msg.step)
    check_image_size(w, h, where)
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    row = w * channels * depth
    if step < row or data.size < step * h:
        raise ImageError(f"{where}: a {w}x{h} {enc} image with step {step} needs {max(step, row) * h} "
                         f"bytes, the message holds {data.size}")
    rows = data[: step * h].reshape(h, step)[:, :row]
    if depth == 2:
        img: NDArray = rows.view(">u2" if int(msg.is_bigendian) else "<u2").astype(np.uint16)
    else:
        img = rows
    img = eight_bit(np.ascontiguousarray(img.reshape(h, w, channels) if channels > 1 else img.reshape(h, w)))
    if enc == "rgb8":
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    if grayscale and img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    return np.array(img, dtype=np.uint8, copy=True)  # owns its pixels (the message is read-only)


@dataclass(frozen=True)
class _Scan:
    """What opening a bag learns: per message of the topic in bag order, its record time
    (ns), its rank among the messages recorded at that time, and its header stamp (ns)."""

    topic: str
    record_ns: list[int]
    rank: list[int]
    stamp_ns: list[int]
    image_size: tuple[int, int] | None
    frame_id: str


class BagSequence(Sequence):
    """A sequence whose frames are the messages of one image topic of a ROS bag.

    Frames are read on demand: consecutive loads continue one pass of the bag reader, a
    jump restarts it at the frame's record time. The reader is opened by the thread that
    loads (the SQLite file of a ROS 2 bag belongs to the thread that opened it), again if
    another thread loads later. :attr:`topic` names the topic; a frame's ``video_index``
    is the number of its message on the topic, in bag order.
    """

    def __init__(self, *args: Any, topic: str, scan: _Scan, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.topic = topic
        self._scan = scan
        self._lock = threading.Lock()
        self._reader: Any = None
        self._owner: int | None = None
        self._connections: list[Any] = []
        self._messages: Iterator[Any] | None = None
        self._next = -1

    def close(self) -> None:
        """Release the bag file."""
        self._messages = None
        if self._reader is not None:
            with contextlib.suppress(Exception):
                self._reader.close()
            self._reader = None

    def __del__(self) -> None:
        self.close()

    def _read(self, frame: Frame, grayscale: bool) -> NDArray[np.uint8]:
        pos = int(frame.video_index if frame.video_index is not None else frame.index)
        where = f"{self.root} {self.topic} message {pos}"
        with self._lock:
            with _reading(where, ImageError):
                try:
                    conn, raw = self._message(pos)
                    msg = self._reader.deserialize(raw, conn.msgtype)
                except BaseException:
                    self._messages = None  # start a fresh pass at the next load
                    raise
        return decode_image_message(msg, conn.msgtype, where, grayscale)

    def _message(self, pos: int) -> tuple[Any, bytes]:
        if self._reader is None or self._owner != threading.get_ident():
            self.close()
            self._reader = _any_reader(self.root)
            self._reader.open()
            self._owner = threading.get_ident()
            self._connections = [c for c in self._reader.connections if c.topic == self.topic
                                 and c.msgtype in IMAGE_TYPES]
        if self._messages is None or pos != self._next:
            self._messages = self._reader.messages(connections=self._connections,
                                                   start=self._scan.record_ns[pos])
            for _ in range(self._scan.rank[pos]):
                next(self._messages, None)
        item = next(self._messages, None)
        if item is None:
            raise ImageError(f"{self.root} {self.topic} message {pos}: not found in the bag")
        self._next = pos + 1
        return item[0], item[2]


def _choose_topic(bag: Path, topic: str | None, connections: list[Any]) -> str:
    images = sorted({c.topic for c in connections if c.msgtype in IMAGE_TYPES})
    listed = ", ".join(images) if images else "none"
    if topic is None:
        if len(images) == 1:
            return images[0]
        if not images:
            raise DatasetError(f"{bag}: the bag has no image topic (sensor_msgs/Image or CompressedImage)")
        raise DatasetError(f"{bag}: the bag has {len(images)} image topics ({listed}); choose one (--topic)")
    if topic in images:
        return topic
    other = sorted({c.msgtype for c in connections if c.topic == topic})
    if other:
        raise DatasetError(f"{bag}: topic {topic} holds {other[0]}, not images; image topics: {listed}")
    raise DatasetError(f"{bag}: no topic {topic} in the bag; image topics: {listed}")


def _scan_topic(bag: Path, reader: Any, topic: str) -> _Scan:
    connections = [c for c in reader.connections if c.topic == topic and c.msgtype in IMAGE_TYPES]
    record: list[int] = []
    rank: list[int] = []
    stamps: list[int] = []
    size: tuple[int, int] | None = None
    frame_id = ""
    for conn, t, raw in reader.messages(connections=connections):
        msg = reader.deserialize(raw, conn.msgtype)
        k = len(record)
        where = f"{bag}: {topic} message {k}"
        if conn.msgtype.endswith("/Image"):
            if str(msg.encoding) not in ENCODINGS:
                raise DatasetError(f"{where}: image encoding {str(msg.encoding)!r} is not supported "
                                   f"({', '.join(ENCODINGS)})")
            if size is None:
                size = (int(msg.width), int(msg.height))
        else:
            if "compresseddepth" in str(msg.format).lower():
                raise DatasetError(f"{where}: compressed depth images ({str(msg.format)!r}) are not supported")
            if size is None:
                size = encoded_size(bytes(np.asarray(msg.data, dtype=np.uint8)[:65536]))
        if k == 0:
            frame_id = str(msg.header.frame_id)
        rank.append(rank[-1] + 1 if record and record[-1] == t else 0)
        record.append(int(t))
        stamps.append(_stamp_ns(msg))
    if not record:
        raise DatasetError(f"{bag}: topic {topic} holds no message")
    return _Scan(topic, record, rank, stamps, size, frame_id)


def _bag_camera(bag: Path, reader: Any, scan: _Scan) -> PinholeCamera:
    """The camera of the bag's CameraInfo topics (module docstring)."""
    firsts: dict[str, Any] = {}
    for conn in reader.connections:
        if conn.msgtype == CAMERA_INFO and conn.topic not in firsts:
            item = next(reader.messages(connections=[c for c in reader.connections if c.topic == conn.topic]), None)
            if item is not None:
                firsts[conn.topic] = reader.deserialize(item[2], item[0].msgtype)
    if not firsts:
        raise DatasetError(f"{bag}: no camera: the bag has no sensor_msgs/CameraInfo message; "
                           "pass a camera file (--camera)")
    same = sorted(t for t, m in firsts.items() if scan.frame_id and str(m.header.frame_id) == scan.frame_id)
    if len(same) > 1:  # several in the images' frame: the one beside the image topic
        near = [t for t in same if t.rpartition("/")[0] == scan.topic.rpartition("/")[0]]
        same = near or same
    if same:
        chosen = same[0]
    elif len(firsts) == 1:
        chosen = next(iter(firsts))
    else:
        raise DatasetError(f"{bag}: no camera: none of the CameraInfo topics ({', '.join(sorted(firsts))}) "
                           f"is in frame {scan.frame_id!r} of {scan.topic}; pass a camera file (--camera)")
    return camera_from_info(firsts[chosen], f"{bag}: CameraInfo {chosen}", scan.image_size)


def _ground_truth_file(bag: Path) -> Path | None:
    if bag.is_dir():
        cands = [bag / "groundtruth.tum", bag.parent / f"{bag.name}.tum"]
    else:
        cands = [bag.with_suffix(".tum"), bag.parent / "groundtruth.tum"]
    return next((c for c in cands if c.is_file()), None)


def open_rosbag(
    path: str | Path,
    camera: PinholeCamera | str | Path | None = None,
    topic: str | None = None,
) -> BagSequence:
    """Open one image topic of a ROS 1 or ROS 2 bag as a sequence (module docstring).

    Parameters
    ----------
    path : a ``.bag`` file, a ROS 2 bag folder, or a ``.db3`` / ``.mcap`` file in one.
    camera : a camera or camera file; else the bag's CameraInfo.
    topic : the image topic, e.g. ``/cam0/image_raw``; else the bag's only image topic.

    Returns
    -------
    BagSequence of kind ``"rosbag"``; frames have ``path=None`` and ``video_index`` (the
    message number on the topic).

    Raises
    ------
    DatasetError
        Not a bag, unreadable (truncated, corrupt, not indexed), no such image topic (the
        message lists the bag's image topics), an unsupported encoding, or no camera.
    CalibrationError
        The CameraInfo or the camera file is not a usable calibration.
    """
    given = Path(path)
    bag = find_bag(given)
    if bag is None:
        raise DatasetError(f"{given}: not a ROS bag (a .bag file or a ROS 2 bag folder with metadata.yaml)")
    reader = _any_reader(bag)
    with _reading(str(bag)):
        reader.open()
        try:
            name = _choose_topic(bag, topic, reader.connections)
            scan = _scan_topic(bag, reader, name)
            if camera is None:
                cam = _bag_camera(bag, reader, scan)
        finally:
            reader.close()
    if isinstance(camera, PinholeCamera):
        cam = camera
    elif camera is not None:
        cam = load_camera(camera, image_size=scan.image_size)
    stamps = np.asarray(scan.stamp_ns, dtype=np.int64)
    ns = np.asarray(scan.record_ns, dtype=np.int64) if not np.any(stamps) else stamps
    order = np.argsort(ns, kind="stable")
    times = [int(ns[k]) / 1_000_000_000 for k in order]  # int / int: the nearest double
    frames = [Frame(i, t, video_index=int(k)) for i, (t, k) in enumerate(zip(times, order))]
    gt_file = _ground_truth_file(bag)
    loader = None
    if gt_file is not None:
        frame_times = np.asarray(times, dtype=np.float64)

        def loader() -> Trajectory:
            return ground_truth_at_frames(read_tum(gt_file), frame_times)
    label = bag.stem if bag.is_file() else bag.name
    return BagSequence(label, bag, cam, frames, "rosbag", loader, topic=name, scan=scan)
