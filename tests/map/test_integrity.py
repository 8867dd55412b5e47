"""Map identity (content, not names), integrity check, damaged rows, concurrent writers, read-only maps."""

from __future__ import annotations

import logging
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from map_files import garbage_in_the_middle, held_writer_lock
from posed_folder import posed_folder, shifted
from textured_images import textured_image

from planarloc.features.extract import FeatureConfig
from planarloc.map.builder import build_map, check_map_settings
from planarloc.map.integrity import check_map
from planarloc.map.lock import MapBusyError, MapWriterLock, lock_path_of, writer_of
from planarloc.map.schema import MapCorruptError, MapFormatError
from planarloc.map.store import MapDatabase

FEATURES = FeatureConfig(max_features=300)
WORDS = 8


def build(images, path: Path) -> Path:
    return build_map(images, path, FEATURES, num_words=WORDS, workers=1)


@pytest.fixture
def seq_a(tmp_path: Path):
    return posed_folder(tmp_path / "seq_a", n=4, seed=1)


@pytest.fixture
def built(seq_a, tmp_path: Path) -> Path:
    return build(seq_a, tmp_path / "map.db")


# ---- identity -----------------------------------------------------------------------------------
def test_changed_poses_are_updated_not_kept(seq_a, built: Path, caplog: pytest.LogCaptureFixture) -> None:
    moved = shifted(seq_a, 5.0)
    with caplog.at_level(logging.WARNING):
        build(moved, built)
    assert "have a new pose" in caplog.text
    with MapDatabase.open(built) as db:
        assert db.num_images() == 4 and db.is_complete
        for im in moved:
            np.testing.assert_allclose(db.get_pose(im.name).center, im.cam_from_world.center, atol=1e-9)
    assert check_map(built).ok


def test_changed_image_file_is_reextracted(seq_a, built: Path, caplog: pytest.LogCaptureFixture) -> None:
    with MapDatabase.open(built) as db:
        before = db.get_features(seq_a[0].name).keypoints.copy()
    cv2.imwrite(str(seq_a[0].path), textured_image(np.random.default_rng(99), 120, 160))
    with caplog.at_level(logging.WARNING):
        build(seq_a, built)
    assert "changed since they were mapped" in caplog.text
    with MapDatabase.open(built) as db:
        after = db.get_features(seq_a[0].name).keypoints
        assert db.num_images() == 4
        assert len(after) != len(before) or not np.allclose(after, before)
    assert check_map(built).ok


