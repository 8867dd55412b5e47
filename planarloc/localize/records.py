"""The record every front door writes: one JSON object per single fix or stream frame.

`planarloc localize` writes them (one file per query, :mod:`planarloc.io.results`), `planarloc
evaluate` lists them (with the ground truth and the errors), `planarloc serve` answers them (a
session's frames too) and the ROS 2 node puts one in each diagnostic. One schema for all, published
as ``docs/schema/record.schema.json`` (:data:`SCHEMA`, versioned) and validated in the tests
against every writer.

Every record has (``null`` where a value is absent — never NaN or Infinity, :mod:`planarloc.io.strict_json`):

- ``schema`` (:data:`SCHEMA`), ``kind`` (``"fix"``: a single-image fix; ``"frame"``: a stream frame),
  ``name``;
- ``success`` — the pose may be used — and ``status``: a fix's
  :class:`~planarloc.robust.status.Status` (``success`` or why not), a frame's ``localized`` /
  ``predicted`` / ``lost``; ``"error"`` when the input could not be processed; ``message`` says why;
- ``stamp``: the image's time in seconds, when its source has one;
- the pose: ``quat_wxyz`` (w, x, y, z) and ``t`` of ``cam_from_world`` (x_cam = R·x_world + t) and
  ``center``, the camera centre in the map's world (``−Rᵀt``);
- its uncertainty: ``position_std_m``, ``rotation_std_deg`` (square roots of the largest eigenvalue
  of the position and rotation blocks) and ``covariance_xyz_rotvec``, a 6 × 6 covariance of the
  frame named by ``covariance_frame`` (``world_from_camera``) in the order of
  ``covariance_order``: the camera centre (x, y, z in the map's world, metres), then a rotation
  vector about the world axes (radians) — ROS' ``PoseWithCovariance`` order (docs/conventions.md,
  "Pose covariances");
- ``time_s``: seconds per stage, ``total`` among them.

A fix adds the estimator's evidence (``num_inliers``, ``references``, ``model``, ...), the map pose
prior it assumed (``map_prior``: the map's measurement, :mod:`planarloc.map.pose_accuracy`) and the
keypoints it used (``keypoint_budget``: 0 for all, else the coarse pass's budget); a frame adds
the stream's bookkeeping (``fix_status``, ``motion_source``, ``late``, ..., and ``fix``: the fix
record handled in its step).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from planarloc.geometry.pose import Pose
from planarloc.localize.sequence import SequenceEstimate
from planarloc.robust.result import PoseEstimate

#: the schema a record follows (``docs/schema/record.schema.json``); the number changes when a
#: field changes meaning or goes away (new optional fields keep it)
SCHEMA = "planarloc.record/1"
#: the frame whose covariance a record holds, and the order of its rows
COVARIANCE_FRAME = "world_from_camera"
COVARIANCE_ORDER = ("x", "y", "z", "rot_x", "rot_y", "rot_z")


def _finite(value: object) -> float | None:
    v = float(value)  # type: ignore[arg-type]
    return v if np.isfinite(v) else None


def _block_std(covariance: np.ndarray | None, block: slice) -> float | None:
    """sqrt of the largest eigenvalue of a diagonal block of a (6, 6) covariance (None: absent)."""
    if covariance is None:
        return None
    C = np.asarray(covariance, dtype=float)[block, block]
    if not np.isfinite(C).all():
        return None
    return float(np.sqrt(max(float(np.linalg.eigvalsh(0.5 * (C + C.T)).max()), 0.0)))


def _pose_fields(pose: Pose | None, covariance: np.ndarray | None) -> dict:
    """The pose and covariance fields of a record (module docstring); all null without a pose."""
    cov = None
    if pose is not None and covariance is not None:
        C = np.asarray(covariance, dtype=float)
        cov = np.where(np.isfinite(C), C, np.nan).tolist()  # strict JSON writes non-finite as null
    return {
        "quat_wxyz": None if pose is None else [float(v) for v in pose.quat_wxyz],
        "t": None if pose is None else [float(v) for v in pose.t],
        "center": None if pose is None else [float(v) for v in pose.center],
        "covariance_xyz_rotvec": cov,
        "covariance_frame": COVARIANCE_FRAME,
        "covariance_order": list(COVARIANCE_ORDER),
    }


def _head(kind: str, name: str, success: bool, status: str, message: str, stamp: float | None) -> dict:
    return {
        "schema": SCHEMA,
        "kind": kind,
        "name": str(name),
        "success": bool(success),
        "status": str(status),
        "message": " ".join(str(message).split()),
        "stamp": None if stamp is None else _finite(stamp),
    }


def query_record(
    name: str, estimate: PoseEstimate, gravity: Iterable[float] | None = None, stamp: float | None = None
) -> dict:
    """The record of one single-image fix (``kind`` ``"fix"``); ``gravity``: the query's gravity
    prior (``query_gravity``; None: assumed mounted like the map cameras); ``stamp``: its time."""
    d = estimate.to_dict()
    pose = estimate.pose if estimate.success else None
    covariance = estimate.covariance if pose is not None else None
    std = _finite(estimate.position_std_m) if pose is not None else None
    return {
        **_head("fix", name, estimate.success, estimate.status, estimate.message, stamp),
        **_pose_fields(pose, covariance),
        "position_std_m": std,
        "rotation_std_deg": None
        if (r := _block_std(covariance, slice(3, 6))) is None
        else float(np.degrees(r)),
        "time_s": {k: _finite(v) for k, v in d["time_s"].items()},
        "num_inliers": d["num_inliers"],
        "num_inliers_3d": d["num_inliers_3d"],
        "num_matches": d["num_matches"],
        "iterations": d["iterations"],
        "references": d["references"],
        "model": d["model"],
        "stats": d["stats"],
        "query_gravity": None if gravity is None else [float(v) for v in gravity],
        "map_prior": None
        if estimate.map_prior is None
        else {
            "rotation_std_deg": float(estimate.map_prior[0]),
            "position_std_m": float(estimate.map_prior[1]),
        },
        "keypoint_budget": int(estimate.keypoint_budget),
    }


def frame_record(name: str, estimate: SequenceEstimate) -> dict:
    """The record of one stream frame (``kind`` ``"frame"``; ``success``: ``localized`` or
    ``predicted``)."""
    e = estimate
    pose = e.pose if e.success else None
    return {
        **_head("frame", name, e.success, e.status, e.message, e.stamp),
        **_pose_fields(pose, e.covariance if pose is not None else None),
        "position_std_m": _finite(e.position_std_m) if pose is not None else None,
        "rotation_std_deg": _finite(e.rotation_std_deg) if pose is not None else None,
        "time_s": {"total": _finite(e.seconds), "latency": _finite(e.latency_s), "cpu": _finite(e.cpu_s)},
        "fix_status": e.fix_status,
        "fix_stamp": None if e.fix_stamp is None else _finite(e.fix_stamp),
        "fix": None if e.fix is None else query_record(name, e.fix, stamp=e.fix_stamp),
        "rejected": e.rejected,
        "mahalanobis_sq": _finite(e.mahalanobis_sq),
        "motion_source": e.motion_source,
        "motion_model": e.motion_model,
        "tracks": int(e.tracks),
        "global_retrieval": bool(e.global_retrieval),
        "kidnap_suspected": bool(e.kidnap_suspected),
        "reinitialized": bool(e.reinitialized),
        "late": bool(e.late),
        "missing_frames": int(e.missing_frames),
    }


def error_record(
    name: str,
    reason: str,
    *,
    kind: str = "fix",
    stamp: float | None = None,
    seconds: float | None = None,
    status: str = "error",
) -> dict:
    """The record of a query or frame that could not be processed (an unreadable image, a size
    its camera does not have): status ``"error"``, ``message`` the reason. An evaluation's
    frame the camera replaced before the stream took it has status ``"dropped"``."""
    if kind not in ("fix", "frame"):
        raise ValueError(f"kind: expected 'fix' or 'frame', got {kind!r}")
    return {
        **_head(kind, name, False, status, reason, stamp),
        **_pose_fields(None, None),
        "position_std_m": None,
        "rotation_std_deg": None,
        "time_s": {} if seconds is None else {"total": _finite(seconds)},
    }


def record_pose(record: dict) -> Pose | None:
    """The usable ``cam_from_world`` of a record (None unless ``success``); raises ValueError on
    a record whose pose is not a pose (e.g. a damaged answer of a server)."""
    if not record.get("success"):
        return None
    return Pose.from_quat_wxyz(record["quat_wxyz"], record["t"])
