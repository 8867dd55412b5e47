"""export.generate: the TUM RGB-D layout, round trip of poses and depth, reuse, errors."""

from __future__ import annotations

import dataclasses
import json
import re

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.synthetic.world import (
    CameraConfig,
    WorldConfig,
    build_sessions,
    generate,
    get_preset,
    is_complete,
    render_frame,
    shrunk,
)
from planarloc.synthetic.world.export import DEPTH_SCALE, MARKER, depth_to_png16, read_gravity

LINE = re.compile(r"^(\d+\.\d{6}) (rgb|depth)/(\d+\.\d{6})\.png$")


@pytest.fixture(scope="module")
def tiny_config() -> WorldConfig:
    return shrunk(get_preset("office"), n_map=5, n_query=4)


@pytest.fixture(scope="module")
def generated(tmp_path_factory, tiny_config):
    out = tmp_path_factory.mktemp("world")
    calls: list[tuple[int, int]] = []
    path = generate(tiny_config, out, seed=3, progress=lambda done, total: calls.append((done, total)))
    return path, calls


def _read_list(path):
    lines = path.read_text().splitlines()
    header = [ln for ln in lines if ln.startswith("#")]
    body = [ln for ln in lines if not ln.startswith("#")]
    assert lines[: len(header)] == header, "comment lines come first"
    assert all(ln.startswith("# ") for ln in header)
    return header, body


