"""Validation of localization requests, shared by the HTTP service and the Ray Serve deployment.

Everything a client sends is checked here, before any CPU-heavy work: the map name (looked up in
the configured maps, never used as a path), the image (JPEG or PNG by its signature, size limit,
dimensions read from the header without decoding), the camera (COLMAP syntax, must fit the
image), gravity, method, structure and seed. A bad field raises :class:`RequestError` with an
HTTP status and a one-line reason.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from planarloc.geometry.camera import Camera
from planarloc.robust.options import Method, Structure

#: Default upper bound of an uploaded image (bytes).
DEFAULT_MAX_IMAGE_BYTES = 20 * 1024 * 1024
#: Upper bound of the decoded image (pixels), against decompression bombs.
MAX_IMAGE_PIXELS = 64 * 1024 * 1024
MAP_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
SESSION = re.compile(r"^[\x21-\x7e]{1,128}$")
FIELDS = ("image", "camera", "map", "gravity", "session", "method", "structure", "seed")


class RequestError(ValueError):
    """A request that cannot be served; ``status`` is the HTTP status, the message one line."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(status, message)
        self.status = int(status)
        self.message = " ".join(str(message).split())

    def __str__(self) -> str:
        return self.message


@dataclass(frozen=True)
class MapSet:
    """The maps a server offers: ``{name: path}``. Names are looked up, never joined to paths."""

    paths: Mapping[str, Path]

    @classmethod
    def from_specs(cls, specs: Sequence[str]) -> MapSet:
        """From ``--map`` values ``PATH`` (name = file stem) or ``NAME=PATH``.

        Raises:
            ValueError: no map, a malformed name, a duplicate name, a missing file.
        """
        paths: dict[str, Path] = {}
        for spec in specs:
            name, sep, path = spec.partition("=")
            if not sep:
                name, path = Path(spec).stem, spec
            if not MAP_NAME.match(name):
                raise ValueError(
                    f"--map {spec!r}: map names are 1-64 characters [A-Za-z0-9_.-] starting with a "
                    f"letter or digit, got {name!r}; use --map NAME=PATH"
                )
            if name in paths:
                raise ValueError(f"--map {spec!r}: the name {name!r} is given twice; use --map NAME=PATH")
            if not Path(path).is_file():
                raise ValueError(f"--map {spec!r}: no such map file {path}")
            paths[name] = Path(path).resolve()
        if not paths:
            raise ValueError("--map: give at least one map (PATH or NAME=PATH)")
        return cls(paths)

    def resolve(self, name: str | None) -> str:
        """The served map's name for a request's ``map`` field (optional when one map is served)."""
        if not name:
            if len(self.paths) == 1:
                return next(iter(self.paths))
            raise RequestError(
                400, f"map: required when several maps are served ({', '.join(sorted(self.paths))})"
            )
        if name not in self.paths:
            raise RequestError(404, f"map: unknown map {name[:64]!r}; GET /v1/maps lists the served maps")
        return name


@dataclass(frozen=True)
class LocalizeRequest:
    """A validated localization request (picklable: it crosses into worker processes)."""

    map_name: str
    name: str
    image: bytes
    camera: Camera
    gravity: tuple[float, float, float] | None = None
    session: str | None = None
    method: str | None = None
    structure: str | None = None
    seed: int | None = None
    image_size: tuple[int, int] = field(default=(0, 0))  # (width, height) from the header


def image_size(data: bytes) -> tuple[str, int, int]:
    """``(format, width, height)`` of a PNG or JPEG from its header, without decoding it.

    Raises:
        RequestError: 415 for anything that is not a PNG or JPEG, 400 for a broken header.
    """
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        if len(data) < 24 or data[12:16] != b"IHDR":
            raise RequestError(400, "image: truncated PNG header")
        w, h = struct.unpack(">II", data[16:24])
        return "png", int(w), int(h)
    if data[:3] == b"\xff\xd8\xff":
        i = 2
        while i + 9 < len(data):
            if data[i] != 0xFF:
                raise RequestError(400, "image: corrupt JPEG (bad marker sequence)")
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
        raise RequestError(400, "image: corrupt JPEG (no frame header)")
    raise RequestError(415, "image: not a JPEG or PNG file")


