"""The text formats of one camera, one gravity vector and one pose: one parser (and writer) each.

Every place that reads these texts uses this module: the command line (``--camera``,
``--gravity``), the service's form fields, the ROS bag options (``camera``, ``base_to_camera``)
and the file readers (camera files, gravity files, pose lists, TUM, COLMAP, kapture). Fields are
separated by whitespace or commas.

========================  ===============================================================
text                      meaning
========================  ===============================================================
``MODEL W H PARAMS...``   a camera, COLMAP model names and parameter order
                          (:func:`parse_camera`); which models exist and how many
                          parameters each takes is :class:`~planarloc.geometry.camera.Camera`'s
                          to say, so a model added there is accepted everywhere
``gx gy gz``              a gravity direction (pointing down, any non-zero length) in a
                          camera frame (:func:`parse_gravity`), returned as a unit vector
``qw qx qy qz tx ty tz``  a pose, quaternion first: hloc results, pose lists, COLMAP
                          ``images.txt``, kapture (:data:`WXYZ_T`)
``tx ty tz qx qy qz qw``  a pose, translation first: TUM trajectories, odometry files and
                          ``base_to_camera`` (the order of ``static_transform_publisher``)
                          (:data:`T_XYZW`)
========================  ===============================================================

Quaternions must have unit norm within :data:`QUAT_NORM_TOL` (files store 4-6 decimals) and
are normalised. A bad text raises :class:`TextError` saying what was expected and what was
found; file readers add their file and line (:func:`planarloc.io.lines.located`), the command
line its option, the service its field.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from planarloc.geometry.camera import UNSUPPORTED_COLMAP_MODELS, Camera, CameraModel
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.robust.pair_matches import unit_gravity

#: Largest accepted deviation ``| |q| - 1 |`` of a stored quaternion before it is normalised.
#: Files store quaternions with 4-6 decimals (norm off by <= 1e-4); a larger deviation means the
#: columns are not a quaternion at all.
QUAT_NORM_TOL = 5e-3
#: Pose layouts: ``(name, quaternion slice, translation slice, quaternion order in the text)``.
WXYZ_T = "qw qx qy qz tx ty tz"
T_XYZW = "tx ty tz qx qy qz qw"
#: Every camera model name COLMAP knows, so that an unsupported one is reported as such.
#: every camera model COLMAP knows: the supported ones and those refused with their own message
COLMAP_MODELS = frozenset({m.value for m in CameraModel} | set(UNSUPPORTED_COLMAP_MODELS))
CAMERA_SYNTAX = "'MODEL WIDTH HEIGHT PARAMS...' (COLMAP syntax), e.g. 'PINHOLE 640 480 500 500 320 240'"
_COLUMN = "\x00column\x00"


class TextError(InputError):
    """A text that does not parse; :meth:`at` renders it with the column where the text starts.

    Attributes:
        column: 0-based index of the offending field, or None when the whole text is at fault.
    """

    def __init__(self, template: str, column: int | None = None) -> None:
        self.template = template
        self.column = column
        super().__init__(self.at(1))

    def at(self, first_column: int) -> str:
        """The message, field numbers counted from ``first_column`` (1 for a bare text)."""
        if self.column is None:
            return self.template
        return self.template.replace(_COLUMN, str(first_column + self.column))


def fields(text: str | Sequence[str]) -> list[str]:
    """The fields of a text (whitespace or commas) or of an already split line."""
    if isinstance(text, str):
        return text.replace(",", " ").split()
    return [str(t) for t in text]


def numbers(tokens: Sequence[str], what: str, first: int = 0) -> np.ndarray:
    """Fields as finite floats; ``first``: index of ``tokens[0]`` in the whole text (messages)."""
    out = np.empty(len(tokens))
    for i, tok in enumerate(tokens):
        shown = repr(tok) if len(tok) <= 40 else repr(tok[:37] + "...")
        try:
            out[i] = float(tok)
        except ValueError:
            raise TextError(
                f"expected a number in column {_COLUMN} ({what}), found {shown}", first + i
            ) from None
        if not math.isfinite(out[i]):
            raise TextError(
                f"expected a finite number in column {_COLUMN} ({what}), found {shown}", first + i
            )
    return out


def _model_hint(name: str) -> str:
    supported = ", ".join(m.value for m in CameraModel)
    if name.upper() in COLMAP_MODELS:
        return (
            f"camera model {name} is not supported (supported: {supported}); undistort the images "
            "(e.g. COLMAP image_undistorter) or convert the camera to a supported model"
        )
    return f"expected a camera model name ({supported}) in column {_COLUMN}, found {name!r}"


def is_camera_model(name: str) -> bool:
    """True for a model name :class:`Camera` takes or COLMAP knows (to tell ``KEY MODEL ...`` lines)."""
    return name.upper() in COLMAP_MODELS


def parse_camera(text: str | Sequence[str]) -> Camera:
    """``MODEL WIDTH HEIGHT PARAMS...`` -> :class:`Camera` (model and parameters checked by it).

    Raises:
        TextError: too few fields, a parameter that is not a number, or what ``Camera`` refuses
            (unknown model, listing the supported ones; wrong parameter count; bad size).
    """
    tok = fields(text)
    if len(tok) < 3:
        raise TextError(f"expected {CAMERA_SYNTAX}, found {len(tok)} field(s)")
    numbers(tok[1:3], "image width and height", 1)  # Camera checks they are whole positive pixel counts
    params = numbers(tok[3:], f"{tok[0].upper()} parameter", 3)
    try:
        # The size goes in as text: Camera checks it is a whole pixel count and quotes the text if not.
        return Camera(tok[0], tok[1], tok[2], tuple(params))  # type: ignore[arg-type]  # Camera converts it
    except InputError as exc:
        try:
            CameraModel(tok[0].upper())
        except ValueError:
            raise TextError(_model_hint(tok[0]), 0) from None
        raise TextError(str(exc)) from None


def camera_text(camera: Camera) -> str:
    """The text of a camera, ``MODEL W H PARAMS...`` (parameters in shortest round-trip form)."""
    return " ".join(
        [
            CameraModel(camera.model).value,
            str(camera.width),
            str(camera.height),
            *(repr(float(p)) for p in camera.params),
        ]
    )


def parse_gravity(text: str | Sequence[str] | np.ndarray) -> np.ndarray:
    """``gx gy gz`` (or three numbers) -> (3,) unit direction of gravity in a camera frame.

    Raises:
        TextError: not three finite numbers, or a zero vector.
    """
    if isinstance(text, np.ndarray) or (not isinstance(text, str) and text and not isinstance(text[0], str)):
        g = np.asarray(text, dtype=float).reshape(-1)
    else:
        g = numbers(fields(text), "gravity component")
    if g.shape != (3,):
        raise TextError(
            "expected three numbers 'gx gy gz' (gravity pointing down in the camera frame, not all "
            f"zero), e.g. '0 1 0' for an upright camera, found {g.size}"
        )
    big = float(np.max(np.abs(g)))
    if big > 1.0:  # |g|² overflows beyond ~1e154: scale first (a direction is wanted)
        g = g / big
    try:
        return unit_gravity("gravity", g)
    except InputError:
        raise TextError(
            f"expected a non-zero gravity direction 'gx gy gz' (pointing down in the camera frame), "
            f"found {g.tolist()}"
        ) from None


def pose_from_numbers(values: Sequence[float] | np.ndarray, layout: str = WXYZ_T) -> Pose:
    """The pose of 7 numbers in ``layout`` (:data:`WXYZ_T` or :data:`T_XYZW`).

    Raises:
        TextError: not 7 numbers, or a quaternion whose norm is not 1 within QUAT_NORM_TOL.
    """
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.shape != (7,):
        raise TextError(f"expected 7 numbers '{layout}', found {v.size}")
    q, t = (v[:4], v[4:]) if layout == WXYZ_T else (v[[6, 3, 4, 5]], v[:3])
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise TextError(
            f"expected a unit quaternion (norm 1 +- {QUAT_NORM_TOL:g}), found norm {norm:.6g}; "
            "check the column order of the file"
        )
    return Pose.from_quat_wxyz(q / norm, t)


def parse_pose(text: str | Sequence[str], layout: str = WXYZ_T) -> Pose:
    """A pose from its text: 7 numbers in ``layout`` (module docstring)."""
    tok = fields(text)
    if len(tok) != 7:
        raise TextError(f"expected 7 numbers '{layout}', found {len(tok)} field(s)")
    return pose_from_numbers(numbers(tok, "quaternion or translation"), layout)


def pose_text(pose: Pose, layout: str = WXYZ_T, digits: int | None = None) -> str:
    """The text of a pose in ``layout``: shortest round-trip floats, or ``digits`` decimals."""
    w, x, y, z = (float(v) for v in pose.quat_wxyz)
    values = (w, x, y, z, *pose.t) if layout == WXYZ_T else (*pose.t, x, y, z, w)
    if digits is None:
        return " ".join(repr(float(v)) for v in values)
    return " ".join(f"{float(v):.{digits}f}" for v in values)
