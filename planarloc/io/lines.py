"""Helpers of the file readers: line iteration, fields at a file position, image files.

Every helper raises :class:`FormatError` naming file and line; the fields themselves are parsed
by :mod:`planarloc.io.text` (one parser per text format).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.format_error import FormatError, missing_file_error
from planarloc.io.text import WXYZ_T, TextError, numbers, pose_from_numbers

#: Largest accepted ``max |R Rᵀ - I|`` of a stored rotation matrix before it is projected onto
#: the nearest rotation (KITTI stores 7 significant digits, i.e. errors of ~1e-7).
ROTATION_TOL = 1e-3


def read_text(path: Path, fmt: str, purpose: str) -> str:
    """The whole file as text; a missing or binary file raises :class:`FormatError`."""
    if not path.is_file():
        raise missing_file_error(path, fmt, purpose)
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise FormatError(
            path, None, f"expected a UTF-8 text file ({purpose}), found binary data ({exc})"
        ) from None


def iter_data_lines(
    path: Path, fmt: str, purpose: str, *, sep: str | None = None, comment: str = "#"
) -> Iterator[tuple[int, list[str]]]:
    """Yield ``(1-based line number, tokens)`` of every non-blank, non-comment line.

    Args:
        path: the text file.
        fmt, purpose: used in the message if the file is missing (see :func:`missing_file_error`).
        sep: ``None`` splits on whitespace; ``","`` splits on commas and strips each field (kapture).
        comment: lines whose first non-blank character starts this prefix are skipped.
    """
    text = read_text(path, fmt, purpose)
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith(comment):
            continue
        tokens = line.split() if sep is None else [tok.strip() for tok in line.split(sep)]
        yield lineno, tokens


def iter_named_lines(path: Path, fmt: str, line: str, n_fields: int) -> Iterator[tuple[int, str, list[str]]]:
    """Yield ``(line number, name, other fields)`` of a per-image list ``name field...``.

    Every data line must have exactly ``n_fields`` fields (``line`` describes them in the
    message, e.g. ``"'name gx gy gz'"``) and names must be unique.
    """
    seen: dict[str, int] = {}
    for lineno, tokens in iter_data_lines(path, fmt, f"one image per line {line}"):
        if len(tokens) != n_fields:
            raise FormatError(path, lineno, f"expected {n_fields} fields {line}, found {len(tokens)}")
        name = tokens[0]
        if name in seen:
            raise FormatError(
                path, lineno, f"expected unique names, found {name!r} again (line {seen[name]})"
            )
        seen[name] = lineno
        yield lineno, name, tokens[1:]


def expect_count(path: Path, lineno: int, tokens: Sequence[str], n: int, what: str) -> None:
    """Raise unless the line has exactly ``n`` fields."""
    if len(tokens) != n:
        raise FormatError(path, lineno, f"expected {n} {what}, found {len(tokens)} field(s)")


@contextmanager
def located(path: Path, lineno: int | None, first_column: int = 1) -> Iterator[None]:
    """Turn a :class:`~planarloc.io.text.TextError` of the fields starting at column
    ``first_column`` of line ``lineno`` into a :class:`FormatError` naming file and line."""
    try:
        yield
    except TextError as exc:
        raise FormatError(path, lineno, exc.at(first_column)) from None


def parse_floats(
    path: Path, lineno: int, tokens: Sequence[str], what: str, first_column: int = 1
) -> np.ndarray:
    """Parse fields as finite floats; ``first_column`` is the 1-based column of ``tokens[0]``."""
    with located(path, lineno, first_column):
        return numbers(tokens, what)


def parse_pose_fields(
    path: Path, lineno: int, tokens: Sequence[str], layout: str = WXYZ_T, first_column: int = 1
) -> Pose:
    """A pose from 7 fields of a line in ``layout`` (:mod:`planarloc.io.text`)."""
    with located(path, lineno, first_column):
        return pose_from_numbers(numbers(tokens, "quaternion or translation"), layout)


def parse_int(path: Path, lineno: int, token: str, what: str, column: int) -> int:
    try:
        return int(token)
    except ValueError:
        raise FormatError(
            path, lineno, f"expected an integer in column {column} ({what}), found {token!r}"
        ) from None


def pose_from_matrix34(path: Path, lineno: int, M: np.ndarray) -> Pose:
    """``b_from_a`` from a (3, 4) ``[R | t]`` whose R is a rotation within ROTATION_TOL.

    R is projected onto the nearest rotation (SVD) so that rounding in the file does not fail
    :class:`Pose` validation.
    """
    R, t = M[:, :3], M[:, 3]
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    det = float(np.linalg.det(R))
    if err > ROTATION_TOL or det <= 0:
        raise FormatError(
            path,
            lineno,
            f"expected a rotation matrix (max|R Rᵀ - I| <= {ROTATION_TOL:g}, det = +1), "
            f"found max|R Rᵀ - I| = {err:.3g}, det = {det:+.4f}",
        )
    U, _, Vt = np.linalg.svd(R)
    return Pose(U @ Vt, t)


def wrap_input_error(path: Path, lineno: int | None, exc: InputError) -> FormatError:
    """Re-raise a validation error of a geometry type at a file position."""
    return FormatError(path, lineno, str(exc))


def resolve_image(path: Path, lineno: int | None, image_root: Path, name: str, *, check: bool = True) -> Path:
    """Absolute path of an image listed in ``path`` at ``lineno``; error if it does not exist."""
    image_path = (image_root / name).absolute()
    if check and not image_path.is_file():
        raise FormatError(path, lineno, f"listed image {name!r} does not exist (looked for {image_path})")
    return image_path


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image from its header, never decoded
    (:func:`planarloc.features.images.declared_size`; the pixel cap of every image path)."""
    from planarloc.features.images import check_image_pixels, declared_size

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise FormatError(path, None, f"cannot read image ({exc})") from None
    try:
        _fmt, width, height = declared_size(data)
        check_image_pixels(width, height, str(path))
    except InputError as exc:
        raise FormatError(path, None, f"cannot determine the image size: {exc}") from None
    return int(width), int(height)
