"""Two different poses at one stamp (TUM ground truth, kapture trajectories): never one of them
picked silently. As the ROS bag reader does (README, "ROS bags"), all of them are dropped with a
warning per line naming the file and line; the same pose given twice counts once."""

from __future__ import annotations

import logging

import pytest
from test_kapture_reader import write_kapture
from test_tum_reader import write_tum

from planarloc.io import FormatError, read_kapture, read_tum
from planarloc.io.odometry import read_odometry


def add_lines(path, lines: list[str]) -> None:
    path.write_text(path.read_text() + "".join(line + "\n" for line in lines))


def tum_line(stamp: str, pose) -> str:
    w, x, y, z = pose.quat_wxyz
    return stamp + " " + " ".join(f"{v:.12f}" for v in (*pose.t, x, y, z, w))


def test_tum_ground_truth_with_two_poses_at_one_stamp(
    tmp_path, write_image, random_poses, pose_close, caplog
):
    poses = random_poses(4, seed=7)
    write_tum(tmp_path, poses[:3], write_image, n_rgb=3, depth=False)  # ground truth on lines 3-5
    gt = tmp_path / "groundtruth.txt"
    add_lines(
        gt,
        [
            tum_line("10.104000", poses[3]),  # line 6: frame 1's stamp, another pose
            tum_line("10.204000", poses[2]),
        ],
    )  # line 7: frame 2's pose again
    with caplog.at_level(logging.WARNING, logger="planarloc.io.tum"):
        frames = read_tum(tmp_path, tum_camera="fr1")
    assert [f.index for f in frames] == [0, 2]  # frame 1 has no usable pose: none is guessed
    pose_close(frames[1].cam_from_world, poses[2].inverse())
    warnings = [r.getMessage() for r in caplog.records]
    assert any(f"{gt}:4: timestamp 10.104 has different poses on line(s) 6" in w for w in warnings)
    assert any(f"{gt}:6: timestamp 10.104 has different poses on line(s) 4" in w for w in warnings)
    assert not any("10.204" in w for w in warnings)  # the same pose twice is fine
    assert "1 of 3 frames have no ground-truth pose" in caplog.text


def test_tum_ground_truth_where_every_stamp_is_ambiguous(tmp_path, write_image, random_poses):
    poses = random_poses(2, seed=8)
    write_tum(tmp_path, poses[:1], write_image, n_rgb=1, depth=False)
    add_lines(tmp_path / "groundtruth.txt", [tum_line("10.004000", poses[1])])
    with pytest.raises(FormatError, match=r"groundtruth\.txt: every timestamp has different poses"):
        read_tum(tmp_path, tum_camera="fr1")


def test_an_odometry_file_read_line_by_line_keeps_its_lines(tmp_path, random_poses):
    """Without frame stamps an odometry file is one pose per frame, in order: nothing is dropped."""
    poses = random_poses(2, seed=9)
    path = tmp_path / "odom.txt"
    path.write_text(tum_line("1.0", poses[0]) + "\n" + tum_line("1.0", poses[1]) + "\n")
    assert len(read_odometry(path)) == 2


def test_kapture_trajectory_with_two_poses_at_one_stamp(
    tmp_path, write_image, random_poses, pose_close, caplog
):
    p = random_poses(4, seed=10)
    write_kapture(tmp_path, [(0, "cam0", p[0]), (1, "cam0", p[1]), (2, "cam0", p[2])], write_image)
    traj = tmp_path / "sensors" / "trajectories.txt"
    line = lambda ts, pose: f"{ts}, cam0, " + ", ".join(f"{v:.15g}" for v in (*pose.quat_wxyz, *pose.t))  # noqa: E731
    add_lines(
        traj,
        [
            line("1.0", p[3]),  # line 6: the stamp of line 4 (1 == 1.0), another pose
            line("2", p[2]),
        ],
    )  # line 7: line 5 again
    with caplog.at_level(logging.WARNING, logger="planarloc.io.kapture"):
        frames = read_kapture(tmp_path)
    assert [f.name for f in frames] == ["cam0/0000.png", "cam0/0002.png"]
    pose_close(frames[1].cam_from_world, p[2])
    warnings = [r.getMessage() for r in caplog.records]
    assert any(f"{traj}:4: 1, cam0 has different poses on line(s) 6" in w for w in warnings)
    assert any(f"{traj}:6: 1, cam0 has different poses on line(s) 4" in w for w in warnings)
    assert "1 camera record(s) have no pose" in caplog.text


def test_kapture_rig_with_two_poses_for_one_sensor(tmp_path, write_image, random_poses, caplog):
    p = random_poses(3, seed=11)
    rig_line = lambda pose: "rig, cam0, " + ", ".join(f"{v:.15g}" for v in (*pose.quat_wxyz, *pose.t))  # noqa: E731
    write_kapture(
        tmp_path,
        [(0, "rig", p[0]), (0, "cam1", p[0])],
        write_image,
        records=[(0, "cam0", "cam0/0000.png"), (0, "cam1", "cam1/0000.png")],
        rigs=rig_line(p[1]) + "\n" + rig_line(p[2]) + "\n",
    )
    with caplog.at_level(logging.WARNING, logger="planarloc.io.kapture"):
        frames = read_kapture(tmp_path)
    assert [f.name for f in frames] == ["cam1/0000.png"]  # cam0's pose in the rig is ambiguous
    assert "rigs.txt:2: rig, cam0 has different poses on line(s) 3" in caplog.text
