"""KITTI odometry sequences.

Layout of a sequence directory ``root``::

    root/
      image_l/000000.png ...   images, one per frame (also accepted: image_0/, image_2/, or
                               any directory given as ``image_dir``); the number in the file
                               name is the frame index
      poses.txt                one line per frame k = 0, 1, ...: 12 numbers, the 3x4 row-major
                               CAMERA-TO-WORLD matrix [R | c] of camera 0 (world = first
                               camera frame, x right, y down, z forward, metres)
      calib.txt                rectified 3x4 projection matrices P = K [I | t], 12 numbers per
                               line, optionally labelled (``P0: ...``, ``P1: ...``, ``Tr: ...``)
      times.txt                optional: one timestamp (seconds) per frame

Intrinsics: a ``PINHOLE`` camera from ``K`` of the first line of ``calib.txt`` — or, if the lines
are labelled and the images come from ``image_N/``, of line ``PN:`` (``calib_key`` overrides). A
projection matrix with a translation column (``P2`` of the colour cameras) also moves the camera:
``cam_from_cam0 = (I, K⁻¹ P[:, 3])``, since KITTI ``poses.txt`` is for camera 0. The image size
is read from the first image. Blank lines and lines starting with ``#`` are ignored.

Returned poses are ``cam_from_world = (world_from_cam)⁻¹``.

Timestamps: ``PosedImage.timestamp`` is line k of ``times.txt`` (None without it). Images given
as files (``localize``) get the same stamps from :func:`kitti_frame_times`.

Gravity: the world is the first camera's frame, so the format declares down = +y
(:data:`WORLD_DOWN`, exact when that camera is level; a map overrides it with ``up=``).
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.gravity.world import WorldDown
from planarloc.io.format_error import FormatError
from planarloc.io.lines import image_size, iter_data_lines, parse_floats, pose_from_matrix34, read_text
from planarloc.map.posed_image import PosedImage

logger = logging.getLogger(__name__)

FORMAT = "KITTI odometry"
IMAGE_DIRS = ("image_l", "image_0", "image_2")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
#: KITTI's world is camera 0 of the first frame (x right, y down, z forward): down = +y.
WORLD_DOWN = WorldDown(
    (0.0, 1.0, 0.0), "declared", "KITTI: world = first camera frame, down = +y (that camera level)"
)


def _find_image_dir(root: Path, image_dir: str | None) -> Path:
    if image_dir is not None:
        d = root / image_dir
        if not d.is_dir():
            raise FormatError(d, None, "image directory not found (given as image_dir)")
        return d
    for name in IMAGE_DIRS:
        if (root / name).is_dir():
            return root / name
    raise FormatError(
        root, None, f"no image directory found; the {FORMAT} format needs one of {', '.join(IMAGE_DIRS)}/"
    )


def _name(path: Path, root: Path) -> str:
    """Image name: the path relative to the sequence root (or below the image directory's parent)."""
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.relative_to(path.parent.parent).as_posix()


def _read_calib(path: Path, key: str | None) -> tuple[np.ndarray, str]:
    """The 3x4 projection matrix (normalised to P[2, 2] = 1) selected by ``key`` (None = first)."""
    entries: list[tuple[int, str | None, np.ndarray]] = []
    for lineno, tokens in iter_data_lines(path, FORMAT, "the 3x4 projection matrix of the camera"):
        label = None
        if tokens[0].endswith(":"):
            label, tokens = tokens[0][:-1], tokens[1:]
        if len(tokens) != 12:
            raise FormatError(
                path, lineno, f"expected 12 numbers (3x4 projection matrix, row-major), found {len(tokens)}"
            )
        first = 2 if label is not None else 1
        entries.append((lineno, label, parse_floats(path, lineno, tokens, "projection matrix", first)))
    if not entries:
        raise FormatError(path, None, "expected a line with 12 numbers (3x4 projection matrix), found none")
    if key is None:
        lineno, label, values = entries[0]
    else:
        found = [e for e in entries if e[1] == key]
        if not found:
            labels = ", ".join(str(e[1]) for e in entries)
            raise FormatError(path, None, f"expected a line labelled '{key}:', found labels: {labels}")
        lineno, label, values = found[0]
    P = values.reshape(3, 4)
    scale = float(np.abs(P[:, :3]).max())
    lower = np.abs([P[1, 0], P[2, 0], P[2, 1], P[0, 1]]).max()
    if P[2, 2] <= 0 or scale == 0 or lower > 1e-6 * scale:
        raise FormatError(
            path,
            lineno,
            "expected a rectified projection matrix K [I | t] (K upper-triangular, no skew, K[2,2] > 0), "
            f"found rows {P.tolist()}",
        )
    return P / P[2, 2], f"{path.name}:{lineno}"


def _read_times(path: Path) -> list[float]:
    times = []
    for lineno, tokens in iter_data_lines(path, FORMAT, "one timestamp per frame"):
        if len(tokens) != 1:
            raise FormatError(
                path, lineno, f"expected 1 number (timestamp in seconds), found {len(tokens)} fields"
            )
        times.append(float(parse_floats(path, lineno, tokens, "timestamp")[0]))
    return times


def kitti_frame_times(paths: Sequence[Path]) -> list[float] | None:
    """The ``times.txt`` stamps of image files that are frames of KITTI sequences.

    An image ``root/image_l/000012.png`` (or in ``image_N/``) of a sequence folder ``root`` with a
    ``times.txt`` is frame 12, taken at line 12's time (seconds), as :func:`read_kitti` reads it.

    Args:
        paths: (N,) image files, e.g. the queries of ``planarloc localize``.

    Returns:
        (N,) stamps in seconds, or None unless every path is such a frame with a line in its
        ``times.txt`` (a mix of seconds and frame numbers would be no trajectory).

    Raises:
        FormatError: a ``times.txt`` that is not one number per line.

    Example:
        >>> kitti_frame_times([Path("seq/image_l/000002.png")])   # doctest: +SKIP
        [0.207491]
    """
    loaded: dict[Path, list[float] | None] = {}
    out = []
    for path in paths:
        path = Path(
            os.path.abspath(path)
        )  # not resolved: a linked image belongs to the folder it is named in
        folder = path.parent
        if not (
            path.stem.isdigit()
            and path.suffix.lower() in IMAGE_SUFFIXES
            and (folder.name in IMAGE_DIRS or re.fullmatch(r"image_\d+", folder.name))
        ):
            return None
        times_path = folder.parent / "times.txt"
        if times_path not in loaded:
            loaded[times_path] = _read_times(times_path) if times_path.is_file() else None
        times = loaded[times_path]
        if times is None or int(path.stem) >= len(times):
            return None
        out.append(times[int(path.stem)])
    return out or None


def read_kitti(
    root: Path, *, image_dir: str | None = None, calib_key: str | None = None, check_images: bool = True
) -> list[PosedImage]:
    """Read a KITTI odometry sequence (format in the module docstring).

    Args:
        root: the sequence directory.
        image_dir: image sub-directory; default: the first of ``image_l``, ``image_0``,
            ``image_2`` that exists.
        calib_key: label of the ``calib.txt`` line to use (e.g. ``"P2"``); default: the first
            line, or ``PN`` for ``image_N/`` when lines are labelled.
        check_images: raise if an image of a posed frame does not exist.

    Returns:
        One :class:`PosedImage` per line of ``poses.txt``, ``index`` = frame number, names
        like ``"image_l/000012.png"``, sorted by index.

    Raises:
        FormatError: missing files/images, wrong column counts, non-numbers, non-rotations.

    Example:
        >>> frames = read_kitti(Path("data/kitti_seq2"))            # doctest: +SKIP
        >>> frames[1].cam_from_world.center                          # doctest: +SKIP
        array([0.0515, -0.0242, 1.0007])
    """
    root = Path(root)
    img_dir = _find_image_dir(root, image_dir)
    poses_path, calib_path, times_path = root / "poses.txt", root / "calib.txt", root / "times.txt"
    read_text(poses_path, FORMAT, "one 3x4 camera-to-world matrix (12 numbers) per frame")

    P, calib_where = _read_calib(calib_path, _calib_key(calib_path, img_dir, calib_key))
    K = P[:, :3]
    cam_from_cam0 = Pose(np.eye(3), np.linalg.solve(K, P[:, 3]))
    moved = bool(np.any(cam_from_cam0.t != 0))

    files = sorted(p for p in img_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if all(p.stem.isdigit() for p in files):
        by_index = {int(p.stem): p for p in files}
    else:
        by_index = dict(enumerate(files))
    times = _read_times(times_path) if times_path.is_file() else None

    frames = _read_frames(poses_path, img_dir, by_index, cam_from_cam0, check_images)
    if not frames:
        raise FormatError(
            poses_path, None, "expected one 3x4 camera-to-world matrix per frame, found no pose"
        )
    if times is not None and len(times) < len(frames):
        raise FormatError(
            times_path, None, f"expected {len(frames)} timestamps (one per pose), found {len(times)}"
        )
    extra = sorted(set(by_index) - {k for k, _, _ in frames})
    if extra:
        logger.warning(
            "%s: %d image(s) in %s/ have no pose in poses.txt; skipped", root, len(extra), img_dir.name
        )

    width, height = image_size(frames[0][1])
    camera = Camera("PINHOLE", width, height, (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    logger.debug(
        "%s: camera %s from %s%s", root, camera, calib_where, " (with baseline offset)" if moved else ""
    )
    return [
        PosedImage(
            name=_name(path, root),
            path=path.absolute(),
            cam_from_world=pose,
            camera=camera,
            index=k,
            timestamp=None if times is None else times[k],
            world_down=WORLD_DOWN,
        )
        for k, path, pose in frames
    ]


def _calib_key(calib_path: Path, img_dir: Path, calib_key: str | None) -> str | None:
    """The ``calib.txt`` label to use: ``calib_key``, else ``PN`` for ``image_N/`` when that line exists."""
    if calib_key is None:
        m = re.fullmatch(r"image_(\d)", img_dir.name)
        text = read_text(calib_path, FORMAT, "the 3x4 projection matrix of the camera")
        if m and re.search(rf"^\s*P{m.group(1)}:", text, flags=re.MULTILINE):
            calib_key = f"P{m.group(1)}"
    return calib_key


def _read_frames(
    poses_path: Path, img_dir: Path, by_index: dict[int, Path], cam_from_cam0: Pose, check_images: bool
) -> list[tuple[int, Path, Pose]]:
    """(frame number, image file, cam_from_world) per line of ``poses.txt``."""
    frames: list[tuple[int, Path, Pose]] = []
    for k, (lineno, tokens) in enumerate(
        iter_data_lines(poses_path, FORMAT, "one 3x4 camera-to-world matrix (12 numbers) per frame")
    ):
        if len(tokens) != 12:
            raise FormatError(
                poses_path, lineno, f"expected 12 numbers (3x4 camera-to-world matrix), found {len(tokens)}"
            )
        world_from_cam0 = pose_from_matrix34(
            poses_path, lineno, parse_floats(poses_path, lineno, tokens, "pose matrix").reshape(3, 4)
        )
        image_path = by_index.get(k)
        if image_path is None:
            image_path = img_dir / f"{k:06d}.png"
            if check_images:
                raise FormatError(
                    poses_path,
                    lineno,
                    f"expected an image for frame {k} in {img_dir}/, found none ({image_path.name})",
                )
        frames.append((k, image_path, cam_from_cam0 @ world_from_cam0.inverse()))
    return frames
