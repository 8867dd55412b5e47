"""Output paths of the CLI: checked before any work, never an input, written atomically.

Every subcommand that writes files calls :func:`check_output_file` / :func:`check_output_dir`
for each output option before it reads its first image, with the list of the command's
inputs: an output that is also an input (``localize --map m.db --out m.db``) is refused, as
is an output that is a folder (or a folder that is a file), or one whose folder cannot be
created or written. Result files are written through :func:`write_text_atomic` /
:func:`atomic_output` (temporary file in the same folder, then a rename), so a crash never
leaves a truncated result and never destroys the previous one. :func:`os_error_message`
turns an ``OSError`` into one line with the path and what to do.
"""

from __future__ import annotations

import errno
import os
import sqlite3
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from planarloc.io.lines import write_text_atomic as _write_lines_atomic


class OutputPathError(ValueError):
    """An output option names a path that cannot or must not be written."""


def _real(path: Path) -> str:
    return os.path.realpath(os.path.abspath(path))


def _same_file(a: Path, b: Path) -> bool:
    if _real(a) == _real(b):
        return True
    try:
        return os.path.samefile(a, b)  # hard links
    except OSError:
        return False


def input_files(paths: Iterable[Path | str | None], with_map_sidecars: Iterable[Path | str | None] = ()) -> list[Path]:
    """The input list for the checks: the given files, plus ``-wal``/``-shm``/``-journal`` of maps."""
    out = [Path(p) for p in paths if p is not None]
    for m in with_map_sidecars:
        if m is not None:
            m = Path(m)
            out += [m, *(m.with_name(m.name + s) for s in ("-wal", "-shm", "-journal"))]
    return out


#: Files the dataset readers read next to the images (an output must never be one of them).
DATASET_FILES = ("poses.txt", "calib.txt", "times.txt", "rgb.txt", "depth.txt", "groundtruth.txt", "camera.txt",
                 "color.txt", "cameras.txt", "images.txt", "points3D.txt", "list.txt")


def dataset_files(root: Path | str) -> list[Path]:
    """The metadata files a dataset at ``root`` may have (``root`` itself if it is a file)."""
    root = Path(root)
    return [root] if root.is_file() else [root / name for name in DATASET_FILES]


def _check_parent(path: Path, option: str) -> None:
    """The first existing ancestor of ``path`` must be a writable folder."""
    parent = Path(os.path.abspath(path)).parent
    while not parent.exists():
        if parent.is_symlink():
            raise OutputPathError(f"{option} {path}: its folder {parent} is a broken link")
        parent = parent.parent
    if not parent.is_dir():
        raise OutputPathError(f"{option} {path}: {parent} is a file, not a folder; choose another path")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputPathError(f"{option} {path}: folder {parent} is not writable; choose a writable location "
                              "or fix its permissions")


def _check_not_input(path: Path, option: str, inputs: Iterable[Path]) -> None:
    for inp in inputs:
        if _same_file(path, inp):
            raise OutputPathError(f"{option} {path}: is also an input ({inp}); writing it would destroy that "
                                  "input, choose another output path")


def check_output_file(path: Path | None, option: str, inputs: Iterable[Path] = ()) -> None:
    """Refuse an output file that is an input, a folder, or not creatable/writable (no-op for None)."""
    if path is None:
        return
    path = Path(path)
    _check_not_input(path, option, inputs)
    if path.is_dir():
        raise OutputPathError(f"{option} {path}: is a folder; give a file path, e.g. {path / 'out'}")
    if path.exists() and not os.access(path, os.W_OK):
        raise OutputPathError(f"{option} {path}: the file is not writable; choose another path or fix its "
                              "permissions")
    _check_parent(path, option)


def check_output_dir(path: Path | None, option: str, inputs: Iterable[Path] = ()) -> None:
    """Refuse an output folder that is a file, an input, or not creatable/writable (no-op for None)."""
    if path is None:
        return
    path = Path(path)
    _check_not_input(path, option, inputs)
    if path.exists():
        if not path.is_dir():
            raise OutputPathError(f"{option} {path}: is a file, not a folder; choose another path")
        if not os.access(path, os.W_OK | os.X_OK):
            raise OutputPathError(f"{option} {path}: folder is not writable; choose a writable location")
        return
    _check_parent(path, option)


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` via a temporary file and a rename (parents are created)."""
    _write_lines_atomic(Path(path), [text])


@contextmanager
def atomic_output(path: Path) -> Iterator[Path]:
    """Yield a temporary path (same folder and suffix) to write to; renamed to ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


_HINTS = {
    errno.EACCES: "choose a writable location or fix its permissions",
    errno.EPERM: "choose a writable location or fix its permissions",
    errno.EROFS: "the file system is read-only; choose another location",
    errno.EISDIR: "it is a folder; give a file path",
    errno.ENOTDIR: "a part of the path is a file, not a folder; choose another path",
    errno.EEXIST: "it exists and is not a folder; choose another path",
    errno.ENOENT: "check the path",
    errno.ENOSPC: "the disk is full; free space and re-run (the work done so far is kept)",
}


def os_error_message(exc: OSError) -> str:
    """One line: the path(s), what went wrong, what to do."""
    where = " -> ".join(str(f) for f in (exc.filename, exc.filename2) if f is not None)
    what = exc.strerror or str(exc)
    hint = _HINTS.get(exc.errno or -1, "check the path and permissions")
    return f"{where}: {what}; {hint}" if where else f"{what}; {hint}"


def sqlite_error_message(exc: sqlite3.Error) -> str:
    """One line for an SQLite error escaping the map layer."""
    text = str(exc)
    if "disk is full" in text:
        return f"the disk is full ({text}); free space and re-run the same command to resume"
    if "locked" in text or "busy" in text:
        return f"the map is busy ({text}); another process holds it, re-run when it is done"
    if "readonly" in text or "unable to open" in text:
        return f"cannot write the map ({text}); check that the map and its folder are writable"
    if isinstance(exc, sqlite3.DatabaseError) and ("malformed" in text or "not a database" in text):
        return f"the map file is damaged ({text}); run `planarloc map check MAP` and rebuild it"
    return f"map database error ({text})"
