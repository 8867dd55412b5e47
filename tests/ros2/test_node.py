"""`planarloc ros2` for real: the node runs as a subprocess, an rclpy publisher replays the tiny
world's query frames on loopback, a subscriber checks the poses against the ground truth (in the
z-up map frame), the ``map → odom`` transform and the diagnostics; bad frames and a missing
CameraInfo do not stop it; SIGINT stops it with exit 0."""

from __future__ import annotations

import os
import subprocess
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="rclpy is not installed (pip install 'planarloc[ros2]')")

from record_schemas import check  # noqa: E402

from planarloc.geometry.pose import Pose, pose_errors  # noqa: E402
from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.ros2.replay import ReplayFrame, loopback_env, planarloc_command, replay  # noqa: E402
from planarloc.ros2.settings import SHARE_DIR  # noqa: E402
from planarloc.synthetic.stream import make_stream, stream_order  # noqa: E402

#: a base_link (x forward, y left, z up) with the optical camera 0.2 m ahead and 0.5 m up
BASE_FROM_CAMERA = Pose.from_quat_wxyz([0.5, -0.5, 0.5, -0.5], [0.2, 0.0, 0.5])
#: per frame: the first one may compile numba's kernels in a fresh checkout (minutes of CPU)
WAIT_S = 900.0
#: gravity (down) in the generated world (x right, y down, z forward of its cameras)
G_WORLD = np.array([0.0, 1.0, 0.0])
#: the z-up map of that world, written out (REP-103): map x = world x, map y = world z, map z = -world y
MAP_FROM_WORLD = Pose(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]), np.zeros(3))


def _frames(tiny_world: Path, odometry: bool) -> tuple[list[ReplayFrame], list[Pose]]:
    queries = read_dataset(tiny_world / "query", "tum")
    stream = make_stream(queries, stream_order(len(queries)), np.random.default_rng(0))
    cam_from_base = BASE_FROM_CAMERA.inverse()
    frames = [
        ReplayFrame(
            f.image.path,
            f.image.camera,
            f.stamp,
            (f.odometry.inverse() @ cam_from_base) if odometry else None,
        )
        for f in stream
    ]
    return frames, [f.image.cam_from_world for f in stream]


def _check_poses(
    result,
    truths: list[Pose],
    frames: list[ReplayFrame],
    child_from_camera: Pose,
    map_from_world: Pose = MAP_FROM_WORLD,
) -> int:
    """Every published pose is within 0.25 m / 10° of the truth taken into the map frame (never
    beyond 1 m, and within 3σ + 5 cm of its covariance); returns how many."""
    good = 0
    for frame, cam_from_world in zip(frames, truths):
        key = round(frame.stamp, 9)
        assert key in result.diagnostics, f"no diagnostic for the frame at {frame.stamp}"
        if key not in result.poses:
            assert result.diagnostics[key]["published"] == "false"
            continue
        map_from_child, cov, frame_id = result.poses[key]
        assert frame_id == "map"
        assert cov.shape == (6, 6) and np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
        truth = map_from_world @ cam_from_world.inverse() @ child_from_camera.inverse()  # map_from_child
        t_err, r_err = pose_errors(map_from_child.inverse(), truth.inverse())
        assert t_err < 1.0
        # the position block is the camera's (or base's) position in the map: the error is within it
        assert t_err <= 3 * np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1]) + 0.05
        good += t_err < 0.25 and r_err < 10
    return good


def _gravity_tilts_deg(
    result, truths: list[Pose], frames: list[ReplayFrame], child_from_camera: Pose
) -> list:
    """Per published pose: the angle between -z of the published frame and the world's gravity carried
    through the pose (the truth's gravity in the child frame, rotated by the published map_from_child)."""
    tilts = []
    for frame, cam_from_world in zip(frames, truths):
        if round(frame.stamp, 9) in result.poses:
            map_from_child = result.poses[round(frame.stamp, 9)][0]
            g_child = (child_from_camera @ cam_from_world).R @ G_WORLD
            tilts.append(np.degrees(np.arccos(np.clip(-(map_from_child.R @ g_child)[2], -1, 1))))
    return tilts


