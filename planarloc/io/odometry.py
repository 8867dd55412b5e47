"""Wheel-odometry pose files for sequential localization (reader), and ordered image lists.

Odometry file (TUM trajectory layout), one line per frame (or per odometry sample)::

    # timestamp tx ty tz qx qy qz qw
    0.000 0.0 0.0 0.0 0 0 0 1
    0.100 0.0 0.0 1.02 0 0.0087 0 0.99996

``timestamp`` in seconds; ``t`` and ``q`` (x, y, z, w order, unit norm) give the pose of the
camera in the odometry frame, ``odom_from_cam`` (camera-to-odometry, like TUM ground truth).
Only differences between frames are used, so the odometry frame is arbitrary. If the poses are
of the robot base, pass ``base_from_camera`` (the camera's pose on the robot). Frames are
associated by nearest timestamp within ``max_dt``; a frame without a sample gets None (the
sequence localizer then uses visual odometry for it).

Image list for ``localize --sequence``: one frame per line, ``path`` or ``timestamp path``
(paths relative to the list's folder), in stream order; ``#`` starts a comment. Each image once,
timestamps increasing (an error names the line otherwise).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.io.format_error import FormatError
from planarloc.io.lines import iter_data_lines, parse_floats
from planarloc.io.tum import associate_timestamps, read_tum_trajectory

logger = logging.getLogger(__name__)

FORMAT = "odometry (TUM layout)"
DEFAULT_MAX_DT = 0.02


def read_odometry(
    path: Path,
    stamps: Sequence[float] | None = None,
    max_dt: float = DEFAULT_MAX_DT,
    base_from_camera: Pose | None = None,
) -> list[Pose | None]:
    """``cam_from_odom`` per frame from an odometry file (module docstring).

    Args:
        path: the file.
        stamps: (N,) frame times to associate; None = one line per frame, in order.
        max_dt: association tolerance in seconds.
        base_from_camera: camera pose on the robot when the file holds base poses.

    Returns:
        N poses (None where no sample is within ``max_dt``), or one per line without ``stamps``.
    """
    path = Path(path)
    times, odom_from_x = read_tum_trajectory(path, FORMAT)
    if base_from_camera is not None:
        odom_from_x = [p @ base_from_camera for p in odom_from_x]
    poses = [p.inverse() for p in odom_from_x]
    if stamps is None:
        return list(poses)
    idx = associate_timestamps(np.asarray(stamps, dtype=float), times, max_dt)
    missing = int((idx < 0).sum())
    if missing == len(idx) and len(idx):
        raise FormatError(
            path,
            None,
            f"no odometry sample within {max_dt} s of any of the {len(idx)} frames; "
            "check that the odometry and the frames use the same clock",
        )
    if missing:
        logger.warning(
            "%s: %d of %d frames have no odometry sample within %g s", path, missing, len(idx), max_dt
        )
    return [poses[i] if i >= 0 else None for i in idx]


def read_image_list(path: Path) -> list[tuple[float | None, Path]]:
    """``(timestamp or None, image path)`` per line of an image list (module docstring)."""
    path = Path(path)
    out: list[tuple[float | None, Path]] = []
    seen: dict[str, int] = {}
    last: tuple[float, int] | None = None
    for lineno, tokens in iter_data_lines(path, "image list", "one 'path' or 'timestamp path' per line"):
        if len(tokens) == 1:
            stamp, name = None, tokens[0]
        elif len(tokens) == 2:
            stamp, name = float(parse_floats(path, lineno, tokens[:1], "timestamp in seconds")[0]), tokens[1]
        else:
            raise FormatError(
                path, lineno, f"expected 'path' or 'timestamp path', found {len(tokens)} fields"
            )
        image = Path(name) if Path(name).is_absolute() else path.parent / name
        if not image.is_file():
            raise FormatError(path, lineno, f"image {image} does not exist")
        key = os.path.realpath(image)
        if key in seen:
            raise FormatError(
                path,
                lineno,
                f"image {image} is already listed on line {seen[key]}; a stream shows each frame once",
            )
        seen[key] = lineno
        if stamp is not None:
            if last is not None and stamp <= last[0]:
                raise FormatError(
                    path,
                    lineno,
                    f"timestamp {stamp:.6f} is not after line {last[1]}'s {last[0]:.6f}; "
                    "a stream's frames come in time order",
                )
            last = (stamp, lineno)
        out.append((stamp, image))
    if not out:
        raise FormatError(path, None, "expected one image per line, found none")
    if any(s is None for s, _ in out) and any(s is not None for s, _ in out):
        raise FormatError(path, None, "either every line has a timestamp or none has")
    return out
