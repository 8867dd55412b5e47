"""kapture datasets (NAVER LABS Europe, format 1.x), camera records with trajectories.

Layout of a dataset directory ``root``; all files are comma-separated, ``#`` starts a comment::

    root/sensors/
      sensors.txt          'sensor_id, name, sensor_type, model, width, height, params...'
                           e.g. 'cam0, front, camera, PINHOLE, 640, 480, 500, 500, 320, 240'
                           (camera models SIMPLE_PINHOLE, PINHOLE, OPENCV; name may be empty;
                           sensors of other types are ignored)
      trajectories.txt     'timestamp, device_id, qw, qx, qy, qz, tx, ty, tz': WORLD-TO-DEVICE
                           pose (device_from_world), device = a camera or a rig
      rigs.txt             optional 'rig_id, sensor_id, qw, qx, qy, qz, tx, ty, tz': sensor_from_rig
      records_camera.txt   'timestamp, device_id, image_path'
      records_data/        the images, at records_data/<image_path>

An image's pose is the trajectory entry with the same timestamp and camera id, or, if the
camera belongs to a rig, ``cam_from_world = cam_from_rig ∘ rig_from_world`` with the rig's
entry at that timestamp. Records without a pose (e.g. query images) are skipped with a warning.
Poses are never guessed, as in the ROS bag reader: trajectory entries that share a timestamp and
device with different poses (or rig entries giving a rig's sensor two poses) are all dropped,
each with a warning naming the file and line; an entry repeated with the same pose counts once.

Gravity: the format does not define the world's up axis (``world_down`` is None): the map
estimates it from its poses, or the user gives it with the dataset option ``up=``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.io.camera_file import camera_from_tokens
from planarloc.io.format_error import FormatError
from planarloc.io.lines import iter_data_lines, parse_floats, parse_pose_fields, resolve_image
from planarloc.io.text import WXYZ_T
from planarloc.map.posed_image import PosedImage

logger = logging.getLogger(__name__)

FORMAT = "kapture"
POSE_FIELDS = "'timestamp, device_id, qw, qx, qy, qz, tx, ty, tz'"


def _timestamp_key(path: Path, lineno: int, token: str) -> int | float:
    try:
        return int(token)
    except ValueError:
        return float(parse_floats(path, lineno, [token], "timestamp")[0])


#: Poses of one key closer than this (matrix entries) are the same pose given twice.
SAME_POSE_TOL = 1e-9


PoseKey = TypeVar("PoseKey", bound=tuple)
"""A pose line's key: (timestamp, device) in trajectories, (rig, sensor) in rigs."""


def _read_poses(
    path: Path, fields: str, key: Callable[[int, str, str], PoseKey]
) -> dict[PoseKey, tuple[int, Pose]]:
    """``{key(lineno, field0, field1): (lineno, pose)}`` of a 9-field kapture pose file
    (trajectories, rigs). A key given on several lines with different poses is dropped, with a
    warning per line (module docstring); with the same pose, its first line counts."""
    lines: dict[PoseKey, list[tuple[int, Pose]]] = {}
    for lineno, tokens in iter_data_lines(path, FORMAT, f"poses {fields}", sep=","):
        if len(tokens) != 9:
            raise FormatError(path, lineno, f"expected 9 fields {fields}, found {len(tokens)}")
        pose = parse_pose_fields(path, lineno, tokens[2:], WXYZ_T, 3)
        lines.setdefault(key(lineno, tokens[0], tokens[1]), []).append((lineno, pose))
    poses: dict[PoseKey, tuple[int, Pose]] = {}
    for k, given in lines.items():
        first = given[0][1]
        if all(np.allclose(first.matrix, pose.matrix, atol=SAME_POSE_TOL) for _, pose in given[1:]):
            poses[k] = given[0]
            continue
        for lineno, _ in given:
            others = ", ".join(str(n) for n, _ in given if n != lineno)
            logger.warning(
                "%s:%d: %s has different poses on line(s) %s; none of them is used",
                path,
                lineno,
                ", ".join(str(v) for v in k),
                others,
            )
    return poses


