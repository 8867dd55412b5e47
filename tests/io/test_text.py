"""One parser per text format, shared by every reader and front door (planarloc.io.text)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from planarloc.cli.options import camera_option, gravity_option
from planarloc.geometry.camera import NUM_PARAMS, Camera, CameraModel
from planarloc.geometry.pose import Pose
from planarloc.io import FormatError
from planarloc.io.camera_file import read_camera_file
from planarloc.io.rosbag import parse_camera_option, parse_transform
from planarloc.io.text import (
    T_XYZW,
    WXYZ_T,
    TextError,
    camera_text,
    parse_camera,
    parse_gravity,
    parse_pose,
    pose_text,
)
from planarloc.serve.requests import RequestError, parse_camera_field, parse_gravity_field


def _a_camera(model: CameraModel) -> Camera | None:
    """A camera of ``model`` that Camera accepts (None if these simple parameters do not fit it)."""
    n = NUM_PARAMS[model]
    for params in (
        [300.0] * n,
        [300.0] * min(n, 4) + [0.0] * max(n - 4, 0),
        [300.0] * min(n, 3) + [0.0] * (n - 3),
    ):
        try:
            return Camera(model, 640, 480, tuple(params))
        except ValueError:
            continue
    return None


@pytest.mark.parametrize("model", list(CameraModel))
def test_every_model_camera_takes_is_taken_by_every_reader_and_front_door(
    model: CameraModel, tmp_path: Path
) -> None:
    camera = _a_camera(model)
    if camera is None:
        pytest.skip(f"no simple parameters fit {model.value}")
    text = camera_text(camera)
    (tmp_path / "cameras.txt").write_text(f"# a camera file\n1 {text}\n")
    parsed = [
        parse_camera(text),
        parse_camera(text.lower().replace(" ", ", ")),
        camera_option(text),
        parse_camera_field(text),
        parse_camera_option(text),
        read_camera_file(tmp_path / "cameras.txt")["1"],
    ]
    assert all(p == camera for p in parsed)


def test_camera_errors_come_from_camera_and_name_their_place(tmp_path: Path) -> None:
    supported = ", ".join(m.value for m in CameraModel)
    with pytest.raises(TextError, match=f"camera model FOV is not supported \\(supported: {supported}\\)"):
        parse_camera("FOV 64 48 50 51 32 24 0.1")
    with pytest.raises(
        TextError, match=f"expected a camera model name \\({supported}\\) in column 1, found 'FOO'"
    ):
        parse_camera("FOO 1 2 3")
    with pytest.raises(TextError, match="Camera.params: PINHOLE takes 4 parameters, got 3"):
        parse_camera("PINHOLE 64 48 1 2 3")
    with pytest.raises(TextError, match="whole pixel counts"):
        parse_camera("PINHOLE 64.5 48 1 2 3 4")
    big = "PINHOLE " + "9" * 400 + " 48 1 2 3 4"  # a 400-digit width is a bad number, not an overflow
    with pytest.raises(TextError, match="expected a finite number in column 2 .*'9{37}...'$"):
        parse_camera(big)
    with pytest.raises(RequestError) as exc:
        parse_camera_field(big)
    assert exc.value.status == 400 and len(exc.value.message) < 400
    with pytest.raises(ValueError, match="^--camera: expected a number in column 5"):
        camera_option("PINHOLE 64 48 1 x 3 4")
    (tmp_path / "camera.txt").write_text("PINHOLE 64 48 1 x 3 4\n")
    with pytest.raises(FormatError, match=r"camera.txt:1: expected a number in column 5"):
        read_camera_file(tmp_path / "camera.txt")
    (tmp_path / "cameras.txt").write_text(
        "7 PINHOLE 64 48 1 x 3 4\n"
    )  # keyed: the columns count from the key
    with pytest.raises(FormatError, match=r"cameras.txt:1: expected a number in column 6"):
        read_camera_file(tmp_path / "cameras.txt")


def test_gravity_is_normalised_the_same_everywhere() -> None:
    for g in (
        parse_gravity("0 2 0"),
        parse_gravity("0, 2, 0"),
        gravity_option("0 2 0"),
        np.array(parse_gravity_field("0 2 0")),
    ):
        np.testing.assert_array_equal(g, [0.0, 1.0, 0.0])
    for bad in ("0 1", "0 0 0", "0 1 nan", "a b c"):
        with pytest.raises(TextError):
            parse_gravity(bad)
        with pytest.raises(RequestError):
            parse_gravity_field(bad)


def test_pose_lines_round_trip_in_both_layouts() -> None:
    rng = np.random.default_rng(0)
    q = rng.normal(size=4)
    pose = Pose.from_quat_wxyz(q / np.linalg.norm(q), rng.normal(size=3))
    for layout in (WXYZ_T, T_XYZW):
        back = parse_pose(pose_text(pose, layout), layout)
        np.testing.assert_allclose(back.matrix, pose.matrix, atol=1e-15)
    x, y, z, w = 0.2, 0.0, 0.9, -0.5  # base_to_camera is 'x y z qx qy qz qw', the TUM layout
    np.testing.assert_allclose(parse_transform("0.2 0 0.9 -0.5 0.5 -0.5 0.5", "base_to_camera").t, [x, y, z])
    assert w < 0
    with pytest.raises(TextError, match="expected a unit quaternion"):
        parse_pose("1 2 3 0 0 0 2", T_XYZW)
    with pytest.raises(TextError, match="expected 7 numbers 'qw qx qy qz tx ty tz', found 6"):
        parse_pose("1 0 0 0 1 2", WXYZ_T)
