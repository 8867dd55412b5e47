"""Images as features see them: (H, W) uint8 gray arrays, read from files, bytes or arrays.

One reader for every path an image takes (map images, query files, uploaded bytes, live
frames, stream frames): :func:`read_gray` (a file), :func:`decode_gray` (JPEG/PNG bytes) and
:func:`to_gray` (an array); :func:`read_bgr` for pictures of them. :func:`image_size_from_header`
reads the size of a PNG or JPEG from its first bytes without decoding it (cheap checks before any
work). Every error is an :class:`~planarloc.geometry.validation.InputError` naming the image.

- **Pixels as stored.** EXIF orientation is ignored (OpenCV's ``IMREAD_IGNORE_ORIENTATION``, as
  COLMAP does): a camera's intrinsics describe the sensor's pixels, and a JPEG rotated on read
  would no longer match them (docs/conventions.md, "Images").
- **Whole files only.** A PNG must end with its ``IEND`` chunk and every chunk must pass its CRC;
  a JPEG must have its end-of-image marker after the scan data (:func:`image_problem`). OpenCV
  decodes a truncated JPEG without a word (the missing rows grey), so a cut file is refused here
  instead. (Bit errors inside a JPEG's scan data cannot be told from valid data.)
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from planarloc.geometry.validation import InputError


class ImageFormatError(InputError):
    """Bytes that are not a PNG or JPEG image (``unsupported``) or a damaged one."""

    def __init__(self, message: str, unsupported: bool = False) -> None:
        super().__init__(message)
        self.unsupported = unsupported


def image_size_from_header(data: bytes) -> tuple[str, int, int]:
    """``(format, width, height)`` of a PNG or JPEG from its header, without decoding it.

    Raises:
        ImageFormatError: ``unsupported`` for anything that is not a PNG or JPEG, else a broken header.
    """
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise ImageFormatError("truncated PNG header")
        w, h = struct.unpack(">II", data[16:24])
        return "png", int(w), int(h)
    if data[:3] == b"\xff\xd8\xff":
        i = 2
        while i + 9 < len(data):
            if data[i] != 0xFF:
                raise ImageFormatError("corrupt JPEG (bad marker sequence)")
            marker = data[i + 1]
            if marker == 0xFF:  # fill byte
                i += 1
                continue
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                i += 2
                continue
            length = struct.unpack(">H", data[i + 2 : i + 4])[0]
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                h, w = struct.unpack(">HH", data[i + 5 : i + 9])
                return "jpeg", int(w), int(h)
            i += 2 + length
        raise ImageFormatError("corrupt JPEG (no frame header)")
    raise ImageFormatError("not a JPEG or PNG file", unsupported=True)


#: Decoding flags: gray, pixels as stored (EXIF orientation ignored).
GRAY = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION
COLOR = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION


def _png_problem(data: bytes) -> str | None:
    i = 8
    while i + 12 <= len(data):
        length = struct.unpack(">I", data[i:i + 4])[0]
        kind = data[i + 4:i + 8]
        end = i + 12 + length
        if end > len(data):
            return f"truncated PNG (its {kind.decode('latin-1')} chunk is cut off)"
        if zlib.crc32(data[i + 4:i + 8 + length]) != struct.unpack(">I", data[i + 8 + length:end])[0]:
            return f"damaged PNG (its {kind.decode('latin-1')} chunk fails its CRC)"
        if kind == b"IEND":
            return None
        i = end
    return "truncated PNG (it ends before its IEND chunk)"


def _jpeg_problem(data: bytes) -> str | None:
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return "damaged JPEG (bad marker sequence)"
        marker = data[i + 1]
        if marker == 0xFF:
            i += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        if marker == 0xD9:
            return "damaged JPEG (it ends before its image data)"
        length = struct.unpack(">H", data[i + 2:i + 4])[0]
        if marker == 0xDA:  # start of scan: the entropy-coded data runs to the end-of-image marker
            return None if data.rfind(b"\xff\xd9") > i + 2 + length else \
                "truncated JPEG (no end-of-image marker after its image data)"
        i += 2 + length
    return "truncated JPEG (it ends before its image data)"


def image_problem(data: bytes) -> str | None:
    """Why the bytes of a PNG or JPEG are not a whole file (truncated, a damaged PNG chunk), or None
    (also for other formats, which are left to the decoder)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return _png_problem(data)
    if data[:3] == b"\xff\xd8\xff":
        return _jpeg_problem(data)
    return None


def to_gray(image: object) -> np.ndarray:
    """An (H, W) or (H, W, 3) BGR uint8 array as a contiguous (H, W) uint8 gray image."""
    if not isinstance(image, np.ndarray):
        raise InputError(f"image: expected a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise InputError(
            f"image: expected dtype uint8, got {image.dtype}; "
            "hint: load with cv2.imread or convert with cv2.convertScaleAbs / np.clip(...).astype(np.uint8)"
        )
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        raise InputError(f"image: expected shape (H, W) or (H, W, 3), got {image.shape}")
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise InputError(f"image: empty image of shape {image.shape}")
    return np.ascontiguousarray(image)


def _decode(data: bytes, what: str, flags: int, failure: str) -> np.ndarray:
    problem = image_problem(data)
    if problem is not None:
        raise InputError(f"{what}: {failure}: {problem}")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    if image is None:
        raise InputError(f"{what}: {failure} (corrupt, truncated or not an image file)")
    return image


def _file_bytes(path: Path | str) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror or exc})") from None


def read_gray(path: Path | str) -> np.ndarray:
    """Read an image file as (H, W) uint8, pixels as stored; clear error when missing, unreadable,
    truncated or damaged (module docstring)."""
    return _decode(_file_bytes(path), str(path), GRAY, "cannot read image")


def decode_gray(data: bytes, what: str = "image") -> np.ndarray:
    """JPEG/PNG bytes as (H, W) uint8, decoded like :func:`read_gray`."""
    return _decode(bytes(data), what, GRAY, "cannot decode")


def read_bgr(path: Path | str) -> np.ndarray:
    """Read an image file as (H, W, 3) BGR uint8 (for pictures), like :func:`read_gray`."""
    return _decode(_file_bytes(path), str(path), COLOR, "cannot read image")
