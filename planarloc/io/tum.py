"""TUM RGB-D sequences (Sturm et al., IROS 2012), and the timestamp association shared with
other RGB-D formats (OpenLORIS).

Layout of a sequence directory ``root``::

    root/
      rgb.txt           '# comment' lines, then 'timestamp filename' per frame, e.g.
                        '1305031102.175304 rgb/1305031102.175304.png' (filename relative to root)
      groundtruth.txt   'timestamp tx ty tz qx qy qz qw': CAMERA-TO-WORLD pose (world_from_cam,
                        metres, quaternion in x y z w order) — or of a body frame, see
                        ``base_from_camera``
      depth.txt         optional, like rgb.txt; uint16 PNGs, metres = value / 5000
      camera.txt        optional intrinsics, one line 'PINHOLE width height fx fy cx cy' or any
                        line '[KEY] MODEL width height params...' (see planarloc.io.camera_file)

Association: each rgb frame takes the ground-truth sample (and the depth frame) with the
nearest timestamp if it is within ``max_dt`` seconds; frames without a pose are skipped (one
warning with their count), frames without depth get ``depth_path = None``. No interpolation.
Stamps are never guessed, as in the ROS bag reader: ground-truth lines that share a timestamp
with different poses are all dropped, each with a warning naming the file and line (a frame at
that time cannot be given the right one); lines repeating the same pose count once.

Intrinsics, first that applies: ``camera=`` argument; ``tum_camera="fr1"|"fr2"|"fr3"``
(TUM's published pinhole defaults for 640x480, distortion not included); ``camera.txt``; the
freiburg number in the directory name (``rgbd_dataset_freiburg2_...``). Otherwise an error
asks for one of them. (Explicit arguments win over files so that an argument is never ignored.)

Gravity: TUM does not define the world's up axis (``world_down`` is None; the map estimates it),
except for sequences of a planarloc generated world (a ``world.json`` of
``planarloc.synthetic.world`` in the parent directory), whose world has y down
(:data:`GENERATED_WORLD_DOWN`).
"""

from __future__ import annotations

import json
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.gravity.world import WorldDown
from planarloc.io.camera_file import read_camera_file
from planarloc.io.format_error import FormatError
from planarloc.io.lines import iter_data_lines, parse_floats, parse_pose_fields, resolve_image
from planarloc.io.output import write_text_atomic
from planarloc.io.text import T_XYZW
from planarloc.map.posed_image import PosedImage

logger = logging.getLogger(__name__)

FORMAT = "TUM RGB-D"
#: TUM's published pinhole intrinsics of the Freiburg Kinects (640x480).
TUM_CAMERAS = {
    "fr1": Camera("PINHOLE", 640, 480, (517.3, 516.5, 318.6, 255.3)),
    "fr2": Camera("PINHOLE", 640, 480, (520.9, 521.0, 325.1, 249.7)),
    "fr3": Camera("PINHOLE", 640, 480, (535.4, 539.2, 320.1, 247.6)),
}
TUM_DEPTH_SCALE = 5000.0
DEFAULT_MAX_DT = 0.02
#: World frame of planarloc's generated worlds (planarloc.synthetic.world.export): y down.
GENERATED_WORLD_DOWN = WorldDown(
    (0.0, 1.0, 0.0), "declared", "planarloc generated world (world.json): down = +y"
)
GENERATED_WORLD_GENERATOR = "planarloc.synthetic.world"


