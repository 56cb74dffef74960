"""Reading images from disk with OpenCV, with one-line errors naming the file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from ..errors import DatasetError, ImageError
from .image_header import check_image_size, encoded_size, header_size

__all__ = ["IMAGE_EXTENSIONS", "read_image", "decode_image", "eight_bit", "image_size", "list_images"]

#: file name endings recognised as images (lower case)
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")


def read_image(path: str | Path, grayscale: bool = False) -> NDArray[np.uint8]:
    """Read an image file.

    Parameters
    ----------
    path : image file.
    grayscale : convert to one channel.

    Returns
    -------
    (H, W) uint8 for grey images or ``grayscale=True``; (H, W, 3) uint8 BGR otherwise.
    16-bit files keep the 8 highest bits their data uses (:func:`sensor_bits`: 12-bit
    camera data is shifted by 4, not 8).

    Raises
    ------
    ImageError
        The file is missing or cannot be decoded, or its header claims a size over the
        memory budget (:data:`~.image_header.MAX_IMAGE_PIXELS`; checked before decoding).
        The message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: image file not found")
    size = header_size(path)
    if size is not None:
        check_image_size(size[0], size[1], str(path))
    flags = (cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_ANYCOLOR) | cv2.IMREAD_ANYDEPTH
    img = cv2.imread(str(path), flags)
    if img is None or img.size == 0:
        raise ImageError(f"{path}: cannot decode image (corrupt or unsupported format)")
    check_image_size(img.shape[1], img.shape[0], str(path))  # formats without a parsed header
    return eight_bit(img)


def decode_image(data: bytes | NDArray[np.uint8], where: str, grayscale: bool = False) -> NDArray[np.uint8]:
    """Decode an encoded image held in memory (the bytes of a PNG, JPEG, ... file), as
    :func:`read_image` reads a file.

    Parameters
    ----------
    data : the encoded bytes.
    where : what the image is, for messages (a file, a message of a ROS bag).
    grayscale : convert to one channel.

    Returns
    -------
    As :func:`read_image`.

    Raises
    ------
    ImageError
        Empty or undecodable data, or a header claiming a size over the memory budget
        (checked before decoding); the message starts with ``where``.
    """
    buf = np.frombuffer(data, np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) \
        else np.ascontiguousarray(data, np.uint8).reshape(-1)
    if buf.size == 0:
        raise ImageError(f"{where}: empty image data")
    size = encoded_size(buf.tobytes())
    if size is not None:
        check_image_size(size[0], size[1], where)
    flags = (cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_ANYCOLOR) | cv2.IMREAD_ANYDEPTH
    img = cv2.imdecode(buf, flags)
    if img is None or img.size == 0:
        raise ImageError(f"{where}: cannot decode image (corrupt or unsupported format)")
    check_image_size(img.shape[1], img.shape[0], where)
    return eight_bit(img)


def eight_bit(img: NDArray) -> NDArray[np.uint8]:
    """An image as 8 bits per channel: 16-bit data keeps the 8 highest bits it uses
    (:func:`sensor_bits`), other depths are scaled to 0..255; uint8 is returned as is."""
    if img.dtype == np.uint16:
        return (img >> (sensor_bits(int(img.max())) - 8)).astype(np.uint8)
    if img.dtype != np.uint8:
        return cv2.convertScaleAbs(img, alpha=255.0 / max(float(img.max()), 1.0))
    return img


SENSOR_BITS = (8, 10, 12, 14, 16)
"""Bit depths of camera data stored in 16-bit files."""


def sensor_bits(top: int) -> int:
    """The bit depth of 16-bit image data whose largest value is ``top``: the smallest of
    :data:`SENSOR_BITS` that holds it. A 12-bit camera's frames (largest values 1024-4095)
    keep their 8 highest bits (``>> 4``); OpenCV's own 16-to-8-bit conversion (``>> 8``)
    would leave them 16 grey levels."""
    return next((b for b in SENSOR_BITS if top < (1 << b)), 16)


def image_size(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` in pixels of an image file (decodes it: EXIF orientation
    counts; the header's claim is checked against the budget first)."""
    img = read_image(path)
    return int(img.shape[1]), int(img.shape[0])


def list_images(folder: str | Path) -> list[Path]:
    """Image files directly inside ``folder``, sorted by file name.

    Raises
    ------
    DatasetError
        The folder does not exist or holds no image.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: image folder not found")
    files = sorted(
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS
    )
    if not files:
        raise DatasetError(f"{folder}: no image files ({', '.join(IMAGE_EXTENSIONS)})")
    return files
