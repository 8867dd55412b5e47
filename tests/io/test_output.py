"""How an output file is written (planarloc.io.output): stdout, written through, or atomically."""

from __future__ import annotations

import errno
import os
import stat
import threading
from pathlib import Path

import cv2
import numpy as np
import pytest

from planarloc.io import output
from planarloc.io.output import is_results_file, output_kind, write_file


def test_kinds_of_targets(tmp_path: Path) -> None:
    fifo, regular, folder = tmp_path / "f", tmp_path / "r.txt", tmp_path / "d"
    os.mkfifo(fifo)
    regular.write_text("")
    folder.mkdir()
    (tmp_path / "to_fifo").symlink_to(fifo)
    (tmp_path / "to_regular").symlink_to(regular)
    assert output_kind("-") == "stdout"
    assert output_kind(fifo) == output_kind(tmp_path / "to_fifo") == "through"
    assert output_kind("/dev/null") == "through"
    assert (
        output_kind(regular)
        == output_kind(tmp_path / "to_regular")
        == output_kind(tmp_path / "new")
        == "file"
    )
    assert output_kind(folder) == "file"  # refused by the checks as a folder, never written through


def test_only_results_files_may_be_replaced(tmp_path: Path) -> None:
    def file(name: str, data: bytes) -> Path:
        (tmp_path / name).write_bytes(data)
        return tmp_path / name

    assert is_results_file(file("empty.txt", b""))
    assert is_results_file(file("poses.txt", b"# c\na.png 1 0 0 0 1 2 3\n\nb/c.png 1 0 0 0 1 2 3\n"))
    assert is_results_file(file("traj.tum", b"0.1 1 2 3 0 0 0 1\n"))
    assert not is_results_file(file("map.db", b"SQLite format 3\x00" + bytes(200)))
    image = tmp_path / "i.png"
    cv2.imwrite(str(image), np.zeros((4, 4), np.uint8))
    assert not is_results_file(image)
    assert not is_results_file(file("notes.txt", b"remember the milk\n"))
    assert not is_results_file(file("seven.txt", b"a.png 1 0 0 0 1 2\n"))
    assert not is_results_file(file("words.txt", b"a b c d e f g h\n"))


def test_a_failed_write_leaves_the_old_file_and_no_temporary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    target = tmp_path / "poses.txt"
    target.write_text("old\n")
    real = os.write
    calls = []

    def full_disk(fd: int, data) -> int:
        calls.append(len(data))
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(fd, data[:4])  # short writes: the loop must go on writing

    monkeypatch.setattr(output.os, "write", full_disk)
    with pytest.raises(OSError) as exc:
        write_file(target, "new results\n" * 10)
    assert exc.value.errno == errno.ENOSPC and exc.value.filename == str(target)  # names the file
    assert target.read_text() == "old\n" and sorted(p.name for p in tmp_path.iterdir()) == ["poses.txt"]
    monkeypatch.setattr(output.os, "write", lambda fd, data: real(fd, data[:4]))
    write_file(target, "new results\n")  # short writes are completed
    assert target.read_text() == "new results\n"


def test_through_and_atomic_writes(tmp_path: Path) -> None:
    fifo = tmp_path / "f"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    write_file(fifo, b"through\n")
    reader.join(10)
    assert got == [b"through\n"] and stat.S_ISFIFO(os.stat(fifo).st_mode)
    real = tmp_path / "real.txt"
    real.write_text("old")
    link = tmp_path / "link.txt"
    link.symlink_to(real)
    old_mask = os.umask(0o077)
    try:
        write_file(link, "new")
        write_file(tmp_path / "sub" / "created.txt", "x")  # folders are created
    finally:
        os.umask(old_mask)
    assert link.is_symlink() and real.read_text() == "new"
    assert stat.S_IMODE(os.stat(real).st_mode) == 0o600  # the umask's, here 077
    assert (tmp_path / "sub" / "created.txt").read_text() == "x"
