"""`planarloc localize --sequence` and `planarloc evaluate --sequential` on the tiny world: the
outputs (TUM, plot, Rerun, speed and latency), bad frames, bad image lists, misused options."""

from __future__ import annotations

import importlib.util
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from _cli_runs import evaluate_argv, localize_argv, run

from planarloc.geometry.pose import Pose


@pytest.fixture(scope="module")
def world_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("seqmap") / "map.db"
    assert run(["map", "build", tiny_world / "map", "--format", "tum", "--out", db]) == 0
    return db


def test_localize_a_stream_with_odometry(tiny_world: Path, world_map: Path, tmp_path: Path) -> None:
    out = tmp_path / "poses.txt"
    q = tiny_world / "query"
    # rgb.txt is an image list 'timestamp path'; the ground truth is a perfect odometry file (TUM layout)
    stream = ("--sequence", q / "rgb.txt", "--odometry", q / "groundtruth.txt")
    assert run(localize_argv(world_map, *stream, "--structure", "tracks", "--out", out)) == 0
    records = [json.loads(p.read_text()) for p in sorted((tmp_path / "poses.txt.json.d").glob("*.json"))]
    assert len(records) == 6
    assert all(r["status"] in ("localized", "predicted", "lost") for r in records)
    assert sum(r["success"] for r in records) >= 5 and sum(r["status"] == "localized" for r in records) >= 1
    assert [r["motion_source"] for r in sorted(records, key=lambda r: r["stamp"])][1:] == ["odometry"] * 5
    assert all(np.array(r["covariance_xyz_rotvec"]).shape == (6, 6) for r in records if r["success"])
    assert len(out.read_text().splitlines()) >= 5


