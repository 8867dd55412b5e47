"""The real `planarloc` command (subprocesses) on real files: what goes to stdout and stderr, results
written through devices, FIFOs and symlinks, refused over maps, atomic under a full disk, the same
record and exit code for one bad image on every localize path, one rule for query names."""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import sqlite3
import stat
import subprocess
import threading
from pathlib import Path

import pytest
from _cli_runs import cli, evaluate_argv, localize_argv, run
from map_files import map_build_argv

from planarloc.cli.main import main

POSE_LINE_FIELDS = 8


def error_lines(proc: subprocess.CompletedProcess) -> list[str]:
    return [line for line in proc.stderr.splitlines() if "error:" in line]


@pytest.fixture(scope="module")
def world_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("doors") / "map.db"
    assert run(map_build_argv(tiny_world / "map", db, "--vocabulary-size", "16")) == 0
    return db


@pytest.fixture
def two_queries(tiny_world: Path) -> tuple[list[Path], str]:
    images = sorted((tiny_world / "query" / "rgb").glob("*.png"))[:2]
    return images, (tiny_world / "query" / "camera.txt").read_text().splitlines()[-1]


def localize(
    world_map: Path, images: list[Path], camera: str, *extra: object, **kw
) -> subprocess.CompletedProcess:
    return cli(
        "localize", "--map", world_map, *images, "--camera", camera, "--structure", "tracks", *extra, **kw
    )


# ---- streams --------------------------------------------------------------------------------------
def test_out_dash_puts_only_the_results_on_stdout(world_map, two_queries, tmp_path) -> None:
    images, cam = two_queries
    proc = localize(world_map, images, cam, "--out", "-", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert sorted(line.split()[0] for line in lines) == sorted(p.name for p in images)
    assert all(len(line.split()) == POSE_LINE_FIELDS for line in lines)
    assert "localized 2 of 2 queries" in proc.stderr  # the summary moves to stderr
    assert not (tmp_path / "-").exists() and list(tmp_path.iterdir()) == []  # no file '-', no records folder


def test_map_info_and_check_streams_and_long_paths_stay_on_one_line(world_map, tmp_path) -> None:
    folder = tmp_path / ("a-folder-with-a-long-name-" * 6)
    folder.mkdir()
    long_map = folder / "map.db"
    shutil.copy(world_map, long_map)
    info = cli("map", "info", long_map)
    assert info.returncode == 0 and info.stderr == ""
    first = info.stdout.splitlines()[0]
    assert first.startswith(f"{long_map}: 12 images") and len(first) > 160  # never hard-wrapped
    assert "gravity (down, world frame)" in info.stdout
    ok = cli("map", "check", long_map)
    assert (
        ok.returncode == 0
        and ok.stdout.strip() == f"{long_map}: ok (12 images, complete)"
        and ok.stderr == ""
    )
    with sqlite3.connect(long_map) as conn:
        conn.execute("UPDATE images SET tx = tx + 1 WHERE id = 2")
    bad = cli("map", "check", long_map)
    assert bad.returncode == 1 and bad.stdout == ""
    problems = bad.stderr.splitlines()
    assert (
        problems[0]
        == f"{long_map}: images row 2 ('rgb/0.100000.png'): checksum mismatch (name, camera, pose or "
        "features changed on disk)"
    )
    assert problems[-1].startswith("planarloc map check: error:") and len(error_lines(bad)) == 1


def test_evaluate_table_and_files_to_stdout_progress_to_stderr(tiny_world, tmp_path) -> None:
    options = ("--vocabulary-size", "16", "--json", tmp_path / "e.json")
    proc = cli(*evaluate_argv(tiny_world / "map", tmp_path, *options))
    assert proc.returncode == 0, proc.stderr
    assert "0.25m/10deg" in proc.stdout and f"wrote {tmp_path / 'e.json'}" in proc.stdout
    assert "0.25m/10deg" not in proc.stderr and "map: 6 frames" in proc.stderr


# ---- results files ------------------------------------------------------------------------------
def test_a_fifo_is_written_through(world_map, two_queries, tmp_path) -> None:
    images, cam = two_queries
    fifo = tmp_path / "results.fifo"
    os.mkfifo(fifo)
    got: list[str] = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_text()))
    reader.start()
    proc = localize(world_map, images, cam, "--out", fifo)
    reader.join(30)
    assert proc.returncode == 0, proc.stderr
    assert stat.S_ISFIFO(os.stat(fifo).st_mode)  # still a FIFO, not replaced by a file
    assert len(got) == 1 and len(got[0].splitlines()) == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.fifo"]  # no records next to a FIFO


def test_a_device_and_a_symlink_to_it_are_written_through(world_map, two_queries, tmp_path) -> None:
    images, cam = two_queries
    device = tmp_path / "null"
    try:
        os.mknod(device, stat.S_IFCHR | 0o666, os.makedev(1, 3))  # our own /dev/null node
    except PermissionError:
        pytest.skip("creating a device node needs CAP_MKNOD")
    link = tmp_path / "out.txt"
    link.symlink_to(device)
    for target in (device, link):
        proc = localize(world_map, images, cam, "--out", target)
        assert proc.returncode == 0, proc.stderr
    assert stat.S_ISCHR(os.stat(device).st_mode) and link.is_symlink() and os.readlink(link) == str(device)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["null", "out.txt"]


