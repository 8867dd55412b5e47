"""`planarloc localize` with bad images among good ones: each bad one gets a record with its reason
(empty, truncated, a bomb: status error; black: a failed localization with its status), the good
ones their results, and the exit code says "partly done" (3), as planarloc/cli/exit_codes.py does."""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from planarloc.cli.exit_codes import EXIT_OK, EXIT_PARTIAL
from planarloc.cli.main import main
from planarloc.io.datasets import read_dataset
from planarloc.map.builder import build_map


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_bomb() -> bytes:
    """A whole, CRC-valid PNG of a few hundred bytes declaring 30000 x 30000 gray pixels."""
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", struct.pack(">IIBBBBB", 30000, 30000, 8, 0, 0, 0, 0))
        + _chunk(b"IDAT", zlib.compress(b"\0" * 30001 * 8))
        + _chunk(b"IEND", b"")
    )


@pytest.fixture(scope="module")
def office(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    """(map file, the query images) of the tiny world."""
    map_path = build_map(
        read_dataset(tiny_world / "map", "tum"), tmp_path_factory.mktemp("map") / "office.db"
    )
    return map_path, sorted((tiny_world / "query" / "rgb").glob("*.png"))


def records(folder: Path) -> dict[str, dict]:
    return {p.name[: -len(".json")]: json.loads(p.read_text()) for p in folder.glob("*.json")}


def test_a_batch_records_each_bad_image_and_localizes_the_good_ones(office, tmp_path: Path, capsys) -> None:
    map_path, queries = office
    shutil.copy(queries[0], tmp_path / "a.png")
    shutil.copy(queries[1], tmp_path / "b.png")
    bad = {
        "empty.png": b"",
        "cut.png": Path(queries[2]).read_bytes()[:3000],
        "bomb.png": png_bomb(),
        "noise.png": np.random.default_rng(0).bytes(2000),
    }
    for name, data in bad.items():
        (tmp_path / name).write_bytes(data)
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros((240, 320), np.uint8))
    names = ["a.png", "empty.png", "cut.png", "black.png", "bomb.png", "noise.png", "b.png"]
    out = tmp_path / "poses.txt"
    code = main(["localize", "--map", str(map_path), *[str(tmp_path / n) for n in names], "--out", str(out)])
    assert code == EXIT_PARTIAL
    got = records(tmp_path / "poses.txt.json.d")
    assert sorted(got) == sorted(names)  # one record per image, none lost
    assert [line.split()[0] for line in out.read_text().splitlines()] == ["a.png", "b.png"]
    assert got["a.png"]["success"] and got["b.png"]["success"]
    reasons = {
        "empty.png": "the image is empty (0 bytes)",
        "cut.png": "truncated PNG",
        "bomb.png": "declares 30000x30000 pixels, over the limit",
        "noise.png": "not a PNG, JPEG",
    }
    for name, reason in reasons.items():
        assert (
            got[name]["status"] == "error" and name in got[name]["message"] and reason in got[name]["message"]
        )
    assert got["black.png"]["status"] == "too_few_matches" and not got["black.png"]["success"]
    assert "featureless" in got["black.png"]["message"]
    err = capsys.readouterr().err
    assert "Traceback" not in err and "query empty.png not processed" in err


def test_only_failed_localizations_exit_0(office, tmp_path: Path) -> None:
    """A black frame is a result (failed, with its status), not an unprocessed image: exit 0."""
    map_path, queries = office
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros((240, 320), np.uint8))
    code = main(
        [
            "localize",
            "--map",
            str(map_path),
            str(tmp_path / "black.png"),
            str(queries[0]),
            "--out",
            str(tmp_path / "poses.txt"),
        ]
    )
    assert code == EXIT_OK


def test_a_stream_records_an_empty_frame_and_goes_on(office, tmp_path: Path) -> None:
    map_path, queries = office
    frames = [shutil.copy(q, tmp_path / q.name) for q in queries[:6]]
    Path(frames[1]).write_bytes(b"")
    cv2.imwrite(str(frames[2]), np.zeros((240, 320), np.uint8))
    listing = tmp_path / "frames.txt"
    listing.write_text("".join(f"{0.1 * k:.1f} {f}\n" for k, f in enumerate(frames)))
    out = tmp_path / "poses.txt"
    assert (
        main(["localize", "--map", str(map_path), "--sequence", str(listing), "--out", str(out)])
        == EXIT_PARTIAL
    )
    got = records(tmp_path / "poses.txt.json.d")
    names = [Path(f).name for f in frames]
    assert sorted(got) == sorted(names)
    assert got[names[1]]["status"] == "error" and "the image is empty" in got[names[1]]["message"]
    assert got[names[2]]["status"] == "lost"  # black: the stream says so and goes on
    # The stream goes on after them (the frame right after the gap may be lost: the stream's call).
    assert got[names[0]]["status"] == "localized" and got[names[-1]]["status"] == "localized"
    assert all(got[n]["status"] in ("localized", "predicted", "lost") for n in names[3:])
