"""Which version of each map a server serves, and whether the file on disk is still that version.

A server opens its maps once, at start. If a map file is then deleted, replaced (renamed over,
copied over) or written to (``map build`` appending to it), workers started later would open
another map than the running ones: two answers from two versions. So the server fingerprints
every map file when it starts (:func:`map_fingerprint`: device, inode, size, modification time,
and the same of its ``-wal`` and ``-journal`` side files) and :class:`MapWatch` compares:

- before a request is handed to a worker and again before its answer is sent;
- when a worker (re)starts: the worker fingerprints the files around opening them, and a
  worker that opened another version is not used;
- on ``/healthz`` and ``/metrics``.

A change is latched: the map is refused (503) until the server is restarted, and ``/healthz``
names it. Other maps go on serving.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

logger = logging.getLogger(__name__)

SIDECARS = ("-wal", "-journal")


@dataclass(frozen=True)
class FileStamp:
    device: int
    inode: int
    size: int
    mtime_ns: int


@dataclass(frozen=True)
class MapFingerprint:
    """The identity of a map file and of its side files (None: absent)."""

    main: FileStamp | None
    sidecars: tuple[FileStamp | None, ...]


def _stamp(path: Path) -> FileStamp | None:
    try:
        st = os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None
    return FileStamp(st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


def map_fingerprint(path: str | os.PathLike) -> MapFingerprint:
    """The fingerprint of a map file now (``main`` None when the file is gone)."""
    path = Path(path)
    return MapFingerprint(_stamp(path), tuple(_stamp(path.with_name(path.name + s)) for s in SIDECARS))


def fingerprint_change(old: MapFingerprint, new: MapFingerprint) -> str | None:
    """What happened to a map between two fingerprints (``deleted``, ``replaced``, ``modified``), or None."""
    if new.main is None:
        return "deleted"
    if old.main is None or (old.main.device, old.main.inode) != (new.main.device, new.main.inode):
        return "replaced"
    if old != new:
        return "modified"
    return None


class MapWatch:
    """The fingerprints of the served maps at start, and the maps found changed since (latched).

    Args:
        maps: ``{name: path}``.
    """

    def __init__(self, maps: Mapping[str, str | os.PathLike]) -> None:
        self.paths = {name: Path(p) for name, p in maps.items()}
        self.original = {name: map_fingerprint(p) for name, p in self.paths.items()}
        self.changed: dict[str, str] = {}

    def mark(self, name: str, change: str) -> None:
        """Latch a change found elsewhere (e.g. by a worker that opened another version)."""
        if name not in self.changed:
            self.changed[name] = change
            logger.error(
                "map %s: the file was %s after the server started; it is refused until the server is "
                "restarted",
                name,
                change,
            )

    def check(self, name: str) -> str | None:
        """The change of one map since start (None: unchanged), re-checked on disk."""
        if name not in self.changed:
            change = fingerprint_change(self.original[name], map_fingerprint(self.paths[name]))
            if change is not None:
                self.mark(name, change)
        return self.changed.get(name)

    def check_all(self) -> dict[str, str | None]:
        return {name: self.check(name) for name in self.paths}

    def refusal(self, name: str) -> str | None:
        """The one-line reason a map is refused (never its path), or None when it is served."""
        change = self.check(name)
        if change is None:
            return None
        return (
            f"map {name!r}: its file was {change} after the server started; the server refuses it until it "
            "is restarted (so that every answer comes from one version of the map)"
        )
