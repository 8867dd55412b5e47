"""Intrinsics text files: one camera per line, COLMAP model names and parameter order.

Format (``#`` starts a comment line)::

    [KEY] MODEL WIDTH HEIGHT PARAMS...

- ``MODEL`` is a COLMAP camera model; planarloc supports ``SIMPLE_PINHOLE`` (f cx cy),
  ``PINHOLE`` (fx fy cx cy) and ``OPENCV`` (fx fy cx cy k1 k2 p1 p2). Other COLMAP models
  (e.g. ``SIMPLE_RADIAL``) are rejected with an error naming the model.
- ``KEY`` is optional. Without it, the line is a camera for every image (TUM ``camera.txt``:
  ``PINHOLE 640 480 517.3 516.5 318.6 255.3``). With it, the key is a COLMAP camera id
  (``cameras.txt``: ``1 PINHOLE 640 480 ...``) or an image name (hloc
  ``queries_with_intrinsics.txt``: ``query/0001.jpg PINHOLE 640 480 ...``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from planarloc.geometry.camera import NUM_PARAMS, Camera, CameraModel
from planarloc.geometry.validation import InputError
from planarloc.io.format_error import FormatError
from planarloc.io.lines import iter_data_lines, parse_floats, parse_int

#: Every model name COLMAP knows (so that an unsupported one is reported as such, not as garbage).
COLMAP_MODELS = frozenset(
    {
        "SIMPLE_PINHOLE",
        "PINHOLE",
        "SIMPLE_RADIAL",
        "RADIAL",
        "OPENCV",
        "OPENCV_FISHEYE",
        "FULL_OPENCV",
        "FOV",
        "SIMPLE_RADIAL_FISHEYE",
        "RADIAL_FISHEYE",
        "THIN_PRISM_FISHEYE",
        "RAD_TAN_THIN_PRISM_FISHEYE",
        "SIMPLE_DIVISION",
        "DIVISION",
    }
)
SUPPORTED = ", ".join(m.value for m in CameraModel)


def camera_from_tokens(path: Path, lineno: int, tokens: Sequence[str], first_column: int = 1) -> Camera:
    """A :class:`Camera` from the fields ``MODEL WIDTH HEIGHT PARAMS...`` of one line.

    Args:
        path, lineno: position for error messages.
        tokens: the fields, starting with the model name.
        first_column: 1-based column of ``tokens[0]`` in the line (for messages).
    """
    if len(tokens) < 3:
        raise FormatError(
            path, lineno, f"expected 'MODEL WIDTH HEIGHT PARAMS...', found {len(tokens)} field(s)"
        )
    name = tokens[0].upper()
    try:
        model = CameraModel(name)
    except ValueError:
        if name in COLMAP_MODELS:
            raise FormatError(
                path,
                lineno,
                f"camera model {tokens[0]} is not supported (supported: {SUPPORTED}); "
                "undistort the images (e.g. COLMAP image_undistorter) or convert the camera to OPENCV",
            ) from None
        raise FormatError(
            path,
            lineno,
            f"expected a camera model name ({SUPPORTED}) in column {first_column}, found {tokens[0]!r}",
        ) from None
    width = parse_int(path, lineno, tokens[1], "image width", first_column + 1)
    height = parse_int(path, lineno, tokens[2], "image height", first_column + 2)
    n = NUM_PARAMS[model]
    if len(tokens) - 3 != n:
        raise FormatError(
            path, lineno, f"expected {n} parameters for camera model {model.value}, found {len(tokens) - 3}"
        )
    params = parse_floats(path, lineno, tokens[3:], f"{model.value} parameter", first_column + 3)
    try:
        return Camera(model, width, height, tuple(params))
    except InputError as exc:
        raise FormatError(path, lineno, str(exc)) from None


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
        if tokens[0].upper() in COLMAP_MODELS:
            key, cam = None, camera_from_tokens(path, lineno, tokens, 1)
        elif len(tokens) > 1 and tokens[1].upper() in COLMAP_MODELS:
            key, cam = tokens[0], camera_from_tokens(path, lineno, tokens[1:], 2)
        else:
            raise FormatError(
                path,
                lineno,
                f"expected '[KEY] MODEL WIDTH HEIGHT PARAMS...' with MODEL one of {SUPPORTED}, "
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
