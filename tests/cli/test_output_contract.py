"""One output contract (issue 32): every JSON file `localize`, `localize --sequence`, `evaluate` and
`evaluate --sequential` write parses as strict JSON and validates against the published schema
(docs/schema/*.schema.json), failures and unprocessable images included; the sequential summary's
late count is the stream's own."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from _cli_runs import evaluate_argv, run
from record_schemas import check, check_file

from planarloc.geometry.pose import Pose


@pytest.fixture(scope="module")
def world_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("contract") / "map.db"
    assert run(["map", "build", tiny_world / "map", "--format", "tum", "--out", db]) == 0
    return db


def _query_list(tiny_world: Path, folder: Path) -> Path:
    """The query list with one unreadable image and one black frame added (TUM 'stamp path')."""
    q = tiny_world / "query"
    lines = [ln.split() for ln in (q / "rgb.txt").read_text().splitlines() if ln and not ln.startswith("#")]
    (folder / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    first = Path(q / lines[0][1])
    import cv2

    size = cv2.imread(str(first)).shape
    cv2.imwrite(str(folder / "black.png"), np.zeros(size, np.uint8))
    rows = [f"{float(s):.6f} {q / p}" for s, p in lines]
    last = float(lines[-1][0])
    rows += [f"{last + 0.1:.6f} {folder / 'black.png'}", f"{last + 0.2:.6f} {folder / 'broken.png'}"]
    path = folder / "queries.txt"
    path.write_text("\n".join(rows) + "\n")
    return path


def _records(folder: Path) -> list[dict]:
    return [check_file("record", p) for p in sorted(folder.glob("*.json"))]  # type: ignore[misc]


def test_localize_records_follow_the_schema(tiny_world: Path, world_map: Path, tmp_path: Path) -> None:
    _query_list(tiny_world, tmp_path)
    images = [
        *sorted((tiny_world / "query" / "rgb").glob("*.png")),
        tmp_path / "black.png",
        tmp_path / "broken.png",
    ]
    out = tmp_path / "poses.txt"
    assert run(["localize", "--map", world_map, *images, "--structure", "tracks", "--out", out]) == 3
    records = {r["name"].rsplit("/", 1)[-1]: r for r in _records(tmp_path / "poses.txt.json.d")}
    assert len(records) == 8 and all(r["kind"] == "fix" for r in records.values())
    ok = [r for r in records.values() if r["success"]]
    assert len(ok) >= 4
    for r in ok:  # the centre is the pose's, the stamp the list's, the covariance named
        pose = Pose.from_quat_wxyz(r["quat_wxyz"], r["t"])
        np.testing.assert_allclose(r["center"], pose.center, atol=1e-9)
        assert r["covariance_frame"] == "world_from_camera"
        assert np.sqrt(
            np.linalg.eigvalsh(np.array(r["covariance_xyz_rotvec"])[:3, :3]).max()
        ) == pytest.approx(r["position_std_m"], rel=1e-3)
        assert r["time_s"]["total"] > 0
    broken, black = records["broken.png"], records["black.png"]
    assert broken["status"] == "error" and "broken.png" in broken["message"] and broken["quat_wxyz"] is None
    assert not black["success"] and black["status"] != "error" and black["center"] is None
    assert black["message"]


def test_stream_records_follow_the_schema(tiny_world: Path, world_map: Path, tmp_path: Path) -> None:
    queries = _query_list(tiny_world, tmp_path)
    out = tmp_path / "stream.txt"
    assert (
        run(["localize", "--map", world_map, "--sequence", queries, "--structure", "tracks", "--out", out])
        == 3
    )
    records = _records(tmp_path / "stream.txt.json.d")
    assert len(records) == 8 and all(r["kind"] == "frame" for r in records)
    assert all(r["stamp"] is not None for r in records)  # the list's times
    assert {r["status"] for r in records} >= {"localized", "error"}
    assert any(r["fix"] is not None and r["fix"]["kind"] == "fix" for r in records)
    assert all(set(r["time_s"]) == {"total", "latency", "cpu"} for r in records if r["status"] != "error")


def test_evaluate_outputs_follow_the_schema(tiny_world: Path, tmp_path: Path) -> None:
    data = tmp_path / "map"
    shutil.copytree(tiny_world / "map", data)
    first = sorted((data / "rgb").glob("*.png"))[1]
    first.write_bytes(first.read_bytes()[:100])  # one query that cannot be read
    summary = tmp_path / "eval.json"
    assert run(evaluate_argv(data, tmp_path, "--structure", "tracks", "--json", summary)) == 3
    s = check_file("evaluation", summary)
    assert s["queries"] == len(s["per_query"]) == 6  # type: ignore[index]
    statuses = [q["status"] for q in s["per_query"]]  # type: ignore[index]
    assert "error" in statuses and statuses.count("success") >= 1
    for q in s["per_query"]:  # type: ignore[index]
        assert (q["translation_error_m"] is None) == (not q["success"])
        if q["success"]:
            assert q["translation_error_m"] == pytest.approx(
                np.linalg.norm(np.subtract(q["center"], q["truth_center"]))
            )


def test_sequential_evaluation_follows_the_schema(tiny_world: Path, tmp_path: Path) -> None:
    summary = tmp_path / "seq.json"
    sequential = ("--structure", "tracks", "--sequential", "--json", summary)
    assert run(evaluate_argv(tiny_world / "query", tmp_path, *sequential)) == 0
    s = check_file("sequence-evaluation", summary)
    assert s["late_frames"] == s["stream"]["late"]  # type: ignore[index]
    assert sum(f["late"] for f in s["per_frame"]) == s["late_frames"]  # type: ignore[index]


def test_the_checker_rejects_what_breaks_the_contract(
    tiny_world: Path, world_map: Path, tmp_path: Path
) -> None:
    """The schema is not vacuous: NaN, a missing field, an unknown field, a success without a pose fail."""
    out = tmp_path / "one.txt"
    q = sorted((tiny_world / "query" / "rgb").glob("*.png"))[0]
    assert run(["localize", "--map", world_map, q, "--structure", "tracks", "--out", out]) == 0
    (record,) = _records(tmp_path / "one.txt.json.d")
    assert record["success"]
    with pytest.raises(ValueError, match="NaN"):
        check("record", json.dumps({**record, "position_std_m": float("nan")}))
    broken: list[dict] = [
        {k: v for k, v in record.items() if k != "message"},
        {**record, "reason": "x"},
        {**record, "quat_wxyz": None},
        {**record, "status": "lost"},
        {**record, "schema": "planarloc.record/0"},
    ]
    for bad in broken:
        with pytest.raises(AssertionError, match="schema error"):
            check("record", bad)
