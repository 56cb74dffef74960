"""Camera calibration files → :class:`~eifslam.geometry.camera.PinholeCamera`.

Formats, sniffed by :func:`load_camera`:

* eifslam ``camera.yaml``: keys ``model`` (``pinhole``, optional), ``width``, ``height``,
  ``fx``, ``fy``, ``cx``, ``cy``, ``distortion`` (list of 4, 5 or 8 OpenCV coefficients,
  optional). Unknown keys are rejected.
* OpenCV / ORB-SLAM settings YAML: ``Camera.fx``, ``Camera.fy``, ``Camera.cx``,
  ``Camera.cy``, ``Camera.k1``, ``Camera.k2``, ``Camera.p1``, ``Camera.p2``,
  ``Camera.k3`` (optional), ``Camera.width``, ``Camera.height`` (ORB-SLAM3's ``Camera1.``
  prefix too). The ``%YAML:1.0`` directive and ``!!opencv-matrix`` tags are accepted.
* EuRoC ``sensor.yaml``: ``intrinsics: [fu, fv, cu, cv]``, ``resolution: [w, h]``,
  ``distortion_coefficients`` (radial-tangential), ``T_BS`` (see :func:`read_euroc_sensor`).
* KITTI odometry ``calib.txt``: rows ``P0: ...`` .. ``P3: ...`` (12 numbers, row-major
  3x4; labels optional). The image size is not in the file: pass ``image_size``.
* Strecha ``.camera``: K (3 rows), distortion (1 row), R (3 rows), C (1 row), ``w h``.

Every problem raises :class:`~eifslam.errors.CalibrationError` naming the file and key.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Callable, Union

import numpy as np
import yaml
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from .files import read_text
from ..errors import CalibrationError, EifslamError

__all__ = [
    "load_camera",
    "write_camera_yaml",
    "parse_camera_yaml",
    "parse_kitti_calib",
    "parse_strecha_camera",
    "read_euroc_sensor",
    "StrechaCamera",
]

ImageSize = Union[tuple[int, int], Callable[[], tuple[int, int]], None]

_EIFSLAM_KEYS = {"model", "width", "height", "fx", "fy", "cx", "cy", "distortion"}
_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_KITTI_LINE = re.compile(rf"^\s*(?:(\w+)\s*:)?\s*((?:{_NUM}\s+){{11}}{_NUM})\s*$")


class _OpenCVLoader(yaml.SafeLoader):
    """SafeLoader that accepts any tag (``!!opencv-matrix``) as a plain node."""


def _any_tag(loader: yaml.SafeLoader, suffix: str, node: yaml.Node) -> Any:
    if isinstance(node, yaml.MappingNode):
        return loader.construct_mapping(node, deep=True)
    if isinstance(node, yaml.SequenceNode):
        return loader.construct_sequence(node, deep=True)
    return loader.construct_scalar(node)


_OpenCVLoader.add_multi_constructor("tag:yaml.org,2002:", _any_tag)
_OpenCVLoader.add_multi_constructor("!", _any_tag)


#: largest camera file read, bytes (a camera file is a few hundred bytes)
MAX_CAMERA_FILE_BYTES = 1_000_000
#: largest number of YAML nodes (scalars, lists, mappings) and deepest nesting accepted
MAX_YAML_NODES = 10_000
MAX_YAML_DEPTH = 32


def _read_text(path: Path) -> str:
    return read_text(path, "camera file", CalibrationError, max_bytes=MAX_CAMERA_FILE_BYTES)


def _check_yaml_events(body: str, name: str) -> None:
    """Refuse, before anything is built, YAML with aliases (``*ref``: their expansion can
    be exponential, the "billion laughs"), more than :data:`MAX_YAML_NODES` nodes or
    nesting deeper than :data:`MAX_YAML_DEPTH`. A camera file needs none of these."""
    nodes = depth = 0
    for event in yaml.parse(body, Loader=yaml.SafeLoader):
        if isinstance(event, yaml.AliasEvent):
            raise CalibrationError(f"{name}: YAML aliases (*{event.anchor}) are not accepted in a camera file")
        if isinstance(event, (yaml.ScalarEvent, yaml.CollectionStartEvent)):
            nodes += 1
            if nodes > MAX_YAML_NODES:
                raise CalibrationError(f"{name}: YAML has more than {MAX_YAML_NODES} values")
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                raise CalibrationError(f"{name}: YAML is nested more than {MAX_YAML_DEPTH} levels deep")
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1


def _load_yaml(text: str, name: str) -> Any:
    # OpenCV's FileStorage writes '%YAML:1.0', which is not valid YAML 1.1: drop directives
    body = "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("%YAML"))
    try:
        _check_yaml_events(body, name)
        return yaml.load(body, Loader=_OpenCVLoader)  # noqa: S506 (SafeLoader subclass)
    except RecursionError:
        raise CalibrationError(f"{name}: YAML is nested too deeply") from None
    except ValueError as exc:  # e.g. an integer of more digits than Python converts
        raise CalibrationError(f"{name}: not valid YAML ({_cut(str(exc).splitlines()[0])})") from None
    except yaml.YAMLError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CalibrationError(f"{name}: not valid YAML ({first})") from None


def _cut(text: str, n: int = 60) -> str:
    """``text`` cut to ``n`` characters, for messages."""
    return text if len(text) <= n else text[: n - 3] + "..."


def _short(v: Any, n: int = 60) -> str:
    """``repr(v)`` cut to ``n`` characters, for messages."""
    try:
        return _cut(repr(v), n)
    except ValueError:  # an int of more digits than Python will print
        return f"a {type(v).__name__} too large to print"


def _number(data: dict, key: str, name: str, default: float | None = None) -> float:
    if key not in data:
        if default is not None:
            return default
        raise CalibrationError(f"{name}: missing key '{key}'")
    v = data[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise CalibrationError(f"{name}: key '{key}' must be a number, got {_short(v)}")
    try:
        f = float(v)
    except OverflowError:  # an int too large for a float
        f = float("inf")
    if not np.isfinite(f):
        raise CalibrationError(f"{name}: key '{key}' must be finite, got {_short(v)}")
    return f


def _positive(value: float, key: str, name: str) -> float:
    if value <= 0:
        raise CalibrationError(f"{name}: key '{key}' must be positive, got {value!r}")
    return value


def _size_value(value: float, key: str, name: str) -> int:
    if value <= 0 or value != int(value):
        raise CalibrationError(f"{name}: key '{key}' must be a positive integer, got {value!r}")
    return int(value)


def _resolve_size(image_size: ImageSize, name: str, what: str) -> tuple[int, int]:
    if image_size is None:
        raise CalibrationError(f"{name}: {what} not in the file; the image size is needed")
    size = image_size() if callable(image_size) else image_size
    return int(size[0]), int(size[1])


def _make_camera(name: str, **kw: Any) -> PinholeCamera:
    try:
        return PinholeCamera(**kw)
    except EifslamError as exc:
        raise CalibrationError(f"{name}: {exc}") from None


def _number_list(v: Any, key: str, name: str) -> list[float]:
    if isinstance(v, dict) and "data" in v:  # !!opencv-matrix
        v = v["data"]
    if not isinstance(v, (list, tuple)):
        raise CalibrationError(f"{name}: key '{key}' must be a list of numbers, got {_short(v)}")
    return [_number({key: x}, key, name) for x in v]


def _parse_eifslam(data: dict, name: str, image_size: ImageSize) -> PinholeCamera:
    unknown = sorted(map(str, set(data) - _EIFSLAM_KEYS))
    if unknown:
        raise CalibrationError(f"{name}: unknown key(s) {_cut(', '.join(map(repr, unknown)))}")
    model = data.get("model", "pinhole")
    if model != "pinhole":
        raise CalibrationError(f"{name}: key 'model' must be 'pinhole', got {_short(model)}")
    fx = _positive(_number(data, "fx", name), "fx", name)
    fy = _positive(_number(data, "fy", name), "fy", name)
    cx, cy = _number(data, "cx", name), _number(data, "cy", name)
    if "width" in data or "height" in data or image_size is None:
        w = _size_value(_number(data, "width", name), "width", name)
        h = _size_value(_number(data, "height", name), "height", name)
    else:
        w, h = _resolve_size(image_size, name, "width/height")
    dist = tuple(_number_list(data.get("distortion", [0.0] * 5), "distortion", name))
    if len(dist) not in (0, 4, 5, 8):
        raise CalibrationError(
            f"{name}: key 'distortion' must have 4, 5 or 8 coefficients, got {len(dist)}"
        )
    return _make_camera(name, fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h, distortion=dist)


def _parse_opencv(data: dict, name: str, image_size: ImageSize) -> PinholeCamera:
    prefix = "Camera1." if "Camera1.fx" in data else "Camera."

    def num(k: str, default: float | None = None) -> float:
        # width/height are 'Camera.width' in both ORB-SLAM2 and ORB-SLAM3 files
        key = prefix + k if prefix + k in data or f"Camera.{k}" not in data else f"Camera.{k}"
        return _number(data, key, name, default)

    fx = _positive(num("fx"), prefix + "fx", name)
    fy = _positive(num("fy"), prefix + "fy", name)
    cx, cy = num("cx"), num("cy")
    if any(f"{p}{k}" in data for p in ("Camera.", "Camera1.") for k in ("width", "height")):
        w = _size_value(num("width"), "Camera.width", name)
        h = _size_value(num("height"), "Camera.height", name)
    else:
        w, h = _resolve_size(image_size, name, "Camera.width/Camera.height")
    dist = tuple(num(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3"))
    return _make_camera(name, fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h, distortion=dist)


def _parse_euroc(data: dict, name: str) -> PinholeCamera:
    intr = _number_list(data.get("intrinsics"), "intrinsics", name)
    if len(intr) != 4:
        raise CalibrationError(f"{name}: key 'intrinsics' must be [fu, fv, cu, cv]")
    if "resolution" not in data:
        raise CalibrationError(f"{name}: missing key 'resolution'")
    res = _number_list(data["resolution"], "resolution", name)
    if len(res) != 2:
        raise CalibrationError(f"{name}: key 'resolution' must be [width, height]")
    model = data.get("camera_model", "pinhole")
    if model != "pinhole":
        raise CalibrationError(f"{name}: key 'camera_model' must be 'pinhole', got {_short(model)}")
    dmodel = data.get("distortion_model", "radial-tangential")
    if dmodel not in ("radial-tangential", "radtan", "none"):
        raise CalibrationError(
            f"{name}: key 'distortion_model' {_short(dmodel)} is not supported (radial-tangential)"
        )
    dist = tuple(_number_list(data.get("distortion_coefficients", [0.0] * 4), "distortion_coefficients", name))
    if len(dist) not in (0, 4, 5, 8):
        raise CalibrationError(f"{name}: key 'distortion_coefficients' must have 4 or 5 values")
    fu = _positive(intr[0], "intrinsics", name)
    fv = _positive(intr[1], "intrinsics", name)
    w = _size_value(res[0], "resolution", name)
    h = _size_value(res[1], "resolution", name)
    return _make_camera(name, fx=fu, fy=fv, cx=intr[2], cy=intr[3], width=w, height=h, distortion=dist)


def parse_camera_yaml(text: str, name: str = "<camera>", image_size: ImageSize = None) -> PinholeCamera:
    """Parse eifslam, OpenCV/ORB-SLAM or EuRoC camera YAML text (format sniffed by keys).

    Parameters
    ----------
    text : YAML text; a leading ``%YAML:1.0`` directive is allowed.
    name : file name for messages.
    image_size : ``(width, height)`` or a callable returning it, used only when the file
        has no image size (ORB-SLAM2 files).
    """
    data = _load_yaml(text, name)
    if not isinstance(data, dict):
        raise CalibrationError(f"{name}: expected a YAML mapping of camera keys")
    if any(str(k).startswith(("Camera.", "Camera1.")) for k in data):
        return _parse_opencv(data, name, image_size)
    if "intrinsics" in data:
        return _parse_euroc(data, name)
    if "fx" in data or "model" in data:
        return _parse_eifslam(data, name, image_size)
    raise CalibrationError(
        f"{name}: unknown camera YAML (expected keys fx/fy/cx/cy, Camera.fx.. or intrinsics)"
    )


def _is_kitti(text: str) -> bool:
    lines = [ln for ln in text.splitlines() if ln.strip()]
    return bool(lines) and all(_KITTI_LINE.match(ln) for ln in lines)


def parse_kitti_calib(
    text: str, name: str = "calib.txt", row: str = "P0", image_size: ImageSize = None
) -> tuple[PinholeCamera, NDArray[np.float64]]:
    """Parse a KITTI odometry ``calib.txt``.

    Parameters
    ----------
    text : file content: rows of 12 numbers (3x4 row-major), labelled ``P0:`` .. or not
        (unlabelled rows are P0, P1, P2, P3 in order).
    name : file name for messages.
    row : projection matrix to use (``P0`` left grey, ``P2`` left colour).
    image_size : ``(width, height)`` or callable; the file does not hold it.

    Returns
    -------
    camera : PinholeCamera
    P : (3, 4) projection matrix ``K [I | t]`` of that camera in the frame of camera 0.
    """
    rows: dict[str, NDArray[np.float64]] = {}
    for k, ln in enumerate(ln for ln in text.splitlines() if ln.strip()):
        m = _KITTI_LINE.match(ln)
        if not m:
            raise CalibrationError(f"{name}: line {k + 1} is not a label and 12 numbers")
        label = m.group(1) or f"P{k}"
        rows[label] = np.array(m.group(2).split(), dtype=np.float64).reshape(3, 4)
    if row not in rows:
        raise CalibrationError(f"{name}: missing row '{row}' (has {', '.join(rows) or 'none'})")
    P = rows[row]
    if not np.all(np.isfinite(P)):
        raise CalibrationError(f"{name}: row '{row}' has non-finite values")
    if abs(P[0, 1]) > 1e-9 or abs(P[1, 0]) > 1e-9 or not np.allclose(P[2, :3], [0, 0, 1]):
        raise CalibrationError(f"{name}: row '{row}' is not of the form K [I | t]")
    fx = _positive(float(P[0, 0]), f"{row} fx", name)
    fy = _positive(float(P[1, 1]), f"{row} fy", name)
    w, h = _resolve_size(image_size, name, "the image size")
    cam = _make_camera(name, fx=fx, fy=fy, cx=float(P[0, 2]), cy=float(P[1, 2]), width=w, height=h)
    return cam, P


class StrechaCamera:
    """Content of a Strecha ``.camera`` file.

    Attributes
    ----------
    camera : PinholeCamera
    R_wc : (3, 3) camera-to-world rotation.
    C : (3,) camera centre in the world frame.
    """

    def __init__(self, camera: PinholeCamera, R_wc: NDArray[np.float64], C: NDArray[np.float64]):
        self.camera, self.R_wc, self.C = camera, R_wc, C


def parse_strecha_camera(text: str, name: str = "<camera>") -> StrechaCamera:
    """Parse a Strecha ``.camera`` file: 9 rows ``K(3) dist(1) R(3) C(1) w h``.

    The distortion row ``k1 k2 k3`` (radial) maps to OpenCV ``(k1, k2, 0, 0, k3)``.
    """
    lines = [ln.split() for ln in text.splitlines() if ln.strip()]
    if len(lines) != 9:
        raise CalibrationError(f"{name}: expected 9 rows (K, distortion, R, C, size), got {len(lines)}")
    try:
        vals = [[float(x) for x in ln] for ln in lines]
    except ValueError:
        raise CalibrationError(f"{name}: non-numeric value") from None
    for k, n in zip(range(9), (3, 3, 3, 3, 3, 3, 3, 3, 2)):
        if len(vals[k]) != n and not (k == 3 and len(vals[k]) in (2, 3, 4, 5)):
            raise CalibrationError(f"{name}: row {k + 1} must have {n} numbers, got {len(vals[k])}")
    if not all(np.all(np.isfinite(v)) for v in vals):
        raise CalibrationError(f"{name}: non-finite value")
    K = np.array(vals[0:3])
    d = vals[3] + [0.0] * (3 - len(vals[3]))
    dist = (d[0], d[1], 0.0, 0.0, d[2]) if len(vals[3]) <= 3 else tuple(vals[3] + [0.0] * (5 - len(vals[3])))
    R = np.array(vals[4:7])
    if abs(np.linalg.det(R) - 1.0) > 1e-3 or not np.allclose(R.T @ R, np.eye(3), atol=1e-3):
        raise CalibrationError(f"{name}: R (rows 5-7) is not a rotation matrix")
    w = _size_value(vals[8][0], "width", name)
    h = _size_value(vals[8][1], "height", name)
    cam = _make_camera(
        name,
        fx=_positive(float(K[0, 0]), "K[0,0]", name),
        fy=_positive(float(K[1, 1]), "K[1,1]", name),
        cx=float(K[0, 2]), cy=float(K[1, 2]), width=w, height=h, distortion=dist,
    )
    return StrechaCamera(cam, R, np.array(vals[7][:3], dtype=np.float64))


def read_euroc_sensor(path: str | Path) -> tuple[PinholeCamera, NDArray[np.float64]]:
    """Read EuRoC ``sensor.yaml``: the camera and ``T_BS`` (4, 4), sensor-to-body."""
    path = Path(path)
    data = _load_yaml(_read_text(path), str(path))
    if not isinstance(data, dict):
        raise CalibrationError(f"{path}: expected a YAML mapping")
    cam = _parse_euroc(data, str(path))
    if "T_BS" not in data:
        raise CalibrationError(f"{path}: missing key 'T_BS'")
    T = np.array(_number_list(data["T_BS"], "T_BS", str(path)))
    if T.size != 16:
        raise CalibrationError(f"{path}: key 'T_BS' must have 16 values, got {T.size}")
    T = T.reshape(4, 4)
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or not np.allclose(T[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{path}: key 'T_BS' is not a rigid transform")
    return cam, T


def load_camera(path: str | Path, image_size: ImageSize = None, kitti_row: str = "P0") -> PinholeCamera:
    """Read a camera file of any supported format (see module docstring).

    Parameters
    ----------
    path : camera file.
    image_size : ``(width, height)`` in pixels, or a callable returning it; used only for
        formats without the size (KITTI ``calib.txt``, ORB-SLAM2 YAML).
    kitti_row : projection row of a KITTI ``calib.txt`` (``P0`` or ``P2``).

    Raises
    ------
    CalibrationError
        Missing file, unknown format, missing key, non-numeric or impossible value.
    """
    path = Path(path)
    text = _read_text(path)
    if path.suffix == ".camera":
        return parse_strecha_camera(text, str(path)).camera
    if _is_kitti(text):
        return parse_kitti_calib(text, str(path), kitti_row, image_size)[0]
    return parse_camera_yaml(text, str(path), image_size)


def write_camera_yaml(path: str | Path, camera: PinholeCamera) -> None:
    """Write ``camera`` as an eifslam ``camera.yaml``."""
    dist = ", ".join(repr(float(d)) for d in camera.distortion)
    Path(path).write_text(
        "# pinhole intrinsics in pixels; image origin top-left, pixel centres at integers\n"
        f"model: pinhole\nwidth: {int(camera.width)}\nheight: {int(camera.height)}\n"
        f"fx: {float(camera.fx)!r}\nfy: {float(camera.fy)!r}\n"
        f"cx: {float(camera.cx)!r}\ncy: {float(camera.cy)!r}\n"
        f"distortion: [{dist}]\n"
    )