def test_colliding_names_of_another_dataset_are_namespaced(
    built: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    seq_b = posed_folder(tmp_path / "seq_b", n=3, seed=2)  # same names image_l/00000k.png, other files
    with caplog.at_level(logging.WARNING):  # random textures that share nothing: appended on purpose
        build_map(seq_b, built, FEATURES, num_words=WORDS, workers=1, allow_unrelated_frames=True)
    assert "already used by different images" in caplog.text and "seq_b/image_l/000000.png" in caplog.text
    with MapDatabase.open(built) as db:
        names = db.image_names()
    assert len(names) == 7 and "seq_b/image_l/000002.png" in names and "image_l/000002.png" in names
    build(seq_b, built)  # appending the same dataset again is a no-op
    with MapDatabase.open(built) as db:
        assert db.num_images() == 7


def test_resume_unchanged_does_not_rebuild_index(seq_a, built: Path) -> None:
    with MapDatabase.open(built) as db:
        vocab, done = db.get_blob("retrieval/vlad_vocabulary"), db.get_meta("completed_at")
    build(seq_a, built)
    with MapDatabase.open(built) as db:
        assert db.get_blob("retrieval/vlad_vocabulary") == vocab and db.num_images() == 4
        assert db.is_complete and db.get_meta("completed_at") == done  # not re-indexed
    test_finished_map_is_one_file_outside_wal(built)


def test_image_size_differing_from_camera_is_left_out_before_storing(tmp_path: Path) -> None:
    images = posed_folder(tmp_path / "s", n=3)
    cv2.imwrite(str(images[1].path), np.zeros((50, 60), np.uint8))
    left_out: list[tuple[str, str]] = []
    build_map(
        images,
        tmp_path / "m.db",
        FEATURES,
        num_words=WORDS,
        workers=1,
        skipped=lambda im, why: left_out.append((im.name, why)),
    )
    assert len(left_out) == 1 and left_out[0][0] == images[1].name
    assert "image is 60x50 but its camera is 160x120" in left_out[0][1]
    with MapDatabase.open(tmp_path / "m.db") as db:
        assert sorted(db.image_names()) == sorted([images[0].name, images[2].name])


@pytest.mark.parametrize("num_words", [0, -1, 2.5])
def test_bad_vocabulary_size_refused_before_any_file(tmp_path: Path, num_words) -> None:
    images = posed_folder(tmp_path / "s", n=2)
    with pytest.raises(ValueError, match="num_words"):
        build_map(images, tmp_path / "m.db", FEATURES, num_words=num_words)
    assert not (tmp_path / "m.db").exists()


# ---- integrity ----------------------------------------------------------------------------------
def test_check_map_sound(built: Path) -> None:
    report = check_map(built)
    assert report.ok and report.num_images == 4 and report.complete


def _raw(path: Path) -> sqlite3.Connection:
    return sqlite3.connect(path, isolation_level=None)


def test_short_keypoint_blob_is_a_named_map_error(built: Path) -> None:
    with _raw(built) as conn:
        conn.execute("UPDATE keypoints SET data = substr(data, 1, 20) WHERE image_id = 2")
    report = check_map(built)
    assert not report.ok and any("images row 2" in p and "keypoint blob" in p for p in report.problems)
    with MapDatabase.open(built) as db:
        with pytest.raises(MapCorruptError, match="image_l/000001.png|row id 2"):
            list(db.iter_features())
        with pytest.raises(MapCorruptError, match="keypoint blob is 20 bytes"):
            db.get_features(2)


def test_changed_pose_row_fails_checksum(built: Path) -> None:
    with _raw(built) as conn:
        conn.execute("UPDATE images SET tx = tx + 1 WHERE id = 3")
    assert any("images row 3" in p and "checksum" in p for p in check_map(built).problems)


def test_missing_feature_rows_named(built: Path) -> None:
    with _raw(built) as conn:
        conn.execute("DELETE FROM descriptors WHERE image_id = 1")
    assert any("images row 1" in p and "missing" in p for p in check_map(built).problems)
    with MapDatabase.open(built) as db, pytest.raises(MapCorruptError, match="missing"):
        db.get_features("image_l/000000.png")


def test_garbage_in_the_middle_of_the_file_is_detected(built: Path) -> None:
    garbage_in_the_middle(built)
    try:
        report = check_map(built)
    except MapFormatError:
        return  # damaged beyond opening: also a clear map error
    assert not report.ok


# ---- writers ------------------------------------------------------------------------------------
def _planarloc(*argv: object, **kw) -> subprocess.Popen:
    """The real `planarloc` command in its own process (PYTHONPATH inherited: this checkout)."""
    return subprocess.Popen([sys.executable, "-m", "planarloc.cli.main", *map(str, argv)], **kw)


def _wait_for(
    condition,
    what: str,
    timeout: float = 120.0,
    proc: subprocess.Popen | None = None,
    output: list[str] | None = None,
) -> None:
    """Poll ``condition``; fail at the timeout, or at once when ``proc`` exits first (with its output)."""
    deadline = time.monotonic() + timeout
    while not condition():
        said = "".join(output or [])
        assert proc is None or proc.poll() is None or condition(), (
            f"{what}: the process exited ({proc.returncode}) first; it said: {said}"
        )
        assert time.monotonic() < deadline, f"timed out waiting for {what}; it said: {said}"
        time.sleep(0.005)


@pytest.mark.parametrize("first_builder", ["finishes", "is SIGKILLed"])
def test_concurrent_builds_overlap_and_the_second_waits_on_the_lock(
    tiny_world: Path, tmp_path: Path, first_builder: str
) -> None:
    """Two `planarloc map build` of one map at once: the second finds the first holding the lock
    (mid-build, frozen there) and waits, naming its PID; the first then finishes or is killed
    with SIGKILL; the second completes the map either way."""
    path = tmp_path / "m.db"
    build = ["map", "build", tiny_world / "map", "-f", "tum", "--out", path, "--vocabulary-size", "16"]
    lock = lock_path_of(path)
    a = _planarloc(*build, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        _wait_for(
            lambda: lock.is_file() and lock.read_text().strip() == str(a.pid), "the first builder's lock"
        )
        os.kill(a.pid, signal.SIGSTOP)  # frozen while it holds the lock: the builds must overlap
        assert lock.read_text().strip() == str(a.pid) and a.poll() is None
        b = _planarloc(*build, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        waiting = f"is being built by PID {a.pid}; waiting for it to finish"
        seen: list[str] = []
        reader = threading.Thread(target=lambda: seen.extend(b.stderr))
        reader.start()
        _wait_for(
            lambda: any(waiting in line for line in seen), "the second builder to wait", proc=b, output=seen
        )
        assert b.poll() is None  # it waits for the first, it does not build alongside
        os.kill(a.pid, signal.SIGKILL if first_builder == "is SIGKILLed" else signal.SIGCONT)
        assert b.wait(300) == 0, "".join(seen)
        reader.join(10)
        assert a.wait(60) == (-signal.SIGKILL if first_builder == "is SIGKILLed" else 0)
    finally:
        for proc in (a,):
            if proc.poll() is None:
                proc.kill()
    report = check_map(path)
    assert report.ok and report.num_images == 12 and report.complete, report.problems
    assert not lock.exists()


def test_settings_check_leaves_a_map_another_process_is_writing_to_the_build(tmp_path: Path) -> None:
    """`map build` checks an existing map's settings before it reads any image; a map another
    process is creating right now (half-made, its writer holding the lock) is not read then: the
    build waits for that writer and checks the settings under the lock."""
    path = tmp_path / "m.db"
    path.write_bytes(b"")  # what a reader may see while the writer is frozen mid-creation
    with held_writer_lock(path) as holder:
        assert writer_of(path) == str(holder.pid)
        check_map_settings(path, FeatureConfig(), 16)  # no MapFormatError: the writer owns the file
    assert writer_of(path) is None
    with pytest.raises(MapFormatError):  # nobody writes it: a broken file is named as such
        check_map_settings(path, FeatureConfig(), 16)


def test_second_writer_waits_or_names_the_pid(built: Path) -> None:
    with held_writer_lock(built) as holder:  # another process holds the map's writer lock
        with pytest.raises(MapBusyError, match=f"being built by PID {holder.pid}"):
            MapDatabase.open(built, mode="a", lock_timeout=0.2)
        with MapDatabase.open(built, mode="r") as reader:  # readers never wait
            assert reader.num_images() == 4
    with MapDatabase.open(built, mode="a"):
        with pytest.raises(MapBusyError, match="already open for writing in this process"):
            MapDatabase.open(built, mode="a")
    with MapDatabase.open(built, mode="a", lock_timeout=0):  # released on close
        pass


def test_lock_of_a_dead_process_is_free(tmp_path: Path) -> None:
    path = tmp_path / "m.db"
    lock_path_of(path).write_text("999999\n")  # left behind by a killed build: no flock held
    with MapWriterLock(path, timeout=0):
        assert lock_path_of(path).read_text().strip() == str(os.getpid())


# ---- read-only use ------------------------------------------------------------------------------
def test_finished_map_is_one_file_outside_wal(built: Path) -> None:
    with open(built, "rb") as f:
        header = f.read(20)
    assert header[18] == 1 and header[19] == 1  # legacy (rollback) journal: no -shm needed to read
    assert (
        not built.with_name(built.name + "-wal").exists()
        and not built.with_name(built.name + "-shm").exists()
    )


def test_map_in_wal_mode_opens_immutable_where_not_writable(
    built: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with MapDatabase.open(built, mode="a") as db:  # an interrupted append: WAL mode, incomplete
        db.set_meta("note", "x")
        db.remove_image("image_l/000003.png")
    with open(built, "rb") as f:
        assert f.read(20)[18] == 2  # WAL
    real_connect = sqlite3.connect

    def no_shm(database, *a, **k):  # what a read-only folder does to a WAL reader
        if "immutable=1" not in str(database):
            raise sqlite3.OperationalError("unable to open database file")
        return real_connect(database, *a, **k)

    monkeypatch.setattr(sqlite3, "connect", no_shm)
    monkeypatch.setattr(os, "access", lambda *a, **k: False)
    with MapDatabase.open(built) as db:
        assert db.num_images() == 3 and db.get_meta("note") == "x" and not db.is_complete


def test_build_on_read_only_media_passes_if_current_else_says_why(
    seq_a, built: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import errno

    def read_only(self) -> None:
        raise PermissionError(errno.EROFS, "Read-only file system", str(self.path))

    monkeypatch.setattr(MapWriterLock, "acquire", read_only)
    assert build(seq_a, built) == built  # e.g. `evaluate --map` on a finished map on a DVD
    with pytest.raises(ValueError, match="cannot write the map .*4 image\\(s\\) must be added or updated"):
        build(shifted(seq_a, 1.0), built)
