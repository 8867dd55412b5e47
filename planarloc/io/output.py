"""Output files: checked before any work, never an input, written so that nothing is lost.

Every command that writes files checks each output before it reads its first input
(:func:`check_output_file`, :func:`check_output_dir`), with the list of the command's inputs: an
output that is also an input (``localize --map m.db --out m.db``) is refused, as is an output that
is a folder (or a folder that is a file), one whose folder cannot be created or written, and —
for results files — an existing file that is not a results file (a map, an image: see
:func:`is_results_file`). An existing planarloc map given as an output (``map build --out``,
``evaluate --map``) may be read-only: whether it must be written is the map builder's decision,
which reuses a map that already holds exactly those images without writing it, and otherwise says
why it cannot (:func:`planarloc.map.builder.build_map`).

Writing (:func:`write_file`, :func:`atomic_output`), by the kind of target (:func:`output_kind`):

- ``-``: standard output.
- an existing file that is not a regular file — a device (``/dev/stdout``), a FIFO, a socket, or a
  symlink to one of them: written through, in place; never replaced by a regular file.
- a regular file (new, existing, or behind a symlink, which stays a symlink): atomically. The data
  go to a temporary file in the same folder, are flushed to disk (fsync), and the temporary file
  is renamed over the target; a write that fails (a full disk, Ctrl-C) removes the temporary file
  and leaves the previous file as it was. New files get the permissions of the umask, like any
  file the shell creates.

Several files that belong together (a results file, its TUM trajectory, its records) are
replaced together with :class:`StagedFiles`: all are written and flushed first, then renamed; a
run that fails before the renames leaves every earlier file as it was.
"""

from __future__ import annotations

import os
import re
import secrets
import stat
import sys
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from planarloc.map.schema import has_map_header

STDOUT = "-"
#: Bytes of an existing file read to tell whether it is a results file.
_SNIFF_BYTES = 1 << 16


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


def input_files(
    paths: Iterable[Path | str | None], with_map_sidecars: Iterable[Path | str | None] = ()
) -> list[Path]:
    """The input list for the checks: the given files, plus ``-wal``/``-shm``/``-journal`` of maps."""
    out = [Path(p) for p in paths if p is not None]
    for m in with_map_sidecars:
        if m is not None:
            m = Path(m)
            out += [m, *(m.with_name(m.name + s) for s in ("-wal", "-shm", "-journal"))]
    return out


#: Files the dataset readers read next to the images (an output must never be one of them).
DATASET_FILES = (
    "poses.txt",
    "calib.txt",
    "times.txt",
    "rgb.txt",
    "depth.txt",
    "groundtruth.txt",
    "camera.txt",
    "color.txt",
    "cameras.txt",
    "images.txt",
    "points3D.txt",
    "list.txt",
)


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
        raise OutputPathError(
            f"{option} {path}: folder {parent} is not writable; choose a writable location "
            "or fix its permissions"
        )


def _check_not_input(path: Path, option: str, inputs: Iterable[Path]) -> None:
    for inp in inputs:
        if _same_file(path, inp):
            raise OutputPathError(
                f"{option} {path}: is also an input ({inp}); writing it would destroy that "
                "input, choose another output path"
            )


def check_output_file(
    path: Path | None, option: str, inputs: Iterable[Path] = (), *, results: bool = False
) -> None:
    """Refuse an output file that is an input, a folder, or not creatable/writable (no-op for
    None and ``-``); with ``results``, also an existing regular file that is not a results file
    (:func:`is_results_file`), e.g. a map given as ``--out``."""
    if path is None or str(path) == STDOUT:
        return
    path = Path(path)
    _check_not_input(path, option, inputs)
    kind = output_kind(path)
    if kind == "through":
        if not os.access(path, os.W_OK):
            raise OutputPathError(
                f"{option} {path}: cannot be written; choose another path or fix its permissions"
            )
        return
    if results and path.is_file() and not is_results_file(path):
        raise OutputPathError(
            f"{option} {path}: exists and is not a results file (not lines of "
            "'name qw qx qy qz tx ty tz'); it is kept: choose another path, or remove it first"
        )
    if path.is_dir():
        raise OutputPathError(f"{option} {path}: is a folder; give a file path, e.g. {path / 'out'}")
    if not results and path.is_file() and has_map_header(path):
        # an existing map, maybe read-only: the map builder reuses it or says why not (module docstring)
        return
    if path.exists() and not os.access(path, os.W_OK):
        raise OutputPathError(
            f"{option} {path}: the file is not writable; choose another path or fix its permissions"
        )
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


def output_kind(path: str | os.PathLike) -> str:
    """``"stdout"`` for ``-``, ``"through"`` for an existing non-regular file (or a link to one),
    else ``"file"`` (written atomically)."""
    if str(path) == STDOUT:
        return "stdout"
    try:
        mode = os.stat(path).st_mode  # follows symlinks
    except (FileNotFoundError, NotADirectoryError):
        return "file"
    return (
        "through"
        if stat.S_ISCHR(mode) or stat.S_ISBLK(mode) or stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode)
        else "file"
    )


