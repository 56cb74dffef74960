"""Data in, results out: data set loaders, camera files, trajectories, point clouds.

Names are imported lazily so that ``eifslam.io.trajectory`` (pure NumPy) can be used
without importing OpenCV. Main entry points:

* :func:`open_source` (``path, camera=None, topic=None -> Sequence``): any supported
  layout, ROS bags included;
* :func:`load_camera`: any supported camera file;
* :func:`read_tum` / :func:`write_tum`, :class:`Trajectory`;
* :func:`write_ply` / :func:`read_ply`.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "open_source": "detect",
    "detect_layout": "detect",
    "Sequence": "sequence",
    "VideoSequence": "sequence",
    "Frame": "sequence",
    "load_camera": "cameras",
    "write_camera_yaml": "cameras",
    "read_image": "images",
    "open_folder": "folder",
    "open_kitti": "kitti",
    "open_tum_rgbd": "tum_rgbd",
    "open_euroc": "euroc",
    "open_strecha": "strecha",
    "open_video": "video",
    "open_rosbag": "rosbag",
    "Trajectory": "trajectory",
    "read_tum": "trajectory",
    "write_tum": "trajectory",
    "associate": "trajectory",
    "write_ply": "ply",
    "read_ply": "ply",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        module = importlib.import_module(f".{_EXPORTS[name]}", __name__)
        return getattr(module, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return __all__
