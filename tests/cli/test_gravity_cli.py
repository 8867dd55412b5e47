"""Gravity on the command line: `map info`, `--dataset-option up=`, `localize --gravity/--gravity-file`."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _cli_runs import evaluate_argv, localize_argv, run
from map_files import map_build_argv


@pytest.fixture(scope="module")
def cli_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("cli_gravity") / "map.db"
    assert run(map_build_argv(tiny_world / "map", db, "--every", "2", "--dataset-option", "up=-y")) == 0
    return db


def test_map_info_reports_gravity(cli_map: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    assert run(["map", "info", cli_map]) == 0
    out = capsys.readouterr().out  # information goes to stdout
    assert "gravity (down, world frame): (+0.0000, +1.0000, +0.0000)  source: option" in out
    assert "up=-y" in out and "mount tilt of the 6 map cameras: pitch" in out


def test_bad_up_option_is_one_line(
    tiny_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert run(map_build_argv(tiny_world / "map", tmp_path / "m.db", "--dataset-option", "up=sideways")) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "up='sideways': expected an axis" in err[0]
    assert not (tmp_path / "m.db").exists()


def test_localize_with_gravity(
    cli_map: Path, tiny_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    queries = sorted((tiny_world / "query" / "rgb").glob("*.png"))[:2]
    out = tmp_path / "poses.txt"
    assert run(["localize", "--map", cli_map, *queries, "--gravity", "0, 2, 0", "--out", out]) == 0
    records = [json.loads(p.read_text()) for p in sorted((tmp_path / "poses.txt.json.d").glob("*.json"))]
    assert [r["query_gravity"] for r in records] == [[0.0, 1.0, 0.0]] * 2

    gfile = tmp_path / "gravity.txt"
    gfile.write_text(f"# name gx gy gz\n{queries[0].name} 0 1 0.05\nunknown.png 0 1 0\n")
    out2 = tmp_path / "p2.txt"
    capsys.readouterr()
    assert run(["localize", "--map", cli_map, *queries, "--gravity-file", gfile, "--out", out2]) == 0
    console = capsys.readouterr().err
    assert "no gravity for 1 of 2 queries" in console and "1 name(s) match no query" in console
    by_name = {
        r["name"]: r for r in map(lambda p: json.loads(p.read_text()), (tmp_path / "p2.txt.json.d").iterdir())
    }
    assert by_name[queries[1].name]["query_gravity"] is None
    assert by_name[queries[0].name]["query_gravity"][2] == pytest.approx(0.05 / (1 + 0.05**2) ** 0.5)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--gravity", "0 1"], "--gravity: expected three numbers"),
        (["--gravity", "0 0 0"], "--gravity: expected a non-zero gravity direction"),
        (["--gravity-file", "BAD"], "gravity.txt:2: expected 4 fields 'name gx gy gz', found 3"),
        (["--gravity-file", "ZERO"], "gravity.txt:1: expected a non-zero gravity direction"),
    ],
)
def test_bad_gravity_is_one_line(
    cli_map: Path,
    tiny_world: Path,
    tmp_path: Path,
    args: list,
    message: str,
    capsys: pytest.CaptureFixture[str],
) -> None:
    gfile = tmp_path / "gravity.txt"
    gfile.write_text("a.png 0 1 0\nb.png 0 1\n" if "BAD" in args else "a.png 0 0 0\n")
    args = [gfile if a in ("BAD", "ZERO") else a for a in args]
    query = sorted((tiny_world / "query" / "rgb").glob("*.png"))[0]
    assert run(["localize", "--map", cli_map, query, *args, "--out", tmp_path / "p.txt"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]


def test_gravity_and_gravity_file_are_exclusive(cli_map: Path, tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as exc:
        run(localize_argv(cli_map, "x.png", "--gravity", "0 1 0", "--gravity-file", tmp_path / "g.txt"))
    assert exc.value.code == 2


def test_evaluate_with_true_gravity(tiny_world: Path, tmp_path: Path) -> None:
    summary = tmp_path / "eval.json"
    options = ("--gravity-from-truth", "--structure", "tracks", "--json", summary)
    assert run(evaluate_argv(tiny_world / "map", tmp_path, *options)) == 0
    s = json.loads(summary.read_text())
    assert s["query_gravity"] == "truth" and s["queries"] == 6 and s["success"]["0.25m/10deg"] >= 80.0