def is_results_file(path: str | os.PathLike) -> bool:
    """True for a file planarloc may replace with results: empty, or text whose data lines are
    8 fields with 7 numbers (hloc ``name qw qx qy qz tx ty tz``, TUM ``t tx ty tz qx qy qz qw``).

    Only the first 64 KiB are read; a map (SQLite), an image or any other file is False.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(_SNIFF_BYTES + 1)
    except OSError:
        return False
    truncated = len(head) > _SNIFF_BYTES
    try:
        text = head[:_SNIFF_BYTES].decode("utf-8")
    except UnicodeDecodeError:
        return False
    lines = text.splitlines()
    if truncated and lines:
        lines = lines[:-1]  # cut in the middle
    for line in lines:
        tok = line.split()
        if not tok or tok[0].startswith("#"):
            continue
        if len(tok) != 8:
            return False
        try:
            [float(v) for v in tok[1:]]
        except ValueError:
            return False
    return True


def _temporary(path: Path) -> Path:
    return path.with_name(f".{path.stem}.{os.getpid()}.{secrets.token_hex(4)}.tmp{path.suffix}")


_TEMPORARY = re.compile(r"^\..*\.(?P<pid>[0-9]+)\.[0-9a-f]{8}\.tmp(\.[^.]*)?$")


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_dead_temporaries(folder: Path) -> list[Path]:
    """Remove the temporary files that killed runs left in ``folder`` (their process is gone)."""
    removed: list[Path] = []
    try:
        entries = list(Path(folder).iterdir())
    except OSError:
        return removed
    for p in entries:
        m = _TEMPORARY.match(p.name)
        if m and int(m.group("pid")) != os.getpid() and not _running(int(m.group("pid"))) and p.is_file():
            p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def _fsync_dir(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _write_through(path: str | os.PathLike, data: bytes) -> None:
    with open(path, "wb") as f:  # a device or FIFO: opened in place, never replaced
        f.write(data)
        f.flush()


def _write_temporary(path: str | os.PathLike, raw: bytes) -> tuple[Path, Path]:
    """``(temporary, target)``: ``raw`` written and flushed to disk next to the regular file
    ``path`` (through a symlink), not yet renamed. On failure nothing is left behind."""
    target = Path(os.path.realpath(path))  # a symlink to a regular file stays a symlink
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary(target)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies
    try:
        try:
            view = memoryview(raw)
            while view:
                view = view[os.write(fd, view) :]
            os.fsync(fd)
        finally:
            os.close(fd)
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        if exc.filename is None:  # os.write names no file: name the target
            raise OSError(exc.errno, exc.strerror, str(path)) from None
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return tmp, target


def _write_direct(path: str | os.PathLike, raw: bytes, kind: str) -> None:
    if kind == "stdout":
        sys.stdout.flush()
        sys.stdout.buffer.write(raw)
        sys.stdout.buffer.flush()
    else:
        _write_through(path, raw)


def _raw(data: bytes | str) -> bytes:
    return data.encode("utf-8") if isinstance(data, str) else bytes(data)


def write_file(path: str | os.PathLike, data: bytes | str) -> None:
    """Write ``data`` to ``path`` by its kind (module docstring): ``-``, through, or atomically.

    Parent folders of a new file are created.

    Raises:
        OSError: the write failed; a regular file at ``path`` is then unchanged.
    """
    raw = _raw(data)
    kind = output_kind(path)
    if kind != "file":
        _write_direct(path, raw, kind)
        return
    tmp, target = _write_temporary(path, raw)
    try:
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(target.parent)


class StagedFiles:
    """Several output files replaced together: each is written to a temporary file and flushed
    (:meth:`add`, where a full disk fails), and only :meth:`commit` renames them all over their
    targets; :meth:`discard` (or a failed :meth:`add`) removes the temporaries, so that a run
    that fails leaves every earlier file as it was. ``-`` and devices are written at commit."""

    def __init__(self) -> None:
        self._files: list[tuple[Path, Path]] = []
        self._direct: list[tuple[str | os.PathLike, bytes, str]] = []

    def add(self, path: str | os.PathLike, data: bytes | str) -> None:
        kind = output_kind(path)
        if kind != "file":
            self._direct.append((path, _raw(data), kind))
            return
        try:
            self._files.append(_write_temporary(path, _raw(data)))
        except BaseException:
            self.discard()
            raise

    def stage(self, tmp: Path, target: Path) -> None:
        """Adopt a temporary file already written and flushed (e.g. a record), renamed at commit."""
        self._files.append((Path(tmp), Path(target)))

    def commit(self) -> None:
        for tmp, target in self._files:
            os.replace(tmp, target)
        for folder in {target.parent for _, target in self._files}:
            _fsync_dir(folder)
        self._files = []
        for path, raw, kind in self._direct:
            _write_direct(path, raw, kind)
        self._direct = []

    def discard(self) -> None:
        for tmp, _ in self._files:
            tmp.unlink(missing_ok=True)
        self._files, self._direct = [], []


def write_text_atomic(path: Path, text: str | Iterable[str]) -> None:
    """Write a text (or its lines) to ``path`` with :func:`write_file`."""
    write_file(path, text if isinstance(text, str) else "".join(text))


@contextmanager
def atomic_output(path: Path) -> Iterator[Path]:
    """Yield a temporary path (same folder and suffix) for a writer that wants a file name
    (a plot, an image); on success it is flushed to disk and renamed to ``path`` (through a
    symlink to a regular file); on failure removed."""
    target = Path(os.path.realpath(path))
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temporary(target)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    _fsync_dir(target.parent)