def associate_timestamps(query: object, reference: object, max_dt: float) -> np.ndarray:
    """For each query timestamp, the index of the nearest reference timestamp within ``max_dt``.

    Args:
        query: (N,) timestamps in seconds.
        reference: (M,) timestamps in seconds, any order (duplicates allowed).
        max_dt: largest accepted ``|query - reference|`` in seconds (inclusive).

    Returns:
        (N,) int64 indices into ``reference``; -1 where no reference is within ``max_dt``.
        Ties go to the earlier reference. A reference may be used by several queries.

    Example:
        >>> associate_timestamps([0.0, 0.5, 1.01], [1.0, 0.0], 0.02)
        array([ 1, -1,  0])
    """
    q = np.asarray(query, dtype=float).reshape(-1)
    r = np.asarray(reference, dtype=float).reshape(-1)
    if not np.isfinite(max_dt) or max_dt < 0:
        raise InputError(f"max_dt: expected a finite number >= 0 seconds, got {max_dt!r}")
    if r.size == 0 or q.size == 0:
        return np.full(q.shape, -1, dtype=np.int64)
    order = np.argsort(r, kind="stable")
    rs = r[order]
    pos = np.searchsorted(rs, q)
    left = np.clip(pos - 1, 0, len(rs) - 1)
    right = np.clip(pos, 0, len(rs) - 1)
    d_left, d_right = np.abs(q - rs[left]), np.abs(rs[right] - q)
    best = np.where(d_right < d_left, right, left)
    return np.where(np.minimum(d_left, d_right) <= max_dt, order[best], -1).astype(np.int64)


@dataclass(frozen=True)
class _Entry:
    lineno: int
    timestamp: float
    name: str


def read_timestamped_list(path: Path, fmt: str, purpose: str) -> list[_Entry]:
    """Entries of a 'timestamp filename' list (TUM rgb.txt/depth.txt, OpenLORIS color.txt)."""
    entries = []
    for lineno, tokens in iter_data_lines(path, fmt, purpose):
        if len(tokens) != 2:
            raise FormatError(path, lineno, f"expected 2 fields 'timestamp filename', found {len(tokens)}")
        ts = float(parse_floats(path, lineno, tokens[:1], "timestamp in seconds")[0])
        entries.append(_Entry(lineno, ts, tokens[1]))
    return entries


#: Poses at one stamp closer than this (matrix entries) are the same pose given twice.
SAME_POSE_TOL = 1e-9


def distinct_stamps(
    path: Path, times: list[float], poses: list[Pose], linenos: list[int]
) -> tuple[list[float], list[Pose], list[int]]:
    """The samples of a pose file without ambiguous stamps: samples sharing a stamp count once
    if their poses agree, else all of them are dropped with a warning per line naming the file,
    the line and the other lines (as :func:`planarloc.io.rosbag.distinct_samples` does for bags)."""
    by_stamp: dict[float, list[int]] = {}
    for i, t in enumerate(times):
        by_stamp.setdefault(float(t), []).append(i)
    keep = []
    for t, idx in by_stamp.items():
        if len(idx) == 1 or all(
            np.allclose(poses[idx[0]].matrix, poses[i].matrix, atol=SAME_POSE_TOL) for i in idx[1:]
        ):
            keep.append(idx[0])
            continue
        for i in idx:
            others = ", ".join(str(linenos[j]) for j in idx if j != i)
            logger.warning(
                "%s:%d: timestamp %.9g has different poses on line(s) %s; none of them is used",
                path,
                linenos[i],
                t,
                others,
            )
    keep.sort()
    return [times[i] for i in keep], [poses[i] for i in keep], [linenos[i] for i in keep]


def read_tum_trajectory(
    path: Path, fmt: str = FORMAT, *, distinct: bool = False
) -> tuple[np.ndarray, list[Pose]]:
    """A TUM trajectory file 'timestamp tx ty tz qx qy qz qw' (``to_world`` poses).

    Args:
        path: the file.
        fmt: format name for messages.
        distinct: drop the samples that share a timestamp with different poses, warning for each
            (:func:`distinct_stamps`; for files whose poses are looked up by time); False: every
            line, in order.

    Returns:
        (N,) timestamps and the N poses ``world_from_frame`` (x_world = R x_frame + t).
    """
    times, poses, linenos = [], [], []
    for lineno, tokens in iter_data_lines(path, fmt, "poses 'timestamp tx ty tz qx qy qz qw'"):
        if len(tokens) != 8:
            raise FormatError(
                path, lineno, f"expected 8 fields 'timestamp tx ty tz qx qy qz qw', found {len(tokens)}"
            )
        times.append(float(parse_floats(path, lineno, tokens[:1], "timestamp in seconds")[0]))
        poses.append(parse_pose_fields(path, lineno, tokens[1:], T_XYZW, 2))
        linenos.append(lineno)
    if not poses:
        raise FormatError(path, None, "expected poses 'timestamp tx ty tz qx qy qz qw', found none")
    if distinct:
        times, poses, _ = distinct_stamps(path, times, poses, linenos)
        if not poses:
            raise FormatError(
                path, None, "every timestamp has different poses on several lines; no pose is usable"
            )
    return np.array(times), poses


