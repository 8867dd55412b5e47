"""The world's down direction each importer declares, and the ``up=`` option of read_dataset."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_colmap_text_reader import write_model
from test_kapture_reader import write_kapture
from test_kitti_reader import write_sequence
from test_openloris_reader import planar_base_poses, write_openloris
from test_tum_reader import write_tum

from planarloc.geometry.validation import InputError
from planarloc.io import read_dataset, write_pose_list
from planarloc.io.tum import GENERATED_WORLD_GENERATOR


def _down(frames) -> set:
    return {None if f.world_down is None else f.world_down.direction for f in frames}


def test_kitti_declares_y_down(tmp_path, write_image, random_poses):
    write_sequence(tmp_path, random_poses(3), write_image)
    frames = read_dataset(tmp_path, "kitti")
    assert _down(frames) == {(0.0, 1.0, 0.0)}
    assert frames[0].world_down.source == "declared" and "KITTI" in frames[0].world_down.detail


def test_openloris_declares_minus_z(tmp_path, write_image):
    write_openloris(tmp_path, planar_base_poses(2), write_image, depth_list=True)
    frames = read_dataset(tmp_path, "openloris")
    assert _down(frames) == {(0.0, 0.0, -1.0)}
    # the robot's camera is mounted level: its y-axis is the declared down direction
    for f in frames:
        np.testing.assert_allclose(f.cam_from_world.R @ [0, 0, -1], [0, 1, 0], atol=0.03)


def test_tum_undefined_unless_generated_world(tmp_path, write_image, random_poses):
    seq = tmp_path / "map"
    seq.mkdir()
    write_tum(seq, random_poses(2), write_image)
    (seq / "camera.txt").write_text("PINHOLE 640 480 500 500 320 240\n")
    assert _down(read_dataset(seq, "tum")) == {None}
    (tmp_path / "world.json").write_text(json.dumps({"generator": "someone else"}))
    assert _down(read_dataset(seq, "tum")) == {None}
    (tmp_path / "world.json").write_text("{not json")
    assert _down(read_dataset(seq, "tum")) == {None}
    (tmp_path / "world.json").write_text(json.dumps({"generator": GENERATED_WORLD_GENERATOR, "seed": 0}))
    assert _down(read_dataset(seq, "tum")) == {(0.0, 1.0, 0.0)}


def test_formats_without_up_axis(tmp_path, write_image, random_poses):
    poses = random_poses(3, seed=2)
    write_kapture(tmp_path / "k", [(k, "cam0", p) for k, p in enumerate(poses)], write_image)
    assert _down(read_dataset(tmp_path / "k", "kapture")) == {None}
    model = write_model(tmp_path / "c", poses, write_image)
    assert _down(read_dataset(model, "colmap")) == {None}
    write_pose_list(tmp_path / "l" / "poses.txt", [(f"{k}.png", p) for k, p in enumerate(poses)])
    for k in range(3):
        write_image(tmp_path / "l" / f"{k}.png")
    (tmp_path / "l" / "cameras.txt").write_text("PINHOLE 8 6 5 5 4 3\n")
    assert _down(read_dataset(tmp_path / "l", "list")) == {None}


@pytest.mark.parametrize(
    ("up", "down"),
    [
        ("z", (0, 0, -1)),
        ("+x", (-1, 0, 0)),
        ("-y", (0, 1, 0)),
        ("0,0,2", (0, 0, -1)),
        ("0 3 -4", (0, -0.6, 0.8)),
        ([1, 0, 0], (-1, 0, 0)),
    ],
)
def test_up_option_overrides_declared(tmp_path, write_image, random_poses, up, down):
    write_sequence(tmp_path, random_poses(2), write_image)
    frames = read_dataset(tmp_path, "kitti", up=up)
    (got,) = _down(frames)
    np.testing.assert_allclose(got, down, atol=1e-12)
    assert frames[0].world_down.source == "option"


@pytest.mark.parametrize("up", ["w", "--z", "1,2", "0,0,0", "a,b,c", "nan,0,1", 1, [0, 0]])
def test_bad_up_option_is_a_clear_error_before_reading(tmp_path, up):
    # the dataset does not even exist: the option is checked first
    with pytest.raises(InputError, match=r"up=.*expected an axis \(x, y, z with optional sign"):
        read_dataset(tmp_path / "missing", "kitti", up=up)


def test_up_estimate_drops_the_declaration(tmp_path, write_image, random_poses):
    write_sequence(tmp_path, random_poses(2), write_image)
    frames = read_dataset(tmp_path, "kitti", up="estimate")
    assert _down(frames) == {None} and frames[0].world_down.source == "option"
