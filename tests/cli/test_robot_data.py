"""End to end on a generated world: cross-session evaluation with queries from a ROS 2 bag equals
the all-TUM run (within 1 mm); bags into `map build` and `localize`; TUM files for evo; match
plots; Rerun."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("rosbags")

from _cli_runs import localize_argv, run  # noqa: E402

from planarloc.geometry.pose import Pose  # noqa: E402
from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.io.rosbag import write_rosbag  # noqa: E402

BASE_FROM_CAMERA = Pose.from_quat_wxyz([0.5, -0.5, 0.5, -0.5], [0.2, 0.0, 0.9])


@pytest.fixture(scope="module")
def query_bag(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The query session as a ROS 2 bag: sensor_msgs/Image, /tf map -> base_link,
    /tf_static base -> camera."""
    out = tmp_path_factory.mktemp("bags") / "query"
    return write_rosbag(
        out,
        read_dataset(tiny_world / "query", "tum"),
        storage="sqlite3",
        pose_message="tf",
        base_from_camera=BASE_FROM_CAMERA,
    )


def test_cross_session_with_bag_queries_equals_all_tum(
    tiny_world: Path, query_bag: Path, tmp_path: Path
) -> None:
    db = tmp_path / "map.db"
    rrd = tmp_path / "run.rrd"
    rerun = ["--rerun", rrd] if importlib.util.find_spec("rerun") else []
    common = [tiny_world / "map", "--format", "tum", "--map", db, "--structure", "tracks"]
    assert (
        run(
            [
                "evaluate",
                *common,
                "--queries",
                tiny_world / "query",
                "--json",
                tmp_path / "tum.json",
                "--tum",
                tmp_path / "tum",
            ]
        )
        == 0
    )
    assert (
        run(
            [
                "evaluate",
                *common,
                "--queries",
                query_bag,
                "--queries-format",
                "rosbag",
                "--queries-option",
                "tf_parent=map",
                "--queries-option",
                "tf_child=base_link",
                "--queries-option",
                f"image_dir={tmp_path / 'bag-images'}",
                "--json",
                tmp_path / "bag.json",
                "--tum",
                tmp_path / "bag",
                "--plot-matches",
                tmp_path / "matches",
                "--plot",
                tmp_path / "traj.png",
                *rerun,
            ]
        )
        == 0
    )
    tum, bag = (json.loads((tmp_path / f"{k}.json").read_text()) for k in ("tum", "bag"))
    assert tum["queries"] == bag["queries"] == 6
    assert tum["success"] == bag["success"] and tum["success"]["0.25m/10deg"] >= 80.0
    assert bag["queries_format"] == "rosbag" and bag["map_datasets"] == [str(tiny_world / "map")]
    map_names = {im.name for im in read_dataset(tiny_world / "map", "tum")}
    for a, b in zip(tum["per_query"], bag["per_query"]):
        assert a["status"] == b["status"]
        assert b["name"].startswith("camera_image_raw/")
        np.testing.assert_allclose(a["truth_center"], b["truth_center"], atol=1e-6)
        if a["success"]:
            assert abs(a["translation_error_m"] - b["translation_error_m"]) < 1e-3
            np.testing.assert_allclose(a["center"], b["center"], atol=1e-3)
            assert b["references"] and set(b["references"]) <= map_names
    # TUM files: evo reads them, and its APE in the JSON is the per-query error of planarloc
    file_interface = pytest.importorskip("evo.tools.file_interface")
    est = file_interface.read_tum_trajectory_file(str(tmp_path / "bag" / "estimate.txt"))
    gt = file_interface.read_tum_trajectory_file(str(tmp_path / "bag" / "groundtruth.txt"))
    localized = [q for q in bag["per_query"] if q["success"]]
    assert est.num_poses == gt.num_poses == len(localized)
    np.testing.assert_allclose(gt.positions_xyz, [q["truth_center"] for q in localized], atol=1e-6)
    np.testing.assert_allclose(est.positions_xyz, [q["center"] for q in localized], atol=1e-6)
    errors = np.linalg.norm(est.positions_xyz - gt.positions_xyz, axis=1)
    assert bag["evo"]["ape_translation_m"]["max"] == pytest.approx(errors.max(), abs=1e-6)
    assert bag["evo"]["ape_translation_m"]["max"] == pytest.approx(
        max(q["translation_error_m"] for q in localized), abs=1e-6
    )
    if rerun:
        data = rrd.read_bytes()
        assert len(data) > 10_000 and b"world/query/estimate" in data and b"world/map/centers" in data
    plots = sorted((tmp_path / "matches").glob("*.png"))
    assert len(plots) == 6
    img = cv2.imread(str(plots[0]))
    assert img is not None and img.shape[0] > 300 and img.std() > 10