def resolve_camera(root: Path, fmt: str, camera: Camera | None, preset: Camera | None, hint: str) -> Camera:
    """Intrinsics: ``camera`` argument, else ``preset``, else ``root/camera.txt``, else an error."""
    if camera is not None:
        if not isinstance(camera, Camera):
            raise InputError(f"camera: expected a planarloc Camera, got {type(camera).__name__}")
        return camera
    if preset is not None:
        return preset
    path = root / "camera.txt"
    if path.is_file():
        cams = read_camera_file(path, fmt)
        if len(cams) != 1:
            raise FormatError(path, None, f"expected exactly one camera line, found {len(cams)}")
        return next(iter(cams.values()))
    raise FormatError(root, None, f"cannot determine the camera intrinsics of this {fmt} sequence; {hint}")


def generated_world_down(root: Path) -> WorldDown | None:
    """:data:`GENERATED_WORLD_DOWN` if ``root`` is a session of a planarloc generated world
    (``root/../world.json`` names the generator), else None."""
    path = Path(root).absolute().parent / "world.json"
    if not path.is_file():
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        logger.debug("%s: not a readable world.json; world gravity unknown", path)
        return None
    generated = isinstance(doc, dict) and doc.get("generator") == GENERATED_WORLD_GENERATOR
    return GENERATED_WORLD_DOWN if generated else None


@dataclass(frozen=True)
class RgbdLayout:
    """The files of a timestamped RGB(-D) sequence with a TUM-style trajectory.

    Attributes:
        fmt: format name for messages.
        image_list: 'timestamp filename' list of the colour images (relative to the root).
        depth_list: optional 'timestamp filename' list of depth images (used if it exists).
        depth_dir: optional depth directory whose file stems are timestamps (used if
            ``depth_list`` does not exist).
        pose_file: TUM trajectory file of the camera or, with ``base_from_camera``, of a body.
    """

    fmt: str
    image_list: str
    depth_list: str | None = None
    depth_dir: str | None = None
    pose_file: str = "groundtruth.txt"


TUM_LAYOUT = RgbdLayout(FORMAT, "rgb.txt", "depth.txt")


