"""Video files (mp4, avi, ...) decoded with ``cv2.VideoCapture``, plus a camera file.

The camera comes from the ``camera`` argument, else from ``<stem>.yaml`` or
``camera.yaml`` next to the video. Frame ``k`` has timestamp ``k / fps`` (seconds; the
frame index when the file reports no frame rate). A video whose middle is corrupt keeps
every frame that decodes: the undecodable ones are skipped (each with a one-line
message) and decoding goes on after them. Optional ground truth: ``<stem>.tum``
or ``groundtruth.tum`` next to the video, associated with the frame times.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..geometry.camera import PinholeCamera
from ..errors import DatasetError
from .cameras import load_camera
from .folder import ground_truth_at_frames
from .sequence import Frame, VideoSequence
from .trajectory import Trajectory, read_tum

__all__ = ["open_video", "VIDEO_EXTENSIONS"]

#: file name endings recognised as videos (lower case)
VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm")


#: undecodable frames in a row after which a video is taken to have ended
MAX_BAD_RUN = 250


def _count_frames(cap) -> int:
    """Frames of an open capture, counted by decoding from the start: a frame that fails
    (a corrupt middle) is counted and decoding goes on, so every decodable frame after it
    is kept; :data:`MAX_BAD_RUN` failures in a row end the count at the last good frame."""
    import cv2

    cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
    k = bad_run = 0
    last_good = -1
    while bad_run < MAX_BAD_RUN:
        if cap.grab():
            last_good, bad_run = k, 0
        else:
            bad_run += 1
        k += 1
    return last_good + 1


def _probe(path: Path) -> tuple[int, float, tuple[int, int]]:
    """Frame count, frame rate (0 if unknown) and (width, height) of a video."""
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise DatasetError(f"{path}: cannot open video file")
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        # CAP_PROP_FRAME_COUNT is an estimate for some containers: trust it only when the
        # last frame it promises decodes and no frame follows; else count by grabbing
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        if n > 0:
            cap.set(cv2.CAP_PROP_POS_FRAMES, n - 1)
            if not (cap.grab() and not cap.grab()):
                n = 0
        if n <= 0:
            n = _count_frames(cap)
    finally:
        cap.release()
    if n == 0:
        raise DatasetError(f"{path}: video has no decodable frames")
    if not np.isfinite(fps) or fps <= 0 or fps > 1e4:
        fps = 0.0
    return n, fps, size


def open_video(
    path: str | Path, camera: PinholeCamera | str | Path | None = None
) -> VideoSequence:
    """Open a video file as a sequence (module docstring).

    Returns
    -------
    VideoSequence of kind ``"video"``; frames have ``path=None`` and ``video_index``.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: video file not found")
    n, fps, size = _probe(path)
    if isinstance(camera, PinholeCamera):
        cam = camera
    else:
        cands = [Path(camera)] if camera is not None else [
            path.with_suffix(".yaml"), path.parent / "camera.yaml"
        ]
        found = next((c for c in cands if c.is_file()), None)
        if found is None:
            raise DatasetError(
                f"{path}: no camera file ({', '.join(c.name for c in cands)}); pass one"
            )
        cam = load_camera(found, image_size=size)
    times = np.arange(n, dtype=np.float64) / (fps if fps > 0 else 1.0)
    frames = [Frame(k, float(t), video_index=k) for k, t in enumerate(times)]
    gt_file = next(
        (c for c in (path.with_suffix(".tum"), path.parent / "groundtruth.tum") if c.is_file()),
        None,
    )
    loader = None
    if gt_file is not None:
        def loader() -> Trajectory:
            return ground_truth_at_frames(read_tum(gt_file), times)
    return VideoSequence(path.stem, path, cam, frames, "video", loader)
