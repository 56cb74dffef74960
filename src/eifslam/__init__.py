"""eifslam: monocular SLAM with an exactly sparse Extended Information Filter.

Implements Wang & Dissanayake, "Efficient Monocular SLAM using sparse information
filters" (ICIAfS 2010). The mathematical core (geometry, camera, observation models,
information filter, recovery, smoothing, synthetic scenes, evaluation) is pure
NumPy/SciPy; OpenCV and matplotlib are used only by the front end, loaders and plots.

The names a user needs first are here, imported on first use (so that ``import
eifslam.geometry`` stays free of OpenCV)::

    from eifslam import Slam, SlamConfig, load_camera, open_source
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "Slam": "eifslam.system.slam",
    "SlamConfig": "eifslam.system.config",
    "TrackResult": "eifslam.system.slam",
    "TrackingState": "eifslam.system.slam",
    "PinholeCamera": "eifslam.geometry.camera",
    "load_camera": "eifslam.io.cameras",
    "open_source": "eifslam.io.detect",
    "Trajectory": "eifslam.io.trajectory",
    "read_tum": "eifslam.io.trajectory",
    "write_tum": "eifslam.io.trajectory",
    "EifslamError": "eifslam.errors",
}

__all__ = ["__version__", *sorted(_EXPORTS)]


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
