"""Cross-check against a peer library: PoseLib's generalized relative pose on the same scenes.

Also pins the convention used by ``benchmarks/poselib_peer.py``: with rig 1 = the query
(identity extrinsic) and rig 2 = the references (extrinsics = their ``cam_from_world``),
PoseLib returns ``rig2_from_rig1 = world_from_query``.
"""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.pose import Pose
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import RansacOptions

poselib = pytest.importorskip("poselib")


def _camera_dict(camera) -> dict:
    return {
        "model": camera.model.value,
        "width": camera.width,
        "height": camera.height,
        "params": list(camera.params),
    }


def _camera_pose(pose: Pose):
    p = poselib.CameraPose()
    p.R, p.t = pose.R, pose.t
    return p


def poselib_world_from_query(sc) -> Pose:
    matches = []
    for k, p in enumerate(sc.pairs):
        m = poselib.PairwiseMatches()
        m.cam_id1, m.cam_id2, m.x1, m.x2 = 0, k, p.query_points, p.ref_points
        matches.append(m)
    cam = _camera_dict(sc.query_camera)
    pose, _ = poselib.estimate_generalized_relative_pose(
        matches,
        [_camera_pose(Pose.identity())],
        [cam],
        [_camera_pose(p.ref_pose) for p in sc.pairs],
        [_camera_dict(p.ref_camera) for p in sc.pairs],
        {"min_iterations": 100, "max_iterations": 100, "max_epipolar_error": 2.0},
        {},
    )
    return Pose(pose.R, pose.t)


@pytest.mark.parametrize("seed", [0, 1])
def test_poselib_returns_world_from_query(scene, seed: int) -> None:
    sc = scene(seed, num_refs=5, matches_per_pair=50, noise_px=0.0)
    world_from_query = poselib_world_from_query(sc)
    query_from_world = world_from_query.inverse()
    assert np.linalg.norm(query_from_world.center - sc.query_pose.center) < 1e-6
    assert np.abs(query_from_world.R - sc.query_pose.R).max() < 1e-8


@pytest.mark.parametrize("method", ["2p1p", "2p2p"])
def test_agrees_with_poselib_on_noisy_scene(scene, method: str) -> None:
    """Both estimators on the same matches land within the noise of each other."""
    sc = scene(5, num_refs=5, matches_per_pair=100, noise_px=1.0, outlier_ratio=0.2)
    ours = estimate_absolute_pose(
        sc.query_camera, sc.pairs, method, RansacOptions(max_iterations=100, min_iterations=100)
    )
    peer = poselib_world_from_query(sc).inverse()
    assert ours.success
    assert np.linalg.norm(ours.pose.center - peer.center) < 0.1
    assert np.linalg.norm(ours.pose.center - sc.query_pose.center) < 0.1
