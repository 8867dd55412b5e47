"""Validation of localization requests, shared by the HTTP service and the Ray Serve deployment.

Everything a client sends is checked here, before any CPU-heavy work: the map name (looked up in
the configured maps, never used as a path), the image (JPEG or PNG by its signature, size limit,
dimensions read from the header without decoding, at most the pixels every image path takes:
:data:`planarloc.features.images.MAX_IMAGE_PIXELS`), the camera (``MODEL W H PARAMS...``, must fit
the image; optional: the map's camera when the map has one), gravity (``gx gy gz``, returned as a
unit vector, as the CLI's ``--gravity``), method, structure and seed, and for a frame of a
session (``session``, one stream per robot) its ``stamp`` (seconds, required, at most
:data:`MAX_STAMP_AHEAD_S` ahead of the server's clock) and ``odometry``
(``tx ty tz qx qy qz qw``: the camera's pose in the odometry frame, the layout of a
``--odometry`` file line). The texts are parsed by :mod:`planarloc.io.text`, the parsers of the
CLI and the file readers. A bad field raises :class:`RequestError` with an HTTP status (4xx) and a
one-line reason; no client text can raise anything else.
"""

from __future__ import annotations

import re
import sqlite3
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np

from planarloc.features.images import (
    ImageFormatError,
    ImageTooLargeError,
    check_image_pixels,
    image_size_from_header,
)
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.text import T_XYZW, parse_camera, parse_gravity, parse_pose
from planarloc.localize.localizer import LocalizerConfig, localizer_config
from planarloc.map.schema import MapFormatError
from planarloc.robust.options import Method, Structure, parse_choice

#: Default upper bound of an uploaded image (bytes).
DEFAULT_MAX_IMAGE_BYTES = 20 * 1024 * 1024
# The pixel cap is the one of every image path (files, uploads, bags, the node):
# planarloc.features.images.MAX_IMAGE_PIXELS; an upload is checked against it here first, from its header.
# Patterns end with \Z: `$` also matches before a trailing newline ("robot-1\n" is not an id).
MAP_NAME = re.compile(r"\A[A-Za-z0-9][A-Za-z0-9_.-]{0,63}\Z")
SESSION = re.compile(r"\A[\x21-\x7e]{1,128}\Z")
SEED = re.compile(r"\A[0-9]{1,18}\Z")
#: A stamp in seconds: a decimal number as Python or C print it (no hex, underscores, nan or inf).
STAMP = re.compile(r"\A[+-]?([0-9]+\.?[0-9]*|\.[0-9]+)([eE][+-]?[0-9]{1,3})?\Z")
#: Largest stamp magnitude accepted (s): beyond ~3e4 years a float no longer resolves milliseconds.
MAX_STAMP_S = 1e12
#: How far a frame's stamp may be ahead of the server's clock (s): a stamp is a capture time,
#: Unix time or a clock that started later (a simulation, a replay); one a day ahead or more was
#: never taken yet (it would also hold its session's later frames off as out of order).
MAX_STAMP_AHEAD_S = 86400.0
_DEFAULT = LocalizerConfig()
FIELDS = ("image", "camera", "map", "gravity", "session", "stamp", "odometry", "method", "structure", "seed")


class RequestError(ValueError):
    """A request that cannot be served; ``status`` is the HTTP status, the message one line;
    ``retry_after_s`` (503) how long the client should wait before retrying."""

    def __init__(self, status: int, message: str, retry_after_s: int | None = None) -> None:
        super().__init__(status, message, retry_after_s)
        self.status = int(status)
        self.message = " ".join(str(message).split())
        self.retry_after_s = retry_after_s

    def __str__(self) -> str:
        return self.message


class ServerFault(RuntimeError):
    """A fault of the server, not of the request (a damaged map, a bug): answered 500 with the
    one-line ``public`` reason (no paths, no internals); ``detail`` goes to the server's log."""

    def __init__(self, public: str, detail: str = "") -> None:
        super().__init__(public, detail)
        self.public = " ".join(str(public).split())
        self.detail = detail

    def __str__(self) -> str:
        return self.public