@pytest.mark.parametrize("storage", ["rosbag1", "sqlite3"])
def test_a_dataset_and_the_same_dataset_as_a_bag_give_the_same_results(
    tiny_world: Path, tmp_path: Path, storage: str
) -> None:
    """The whole dataset (map and queries) read from its TUM folder and from a bag written of it:
    same map images, same estimates, same statuses, same success rates."""
    dataset = read_dataset(tiny_world / "map", "tum")
    bag = write_rosbag(tmp_path / ("data.bag" if storage == "rosbag1" else "data"), dataset, storage=storage)
    common = [
        "--map-every",
        "2",
        "--structure",
        "tracks",
        "--vocabulary-size",
        "16",
        "--seed",
        "3",
        "--dataset-option",
        "up=-y",
    ]  # the generated world's gravity, declared by its folder only
    assert (
        run(
            [
                "evaluate",
                tiny_world / "map",
                "-f",
                "tum",
                *common,
                "--map",
                tmp_path / "tum.db",
                "--json",
                tmp_path / "tum.json",
            ]
        )
        == 0
    )
    assert (
        run(
            [
                "evaluate",
                bag,
                "-f",
                "rosbag",
                "--dataset-option",
                "pose_topic=/pose",
                "--dataset-option",
                f"image_dir={tmp_path / 'images'}",
                *common,
                "--map",
                tmp_path / "bag.db",
                "--json",
                tmp_path / "bag.json",
            ]
        )
        == 0
    )
    tum, from_bag = (json.loads((tmp_path / f"{k}.json").read_text()) for k in ("tum", "bag"))
    assert tum["queries"] == from_bag["queries"] == 6 and tum["success"] == from_bag["success"]
    assert tum["status_counts"] == from_bag["status_counts"] and tum["localized"] >= 5
    for a, b in zip(tum["per_query"], from_bag["per_query"]):
        assert a["status"] == b["status"] and a["num_inliers"] == b["num_inliers"]
        assert b["name"] == f"camera_image_raw/{a['stamp']:.9f}.png"  # the bag names frames by stamp
        if a["success"]:
            np.testing.assert_allclose(a["center"], b["center"], atol=1e-6)


def test_bags_into_map_build_and_localize(
    tiny_world: Path, query_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    map_bag = write_rosbag(
        tmp_path / "map.bag",
        read_dataset(tiny_world / "map", "tum"),
        storage="rosbag1",
        compressed=True,
        pose_message="Odometry",
        base_from_camera=BASE_FROM_CAMERA,
    )
    db = tmp_path / "map.db"
    assert (
        run(
            [
                "map",
                "build",
                map_bag,
                "--format",
                "rosbag",
                "--dataset-option",
                "pose_topic=/pose",
                "--dataset-option",
                f"image_dir={tmp_path / 'map-images'}",
                "--out",
                db,
            ]
        )
        == 0
    )
    assert "12 images" in capsys.readouterr().err.replace("\n", " ")
    # queries from the bag without poses (images + CameraInfo only), TUM trajectory out
    out = tmp_path / "poses.txt"
    queries = localize_argv(db, query_bag, "--format", "rosbag")
    outputs = ("--structure", "tracks", "--out", out, "--tum", tmp_path / "est.tum")
    assert run([*queries, "--dataset-option", f"image_dir={tmp_path / 'q-images'}", *outputs]) == 0
    lines = [ln.split() for ln in (tmp_path / "est.tum").read_text().splitlines() if not ln.startswith("#")]
    truth = read_dataset(tiny_world / "query", "tum")
    by_time = {round(q.timestamp, 6): q for q in truth}
    assert len(lines) >= 5
    for ln in lines:
        q = by_time[round(float(ln[0]), 6)]
        assert np.linalg.norm(np.array(ln[1:4], float) - q.cam_from_world.center) < 0.25
    capsys.readouterr()
    assert run([*queries, "--dataset-option", "image_topic=/x", "--out", tmp_path / "p2.txt"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "image_topic='/x': no such topic" in err[0]


def test_protocol_errors_are_one_line(
    tiny_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    one, two = [tiny_world / "map"], [tiny_world / "map", tiny_world / "query"]
    for data, extra, message in (
        (one, [], "give either --map-every"),
        (one, ["--map-every", "2", "--queries", two[1]], "give either --map-every"),
        (two, ["--map-every", "2"], "splits one dataset, got 2"),
    ):
        assert run(["evaluate", *data, "--format", "tum", "--map", tmp_path / "m.db", *extra]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0]
    assert not (tmp_path / "m.db").exists()
