"""Tables printed to a file or a pipe (no terminal) come out whole (#32): every column header and
value in full, none cut with "…", whatever the table's width."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _cli_runs import evaluate_argv, run

from planarloc.cli.report import print_summary_table
from planarloc.cli.sequence_cli import print_sequence_table

SEQUENCE_HEADERS = (
    "run",
    "0.25m/10deg",
    "0.5m/10deg",
    "1m/20deg",
    "localized/predicted/lost",
    "confident wrong",
    "rejected",
    "first correct",
    "after kidnap",
    "frames/s",
    "latency p50/p99 [ms]",
    "late/dropped",
)


def sequence_summary() -> dict:
    return {
        "success": {"0.25m/10deg": 83.3, "0.5m/10deg": 91.7, "1m/20deg": 100.0},
        "status_counts": {"localized": 4123, "predicted": 1, "lost": 17},
        "relocalization": {"start": {"frames": 3}, "kidnaps": [None, {"frames": 12}]},
        "frames_per_second": 14.92,
        "latency_ms": {"p50": 78, "p99": 1096},
        "confident_wrong": 2,
        "rejected_fixes": 5,
        "late_frames": 1234,
        "dropped_frames": 56,
    }


def printed(capsys: pytest.CaptureFixture[str]) -> str:
    out = capsys.readouterr()
    return out.out + out.err  # `--out -` sends information to stderr


def lines_with(text: str, needle: str) -> list[str]:
    return [line for line in text.splitlines() if needle in line]


def test_sequence_table_is_whole_off_a_terminal(capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    print_sequence_table([("simulated odometry with a long label", sequence_summary())], "a title")
    text = printed(capsys)
    assert "…" not in text
    header = lines_with(text, "localized/predicted/lost")
    assert len(header) == 1  # one header line: no header is wrapped either
    for col in SEQUENCE_HEADERS:
        assert col in header[0], col
    row = lines_with(text, "simulated odometry with a long label")
    assert len(row) == 1
    for value in ("83.3%", "91.7%", "100.0%", "4123/1/17", "never, 12", "14.92", "78/1096", "1234/56"):
        assert value in row[0], value
    assert len(header[0]) > 120  # wider than the 120 columns tables used to be squeezed into


def test_summary_table_is_whole_off_a_terminal(capsys: pytest.CaptureFixture[str]) -> None:
    summary = {
        "method": "5p5p-stewenius",
        "structure": "tracks",
        "success": {"0.25m/10deg": 12.5, "0.5m/10deg": 50.0, "1m/20deg": 100.0},
        "median_translation_error_m": 0.123,
        "median_rotation_error_deg": 1.25,
        "failed_queries": 3,
        "queries": 1000,
        "status_counts": {"degenerate_scale": 7},
        "seconds_per_query": 0.42,
    }
    capsys.readouterr()
    print_summary_table([summary], "kitti_seq2, map every 2")
    text = printed(capsys)
    assert "…" not in text
    header = lines_with(text, "structure")
    assert len(header) == 1
    for col in (
        "method",
        "0.25m/10deg",
        "0.5m/10deg",
        "1m/20deg",
        "median t [m]",
        "median R [°]",
        "failed",
        "degenerate",
        "s/query",
    ):
        assert col in header[0], col
    row = lines_with(text, "5p5p-stewenius")
    assert len(row) == 1
    for value in ("tracks", "12.5%", "50.0%", "100.0%", "0.123", "1.25", "3/1000", "7", "0.42"):
        assert value in row[0], value


def test_evaluate_sequential_table_piped(
    tiny_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The command itself, its stdout captured (not a terminal): the whole table, as in its JSON."""
    capsys.readouterr()
    sequential = ("--structure", "tracks", "--sequential", "--json", tmp_path / "s.json")
    assert run(evaluate_argv(tiny_world / "query", tmp_path, *sequential)) == 0
    text = printed(capsys)
    assert "…" not in text
    header = lines_with(text, "localized/predicted/lost")
    assert len(header) == 1
    for col in SEQUENCE_HEADERS:
        assert col in header[0], col
    s = json.loads((tmp_path / "s.json").read_text())
    c = s["status_counts"]
    row = lines_with(text, s["motion"])
    assert len(row) == 1
    assert f"{c.get('localized', 0)}/{c.get('predicted', 0)}/{c.get('lost', 0)}" in row[0]
    assert all(f"{v:.1f}%" in row[0] for v in s["success"].values())
