"""OpenLORIS-Scene reader: base_link -> camera extrinsic, d400 intrinsics, aligned depth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.io import FormatError, read_dataset, read_openloris
from planarloc.io.openloris import D400_COLOR_CAMERA, DEFAULT_BASE_FROM_CAMERA


def planar_base_poses(n: int) -> list[Pose]:
    """world_from_base: robot on the floor (z = 0), yaw only."""
    return [
        Pose(Rotation.from_euler("z", 0.3 * k).as_matrix(), np.array([0.5 * k, 0.2 * k, 0.0]))
        for k in range(n)
    ]


def write_openloris(root, world_from_base, write_image, *, depth_list: bool):
    color = ["# color images", "# timestamp filename"]
    gt = ["#Time px py pz qx qy qz qw"]
    depth = []
    for k, p in enumerate(world_from_base):
        t = 1560000000.0 + k / 30
        color.append(f"{t:.6f} color/{t:.6f}.png")
        write_image(root / "color" / f"{t:.6f}.png", 848, 480)
        w, x, y, z = p.quat_wxyz
        gt.append(f"{t + 0.001:.6f} " + " ".join(f"{v:.12f}" for v in (*p.t, x, y, z, w)))
        write_image(root / "aligned_depth" / f"{t - 0.002:.6f}.png", 848, 480)
        depth.append(f"{t - 0.002:.6f} aligned_depth/{t - 0.002:.6f}.png")
    (root / "color.txt").write_text("\n".join(color) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    if depth_list:
        (root / "aligned_depth.txt").write_text("\n".join(depth) + "\n")


@pytest.mark.parametrize("depth_list", [True, False])
def test_camera_pose_is_base_composed_with_extrinsic(tmp_path, write_image, pose_close, depth_list):
    world_from_base = planar_base_poses(3)
    write_openloris(tmp_path, world_from_base, write_image, depth_list=depth_list)
    frames = read_openloris(tmp_path)
    assert len(frames) == 3 and frames[0].camera == D400_COLOR_CAMERA
    for f, wb in zip(frames, world_from_base):
        pose_close(f.cam_from_world, (wb @ DEFAULT_BASE_FROM_CAMERA).inverse(), atol=1e-8)
        # the camera sits 0.916 m above the floor, looking along the robot's x axis
        assert f.cam_from_world.center[2] == pytest.approx(0.916, abs=1e-6)
        optical_axis = f.cam_from_world.R.T @ [0, 0, 1]
        np.testing.assert_allclose(optical_axis, wb.R @ [1, 0, 0], atol=0.03)
        assert f.depth_scale == 1000.0 and f.depth_path is not None and f.depth_path.is_file()
    np.testing.assert_allclose(DEFAULT_BASE_FROM_CAMERA.t, [0.2265, -0.0511, 0.916])


def test_overrides_and_registry(tmp_path, write_image, pose_close):
    world_from_base = planar_base_poses(2)
    write_openloris(tmp_path, world_from_base, write_image, depth_list=True)
    cam = Camera("PINHOLE", 848, 480, (600.0, 600.0, 424.0, 240.0))
    frames = read_dataset(tmp_path, "openloris", camera=cam, base_from_camera=None)
    assert frames[0].camera == cam
    pose_close(frames[1].cam_from_world, world_from_base[1].inverse(), atol=1e-8)


def test_missing_groundtruth(tmp_path, write_image):
    write_openloris(tmp_path, planar_base_poses(1), write_image, depth_list=False)
    (tmp_path / "groundtruth.txt").write_text("#Time px py pz qx qy qz qw\n1.0 0 0 0 0 0 1\n")
    with pytest.raises(FormatError, match=r"groundtruth\.txt:2: expected 8 fields"):
        read_openloris(tmp_path)
    (tmp_path / "color.txt").unlink()
    with pytest.raises(FormatError, match=r"color\.txt: file not found; the OpenLORIS-Scene format needs"):
        read_openloris(tmp_path)
