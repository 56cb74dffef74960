"""Sessions: a whole :class:`~eifslam.system.slam.Slam` saved to a file and loaded back.

The file is an ``.npz`` archive (a zip of ``.npy`` arrays) that holds nothing but data:

* ``session.json.npy``: a ``uint8`` array, the UTF-8 JSON document
  ``{"format": "eifslam-session", "version": SESSION_VERSION, "eifslam_version", "camera",
  "config", "results", "waiting", "filter", "frontend", "tracker", "mapper"}``, where every
  array is a reference ``{"$array": NAME}`` to the member ``NAME.npy``;
* one member per array (numbers, booleans and descriptors only; no object arrays).

Each part says what it keeps (``state_dict()``) and takes it back checked
(``load_state_dict(d)``): the filter (layout, estimate, ``I`` as CSC arrays, ``i``,
priors, stored measurements; the incremental window is rebuilt from ``I`` at the next
frame), the front end (keypoints, descriptors, tracks), the tracker, the mapper, the
keyframe step (the frames localised on the map between keyframes) and the loop closer
(vocabulary, bag-of-words index, loops found).
Loading never unpickles (``np.load(..., allow_pickle=False)``) and never trusts a size:
each member's header is read first and its declared shape checked against the bytes it
holds. A foreign, truncated or crafted file, or one of another version, gives one
:class:`~eifslam.errors.SessionError` line naming the file.
"""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping

import numpy as np

from ..errors import EifslamError, SessionError
from ..estimation.statedict import sub, take, take_float, take_ids, take_int

if TYPE_CHECKING:
    from .slam import Slam, TrackResult

__all__ = ["SESSION_FORMAT", "SESSION_VERSION", "save_session", "load_session"]

#: The ``format`` field of a session's JSON document.
SESSION_FORMAT = "eifslam-session"
#: Version of the session file format (3: npz + JSON, no pickle).
SESSION_VERSION = 3

_JSON = "session.json"
_DTYPES = {np.dtype(t) for t in (bool, np.int8, np.uint8, np.int64, np.float32, np.float64)}
_MAX_JSON_BYTES = 1 << 28
_MAX_DEPTH = 12


# -- save -------------------------------------------------------------------------------
def save_session(slam: "Slam", path: str | Path) -> None:
    """Save a session to ``path`` (an ``.npz`` file; written to a temporary file first).

    Raises
    ------
    EifslamError
        When the file cannot be written, or the system has a front end or back end other
        than eifslam's OpenCV :class:`~eifslam.frontend.FrontEnd` and
        :class:`~eifslam.estimation.filter.InformationFilter`.
    """
    from .. import __version__
    from ..estimation.filter import InformationFilter
    from ..frontend.frontend import FrontEnd

    for part, cls in ((slam.frontend, FrontEnd), (slam.filter, InformationFilter)):
        if type(part) is not cls:
            raise EifslamError(f"cannot save session to {path}: a {type(part).__name__} does not save "
                               f"(sessions hold the OpenCV front end and the information filter)")
    slam.filter.complete_estimate()  # every state at the solution before it is saved
    c = slam.camera
    state = {
        "format": SESSION_FORMAT, "version": SESSION_VERSION, "eifslam_version": __version__,
        "camera": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": int(c.width), "height": int(c.height),
                   "distortion": [float(v) for v in c.distortion]},
        "config": slam.config.to_dict(),
        "results": _pack_results(slam.results),
        "waiting": slam.waiting,
        "filter": slam.filter.state_dict(),
        "frontend": slam.frontend.state_dict(),
        "tracker": slam.tracker.state_dict(),
        "mapper": slam.mapper.state_dict(),
        "keyframes": slam.keyframes.state_dict(),
        "loops": slam.loops.state_dict(),
    }
    arrays: dict[str, np.ndarray] = {}
    doc = _split(state, "", arrays)
    arrays[_JSON] = np.frombuffer(json.dumps(doc, allow_nan=False).encode(), np.uint8)
    path = Path(path)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, **arrays)
        os.replace(tmp, path)
        tmp = None
    except (OSError, ValueError) as exc:
        raise EifslamError(f"cannot save session to {path}: {exc}") from exc
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)


def _split(v: Any, name: str, arrays: dict[str, np.ndarray]) -> Any:
    """The JSON document of a state: arrays moved to ``arrays`` and referenced by name."""
    if isinstance(v, np.ndarray):
        arrays[name] = np.ascontiguousarray(v)
        return {"$array": name}
    if isinstance(v, dict):
        return {str(k): _split(x, f"{name}.{k}" if name else str(k), arrays) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_split(x, f"{name}.{i}", arrays) for i, x in enumerate(v)]
    if isinstance(v, (np.integer, np.floating, np.bool_)):
        return v.item()
    return v


