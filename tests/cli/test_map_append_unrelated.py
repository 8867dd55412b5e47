"""`planarloc map build` onto a map of another world (issue #32): one error line naming what was found and
the option, exit code 1, the map file as it was; with --allow-unrelated-frames the images are appended
after a warning."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from planarloc.cli.exit_codes import EXIT_ERROR, EXIT_OK
from planarloc.cli.main import main
from planarloc.map.store import MapDatabase


def run(argv: list[object]) -> int:
    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def corridor_map(straight_corridor: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("corridor") / "corridor.db"
    assert run(["map", "build", straight_corridor / "map", "-f", "tum", "--out", db]) == EXIT_OK
    return db


def test_appending_another_world_is_refused_in_one_line(
    corridor_map: Path, tiny_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db = tmp_path / "m.db"
    shutil.copyfile(corridor_map, db)
    before = db.read_bytes()
    capsys.readouterr()
    assert run(["map", "build", tiny_world / "map", "-f", "tum", "--out", db]) == EXIT_ERROR
    err = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(err) == 1, err
    assert "the 12 new images look unrelated to the map's world frame" in err[0]
    assert "no pair shares matches" in err[0] and "--allow-unrelated-frames" in err[0]
    assert db.read_bytes() == before


def test_allow_unrelated_frames_appends_them(
    corridor_map: Path, tiny_world: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    db = tmp_path / "m.db"
    shutil.copyfile(corridor_map, db)
    capsys.readouterr()
    assert (
        run(["map", "build", tiny_world / "map", "-f", "tum", "--out", db, "--allow-unrelated-frames"])
        == EXIT_OK
    )
    captured = capsys.readouterr()
    assert "appending them anyway (allow_unrelated_frames)" in captured.err
    assert f"{db}: 22 images" in captured.out
    with MapDatabase.open(db) as m:
        assert m.num_images() == 22 and m.is_complete


def test_the_option_is_documented(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        run(["map", "build", "--help"])
    assert "--allow-unrelated-frames" in capsys.readouterr().out
