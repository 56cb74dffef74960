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

    Checked in this order: ``rosbag`` (a ``.bag`` file or a ROS 2 bag folder, see
    :func:`~.rosbag.find_bag`), ``video`` (a file with a video extension), ``euroc``
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
    from .rosbag import find_bag
    from .strecha import find_strecha
    from .video import VIDEO_EXTENSIONS

    p = Path(path)
    if find_bag(p) is not None:
        return "rosbag"
    if p.is_file():
        if p.suffix.lower() in VIDEO_EXTENSIONS:
            return "video"
        raise DatasetError(f"{p}: not a video file ({', '.join(VIDEO_EXTENSIONS)}), a ROS bag (.bag) "
                           "or a folder")
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
        "EuRoC, Strecha, a ROS 2 bag or a video file)"
    )


def open_source(path: str | Path, camera: PinholeCamera | str | Path | None = None,
                topic: str | None = None) -> Sequence:
    """Open a sequence from a folder, video file or ROS bag, detecting its layout.

    Parameters
    ----------
    path : data set folder, video file, ROS 1 ``.bag`` file or ROS 2 bag folder.
    camera : a :class:`PinholeCamera` or a camera file (any format of
        :func:`~eifslam.io.cameras.load_camera`) overriding the data set's own.
    topic : the image topic of a ROS bag (default: the bag's only image topic); only
        for bags.

    Returns
    -------
    Sequence
        ``camera``, ``frames`` (lazy), ``load(i)``, ``ground_truth()``; see
        :class:`~eifslam.io.sequence.Sequence`.

    Raises
    ------
    DatasetError, CalibrationError
        Unrecognised layout, a missing / malformed file (names the file), or a topic
        given for a source that is not a ROS bag.
    """
    kind = detect_layout(path)
    p = Path(path)
    if kind == "rosbag":
        from .rosbag import open_rosbag

        return open_rosbag(p, camera, topic)
    if topic is not None:
        raise DatasetError(f"{p}: not a ROS bag; a topic ({topic}) applies to ROS bags only")
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
