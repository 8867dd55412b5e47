"""The records every front door writes: one JSON object per query or stream frame.

`planarloc localize` writes them (one file per query, :mod:`planarloc.io.results`), `planarloc
serve` answers them, a ROS node would publish from them; one function per kind, so all are
identical.

Schema: ``{"name": <query name>, "success": bool, "status": str, ...}``:

- a query (:func:`query_record`): ``**PoseEstimate.to_dict()`` — ``message``, ``num_inliers``, ...,
  and ``query_gravity``, the unit gravity it was given (None: assumed mounted like the map cameras);
- a stream frame (:func:`frame_record`): ``**SequenceEstimate.to_dict()`` — ``stamp``, ``status``
  ``localized``/``predicted``/``lost``, ``covariance_xyz_rotvec``, ``fix_status``, ``latency_s``,
  ``late``, ...;
- a query or frame that could not be processed (:func:`error_record`): ``status`` ``"error"``
  and its ``reason`` (an unreadable image, a size different from its camera's).

A returned pose is ``quat_wxyz`` (w, x, y, z) and ``t`` of ``cam_from_world``
(x_cam = R·x_world + t); ``success`` says whether it may be used (:func:`record_pose`). Its
covariance, ``covariance_xyz_rotvec`` (6 × 6 nested lists; a query's only on success), is in ROS
order for ``world_from_camera``: the camera centre (x, y, z in the map's world, metres), then a
rotation vector about the world axes (radians) (docs/conventions.md, "Pose covariances").
"""

from __future__ import annotations

from planarloc.geometry.pose import Pose
from planarloc.localize.sequence import SequenceEstimate
from planarloc.robust.result import PoseEstimate


def query_record(name: str, estimate: PoseEstimate, gravity: object | None = None) -> dict:
    """The JSON-serialisable record of one localized (or failed) query; ``query_gravity`` is the
    gravity prior it was given (None: assumed mounted like the map cameras)."""
    g = None if gravity is None else [float(v) for v in gravity]
    return {"name": name, **estimate.to_dict(), "query_gravity": g}


def frame_record(name: str, estimate: SequenceEstimate) -> dict:
    """The record of one frame of a stream (``success``: ``localized`` or ``predicted``)."""
    return {"name": name, **estimate.to_dict()}


def error_record(name: str, reason: str, **extra: object) -> dict:
    """The record of a query (or frame) that could not be processed, with its reason."""
    return {"name": name, "success": False, "status": "error", "reason": " ".join(str(reason).split()), **extra}


def record_pose(record: dict) -> Pose | None:
    """The usable ``cam_from_world`` of a record (None unless ``success``); raises ValueError on
    a record whose pose is not a pose (e.g. a damaged answer of a server)."""
    if not record.get("success"):
        return None
    return Pose.from_quat_wxyz(record["quat_wxyz"], record["t"])
