"""`planarloc evaluate` with a map image that cannot go into the map: left out, named, listed in the
JSON, and exit code 3, as `map build` does (planarloc/cli/exit_codes.py), also when the cached map
is reused."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from planarloc.cli.exit_codes import EXIT_PARTIAL
from planarloc.cli.main import main


def test_evaluate_says_which_map_images_were_left_out(tiny_world: Path, tmp_path: Path, capsys) -> None:
    world = tmp_path / "office"
    shutil.copytree(tiny_world, world)
    images = sorted((world / "map" / "rgb").glob("*.png"))
    bad = images[3]  # index 3: a map frame with --map-every 3
    bad.write_bytes(bad.read_bytes()[:500])
    args = [
        "evaluate",
        str(world / "map"),
        "-f",
        "tum",
        "--map-every",
        "3",
        "--map",
        str(tmp_path / "m.db"),
        "--json",
        str(tmp_path / "eval.json"),
    ]
    for run in ("build", "reuse"):
        assert main(args) == EXIT_PARTIAL, run
        summary = json.loads((tmp_path / "eval.json").read_text())
        left_out = summary["map_images_left_out"]
        assert [entry["name"] for entry in left_out] == [f"rgb/{bad.name}"], run
        assert "truncated PNG" in left_out[0]["reason"]
        assert summary["queries"] == 8 and summary["failed_queries"] < 8  # the others were evaluated
        err = capsys.readouterr().err
        assert f"image rgb/{bad.name} left out of the map" in err and "1 of 4 map images were left out" in err
