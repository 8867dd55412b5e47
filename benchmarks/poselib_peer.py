"""PoseLib as a peer estimator for the benchmarks: the query pose from 2D-2D matches to posed
references by PoseLib's generalized relative pose (6DoF, no planar prior).

Set-up (one call per query):

* rig 1 = the query camera alone, extrinsic ``cam_from_rig1 = identity`` (rig 1 frame = query);
* rig 2 = the references, extrinsics ``cam_from_rig2 = ref cam_from_world`` (rig 2 frame = world);
* one ``PairwiseMatches(cam_id1=0, cam_id2=k, x1=query pixels, x2=reference pixels)`` per pair.

Convention (checked on noise-free scenes in ``tests/robust/test_poselib_peer.py``): PoseLib
returns ``rig2_from_rig1`` (``x_rig2 = R x_rig1 + t``), i.e. ``world_from_query``; the query
``cam_from_world`` is its inverse. PoseLib normalises pixels with the camera intrinsics and
divides ``max_epipolar_error`` by the mean focal length, so the threshold is in pixels as ours.

PoseLib's iteration options are honoured exactly (``min_iterations = max_iterations`` fixes
the count); after RANSAC it runs its own non-linear refinement (``bundle_opt``) like ours.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import poselib

from planarloc.geometry.camera import Camera, CameraModel
from planarloc.geometry.pose import Pose
from planarloc.robust.pair_matches import PairMatches


@dataclass(frozen=True)
class PeerEstimate:
    """Result of :func:`estimate_query_pose_poselib`.

    Attributes:
        pose: query ``cam_from_world``; None if PoseLib returned no finite rotation.
        num_inliers: PoseLib's inlier count over all pairs.
        iterations: RANSAC iterations PoseLib reports.
        time_s: wall time of the whole call, including building PoseLib's inputs.
        cpu_s: CPU time of this process during the call (PoseLib is single-threaded), less
            sensitive than ``time_s`` to other load on the machine.
    """

    pose: Pose | None
    num_inliers: int
    iterations: int
    time_s: float
    cpu_s: float


def poselib_camera(camera: Camera) -> dict:
    """A PoseLib camera dict of the same model and parameters (COLMAP names and order)."""
    if camera.model not in (CameraModel.PINHOLE, CameraModel.SIMPLE_PINHOLE, CameraModel.OPENCV):
        raise ValueError(f"camera model {camera.model} has no PoseLib counterpart here")
    return {
        "model": camera.model.value,
        "width": camera.width,
        "height": camera.height,
        "params": list(camera.params),
    }


def poselib_pose(pose: Pose) -> poselib.CameraPose:
    """A ``poselib.CameraPose`` with the same ``b_from_a`` meaning (``x_b = R x_a + t``)."""
    p = poselib.CameraPose()
    p.R = pose.R
    p.t = pose.t
    return p


def estimate_query_pose_poselib(
    query_camera: Camera,
    pairs: Sequence[PairMatches],
    iterations: int = 100,
    threshold_px: float = 2.0,
    seed: int = 0,
    refine: bool = True,
) -> PeerEstimate:
    """Query ``cam_from_world`` with ``poselib.estimate_generalized_relative_pose``.

    Args:
        query_camera: intrinsics of the query.
        pairs: matches to the posed references (``ref_pose`` = reference ``cam_from_world``).
        iterations: exact RANSAC iteration count (PoseLib ``min_iterations = max_iterations``).
        threshold_px: PoseLib ``max_epipolar_error`` in pixels.
        seed: PoseLib's RANSAC seed.
        refine: run PoseLib's final non-linear refinement (``bundle_opt.max_iterations``).

    Returns:
        :class:`PeerEstimate`.
    """
    t0, c0 = time.perf_counter(), time.process_time()
    matches = []
    for k, p in enumerate(pairs):
        m = poselib.PairwiseMatches()
        m.cam_id1 = 0
        m.cam_id2 = k
        m.x1 = p.query_points
        m.x2 = p.ref_points
        matches.append(m)
    rig1_ext = [poselib_pose(Pose.identity())]
    rig1_cams = [poselib_camera(query_camera)]
    rig2_ext = [poselib_pose(p.ref_pose) for p in pairs]
    rig2_cams = [poselib_camera(p.ref_camera) for p in pairs]
    ransac_opt = {
        "min_iterations": iterations,
        "max_iterations": iterations,
        "max_epipolar_error": threshold_px,
        "seed": seed,
    }
    bundle_opt = {} if refine else {"max_iterations": 0}
    rig2_from_rig1, info = poselib.estimate_generalized_relative_pose(
        matches, rig1_ext, rig1_cams, rig2_ext, rig2_cams, ransac_opt, bundle_opt
    )
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    R, t = np.asarray(rig2_from_rig1.R), np.asarray(rig2_from_rig1.t)
    pose = None
    if np.all(np.isfinite(R)) and np.all(np.isfinite(t)) and abs(np.linalg.det(R) - 1.0) < 1e-6:
        pose = Pose(R, t).inverse()  # query cam_from_world = (world_from_query)⁻¹
    return PeerEstimate(pose, int(info.get("num_inliers", 0)), int(info.get("iterations", 0)), elapsed, cpu)
