"""Intrinsics text files: one camera per line, COLMAP model names and parameter order.

Format (``#`` starts a comment line)::

    [KEY] MODEL WIDTH HEIGHT PARAMS...

- ``MODEL`` is a COLMAP camera model, with its parameters in COLMAP's order; the models
  :class:`~planarloc.geometry.camera.Camera` supports are accepted (docs/conventions.md), other
  COLMAP models are rejected with an error naming the model and the supported ones.
- ``KEY`` is optional. Without it, the line is a camera for every image (TUM ``camera.txt``:
  ``PINHOLE 640 480 517.3 516.5 318.6 255.3``). With it, the key is a COLMAP camera id
  (``cameras.txt``: ``1 PINHOLE 640 480 ...``) or an image name (hloc
  ``queries_with_intrinsics.txt``: ``query/0001.jpg PINHOLE 640 480 ...``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from planarloc.geometry.camera import Camera, CameraModel
from planarloc.io.format_error import FormatError
from planarloc.io.lines import iter_data_lines, located
from planarloc.io.text import is_camera_model, parse_camera


def camera_from_tokens(path: Path, lineno: int, tokens: Sequence[str], first_column: int = 1) -> Camera:
    """A :class:`Camera` from the fields ``MODEL WIDTH HEIGHT PARAMS...`` of one line
    (:func:`planarloc.io.text.parse_camera`), errors naming file, line and column.

    Args:
        path, lineno: position for error messages.
        tokens: the fields, starting with the model name.
        first_column: 1-based column of ``tokens[0]`` in the line (for messages).
    """
    with located(path, lineno, first_column):
        return parse_camera(tokens)


def read_camera_file(path: Path, fmt: str = "camera", *, sep: str | None = None) -> dict[str | None, Camera]:
    """Read an intrinsics file (see module docstring).

    Args:
        path: the file.
        fmt: format name used in the message if the file is missing.
        sep: field separator (``None`` = whitespace).

    Returns:
        ``{key: Camera}`` in file order; keyless lines have key ``None`` (at most one allowed).

    Raises:
        FormatError: missing file, no camera line, duplicate key, bad model or parameters.
    """
    cameras: dict[str | None, Camera] = {}
    for lineno, tokens in iter_data_lines(
        path, fmt, "camera intrinsics 'MODEL WIDTH HEIGHT PARAMS...'", sep=sep
    ):
        if is_camera_model(tokens[0]):
            key, cam = None, camera_from_tokens(path, lineno, tokens, 1)
        elif len(tokens) > 1 and is_camera_model(tokens[1]):
            key, cam = tokens[0], camera_from_tokens(path, lineno, tokens[1:], 2)
        else:
            raise FormatError(
                path,
                lineno,
                f"expected '[KEY] MODEL WIDTH HEIGHT PARAMS...' with MODEL one of "
                f"{', '.join(m.value for m in CameraModel)}, "
                f"found {' '.join(tokens[:3])!r}...",
            )
        if key in cameras:
            what = "a second camera line without key" if key is None else f"duplicate camera key {key!r}"
            raise FormatError(path, lineno, f"expected one camera per key, found {what}")
        cameras[key] = cam
    if not cameras:
        raise FormatError(
            path, None, "expected at least one camera line 'MODEL WIDTH HEIGHT PARAMS...', found none"
        )
    return cameras
