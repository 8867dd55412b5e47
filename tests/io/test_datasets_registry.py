"""The format registry: names, dispatch and option errors."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.validation import InputError
from planarloc.io import FORMATS, FormatError, read_dataset
from planarloc.io.datasets import format_options


def test_formats_registered():
    assert set(FORMATS) == {"kitti", "tum", "openloris", "kapture", "colmap", "list", "rosbag"}
    assert {"image_topic", "pose_topic", "tf_parent", "tf_child", "base_to_camera", "every"} <= set(
        format_options("rosbag")
    )
    assert "max_dt" in format_options("tum") and "image_dir" in format_options("colmap")


def test_unknown_format_lists_known():
    with pytest.raises(InputError, match="unknown dataset format 'euroc'; known formats: kitti, tum"):
        read_dataset("/nowhere", "euroc")


def test_dispatch_and_unknown_option(tmp_path, write_image):
    write_image(tmp_path / "image_l" / "000000.png", 10, 4)
    (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    (tmp_path / "calib.txt").write_text("P0: 7 0 5 0 0 7 2 0 0 0 1 0\n")
    frames = read_dataset(tmp_path, "KITTI")
    assert len(frames) == 1 and np.allclose(frames[0].camera.K, [[7, 0, 5], [0, 7, 2], [0, 0, 1]])
    with pytest.raises(InputError, match="unknown option.*max_dt.*accepted: image_dir"):
        read_dataset(tmp_path, "kitti", max_dt=0.1)
    with pytest.raises(FormatError):
        read_dataset(tmp_path / "empty", "tum", tum_camera="fr1")
    assert issubclass(FormatError, InputError) and issubclass(FormatError, ValueError)
