"""Image sequences as the loaders return them: a camera, lazy frames, ground truth apart.

Every loader (:mod:`.folder`, :mod:`.kitti`, :mod:`.tum_rgbd`, :mod:`.euroc`,
:mod:`.strecha`, :mod:`.video`, :mod:`.rosbag`) returns a :class:`Sequence`. Images are read only when
:meth:`Sequence.load` is called. Ground truth is *not* an attribute: it is returned by
:meth:`Sequence.ground_truth`, which is meant for scoring only; the estimator never needs
it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np
from numpy.typing import NDArray

from ..geometry.camera import PinholeCamera
from ..errors import DatasetError, ImageError
from .image_header import check_image_size
from .images import read_image
from .trajectory import Trajectory

__all__ = ["Frame", "Sequence", "VideoSequence"]


@dataclass(frozen=True)
class Frame:
    """One frame of a sequence.

    Attributes
    ----------
    index : int
        Position in the sequence, 0-based.
    timestamp : float
        Seconds (data set clock; the frame index when the data set has no times).
    path : Path or None
        Image file; ``None`` for video frames and ROS bag messages.
    video_index : int or None
        Frame number inside the video file, or message number on the ROS bag topic (in
        bag order); ``None`` for image files.
    """

    index: int
    timestamp: float
    path: Path | None = None
    video_index: int | None = None

    @property
    def name(self) -> str:
        """Short label for messages: the file name, or ``frame N`` of a video or bag topic."""
        return self.path.name if self.path is not None else f"frame {self.video_index}"


class Sequence:
    """An ordered list of frames seen by one calibrated camera.

    Parameters
    ----------
    name : str
        Label (usually the folder name).
    root : Path
        The folder or file the sequence was opened from.
    camera : PinholeCamera
        Intrinsics of every frame (pixels).
    frames : list of Frame
        In time order, timestamps strictly increasing.
    kind : str
        Layout it was read from: ``folder``, ``kitti``, ``tum``, ``euroc``, ``strecha``,
        ``video``, ``rosbag``.
    ground_truth_loader : callable returning Trajectory or None, optional
        Called (once) by :meth:`ground_truth`.
    check_size : bool
        Raise :class:`ImageError` when a loaded image's size differs from the camera's.
    """

    def __init__(
        self,
        name: str,
        root: Path,
        camera: PinholeCamera,
        frames: list[Frame],
        kind: str,
        ground_truth_loader: Callable[[], Trajectory | None] | None = None,
        check_size: bool = True,
    ) -> None:
        if not frames:
            raise DatasetError(f"{root}: sequence has no frames")
        ts = np.array([f.timestamp for f in frames], dtype=np.float64)
        if not np.all(np.isfinite(ts)):
            raise DatasetError(f"{root}: non-finite frame timestamp")
        bad = np.nonzero(np.diff(ts) <= 0)[0]
        if len(bad):
            k = int(bad[0]) + 1
            raise DatasetError(
                f"{root}: frame timestamps must increase strictly "
                f"({frames[k].name} at t={ts[k]!r} follows t={ts[k - 1]!r})"
            )
        # the camera's image size against the memory budget, before any image is read
        check_image_size(int(camera.width), int(camera.height), str(root))
        self.name = name
        self.root = Path(root)
        self.camera = camera
        self.frames: tuple[Frame, ...] = tuple(frames)
        self.kind = kind
        self._gt_loader = ground_truth_loader
        self._gt_cache: tuple[Trajectory | None] | None = None
        self._check_size = check_size

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(kind={self.kind!r}, name={self.name!r}, "
            f"frames={len(self)}, camera={self.camera.width}x{self.camera.height})"
        )

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self.frames[i]

    def __iter__(self) -> Iterator[Frame]:
        return iter(self.frames)

    @property
    def timestamps(self) -> NDArray[np.float64]:
        """(N,) frame timestamps in seconds."""
        return np.array([f.timestamp for f in self.frames], dtype=np.float64)

    def load(self, i: int, grayscale: bool = False) -> NDArray[np.uint8]:
        """Image of frame ``i``: (H, W) uint8 grey or (H, W, 3) uint8 BGR.

        Raises
        ------
        ImageError
            The image is missing, corrupt or not of the camera's size (names the file).
        """
        frame = self.frames[i]
        img = self._read(frame, grayscale)
        if self._check_size and (img.shape[1], img.shape[0]) != (
            self.camera.width,
            self.camera.height,
        ):
            where = frame.path if frame.path is not None else f"{self.root} {frame.name}"
            raise ImageError(
                f"{where}: image is {img.shape[1]}x{img.shape[0]} but the camera is "
                f"{self.camera.width}x{self.camera.height}"
            )
        return img

    def images(self, grayscale: bool = False) -> Iterator[tuple[Frame, NDArray[np.uint8]]]:
        """Yield ``(frame, image)`` for every frame in order, reading lazily."""
        for i, frame in enumerate(self.frames):
            yield frame, self.load(i, grayscale)

    def ground_truth(self) -> Trajectory | None:
        """Ground-truth camera-to-world poses for scoring, or ``None`` when there is none.

        The poses are given at the timestamps of the frames that have one (a subset of
        :attr:`timestamps`), in the data set's world frame and units.

        Raises
        ------
        DatasetError
            The ground-truth file is malformed (names the file).
        """
        if self._gt_cache is None:
            self._gt_cache = (self._gt_loader() if self._gt_loader is not None else None,)
        return self._gt_cache[0]

    @property
    def has_ground_truth(self) -> bool:
        """True when a ground-truth source exists (the file is not parsed)."""
        return self._gt_loader is not None

    def _read(self, frame: Frame, grayscale: bool) -> NDArray[np.uint8]:
        if frame.path is None:
            raise ImageError(f"{self.root}: {frame.name} has no image file")
        return read_image(frame.path, grayscale)


class VideoSequence(Sequence):
    """A sequence whose frames are decoded from a video file with ``cv2.VideoCapture``.

    Frames are decoded in order, never by seeking (seeking lands on the nearest key frame
    for many codecs, and on the wrong frame after a corrupt stretch): a jump forward
    decodes the frames in between, a jump back re-opens the file. A frame that does not
    decode raises :class:`ImageError` and the next one is decoded after it, so a corrupt
    middle costs only its own frames.
    """

    def __init__(self, *args, **kwargs) -> None:  # same parameters as Sequence
        super().__init__(*args, **kwargs)
        self._cap = None
        self._next = 0

    def close(self) -> None:
        """Release the video file."""
        if self._cap is not None:
            self._cap.release()
            self._cap = None

    def __del__(self) -> None:
        self.close()

    def _read(self, frame: Frame, grayscale: bool) -> NDArray[np.uint8]:
        import cv2

        if self._cap is None:
            self._cap = cv2.VideoCapture(str(self.root))
            self._next = 0
            if not self._cap.isOpened():
                self._cap = None
                raise ImageError(f"{self.root}: cannot open video file")
        k = int(frame.video_index if frame.video_index is not None else frame.index)
        if k < self._next:  # back: start again
            self.close()
            return self._read(frame, grayscale)
        while self._next < k:  # forward: decode (not seek) the frames in between
            self._cap.grab()
            self._next += 1
        ok, img = self._cap.read()
        self._next = k + 1  # a failed frame is consumed too: the next one follows it
        if not ok or img is None:
            raise ImageError(f"{self.root}: cannot decode video frame {k}")
        if grayscale and img.ndim == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        return img
