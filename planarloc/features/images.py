"""Images as features see them: (H, W) uint8 gray arrays, read from files, bytes or arrays.

One reader for every path an image takes (map images, query files, uploaded bytes, live
frames, stream frames): :func:`read_gray` (a file), :func:`decode_gray` (JPEG/PNG bytes) and
:func:`to_gray` (an array); :func:`read_bgr` for pictures of them. :func:`image_size_from_header`
reads the size of a PNG or JPEG from its first bytes without decoding it (cheap checks before any
work), :func:`declared_size` that of every supported format. Every error is an
:class:`~planarloc.geometry.validation.InputError` naming the image.

- **Pixels as stored.** EXIF orientation is ignored (OpenCV's ``IMREAD_IGNORE_ORIENTATION``, as
  COLMAP does): a camera's intrinsics describe the sensor's pixels, and a JPEG rotated on read
  would no longer match them (docs/conventions.md, "Images").
- **Whole files only.** A PNG must end with its ``IEND`` chunk and every chunk must pass its CRC;
  a JPEG must have its end-of-image marker after the scan data (:func:`image_problem`). OpenCV
  decodes a truncated JPEG without a word (the missing rows grey), so a cut file is refused here
  instead. (Bit errors inside a JPEG's scan data cannot be told from valid data.)
- **One pixel cap, checked before decoding.** :data:`MAX_IMAGE_PIXELS` bounds every image any
  path takes (files, uploads, bag and ROS messages, arrays): the size an image declares in its
  header (:func:`declared_size`) is checked before a byte is decoded, so a small file declaring
  30000x30000 pixels (a decompression bomb) is refused at the cost of reading its header.
  OpenCV (4.8 to 5.x) has no header-only reading in Python, so the headers are read here.
- **Formats.** PNG, JPEG, BMP, TIFF, PNM (PBM/PGM/PPM/PAM/PFM) and WebP; anything else, and an
  empty file, is refused with the reason instead of being handed to OpenCV.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from planarloc.geometry.validation import InputError

#: The largest image any path decodes, in pixels (64 Mpx, e.g. 8192x8192): files, uploads, ROS
#: bag and node messages, arrays. Larger images are refused from their header (module docstring).
MAX_IMAGE_PIXELS = 64 * 1024 * 1024
#: The image formats whose size :func:`declared_size` reads (the others are refused).
SUPPORTED_FORMATS = "PNG, JPEG, BMP, TIFF, PNM (PBM/PGM/PPM/PAM/PFM) or WebP"


class ImageFormatError(InputError):
    """Bytes that are not a PNG or JPEG image (``unsupported``) or a damaged one."""

    def __init__(self, message: str, unsupported: bool = False) -> None:
        super().__init__(message)
        self.unsupported = unsupported


class ImageTooLargeError(InputError):
    """An image declaring more pixels than :data:`MAX_IMAGE_PIXELS` (or none); ``width`` and
    ``height`` are what it declares."""

    def __init__(self, message: str, width: int, height: int) -> None:
        super().__init__(message)
        self.width, self.height = int(width), int(height)


def check_image_pixels(width: int, height: int, what: str = "image") -> None:
    """Refuse an image of ``width`` x ``height`` pixels that is empty or over :data:`MAX_IMAGE_PIXELS`.

    Raises:
        ImageTooLargeError: naming ``what``, the size and the limit.
    """
    w, h = int(width), int(height)
    if w < 1 or h < 1:
        raise ImageTooLargeError(f"{what}: the image declares {w}x{h} pixels (an empty image)", w, h)
    if w * h > MAX_IMAGE_PIXELS:
        raise ImageTooLargeError(
            f"{what}: the image declares {w}x{h} pixels, over the limit of {MAX_IMAGE_PIXELS} pixels "
            f"({MAX_IMAGE_PIXELS // 2**20} Mpx); refused before decoding (downscale it first)",
            w,
            h,
        )


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


def _tiff_size(data: bytes) -> tuple[int, int]:
    """Width and height of a TIFF's first image (tags 256 and 257 of its first IFD; BigTIFF too)."""
    order = "<" if data[:2] == b"II" else ">"
    big = struct.unpack(order + "H", data[2:4])[0] == 43
    try:
        if big:
            ifd = struct.unpack(order + "Q", data[8:16])[0]
            count, entry, size, head = struct.unpack(order + "Q", data[ifd : ifd + 8])[0], 20, 8, 8
        else:
            ifd = struct.unpack(order + "I", data[4:8])[0]
            count, entry, size, head = struct.unpack(order + "H", data[ifd : ifd + 2])[0], 12, 4, 2
        found: dict[int, int] = {}
        for k in range(min(count, 4096)):
            at = ifd + head + k * entry
            tag, kind = struct.unpack(order + "HH", data[at : at + 4])
            if tag in (256, 257):
                value = data[at + 4 + size : at + 4 + 2 * size]
                fmt = {3: "H", 4: "I", 16: "Q"}.get(kind)
                if fmt is None:
                    raise ImageFormatError(f"damaged TIFF (its image size has field type {kind})")
                found[tag] = struct.unpack(order + fmt, value[: struct.calcsize(fmt)])[0]
    except struct.error:
        raise ImageFormatError("truncated TIFF (its first directory is cut off)") from None
    if 256 not in found or 257 not in found:
        raise ImageFormatError("damaged TIFF (no image width and length in its first directory)")
    return int(found[256]), int(found[257])