def classify_error(exc: BaseException, what: str = "request") -> RequestError | ServerFault:
    """Whose fault an exception raised while serving a request is.

    The request's (a :class:`RequestError`, 4xx): what :func:`parse_localize_request` or the
    localizer's query checks refuse (:class:`InputError`: an undecodable image, a camera that does
    not fit it, bad options). The server's (:class:`ServerFault`, 500): a damaged or unreadable map
    (``MapFormatError``, SQLite or file errors) and anything else (a bug).
    """
    if isinstance(exc, (RequestError, ServerFault)):
        return exc
    detail = f"{what}: {type(exc).__name__}: {exc}"
    if isinstance(exc, MapFormatError):
        return ServerFault(
            "the map is damaged or unreadable on the server (logged there); the operator must check "
            "it with `planarloc map check`",
            detail,
        )
    if isinstance(exc, ImageTooLargeError):
        return RequestError(413, str(exc) if str(exc).startswith(f"{what}:") else f"{what}: {exc}")
    if isinstance(exc, InputError):
        return RequestError(400, str(exc) if str(exc).startswith(f"{what}:") else f"{what}: {exc}")
    if isinstance(exc, (sqlite3.Error, OSError)):
        return ServerFault("the server cannot read its map (logged there)", detail)
    return ServerFault(f"internal error ({type(exc).__name__}, logged on the server)", detail)


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
class QuerySettings:
    """What configures the localizer for a request (and a session, from its first frame): the
    defaults are :class:`~planarloc.localize.localizer.LocalizerConfig`'s, so the service, the CLI
    and the ROS node configure alike."""

    method: Method = Method(_DEFAULT.method)
    structure: Structure = Structure(_DEFAULT.ransac.structure)
    seed: int | None = _DEFAULT.ransac.seed

    def config(self) -> LocalizerConfig:
        """The localizer's configuration.

        Raises:
            InputError: a value the options refuse.
        """
        return localizer_config(method=self.method, structure=self.structure, seed=self.seed)

    def __str__(self) -> str:
        return f"(method, structure, seed) = ({self.method.value}, {self.structure.value}, {self.seed})"


@dataclass(frozen=True)
class LocalizeRequest:
    """A validated localization request (picklable: it crosses into worker processes)."""

    map_name: str
    name: str
    image: bytes | np.ndarray  # the request's bytes; a session frame's decoded image once checked
    camera: Camera | None
    gravity: tuple[float, float, float] | None = None
    session: str | None = None
    method: Method | None = None  # None: the default (QuerySettings)
    structure: Structure | None = None
    seed: int | None = None
    image_size: tuple[int, int] = field(default=(0, 0))  # (width, height) from the header
    stamp: float | None = None  # a session frame's time (s)
    odometry: Pose | None = None  # a session frame's cam_from_odom, or None

    @property
    def settings(self) -> QuerySettings:
        """What configures the localizer, defaults filled in (a session keeps those of its first frame)."""
        given = {"method": self.method, "structure": self.structure, "seed": self.seed}
        return QuerySettings(**{k: v for k, v in given.items() if v is not None})  # type: ignore[arg-type]


def image_size(data: bytes) -> tuple[str, int, int]:
    """``(format, width, height)`` of a PNG or JPEG from its header, without decoding it.

    Raises:
        RequestError: 415 for anything that is not a PNG or JPEG, 400 for a broken header.
    """
    try:
        return image_size_from_header(data)
    except ImageFormatError as exc:
        raise RequestError(415 if exc.unsupported else 400, f"image: {exc}") from None


def parse_camera_field(text: str) -> Camera:
    """``MODEL WIDTH HEIGHT PARAMS...`` (:func:`planarloc.io.text.parse_camera`), else a 400."""
    try:
        return parse_camera(text)
    except InputError as exc:
        raise RequestError(400, f"camera {text[:80]!r}: {str(exc)[:200]}") from None


def parse_gravity_field(text: str) -> tuple[float, float, float]:
    """``gx gy gz`` (:func:`planarloc.io.text.parse_gravity`) as a unit vector, else a 400."""
    try:
        return tuple(float(v) for v in parse_gravity(text))  # type: ignore[return-value]
    except InputError as exc:
        raise RequestError(400, f"gravity {text[:80]!r}: {exc}") from None


def parse_stamp_field(text: str, now: float | None = None) -> float:
    """A session frame's ``stamp``: seconds as a plain decimal number, not more than
    :data:`MAX_STAMP_AHEAD_S` ahead of the server's clock ``now`` (default: ``time.time()``), else a 400."""
    text = text.strip()
    if len(text) > 40 or not STAMP.match(text) or not abs(float(text)) <= MAX_STAMP_S:
        raise RequestError(
            400, f"stamp: expected the frame's time in seconds (e.g. 1305031102.175), got {text[:40]!r}"
        )
    stamp = float(text)
    now = time.time() if now is None else float(now)
    if stamp > now + MAX_STAMP_AHEAD_S:
        raise RequestError(
            400,
            f"stamp: {text[:40]} is {stamp - now:.3g} s ahead of the server's clock (Unix time "
            f"{now:.0f}); a frame's stamp is the time it was taken, in seconds (Unix time or a "
            f"clock started later), at most {MAX_STAMP_AHEAD_S:g} s ahead; the frame was not "
            "used and the session is unchanged",
        )
    return stamp


