"""Where `localize` takes its queries from: image files and folders, or a dataset in any
format (``--format``; e.g. a ROS bag, whose images need no poses)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.io.datasets import read_dataset

#: rosbag options that make poses required; without them only the images are read
_ROSBAG_POSE_OPTIONS = {"pose_topic", "tf_parent", "tf_child", "base_to_camera", "max_dt"}


@dataclass(frozen=True)
class QuerySource:
    """One query: its name, image file, and what its dataset knows (intrinsics, time, truth)."""

    name: str
    path: Path
    camera: Camera | None = None
    timestamp: float | None = None
    truth: Pose | None = None


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
        return [QuerySource(im.name, im.path, im.camera, im.timestamp)
                for im in read_rosbag_images(paths[0], **options)]
    return [QuerySource(im.name, im.path, im.camera, im.timestamp, im.cam_from_world)
            for im in read_dataset(paths[0], fmt, **options)]
