"""Map gravity: recovery from map poses in a world frame that is not gravity-aligned."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.gravity.upright import upright_from_cam_rotation
from planarloc.gravity.world import (
    GravityReport,
    WorldDown,
    gravity_from_map_poses,
    gravity_in_camera,
    mount_tilt,
    parse_up,
    world_down_from_up,
)


def robot_poses(world_from_level, centers_level, yaws, pitch, roll):
    """cam_from_world of a camera mounted with (pitch, roll) on a robot at ``centers_level``
    (level frame: y down, floor plane x-z) with heading ``yaws``; the world is ``world_from_level``."""
    pitch, roll = np.broadcast_to(pitch, len(yaws)), np.broadcast_to(roll, len(yaws))
    out = []
    for c, yaw, p, r in zip(centers_level, yaws, pitch, roll):
        cam_from_upright = upright_from_cam_rotation(p, r).T
        upright_from_level = Rotation.from_rotvec([0.0, yaw, 0.0]).as_matrix()
        R = cam_from_upright @ upright_from_level @ world_from_level.T
        out.append(Pose.from_center(R, world_from_level @ c))
    return out


@pytest.fixture
def world_rotation():
    return Rotation.from_rotvec([0.7, -1.9, 0.4]).as_matrix()  # far from any axis alignment


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1, 1)))


@pytest.mark.parametrize(("pitch", "roll"), [(0.0, 0.0), (8.0, 2.0), (-12.5, -3.0)])
def test_exact_recovery_from_plane_of_centres(world_rotation, pitch, roll):
    rng = np.random.default_rng(1)
    n = 12
    centers = np.column_stack([rng.uniform(-5, 5, n), np.full(n, -1.3), rng.uniform(-2, 8, n)])
    poses = robot_poses(world_rotation, centers, rng.uniform(-np.pi, np.pi, n), pitch, roll)
    g, rep = gravity_from_map_poses(poses)
    g_true = world_rotation @ [0.0, 1.0, 0.0]
    np.testing.assert_allclose(g, g_true, atol=1e-9)
    assert rep.source == "estimated" and rep.method == "plane" and rep.warnings == ()
    assert rep.pitch_deg == pytest.approx(pitch, abs=1e-7) and rep.roll_deg == pytest.approx(roll, abs=1e-7)
    assert rep.pitch_spread_deg < 1e-7 and rep.roll_max_dev_deg < 1e-7 and rep.plane_rms < 1e-9
    # the camera's gravity is what the mount predicts, and the report's mount gravity equals it
    g_cam = gravity_in_camera(poses[0], g)
    np.testing.assert_allclose(upright_from_cam_rotation(pitch, roll) @ g_cam, [0, 1, 0], atol=1e-9)
    np.testing.assert_allclose(rep.mount_gravity, g_cam, atol=1e-9)


def test_sign_follows_the_cameras_not_the_svd(world_rotation):
    rng = np.random.default_rng(2)
    centers = np.column_stack([rng.uniform(-5, 5, 8), np.zeros(8), rng.uniform(-5, 5, 8)])
    poses = robot_poses(world_rotation, centers, rng.uniform(-3, 3, 8), 5.0, 0.0)
    g, _ = gravity_from_map_poses(poses)
    flipped = [Pose(np.diag([1.0, -1.0, -1.0]) @ p.R, np.diag([1.0, -1.0, -1.0]) @ p.t) for p in poses]
    g_flipped, rep = gravity_from_map_poses(flipped)  # camera y-axes reversed: so is gravity
    np.testing.assert_allclose(g_flipped, -g, atol=1e-9)
    assert rep.roll_deg == pytest.approx(0.0, abs=1e-6) and rep.pitch_deg == pytest.approx(5.0, abs=1e-6)


def test_collinear_centres_recover_pitch_exactly(world_rotation):
    """Straight drive: the tilt about the line is unobservable; the pitch (about the axis
    across the line for a forward-looking camera) is recovered exactly, the roll is assumed 0."""
    s = np.linspace(0, 20, 15)
    heading = 0.6
    centers = np.column_stack([np.sin(heading) * s, np.full(15, -1.0), np.cos(heading) * s])
    yaws = np.full(15, -heading)  # optical axis along the line
    g_true = world_rotation @ [0.0, 1.0, 0.0]
    g, rep = gravity_from_map_poses(robot_poses(world_rotation, centers, yaws, 9.0, 0.0))
    np.testing.assert_allclose(g, g_true, atol=1e-9)
    assert rep.method == "line" and rep.pitch_deg == pytest.approx(9.0, abs=1e-7)
    # with a roll, the estimate is off by about that roll (about the line direction), and the roll
    # relative to the estimate is about zero: it is not observable
    g2, rep2 = gravity_from_map_poses(robot_poses(world_rotation, centers, yaws, 9.0, 3.0))
    assert 2.5 < angle_deg(g2, g_true) < 3.5
    assert abs(rep2.roll_deg) < 0.5 and rep2.pitch_deg == pytest.approx(9.0, abs=0.1)
    # two cameras are always collinear
    assert (
        gravity_from_map_poses(robot_poses(world_rotation, centers[:2], yaws[:2], 9.0, 0.0))[1].method
        == "line"
    )


def test_inconsistent_tilt_warns(world_rotation):
    rng = np.random.default_rng(3)
    n = 20
    centers = np.column_stack([rng.uniform(-5, 5, n), np.zeros(n), rng.uniform(-5, 5, n)])
    yaws = rng.uniform(-3, 3, n)
    _, calm = gravity_from_map_poses(
        robot_poses(world_rotation, centers, yaws, 4 + rng.normal(0, 0.3, n), 0.0)
    )
    assert calm.warnings == () and calm.pitch_spread_deg < 0.6
    _, shaky = gravity_from_map_poses(robot_poses(world_rotation, centers, yaws, rng.normal(0, 6, n), 0.0))
    assert shaky.pitch_spread_deg > 2.0 and any("inconsistent" in w for w in shaky.warnings)


def test_centres_spanning_3d_fall_back_with_warning(world_rotation):
    rng = np.random.default_rng(4)
    centers = rng.uniform(-3, 3, (10, 3))
    g, rep = gravity_from_map_poses(robot_poses(world_rotation, centers, rng.uniform(-3, 3, 10), 0.0, 0.0))
    assert rep.method == "camera_y" and any("do not lie on a plane" in w for w in rep.warnings)
    np.testing.assert_allclose(g, world_rotation @ [0, 1, 0], atol=1e-9)  # upright cameras: mean y is exact


def test_plane_far_from_the_cameras_y_axes_warns(world_rotation):
    """Centres on a vertical wall (e.g. a handheld scan): the plane normal is horizontal."""
    rng = np.random.default_rng(5)
    centers = np.column_stack([rng.uniform(-5, 5, 10), rng.uniform(-2, 0, 10), np.zeros(10)])
    _, rep = gravity_from_map_poses(robot_poses(world_rotation, centers, np.zeros(10), 0.0, 0.0))
    assert rep.method == "plane" and any("not level" in w for w in rep.warnings)


def test_declared_gravity_is_used_and_tilt_measured(world_rotation):
    rng = np.random.default_rng(6)
    centers = rng.uniform(-3, 3, (6, 3))  # no plane needed when declared
    poses = robot_poses(world_rotation, centers, rng.uniform(-3, 3, 6), 7.0, -1.5)
    down = WorldDown(tuple(world_rotation @ [0, 2.0, 0]), "option", "up=...")
    g, rep = gravity_from_map_poses(poses, down)
    np.testing.assert_allclose(g, world_rotation @ [0, 1, 0], atol=1e-12)
    assert (rep.source, rep.method, rep.detail) == ("option", "given", "up=...")
    assert rep.pitch_deg == pytest.approx(7.0, abs=1e-7) and rep.roll_deg == pytest.approx(-1.5, abs=1e-7)
    pitch, roll = mount_tilt(poses, g)
    np.testing.assert_allclose(pitch, 7.0, atol=1e-7)
    np.testing.assert_allclose(roll, -1.5, atol=1e-7)


def test_up_estimate_estimates_even_when_declared(world_rotation):
    rng = np.random.default_rng(8)
    centers = np.column_stack([rng.uniform(-5, 5, 6), np.zeros(6), rng.uniform(-5, 5, 6)])
    poses = robot_poses(world_rotation, centers, rng.uniform(-3, 3, 6), 4.0, 0.0)
    g, rep = gravity_from_map_poses(poses, world_down_from_up("estimate"))
    np.testing.assert_allclose(g, world_rotation @ [0, 1, 0], atol=1e-9)
    assert rep.source == "estimated" and rep.method == "plane" and rep.detail.startswith("up=estimate")
    assert (
        WorldDown.from_dict(json.loads(json.dumps(world_down_from_up("estimate").to_dict()))).direction
        is None
    )
    with pytest.raises(InputError, match="only an option"):
        WorldDown(None, "declared", "")


def test_report_round_trips_through_json(world_rotation):
    rng = np.random.default_rng(7)
    centers = np.column_stack([rng.uniform(-5, 5, 6), np.zeros(6), rng.uniform(-5, 5, 6)])
    _, rep = gravity_from_map_poses(robot_poses(world_rotation, centers, rng.uniform(-3, 3, 6), 3.0, 1.0))
    back = GravityReport.from_dict(json.loads(json.dumps(rep.to_dict())))
    assert back == rep
    assert any("source: estimated" in line for line in back.summary_lines())
    assert WorldDown.from_dict(json.loads(json.dumps(world_down_from_up("z").to_dict()))).direction == (
        0,
        0,
        -1,
    )


def test_bad_input():
    with pytest.raises(InputError, match="at least one"):
        gravity_from_map_poses([])
    with pytest.raises(InputError, match=r"poses\[1\]"):
        gravity_from_map_poses([Pose.identity(), np.eye(4)])
    with pytest.raises(InputError, match="non-zero"):
        gravity_in_camera(Pose.identity(), [0, 0, 0])
    with pytest.raises(InputError, match="source"):
        WorldDown((0, 1, 0), "guessed", "")
    # centres on a line along the cameras' y-axes: nothing is known about gravity
    with pytest.raises(InputError, match="up="):
        gravity_from_map_poses([Pose.from_center(np.eye(3), [0, y, 0]) for y in range(3)])
    g, rep = gravity_from_map_poses([Pose.from_center(np.eye(3), [0, 0, z]) for z in range(3)])
    assert rep.method == "line" and np.allclose(g, [0, 1, 0])


@pytest.mark.parametrize(
    ("text", "up"),
    [("z", (0, 0, 1)), ("-Y", (0, -1, 0)), ("+x", (1, 0, 0)), ("1, 1, 0", (2**-0.5, 2**-0.5, 0))],
)
def test_parse_up(text, up):
    np.testing.assert_allclose(parse_up(text), up, atol=1e-12)


def test_building_scale_maps_estimate_gravity_in_bounded_memory(world_rotation):
    # 20,000-image maps (issue 20): the centres' SVD must not form the N x N left factor (3.2 GB there)
    import tracemalloc

    rng = np.random.default_rng(3)
    n = 4000  # a full left factor would be 128 MB
    centers = np.column_stack([rng.uniform(-50, 50, n), np.full(n, -1.3), rng.uniform(-20, 80, n)])
    poses = robot_poses(world_rotation, centers, rng.uniform(-np.pi, np.pi, n), 4.0, -1.0)
    tracemalloc.start()
    try:
        g, rep = gravity_from_map_poses(poses)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, peak
    np.testing.assert_allclose(g, world_rotation @ [0.0, 1.0, 0.0], atol=1e-9)
    assert rep.method == "plane" and rep.pitch_deg == pytest.approx(4.0, abs=1e-7)
