"""`planarloc localize --sequence` and `planarloc evaluate --sequential` on the tiny world."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from planarloc.cli.main import main


def run(argv: list) -> int:
    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def world_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("seqmap") / "map.db"
    assert run(["map", "build", tiny_world / "map", "--format", "tum", "--out", db]) == 0
    return db


def test_localize_a_stream_with_odometry(tiny_world: Path, world_map: Path, tmp_path: Path) -> None:
    out = tmp_path / "poses.txt"
    q = tiny_world / "query"
    # rgb.txt is an image list 'timestamp path'; the ground truth is a perfect odometry file (TUM layout)
    assert run(["localize", "--map", world_map, "--sequence", q / "rgb.txt", "--odometry", q / "groundtruth.txt",
                "--structure", "tracks", "--out", out]) == 0
    records = [json.loads(p.read_text()) for p in sorted((tmp_path / "poses.txt.json.d").glob("*.json"))]
    assert len(records) == 6
    assert all(r["status"] in ("localized", "predicted", "lost") for r in records)
    assert sum(r["status"] == "localized" for r in records) >= 5
    assert [r["motion_source"] for r in sorted(records, key=lambda r: r["stamp"])][1:] == ["odometry"] * 5
    assert all(len(r["covariance"]) == 6 for r in records if "covariance" in r)
    assert len(out.read_text().splitlines()) >= 5


def test_evaluate_sequential_counts_every_frame(tiny_world: Path, tmp_path: Path) -> None:
    summary = tmp_path / "seq.json"
    assert run(["evaluate", tiny_world / "query", "--format", "tum", "--map-every", "2", "--map", tmp_path / "e.db",
                "--structure", "tracks", "--sequential", "--simulate-odometry", "--json", summary]) == 0
    s = json.loads(summary.read_text())
    assert s["frames"] == 3 == len(s["per_frame"]) and s["motion"] == "simulated odometry"
    assert set(s["success"]) == {"0.25m/10deg", "0.5m/10deg", "1m/20deg"}
    for key in ("confident_wrong", "relocalization", "frames_per_second", "status_counts"):
        assert key in s


@pytest.mark.parametrize("argv, message", [
    (["localize", "--map", "m.db", "x.png", "--odometry", "o.txt"], "--odometry: only used with --sequence"),
    (["evaluate", "d", "-f", "tum", "--map-every", "2", "--kidnap-at", "3"], "--kidnap-at: only used with --sequential"),
    (["evaluate", "d", "-f", "tum", "--map-every", "2", "--sequential", "--plot", "p.png"], "--plot"),
])
def test_misused_options_are_one_line_errors(argv: list, message: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(argv) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