def read_rgbd_sequence(
    root: Path,
    layout: RgbdLayout,
    camera: Camera,
    *,
    depth_scale: float,
    base_from_camera: Pose | None,
    max_dt: float,
    check_images: bool,
    world_down: WorldDown | None = None,
) -> list[PosedImage]:
    """The shared reader of timestamped RGB(-D) sequences with a TUM-style trajectory.

    Args:
        root: sequence directory.
        layout: its files (:class:`RgbdLayout`).
        camera: intrinsics of every image.
        depth_scale: stored depth value per metre.
        base_from_camera: extrinsic of the camera in the trajectory's body frame; ``None`` if
            the trajectory is the camera's.
        max_dt: association tolerance in seconds.
        check_images: raise if a listed image does not exist.
        world_down: the world's down direction if the format declares one.
    """
    if base_from_camera is not None and not isinstance(base_from_camera, Pose):
        raise InputError(
            f"base_from_camera: expected a planarloc Pose, got {type(base_from_camera).__name__}"
        )
    fmt, image_list, pose_file = layout.fmt, layout.image_list, layout.pose_file
    list_path = root / image_list
    entries = read_timestamped_list(list_path, fmt, "'timestamp filename' per colour image")
    gt_times, world_from_body = read_tum_trajectory(root / pose_file, fmt, distinct=True)

    depth_times, depth_paths = _depth_images(root, layout, check_images)
    ts = np.array([e.timestamp for e in entries])
    pose_idx = associate_timestamps(ts, gt_times, max_dt)
    depth_idx = associate_timestamps(ts, depth_times, max_dt)
    _warn_unposed(root, layout, entries, pose_idx, max_dt)
    if depth_times:
        logger.debug("%s: %d frames without depth within %g s", root, int(np.sum(depth_idx < 0)), max_dt)

    out = []
    for index, (e, gi, di) in enumerate(zip(entries, pose_idx, depth_idx)):
        if gi < 0:
            continue
        world_from_cam = (
            world_from_body[gi] if base_from_camera is None else world_from_body[gi] @ base_from_camera
        )
        out.append(
            PosedImage(
                name=e.name,
                path=resolve_image(list_path, e.lineno, root, e.name, check=check_images),
                cam_from_world=world_from_cam.inverse(),
                camera=camera,
                index=index,
                timestamp=e.timestamp,
                depth_path=depth_paths[di] if di >= 0 else None,
                depth_scale=depth_scale,
                world_down=world_down,
            )
        )
    if not out:
        raise FormatError(
            list_path,
            None,
            f"expected frames with a pose in {pose_file} within max_dt = {max_dt:g} s, found none "
            f"({len(entries)} frames listed); check the timestamps or raise max_dt",
        )
    return out


def _depth_images(root: Path, layout: RgbdLayout, check_images: bool) -> tuple[list[float], list[Path]]:
    """Stamps and files of the depth images: from the layout's depth list, else its depth folder
    (files named by their stamp); empty if neither exists."""
    depth_times: list[float] = []
    depth_paths: list[Path] = []
    depth_list, depth_dir = layout.depth_list, layout.depth_dir
    if depth_list is not None and (root / depth_list).is_file():
        dpath = root / depth_list
        for e in read_timestamped_list(dpath, layout.fmt, "'timestamp filename' per depth image"):
            depth_times.append(e.timestamp)
            depth_paths.append(resolve_image(dpath, e.lineno, root, e.name, check=check_images))
    elif depth_dir is not None and (root / depth_dir).is_dir():
        for p in sorted((root / depth_dir).iterdir()):
            try:
                depth_times.append(float(p.stem))
            except ValueError:
                continue
            depth_paths.append(p.absolute())
    return depth_times, depth_paths


def _warn_unposed(root: Path, layout: RgbdLayout, entries: list, pose_idx: np.ndarray, max_dt: float) -> None:
    skipped = [e for e, i in zip(entries, pose_idx) if i < 0]
    if skipped:
        logger.warning(
            "%s: %d of %d frames have no ground-truth pose within max_dt = %g s in %s and are skipped "
            "(first at %s line %d, t = %.6f)",
            root,
            len(skipped),
            len(entries),
            max_dt,
            layout.pose_file,
            layout.image_list,
            skipped[0].lineno,
            skipped[0].timestamp,
        )


