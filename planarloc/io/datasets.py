"""Registry of dataset readers: one name per format, one entry point.

========== ======================================= ==========================================
name       reader                                   root
========== ======================================= ==========================================
kitti      :func:`planarloc.io.kitti.read_kitti`    sequence dir (image_l/, poses.txt, calib.txt)
tum        :func:`planarloc.io.tum.read_tum`        sequence dir (rgb.txt, groundtruth.txt)
openloris  :func:`planarloc.io.openloris.read_openloris`  sequence dir (color.txt, groundtruth.txt)
kapture    :func:`planarloc.io.kapture.read_kapture`      dataset dir (sensors/...)
colmap     :func:`planarloc.io.colmap_text.read_colmap`   model dir (cameras.txt, images.txt)
list       :func:`planarloc.io.pose_list.read_pose_list`  list file or its directory
rosbag     :func:`planarloc.io.rosbag.read_rosbag`        .bag file or ROS 2 bag folder (needs rosbags)
========== ======================================= ==========================================

Every format also accepts the option ``up``: the world's up direction (``"z"``, ``"-y"``,
``"0,0,1"``, see :func:`planarloc.gravity.world.parse_up`) or ``estimate`` (estimate it from
the map's poses); it replaces the format's declared gravity (``PosedImage.world_down``) on every
image.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import numbers
import re
import typing
from collections.abc import Callable
from pathlib import Path

from planarloc.geometry.validation import InputError
from planarloc.gravity.world import world_down_from_up
from planarloc.io.colmap_text import read_colmap
from planarloc.io.format_error import FormatError
from planarloc.io.kapture import read_kapture
from planarloc.io.kitti import read_kitti
from planarloc.io.openloris import read_openloris
from planarloc.io.pose_list import read_pose_list
from planarloc.io.rosbag import read_rosbag
from planarloc.io.tum import read_tum
from planarloc.map.posed_image import PosedImage

FORMATS: dict[str, Callable[..., list[PosedImage]]] = {
    "kitti": read_kitti,
    "tum": read_tum,
    "openloris": read_openloris,
    "kapture": read_kapture,
    "colmap": read_colmap,
    "list": read_pose_list,
    "rosbag": read_rosbag,
}


UP_OPTION = "up"

#: Files (relative to the root) whose presence identifies each folder format. ``list`` accepts
#: any file, so it has none and is never guessed.
SIGNATURES: dict[str, tuple[str, ...]] = {
    "kitti": ("poses.txt", "calib.txt"),
    "tum": ("rgb.txt", "groundtruth.txt"),
    "openloris": ("color.txt", "groundtruth.txt"),
    "kapture": ("sensors/sensors.txt",),
    "colmap": ("cameras.txt", "images.txt"),
}


def detect_formats(root: Path) -> list[str]:
    """The formats whose signature files are all present in folder ``root`` (maybe none)."""
    root = Path(root)
    return [
        f for f, files in SIGNATURES.items() if root.is_dir() and all((root / n).is_file() for n in files)
    ]


def _check_layout(root: Path, fmt: str) -> None:
    """Say "not a TUM folder" (and which format it looks like) before the reader asks for
    files of the wrong format, e.g. TUM intrinsics for a KITTI sequence."""
    if not root.exists():
        raise FormatError(root, None, "no such file or folder")
    files = SIGNATURES.get(fmt)
    if files is None:
        return
    if not root.is_dir():
        raise FormatError(
            root, None, f"is a file; the {fmt} format needs its folder (with {', '.join(files)})"
        )
    missing = [n for n in files if not (root / n).is_file()]
    if not missing:
        return
    looks = [f for f in detect_formats(root) if f != fmt]
    hint = f"; it looks like a {looks[0]} dataset: use --format {looks[0]}" if looks else ""
    raise FormatError(root, None, f"not a {fmt} folder (no {', '.join(missing)}){hint}")


def format_options(fmt: str) -> list[str]:
    """Names of the keyword options the reader of ``fmt`` accepts (``up`` is common to all)."""
    reader = _reader(fmt)
    return [
        p.name
        for p in inspect.signature(reader).parameters.values()
        if p.kind is inspect.Parameter.KEYWORD_ONLY
    ] + [UP_OPTION]


_KINDS: dict[object, str] = {bool: "bool", int: "int", float: "float"}  # a type hint -> its kind


def option_kind(fmt: str, key: str) -> str:
    """What the option ``key`` of format ``fmt`` takes: ``"bool"``, ``"int"``, ``"float"`` (a
    number) or ``"text"`` (anything else: paths, topics, cameras, poses; their readers parse them)."""
    if key == UP_OPTION:
        return "text"
    hint = typing.get_type_hints(_reader(fmt)).get(key)
    args = set(typing.get_args(hint)) - {type(None)} if typing.get_args(hint) else {hint}
    kinds = {_KINDS.get(a, "text") for a in args}
    return kinds.pop() if len(kinds) == 1 else "text"


_INT = re.compile(r"^[+-]?[0-9]{1,18}$")
_BOOLS = {"true": True, "false": False, "1": True, "0": False, "yes": True, "no": False}


def parse_option_text(fmt: str, key: str, text: str) -> object:
    """The value of ``KEY=TEXT`` (command line) for format ``fmt``, by :func:`option_kind`.

    Raises:
        InputError: a text that is not of the option's kind, naming the option and the kind.
    """
    kind = option_kind(fmt, key)
    text = str(text).strip()
    if kind == "bool":
        if text.lower() not in _BOOLS:
            raise InputError(f"{key}={text!r}: expected true or false")
        return _BOOLS[text.lower()]
    if kind == "int":
        if not _INT.match(text):
            raise InputError(f"{key}={text!r}: expected an integer, e.g. {key}=2")
        return int(text)
    if kind == "float":
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not math.isfinite(value) or "_" in text:
            raise InputError(f"{key}={text!r}: expected a finite number, e.g. {key}=0.05")
        return value
    return text


def check_option_value(fmt: str, key: str, value: object) -> object:
    """An option value given to :func:`read_dataset` (Python), checked against its kind like
    :func:`parse_option_text` (a text is parsed by it)."""
    if isinstance(value, str):
        return parse_option_text(fmt, key, value)
    kind = option_kind(fmt, key)
    if kind == "bool" and not isinstance(value, bool):
        raise InputError(f"{key}={value!r}: expected true or false")
    if kind == "int" and (isinstance(value, bool) or not isinstance(value, numbers.Integral)):
        raise InputError(f"{key}={value!r}: expected an integer, e.g. {key}=2")
    if kind == "float" and (
        isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value))
    ):
        raise InputError(f"{key}={value!r}: expected a finite number, e.g. {key}=0.05")
    return value


def _reader(fmt: str) -> Callable[..., list[PosedImage]]:
    try:
        return FORMATS[str(fmt).lower()]
    except KeyError:
        raise InputError(f"unknown dataset format {fmt!r}; known formats: {', '.join(FORMATS)}") from None


def read_dataset(root: Path, fmt: str, **options: object) -> list[PosedImage]:
    """Read a dataset of posed images in format ``fmt``.

    Args:
        root: dataset root (see the table in the module docstring).
        fmt: a key of :data:`FORMATS` (case-insensitive).
        **options: keyword options of that format's reader, and ``up`` (the world's up
            direction, overrides the format's declared gravity).

    Returns:
        The reader's :class:`PosedImage` list, sorted by index.

    Raises:
        InputError: unknown format or option; FormatError (an InputError) from the reader, or
            when ``root`` lacks the format's files (naming the format it looks like instead).

    Example:
        >>> frames = read_dataset(Path("data/kitti_seq2"), "kitti")   # doctest: +SKIP
    """
    reader = _reader(fmt)
    allowed = format_options(fmt)
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise InputError(
            f"format {fmt!r}: unknown option(s) {', '.join(unknown)}; accepted: "
            f"{', '.join(allowed) or 'none'}"
        )
    options = {k: check_option_value(fmt, k, v) for k, v in options.items()}
    up = options.pop(UP_OPTION, None)
    world_down = None if up is None else world_down_from_up(up)  # a bad value fails before reading
    _check_layout(Path(root), str(fmt).lower())
    images = reader(Path(root), **options)
    if world_down is not None:
        images = [dataclasses.replace(im, world_down=world_down) for im in images]
    return images
