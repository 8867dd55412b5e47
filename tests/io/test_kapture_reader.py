"""kapture reader: sensors, world-to-device trajectories, rigs, records, errors."""

from __future__ import annotations

import logging

import pytest

from planarloc.io import FormatError, read_kapture

HEADER = "# kapture format: 1.1\n"


def write_kapture(root, poses, write_image, *, sensors=None, records=None, rigs=None):
    s = root / "sensors"
    s.mkdir(parents=True, exist_ok=True)
    (s / "sensors.txt").write_text(
        HEADER
        + "# sensor_id, name, sensor_type, [sensor_params]+\n"
        + (
            sensors
            or "cam0, front, camera, PINHOLE, 64, 48, 50, 51, 32, 24\n"
            "cam1, , camera, SIMPLE_PINHOLE, 64, 48, 40, 32, 24\n"
            "lidar0, , lidar\n"
        )
    )
    lines = []
    for ts, dev, p in poses:
        lines.append(f"{ts}, {dev}, " + ", ".join(f"{v:.15g}" for v in (*p.quat_wxyz, *p.t)))
    (s / "trajectories.txt").write_text(
        HEADER + "# timestamp, device_id, qw, qx, qy, qz, tx, ty, tz\n" + "\n".join(lines) + "\n"
    )
    if rigs is not None:
        (s / "rigs.txt").write_text(HEADER + rigs)
    recs = records if records is not None else [(ts, dev, f"{dev}/{ts:04d}.png") for ts, dev, _ in poses]
    for _, _, path in recs:
        write_image(s / "records_data" / path)
    (s / "records_camera.txt").write_text(
        HEADER
        + "# timestamp, device_id, image_path\n"
        + "\n".join(f"{t}, {d}, {p}" for t, d, p in recs)
        + "\n"
    )


def test_read_kapture(tmp_path, write_image, random_poses, pose_close, caplog):
    p = random_poses(3, seed=4)
    poses = [(0, "cam0", p[0]), (1, "cam0", p[1]), (1, "cam1", p[2])]
    records = [
        (0, "cam0", "cam0/0000.png"),
        (1, "cam0", "cam0/0001.png"),
        (1, "cam1", "cam1/0001.png"),
        (2, "cam0", "cam0/0002.png"),
    ]  # the last one has no pose (e.g. a query)
    write_kapture(tmp_path, poses, write_image, records=records)
    with caplog.at_level(logging.WARNING, logger="planarloc.io.kapture"):
        frames = read_kapture(tmp_path)
    assert "1 camera record(s) have no pose" in caplog.text
    assert [f.name for f in frames] == ["cam0/0000.png", "cam0/0001.png", "cam1/0001.png"]
    assert [f.index for f in frames] == [0, 1, 2]
    for f, (_, _, pose) in zip(frames, poses):
        pose_close(f.cam_from_world, pose)  # kapture stores world-to-device = cam_from_world
    assert frames[0].camera.params == (50.0, 51.0, 32.0, 24.0)
    assert frames[2].camera.model.value == "SIMPLE_PINHOLE"
    assert frames[2].path == (tmp_path / "sensors/records_data/cam1/0001.png").absolute()


def test_rig(tmp_path, write_image, random_poses, pose_close):
    rig_from_world, cam_from_rig = random_poses(2, seed=9)
    rigs = (
        "# rig_id, sensor_id, qw, qx, qy, qz, tx, ty, tz\nrig, cam0, "
        + ", ".join(f"{v:.15g}" for v in (*cam_from_rig.quat_wxyz, *cam_from_rig.t))
        + "\n"
    )
    write_kapture(
        tmp_path, [(5, "rig", rig_from_world)], write_image, rigs=rigs, records=[(5, "cam0", "a.png")]
    )
    (frame,) = read_kapture(tmp_path)
    pose_close(frame.cam_from_world, cam_from_rig @ rig_from_world)


@pytest.mark.parametrize(
    "sensors, pattern",
    [
        (
            "cam0, , camera, FOV, 64, 48, 50, 51, 32, 24, 0.1\n",
            r"sensors\.txt:3: camera model FOV is not supported",
        ),
        (
            "cam0, , camera, PINHOLE, 64, 48, 50, 51, 32\n",
            r"sensors\.txt:3: Camera.params: PINHOLE takes 4 parameters, got 3",
        ),
        (
            "cam0, , camera, PINHOLE, 64, x, 50, 51, 32, 24\n",
            r"sensors\.txt:3: expected a number in column 6",
        ),
    ],
)
def test_bad_sensors(tmp_path, write_image, random_poses, sensors, pattern):
    write_kapture(tmp_path, [(0, "cam0", random_poses(1)[0])], write_image, sensors=sensors)
    with pytest.raises(FormatError, match=pattern):
        read_kapture(tmp_path)


def test_bad_trajectories_and_records(tmp_path, write_image, random_poses):
    write_kapture(tmp_path, [(0, "cam0", random_poses(1)[0])], write_image)
    traj = tmp_path / "sensors" / "trajectories.txt"
    traj.write_text(HEADER + "0, cam0, 1, 0, 0, 0, 1, 2\n")
    with pytest.raises(FormatError, match=r"trajectories\.txt:2: expected 9 fields .* found 8"):
        read_kapture(tmp_path)
    traj.write_text(HEADER + "0, cam0, 0.5, 0, 0, 0, 1, 2, 3\n")
    with pytest.raises(FormatError, match=r"trajectories\.txt:2: expected a unit quaternion"):
        read_kapture(tmp_path)
    traj.write_text(HEADER + "0, cam0, 1, 0, 0, 0, 1, 2, 3\n")
    rec = tmp_path / "sensors" / "records_camera.txt"
    rec.write_text(HEADER + "0, cam7, x.png\n")
    with pytest.raises(FormatError, match=r"records_camera\.txt:2: expected a camera sensor id .* 'cam7'"):
        read_kapture(tmp_path)
    rec.write_text(HEADER + "0, cam0, missing.png\n")
    with pytest.raises(
        FormatError, match=r"records_camera\.txt:2: listed image 'missing\.png' does not exist"
    ):
        read_kapture(tmp_path)
    (tmp_path / "sensors" / "sensors.txt").unlink()
    with pytest.raises(FormatError, match=r"sensors\.txt: file not found; the kapture format needs"):
        read_kapture(tmp_path)
