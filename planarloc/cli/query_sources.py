"""Where `localize` takes its queries from, and what each query is called.

Sources: image files and folders; one dataset in any format (``--format``; e.g. a ROS bag, whose
images need no poses); for ``--sequence`` also an image list (``path`` or ``timestamp path`` per
line, :func:`planarloc.io.odometry.read_image_list`).

**The naming rule** (README, "Query names"): a query is named by its path relative to the folder
or the dataset it was found in (``image_l/000001.png`` for ``localize data/seq`` and for
``--format kitti data/seq``); an image file named on the command line or in an image list is named
by its file name (``000001.png``). When different files of one run get the same name, each gets as
many parent folders as it takes to tell them apart (``a/q.png``, ``b/q.png``); a file listed twice
is one query. Names key the results file, the records, the pairs file (``--pairs``) and the
gravity file (``--gravity-file``); they must not contain whitespace.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import cast

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.io.datasets import read_dataset

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm"}
#: rosbag options that make poses required; without them only the images are read
_ROSBAG_POSE_OPTIONS = {"pose_topic", "tf_parent", "tf_child", "base_to_camera", "max_dt"}


@dataclass(frozen=True)
class QuerySource:
    """One query: its name, image file, and what its source knows (intrinsics, time, truth)."""

    name: str
    path: Path
    camera: Camera | None = None
    timestamp: float | None = None
    truth: Pose | None = None


def image_queries(paths: Sequence[Path]) -> list[QuerySource]:
    """Queries of image files and folders (folders: every image below, sorted), named by the rule."""
    out = []
    for p in paths:
        if p.is_dir():
            files = sorted(f for f in p.rglob("*") if f.suffix.lower() in IMAGE_SUFFIXES)
            out += [QuerySource(str(f.relative_to(p)), f) for f in files]
        elif p.exists():
            out.append(QuerySource(p.name, p))
        else:
            raise ValueError(f"{p}: no such image or folder")
    if not out:
        raise ValueError("no query images found")
    return unique_names(out)


def list_queries(path: Path, frame_period_s: float) -> tuple[list[QuerySource], bool]:
    """Queries of an image list, in order, with their stamps (the list's, else ``k * frame_period_s``);
    and whether the stamps came from the list."""
    from planarloc.io.odometry import read_image_list

    entries = read_image_list(path)
    timed = entries[0][0] is not None
    out = [
        QuerySource(p.name, p, timestamp=float(cast(float, s)) if timed else k * frame_period_s)
        for k, (s, p) in enumerate(entries)
    ]
    return unique_names(out, keep_repeats=True), timed


def unique_names(items: list[QuerySource], keep_repeats: bool = False) -> list[QuerySource]:
    """Drop repeated files (unless ``keep_repeats``: a stream may show a file twice); give
    different files with the same name (a/1.png, b/1.png) names with as many parent folders as
    it takes to tell them apart, so results never mix up."""
    seen: set[str] = set()
    files = []
    for q in items:
        key = os.path.realpath(q.path)
        if keep_repeats or key not in seen:
            seen.add(key)
            files.append(q)
    names = [q.name for q in files]
    for depth in range(1, 64):
        owners: dict[str, set[str]] = {}
        for n, q in zip(names, files):
            owners.setdefault(n, set()).add(os.path.realpath(q.path))
        clash = {n for n, o in owners.items() if len(o) > 1}
        if not clash:
            break
        for i, q in enumerate(files):
            if names[i] in clash:
                parts = Path(os.path.abspath(q.path)).parts[-depth - 1 :]
                names[i] = "/".join(parts) if len(parts) > depth else os.path.abspath(q.path)
    for n, q in zip(names, files):
        if any(c.isspace() for c in n):  # before any work: the results file could not hold it
            raise ValueError(
                f"{q.path}: query image names must not contain whitespace (the hloc results format "
                "is 'name qw qx qy qz tx ty tz'); rename the file"
            )
    return [replace(q, name=n) for n, q in zip(names, files)]


def dataset_queries(paths: list[Path], fmt: str, options: dict, camera: Camera | None) -> list[QuerySource]:
    """The images of one dataset as queries, with their ground truth when the format has poses.

    A ROS bag without pose options is read for its images only (no poses needed); ``camera``
    (``--camera``) then stands in for a missing CameraInfo.
    """
    if len(paths) != 1:
        raise ValueError(f"--format {fmt}: expected one dataset, got {len(paths)} paths")
    if fmt == "rosbag" and not (_ROSBAG_POSE_OPTIONS & set(options)):
        from planarloc.io.rosbag import read_rosbag_images

        if camera is not None:
            options = {"camera": camera, **options}
        return [
            QuerySource(im.name, im.path, im.camera, im.timestamp)
            for im in read_rosbag_images(paths[0], **options)
        ]
    return [
        QuerySource(im.name, im.path, im.camera, im.timestamp, im.cam_from_world)
        for im in read_dataset(paths[0], fmt, **options)
    ]
