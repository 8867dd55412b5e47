"""The results writer marks or drops a stream's predicted frames in the pose files, and keeps
every frame's record."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.io.pose_list import read_pose_list
from planarloc.io.results import ResultsWriter
from planarloc.io.tum import read_tum_trajectory


def _record(name: str, stamp: float, status: str, z: float) -> dict:
    success = status != "lost"
    return {
        "name": name,
        "stamp": stamp,
        "status": status,
        "success": success,
        "position_std_m": 0.2,
        "quat_wxyz": [1.0, 0.0, 0.0, 0.0],
        "t": [0.0, 0.0, -z],
    }


def _names(path: Path) -> list[str]:
    camera = Camera("PINHOLE", 100, 100, (100.0, 100.0, 50.0, 50.0))
    return [p.name for p in read_pose_list(path, camera=camera, check_images=False)]


def _write(tmp_path: Path, predicted: str) -> tuple[Path, Path]:
    out, tum = tmp_path / f"{predicted}.txt", tmp_path / f"{predicted}.tum"
    writer = ResultsWriter(out, tmp_path / f"{predicted}.d", tum=tum, predicted=predicted)
    for k, status in enumerate(["localized", "predicted", "lost", "localized"]):
        writer.add(_record(f"f{k}.png", 0.1 * k, status, float(k)), timestamp=0.1 * k)
    writer.close()
    return out, tum


def test_predicted_frames_are_marked_by_default_and_still_read(tmp_path: Path) -> None:
    out, tum = _write(tmp_path, "mark")
    lines = out.read_text().splitlines()
    assert lines[1] == "# predicted f1.png position_std_m=0.2000"
    assert _names(out) == ["f0.png", "f1.png", "f3.png"]
    text = tum.read_text().splitlines()
    assert "# predicted f1.png position_std_m=0.2000" in text
    stamps, _ = read_tum_trajectory(tum)
    assert np.allclose(stamps, [0.0, 0.1, 0.3])
    records = sorted((tmp_path / "mark.d").glob("*.json"))
    assert [json.loads(p.read_text())["status"] for p in records] == [
        "localized",
        "predicted",
        "lost",
        "localized",
    ]


def test_predicted_frames_can_be_left_out_of_the_pose_files(tmp_path: Path) -> None:
    out, tum = _write(tmp_path, "drop")
    assert _names(out) == ["f0.png", "f3.png"]
    assert "predicted" not in out.read_text() and "predicted" not in tum.read_text()
    assert len(list((tmp_path / "drop.d").glob("*.json"))) == 4


def test_an_unknown_mode_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="predicted: expected one of"):
        ResultsWriter(tmp_path / "x.txt", predicted="hide")