def _pack_results(results: "list[TrackResult]") -> dict:
    n = len(results)
    pos = np.zeros((n, 3))
    quat = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    cov = np.zeros((n, 6, 6))
    for k, r in enumerate(results):
        if r.position is not None:
            pos[k], quat[k] = r.position, r.quat_wxyz
        if r.covariance is not None:
            cov[k] = r.covariance
    return {
        "frame_id": np.array([r.frame_id for r in results], np.int64),
        "timestamp": np.array([r.timestamp for r in results], float),
        "state": [r.state.value for r in results],
        "reason": [r.reason for r in results],
        "has_pose": np.array([r.position is not None for r in results], bool),
        "position": pos, "quat_wxyz": quat,
        "has_covariance": np.array([r.covariance is not None for r in results], bool),
        "covariance": cov,
        "reference": np.array([-1 if r.reference is None else r.reference for r in results], np.int64),
        "timings_ms": [{k: float(v) for k, v in r.timings_ms.items()} for r in results],
        "map_features": np.array([r.map_features for r in results], np.int64),
        "state_dim": np.array([r.state_dim for r in results], np.int64),
        "keyframe": np.array([r.keyframe for r in results], bool),
    }


# -- load -------------------------------------------------------------------------------
def load_session(path: str | Path, make: Callable[..., "Slam"]) -> "Slam":
    """Load a session saved by :func:`save_session`.

    Parameters
    ----------
    path : str or Path
    make : callable
        ``(camera, config) -> Slam``: the system to restore into (``Slam`` itself; passed
        in, so that this module never imports the one that uses it).

    Raises
    ------
    SessionError
        One line naming the file when it cannot be read, is not an eifslam session
        (a pickle, random bytes, another zip), is truncated or inconsistent, or is of
        another version.
    """
    try:
        doc, arrays = _read(Path(path))
        return _build(_join(doc, arrays, 0), make)
    except SessionError as exc:
        raise SessionError(_one_line(f"{path}: not a usable eifslam session: {exc}")) from None
    except EifslamError as exc:  # a config or camera in the file that this eifslam refuses
        raise SessionError(_one_line(f"{path}: {exc}")) from None
    except (OSError, EOFError, ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError,
            MemoryError, RecursionError, zipfile.BadZipFile, NotImplementedError) as exc:
        raise SessionError(_one_line(f"cannot load session {path}: {type(exc).__name__}: {exc}")) from None


def _one_line(msg: str) -> str:
    return " ".join(msg.split())


def _read(path: Path) -> tuple[Any, dict[str, np.ndarray]]:
    """The JSON document and the arrays of a session file, every member checked before
    it is read."""
    if not path.is_file():
        raise OSError(f"no such file: {path}")
    if not zipfile.is_zipfile(path):
        raise SessionError("not an npz/zip archive (pickled sessions of earlier eifslam versions are refused)")
    with zipfile.ZipFile(path) as zf:
        infos = zf.infolist()
        if f"{_JSON}.npy" not in {i.filename for i in infos}:
            raise SessionError(f"no {_JSON} member")
        for info in infos:
            _check_member(zf, info)
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    raw = arrays.pop(_JSON)
    if raw.dtype != np.uint8 or raw.ndim != 1 or raw.size > _MAX_JSON_BYTES:
        raise SessionError(f"member {_JSON} is not a UTF-8 byte string")
    doc = json.loads(raw.tobytes().decode("utf-8"))
    if not isinstance(doc, dict) or doc.get("format") != SESSION_FORMAT:
        raise SessionError(f"its JSON document is not of format {SESSION_FORMAT!r}")
    if doc.get("version") != SESSION_VERSION:
        raise SessionError(f"a session of version {doc.get('version')!r}; this eifslam reads version "
                           f"{SESSION_VERSION} only (run the sequence again)")
    return doc, arrays


