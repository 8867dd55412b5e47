"""Only the map's own lookup error becomes the one-line "run `planarloc map check`" advice; any
other KeyError is a bug and keeps its traceback (issue 28)."""

from __future__ import annotations

import pytest

from planarloc.cli import map_command
from planarloc.cli.exit_codes import EXIT_ERROR
from planarloc.cli.main import main
from planarloc.map.errors import MapKeyError


def test_a_map_lookup_error_is_one_line_with_advice(monkeypatch, capsys, tmp_path) -> None:
    def lookup(args):
        raise MapKeyError(f"image 'q.png' is not in map {tmp_path / 'm.db'}")

    monkeypatch.setattr(map_command, "run_info", lookup)
    assert main(["map", "info", str(tmp_path / "m.db")]) == EXIT_ERROR
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not in map" in err[0] and "planarloc map check" in err[0]


def test_a_bug_keyerror_is_not_disguised_as_map_damage(monkeypatch, capsys, tmp_path) -> None:
    def buggy(args):
        return {}["missing_key"]

    monkeypatch.setattr(map_command, "run_info", buggy)
    with pytest.raises(KeyError, match="missing_key"):
        main(["map", "info", str(tmp_path / "m.db")])
    assert "planarloc map check" not in capsys.readouterr().err
