"""Images as features see them: (H, W) uint8 gray arrays, read from files, bytes or arrays.

One reader for every path an image takes (map images, query files, uploaded bytes, live
frames): :func:`read_gray` (a file), :func:`decode_gray` (JPEG/PNG bytes) and :func:`to_gray`
(an array). :func:`image_size_from_header` reads the size of a PNG or JPEG from its first bytes
without decoding it (cheap checks before any work). Every error is an
:class:`~planarloc.geometry.validation.InputError` naming the image.
"""

from __future__ import annotations

import struct
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


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG file's header (24 bytes read), None for other or unreadable files."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
        fmt, w, h = image_size_from_header(head)
    except (OSError, ImageFormatError):
        return None
    return (w, h) if fmt == "png" else None


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


def read_gray(path: Path | str) -> np.ndarray:
    """Read an image file as (H, W) uint8; clear error when missing or unreadable."""
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{path}: cannot read image (missing file or unsupported format)")
    return image


def decode_gray(data: bytes, what: str = "image") -> np.ndarray:
    """JPEG/PNG bytes as (H, W) uint8, decoded like :func:`read_gray`."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{what}: cannot decode (corrupt or truncated JPEG/PNG)")
    return image
