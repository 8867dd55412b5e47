"""TUM RGB-D reader: association, camera-to-world poses, intrinsics sources, errors."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io import FormatError, associate_timestamps, read_tum
from planarloc.io.tum import TUM_CAMERAS


def test_associate_timestamps():
    ref = [1.0, 0.0, 2.0, 0.5]
    got = associate_timestamps([0.0, 0.26, 0.49, 1.015, 3.0, 0.25], ref, 0.02)
    np.testing.assert_array_equal(got, [1, -1, 3, 0, -1, -1])
    # nearest wins, ties go to the earlier reference, max_dt is inclusive
    np.testing.assert_array_equal(associate_timestamps([0.25, 0.74], ref, 0.25), [1, 3])
    assert associate_timestamps([1.0], [], 0.1).tolist() == [-1]
    with pytest.raises(InputError, match="max_dt"):
        associate_timestamps([1.0], [1.0], -1)


def write_tum(root, world_from_cam, write_image, *, gt_offset=0.004, n_rgb=None, depth=True):
    """rgb at t = 10 + k/10; ground truth at t + gt_offset for the given poses; depth at t - 0.003."""
    n_rgb = len(world_from_cam) if n_rgb is None else n_rgb
    rgb = ["# color images", "# timestamp filename"]
    for k in range(n_rgb):
        t = 10 + k / 10
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        write_image(root / "rgb" / f"{t:.6f}.png", 640, 480)
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    gt = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for k, p in enumerate(world_from_cam):
        w, x, y, z = p.quat_wxyz
        gt.append(f"{10 + k / 10 + gt_offset:.6f} " + " ".join(f"{v:.12f}" for v in (*p.t, x, y, z, w)))
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if depth:
        lines = []
        for k in range(0, n_rgb, 2):  # depth for every other frame only
            t = 10 + k / 10 - 0.003
            lines.append(f"{t:.6f} depth/{t:.6f}.png")
            write_image(root / "depth" / f"{t:.6f}.png", 640, 480)
        (root / "depth.txt").write_text("# depth\n" + "\n".join(lines) + "\n")


def test_read_tum_associates_and_inverts(tmp_path, write_image, random_poses, pose_close, caplog):
    world_from_cam = random_poses(4, seed=2)
    write_tum(tmp_path, world_from_cam, write_image, n_rgb=5)  # frame 4 has no pose
    with caplog.at_level(logging.WARNING, logger="planarloc.io.tum"):
        frames = read_tum(tmp_path, tum_camera="fr1")
    assert "1 of 5 frames have no ground-truth pose" in caplog.text
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert frames[1].name == "rgb/10.100000.png" and frames[1].timestamp == pytest.approx(10.1)
    for f, wc in zip(frames, world_from_cam):
        pose_close(f.cam_from_world, wc.inverse(), atol=1e-9)
        assert f.camera == TUM_CAMERAS["fr1"] and f.depth_scale == 5000.0
    assert frames[0].depth_path == (tmp_path / "depth/9.997000.png").absolute()
    assert frames[1].depth_path is None
    # a tolerance below the ground-truth offset keeps no frame
    with pytest.raises(FormatError, match="found none"):
        read_tum(tmp_path, tum_camera="fr1", max_dt=0.001)


def test_intrinsics_sources(tmp_path, write_image, random_poses):
    write_tum(tmp_path, random_poses(2), write_image, depth=False)
    with pytest.raises(FormatError, match="cannot determine the camera intrinsics.*tum_camera"):
        read_tum(tmp_path)
    (tmp_path / "camera.txt").write_text("# fx fy cx cy\nPINHOLE 640 480 500 501 320 240\n")
    assert read_tum(tmp_path)[0].camera.params == (500.0, 501.0, 320.0, 240.0)
    assert read_tum(tmp_path, tum_camera="fr3")[0].camera == TUM_CAMERAS["fr3"]
    mine = Camera("SIMPLE_PINHOLE", 640, 480, (400.0, 320.0, 240.0))
    assert read_tum(tmp_path, camera=mine)[0].camera == mine
    with pytest.raises(InputError, match="fr1, fr2, fr3"):
        read_tum(tmp_path, tum_camera="fr9")
    (tmp_path / "camera.txt").write_text("PINHOLE 640 480 500 501 320\n")
    with pytest.raises(FormatError, match=r"camera\.txt:1: Camera.params: PINHOLE takes 4 parameters, got 3"):
        read_tum(tmp_path)


def test_freiburg_directory_name(tmp_path, write_image, random_poses):
    root = tmp_path / "rgbd_dataset_freiburg2_desk"
    write_tum(root, random_poses(2), write_image, depth=False)
    assert read_tum(root)[0].camera == TUM_CAMERAS["fr2"]


def test_base_from_camera(tmp_path, write_image, random_poses, pose_close):
    world_from_base = random_poses(3, seed=5)
    base_from_camera = Pose.from_quat_wxyz([0.5, -0.5, 0.5, -0.5], [0.2, 0.0, 0.9])
    write_tum(tmp_path, world_from_base, write_image, depth=False)
    frames = read_tum(tmp_path, tum_camera="fr1", base_from_camera=base_from_camera)
    for f, wb in zip(frames, world_from_base):
        pose_close(f.cam_from_world, (wb @ base_from_camera).inverse(), atol=1e-9)


@pytest.mark.parametrize(
    "line, pattern",
    [
        ("10.0 1 2 3 0 0 0", r"groundtruth\.txt:3: expected 8 fields .* found 7"),
        ("10.0 1 2 x 0 0 0 1", r"groundtruth\.txt:3: expected a number in column 4 .*'x'"),
        ("10.0 1 2 3 0 0 0 2", r"groundtruth\.txt:3: expected a unit quaternion .* found norm 2"),
        ("10.0 1 2 3 0 0 0 0", r"groundtruth\.txt:3: expected a unit quaternion .* found norm 0"),
    ],
)
def test_malformed_groundtruth(tmp_path, write_image, random_poses, line, pattern):
    write_tum(tmp_path, random_poses(2), write_image, depth=False)
    text = (tmp_path / "groundtruth.txt").read_text().splitlines()
    text.insert(2, line)
    (tmp_path / "groundtruth.txt").write_text("\n".join(text) + "\n")
    with pytest.raises(FormatError, match=pattern):
        read_tum(tmp_path, tum_camera="fr1")


def test_malformed_rgb_list_and_missing(tmp_path, write_image, random_poses):
    write_tum(tmp_path, random_poses(2), write_image, depth=False)
    (tmp_path / "rgb" / "10.100000.png").unlink()
    with pytest.raises(FormatError, match=r"rgb\.txt:4: listed image 'rgb/10\.100000\.png' does not exist"):
        read_tum(tmp_path, tum_camera="fr1")
    (tmp_path / "rgb.txt").write_text("10.0 rgb/a.png extra\n")
    with pytest.raises(FormatError, match=r"rgb\.txt:1: expected 2 fields 'timestamp filename', found 3"):
        read_tum(tmp_path, tum_camera="fr1")
    (tmp_path / "groundtruth.txt").unlink()
    (tmp_path / "rgb.txt").write_text("10.0 rgb/10.000000.png\n")
    with pytest.raises(FormatError, match=r"groundtruth\.txt: file not found; the TUM RGB-D format needs"):
        read_tum(tmp_path, tum_camera="fr1")
