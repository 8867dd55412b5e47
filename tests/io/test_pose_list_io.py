"""Pose lists (hloc results convention): write/read round trip, intrinsics files, errors."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.io import FormatError, read_pose_list, write_pose_list

CAM = Camera("PINHOLE", 64, 48, (50.0, 51.0, 32.0, 24.0))


def test_round_trip_exact(tmp_path, random_poses, write_image):
    poses = random_poses(5, seed=8)
    names = [f"query/{k:04d}.jpg" for k in range(5)]
    out = tmp_path / "results" / "poses.txt"
    write_pose_list(out, zip(names, poses))
    first = out.read_text().splitlines()[0].split()
    assert first[0] == "query/0000.jpg" and len(first) == 8
    q = np.array([float(v) for v in first[1:5]])
    np.testing.assert_allclose(q, poses[0].quat_wxyz, atol=0)  # qw first, full precision
    frames = read_pose_list(out, camera=CAM, check_images=False)
    assert [f.name for f in frames] == names and [f.index for f in frames] == list(range(5))
    for f, p in zip(frames, poses):
        np.testing.assert_allclose(f.cam_from_world.R, p.R, atol=1e-14)
        np.testing.assert_array_equal(f.cam_from_world.t, p.t)
        assert f.camera == CAM and f.path == (out.parent / f.name).absolute()


def test_cameras_file_per_image_and_default(tmp_path, write_image):
    for name in ("a.png", "b.png"):
        write_image(tmp_path / "imgs" / name)
    (tmp_path / "list.txt").write_text(
        "# name qw qx qy qz tx ty tz\na.png 1 0 0 0 1 2 3\n\nb.png 0 1 0 0 0 0 0\n"
    )
    (tmp_path / "intrinsics.txt").write_text(
        "a.png SIMPLE_PINHOLE 64 48 40 32 24\nPINHOLE 64 48 50 51 32 24\n"
    )
    frames = read_pose_list(
        tmp_path / "list.txt", cameras_file=tmp_path / "intrinsics.txt", image_dir=tmp_path / "imgs"
    )
    assert frames[0].camera.model.value == "SIMPLE_PINHOLE" and frames[1].camera == CAM
    np.testing.assert_allclose(frames[0].cam_from_world.center, [-1, -2, -3])
    # a directory root uses poses.txt and cameras.txt (a COLMAP cameras.txt with one camera)
    (tmp_path / "imgs" / "poses.txt").write_text("a.png 1 0 0 0 0 0 0\n")
    (tmp_path / "imgs" / "cameras.txt").write_text("1 PINHOLE 64 48 50 51 32 24\n")
    assert read_pose_list(tmp_path / "imgs")[0].camera == CAM


def test_errors(tmp_path, write_image):
    lst = tmp_path / "poses.txt"
    lst.write_text("a.png 1 0 0 0 0 0 0\n")
    with pytest.raises(FormatError, match="cannot determine the camera intrinsics"):
        read_pose_list(lst, check_images=False)
    (tmp_path / "cams.txt").write_text("x.png PINHOLE 64 48 50 51 32 24\ny.png PINHOLE 64 48 50 51 32 24\n")
    with pytest.raises(FormatError, match=r"poses\.txt:1: expected intrinsics for image 'a\.png'"):
        read_pose_list(lst, cameras_file=tmp_path / "cams.txt", check_images=False)
    with pytest.raises(FormatError, match=r"poses\.txt:1: listed image 'a\.png' does not exist"):
        read_pose_list(lst, camera=CAM)
    for text, pattern in [
        ("a.png 1 0 0 0 0 0\n", r"poses\.txt:1: expected 8 fields .* found 7"),
        (
            "a.png 1 0 0 0 0 0 0\nb.png 1 0 0 0 0 0 zero\n",
            r"poses\.txt:2: expected a number in column 8 .*'zero'",
        ),
        ("a.png 0.2 0 0 0 0 0 0\n", r"poses\.txt:1: expected a unit quaternion"),
        ("a.png 1 0 0 0 0 0 0\na.png 1 0 0 0 0 0 0\n", r"poses\.txt:2: expected unique names"),
    ]:
        lst.write_text(text)
        with pytest.raises(FormatError, match=pattern):
            read_pose_list(lst, camera=CAM, check_images=False)
    with pytest.raises(InputError, match="whitespace"):
        write_pose_list(tmp_path / "out.txt", [("my image.png", Pose.identity())])
    assert not (tmp_path / "out.txt").exists()
