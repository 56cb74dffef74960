"""Open any supported data source: :func:`open_source` sniffs the layout."""

from __future__ import annotations

from pathlib import Path

from ..geometry.camera import PinholeCamera
from ..errors import DatasetError
from .images import IMAGE_EXTENSIONS
from .sequence import Sequence

__all__ = ["detect_layout", "open_source"]


def detect_layout(path: str | Path) -> str:
    """Name of the layout at ``path``.

    Checked in this order: ``video`` (a file with a video extension), ``euroc``
    (``mav0/cam0/data.csv``), ``tum`` (``rgb.txt``), ``kitti`` (``calib.txt`` and
    ``image_0``/``image_2``), ``folder`` (``images/`` and ``camera.yaml``), ``strecha``
    (images with ``.camera`` files), ``folder`` (``images/`` or images in the folder).

    Raises
    ------
    DatasetError
        Nothing recognisable at ``path``.
    """
    from .euroc import find_mav0
    from .kitti import is_kitti
    from .strecha import find_strecha
    from .video import VIDEO_EXTENSIONS

    p = Path(path)
    if p.is_file():
        if p.suffix.lower() in VIDEO_EXTENSIONS:
            return "video"
        raise DatasetError(f"{p}: not a video file ({', '.join(VIDEO_EXTENSIONS)}) or a folder")
    if not p.is_dir():
        raise DatasetError(f"{p}: no such file or folder")
    if find_mav0(p) is not None:
        return "euroc"
    if (p / "rgb.txt").is_file():
        return "tum"
    if is_kitti(p):
        return "kitti"
    if (p / "images").is_dir() and (p / "camera.yaml").is_file():
        return "folder"
    if find_strecha(p):
        return "strecha"
    if (p / "images").is_dir():
        return "folder"
    if any(q.suffix.lower() in IMAGE_EXTENSIONS for q in p.iterdir()):
        return "folder"
    raise DatasetError(
        f"{p}: unrecognised layout (expected images/ + camera.yaml, KITTI, TUM RGB-D, "
        "EuRoC, Strecha or a video file)"
    )


def open_source(path: str | Path, camera: PinholeCamera | str | Path | None = None) -> Sequence:
    """Open a sequence from a folder or video file, detecting its layout.

    Parameters
    ----------
    path : data set folder or video file.
    camera : a :class:`PinholeCamera` or a camera file (any format of
        :func:`~eifslam.io.cameras.load_camera`) overriding the data set's own.

    Returns
    -------
    Sequence
        ``camera``, ``frames`` (lazy), ``load(i)``, ``ground_truth()``; see
        :class:`~eifslam.io.sequence.Sequence`.

    Raises
    ------
    DatasetError, CalibrationError
        Unrecognised layout or a missing / malformed file (names the file).
    """
    kind = detect_layout(path)
    p = Path(path)
    if kind == "video":
        from .video import open_video

        return open_video(p, camera)
    if kind == "euroc":
        from .euroc import open_euroc

        return open_euroc(p, camera)
    if kind == "tum":
        from .tum_rgbd import open_tum_rgbd

        return open_tum_rgbd(p, camera)
    if kind == "kitti":
        from .kitti import open_kitti

        return open_kitti(p, camera)
    if kind == "strecha":
        from .strecha import open_strecha

        return open_strecha(p, camera)
    from .folder import open_folder

    return open_folder(p, camera, "images" if (p / "images").is_dir() else ".")