def read_kapture(root: Path, *, timestamp_scale: float = 1.0, check_images: bool = True) -> list[PosedImage]:
    """Read the posed camera images of a kapture dataset (format in the module docstring).

    Args:
        root: the dataset directory (containing ``sensors/``).
        timestamp_scale: seconds per timestamp unit (kapture does not fix the unit; e.g. 1e-6
            for microseconds); ``PosedImage.timestamp = timestamp * timestamp_scale``.
        check_images: raise if a recorded image does not exist.

    Returns:
        One :class:`PosedImage` per camera record with a pose, ``index`` = position in
        ``records_camera.txt`` (0-based), name = the record's ``image_path``.

    Raises:
        FormatError: missing files/images, malformed lines, unknown sensors, unsupported models.
    """
    root = Path(root)
    sdir = root / "sensors"
    sensors_path, traj_path = sdir / "sensors.txt", sdir / "trajectories.txt"
    records_path, rigs_path = sdir / "records_camera.txt", sdir / "rigs.txt"

    camera_lines = _camera_lines(sensors_path)
    cameras: dict[str, Camera] = {}

    def camera_of(sensor_id: str) -> Camera:
        if sensor_id not in cameras:
            lineno, tokens = camera_lines[sensor_id]
            cameras[sensor_id] = camera_from_tokens(sensors_path, lineno, tokens, first_column=4)
        return cameras[sensor_id]

    trajectories = _read_poses(
        traj_path, POSE_FIELDS, lambda ln, ts, dev: (_timestamp_key(traj_path, ln, ts), dev)
    )
    cam_from_rig = _cam_from_rig(rigs_path)
    out: list[PosedImage] = []
    unposed = 0
    for index, (lineno, tokens) in enumerate(
        iter_data_lines(records_path, FORMAT, "'timestamp, device_id, image_path' per image", sep=",")
    ):
        if len(tokens) != 3:
            raise FormatError(
                records_path,
                lineno,
                f"expected 3 fields 'timestamp, device_id, image_path', found {len(tokens)}",
            )
        ts_token, device, image_path = tokens
        ts = _timestamp_key(records_path, lineno, ts_token)
        if device not in camera_lines:
            raise FormatError(
                records_path, lineno, f"expected a camera sensor id of sensors.txt, found {device!r}"
            )
        pose = _record_pose(ts, device, trajectories, cam_from_rig)
        if pose is None:
            unposed += 1
            continue
        out.append(
            PosedImage(
                name=image_path,
                path=resolve_image(
                    records_path, lineno, sdir / "records_data", image_path, check=check_images
                ),
                cam_from_world=pose,
                camera=camera_of(device),
                index=index,
                timestamp=float(ts) * timestamp_scale,
            )
        )
    if unposed:
        logger.warning("%s: %d camera record(s) have no pose in trajectories.txt; skipped", root, unposed)
    if not out:
        raise FormatError(
            records_path, None, "expected camera records with a pose in trajectories.txt, found none"
        )
    return out


def _camera_lines(sensors_path: Path) -> dict[str, tuple[int, list[str]]]:
    """sensor id -> (line number, model and params tokens) of every camera in ``sensors.txt``."""
    camera_lines: dict[str, tuple[int, list[str]]] = {}
    for lineno, tokens in iter_data_lines(
        sensors_path, FORMAT, "'sensor_id, name, sensor_type, model, params...' per sensor", sep=","
    ):
        if len(tokens) < 3:
            raise FormatError(
                sensors_path,
                lineno,
                f"expected 'sensor_id, name, sensor_type, ...', found {len(tokens)} fields",
            )
        if tokens[2].lower() == "camera":
            camera_lines[tokens[0]] = (lineno, tokens[3:])
    return camera_lines


def _cam_from_rig(rigs_path: Path) -> dict[str, tuple[str, Pose]]:
    """sensor id -> (its rig id, cam_from_rig) from ``rigs.txt`` (empty without the file)."""
    cam_from_rig: dict[str, tuple[str, Pose]] = {}
    if rigs_path.is_file():
        for (rig, sensor), (_, pose) in _read_poses(
            rigs_path,
            "'rig_id, sensor_id, qw, qx, qy, qz, tx, ty, tz'",
            lambda ln, rig, sensor: (rig, sensor),
        ).items():
            cam_from_rig[sensor] = (rig, pose)
    return cam_from_rig


def _record_pose(
    ts: object, device: str, trajectories: dict, cam_from_rig: dict[str, tuple[str, Pose]]
) -> Pose | None:
    """cam_from_world of a record: the device's own trajectory pose, else through its rig; None if unposed."""
    if (ts, device) in trajectories:
        return trajectories[(ts, device)][1]
    if device in cam_from_rig and (ts, cam_from_rig[device][0]) in trajectories:
        rig, c_from_r = cam_from_rig[device]
        return c_from_r @ trajectories[(ts, rig)][1]
    return None
