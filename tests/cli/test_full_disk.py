"""A real full disk (a tmpfs mounted for the test; RLIMIT_FSIZE where mounting is not allowed):
every failed run — batch, stream, through a server — leaves the earlier results file, TUM
trajectory and per-query records exactly as they were, with no temporary file left behind;
and records of killed runs are cleaned up by the next run."""

from __future__ import annotations

import json
import os
import resource
import signal
import subprocess
import sys
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from _cli_runs import cli, localize_argv

from planarloc.cli.main import main

OLD_RESULTS = "old.png 1.0 0.0 0.0 0.0 1.0 2.0 3.0\n"


@pytest.fixture
def small_disk(tmp_path) -> Iterator[Path]:
    """A 256 KB tmpfs (root only; skipped elsewhere — the RLIMIT test below runs everywhere)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount)], capture_output=True
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.decode().strip()})")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def fill(disk: Path, leave: int) -> None:
    """Fill the disk up to ``leave`` bytes of free space."""
    free = os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize
    with open(disk / f"filler-{uuid.uuid4().hex}", "wb") as f:
        f.write(b"\0" * max(0, free - leave))
    assert os.statvfs(disk).f_bavail * os.statvfs(disk).f_frsize <= leave + 4096


def earlier_run(folder: Path) -> dict[Path, bytes]:
    """What a previous run left: results, a TUM trajectory and two records."""
    records = folder / "poses.txt.json.d"
    records.mkdir(parents=True)
    files = {
        folder / "poses.txt": OLD_RESULTS.encode(),
        folder / "poses.tum": b"# timestamp tx ty tz qx qy qz qw (camera-to-world)\n1.0 0 0 0 0 0 0 1\n",
        records / "0.000000.png.json": json.dumps({"name": "0.000000.png", "old": True}).encode(),
        records / "0.100000.png.json": json.dumps({"name": "0.100000.png", "old": True}).encode(),
    }
    for path, data in files.items():
        path.write_bytes(data)
    return files


def unchanged(files: dict[Path, bytes]) -> bool:
    return all(p.read_bytes() == data for p, data in files.items())


def no_temporaries(folder: Path) -> bool:
    return not [p for p in folder.rglob("*") if ".tmp" in p.name]


@pytest.fixture(scope="module")
def world_map(tiny_world, tmp_path_factory) -> Path:
    db = tmp_path_factory.mktemp("disk-map") / "map.db"
    assert main(["map", "build", str(tiny_world / "map"), "-f", "tum", "--out", str(db)]) == 0
    return db


def queries(tiny_world: Path) -> tuple[list[Path], str]:
    return sorted((tiny_world / "query" / "rgb").glob("*.png")), (
        tiny_world / "query" / "camera.txt"
    ).read_text().splitlines()[-1]


def localize_queries(
    world_map: Path, tiny_world: Path, *options: object, preexec: Callable[[], None] | None = None
) -> subprocess.CompletedProcess:
    """`localize` of every query image with the query camera, in a new process."""
    images, camera = queries(tiny_world)
    return cli(*localize_argv(world_map, *images, "--camera", camera, *options), preexec=preexec)


@pytest.mark.parametrize(
    "pages", [0, 3, 6]
)  # tmpfs pages of 4 KB left: the 1st record, the 4th, the trajectory
def test_a_full_disk_during_a_batch_run_keeps_everything_earlier(
    small_disk, world_map, tiny_world, pages
) -> None:
    files = earlier_run(small_disk)
    fill(small_disk, pages * 4096)
    outputs = ("--out", small_disk / "poses.txt", "--tum", small_disk / "poses.tum")
    proc = localize_queries(world_map, tiny_world, *outputs)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    errors = [line for line in proc.stderr.splitlines() if "error:" in line]
    assert len(errors) == 1 and "No space left on device" in errors[0] and "disk is full" in errors[0]
    failed_at = {0: "0.000000.png.json", 3: "0.300000.png.json", 6: "poses.tum"}[pages]
    assert failed_at in errors[0], errors[0]
    assert unchanged(files) and no_temporaries(small_disk)
    assert sorted(p.name for p in (small_disk / "poses.txt.json.d").iterdir()) == [
        "0.000000.png.json",
        "0.100000.png.json",
    ]


def test_a_full_disk_under_the_results_file_only_keeps_the_records_too(
    small_disk, world_map, tiny_world, tmp_path
) -> None:
    """Records on a roomy disk, the results file on the full one: the records written during the
    run are dropped with it (one run, all or nothing)."""
    files = earlier_run(tmp_path / "roomy")
    (small_disk / "poses.txt").write_text(OLD_RESULTS)
    fill(small_disk, 0)
    records = tmp_path / "roomy" / "poses.txt.json.d"
    proc = localize_queries(world_map, tiny_world, "--out", small_disk / "poses.txt", "--json-dir", records)
    assert proc.returncode == 1
    assert (small_disk / "poses.txt").read_text() == OLD_RESULTS and unchanged(files)
    assert no_temporaries(tmp_path) and no_temporaries(small_disk)


def test_a_full_disk_during_a_stream_keeps_every_earlier_frame_record(
    small_disk, world_map, tiny_world
) -> None:
    files = earlier_run(small_disk)
    images, camera = queries(tiny_world)
    listing = small_disk / "frames.txt"
    listing.write_text("".join(f"{0.1 * k:.6f} {p}\n" for k, p in enumerate(images)))
    fill(small_disk, 6000)
    out = small_disk / "poses.txt"
    proc = cli(*localize_argv(world_map, "--sequence", listing, "--camera", camera, "--out", out))
    assert proc.returncode == 1, proc.stderr
    assert unchanged(files) and no_temporaries(small_disk)
    for record in (small_disk / "poses.txt.json.d").iterdir():
        json.loads(record.read_text())  # every JSON there is whole


def test_a_full_disk_in_server_mode_keeps_everything_earlier(
    small_disk, served_world_map, tiny_world
) -> None:
    url, _proc = served_world_map
    files = earlier_run(small_disk)
    fill(small_disk, 3000)
    images, camera = queries(tiny_world)
    proc = cli(
        "localize",
        "--server",
        url,
        "--map",
        "office",
        *images,
        "--camera",
        camera,
        "--out",
        small_disk / "poses.txt",
    )
    assert proc.returncode == 1, proc.stderr
    assert unchanged(files) and no_temporaries(small_disk)


@pytest.fixture(scope="module")
def served_world_map(world_map) -> Iterator[tuple[str, subprocess.Popen]]:
    pytest.importorskip("fastapi")
    from planarloc.serve.launcher import start_server, stop_server

    url, proc = start_server(["--map", f"office={world_map}", "--workers", "1"])
    try:
        yield url, proc
    finally:
        stop_server(proc)


def test_rlimit_full_disk_keeps_the_records(world_map, tiny_world, tmp_path) -> None:
    """Where no tmpfs can be mounted: every file this process writes is cut at 600 bytes."""
    files = earlier_run(tmp_path)

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (600, 600))

    outputs = ("--out", tmp_path / "poses.txt", "--tum", tmp_path / "poses.tum")
    proc = localize_queries(world_map, tiny_world, *outputs, preexec=limit)
    assert proc.returncode == 1 and "File too large" in proc.stderr
    assert unchanged(files) and no_temporaries(tmp_path)


def test_temporaries_of_a_killed_run_are_removed_by_the_next(world_map, tiny_world, tmp_path) -> None:
    records = tmp_path / "poses.txt.json.d"
    records.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = records / f".0.000000.png.{dead.pid}.0123abcd.tmp.json"
    stale.write_text('{"cut": ')
    images, camera = queries(tiny_world)
    assert (
        main(
            [
                "localize",
                "--map",
                str(world_map),
                str(images[0]),
                "--camera",
                camera,
                "--out",
                str(tmp_path / "poses.txt"),
            ]
        )
        == 0
    )
    assert not stale.exists() and [p.name for p in records.iterdir()] == [f"{images[0].name}.json"]