def test_evaluate_sequential_counts_every_frame(tiny_world: Path, tmp_path: Path) -> None:
    summary = tmp_path / "seq.json"
    sequential = ("--structure", "tracks", "--sequential", "--simulate-odometry", "--json", summary)
    assert run(evaluate_argv(tiny_world / "query", tmp_path, *sequential)) == 0
    s = json.loads(summary.read_text())
    assert s["frames"] == 3 == len(s["per_frame"]) and s["motion"] == "simulated odometry"
    assert set(s["success"]) == {"0.25m/10deg", "0.5m/10deg", "1m/20deg"}
    for key in ("confident_wrong", "relocalization", "frames_per_second", "status_counts"):
        assert key in s


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["localize", "--map", "m.db", "x.png", "--odometry", "o.txt"],
            "--odometry: only used with --sequence",
        ),
        (
            ["evaluate", "d", "-f", "tum", "--map-every", "2", "--kidnap-at", "3"],
            "--kidnap-at: only used with --sequential",
        ),
        (
            ["evaluate", "d", "-f", "tum", "--map-every", "2", "--rate", "10"],
            "--rate: only used with --sequential",
        ),
        (
            ["evaluate", "d", "-f", "tum", "--map-every", "2", "--sequential", "--fix-delay", "2"],
            "--fix-delay: only used with --fixes wait",
        ),
        (["localize", "--map", "m.db", "x.png", "--fixes", "wait"], "--fixes: only used with --sequence"),
        (
            ["evaluate", "d", "-f", "tum", "--map-every", "2", "--sequential", "--rate", "0"],
            "--rate: expected a frame rate",
        ),
    ],
)
def test_misused_options_are_one_line_errors(
    argv: list, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def _frames(tiny_world: Path) -> tuple[list[Path], list[float]]:
    query = tiny_world / "query"
    frames = sorted((query / "rgb").glob("*.png"))
    stamps = [
        float(line.split()[0]) for line in (query / "rgb.txt").read_text().splitlines() if line[0] != "#"
    ]
    return frames, stamps


def test_localize_a_stream_with_tum_and_rerun(tiny_world: Path, world_map: Path, tmp_path: Path) -> None:
    out, tum, rrd = tmp_path / "poses.txt", tmp_path / "stream.tum", tmp_path / "stream.rrd"
    rerun = ["--rerun", rrd] if importlib.util.find_spec("rerun") else []
    query = tiny_world / "query"  # its frames are 1-5 m apart: too far to track, odometry gives the motion
    stream = ("--sequence", query / "rgb.txt", "--odometry", query / "groundtruth.txt", "--fixes", "wait")
    assert run(localize_argv(world_map, *stream, "--out", out, "--tum", tum, *rerun)) == 0
    records = [json.loads(p.read_text()) for p in sorted((tmp_path / "poses.txt.json.d").glob("*.json"))]
    usable = sorted((r for r in records if r["success"]), key=lambda r: r["stamp"])
    rows = [line.split() for line in tum.read_text().splitlines() if not line.startswith("#")]
    assert len(rows) == len(usable) >= 4
    for row, r in zip(rows, usable):  # TUM: stamp, camera-to-world
        assert float(row[0]) == pytest.approx(r["stamp"])
        c = -np.array(Pose.from_quat_wxyz(r["quat_wxyz"], r["t"]).R).T @ np.array(r["t"])
        np.testing.assert_allclose([float(v) for v in row[1:4]], c, atol=1e-5)
        assert np.array(r["covariance_xyz_rotvec"]).shape == (6, 6)
    if rerun:
        data = rrd.read_bytes()
        assert b"world/stream/estimate" in data and b"world/map/centers" in data


def test_evaluate_sequential_reports_speed_and_writes_tum_plot_rerun(
    tiny_world: Path, tmp_path: Path
) -> None:
    summary, plot, rrd = tmp_path / "seq.json", tmp_path / "traj.png", tmp_path / "seq.rrd"
    rerun = ["--rerun", rrd] if importlib.util.find_spec("rerun") else []
    outputs = ("--json", summary, "--tum", tmp_path / "tum", "--plot", plot, *rerun)
    assert (
        run(evaluate_argv(tiny_world / "map", tmp_path, "--sequential", "--simulate-odometry", *outputs)) == 0
    )
    s = json.loads(summary.read_text())
    assert s["fixes"] == "background" and s["frames"] == 6 and s["frames_with_pose"] >= 4
    assert s["frames_per_second"] > 0 and set(s["latency_ms"]) == {"p50", "p99", "max"}
    assert s["first_frame_latency_ms"] > 0 and s["dropped_frames"] == 0 and "late_frames" in s
    assert s["stream"]["frames"] == 6 and s["stream"]["fixes_submitted"] >= 1
    assert (tmp_path / "tum" / "estimate.txt").is_file() and (tmp_path / "tum" / "groundtruth.txt").is_file()
    img = cv2.imread(str(plot))
    assert img is not None and img.std() > 5
    if rerun:
        assert b"world/stream/trajectory" in rrd.read_bytes()


def test_a_stream_records_bad_frames_and_goes_on(tiny_world: Path, world_map: Path, tmp_path: Path) -> None:
    """A truncated PNG and a frame of another size (with --camera): status error with the reason,
    exit code 3, the other frames localized and written."""
    frames, stamps = _frames(tiny_world)
    truncated, small = tmp_path / "cut.png", tmp_path / "small.png"
    data = frames[2].read_bytes()
    truncated.write_bytes(data[: len(data) // 2])
    cv2.imwrite(str(small), cv2.resize(cv2.imread(str(frames[3])), (160, 120)))
    entries = [
        *zip(stamps[:3], frames[:3]),
        ((stamps[2] + stamps[3]) / 2, truncated),
        (stamps[3], frames[3]),
        ((stamps[3] + stamps[4]) / 2, small),
        *zip(stamps[4:], frames[4:]),
    ]
    listing = tmp_path / "frames.txt"
    listing.write_text("".join(f"{t:.6f} {p}\n" for t, p in entries))
    camera = (tiny_world / "query" / "camera.txt").read_text().splitlines()[-1]
    out = tmp_path / "poses.txt"
    odometry = ("--odometry", tiny_world / "query" / "groundtruth.txt")
    argv = localize_argv(world_map, "--sequence", listing, "--camera", camera, "--fixes", "wait", *odometry)
    assert run([*argv, "--out", out]) == 3
    records = {
        r["name"]: r for r in (json.loads(p.read_text()) for p in (tmp_path / "poses.txt.json.d").iterdir())
    }
    assert records["cut.png"]["status"] == "error" and "cannot read image" in records["cut.png"]["message"]
    assert records["small.png"]["status"] == "error" and "160x120" in records["small.png"]["message"]
    others = [records[p.name] for p in frames]
    assert all(r["status"] in ("localized", "predicted", "lost") for r in others)
    assert sum(r["success"] for r in others) >= 4
    assert {line.split()[0] for line in out.read_text().splitlines()} == {
        r["name"] for r in others if r["success"]
    }


@pytest.mark.parametrize(
    "bad, message", [("backwards", "is not after line 2's"), ("twice", "is already listed on line 1")]
)
def test_an_image_list_out_of_order_is_a_one_line_error(
    tiny_world: Path,
    world_map: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    bad: str,
    message: str,
) -> None:
    frames, stamps = _frames(tiny_world)
    entries = [
        (stamps[0], frames[0]),
        (stamps[1], frames[1]),
        (stamps[0] - 1.0, frames[2]) if bad == "backwards" else (stamps[2], frames[0]),
    ]
    listing = tmp_path / "frames.txt"
    listing.write_text("".join(f"{t:.6f} {p}\n" for t, p in entries))
    out = tmp_path / "poses.txt"
    out.write_text("old results\n")
    assert run(localize_argv(world_map, "--sequence", listing, "--out", out)) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "frames.txt:3:" in err[0] and message in err[0]
    assert out.read_text() == "old results\n"  # nothing was touched
    # the same frame twice on the command line
    assert run(localize_argv(world_map, "--sequence", frames[0], frames[0], "--out", out)) == 1
    assert "given twice" in capsys.readouterr().err


def test_evaluate_sequential_records_a_bad_frame(tiny_world: Path, tmp_path: Path) -> None:
    data = tmp_path / "query"
    shutil.copytree(tiny_world / "query", data)
    frames = sorted((data / "rgb").glob("*.png"))
    raw = frames[3].read_bytes()
    frames[3].write_bytes(raw[: len(raw) // 3])  # a query frame (index 3), truncated
    summary = tmp_path / "seq.json"
    assert run(evaluate_argv(data, tmp_path, "--sequential", "--fixes", "wait", "--json", summary)) == 3
    s = json.loads(summary.read_text())
    bad = [f for f in s["per_frame"] if f["status"] == "error"]
    assert len(bad) == 1 and "cannot read image" in bad[0]["message"] and s["frames"] == 3
    assert s["status_counts"]["error"] == 1
