"""The map's gravity warning is printed once per run, and its advice does what it says (#32).

The sequence: the tiny world's map frames as a KITTI sequence whose world frame is tilted 6°, so
KITTI's declared down (+y of the world) is 6° off while the cameras are level and the robot turns:
relative to the declared gravity their tilt varies with the heading (the KITTI warning).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
from _cli_runs import kitti_evaluate_argv, run
from kitti_layout import write_kitti_sequence
from scipy.spatial.transform import Rotation

from planarloc.geometry.pose import Pose
from planarloc.gravity.world import gravity_from_map_poses
from planarloc.io.datasets import read_dataset
from planarloc.io.kitti import WORLD_DOWN
from planarloc.map.gravity import map_gravity
from planarloc.map.store import MapDatabase

WARNING = "the cameras' tilt relative to gravity is inconsistent"
ADVICE = "--dataset-option up=estimate"
#: tilted_from_world: the KITTI world of the sequence is the generated world turned 6° about x
TILT = Rotation.from_rotvec(np.radians([6.0, 0.0, 0.0])).as_matrix()


@pytest.fixture(scope="module")
def tilted_kitti(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("tilted") / "seq"
    frames = read_dataset(tiny_world / "map", "tum")
    write_kitti_sequence(frames, root, world_from_kitti=Pose(TILT, np.zeros(3)).inverse())
    return root


def shown(capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture) -> str:
    """Everything a run showed: stdout, stderr and the log records at WARNING or above."""
    out = capsys.readouterr()
    logged = "\n".join(r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING)
    caplog.clear()
    return "\n".join([out.out, out.err, logged])


def test_evaluate_prints_it_once_per_run_and_the_advice_works(
    tilted_kitti: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    db = tmp_path / "map.db"
    evaluate = kitti_evaluate_argv(tilted_kitti, db)
    capsys.readouterr()
    assert run(evaluate) == 0  # builds the map
    text = shown(capsys, caplog)
    assert text.count(WARNING) == 1 and text.count(ADVICE) == 1
    assert run(evaluate) == 0  # the same map again: the warning concerns this run's queries too, once
    assert shown(capsys, caplog).count(WARNING) == 1
    with MapDatabase.open(db) as m:
        before = map_gravity(m)
    assert before.source == "declared" and max(before.pitch_spread_deg, before.roll_spread_deg) > 2.0

    # following the advice, on the same map file: the gravity is estimated, the tilt consistent, no warning
    assert run([*evaluate, "--dataset-option", "up=estimate"]) == 0
    assert WARNING not in shown(capsys, caplog)
    with MapDatabase.open(db) as m:
        after = map_gravity(m)
    assert after.source == "estimated" and max(after.pitch_spread_deg, after.roll_spread_deg) < 2.0
    true_down = TILT @ [0.0, 1.0, 0.0]
    assert math.degrees(math.acos(min(1.0, float(np.dot(after.g_world, true_down))))) < 0.5
    assert after.warnings == ()


def test_map_build_prints_it_once(
    tilted_kitti: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], caplog: pytest.LogCaptureFixture
) -> None:
    capsys.readouterr()
    assert run(["map", "build", tilted_kitti, "-f", "kitti", "--every", "2", "--out", tmp_path / "m.db"]) == 0
    text = shown(capsys, caplog)
    assert text.count(WARNING) == 1 and text.count(ADVICE) == 1  # in the map's summary, not also logged


def test_the_advice_is_given_only_where_it_helps(tilted_kitti: Path) -> None:
    """up=estimate is advised when the estimated gravity makes the tilt consistent; a shaky mount
    (each camera tilted its own way) keeps the warning without that advice."""
    poses = [im.cam_from_world for im in read_dataset(tilted_kitti, "kitti")]
    warnings = gravity_from_map_poses(poses, WORLD_DOWN)[1].warnings
    assert len(warnings) == 1 and WARNING in warnings[0] and ADVICE in warnings[0]
    rng = np.random.default_rng(0)
    shaky = [
        Pose(Rotation.from_rotvec(np.radians(rng.normal(0, 4, 3) * [1, 0, 1])).as_matrix() @ p.R, p.t)
        for p in poses
    ]
    warnings = gravity_from_map_poses(shaky, WORLD_DOWN)[1].warnings
    assert len(warnings) == 1 and WARNING in warnings[0] and "up=estimate" not in warnings[0]
