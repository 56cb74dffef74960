"""The size an image file claims, read from its header without decoding it.

A file may claim any size: a PNG of a few hundred bytes can say 100000 x 100000 pixels,
and decoding it would ask for 30 GB. :func:`check_image_size` reads the header (PNG,
JPEG, BMP, PNM, WebP, TIFF) and refuses an image over the memory budget
:data:`MAX_IMAGE_PIXELS` *before* OpenCV is asked to decode it. eifslam does not
downscale large images (the intrinsics would have to follow); it refuses them with a
one-line error, and the user resizes the images and the camera file together.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path
from typing import BinaryIO

from ..errors import ImageError

__all__ = ["MAX_IMAGE_PIXELS", "MAX_IMAGE_SIDE", "header_size", "encoded_size", "check_image_size"]

#: largest image accepted, in pixels (width x height): 40 megapixels, i.e. 120 MB as
#: 8-bit BGR before the front end's own buffers (a 7000 x 5000 camera still fits)
MAX_IMAGE_PIXELS = 40_000_000
#: largest accepted width or height, pixels
MAX_IMAGE_SIDE = 20_000


#: bytes of a JPEG searched for its frame header (it follows the EXIF/ICC segments)
_JPEG_SCAN_BYTES = 4_000_000


def _png(h: bytes) -> tuple[int, int] | None:
    if h[:8] == b"\x89PNG\r\n\x1a\n" and h[12:16] == b"IHDR":
        return struct.unpack(">II", h[16:24])
    return None


def _bmp(h: bytes) -> tuple[int, int] | None:
    if h[:2] == b"BM" and len(h) >= 26:
        w, hh = struct.unpack("<ii", h[18:26])
        return abs(w), abs(hh)
    return None


def _pnm(h: bytes) -> tuple[int, int] | None:
    if len(h) < 3 or h[0:1] != b"P" or h[1:2] not in b"123456":
        return None
    nums: list[int] = []
    for line in h[2:].split(b"\n"):
        for tok in line.split(b"#")[0].split():
            if not tok.isdigit():
                return None
            nums.append(int(tok))
            if len(nums) == 2:
                return nums[0], nums[1]
    return None


def _webp(h: bytes) -> tuple[int, int] | None:
    if h[:4] != b"RIFF" or h[8:12] != b"WEBP":
        return None
    kind = h[12:16]
    if kind == b"VP8X":
        return 1 + int.from_bytes(h[24:27], "little"), 1 + int.from_bytes(h[27:30], "little")
    if kind == b"VP8L" and len(h) >= 25:
        b = int.from_bytes(h[21:25], "little")
        return 1 + (b & 0x3FFF), 1 + ((b >> 14) & 0x3FFF)
    if kind == b"VP8 " and len(h) >= 30:
        w, hh = struct.unpack("<HH", h[26:30])
        return w & 0x3FFF, hh & 0x3FFF
    return None


def _jpeg(fh) -> tuple[int, int] | None:
    fh.seek(2)
    for _ in range(10_000):  # markers before the frame header; bounded
        if fh.tell() > _JPEG_SCAN_BYTES:  # no frame header near the start: let OpenCV say
            return None
        b = fh.read(1)
        while b and b != b"\xff" and fh.tell() <= _JPEG_SCAN_BYTES:
            b = fh.read(1)
        while b == b"\xff":
            b = fh.read(1)
        if not b:
            return None
        marker = b[0]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            continue
        seg = fh.read(2)
        if len(seg) < 2:
            return None
        length = struct.unpack(">H", seg)[0]
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            body = fh.read(5)
            if len(body) < 5:
                return None
            hh, w = struct.unpack(">HH", body[1:5])
            return w, hh
        fh.seek(max(length - 2, 0), 1)
    return None


def _tiff(fh, h: bytes) -> tuple[int, int] | None:
    end = {b"II": "<", b"MM": ">"}.get(h[:2])
    if end is None or struct.unpack(end + "H", h[2:4])[0] != 42:
        return None
    fh.seek(struct.unpack(end + "I", h[4:8])[0])
    raw = fh.read(2)
    if len(raw) < 2:
        return None
    size: dict[int, int] = {}
    for _ in range(min(struct.unpack(end + "H", raw)[0], 4096)):
        entry = fh.read(12)
        if len(entry) < 12:
            break
        tag, typ = struct.unpack(end + "HH", entry[:4])
        if tag in (256, 257):
            size[tag] = (struct.unpack(end + "H", entry[8:10])[0] if typ == 3
                         else struct.unpack(end + "I", entry[8:12])[0])
    return (size[256], size[257]) if len(size) == 2 else None


def header_size(path: str | Path) -> tuple[int, int] | None:
    """``(width, height)`` in pixels that the image file's header claims.

    Returns
    -------
    tuple of int, or None
        None for a format not parsed here or a header too short to say.

    Raises
    ------
    ImageError
        The file cannot be opened (names it).
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return _header_size(fh)
    except OSError as exc:
        raise ImageError(f"{path}: cannot read image ({exc.strerror or exc})") from None


def encoded_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` that the header of an encoded image in memory claims (the
    bytes of a PNG or JPEG file, as a ``sensor_msgs/CompressedImage`` holds them); None
    as :func:`header_size`."""
    return _header_size(io.BytesIO(data))


def _header_size(fh: BinaryIO) -> tuple[int, int] | None:
    try:
        h = fh.read(64)
        for parse in (_png, _bmp, _pnm, _webp):
            size = parse(h)
            if size is not None:
                return int(size[0]), int(size[1])
        if h[:2] == b"\xff\xd8":
            return _jpeg(fh)
        if h[:2] in (b"II", b"MM"):
            return _tiff(fh, h)
    except struct.error:
        return None
    return None


def check_image_size(width: int, height: int, where: str) -> None:
    """Refuse an image of ``width`` x ``height`` pixels over the memory budget.

    Raises
    ------
    ImageError
        Over :data:`MAX_IMAGE_PIXELS` or :data:`MAX_IMAGE_SIDE`, or not positive; the
        message starts with ``where`` (the file).
    """
    if width <= 0 or height <= 0:
        raise ImageError(f"{where}: image claims an impossible size {width}x{height}")
    if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE or width * height > MAX_IMAGE_PIXELS:
        raise ImageError(
            f"{where}: image is {width}x{height} pixels, over the limit of "
            f"{MAX_IMAGE_PIXELS // 1_000_000} megapixels ({MAX_IMAGE_SIDE} per side); "
            "resize the images and the camera file together"
        )