def read_tum(
    root: Path,
    *,
    camera: Camera | None = None,
    tum_camera: str | None = None,
    max_dt: float = DEFAULT_MAX_DT,
    base_from_camera: Pose | None = None,
    depth_scale: float = TUM_DEPTH_SCALE,
    check_images: bool = True,
) -> list[PosedImage]:
    """Read a TUM RGB-D sequence (format in the module docstring).

    Args:
        root: sequence directory (with ``rgb.txt`` and ``groundtruth.txt``).
        camera: intrinsics of the colour camera; overrides everything else.
        tum_camera: ``"fr1"``, ``"fr2"`` or ``"fr3"``: use TUM's published defaults.
        max_dt: association tolerance in seconds between rgb, ground truth and depth.
        base_from_camera: if ``groundtruth.txt`` is the pose of a body frame, the camera's pose
            in it (``x_base = R x_cam + t``); camera pose = world_from_base ∘ base_from_camera.
        depth_scale: depth PNG value per metre (TUM: 5000).
        check_images: raise if a listed image does not exist.

    Returns:
        One :class:`PosedImage` per rgb frame that has a pose, ``index`` = its position in
        ``rgb.txt`` (0-based, counting skipped frames), names as listed in ``rgb.txt``.

    Raises:
        FormatError: missing/malformed files, missing images, no intrinsics.
    """
    root = Path(root)
    preset = None
    if tum_camera is not None:
        if camera is not None:
            raise InputError("read_tum: give either camera= or tum_camera=, not both")
        key = str(tum_camera).lower()
        if key not in TUM_CAMERAS:
            raise InputError(f"tum_camera: expected one of {', '.join(TUM_CAMERAS)}, got {tum_camera!r}")
        preset = TUM_CAMERAS[key]
    elif camera is None and not (root / "camera.txt").is_file():
        m = re.search(r"freiburg([123])", root.absolute().name)
        if m:
            preset = TUM_CAMERAS[f"fr{m.group(1)}"]
            logger.info(
                "%s: using the TUM fr%s default intrinsics (from the directory name)", root, m.group(1)
            )
    cam = resolve_camera(
        root,
        FORMAT,
        camera,
        preset,
        "pass camera=Camera(...) or tum_camera='fr1'|'fr2'|'fr3', or write camera.txt "
        "('PINHOLE width height fx fy cx cy')",
    )
    return read_rgbd_sequence(
        root,
        TUM_LAYOUT,
        cam,
        depth_scale=depth_scale,
        base_from_camera=base_from_camera,
        max_dt=max_dt,
        check_images=check_images,
        world_down=generated_world_down(root),
    )


def tum_lines(timestamps: object, world_from_cam: list[Pose]) -> list[str]:
    """TUM trajectory lines ``timestamp tx ty tz qx qy qz qw`` (camera-to-world, as read by evo).

    Args:
        timestamps: (N,) seconds.
        world_from_cam: N poses ``world_from_cam`` (x_world = R x_cam + t).
    """
    ts = np.asarray(timestamps, dtype=float).reshape(-1)
    if len(ts) != len(world_from_cam):
        raise InputError(f"tum_lines: {len(ts)} timestamps for {len(world_from_cam)} poses")
    out = []
    for t, p in zip(ts, world_from_cam):
        w, x, y, z = p.quat_wxyz
        out.append(f"{t:.9f} " + " ".join(f"{v:.9f}" for v in (*p.t, x, y, z, w)) + "\n")
    return out


def tum_trajectory_text(path: Path | str, timestamps: object, world_from_cam: list[Pose]) -> str:
    """The text of a TUM trajectory file: a header line and :func:`tum_lines`.

    Raises:
        InputError: timestamps not strictly increasing (evo rejects anything else), naming ``path``.
    """
    ts = np.asarray(timestamps, dtype=float).reshape(-1)
    if len(ts) > 1 and not np.all(np.diff(ts) > 0):
        raise InputError(
            f"{path}: TUM timestamps must be strictly increasing (evo requires it); two localized "
            "queries share a timestamp or come out of order"
        )
    return "".join(["# timestamp tx ty tz qx qy qz qw (camera-to-world)\n", *tum_lines(ts, world_from_cam)])


def write_tum_trajectory(path: Path, timestamps: object, world_from_cam: list[Pose]) -> None:
    """Write a TUM trajectory file (:func:`tum_trajectory_text`; ``evo_ape tum gt.txt est.txt``
    reads it), atomically (never half a file)."""
    write_text_atomic(Path(path), tum_trajectory_text(path, timestamps, world_from_cam))