def test_regular_results_are_replaced_atomically_through_a_symlink_with_umask_permissions(
    world_map, two_queries, tmp_path
) -> None:
    images, cam = two_queries
    real, link = tmp_path / "real.txt", tmp_path / "poses.txt"
    real.write_text("old.png 1 0 0 0 0 0 0\n")
    link.symlink_to(real)
    proc = localize(world_map, images, cam, "--out", link, preexec=lambda: os.umask(0o027))
    assert proc.returncode == 0, proc.stderr
    assert link.is_symlink() and os.readlink(link) == str(real)
    assert sorted(line.split()[0] for line in real.read_text().splitlines()) == sorted(p.name for p in images)
    records = sorted((tmp_path / "poses.txt.json.d").iterdir())
    assert len(records) == 2
    for path in (real, *records):
        assert stat.S_IMODE(os.stat(path).st_mode) == 0o640, path  # 0o666 & ~umask, not 0600
    assert [p.name for p in tmp_path.iterdir() if ".tmp" in p.name] == []


def test_an_existing_map_or_image_is_never_replaced_by_results(world_map, two_queries, tmp_path) -> None:
    images, cam = two_queries
    other = tmp_path / "other_map.db"
    shutil.copy(world_map, other)
    picture = tmp_path / "picture.png"
    shutil.copy(images[0], picture)
    for target in (other, picture):
        before = target.read_bytes()
        proc = localize(world_map, images, cam, "--out", target)
        assert proc.returncode == 1 and len(proc.stderr.strip().splitlines()) == 1
        assert proc.stderr.startswith(
            f"planarloc localize: error: --out {target}: exists and is not a results file"
        )
        assert target.read_bytes() == before


def test_a_full_disk_leaves_the_old_results_intact(world_map, two_queries, tmp_path) -> None:
    images, cam = two_queries
    out = tmp_path / "poses.txt"
    old = "q.png 1.0 0.0 0.0 0.0 1.0 2.0 3.0\n"
    out.write_text(old)

    def full_disk() -> None:  # every file this process writes is cut at 64 bytes
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (64, 64))

    proc = localize(world_map, images, cam, "--out", out, preexec=full_disk)
    assert proc.returncode == 1
    assert len(error_lines(proc)) == 1 and "File too large" in proc.stderr
    assert out.read_text() == old
    assert not [p for p in tmp_path.rglob("*") if ".tmp" in p.name]  # no temporary file left behind


# ---- one bad image, every path --------------------------------------------------------------------
def test_a_stream_records_an_unreadable_frame_and_goes_on(world_map, tiny_world, tmp_path) -> None:
    query = tiny_world / "query"
    frames = sorted((query / "rgb").glob("*.png"))
    stamps = [
        float(line.split()[0]) for line in (query / "rgb.txt").read_text().splitlines() if line[0] != "#"
    ]
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not an image")
    listing = (
        tmp_path / "frames.txt"
    )  # the broken frame between the 3rd and the 4th, with a stamp between theirs
    entries = [
        *zip(stamps[:3], frames[:3]),
        ((stamps[2] + stamps[3]) / 2, broken),
        *zip(stamps[3:], frames[3:]),
    ]
    listing.write_text("".join(f"{t:.6f} {p}\n" for t, p in entries))
    out = tmp_path / "poses.txt"
    out.write_text("")
    stream = ("--sequence", listing, "--odometry", query / "groundtruth.txt")
    proc = cli(*localize_argv(world_map, *stream, "--structure", "tracks", "--out", out))
    assert proc.returncode == 3, proc.stderr
    records = {
        r["name"]: r for r in (json.loads(p.read_text()) for p in (tmp_path / "poses.txt.json.d").iterdir())
    }
    assert (
        records["broken.png"]["status"] == "error" and "cannot read image" in records["broken.png"]["message"]
    )
    assert records["broken.png"]["stamp"] == pytest.approx((stamps[2] + stamps[3]) / 2)
    others = [records[p.name] for p in frames]
    assert all(r["status"] in ("localized", "predicted", "lost") for r in others)
    assert sum(r["success"] for r in others) >= 5 and others[3]["motion_source"] == "odometry"
    # predicted frames are marked by a comment line before their pose (`--predicted mark`, the default)
    assert {line.split()[0] for line in out.read_text().splitlines() if not line.startswith("#")} == {
        r["name"] for r in others if r["success"]
    }
    assert "query broken.png not processed" in proc.stderr and "7 frames:" in proc.stdout


def test_query_names_follow_one_rule(world_map, tiny_world, tmp_path) -> None:
    """A file named directly or in an image list is named by its file name; a folder's images by
    their path relative to it; equal names get parent folders."""
    rgb = tiny_world / "query" / "rgb"
    frames = sorted(rgb.glob("*.png"))[:2]
    listing = tmp_path / "frames.txt"
    listing.write_text("".join(f"{p}\n" for p in frames))

    def names(*args: object, out: str) -> list[str]:
        assert (
            main(
                [
                    str(a)
                    for a in [
                        "localize",
                        "--map",
                        world_map,
                        *args,
                        "--structure",
                        "tracks",
                        "--out",
                        tmp_path / out,
                    ]
                ]
            )
            == 0
        )
        return sorted(json.loads(p.read_text())["name"] for p in (tmp_path / f"{out}.json.d").iterdir())

    files = names(*frames, out="files.txt")
    assert files == [p.name for p in frames]
    assert names("--sequence", listing, out="stream.txt") == files
    folder = tmp_path / "folder"
    (folder / "sub").mkdir(parents=True)
    for p in frames:
        shutil.copy(p, folder / "sub" / p.name)
    assert names(folder, out="folder.txt") == [f"sub/{p.name}" for p in frames]
    copy = tmp_path / "b" / frames[0].name
    copy.parent.mkdir()
    shutil.copy(frames[1], copy)  # another image with the same file name
    assert names(frames[0], copy, out="clash.txt") == sorted([f"rgb/{frames[0].name}", f"b/{frames[0].name}"])
