"""One writer per map file: an advisory lock file next to the map, held while it is written.

SQLite serialises single transactions, but a map build is many transactions plus the
creation of the file itself (a temporary file renamed into place). Two builds interleaving
those steps lose images or replace each other's file. :class:`MapWriterLock` makes writers
take turns: the lock file ``.<map name>.lock`` holds an ``fcntl.flock`` lock and the owner's
PID. A second writer waits (and is told which PID it waits for) or, with ``timeout=0``,
fails with :class:`MapBusyError` naming that PID. The kernel drops the lock when the owner
dies, so a crashed build never blocks the next one. The lock file is removed by its owner
on release; a waiter that acquires an already removed file retries on the new one.

The lock belongs to the file, not to the name it is given by: the map path is resolved first
(symbolic links to the map or to a folder above it), so a build through a link and one through
the real path take turns. The lock file itself is never followed if it is a symbolic link (one
planted in a shared folder would otherwise make the writer truncate its target): that is an error.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

from planarloc.geometry.validation import InputError

logger = logging.getLogger(__name__)

#: Lock files held by this process: a second writer in the same process would wait for itself.
_HELD: set[str] = set()


class MapBusyError(InputError):
    """Another process is writing the map and did not finish within the timeout."""


def lock_path_of(map_path: Path) -> Path:
    """The lock file of a map: ``.<name>.lock`` in the folder of the file the path resolves to
    (symbolic links followed; the map need not exist yet)."""
    map_path = Path(os.path.realpath(map_path))
    return map_path.with_name(f".{map_path.name}.lock")


def _open_lock(path: Path, flags: int) -> int:
    """``os.open`` of a lock file that refuses a symbolic link in its place (ELOOP: one line)."""
    try:
        return os.open(path, flags | os.O_NOFOLLOW, 0o644)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise OSError(
                errno.ELOOP,
                "the map's lock file is a symbolic link; planarloc does not follow it "
                "(remove it if no build runs)",
                str(path),
            ) from None
        raise


def _read_owner(fd: int) -> str:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        text = os.read(fd, 64).decode("ascii", "replace").strip()
    except OSError:
        return "?"
    return text or "?"


def writer_of(map_path: Path) -> str | None:
    """The PID (as text) of the process writing ``map_path`` now, or None when nobody holds its
    writer lock. It only looks: it neither takes the lock nor creates the lock file."""
    try:
        fd = _open_lock(lock_path_of(map_path), os.O_RDONLY)
    except FileNotFoundError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except OSError as exc:
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                raise
            return _read_owner(fd)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


class MapWriterLock:
    """Exclusive writer lock of one map file (a context manager).

    Args:
        map_path: the map file (it need not exist yet).
        timeout: seconds to wait for another writer; ``None`` waits for ever, 0 fails at once.
        on_wait: called once with the owner's PID (as text) when this writer has to wait.

    Raises:
        MapBusyError: the timeout passed while another process held the lock.
        OSError: the lock file cannot be created (e.g. read-only folder).
    """

    def __init__(
        self,
        map_path: str | os.PathLike,
        timeout: float | None = None,
        on_wait: Callable[[str], None] | None = None,
    ) -> None:
        self.map_path = Path(map_path)
        self.path = lock_path_of(self.map_path)
        self.timeout = timeout
        self.on_wait = on_wait
        self._fd: int | None = None
        self._key = ""

    @property
    def held(self) -> bool:
        return self._fd is not None

    def acquire(self) -> None:
        if self._fd is not None:
            return
        key = os.path.realpath(self.path)
        if key in _HELD:
            raise MapBusyError(
                f"{self.map_path} is already open for writing in this process; close that MapDatabase first"
            )
        deadline = None if self.timeout is None else time.monotonic() + self.timeout
        told = False
        while True:
            fd = _open_lock(self.path, os.O_RDWR | os.O_CREAT)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                    os.close(fd)
                    raise
                owner = _read_owner(fd)
                os.close(fd)
                if deadline is not None and time.monotonic() >= deadline:
                    raise MapBusyError(
                        f"{self.map_path} is being built by PID {owner}; wait for it to finish "
                        f"(or stop it) and re-run"
                    ) from None
                if not told:
                    told = True
                    logger.warning(
                        "%s is being built by PID %s; waiting for it to finish", self.map_path, owner
                    )
                    if self.on_wait is not None:
                        self.on_wait(owner)
                time.sleep(0.05)
                continue
            # The previous owner may have removed the file between our open and our lock:
            # then we hold a lock on an orphan inode and must retry on the current file.
            try:
                same = os.fstat(fd).st_ino == os.lstat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            self._fd = fd
            self._key = key
            _HELD.add(key)
            return

    def release(self) -> None:
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        _HELD.discard(self._key)
        try:
            self.path.unlink(missing_ok=True)  # while still locked: waiters then retry on a new file
        except OSError:
            pass
        os.close(fd)

    def __enter__(self) -> MapWriterLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def __del__(self) -> None:  # a forgotten lock must not outlive its object
        self.release()
