"""Trajectories and sessions: viewpoint change between map and query, free space, conventions, effects."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from planarloc.synthetic.world import build_sessions, get_preset, preset_names, shrunk
from planarloc.synthetic.world.effects import gravity_in_camera, mount_poses, tilt_poses, tilt_rotation
from planarloc.synthetic.world.placement import clearance, polygon_distance
from planarloc.synthetic.world.trajectory import (
    camera_centers,
    ellipse_loop,
    heading_of,
    height_profile,
    offset_path,
    planar_poses,
    straight_line,
    yaw_rotation,
)


@pytest.fixture(scope="module", params=preset_names())
def preset_sessions(request):
    # Full-size trajectories and layouts; textures coarse to keep the test fast (they do not affect poses).
    config = get_preset(request.param)
    config = dataclasses.replace(config, scene=dataclasses.replace(config.scene, px_per_m=40.0))
    return request.param, build_sessions(config, seed=0)


def _expected_heights(config, session):
    tc = config.trajectory
    if session.name == "map":
        return np.full(len(session), tc.camera_height)
    return height_profile(tc.camera_height, tc.query_height_drop, tc.query_height_wobble, len(session))


def _mount(config, session_name):
    tc = config.trajectory
    pitch, roll = (tc.mount_pitch_deg, tc.mount_roll_deg) if session_name == "map" else tc.query_mount_deg()
    return tilt_rotation(np.radians(pitch), np.radians(roll))


def _wrap_deg(a):
    return np.degrees(np.abs((a + np.pi) % (2 * np.pi) - np.pi))


def test_yaw_convention():
    theta = 0.3
    R = yaw_rotation(theta)
    np.testing.assert_allclose(
        R, [[np.cos(theta), 0, -np.sin(theta)], [0, 1, 0], [np.sin(theta), 0, np.cos(theta)]]
    )
    Rs, ts = planar_poses(np.array([[2.0, 3.0]]), np.array([theta]), 1.0)
    np.testing.assert_allclose(camera_centers(Rs, ts), [[2.0, -1.0, 3.0]])  # y down: 1 m above the floor
    np.testing.assert_allclose(Rs[0][2], [np.sin(theta), 0, np.cos(theta)])  # optical axis in world
    np.testing.assert_allclose(heading_of(Rs), [theta])
    np.testing.assert_allclose(Rs[0][1], [0, 1, 0])  # camera y = gravity


def test_paths_head_along_travel():
    xz, yaw = ellipse_loop((4, 3), (2, 1), 16)
    step = np.roll(xz, -1, axis=0) - xz
    travel = np.arctan2(step[:, 0], step[:, 1])
    assert np.all(_wrap_deg(travel - yaw) < 360 / 16)
    xz, yaw = straight_line((1, 1), (1, 5), 5)
    np.testing.assert_allclose(yaw, 0.0)
    shifted, yaw2 = offset_path(xz, yaw, 0.3, np.radians(10))
    np.testing.assert_allclose(shifted[:, 0], 1.3)  # right of +z travel is +x
    np.testing.assert_allclose(yaw2, np.radians(10))


def test_cameras_inside_room_clear_of_walls_and_boxes(preset_sessions):
    name, sessions = preset_sessions
    for session in sessions:
        c = camera_centers(session.R, session.t)
        room = session.world.room
        assert np.all((c[:, 0] > 0) & (c[:, 0] < room.size_x) & (c[:, 2] > 0) & (c[:, 2] < room.size_z)), name
        np.testing.assert_allclose(c[:, 1], -_expected_heights(get_preset(name), session))
        assert clearance(c[:, [0, 2]], room, session.world.boxes).min() >= 0.5, f"{name} {session.name}"
        for box in session.world.boxes:
            assert box.size[1] < room.height


def test_query_viewpoint_differs_from_nearest_map_frame(preset_sessions):
    name, (m, q) = preset_sessions
    cm, cq = camera_centers(m.R, m.t)[:, [0, 2]], camera_centers(q.R, q.t)[:, [0, 2]]  # on the floor
    dist = np.linalg.norm(cq[:, None] - cm[None], axis=2)
    nearest = dist.argmin(axis=1)
    d = dist[np.arange(len(q)), nearest]
    config = get_preset(name)  # headings of the cameras before their mounts
    yaw_m = heading_of(np.einsum("ji,njk->nik", _mount(config, "map"), m.R))
    yaw_q = heading_of(np.einsum("ji,njk->nik", _mount(config, "query"), q.R))
    dyaw = _wrap_deg(yaw_q - yaw_m[nearest])
    assert np.all(d >= 0.1) and 0.2 <= np.median(d) <= 0.6, f"{name}: nearest map distances {d}"
    if name == "corridor":
        assert np.all(dyaw < 3.0), "corridor query walks straight, like the map"
    else:
        assert np.median(dyaw) >= 12.0 and np.all(dyaw >= 5.0), f"{name}: yaw changes {dyaw}"


def test_map_upright_on_its_mount_query_tilted_as_configured(preset_sessions):
    name, (m, q) = preset_sessions
    config = get_preset(name)
    unmounted = np.einsum("ji,njk->nik", _mount(config, "map"), m.R)  # mount^T R: the robot's frame
    np.testing.assert_allclose(unmounted[:, 1], np.tile([0.0, 1.0, 0.0], (len(m), 1)), atol=1e-12)
    # The query's floor jitter is applied on top of its mount: R = jitter @ mount @ R_yaw.
    g_mounted = gravity_in_camera(q.R) @ _mount(config, "query")  # mount^T g: gravity in the mount frame
    tilt = np.degrees(np.arccos(np.clip(g_mounted[:, 1], -1, 1)))
    limit = config.query_effects.tilt_deg * np.sqrt(2)
    assert tilt.max() <= limit + 1e-9 and tilt.max() > 0.2 * config.query_effects.tilt_deg


def test_existing_presets_unchanged():
    # Poses of the presets that existed before the mount/off-plane options, to 1e-12: the new
    # options must not change them (nor the random streams of their floor jitter).
    c = get_preset("office")
    m, q = build_sessions(dataclasses.replace(c, scene=dataclasses.replace(c.scene, px_per_m=40.0)), seed=0)
    R3 = [
        [0.8825761584140888, 0.009201720980649806, 0.4700794113019881],
        [-0.004257638222708759, 0.999923889816133, -0.01157959808191193],
        [-0.4701501857021796, 0.008218449121845207, 0.882548162979357],
    ]
    np.testing.assert_allclose(q.R[3], R3, atol=1e-12)
    t3 = [-7.405734647348958, 1.075905718506971, -0.934279342664057]
    np.testing.assert_allclose(q.t[3], t3, atol=1e-12)
    np.testing.assert_allclose(m.t[5], [-6.578447439957221, 1.0, 2.807147204510538], atol=1e-12)


def test_mount_pitch_and_roll_exact_centres_kept():
    base = shrunk(get_preset("office"), n_map=6, n_query=5)
    pitch, roll, q_pitch, q_roll = 10.0, -2.0, 13.0, 1.5
    tc = dataclasses.replace(
        base.trajectory,
        mount_pitch_deg=pitch,
        mount_roll_deg=roll,
        query_mount_pitch_deg=q_pitch,
        query_mount_roll_deg=q_roll,
    )
    upright = dataclasses.replace(base, query_effects=dataclasses.replace(base.query_effects, tilt_deg=0.0))
    mounted = dataclasses.replace(upright, trajectory=tc)
    mounts = [(pitch, roll), (q_pitch, q_roll)]
    for s0, s1, (p, r) in zip(build_sessions(upright, 4), build_sessions(mounted, 4), mounts, strict=True):
        np.testing.assert_allclose(camera_centers(s1.R, s1.t), camera_centers(s0.R, s0.t), atol=1e-12)
        g = gravity_in_camera(s1.R)
        # Pitch: the optical axis is p below the horizon (gravity leans towards +z); roll: x-axis up.
        np.testing.assert_allclose(np.degrees(np.arctan2(g[:, 2], g[:, 1])), p, atol=1e-9)
        np.testing.assert_allclose(np.degrees(-np.arcsin(g[:, 0])), r, atol=1e-9)
        axis_in_world = s1.R[:, 2]  # third row: the optical axis in world coordinates (y down)
        if r == 0:
            np.testing.assert_allclose(np.degrees(np.arcsin(axis_in_world[:, 1])), p, atol=1e-9)
        assert np.all(axis_in_world[:, 1] > 0)  # looks down
    R2, t2 = mount_poses(m := s0.R, s0.t, 0.0, 0.0)
    assert R2 is m and t2 is s0.t  # no mount: the very same arrays


def test_offplane_queries_lower_and_handheld():
    config = get_preset("offplane")
    config = dataclasses.replace(config, scene=dataclasses.replace(config.scene, px_per_m=40.0))
    m, q = build_sessions(config, seed=0)
    drop = camera_centers(q.R, q.t)[:, 1] - camera_centers(m.R, m.t)[0, 1]  # y down: positive = lower
    assert drop.min() == pytest.approx(0.2, abs=0.01) and drop.max() == pytest.approx(0.7, abs=0.01)
    tilt = np.degrees(np.arccos(np.clip(gravity_in_camera(q.R)[:, 1], -1, 1)))
    assert 2.0 < tilt.max() <= 4.0 * np.sqrt(2) + 1e-9
    np.testing.assert_allclose(gravity_in_camera(m.R), np.tile([0.0, 1.0, 0.0], (len(m), 1)), atol=1e-12)


def test_mount_and_height_configs_validate():
    tc = get_preset("office").trajectory
    with pytest.raises(ValueError, match="mount pitch"):
        dataclasses.replace(tc, mount_pitch_deg=60.0)
    with pytest.raises(ValueError, match="mount pitch"):
        dataclasses.replace(tc, query_mount_roll_deg=float("nan"))
    with pytest.raises(ValueError, match="0.1 m"):
        dataclasses.replace(tc, query_height_drop=0.8, query_height_wobble=0.2)
    with pytest.raises(ValueError, match="wobble"):
        dataclasses.replace(tc, query_height_wobble=-0.1)
    with pytest.raises(ValueError, match="ceiling"):
        dataclasses.replace(get_preset("office"), trajectory=dataclasses.replace(tc, query_height_drop=-1.7))


def test_lifelong_query_world_changed():
    config = shrunk(get_preset("lifelong"))
    m, q = build_sessions(config, seed=0)
    assert len(q.world.boxes) == len(m.world.boxes) + config.query_effects.added_boxes
    moved = [b for b in m.world.boxes if b not in q.world.boxes]
    assert len(moved) == config.query_effects.moved_boxes
    seeds = {b.texture_seed: b for b in q.world.boxes}
    for b in moved:  # same object (size and look), new place
        assert seeds[b.texture_seed].size == b.size and seeds[b.texture_seed].center_xz != b.center_xz
    static_m = [p for p in m.world.planes if not p.name.startswith("box")]
    static_q = [p for p in q.world.planes if not p.name.startswith("box")]
    assert len(static_m) == len(static_q) and all(a is b for a, b in zip(static_m, static_q, strict=True))
    assert q.effects.gain != 1.0 and q.effects.shading_gradient > 0


def test_tilt_keeps_centres():
    R, t = planar_poses(np.array([[1.0, 2.0], [3.0, 4.0]]), np.array([0.1, 2.0]), 0.8)
    R2, t2 = tilt_poses(R, t, np.random.default_rng(0), 2.0)
    np.testing.assert_allclose(camera_centers(R2, t2), camera_centers(R, t), atol=1e-12)
    assert np.all(np.abs(np.einsum("nij,nkj->nik", R2, R2) - np.eye(3)) < 1e-12)


def test_polygon_distance():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    np.testing.assert_allclose(
        polygon_distance(np.array([[0.5, 0.5], [2, 0.5], [2, 2]]), square), [-0.5, 1.0, np.sqrt(2)]
    )


def test_bad_trajectory_configs_raise():
    base = get_preset("office")
    too_close = dataclasses.replace(
        base, trajectory=dataclasses.replace(base.trajectory, wall_margin=0.7, lateral_offset=0.3)
    )
    with pytest.raises(ValueError, match="query trajectory"):
        build_sessions(too_close)
    no_loop = dataclasses.replace(base, trajectory=dataclasses.replace(base.trajectory, wall_margin=3.5))
    with pytest.raises(ValueError, match="wall_margin"):
        build_sessions(no_loop)
    crowded = dataclasses.replace(base, scene=dataclasses.replace(base.scene, n_boxes=60, px_per_m=40.0))
    with pytest.raises(ValueError, match="cannot place"):
        build_sessions(crowded)
    with pytest.raises(ValueError, match="shape"):
        dataclasses.replace(base.trajectory, shape="circle")
    with pytest.raises(ValueError, match="seed"):
        build_sessions(base, seed=-3)