def test_node_localizes_a_replayed_stream_with_odometry_and_publishes_map_to_odom(
    tiny_world: Path, world_map: Path, start_node
) -> None:
    """Defaults: a z-up map, map -> odom stamped transform_tolerance_s = 1 s ahead (as AMCL)."""
    node = start_node(
        "--map",
        world_map,
        "--ros-args",
        "-p",
        "odom_topic:=/odom",
        "-p",
        "base_frame:=base_link",
        "-p",
        "fixes:=wait",
    )  # a sparse stream: each frame needs its fix
    frames, truths = _frames(tiny_world, odometry=True)
    result = replay(frames, base_from_camera=BASE_FROM_CAMERA, wait_s=WAIT_S)
    good = _check_poses(result, truths, frames, BASE_FROM_CAMERA)
    assert good >= len(frames) - 1
    # z-up: the world's gravity is -z of the published frame (a base_link is z-up itself: its z is up too)
    tilts = _gravity_tilts_deg(result, truths, frames, BASE_FROM_CAMERA)
    assert len(tilts) == len(result.poses) and max(tilts) < 1.0, tilts
    assert all(p.R[2, 2] > np.cos(np.radians(1.0)) for p, _, _ in result.poses.values())  # base z is map z
    # AMCL's contract: map_from_odom · odom_from_base(t) is the base's pose in the map at t, stamped t + 1 s
    assert result.map_from_odom, "no map -> odom transform on /tf"
    assert len(result.map_from_odom) == len(result.poses)
    for frame, cam_from_world in zip(frames, truths):
        key = round(frame.stamp, 9)
        assert key not in result.map_from_odom  # never stamped with the image's own stamp
        if key in result.poses:
            map_from_odom, parent, child = result.map_from_odom[round(frame.stamp + 1.0, 9)]
            assert (parent, child) == ("map", "odom")
            map_from_base = map_from_odom @ frame.odom_from_base
            assert np.allclose(map_from_base.matrix, result.poses[key][0].matrix, atol=1e-6)
    last = result.diagnostics[round(frames[-1].stamp, 9)]
    assert int(last["frames_received"]) == int(last["frames_processed"]) == len(frames)
    assert int(last["frames_dropped"]) == 0 and last["motion_source"] == "odometry"
    assert float(last["fix_rate"]) == int(last["frames_localized"]) / len(frames) > 0.8
    assert node.interrupt() == 0
    err = "".join(node.stderr)
    assert "Traceback" not in err and f"stopped after {len(frames)} frames" in err


def test_bad_frames_and_no_camera_info_never_stop_the_node(
    tiny_world: Path, world_map: Path, start_node
) -> None:
    """Compressed images without CameraInfo (the map's only camera, a warning once) and without
    odometry, the packaged params.yaml; a black, an empty and a damaged frame in the stream are
    failed diagnostics with their reason, and good poses follow them."""
    node = start_node(
        "--map",
        world_map,
        "--ros-args",
        "--params-file",
        SHARE_DIR / "params.yaml",
        "-p",
        "image_topic:=/cam/image/compressed",
        "-p",
        "camera_info_topic:=/cam/camera_info",
        "-p",
        "odom_topic:=''",
        "-p",
        "fixes:=wait",
    )
    frames, truths = _frames(tiny_world, odometry=False)
    frames = [replace(f, camera=None) for f in frames]
    at = frames[2].stamp
    bad = {
        round(at + 0.02, 9): (np.zeros((240, 320), np.uint8), "uniform image"),
        round(at + 0.04, 9): (b"", "0 bytes"),
        round(at + 0.06, 9): (b"\x89PNG\r\n\x1a\n" + bytes(range(64)), "PNG"),
    }
    stream = frames[:3] + [ReplayFrame(image, None, stamp) for stamp, (image, _) in bad.items()] + frames[3:]
    result = replay(
        stream, image_topic="/cam/image/compressed", camera_info_topic="/cam/camera_info", wait_s=WAIT_S
    )
    for stamp, (_, reason) in bad.items():
        diag = result.diagnostics[stamp]
        assert diag["status"] == "failed" and diag["published"] == "false" and stamp not in result.poses
        assert diag["reason"].startswith("bad frame: ") and reason in diag["reason"], diag
        record = check("record", diag["record"], f"diagnostic record of the bad frame at {stamp}")
        assert (
            record["kind"] == "frame" and record["status"] == "error" and record["message"] == diag["reason"]
        )
    for f in frames:  # every diagnostic carries the frame's record (one schema for every front door)
        record = check("record", result.diagnostics[round(f.stamp, 9)]["record"], f"record at {f.stamp}")
        assert record["status"] == result.diagnostics[round(f.stamp, 9)]["status"]
        assert record["stamp"] == pytest.approx(f.stamp, abs=1e-6)
    # every published pose keeps the promise (3σ + 5 cm); poses go on after the bad frames
    assert _check_poses(result, truths, frames, Pose.identity()) >= 2
    assert any(stamp > max(bad) for stamp in result.poses), sorted(result.poses)
    assert {result.diagnostics[round(f.stamp, 9)]["camera_source"] for f in frames} == {"map"}
    last = result.diagnostics[round(frames[-1].stamp, 9)]
    assert int(last["frames_failed"]) == 3 and int(last["frames_processed"]) == len(frames)
    assert not result.map_from_odom
    assert node.interrupt() == 0
    err = "".join(node.stderr)
    assert "Traceback" not in err and "3 failed" in err
    warnings = [
        line
        for line in err.splitlines()
        if "no CameraInfo on /cam/camera_info: using the map's only camera" in line
    ]
    assert len(warnings) == 1 and "WARN" in warnings[0], err


