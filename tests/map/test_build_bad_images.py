"""A map build over bad image files (truncated, damaged, of another size, undecodable): each is left
out and named, the build goes on, the list ends the output and the exit code is 3; fixing the
files and re-running adds them; a build with no usable image fails before the map exists."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from planarloc.io.datasets import read_dataset
from planarloc.map.builder import build_map
from planarloc.map.store import MapDatabase


def cli(*argv: object) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "planarloc.cli.main", *map(str, argv)],
        capture_output=True,
        text=True,
        timeout=600,
    )


@pytest.fixture
def bad_dataset(tiny_world, tmp_path) -> tuple[Path, dict[str, bytes]]:
    """The tiny world's map images with four broken ones; returns the folder and the originals."""
    root = tmp_path / "map"
    shutil.copytree(tiny_world / "map", root)
    images = sorted((root / "rgb").glob("*.png"))
    originals = {p.name: p.read_bytes() for p in images}
    data = originals[images[1].name]
    images[1].write_bytes(data[: len(data) // 2])  # truncated
    flipped = bytearray(originals[images[4].name])
    flipped[len(flipped) // 2] ^= 0x01
    images[4].write_bytes(bytes(flipped))  # one bit flipped: its chunk fails the CRC
    assert cv2.imwrite(str(images[6]), np.zeros((50, 70), np.uint8))  # another size than its camera
    images[9].write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)  # a PNG signature, then nothing
    return root, originals


def test_map_build_leaves_bad_images_out_lists_them_and_exits_3(bad_dataset, tmp_path) -> None:
    root, originals = bad_dataset
    out = tmp_path / "map.db"
    proc = cli("map", "build", root, "-f", "tum", "--out", out, "--vocabulary-size", "16")
    assert proc.returncode == 3, proc.stderr
    names = sorted(originals)
    bad = {
        names[1]: "truncated PNG",
        names[4]: "fails its CRC",
        names[6]: "is 70x50 but its camera is 320x240",
        names[9]: "truncated PNG",
    }
    tail = proc.stderr.splitlines()[-5:]
    assert tail[0].startswith("4 of 12 images were left out of the map")
    for name, why in bad.items():
        assert any(f"rgb/{name}:" in line and why in line for line in tail[1:]), (name, tail)
    assert "12 images" not in proc.stdout and f"{out}: 8 images" in proc.stdout  # map info of the map built
    with MapDatabase.open(out) as db:
        assert db.num_images() == 8 and db.is_complete
        assert not any(Path(n).name in bad for n in db.image_names())
    # Fixed files: the same command adds them and says nothing is left out.
    for name in bad:
        (root / "rgb" / name).write_bytes(originals[name])
    again = cli("map", "build", root, "-f", "tum", "--out", out, "--vocabulary-size", "16")
    assert again.returncode == 0, again.stderr
    with MapDatabase.open(out) as db:
        assert db.num_images() == 12


def test_the_library_reports_each_image_and_refuses_a_build_with_none(bad_dataset, tmp_path) -> None:
    root, _ = bad_dataset
    images = read_dataset(root, "tum")
    left_out: list[tuple[str, str]] = []
    build_map(
        images, tmp_path / "a.db", num_words=16, skipped=lambda im, why: left_out.append((im.name, why))
    )
    assert len(left_out) == 4 and all(why for _, why in left_out)
    broken = [im for im in images if any(im.name == n for n, _ in left_out)]
    with pytest.raises(ValueError, match="none of the 4 images can go into the map"):
        build_map(broken, tmp_path / "b.db", num_words=16)
    assert not (tmp_path / "b.db").exists()


def test_a_misspelt_run_option_is_refused_before_any_work(bad_dataset, tmp_path) -> None:
    root, _ = bad_dataset
    with pytest.raises(TypeError, match="unexpected keyword argument.*worker"):
        build_map(read_dataset(root, "tum"), tmp_path / "c.db", num_words=16, worker=2)  # type: ignore[call-arg]
    assert not (tmp_path / "c.db").exists()