def _check_member(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> None:
    """A member is a plain ``.npy`` of an allowed dtype whose declared size fits its bytes."""
    name = info.filename
    if not name.endswith(".npy") or info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        raise SessionError(f"unexpected member {name!r}")
    with zf.open(info) as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise SessionError(f"member {name!r} is an npy file of version {version}")
    if dtype not in _DTYPES:
        raise SessionError(f"member {name!r} has dtype {dtype}")
    nbytes = int(np.prod([int(s) for s in shape], dtype=object)) * dtype.itemsize if shape else dtype.itemsize
    if nbytes > info.file_size:
        raise SessionError(f"member {name!r} declares shape {tuple(shape)} but holds {info.file_size} bytes")


def _join(v: Any, arrays: Mapping[str, np.ndarray], depth: int) -> Any:
    """Put the arrays back where the JSON document references them."""
    if depth > _MAX_DEPTH:
        raise SessionError("its JSON document is nested too deeply")
    if isinstance(v, dict):
        if set(v) == {"$array"}:
            a = arrays.get(v["$array"]) if isinstance(v["$array"], str) else None
            if a is None:
                raise SessionError(f"array {v['$array']!r} is referenced but not stored")
            return a
        return {k: _join(x, arrays, depth + 1) for k, x in v.items()}
    if isinstance(v, list):
        return [_join(x, arrays, depth + 1) for x in v]
    return v


def _build(doc: Mapping[str, Any], make: Callable[..., "Slam"]) -> "Slam":
    from ..geometry.camera import PinholeCamera
    from .config import SlamConfig

    cam = sub(doc, "camera")
    dist = cam.get("distortion")
    if not (isinstance(dist, list) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in dist)):
        raise SessionError("entry 'distortion' must be a list of numbers")
    camera = PinholeCamera(take_float(cam, "fx"), take_float(cam, "fy"), take_float(cam, "cx"),
                           take_float(cam, "cy"), take_int(cam, "width", 1), take_int(cam, "height", 1),
                           tuple(float(v) for v in dist))
    cfg = sub(doc, "config")
    if not all(isinstance(v, Mapping) for v in cfg.values()):
        raise SessionError("entry 'config' must map sections to settings")
    slam = make(camera, SlamConfig.from_dict(cfg))
    results = _unpack_results(sub(doc, "results"))
    slam.filter.load_state_dict(sub(doc, "filter"))
    slam.frontend.load_state_dict(sub(doc, "frontend"))
    slam.tracker.load_state_dict(sub(doc, "tracker"))
    slam.mapper.load_state_dict(sub(doc, "mapper"))
    slam.keyframes.load_state_dict(sub(doc, "keyframes"))
    if "loops" in doc:  # sessions saved before loop closure keep none
        slam.loops.load_state_dict(sub(doc, "loops"))
    n = len(results)
    frames, poses = np.array(slam.frontend.frame_ids, np.int64), np.array(slam.filter.layout.pose_ids, np.int64)
    waiting = doc.get("waiting")
    if not (isinstance(waiting, list) and all(isinstance(j, int) and not isinstance(j, bool) for j in waiting)):
        raise SessionError("entry 'waiting' must be a list of frame ids")
    between = np.array(slam.keyframes.poses()[0], np.int64)
    for what, ids in (("front end", frames), ("filter", poses), ("waiting", np.array(waiting, np.int64)),
                      ("keyframe step", between)):
        if ids.size and (ids.min() < 0 or ids.max() >= n):
            raise SessionError(f"the {what} holds a frame the results do not")
    if not np.all(np.isin(poses, frames)):
        raise SessionError("the filter holds a pose whose frame the front end does not")
    slam.restore(results, waiting)
    return slam


def _unpack_results(d: Mapping[str, Any]) -> "list[TrackResult]":
    from .results import TrackingState, TrackResult

    fid = take_ids(d, "frame_id")
    n = len(fid)
    if not np.array_equal(fid, np.arange(n)):
        raise SessionError("results are not one per frame in order")
    ts = take(d, "timestamp", np.float64, (n,))
    has_pose, has_cov = take(d, "has_pose", bool, (n,)), take(d, "has_covariance", bool, (n,))
    pos, quat = take(d, "position", np.float64, (n, 3)), take(d, "quat_wxyz", np.float64, (n, 4))
    cov = take(d, "covariance", np.float64, (n, 6, 6))
    ref, mf, sd = take_ids(d, "reference", n, -1), take_ids(d, "map_features", n), take_ids(d, "state_dim", n)
    kf = take(d, "keyframe", bool, (n,))
    lists = {k: d.get(k) for k in ("state", "reason", "timings_ms")}
    if not all(isinstance(v, list) and len(v) == n for v in lists.values()):
        raise SessionError("results 'state', 'reason' and 'timings_ms' must be lists, one per frame")
    states = {s.value: s for s in TrackingState}
    out = []
    for k in range(n):
        st, reason, tm = lists["state"][k], lists["reason"][k], lists["timings_ms"][k]
        if st not in states or not isinstance(reason, str) or not isinstance(tm, dict) or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) for v in tm.values()):
            raise SessionError(f"result of frame {k} is malformed")
        out.append(TrackResult(k, float(ts[k]), states[st], pos[k].copy() if has_pose[k] else None,
                               quat[k].copy() if has_pose[k] else None, cov[k].copy() if has_cov[k] else None,
                               reason, None if ref[k] < 0 else int(ref[k]), {str(a): float(b) for a, b in tm.items()},
                               int(mf[k]), int(sd[k]), bool(kf[k])))
    return out
