"""`planarloc ros2` for real: the node runs as a subprocess, an rclpy publisher replays the tiny
world's query frames on loopback, a subscriber checks the poses against the ground truth, the
``map → odom`` transform and the diagnostics; SIGINT stops it with exit 0."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rclpy", reason="rclpy is not installed (pip install 'planarloc[ros2]')")

from planarloc.geometry.pose import Pose, pose_errors  # noqa: E402
from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.ros2.replay import ReplayFrame, loopback_env, planarloc_command, replay  # noqa: E402
from planarloc.synthetic.stream import make_stream, stream_order  # noqa: E402

#: a base_link (x forward, y left, z up) with the optical camera 0.2 m ahead and 0.5 m up
BASE_FROM_CAMERA = Pose.from_quat_wxyz([0.5, -0.5, 0.5, -0.5], [0.2, 0.0, 0.5])
#: per frame: the first one may compile numba's kernels in a fresh checkout (minutes of CPU)
WAIT_S = 900.0


def _frames(tiny_world: Path, odometry: bool) -> tuple[list[ReplayFrame], list[Pose]]:
    queries = read_dataset(tiny_world / "query", "tum")
    stream = make_stream(queries, stream_order(len(queries)), np.random.default_rng(0))
    cam_from_base = BASE_FROM_CAMERA.inverse()
    frames = [ReplayFrame(f.image.path, f.image.camera, f.stamp,
                          (f.odometry.inverse() @ cam_from_base) if odometry else None) for f in stream]
    return frames, [f.image.cam_from_world for f in stream]


def _check_poses(result, truths: list[Pose], frames: list[ReplayFrame], child_from_camera: Pose) -> int:
    """Every published pose is within 0.25 m / 10° of the truth (never beyond 1 m); returns how many."""
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
        truth = cam_from_world.inverse() @ child_from_camera.inverse()   # map_from_child
        t_err, r_err = pose_errors(map_from_child.inverse(), truth.inverse())
        assert t_err < 1.0
        # the position block is the camera's (or base's) position in the map: the error is within it
        assert t_err <= 3 * np.sqrt(np.linalg.eigvalsh(cov[:3, :3])[-1]) + 0.05
        good += t_err < 0.25 and r_err < 10
    return good


def test_node_localizes_a_replayed_stream_with_odometry_and_publishes_map_to_odom(
        tiny_world: Path, world_map: Path, start_node) -> None:
    node = start_node("--map", world_map, "--ros-args", "-p", "odom_topic:=/odom", "-p", "base_frame:=base_link",
                      "-p", "fixes:=wait")  # a sparse stream: each frame needs its fix
    frames, truths = _frames(tiny_world, odometry=True)
    result = replay(frames, base_from_camera=BASE_FROM_CAMERA, wait_s=WAIT_S)
    good = _check_poses(result, truths, frames, BASE_FROM_CAMERA)
    assert good >= len(frames) - 1
    # AMCL's contract: map_from_odom · odom_from_base(t) is the base's pose in the map at t
    assert result.map_from_odom, "no map -> odom transform on /tf"
    for frame, cam_from_world in zip(frames, truths):
        key = round(frame.stamp, 9)
        if key in result.poses:
            map_from_odom, parent, child = result.map_from_odom[key]
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


def test_compressed_images_without_odometry_give_the_camera_pose_and_no_transform(
        tiny_world: Path, world_map: Path, start_node) -> None:
    node = start_node("--map", world_map, "--ros-args", "-p", "image_topic:=/cam/image/compressed",
                      "-p", "camera_info_topic:=/cam/camera_info", "-p", "odom_topic:=''", "-p", "fixes:=wait")
    frames, truths = _frames(tiny_world, odometry=False)
    result = replay(frames, image_topic="/cam/image/compressed", camera_info_topic="/cam/camera_info",
                    wait_s=WAIT_S)
    # every published pose is right; without odometry this sparse stream (frames ~1 m apart) loses some frames
    assert _check_poses(result, truths, frames, Pose.identity()) >= 2
    assert not result.map_from_odom
    assert node.interrupt() == 0
    assert "Traceback" not in "".join(node.stderr)


def test_initial_pose_and_time_going_back_restart_the_stream(tiny_world: Path, world_map: Path, start_node) -> None:
    node = start_node("--map", world_map)
    frames, truths = _frames(tiny_world, odometry=True)
    first = replay(frames[:3], base_from_camera=BASE_FROM_CAMERA, wait_s=WAIT_S, initialpose_before=2)
    assert first.diagnostics[round(frames[2].stamp, 9)]["note"] == "restarted by the initial pose"
    assert first.diagnostics[round(frames[2].stamp, 9)]["motion_source"] == "none"   # a new stream
    again = replay(frames[:2], base_from_camera=BASE_FROM_CAMERA, wait_s=WAIT_S)     # a bag played again
    assert again.diagnostics[round(frames[0].stamp, 9)]["note"].startswith("time went back")
    assert _check_poses(again, truths[:2], frames[:2], BASE_FROM_CAMERA) >= 1
    assert node.interrupt() == 0


@pytest.mark.parametrize("args, message", [
    (["--ros-args", "-p", "nosuch:=1"], "unknown parameter 'nosuch'"),
    (["--ros-args", "-p", "method:=bogus"], "parameter method: expected one of auto"),
    (["--ros-args", "-p", "top_n:=abc"], "parameter top_n: expected an integer"),
    (["--ros-args", "-p", "image_qos:=fast"], "parameter image_qos"),
    (["--ros-args", "-p", "base_to_camera:=1 2 3"], "parameter base_to_camera"),
])
def test_bad_parameters_are_one_line_errors(world_map: Path, ros_domain: int, args: list, message: str) -> None:
    proc = subprocess.run([*planarloc_command(), "ros2", "--map", str(world_map), *args], capture_output=True,
                          text=True, timeout=300, env={**os.environ, **loopback_env(ros_domain)})
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], proc.stderr


def test_a_missing_map_is_a_one_line_error(tmp_path: Path, ros_domain: int) -> None:
    proc = subprocess.run([*planarloc_command(), "ros2", "--map", str(tmp_path / "none.db")], capture_output=True,
                          text=True, timeout=300, env={**os.environ, **loopback_env(ros_domain)})
    assert proc.returncode == 1 and proc.stderr.strip() == f"planarloc ros2: error: {tmp_path / 'none.db'}: no such map file"


def test_sigint_before_any_frame_exits_cleanly(world_map: Path, start_node) -> None:
    node = start_node("--map", world_map)
    assert node.interrupt() == 0
    err = "".join(node.stderr)
    assert "Traceback" not in err and "stopped after 0 frames" in err


def test_tf2_msgs_that_cannot_be_built_is_a_one_line_error(world_map: Path, tmp_path: Path, ros_domain: int) -> None:
    env = {**os.environ, **loopback_env(ros_domain), "PLANARLOC_CACHE": str(tmp_path), "CC": "no-such-cc"}
    proc = subprocess.run([*planarloc_command(), "ros2", "--map", str(world_map)], capture_output=True, text=True,
                          timeout=300, env=env)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(lines) == 1, proc.stderr
    assert "tf2_msgs" in lines[0] and "no C/C++ compiler (CC=no-such-cc)" in lines[0]
