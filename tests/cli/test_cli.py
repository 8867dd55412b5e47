"""Smoke tests of the `planarloc` command line on a tiny generated world."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from _cli_runs import evaluate_argv, run
from map_files import map_build_argv

from planarloc.cli.main import build_parser
from planarloc.map.std_calibration import MIN_SAMPLES, load_std_calibration
from planarloc.map.store import MapDatabase


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["map"],
        ["map", "build"],
        ["map", "info"],
        ["localize"],
        ["evaluate"],
        ["demo"],
        ["warmup"],
        ["cache"],
        ["cache", "list"],
        ["cache", "clean"],
    ],
)
def test_help_teaches(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        build_parser().parse_args([*argv, "--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert "usage: planarloc" in out
    # Every help page, the top-level one included, shows a command to copy.
    assert "example" in out and "planarloc " + " ".join(argv) in out


def test_map_build_storage_compact_is_a_smaller_map_that_localizes(tiny_world: Path, tmp_path: Path) -> None:
    from planarloc.map.store import MapDatabase

    sizes = {}
    for storage in ("full", "compact"):
        db = tmp_path / f"{storage}.db"
        assert run(map_build_argv(tiny_world / "map", db, "--storage", storage)) == 0
        with MapDatabase.open(db) as m:
            assert m.storage == storage
        sizes[storage] = db.stat().st_size
    assert sizes["compact"] < 0.6 * sizes["full"]
    query = sorted((tiny_world / "query" / "rgb").glob("*.png"))[0]
    cam = (tiny_world / "query" / "camera.txt").read_text().splitlines()[-1]
    out = tmp_path / "p.txt"
    assert run(["localize", "--map", tmp_path / "compact.db", query, "--camera", cam, "--out", out]) == 0
    assert len(out.read_text().splitlines()) == 1
    with pytest.raises(SystemExit):
        run(map_build_argv(tiny_world / "map", tmp_path / "x.db", "--storage", "tiny"))


def test_map_build_localize_evaluate(
    tiny_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db = tmp_path / "map.db"
    assert run(["map", "build", tiny_world / "map", "--format", "tum", "--out", db]) == 0
    capsys.readouterr()
    assert run(["map", "info", db]) == 0
    printed = capsys.readouterr().out
    assert "map poses agree with their images to" in printed  # the measured map prior
    with MapDatabase.open(db) as m:  # `map build` measured the std calibration on held-out map images
        calibration = load_std_calibration(m)
    assert calibration is not None and calibration.samples >= MIN_SAMPLES, printed
    assert f"std calibration: {calibration.summary()}" in printed
    out = tmp_path / "poses.txt"
    queries = sorted((tiny_world / "query" / "rgb").glob("*.png"))[:3]
    cam = (tiny_world / "query" / "camera.txt").read_text().splitlines()[-1]
    assert (
        run(["localize", "--map", db, *queries, "--camera", cam, "--structure", "tracks", "--out", out]) == 0
    )
    lines = out.read_text().splitlines()
    assert len(lines) == 3 and all(len(line.split()) == 8 for line in lines)
    records = [json.loads(p.read_text()) for p in sorted((tmp_path / "poses.txt.json.d").glob("*.json"))]
    assert len(records) == 3 and all(r["success"] and r["num_inliers"] > 0 for r in records)
    # the rendered world's poses are exact: the measured prior is far below the 0.1° / 2 cm default
    assert all(
        r["map_prior"]["rotation_std_deg"] < 0.05 and r["map_prior"]["position_std_m"] < 0.01 for r in records
    ), [r["map_prior"] for r in records]
    summary = tmp_path / "eval.json"
    plot = tmp_path / "eval.png"
    assert (
        run(
            evaluate_argv(
                tiny_world / "map", tmp_path, "--structure", "tracks", "--json", summary, "--plot", plot
            )
        )
        == 0
    )
    s = json.loads(summary.read_text())
    assert s["queries"] == 6 and s["method"] == "auto" and s["structure"] == "tracks"
    assert set(s["success"]) == {"0.25m/10deg", "0.5m/10deg", "1m/20deg"}
    assert s["success"]["0.25m/10deg"] >= 80.0 and plot.stat().st_size > 1000
    for key in (
        "median_translation_error_m",
        "median_rotation_error_deg",
        "failed_queries",
        "seconds_per_query",
    ):
        assert key in s


def test_known_errors_print_one_line_and_exit_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run(["map", "build", tmp_path / "missing", "--format", "kitti", "--out", tmp_path / "m.db"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("planarloc map build: error:")
    (tmp_path / "not_a_map.db").write_text("hello")
    assert run(["map", "info", tmp_path / "not_a_map.db"]) == 1
    assert "not a planarloc map" in capsys.readouterr().err


def test_help_pages_say_what_the_code_does(capsys: pytest.CaptureFixture[str]) -> None:
    from planarloc.synthetic.world.presets import preset_names

    def page(*argv: str) -> str:
        with pytest.raises(SystemExit):
            build_parser().parse_args([*argv, "--help"])
        return capsys.readouterr().out

    assert "%%" not in page("evaluate") and "index % N == 0" in page("evaluate")
    demo = page("demo")
    assert all(f"\n  {name} " in demo for name in preset_names())  # every preset, described
    serve = page("serve")
    assert "optionally camera" in serve and "--port 0" in serve and "422" not in serve
    assert "'-' for stdout" in page("localize")


def test_map_build_interrupted_says_it_resumes(
    tiny_world: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from planarloc.cli import map_building

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(map_building, "build_map", interrupted)  # the build `map build` runs
    assert run(["map", "build", tiny_world / "map", "-f", "tum", "--out", tmp_path / "m.db"]) == 130
    assert (
        capsys.readouterr()
        .err.strip()
        .splitlines()[-1]
        .startswith("interrupted; re-run the same command to resume the build")
    )


def test_map_info_says_when_the_std_calibration_is_still_due(
    tiny_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from planarloc.io.datasets import read_dataset
    from planarloc.map.builder import build_map

    db = build_map(
        read_dataset(tiny_world / "map", "tum"), tmp_path / "lib.db", num_words=16
    )  # no calibration
    capsys.readouterr()
    assert run(["map", "info", db]) == 0
    assert "std calibration: not measured yet" in capsys.readouterr().out
    assert run(["map", "build", tiny_world / "map", "-f", "tum", "--out", db, "--vocabulary-size", "16"]) == 0
    assert (
        "std calibration: position std x" in capsys.readouterr().out
    )  # the same images: measured, unchanged map