def test_layout(generated, tiny_config):
    out, calls = generated
    assert sorted(p.name for p in out.iterdir()) == sorted([MARKER, "world.json", "map", "query"])
    sizes = {"map": tiny_config.trajectory.n_map, "query": tiny_config.trajectory.n_query}
    for name, n in sizes.items():
        folder = out / name
        assert sorted(p.name for p in folder.iterdir()) == sorted(
            ["rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "camera.txt", "gravity.txt"]
        )
        for kind in ("rgb", "depth"):
            header, body = _read_list(folder / f"{kind}.txt")
            assert header[-1] == "# timestamp filename"
            assert len(body) == n
            for k, line in enumerate(body):
                m = LINE.match(line)
                assert m and m.group(2) == kind and m.group(1) == m.group(3), line
                assert float(m.group(1)) == pytest.approx(k * tiny_config.trajectory.frame_period)
                img = cv2.imread(str(folder / f"{kind}/{m.group(1)}.png"), cv2.IMREAD_UNCHANGED)
                cam = tiny_config.camera
                if kind == "rgb":
                    assert img.shape == (cam.height, cam.width, 3) and img.dtype == np.uint8
                else:
                    assert img.shape == (cam.height, cam.width) and img.dtype == np.uint16
            assert sorted(p.name for p in (folder / kind).iterdir()) == sorted(
                f"{LINE.match(b).group(1)}.png" for b in body
            )
        assert (folder / "rgb.txt").read_text().splitlines()[-n] == "0.000000 rgb/0.000000.png"
        cam_lines = (folder / "camera.txt").read_text().splitlines()
        assert len(cam_lines) == 2 and cam_lines[0].startswith("# ")
        fields = cam_lines[1].split()
        assert fields[0] == "PINHOLE" and fields[1:3] == [
            str(tiny_config.camera.width),
            str(tiny_config.camera.height),
        ]
        K = tiny_config.camera.intrinsics()
        assert [float(f) for f in fields[3:]] == [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    total = sum(sizes.values())
    assert calls == [(k, total) for k in range(1, total + 1)]
    doc = json.loads((out / "world.json").read_text())
    assert doc["preset"] == "office" and doc["seed"] == 3
    assert WorldConfig.from_dict(doc["config"]) == tiny_config


def test_groundtruth_is_camera_to_world_of_rendered_poses(generated, tiny_config):
    out, _ = generated
    sessions = build_sessions(tiny_config, seed=3)
    for session in sessions:
        header, body = _read_list(out / session.name / "groundtruth.txt")
        assert header[-1] == "# timestamp tx ty tz qx qy qz qw"
        data = np.array([[float(x) for x in line.split()] for line in body])
        assert data.shape == (len(session), 8)
        np.testing.assert_allclose(data[:, 0], session.timestamps, atol=1e-6)
        world_from_cam = Rotation.from_quat(data[:, 4:8]).as_matrix()  # x y z w
        np.testing.assert_allclose(world_from_cam, np.transpose(session.R, (0, 2, 1)), atol=1e-8)
        centers = -np.einsum("nji,nj->ni", session.R, session.t)
        np.testing.assert_allclose(data[:, 1:4], centers, atol=1e-8)
        np.testing.assert_allclose(
            data[:, 2], -tiny_config.trajectory.camera_height, atol=1e-8
        )  # y down: camera above floor


def test_gravity_file_is_world_down_in_each_camera(tmp_path):
    # A pitched, rolled and jittered session: the file must hold R (0, 1, 0) of the rendered poses.
    config = shrunk(get_preset("pitched"), n_map=3, n_query=3, scale=0.1)
    out = generate(config, tmp_path / "w", seed=1)
    for session in build_sessions(config, seed=1):
        header, body = _read_list(out / session.name / "gravity.txt")
        assert header[-1] == "# timestamp gx gy gz" and len(body) == len(session)
        gravity = read_gravity(out / session.name / "gravity.txt")
        assert list(gravity) == [f"{ts:.6f}" for ts in session.timestamps]
        g = np.array(list(gravity.values()))
        world_down = np.einsum("nji,nj->ni", session.R, g)  # back to the world frame: R^T g
        np.testing.assert_allclose(world_down, np.tile([0.0, 1.0, 0.0], (len(session), 1)), atol=1e-11)
    assert not np.allclose(g, [0.0, 1.0, 0.0], atol=0.1)  # the query camera is pitched ~14 degrees
    bad = tmp_path / "gravity.txt"
    bad.write_text("# timestamp gx gy gz\n0.000000 0 0 0\n")
    with pytest.raises(ValueError, match=r"gravity.txt:2"):
        read_gravity(bad)


def test_images_and_depth_match_renders(generated, tiny_config):
    out, _ = generated
    m, q = build_sessions(tiny_config, seed=3)
    for session in (m, q):
        for i in (0, len(session) - 1):
            image, depth = render_frame(session, i)
            name = f"{session.timestamps[i]:.6f}"
            rgb = cv2.cvtColor(cv2.imread(str(out / session.name / "rgb" / f"{name}.png")), cv2.COLOR_BGR2RGB)
            assert np.array_equal(rgb, image)
            stored = cv2.imread(str(out / session.name / "depth" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
            valid = stored > 0
            assert valid.mean() > 0.99
            np.testing.assert_allclose(
                stored[valid] / DEPTH_SCALE, depth[valid], atol=0.5 / DEPTH_SCALE + 1e-6
            )


def test_depth_png_encoding():
    depth = np.array([[0.0, np.inf, 1.0, 13.0, 14.0]], np.float32)
    assert depth_to_png16(depth).tolist() == [[0, 0, 5000, 65000, 0]]


def test_reuse_and_regeneration(tmp_path, tiny_config):
    small = dataclasses.replace(
        tiny_config, trajectory=dataclasses.replace(tiny_config.trajectory, n_map=2, n_query=2)
    )
    calls: list[tuple[int, int]] = []
    generate(small, tmp_path, seed=0, progress=lambda d, t: calls.append((d, t)))
    assert is_complete(tmp_path, small, 0) and len(calls) == 4
    first = (tmp_path / "map" / "rgb" / "0.000000.png").read_bytes()
    (tmp_path / "keep.txt").write_text("user file")
    generate(small, tmp_path, seed=0, progress=lambda d, t: calls.append((d, t)))
    assert len(calls) == 4, "a complete generation with the same config and seed is reused"
    generate(small, tmp_path, seed=1)
    assert is_complete(tmp_path, small, 1) and not is_complete(tmp_path, small, 0)
    assert (tmp_path / "map" / "rgb" / "0.000000.png").read_bytes() != first
    (tmp_path / MARKER).unlink()  # an interrupted generation is redone
    generate(small, tmp_path, seed=0)
    assert (tmp_path / "map" / "rgb" / "0.000000.png").read_bytes() == first
    assert (tmp_path / "keep.txt").read_text() == "user file"


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown world preset"):
        generate("nope", tmp_path)
    with pytest.raises(ValueError, match="seed"):
        generate("office", tmp_path, seed=-1)
    with pytest.raises(ValueError, match="camera size"):
        CameraConfig(width=0)
    with pytest.raises(ValueError, match="unknown"):
        WorldConfig.from_dict({"name": "x", "colour": 1})
    assert not any(tmp_path.iterdir())