def parse_camera_field(text: str) -> Camera:
    """``MODEL WIDTH HEIGHT PARAMS...`` (COLMAP syntax) -> :class:`Camera`, else a 400."""
    tok = text.replace(",", " ").split()
    if len(tok) < 4:
        raise RequestError(
            400, f"camera: expected 'MODEL WIDTH HEIGHT PARAMS...' (COLMAP syntax), got {text[:80]!r}"
        )
    try:
        return Camera(tok[0], int(tok[1]), int(tok[2]), tuple(float(v) for v in tok[3:]))
    except ValueError as exc:
        raise RequestError(400, f"camera {text[:80]!r}: {exc}") from None


def _parse_gravity(text: str) -> tuple[float, float, float]:
    try:
        g = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        g = ()
    if len(g) != 3 or not all(abs(v) < float("inf") for v in g) or sum(v * v for v in g) == 0:
        raise RequestError(
            400,
            f"gravity: expected three finite numbers 'gx gy gz' (camera frame, not all zero), "
            f"got {text[:80]!r}",
        )
    return g  # type: ignore[return-value]


def _choice(name: str, text: str | None, choices: Sequence[str]) -> str | None:
    if not text:
        return None
    if text not in choices:
        raise RequestError(400, f"{name}: expected one of {', '.join(choices)}, got {text[:40]!r}")
    return text


def parse_localize_request(
    fields: Mapping[str, str],
    image: bytes | None,
    filename: str | None,
    maps: MapSet,
    max_image_bytes: int = DEFAULT_MAX_IMAGE_BYTES,
) -> LocalizeRequest:
    """Validate the fields of ``POST /v1/localize`` (module docstring).

    Args:
        fields: the text fields of the form (``camera``, ``map``, ``gravity``, ...).
        image: the bytes of the ``image`` file field, None when missing.
        filename: the uploaded file's name (the record's ``name``; default ``"query"``).
        maps: the served maps.
        max_image_bytes: larger images are refused with 413.
    """
    unknown = sorted(set(fields) - set(FIELDS))
    if unknown:
        raise RequestError(
            400, f"unknown form field(s) {', '.join(unknown)[:80]}; expected {', '.join(FIELDS)}"
        )
    map_name = maps.resolve(fields.get("map") or None)
    if image is None:
        raise RequestError(400, "image: missing (multipart file field 'image', a JPEG or PNG)")
    if len(image) > max_image_bytes:
        raise RequestError(413, f"image: {len(image)} bytes is over the limit of {max_image_bytes} bytes")
    _fmt, w, h = image_size(image)
    if w <= 0 or h <= 0 or w * h > MAX_IMAGE_PIXELS:
        raise RequestError(413, f"image: {w}x{h} pixels is outside 1..{MAX_IMAGE_PIXELS} pixels")
    if not fields.get("camera"):
        raise RequestError(400, "camera: missing (form field 'MODEL WIDTH HEIGHT PARAMS...', COLMAP syntax)")
    camera = parse_camera_field(fields["camera"])
    if (camera.width, camera.height) != (w, h):
        raise RequestError(400, f"camera: {camera.width}x{camera.height} does not fit the {w}x{h} image")
    session = fields.get("session") or None
    if session is not None and not SESSION.match(session):
        raise RequestError(400, "session: expected 1-128 printable ASCII characters without spaces")
    seed = fields.get("seed") or None
    if seed is not None:
        if not seed.isdigit() or len(seed) > 18:
            raise RequestError(400, f"seed: expected a non-negative integer, got {seed[:40]!r}")
    name = Path(filename or "query").name or "query"
    if any(c.isspace() for c in name) or len(name) > 255:
        raise RequestError(400, "image: the file name must be at most 255 characters without whitespace")
    return LocalizeRequest(
        map_name=map_name,
        name=name,
        image=bytes(image),
        camera=camera,
        gravity=_parse_gravity(fields["gravity"]) if fields.get("gravity") else None,
        session=session,
        method=_choice("method", fields.get("method"), [m.value for m in Method]),
        structure=_choice("structure", fields.get("structure"), [s.value for s in Structure]),
        seed=None if seed is None else int(seed),
        image_size=(w, h),
    )