def parse_odometry_field(text: str) -> Pose:
    """``tx ty tz qx qy qz qw`` (the camera's pose in the odometry frame, an ``--odometry`` file
    line without its timestamp) -> ``cam_from_odom``, else a 400."""
    try:
        return parse_pose(text, T_XYZW).inverse()
    except InputError as exc:
        raise RequestError(400, f"odometry {text[:80]!r}: {str(exc)[:200]}") from None


_Choice = TypeVar("_Choice", Method, Structure)


def _choice_field(kind: type[_Choice], name: str, text: str | None) -> _Choice | None:
    """A form field naming a member of ``kind`` (empty: the default, None), else a 400."""
    if not text:
        return None
    try:
        return parse_choice(kind, text, name)
    except InputError:
        raise RequestError(
            400, f"{name}: expected one of {', '.join(m.value for m in kind)}, got {text[:40]!r}"
        ) from None


def parse_method_field(text: str | None) -> Method | None:
    """``method`` (a :class:`Method`'s name; empty: the default), else a 400."""
    return _choice_field(Method, "method", text)


def parse_structure_field(text: str | None) -> Structure | None:
    """``structure`` (a :class:`Structure`'s name; empty: the default), else a 400."""
    return _choice_field(Structure, "structure", text)


def parse_localize_request(
    fields: Mapping[str, str],
    image: bytes | None,
    filename: str | None,
    maps: MapSet,
    max_image_bytes: int = DEFAULT_MAX_IMAGE_BYTES,
    now: float | None = None,
) -> LocalizeRequest:
    """Validate the fields of ``POST /v1/localize`` (module docstring).

    Args:
        fields: the text fields of the form (``camera``, ``map``, ``gravity``, ...).
        image: the bytes of the ``image`` file field, None when missing.
        filename: the uploaded file's name (the record's ``name``; default ``"query"``).
        maps: the served maps.
        max_image_bytes: larger images are refused with 413.
        now: the server's clock (Unix time; default ``time.time()``), for a stamp far ahead of it.
    """
    unknown = sorted(set(fields) - set(FIELDS))
    if unknown:
        raise RequestError(
            400, f"unknown form field(s) {', '.join(unknown)[:80]}; expected {', '.join(FIELDS)}"
        )
    map_name = maps.resolve(fields.get("map") or None)
    if image is None:
        raise RequestError(400, "image: missing (multipart file field 'image', a JPEG or PNG)")
    if not image:
        raise RequestError(400, "image: the file is empty (0 bytes); send a JPEG or PNG")
    if len(image) > max_image_bytes:
        raise RequestError(413, f"image: {len(image)} bytes is over the limit of {max_image_bytes} bytes")
    _fmt, w, h = image_size(image)
    try:
        check_image_pixels(w, h, "image")
    except ImageTooLargeError as exc:
        raise RequestError(413, str(exc)) from None
    camera = parse_camera_field(fields["camera"]) if fields.get("camera") else None
    if camera is not None and (camera.width, camera.height) != (w, h):
        raise RequestError(400, f"camera: {camera.width}x{camera.height} does not fit the {w}x{h} image")
    session = fields.get("session") or None
    if session is not None and not SESSION.match(session):
        raise RequestError(400, "session: expected 1-128 printable ASCII characters without spaces")
    stamp = parse_stamp_field(fields["stamp"], now) if fields.get("stamp") else None
    odometry = parse_odometry_field(fields["odometry"]) if fields.get("odometry") else None
    if session is None and (stamp is not None or odometry is not None):
        raise RequestError(
            400, "stamp, odometry: only for a frame of a session (give the field session=ROBOT_ID)"
        )
    if session is not None and stamp is None:
        raise RequestError(400, "stamp: required with session (the frame's time in seconds)")
    seed = fields.get("seed") or None
    if seed is not None and not SEED.match(seed):
        raise RequestError(
            400, f"seed: expected a non-negative integer of at most 18 digits, got {seed[:40]!r}"
        )
    name = Path(filename or "query").name or "query"
    if len(name) > 255 or not name.isprintable() or any(c.isspace() for c in name):
        raise RequestError(
            400, "image: the file name must be at most 255 printable characters without whitespace"
        )
    return LocalizeRequest(
        map_name=map_name,
        name=name,
        image=bytes(image),
        camera=camera,
        gravity=parse_gravity_field(fields["gravity"]) if fields.get("gravity") else None,
        session=session,
        method=parse_method_field(fields.get("method")),
        structure=parse_structure_field(fields.get("structure")),
        seed=None if seed is None else int(seed),
        image_size=(w, h),
        stamp=stamp,
        odometry=odometry,
    )
