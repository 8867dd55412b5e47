"""The CLI never loses, mixes up or misreports data: outputs, batches, validation, exit codes."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from _cli_runs import evaluate_argv, localize_argv, run

from planarloc.cli.main import build_parser
from planarloc.evaluation.queries import default_map_path
from planarloc.io.datasets import read_dataset
from planarloc.map.store import MapDatabase


def one_error_line(capsys: pytest.CaptureFixture[str], *expected: str) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    for text in expected:
        assert text in err[0], err[0]
    return err[0]


@pytest.fixture(scope="module")
def world_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("map") / "map.db"
    assert run(["map", "build", tiny_world / "map", "-f", "tum", "--out", db, "--vocabulary-size", "16"]) == 0
    return db


@pytest.fixture
def queries(tiny_world: Path) -> tuple[list[Path], str]:
    images = sorted((tiny_world / "query" / "rgb").glob("*.png"))[:2]
    return images, (tiny_world / "query" / "camera.txt").read_text().splitlines()[-1]


@pytest.mark.parametrize("argv", [["map", "info"], ["map", "check"]])
def test_map_subcommands_have_examples(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args([*argv, "--help"])
    assert "example" in capsys.readouterr().out


def test_exit_codes_documented(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    out = capsys.readouterr().out
    assert "exit codes" in out and "130" in out and "  3 " in out


# ---- outputs ------------------------------------------------------------------------------------
def test_localize_out_equal_to_map_is_refused(world_map: Path, queries, capsys) -> None:
    before = world_map.read_bytes()
    images, cam = queries
    assert run(["localize", "--map", world_map, *images, "--camera", cam, "--out", world_map]) == 1
    one_error_line(capsys, "--out", "is also an input")
    assert world_map.read_bytes() == before


def test_localize_out_equal_to_a_query_is_refused(world_map: Path, queries, tmp_path: Path, capsys) -> None:
    images, cam = queries
    copy = tmp_path / "q.png"
    shutil.copy(images[0], copy)
    assert run(["localize", "--map", world_map, copy, "--camera", cam, "--out", copy]) == 1
    one_error_line(capsys, "is also an input")
    assert copy.read_bytes() == images[0].read_bytes()


@pytest.mark.parametrize("case", ["out_is_dir", "json_dir_is_file", "parent_is_file"])
def test_bad_output_paths_one_line_before_work(
    world_map: Path, queries, tmp_path: Path, capsys, case: str
) -> None:
    images, cam = queries
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "a_dir").mkdir()
    extra = {
        "out_is_dir": ["--out", tmp_path / "a_dir"],
        "json_dir_is_file": ["--out", tmp_path / "p.txt", "--json-dir", tmp_path / "a_file"],
        "parent_is_file": ["--out", tmp_path / "a_file" / "p.txt"],
    }[case]
    assert run(["localize", "--map", world_map, *images, "--camera", cam, *extra]) == 1
    one_error_line(capsys, "planarloc localize: error:")
    assert (tmp_path / "a_file").read_text() == "x" and not (tmp_path / "p.txt").exists()


def test_os_errors_are_one_line(capsys) -> None:
    assert run(["map", "info", "/proc/self/nonexistent/map.db"]) == 1
    one_error_line(capsys, "planarloc map info: error:")


# ---- batches ------------------------------------------------------------------------------------
def test_bad_queries_are_recorded_and_the_batch_goes_on(
    world_map: Path, queries, tmp_path: Path, capsys
) -> None:
    images, cam = queries
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not an image")
    small = tmp_path / "small.png"
    import cv2

    cv2.imwrite(str(small), np.zeros((60, 80), np.uint8))
    out = tmp_path / "poses.txt"
    batch = (broken, images[0], small, images[1])
    rc = run(localize_argv(world_map, *batch, "--camera", cam, "--structure", "tracks", "--out", out))
    assert rc == 3
    lines = out.read_text().splitlines()
    assert sorted(line.split()[0] for line in lines) == sorted(p.name for p in images)
    records = {
        r["name"]: r for r in (json.loads(p.read_text()) for p in (tmp_path / "poses.txt.json.d").glob("*"))
    }
    assert (
        records["broken.png"]["status"] == "error" and "cannot read image" in records["broken.png"]["message"]
    )
    assert records["small.png"]["status"] == "error" and "80x60" in records["small.png"]["message"]
    captured = capsys.readouterr()
    assert "localized 2 of 4 queries (2 failed, 2 could not be processed)" in captured.out
    assert (
        "query broken.png not processed: " in captured.err
        and "query small.png not processed: " in captured.err
    )


def test_camera_of_another_size_is_not_silently_used(world_map: Path, queries, tmp_path: Path) -> None:
    images, _ = queries
    out = tmp_path / "poses.txt"
    camera = "PINHOLE 640 480 500 500 320 240"
    assert run(localize_argv(world_map, images[0], "--camera", camera, "--out", out)) == 3
    assert out.read_text() == ""
    record = json.loads(next((tmp_path / "poses.txt.json.d").glob("*")).read_text())
    assert not record["success"] and "640x480" in record["message"]


# ---- validation before work ---------------------------------------------------------------------
@pytest.mark.parametrize(
    "option",
    [["--vocabulary-size", "0"], ["--max-features", "0"], ["--every", "0"], ["--dataset-option", "nonsense"]],
)
def test_map_build_options_checked_before_any_file(tiny_world: Path, tmp_path: Path, capsys, option) -> None:
    db = tmp_path / "m.db"
    assert run(["map", "build", tiny_world / "map", "-f", "tum", "--out", db, *option]) == 1
    one_error_line(capsys, "planarloc map build: error:")
    assert not db.exists()


def test_localize_options_checked_before_the_map(tmp_path: Path, queries, capsys) -> None:
    images, _ = queries
    assert (
        run(
            ["localize", "--map", tmp_path / "missing.db", images[0], "--camera", "PINHOLE 640.5 480 1 1 1 1"]
        )
        == 1
    )
    one_error_line(capsys, "--camera", "whole")


def test_wrong_format_says_what_the_folder_is(tmp_path: Path, capsys) -> None:
    (tmp_path / "image_l").mkdir()
    (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    (tmp_path / "calib.txt").write_text("P0: 500 0 320 0 0 500 240 0 0 0 1 0\n")
    assert run(["map", "build", tmp_path, "-f", "tum", "--out", tmp_path / "m.db"]) == 1
    one_error_line(capsys, "not a tum folder", "--format kitti")


def test_map_build_out_equal_to_an_image_is_refused(tiny_world: Path, tmp_path: Path, capsys) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny_world / "map", data)
    image = sorted((data / "rgb").glob("*.png"))[0]
    before = image.read_bytes()
    assert run(["map", "build", data, "-f", "tum", "--out", image]) == 1
    one_error_line(capsys, "is also an input")
    assert image.read_bytes() == before


def test_evaluate_outputs_must_differ_from_inputs_and_each_other(
    tiny_world: Path, tmp_path: Path, capsys
) -> None:
    m = tmp_path / "e.db"
    assert (
        run(["evaluate", tiny_world / "map", "-f", "tum", "--map-every", "2", "--map", m, "--json", m]) == 1
    )
    one_error_line(capsys, "--json", "same path")
    gt = tiny_world / "map" / "groundtruth.txt"
    before = gt.read_bytes()
    assert (
        run(["evaluate", tiny_world / "map", "-f", "tum", "--map-every", "2", "--map", m, "--json", gt]) == 1
    )
    one_error_line(capsys, "is also an input")
    assert gt.read_bytes() == before and not m.exists()


# ---- identity -----------------------------------------------------------------------------------
def _shift_groundtruth(folder: Path, dx: float) -> None:
    gt = folder / "groundtruth.txt"
    lines = []
    for line in gt.read_text().splitlines():
        tok = line.split()
        if tok and not line.startswith("#"):
            tok[1] = repr(float(tok[1]) + dx)
        lines.append(" ".join(tok))
    gt.write_text("\n".join(lines) + "\n")


def test_fixed_poses_replace_stale_ones_in_map_and_evaluate_cache(
    tiny_world: Path, tmp_path: Path, capsys
) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny_world / "map", data)
    db = tmp_path / "m.db"
    assert run(["map", "build", data, "-f", "tum", "--out", db, "--vocabulary-size", "16"]) == 0
    old_key = default_map_path(data, 2, "rootsift", read_dataset(data, "tum")[::2])
    _shift_groundtruth(data, 5.0)
    capsys.readouterr()
    assert run(["map", "build", data, "-f", "tum", "--out", db, "--vocabulary-size", "16"]) == 0
    assert "have a new pose" in capsys.readouterr().err
    images = read_dataset(data, "tum")
    with MapDatabase.open(db) as m:
        for im in images:
            np.testing.assert_allclose(m.get_pose(im.name).t, im.cam_from_world.t, atol=1e-9)
    assert default_map_path(data, 2, "rootsift", images[::2]) != old_key


def test_damaged_map_fails_info_and_check_with_the_row_named(world_map: Path, tmp_path: Path, capsys) -> None:
    import sqlite3

    db = tmp_path / "d.db"
    shutil.copy(world_map, db)
    with sqlite3.connect(db) as conn:
        conn.execute("UPDATE keypoints SET data = substr(data, 1, 100) WHERE image_id = 3")
    capsys.readouterr()
    assert run(["map", "info", db]) == 1
    one_error_line(capsys, "damaged map", "images row 3")
    assert run(["map", "check", db]) == 1
    captured = capsys.readouterr()  # the problems are diagnostics (stderr), then one error line
    assert "images row 3" in captured.err and captured.out == ""
    assert captured.err.strip().splitlines()[-1].startswith("planarloc map check: error:")
    assert run(["map", "check", world_map]) == 0


def test_same_file_names_in_two_folders_do_not_mix_up(world_map: Path, queries, tmp_path: Path) -> None:
    images, cam = queries
    for sub, src in (("a", images[0]), ("b", images[1])):
        (tmp_path / sub).mkdir()
        shutil.copy(src, tmp_path / sub / "q.png")
    out = tmp_path / "poses.txt"
    same_names = (tmp_path / "a" / "q.png", tmp_path / "b" / "q.png")
    assert (
        run(localize_argv(world_map, *same_names, "--camera", cam, "--structure", "tracks", "--out", out))
        == 0
    )
    names = sorted(line.split()[0] for line in out.read_text().splitlines())
    assert names == ["a/q.png", "b/q.png"]
    assert len(list((tmp_path / "poses.txt.json.d").glob("*.json"))) == 2


def test_query_names_with_whitespace_refused_before_work(
    world_map: Path, queries, tmp_path: Path, capsys
) -> None:
    images, cam = queries
    odd = tmp_path / "my query.png"
    shutil.copy(images[0], odd)
    assert (
        run(["localize", "--map", world_map, images[1], odd, "--camera", cam, "--out", tmp_path / "p.txt"])
        == 1
    )
    one_error_line(capsys, "whitespace")
    assert not (tmp_path / "p.txt").exists()


def test_demo_out_that_is_a_file_is_refused_before_rendering(tmp_path: Path, capsys) -> None:
    (tmp_path / "f").write_text("keep")
    assert run(["demo", "--out", tmp_path / "f"]) == 1
    one_error_line(capsys, "is a file, not a folder")
    assert (tmp_path / "f").read_text() == "keep"


def test_evaluate_records_a_broken_query_and_goes_on(tiny_world: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    shutil.copytree(tiny_world / "map", data)
    broken = read_dataset(data, "tum")[1]  # odd index: a query at --map-every 2
    broken.path.write_bytes(b"truncated")
    summary = tmp_path / "e.json"
    options = ("--vocabulary-size", "16", "--structure", "tracks", "--json", summary)
    assert run(evaluate_argv(data, tmp_path, *options)) == 3
    s = json.loads(summary.read_text())
    errors = [q for q in s["per_query"] if q["status"] == "error"]
    assert s["queries"] == 6 and len(errors) == 1 and errors[0]["name"] == broken.name
    assert "cannot read image" in errors[0]["message"] and s["localized"] >= 4


def test_interrupted_batch_keeps_the_poses_so_far(
    world_map: Path, queries, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys
) -> None:
    from planarloc.localize.localizer import Localizer

    images, cam = queries
    real, calls = Localizer.localize_query, []

    def interrupt_second(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Localizer, "localize_query", interrupt_second)
    out = tmp_path / "poses.txt"
    assert (
        run(["localize", "--map", world_map, *images, "--camera", cam, "--structure", "tracks", "--out", out])
        == 130
    )
    assert [line.split()[0] for line in out.read_text().splitlines()] == [images[0].name]
    # The message tells the truth: what is in the results file, and that localize does not resume.
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("interrupted after 1 of 2 queries: their results are in ") and str(out) in last
    assert "localizes all 2 again" in last and "resume" not in last
