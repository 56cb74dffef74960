"""Sessions: a whole :class:`~eifslam.system.slam.Slam` saved to a file and loaded back.

The file is a pickle of ``{"version": SESSION_VERSION, "slam": slam}``. Every object in
it pickles itself: the front end drops its OpenCV detector and matcher and recreates
them when loaded (``FrontEnd.__getstate__``/``__setstate__``), the filter its cached
factorisations. Files of an older version are refused (no compatibility patches).
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import EifslamError

if TYPE_CHECKING:
    from .slam import Slam

__all__ = ["SESSION_VERSION", "save_session", "load_session"]

#: Version of the session file format (2: the system split into tracking and mapping).
SESSION_VERSION = 2


def save_session(slam: "Slam", path: str | Path) -> None:
    """Save a session to ``path``.

    Raises
    ------
    EifslamError
        When the file cannot be written or the session does not pickle.
    """
    slam.filter.complete_estimate()  # every state at the solution before it is saved
    try:
        with open(path, "wb") as fh:
            pickle.dump({"version": SESSION_VERSION, "slam": slam}, fh, protocol=pickle.HIGHEST_PROTOCOL)
    except (OSError, TypeError, AttributeError, pickle.PicklingError) as exc:
        raise EifslamError(f"cannot save session to {path}: {exc}") from exc


def load_session(path: str | Path) -> "Slam":
    """Load a session saved by :func:`save_session`.

    Raises
    ------
    EifslamError
        When the file cannot be read, is not a session, or is of another version.
    """
    from .slam import Slam

    try:
        with open(path, "rb") as fh:
            blob = pickle.load(fh)
    except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError) as exc:
        raise EifslamError(f"cannot load session {path}: {exc}") from exc
    if not isinstance(blob, dict) or not isinstance(blob.get("slam"), Slam):
        raise EifslamError(f"{path} is not an eifslam session file")
    if blob.get("version") != SESSION_VERSION:
        raise EifslamError(f"{path} is a session of version {blob.get('version')}; this eifslam reads "
                           f"version {SESSION_VERSION} only (run the sequence again)")
    return blob["slam"]