def test_initial_pose_and_time_going_back_restart_the_stream(
    tiny_world: Path, world_map: Path, start_node
) -> None:
    """Also the old frame (map_frame_convention:=world) and no TF (tf_broadcast:=false)."""
    node = start_node(
        "--map", world_map, "--ros-args", "-p", "tf_broadcast:=false", "-p", "map_frame_convention:=world"
    )
    assert "in map: the map's world" in "".join(node.stderr)
    frames, truths = _frames(tiny_world, odometry=True)
    first = replay(frames[:3], base_from_camera=BASE_FROM_CAMERA, wait_s=WAIT_S, initialpose_before=2)
    assert first.diagnostics[round(frames[2].stamp, 9)]["note"] == "restarted by the initial pose"
    assert first.diagnostics[round(frames[2].stamp, 9)]["motion_source"] == "none"  # a new stream
    again = replay(frames[:2], base_from_camera=BASE_FROM_CAMERA, wait_s=WAIT_S)  # a bag played again
    assert again.diagnostics[round(frames[0].stamp, 9)]["note"].startswith("time went back")
    assert _check_poses(again, truths[:2], frames[:2], BASE_FROM_CAMERA, map_from_world=Pose.identity()) >= 1
    assert first.poses and not first.map_from_odom and not again.map_from_odom  # poses, with odometry, no TF
    assert node.interrupt() == 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["--ros-args", "-p", "nosuch:=1"], "unknown parameter 'nosuch'"),
        (["--ros-args", "-p", "method:=bogus"], "parameter method: expected one of auto"),
        (["--ros-args", "-p", "top_n:=abc"], "parameter top_n: expected an integer"),
        (["--ros-args", "-p", "image_qos:=fast"], "parameter image_qos"),
        (["--ros-args", "-p", "base_to_camera:=1 2 3"], "parameter base_to_camera"),
    ],
)
def test_bad_parameters_are_one_line_errors(
    world_map: Path, ros_domain: int, args: list, message: str
) -> None:
    proc = subprocess.run(
        [*planarloc_command(), "ros2", "--map", str(world_map), *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **loopback_env(ros_domain)},
    )
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr


def test_a_missing_map_is_a_one_line_error(tmp_path: Path, ros_domain: int) -> None:
    proc = subprocess.run(
        [*planarloc_command(), "ros2", "--map", str(tmp_path / "none.db")],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, **loopback_env(ros_domain)},
    )
    assert (
        proc.returncode == 1
        and proc.stderr.strip() == f"planarloc ros2: error: {tmp_path / 'none.db'}: no such map file"
    )


def test_sigint_before_any_frame_exits_cleanly(world_map: Path, start_node) -> None:
    node = start_node("--map", world_map)
    assert node.interrupt() == 0
    err = "".join(node.stderr)
    assert "Traceback" not in err and "stopped after 0 frames" in err


def test_tf2_msgs_that_cannot_be_built_is_a_one_line_error(
    world_map: Path, tmp_path: Path, ros_domain: int
) -> None:
    env = {**os.environ, **loopback_env(ros_domain), "PLANARLOC_CACHE": str(tmp_path), "CC": "no-such-cc"}
    proc = subprocess.run(
        [*planarloc_command(), "ros2", "--map", str(world_map)],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(lines) == 1, proc.stderr
    assert "tf2_msgs" in lines[0] and "no C/C++ compiler (CC=no-such-cc)" in lines[0]


def test_on_an_empty_kernel_cache_the_node_is_up_in_seconds_and_publishes_poses_as_python(
    tiny_world: Path, world_map: Path, ros_domain: int, tmp_path: Path
) -> None:
    """No `planarloc warmup`: the node says so once, runs its kernels as Python while one detached
    process compiles them, and its poses are as good as the compiled ones."""
    import re
    import signal

    from planarloc.ros2.replay import NodeProcess

    (tmp_path / "tmp").mkdir()
    cold = {
        **loopback_env(ros_domain),
        "NUMBA_CACHE_DIR": str(tmp_path / "numba"),  # empty: a machine without the warm-up
        "TMPDIR": str(tmp_path / "tmp"),
        "PLANARLOC_COMPILE": "auto",  # the default (the tests' conftest sets wait)
    }
    node = NodeProcess(["--map", str(world_map), "--ros-args", "-p", "fixes:=wait"], cold)
    pid = None
    try:
        node.wait_ready(timeout=120.0)
        notice = re.compile(r".*kernels are not compiled yet .*compiling them in the background \(pid (\d+),")
        notices = [m for m in map(notice.match, node.stderr) if m]
        assert len(notices) == 1, "".join(node.stderr)
        pid = int(notices[0][1])
        frames, truths = _frames(tiny_world, odometry=False)
        frames, truths = frames[:3], truths[:3]
        result = replay(frames, wait_s=WAIT_S)
        assert _check_poses(result, truths, frames, Pose.identity()) >= 2
        assert node.interrupt() == 0
        assert "Traceback" not in "".join(node.stderr)
    finally:
        node.kill()
        if pid is not None:
            os.killpg(pid, signal.SIGKILL)  # the detached compile and its workers (minutes of CPU)
