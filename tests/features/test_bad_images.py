"""Bad pixels on every image path: empty, garbage, truncated and image bombs are refused with one
InputError naming the image, never an OpenCV traceback; a bomb is refused from its header, before
anything is decoded, by the one pixel cap that files, bytes, arrays, uploads and bags share."""

from __future__ import annotations

import re
import struct
import tomllib
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from planarloc.features import images
from planarloc.features.images import (
    MAX_IMAGE_PIXELS,
    ImageTooLargeError,
    declared_size,
    decode_gray,
    read_bgr,
    read_gray,
    to_gray,
)
from planarloc.geometry.validation import InputError

BOMB = 30000  # a side of 30000 pixels: 900 Mpx, 0.9 GB as gray, 2.7 GB as colour


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_declaring(width: int, height: int) -> bytes:
    """A whole, CRC-valid gray PNG that declares ``width`` x ``height`` (its data holds a few rows:
    the header is what a bomb lies with)."""
    rows = zlib.compress(b"\0" * (width + 1) * 4, 9)
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
        + _chunk(b"IDAT", rows)
        + _chunk(b"IEND", b"")
    )


def jpeg_declaring(width: int, height: int) -> bytes:
    """A real JPEG whose frame header (SOF0) is rewritten to declare ``width`` x ``height``."""
    data = bytearray(cv2.imencode(".jpg", np.full((16, 16), 90, np.uint8))[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


def bombs() -> dict[str, bytes]:
    """Small files in every supported format, each declaring 30000 x 30000 pixels."""
    bmp = bytearray(cv2.imencode(".bmp", np.zeros((4, 4), np.uint8))[1].tobytes())
    bmp[18:26] = struct.pack("<ii", BOMB, BOMB)
    tif = cv2.imencode(".tif", np.zeros((4, 4), np.uint8))[1].tobytes()
    tif = tif.replace(struct.pack("<HHII", 256, 3, 1, 4), struct.pack("<HHII", 256, 4, 1, BOMB))
    tif = tif.replace(struct.pack("<HHII", 257, 3, 1, 4), struct.pack("<HHII", 257, 4, 1, BOMB))
    webp = (
        b"RIFF"
        + struct.pack("<I", 22)
        + b"WEBPVP8X"
        + struct.pack("<I", 10)
        + b"\0" * 4
        + (BOMB - 1).to_bytes(3, "little")
        + (BOMB - 1).to_bytes(3, "little")
    )
    return {
        "png": png_declaring(BOMB, BOMB),
        "jpeg": jpeg_declaring(BOMB, BOMB),
        "bmp": bytes(bmp),
        "tiff": tif,
        "pgm": f"P5\n{BOMB} {BOMB}\n255\n".encode() + b"\0" * 64,
        "webp": webp,
    }


@pytest.fixture
def no_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    """Any decoding fails the test: what is checked must be refused before it."""

    def decode(*_args, **_kwargs):
        raise AssertionError("cv2.imdecode was called")

    monkeypatch.setattr(images.cv2, "imdecode", decode)


# ---- empty, garbage, truncated ----------------------------------------------------------------------------
def test_an_empty_image_is_a_clear_input_error_on_every_path(tmp_path: Path) -> None:
    """OpenCV 5 raises `!buf.empty()` for zero bytes: it must never get them."""
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    for read in (read_gray, read_bgr):
        with pytest.raises(
            InputError, match=r"empty\.png: cannot read image: the image is empty \(0 bytes\)"
        ):
            read(empty)
    for data in (b"", bytearray(), memoryview(b"")):
        with pytest.raises(InputError, match=r"upload\.jpg: cannot decode: the image is empty \(0 bytes\)"):
            decode_gray(data, "upload.jpg")
    with pytest.raises(InputError, match="empty image of shape"):
        to_gray(np.zeros((0, 5), np.uint8))


@pytest.mark.parametrize("ext", [".bmp", ".tif", ".pgm", ".webp", ".png", ".jpg"])
def test_truncated_files_of_every_format_are_refused(tmp_path: Path, ext: str) -> None:
    pixels = np.random.default_rng(1).integers(0, 255, (60, 80), np.uint8)
    data = cv2.imencode(ext, pixels)[1].tobytes()
    assert decode_gray(data).shape == (60, 80)
    for cut in (data[: len(data) // 2], data[:40], data[:5]):
        path = tmp_path / f"cut{ext}"
        path.write_bytes(cut)
        with pytest.raises(InputError, match=rf"cut\{ext}: cannot read image"):
            read_gray(path)


def test_garbage_and_unsupported_formats_are_refused_naming_the_formats() -> None:
    rng = np.random.default_rng(2)
    garbage = [
        rng.integers(0, 256, 4096, np.uint8).tobytes(),
        b"\0",
        b"GIF89a" + b"\0" * 64,
        b"P5\nxx yy\n255\n",
        b"\x89PNG\r\n\x1a\n",
        b"\xff\xd8\xff" + b"\0" * 4,
        b"II*\x00\xff\xff\xff\x00",
        b"RIFF\0\0\0\0WEBPVP8Z",
        cv2.imencode(".hdr", np.zeros((4, 4, 3), np.float32))[1].tobytes(),
    ]
    for data in garbage:
        with pytest.raises(InputError, match=r"^frame: cannot decode"):
            decode_gray(data, "frame")


def test_an_opencv_error_becomes_an_input_error(monkeypatch: pytest.MonkeyPatch) -> None:
    """Whatever OpenCV refuses with an exception (versions differ in what raises and what returns
    None) reaches the caller as an InputError naming the image."""

    def decode(*_args, **_kwargs):
        raise cv2.error("OpenCV(9.0) loadsave.cpp: error: (-215:Assertion failed) something")

    monkeypatch.setattr(images.cv2, "imdecode", decode)
    with pytest.raises(InputError, match=r"q\.png: cannot decode .*Assertion failed"):
        decode_gray(cv2.imencode(".png", np.zeros((4, 4), np.uint8))[1].tobytes(), "q.png")


# ---- image bombs: one cap, from the header --------------------------------------------------------------
@pytest.mark.parametrize("kind", sorted(bombs()))
def test_a_bomb_is_refused_from_its_header_before_decoding(
    tmp_path: Path, kind: str, no_decoding: None
) -> None:
    data = bombs()[kind]
    assert len(data) < 4096 and declared_size(data)[1:] == (BOMB, BOMB)
    path = tmp_path / f"bomb.{kind}"
    path.write_bytes(data)
    for refuse in (
        lambda: read_gray(path),
        lambda: read_bgr(path),
        lambda: decode_gray(data, f"bomb.{kind}"),
    ):
        with pytest.raises(
            ImageTooLargeError,
            match=rf"bomb\.{kind}: the image declares 30000x30000 pixels, over "
            rf"the limit of {MAX_IMAGE_PIXELS} pixels",
        ) as exc:
            refuse()
        assert (exc.value.width, exc.value.height) == (BOMB, BOMB)


def test_an_array_over_the_cap_is_refused_before_any_conversion() -> None:
    huge = np.broadcast_to(
        np.uint8(7), (BOMB, BOMB, 3)
    )  # no memory behind it: converting it would take 0.9 GB
    with pytest.raises(ImageTooLargeError, match="30000x30000 pixels"):
        to_gray(huge)


def test_an_image_declaring_no_pixels_is_refused(no_decoding: None) -> None:
    with pytest.raises(ImageTooLargeError, match=r"declares 0x480 pixels \(an empty image\)"):
        decode_gray(png_declaring(0, 480))


def test_every_path_shares_the_one_cap(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Lowering features.images.MAX_IMAGE_PIXELS lowers it for files, bytes, arrays, the service's
    uploads, ROS bag messages and the dataset readers' size checks: there is one cap."""
    from planarloc.io.format_error import FormatError
    from planarloc.io.lines import image_size
    from planarloc.io.rosbag import COMPRESSED_IMAGE, _store_image
    from planarloc.serve.requests import MapSet, RequestError, parse_localize_request

    pixels = np.random.default_rng(3).integers(0, 255, (120, 160), np.uint8)
    png = cv2.imencode(".png", pixels)[1].tobytes()
    path = tmp_path / "q.png"
    path.write_bytes(png)
    map_file = tmp_path / "m.db"
    map_file.write_bytes(b"")
    maps = MapSet.from_specs([f"m={map_file}"])
    assert decode_gray(png).shape == (120, 160) and image_size(path) == (160, 120)
    assert parse_localize_request({}, png, "q.png", maps).image_size == (160, 120)

    monkeypatch.setattr(images, "MAX_IMAGE_PIXELS", 160 * 120 - 1)
    for refuse in (lambda: read_gray(path), lambda: decode_gray(png), lambda: to_gray(pixels)):
        with pytest.raises(ImageTooLargeError, match="160x120 pixels, over the limit of 19199 pixels"):
            refuse()
    with pytest.raises(RequestError, match="160x120 pixels, over the limit of 19199 pixels") as exc:
        parse_localize_request({}, png, "q.png", maps)
    assert exc.value.status == 413
    with pytest.raises(FormatError, match="over the limit of 19199 pixels"):
        image_size(path)

    class Message:
        format = "png"
        data = png

    with pytest.raises(InputError, match="CompressedImage data .* over the limit of 19199 pixels"):
        _store_image(tmp_path / "bag", "frame", Message(), COMPRESSED_IMAGE)


# ---- formats and the OpenCV range -----------------------------------------------------------------------
@pytest.mark.parametrize(
    "ext", [".png", ".jpg", ".bmp", ".tif", ".pgm", ".ppm", ".pbm", ".pam", ".pfm", ".webp"]
)
def test_the_declared_size_is_the_decoded_size_for_every_supported_format(ext: str) -> None:
    pixels = np.random.default_rng(4).integers(0, 255, (37, 53), np.uint8)
    if ext == ".ppm":
        pixels = cv2.cvtColor(pixels, cv2.COLOR_GRAY2BGR)
    if ext == ".pfm":
        pixels = pixels.astype(np.float32)
    for params in ([], [cv2.IMWRITE_WEBP_QUALITY, 80]) if ext == ".webp" else ([],):
        data = cv2.imencode(ext, pixels, params)[1].tobytes()
        assert declared_size(data)[1:] == (53, 37)
        assert decode_gray(data).shape == (37, 53)


def test_the_installed_opencv_is_in_the_supported_range() -> None:
    """pyproject.toml's lower bound, and the majors this module's checks were tested with (4, 5);
    a new major must be tested (what it raises for bad bytes, its flags) before it is supported."""
    project = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())
    requirement = next(
        r for r in project["project"]["dependencies"] if r.startswith("opencv-python-headless")
    )
    lower = tuple(int(v) for v in re.search(r">=\s*([0-9.]+)", requirement).group(1).split("."))
    version = tuple(int(v) for v in cv2.__version__.split(".")[:2])
    assert version >= lower[:2], (cv2.__version__, requirement)
    assert version[0] in (4, 5), f"OpenCV {cv2.__version__} is not a tested major (4, 5)"
    assert cv2.IMREAD_IGNORE_ORIENTATION and cv2.IMREAD_GRAYSCALE == 0
    # What the versions differ in, handled either way: garbage gives None or raises cv2.error.
    try:
        assert cv2.imdecode(np.frombuffer(b"\0" * 16, np.uint8), cv2.IMREAD_GRAYSCALE) is None
    except cv2.error:
        pass
