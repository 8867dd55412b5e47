"""Plain pose lists: one image per line, ``name qw qx qy qz tx ty tz`` (cam_from_world).

This is the hloc localization-results convention (world-to-camera pose, quaternion scalar
first); ``#`` comment lines and blank lines are ignored when reading, names must not contain
whitespace. planarloc writes its localization results in this format with
:func:`write_pose_list` (shortest round-trip float repr, i.e. up to 17 significant digits).

Intrinsics for :func:`read_pose_list` come from the ``camera=`` argument or from a camera
file (:mod:`planarloc.io.camera_file`): lines ``[KEY] MODEL WIDTH HEIGHT PARAMS...`` where a
KEY equal to an image name gives that image's camera (hloc ``queries_with_intrinsics.txt``)
and a keyless line — or the only line of the file, e.g. a COLMAP ``cameras.txt`` with one
camera — applies to all other images.

Gravity: the format does not define the world's up axis (``world_down`` is None): the map
estimates it from its poses, or the user gives it with the dataset option ``up=``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io.camera_file import read_camera_file
from planarloc.io.format_error import FormatError
from planarloc.io.lines import iter_named_lines, parse_pose_fields, resolve_image
from planarloc.io.output import write_text_atomic
from planarloc.io.text import WXYZ_T
from planarloc.map.posed_image import PosedImage

FORMAT = "pose list"
LINE = "'name qw qx qy qz tx ty tz'"


def read_pose_list(
    root: Path,
    *,
    camera: Camera | None = None,
    cameras_file: Path | None = None,
    image_dir: Path | None = None,
    list_file: str = "poses.txt",
    check_images: bool = True,
) -> list[PosedImage]:
    """Read a pose list (format in the module docstring).

    Args:
        root: the list file itself, or a directory containing ``list_file``.
        camera: intrinsics of every image; overrides ``cameras_file``.
        cameras_file: camera file; default ``cameras.txt`` next to the list, if it exists.
        image_dir: directory the names are relative to; default the list's directory.
        list_file: name of the list inside ``root`` when ``root`` is a directory.
        check_images: raise if a listed image does not exist.

    Returns:
        One :class:`PosedImage` per line, ``index`` = line order (0-based).

    Raises:
        FormatError: missing files/images, malformed lines, non-rotations, no intrinsics.
    """
    root = Path(root)
    list_path = root / list_file if root.is_dir() else root
    base = list_path.parent
    img_root = Path(image_dir) if image_dir is not None else base
    cams: dict[str | None, Camera] = {}
    cam_path: Path | None = None
    if camera is not None:
        if not isinstance(camera, Camera):
            raise InputError(f"camera: expected a planarloc Camera, got {type(camera).__name__}")
    else:
        cam_path = Path(cameras_file) if cameras_file is not None else base / "cameras.txt"
        if cameras_file is None and not cam_path.is_file():
            raise FormatError(
                list_path,
                None,
                "cannot determine the camera intrinsics: pass camera=Camera(...) or "
                "cameras_file= (lines '[KEY] MODEL WIDTH HEIGHT PARAMS...'), "
                "or put cameras.txt next to the list",
            )
        cams = read_camera_file(cam_path, FORMAT)
    fallback = (
        camera
        if camera is not None
        else cams.get(None, next(iter(cams.values())) if len(cams) == 1 else None)
    )

    out: list[PosedImage] = []
    for lineno, name, fields in iter_named_lines(list_path, FORMAT, LINE, 8):
        pose = parse_pose_fields(list_path, lineno, fields, WXYZ_T, 2)
        cam = cams.get(name, fallback) if camera is None else camera
        if cam is None:
            raise FormatError(
                list_path,
                lineno,
                f"expected intrinsics for image {name!r} in {cam_path}, found none (no line "
                "with this name and no keyless or single camera line)",
            )
        out.append(
            PosedImage(
                name=name,
                path=resolve_image(list_path, lineno, img_root, name, check=check_images),
                cam_from_world=pose,
                camera=cam,
                index=len(out),
            )
        )
    if not out:
        raise FormatError(list_path, None, f"expected at least one line {LINE}, found none")
    return out


def pose_line(name: str, values: Sequence[float]) -> str:
    """One line ``name qw qx qy qz tx ty tz`` (no newline) from the 7 numbers, written as the
    shortest round-trip floats (so a record's numbers are written exactly as they are)."""
    if not isinstance(name, str) or not name or any(c.isspace() for c in name):
        raise InputError(f"pose list: image names must be non-empty without whitespace, got {name!r}")
    if len(values) != 7:
        raise InputError(
            f"pose list: expected 7 numbers 'qw qx qy qz tx ty tz' for {name!r}, got {len(values)}"
        )
    return name + " " + " ".join(repr(float(v)) for v in values)


def format_pose_line(name: str, cam_from_world: Pose) -> str:
    """One line ``name qw qx qy qz tx ty tz`` (no newline)."""
    if not isinstance(cam_from_world, Pose):
        raise InputError(
            f"pose list: expected a planarloc Pose for {name!r}, got {type(cam_from_world).__name__}"
        )
    return pose_line(name, [*cam_from_world.quat_wxyz, *cam_from_world.t])


def write_pose_list(path: Path, items: Iterable[tuple[str, Pose]]) -> None:
    """Write ``(name, cam_from_world)`` pairs as a pose list (format in the module docstring).

    The file is written to a temporary file and renamed, so an interrupted write never leaves
    a truncated result file.

    Args:
        path: output file (parent directories are created).
        items: ``(image name, cam_from_world)`` pairs; names must not contain whitespace.

    Example:
        >>> write_pose_list(Path("results.txt"), [("q/0001.png", Pose.identity())])  # doctest: +SKIP
        # results.txt: 'q/0001.png 1.0 0.0 0.0 0.0 0.0 0.0 0.0'
    """
    path = Path(path)
    lines = [format_pose_line(name, pose) + "\n" for name, pose in items]
    write_text_atomic(path, lines)
