"""Maps under hostile or unusual file systems: one writer per file whatever path names it (symbolic
links), lock files that are links, read-only maps reused by another user without writing, and a
damaged file refused when it is opened."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from map_files import SMALL_VOCABULARY, garbage_in_the_middle, held_writer_lock, map_build_argv
from other_user import base_env, other_user, run_as, shared_folder

from planarloc.map.lock import MapBusyError, MapWriterLock, lock_path_of
from planarloc.map.schema import MapCorruptError
from planarloc.map.store import MapDatabase

CLI = [sys.executable, "-m", "planarloc.cli.main"]


def cli(*argv: object, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, argv)], capture_output=True, text=True, env=env, timeout=900)


@pytest.fixture(scope="module")
def world_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("map") / "map.db"
    built = cli(*map_build_argv(tiny_world / "map", db, *SMALL_VOCABULARY))
    assert built.returncode == 0, built.stderr
    return db


def _query(world: Path) -> tuple[Path, str]:
    return sorted((world / "query" / "rgb").glob("*.png"))[0], (
        world / "query" / "camera.txt"
    ).read_text().splitlines()[-1]


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---- one writer per file ----------------------------------------------------------------------------
def test_writers_through_a_link_and_the_real_path_take_turns(world_map: Path, tmp_path: Path) -> None:
    real = tmp_path / "real" / "m.db"
    real.parent.mkdir()
    shutil.copy(world_map, real)
    file_link = tmp_path / "m-link.db"
    file_link.symlink_to(real)
    folder_link = tmp_path / "maps"
    folder_link.symlink_to(real.parent)
    assert lock_path_of(file_link) == lock_path_of(folder_link / "m.db") == lock_path_of(real)
    for held, other in ((file_link, real), (real, folder_link / "m.db"), (folder_link / "m.db", file_link)):
        with held_writer_lock(held) as holder:
            with pytest.raises(MapBusyError, match=f"being built by PID {holder.pid}"):
                MapDatabase.open(other, mode="a", lock_timeout=0.2)
    with MapDatabase.open(file_link, mode="a", lock_timeout=0):  # free again; in-process too
        with pytest.raises(MapBusyError, match="already open for writing in this process"):
            MapWriterLock(real, timeout=0).acquire()


def test_a_new_map_through_a_dangling_link_is_made_where_the_link_points(tmp_path: Path) -> None:
    link = tmp_path / "link.db"
    link.symlink_to(tmp_path / "target.db")
    with MapDatabase.create(link, {"features": "test"}) as db:
        assert db.num_images() == 0
    assert link.is_symlink() and (tmp_path / "target.db").is_file()


def test_a_lock_file_that_is_a_link_is_refused_not_followed(tmp_path: Path) -> None:
    victim = tmp_path / "victim.txt"
    victim.write_text("do not truncate")
    path = tmp_path / "m.db"
    lock_path_of(path).symlink_to(victim)  # planted in a shared folder
    with pytest.raises(OSError, match="lock file is a symbolic link"):
        MapWriterLock(path, timeout=0).acquire()
    assert victim.read_text() == "do not truncate"


# ---- read-only maps: reused without writing -------------------------------------------------------------
@pytest.fixture(scope="module")
def shared_world(tiny_world: Path):
    """The tiny world, a map of all its map images (`map build`) and one of every second image
    (`evaluate --map-every 2`), made by root in a folder other users can read but not write."""
    user = other_user()
    with shared_folder() as root:
        shutil.copytree(tiny_world, root / "world")
        built = cli(*map_build_argv(root / "world" / "map", root / "map.db", *SMALL_VOCABULARY))
        assert built.returncode == 0, built.stderr
        evaluated = cli(
            "evaluate", root / "world" / "map", "-f", "tum", "--map-every", "2", "--map", root / "e.db"
        )
        assert evaluated.returncode == 0, evaluated.stderr
        subprocess.run(["chmod", "-R", "a+rX,go-w", str(root)], check=True)
        yield root, user


def test_map_build_onto_a_read_only_map_holding_those_images_succeeds_without_writing(shared_world) -> None:
    root, user = shared_world
    env = base_env()
    before = _sha(root / "map.db")
    proc = run_as(
        user, [*CLI, *map_build_argv(root / "world" / "map", root / "map.db", *SMALL_VOCABULARY)], env=env
    )
    assert proc.returncode == 0, proc.stderr
    assert "12 images" in proc.stdout and _sha(root / "map.db") == before
    assert not list(root.glob(".map.db*")) and not list(root.glob("map.db-*"))  # no lock, no journal


def test_map_build_onto_a_read_only_map_file_in_a_writable_folder_succeeds_without_writing(
    shared_world,
) -> None:
    root, user = shared_world
    folder = root / "users-folder"
    folder.mkdir()
    shutil.copy(root / "map.db", folder / "map.db")  # root's file, mode 0644, in the user's folder
    os.chown(folder, user.pw_uid, user.pw_gid)
    before = _sha(folder / "map.db")
    proc = run_as(
        user,
        [*CLI, *map_build_argv(root / "world" / "map", folder / "map.db", *SMALL_VOCABULARY)],
        env=base_env(),
    )
    assert proc.returncode == 0, proc.stderr
    assert _sha(folder / "map.db") == before and not list(folder.glob("map.db-*"))


def test_a_read_only_map_missing_images_says_why_in_one_line(shared_world) -> None:
    root, user = shared_world
    proc = run_as(
        user,
        [*CLI, *map_build_argv(root / "world" / "query", root / "map.db", *SMALL_VOCABULARY)],
        env=base_env(),
    )
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(err) >= 1
    assert "cannot write the map" in err[-1] and "must be added or updated" in err[-1]


def test_evaluate_with_a_read_only_map_succeeds_without_writing(shared_world) -> None:
    root, user = shared_world
    before = _sha(root / "e.db")
    tmp = root / "tmp"
    tmp.mkdir(mode=0o1777, exist_ok=True)
    tmp.chmod(0o1777)
    proc = run_as(
        user,
        [*CLI, "evaluate", root / "world" / "map", "-f", "tum", "--map-every", "2", "--map", root / "e.db"],
        env=base_env(TMPDIR=str(tmp)),
    )
    assert proc.returncode == 0, proc.stderr
    assert "localize: 6/6" in proc.stderr and _sha(root / "e.db") == before


# ---- a damaged map is refused when it is opened ----------------------------------------------------------
def test_a_map_with_garbage_in_its_middle_is_refused_at_open(
    world_map: Path, tiny_world: Path, tmp_path: Path
) -> None:
    damaged = tmp_path / "damaged.db"
    shutil.copy(world_map, damaged)
    garbage_in_the_middle(damaged)
    for mode in ("r", "a"):
        with pytest.raises(MapCorruptError, match="damaged map file .*map check"):
            MapDatabase.open(damaged, mode=mode)
    query, cam = _query(tiny_world)
    proc = cli("localize", "--map", damaged, query, "--camera", cam, "--out", tmp_path / "poses.txt")
    err = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and len(err) == 1, proc.stderr
    assert err[0].startswith("planarloc localize: error: ") and "damaged map file" in err[0]
    assert not (tmp_path / "poses.txt").exists()


def test_a_sound_map_is_page_checked_once_per_process_while_unchanged(
    world_map: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import planarloc.map.store as store

    monkeypatch.setattr(store, "_PAGES_SOUND", set())
    with MapDatabase.open(world_map) as db:
        assert db.num_images() == 12
    assert store._PAGES_SOUND == {store._file_state(world_map)}