def _pnm_size(data: bytes) -> tuple[int, int]:
    """Width and height of a PBM/PGM/PPM (``P1``-``P6``), PFM (``PF``/``Pf``) or PAM (``P7``) header."""
    head = data[:4096]
    if head[:2] == b"P7":
        keys = dict(line.split(None, 1) for line in head.split(b"\n")[1:] if len(line.split(None, 1)) == 2)
        try:
            return int(keys[b"WIDTH"]), int(keys[b"HEIGHT"])
        except (KeyError, ValueError):
            raise ImageFormatError("damaged PAM header (no WIDTH and HEIGHT)") from None
    tokens: list[bytes] = []
    for line in head[2:].split(b"\n"):
        tokens += line.split(b"#", 1)[0].split()
        if len(tokens) >= 2:
            break
    if len(tokens) < 2 or not (tokens[0].isdigit() and tokens[1].isdigit()):
        raise ImageFormatError("damaged PNM header (no width and height)")
    return int(tokens[0]), int(tokens[1])


def _webp_size(data: bytes) -> tuple[int, int]:
    """Width and height of a WebP from its ``VP8 ``, ``VP8L`` or ``VP8X`` chunk header."""
    kind = data[12:16]
    if kind == b"VP8 " and len(data) >= 30:
        w, h = struct.unpack("<HH", data[26:30])
        return w & 0x3FFF, h & 0x3FFF
    if kind == b"VP8L" and len(data) >= 25:
        bits = int.from_bytes(data[21:25], "little")
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if kind == b"VP8X" and len(data) >= 30:
        return int.from_bytes(data[24:27], "little") + 1, int.from_bytes(data[27:30], "little") + 1
    raise ImageFormatError("damaged WebP header")


def declared_size(data: bytes) -> tuple[str, int, int]:
    """``(format, width, height)`` an image declares in its header, for every format read here
    (:data:`SUPPORTED_FORMATS`), without decoding it.

    Raises:
        ImageFormatError: ``unsupported`` for an empty file or another format, else a broken header.
    """
    if not data:
        raise ImageFormatError("empty (0 bytes)", unsupported=True)
    if data[:8] == b"\x89PNG\r\n\x1a\n" or data[:3] == b"\xff\xd8\xff":
        return image_size_from_header(data)
    if data[:2] == b"BM" and len(data) >= 26:
        if struct.unpack("<I", data[14:18])[0] == 12:  # OS/2 BITMAPCOREHEADER
            w, h = struct.unpack("<HH", data[18:22])
        else:
            w, h = struct.unpack("<ii", data[18:26])
        return "bmp", int(w), abs(int(h))  # a negative height is a top-down bitmap
    if data[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return ("tiff", *_tiff_size(data))
    if len(data) >= 3 and data[:1] == b"P" and data[1:2] in b"1234567Ff" and data[2:3].isspace():
        return ("pnm", *_pnm_size(data))
    if data[:4] == b"RIFF" and data[8:12] == b"WEBP":
        return ("webp", *_webp_size(data))
    raise ImageFormatError(f"not a {SUPPORTED_FORMATS} image", unsupported=True)


#: Decoding flags: gray, pixels as stored (EXIF orientation ignored).
GRAY = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION
COLOR = cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION


def _png_problem(data: bytes) -> str | None:
    i = 8
    while i + 12 <= len(data):
        length = struct.unpack(">I", data[i : i + 4])[0]
        kind = data[i + 4 : i + 8]
        end = i + 12 + length
        if end > len(data):
            return f"truncated PNG (its {kind.decode('latin-1')} chunk is cut off)"
        if zlib.crc32(data[i + 4 : i + 8 + length]) != struct.unpack(">I", data[i + 8 + length : end])[0]:
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
        length = struct.unpack(">H", data[i + 2 : i + 4])[0]
        if marker == 0xDA:  # start of scan: the entropy-coded data runs to the end-of-image marker
            return (
                None
                if data.rfind(b"\xff\xd9") > i + 2 + length
                else "truncated JPEG (no end-of-image marker after its image data)"
            )
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
    if image.ndim in (2, 3) and image.shape[0] * image.shape[1] > MAX_IMAGE_PIXELS:
        check_image_pixels(image.shape[1], image.shape[0])  # before any conversion allocates
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
    """Decode after the cheap checks: not empty, whole (:func:`image_problem`), a supported format
    declaring at most :data:`MAX_IMAGE_PIXELS` (:func:`declared_size`); OpenCV's own errors
    become an :class:`InputError` too."""
    if not data:
        raise ImageFormatError(f"{what}: {failure}: the image is empty (0 bytes)", unsupported=True)
    problem = image_problem(data)
    if problem is not None:
        raise ImageFormatError(f"{what}: {failure}: {problem}")
    try:
        _fmt, width, height = declared_size(data)
    except ImageFormatError as exc:
        raise ImageFormatError(f"{what}: {failure}: {exc}", unsupported=exc.unsupported) from None
    check_image_pixels(width, height, what)
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as exc:  # OpenCV refuses some damaged files with an exception, others with None
        reason = " ".join(str(exc).split())[-160:]
        raise ImageFormatError(
            f"{what}: {failure} (corrupt or not an image file; OpenCV: {reason})"
        ) from None
    if image is None or image.size == 0:
        raise ImageFormatError(f"{what}: {failure} (corrupt, truncated or not an image file)")
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
