"""COLMAP text model reader: cameras, two-line images.txt, model errors."""

from __future__ import annotations

import pytest

from planarloc.io import FormatError, read_colmap
from planarloc.io.colmap_text import read_colmap_cameras

CAMERAS = """# Camera list with one line of data per camera:
#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]
1 PINHOLE 64 48 50 51 32 24
2 SIMPLE_PINHOLE 64 48 40 32 24
3 OPENCV 64 48 50 51 32 24 -0.1 0.01 0.001 0.002
"""


def image_line(image_id, pose, cam_id, name):
    return f"{image_id} " + " ".join(f"{v:.17g}" for v in (*pose.quat_wxyz, *pose.t)) + f" {cam_id} {name}"


def write_model(root, poses, write_image, *, cameras=CAMERAS, names=None):
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(cameras)
    names = names or [f"frame_{k:03d}.png" for k in range(len(poses))]
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
    ]
    for k, (pose, name) in enumerate(reversed(list(zip(poses, names)))):  # ids not in name order
        lines.append(image_line(10 + k, pose, 1 + k % 3, name))
        lines.append("" if k % 2 else "12.5 3.25 -1 40.0 30.0 7")
        write_image(root / "images" / name)
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    return model


def test_read_colmap(tmp_path, write_image, random_poses, pose_close):
    poses = random_poses(4, seed=6)
    model = write_model(tmp_path, poses, write_image)
    frames = read_colmap(model)  # images found at ../../images
    assert [f.name for f in frames] == [f"frame_{k:03d}.png" for k in range(4)]
    assert [f.index for f in frames] == [0, 1, 2, 3]
    for f, p in zip(frames, poses):
        pose_close(f.cam_from_world, p)  # COLMAP stores cam_from_world
        assert f.path == (tmp_path / "images" / f.name).absolute()
    models = {f.name: f.camera.model.value for f in frames}
    assert models == {
        "frame_003.png": "PINHOLE",
        "frame_002.png": "SIMPLE_PINHOLE",
        "frame_001.png": "OPENCV",
        "frame_000.png": "PINHOLE",
    }
    assert frames[1].camera.params[4:] == (-0.1, 0.01, 0.001, 0.002)
    assert len(read_colmap(model, image_dir=tmp_path / "images")) == 4


def test_points_line_omitted(tmp_path, write_image, random_poses, pose_close):
    poses = random_poses(2)
    model = write_model(tmp_path, poses, write_image)
    text = "\n".join(image_line(i + 1, p, 1, f"frame_{i:03d}.png") for i, p in enumerate(poses)) + "\n"
    (model / "images.txt").write_text(text)
    frames = read_colmap(model)
    assert len(frames) == 2
    pose_close(frames[1].cam_from_world, poses[1])


def test_radial_and_fisheye_models_are_read_with_the_pixel_shift(tmp_path, write_image, random_poses):
    cameras = (
        "1 SIMPLE_RADIAL 64 48 50 32 24 0.01\n2 OPENCV_FISHEYE 64 48 20 21 32 24 0.1 0.01 0.001 0.0001\n"
    )
    model = write_model(tmp_path, random_poses(1), write_image, cameras=cameras)
    cams = read_colmap_cameras(model / "cameras.txt")
    assert cams[1].params == (50.0, 31.5, 23.5, 0.01)
    assert cams[2].params == (20.0, 21.0, 31.5, 23.5, 0.1, 0.01, 0.001, 0.0001)
    (frame,) = read_colmap(model)
    assert frame.camera == cams[1]


def test_unsupported_model_named(tmp_path, write_image, random_poses):
    model = write_model(
        tmp_path, random_poses(1), write_image, cameras="# cams\n1 FOV 64 48 50 51 32 24 0.01\n"
    )
    with pytest.raises(FormatError, match=r"cameras\.txt:2: camera model FOV is not supported .*PINHOLE"):
        read_colmap(model)
    (model / "cameras.txt").write_text("1 FISHY 64 48 50 32 24\n")
    with pytest.raises(FormatError, match=r"cameras\.txt:1: expected '\[KEY\] MODEL"):
        read_colmap(model)


@pytest.mark.parametrize(
    "line, pattern",
    [
        ("1 1 0 0 0 0 0 0 1", r"images\.txt:1: expected 10 fields .* found 9"),
        ("1 1 0 0 0 0 0 0 9 frame_000.png", r"images\.txt:1: expected a CAMERA_ID of cameras\.txt, found 9"),
        ("1 1 0 0 q 0 0 0 1 frame_000.png", r"images\.txt:1: expected a number in column 5 .*'q'"),
        ("x 1 0 0 0 0 0 0 1 frame_000.png", r"images\.txt:1: expected an integer in column 1"),
        ("1 3 0 0 0 0 0 0 1 frame_000.png", r"images\.txt:1: expected a unit quaternion"),
        ("1 1 0 0 0 0 0 0 1 nothere.png", r"images\.txt:1: listed image 'nothere\.png' does not exist"),
    ],
)
def test_malformed_images(tmp_path, write_image, random_poses, line, pattern):
    model = write_model(tmp_path, random_poses(1), write_image)
    (model / "images.txt").write_text(line + "\n\n")
    with pytest.raises(FormatError, match=pattern):
        read_colmap(model)


def test_missing_files(tmp_path, write_image, random_poses):
    model = write_model(tmp_path, random_poses(1), write_image)
    (model / "images.txt").unlink()
    with pytest.raises(FormatError, match=r"images\.txt: file not found; the COLMAP text model format needs"):
        read_colmap(model)
    with pytest.raises(FormatError, match=r"cameras\.txt: file not found"):
        read_colmap(tmp_path)
