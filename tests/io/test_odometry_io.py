"""Odometry files (TUM layout) and image lists."""

from __future__ import annotations

from pathlib import Path

import pytest

from planarloc.geometry.pose import Pose, pose_errors
from planarloc.io.format_error import FormatError
from planarloc.io.odometry import read_image_list, read_odometry
from planarloc.robust.pose_graph import so3_exp


def test_round_trip_and_association(tmp_path: Path) -> None:
    poses = [Pose(so3_exp([[0, 0.1 * k, 0]])[0], [0.2 * k, 0, 1.0]) for k in range(4)]
    path = tmp_path / "odom.txt"
    lines = []
    for s, p in zip([0.0, 0.1, 0.2, 0.3], poses):
        q = p.inverse()  # the file holds odom_from_cam
        w, x, y, z = q.quat_wxyz
        lines.append(" ".join(f"{v:.12g}" for v in (s, *q.t, x, y, z, w)))
    path.write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(lines) + "\n")
    back = read_odometry(path)
    assert all(pose_errors(a, b)[0] < 1e-6 and pose_errors(a, b)[1] < 1e-2 for a, b in zip(back, poses))
    assoc = read_odometry(path, stamps=[0.101, 0.25, 0.3])
    assert assoc[1] is None and pose_errors(assoc[0], poses[1])[0] < 1e-6
    base = read_odometry(path, base_from_camera=Pose(so3_exp([[0.1, 0, 0]])[0], [0, 0, 0.5]))
    assert pose_errors(base[1] @ base[0].inverse(), poses[1] @ poses[0].inverse())[0] > 1e-3


def test_bad_files_name_the_line(tmp_path: Path) -> None:
    path = tmp_path / "odom.txt"
    path.write_text("0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"odom.txt.*2"):
        read_odometry(path)
    path.write_text("5 0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match="no odometry sample") as exc:
        read_odometry(path, stamps=[0.0, 0.1])
    # what to do, without an option that does not exist (it once named --odometry-max-dt)
    assert str(exc.value).endswith("check that the odometry and the frames use the same clock")


def test_image_list(tmp_path: Path) -> None:
    (tmp_path / "a.png").write_bytes(b"x")
    (tmp_path / "b.png").write_bytes(b"x")
    lst = tmp_path / "frames.txt"
    lst.write_text("# stream\n0.0 a.png\n0.1 b.png\n")
    assert read_image_list(lst) == [(0.0, tmp_path / "a.png"), (0.1, tmp_path / "b.png")]
    lst.write_text("a.png\nmissing.png\n")
    with pytest.raises(FormatError, match="missing.png"):
        read_image_list(lst)
    lst.write_text("0.0 a.png\nb.png\n")
    with pytest.raises(FormatError, match="every line"):
        read_image_list(lst)
