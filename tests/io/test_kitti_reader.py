"""KITTI odometry reader: poses (camera-to-world -> cam_from_world), calib, images, errors."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from planarloc.geometry.pose import Pose
from planarloc.io import FormatError, read_kitti
from planarloc.io.kitti import kitti_frame_times

K = np.array([[718.856, 0, 607.1928], [0, 718.856, 185.2157], [0, 0, 1]])


def fmt_row(values) -> str:
    return " ".join(f"{v:.17g}" for v in np.ravel(values))


def write_sequence(
    root: Path, world_from_cam: list[Pose], write_image, *, image_dir="image_l", calib=None, n_images=None
) -> None:
    root.mkdir(parents=True, exist_ok=True)
    (root / "poses.txt").write_text("".join(fmt_row(p.matrix) + "\n" for p in world_from_cam))
    P0 = np.hstack([K, np.zeros((3, 1))])
    (root / "calib.txt").write_text(calib if calib is not None else fmt_row(P0) + "\n")
    for k in range(len(world_from_cam) if n_images is None else n_images):
        write_image(root / image_dir / f"{k:06d}.png", 12, 5)


def test_poses_camera_to_world_become_cam_from_world(tmp_path, write_image, random_poses, pose_close):
    world_from_cam = random_poses(4, seed=1)
    write_sequence(tmp_path, world_from_cam, write_image)
    frames = read_kitti(tmp_path)
    assert [f.index for f in frames] == [0, 1, 2, 3]
    assert [f.name for f in frames] == [f"image_l/{k:06d}.png" for k in range(4)]
    for f, wc in zip(frames, world_from_cam):
        pose_close(f.cam_from_world, wc.inverse())
        np.testing.assert_allclose(f.cam_from_world.center, wc.t, atol=1e-9)  # poses.txt column 4 = centre
        assert f.path == (tmp_path / f.name).absolute() and f.timestamp is None
    cam = frames[0].camera
    assert cam.model.value == "PINHOLE" and (cam.width, cam.height) == (12, 5)
    assert cam.params == (718.856, 718.856, 607.1928, 185.2157)


def test_labelled_calib_times_and_image_0(tmp_path, write_image, random_poses):
    P0 = np.hstack([K, np.zeros((3, 1))])
    calib = f"P0: {fmt_row(P0)}\nP1: {fmt_row(P0)}\n"
    write_sequence(tmp_path, random_poses(3), write_image, image_dir="image_0", calib=calib)
    (tmp_path / "times.txt").write_text("0.0\n0.1\n0.2\n")
    frames = read_kitti(tmp_path)
    assert frames[0].name == "image_0/000000.png"
    assert [f.timestamp for f in frames] == [0.0, 0.1, 0.2]


def test_image_2_uses_P2_with_its_baseline(tmp_path, write_image, random_poses, pose_close):
    world_from_cam0 = random_poses(2, seed=3)
    K2 = K + np.array([[0, 0, 2.0], [0, 0, 1.0], [0, 0, 0]])
    offset = np.array([0.06, -0.001, 0.003])  # cam2_from_cam0 translation
    P2 = np.hstack([K2, (K2 @ offset)[:, None]])
    P0 = np.hstack([K, np.zeros((3, 1))])
    calib = f"P0: {fmt_row(P0)}\nP2: {fmt_row(P2)}\nTr: {fmt_row(np.eye(3, 4))}\n"
    write_sequence(tmp_path, world_from_cam0, write_image, image_dir="image_2", calib=calib)
    frames = read_kitti(tmp_path)
    assert frames[0].camera.principal_point == (K2[0, 2], K2[1, 2])
    for f, wc in zip(frames, world_from_cam0):
        pose_close(f.cam_from_world, Pose(np.eye(3), offset) @ wc.inverse())
    # an explicit key wins
    assert read_kitti(tmp_path, calib_key="P0")[0].camera.principal_point == (K[0, 2], K[1, 2])


def test_extra_images_are_skipped_with_warning(tmp_path, write_image, random_poses, caplog):
    write_sequence(tmp_path, random_poses(2), write_image, n_images=4)
    with caplog.at_level(logging.WARNING, logger="planarloc.io.kitti"):
        frames = read_kitti(tmp_path)
    assert len(frames) == 2
    assert "2 image(s)" in caplog.text


def _poses_lines(world_from_cam: list[Pose]) -> list[str]:
    return [fmt_row(p.matrix) for p in world_from_cam]


@pytest.mark.parametrize(
    "edit, pattern",
    [
        (
            lambda ls: ls.__setitem__(2, " ".join(ls[2].split()[:11])),
            r"poses\.txt:3: expected 12 numbers .* found 11",
        ),
        (
            lambda ls: ls.__setitem__(1, ls[1].replace(ls[1].split()[4], "abc", 1)),
            r"poses\.txt:2: .*column 5.*'abc'",
        ),
        (lambda ls: ls.__setitem__(1, ls[1].replace(ls[1].split()[0], "nan", 1)), r"poses\.txt:2: .*finite"),
        (
            lambda ls: ls.__setitem__(0, fmt_row(np.hstack([2 * np.eye(3), np.zeros((3, 1))]))),
            r"poses\.txt:1: .*rotation",
        ),
        (
            lambda ls: ls.__setitem__(0, fmt_row(np.hstack([np.diag([1, 1, -1]), np.zeros((3, 1))]))),
            r"poses\.txt:1: .*det = -1",
        ),
    ],
)
def test_malformed_poses(tmp_path, write_image, random_poses, edit, pattern):
    world_from_cam = random_poses(3)
    write_sequence(tmp_path, world_from_cam, write_image)
    lines = _poses_lines(world_from_cam)
    edit(lines)
    (tmp_path / "poses.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(FormatError, match=pattern) as info:
        read_kitti(tmp_path)
    assert info.value.path == tmp_path / "poses.txt"


def test_malformed_calib_and_missing_files(tmp_path, write_image, random_poses):
    write_sequence(tmp_path, random_poses(2), write_image, calib="P0: 1 2 3\n")
    with pytest.raises(FormatError, match=r"calib\.txt:1: expected 12 numbers .*found 3"):
        read_kitti(tmp_path)
    skew = np.hstack([K, np.zeros((3, 1))])
    skew[1, 0] = 3.0
    (tmp_path / "calib.txt").write_text(fmt_row(skew) + "\n")
    with pytest.raises(FormatError, match=r"calib\.txt:1: expected a rectified projection matrix"):
        read_kitti(tmp_path)
    (tmp_path / "calib.txt").unlink()
    with pytest.raises(
        FormatError, match=r"calib\.txt: file not found; the KITTI odometry format needs calib\.txt"
    ):
        read_kitti(tmp_path)


def test_missing_image_and_missing_poses(tmp_path, write_image, random_poses):
    write_sequence(tmp_path, random_poses(3), write_image)
    (tmp_path / "image_l" / "000002.png").unlink()
    with pytest.raises(FormatError, match=r"poses\.txt:3: expected an image for frame 2 .*000002\.png"):
        read_kitti(tmp_path)
    assert len(read_kitti(tmp_path, check_images=False)) == 3
    (tmp_path / "poses.txt").unlink()
    with pytest.raises(FormatError, match=r"poses\.txt: file not found.*camera-to-world"):
        read_kitti(tmp_path)


def test_missing_image_directory(tmp_path):
    tmp_path.joinpath("poses.txt").write_text("")
    with pytest.raises(FormatError, match="image_l, image_0, image_2"):
        read_kitti(tmp_path)


def test_image_files_get_the_times_of_their_sequence(tmp_path, write_image, random_poses):
    """Images given as files (``localize``) get times.txt's stamps, as read_kitti gives them."""
    write_sequence(tmp_path, random_poses(3), write_image, image_dir="image_0")
    files = [tmp_path / "image_0" / f"{k:06d}.png" for k in (2, 0)]
    assert kitti_frame_times(files) is None  # no times.txt: nothing invented
    (tmp_path / "times.txt").write_text("# seconds\n1317384506.40\n1317384506.50\n1317384506.61\n")
    assert kitti_frame_times(files) == [1317384506.61, 1317384506.40]
    assert kitti_frame_times(files) == [read_kitti(tmp_path)[k].timestamp for k in (2, 0)]
    # one file that is no frame with a time: none gets one (no mix of seconds and frame numbers)
    other = write_image(tmp_path / "other" / "000001.png")
    assert kitti_frame_times([files[0], other]) is None
    assert (
        kitti_frame_times([files[0], write_image(tmp_path / "image_0" / "000003.png")]) is None
    )  # past times.txt
    assert kitti_frame_times([]) is None
    (tmp_path / "times.txt").write_text("0.0\nsoon\n")
    with pytest.raises(FormatError, match=r"times\.txt:2"):
        kitti_frame_times(files)
