"""`planarloc cache list|clean`: what planarloc keeps that it can rebuild, where, and how much.

Three caches:

- ``maps``: the maps `evaluate` builds when no ``--map`` is given (keyed by the map images and
  settings; :func:`planarloc.map.settings.cache_dir`);
- ``bags``: images unpacked from ROS bags (``--format rosbag`` without ``image_dir``);
- ``kernels``: numba's compiled kernels (``*.nbi``/``*.nbc``, next to planarloc's modules, or
  in ``NUMBA_CACHE_DIR``; on a read-only install also this user's folders:
  :mod:`planarloc.numerics.kernel_cache`); `planarloc warmup` rebuilds them.

``clean`` removes ``maps`` and ``bags`` unless told which. A map that a running build holds
(its writer lock) is skipped and named.

The ``maps`` and ``bags`` folders are this user's (``<temp>/planarloc-<uid>/…``,
:func:`planarloc.map.settings.cache_dir`): a folder of that name that is a symbolic link or
another user's is refused, not cleaned. Cleaning never follows a symbolic link: a link found
in a cache is removed as a link, its target is left alone, and folders are walked without
entering linked ones. Kernels of a read-only install (its ``__pycache__``) are kept, and said so.
"""

from __future__ import annotations

import argparse
import errno
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from planarloc.cli.commands import add_command
from planarloc.cli.console import info, note
from planarloc.map.lock import MapBusyError, MapWriterLock
from planarloc.map.schema import sidecars
from planarloc.map.settings import CACHES, cache_dir

KINDS = (*CACHES, "kernels")
KERNELS = (
    "numba's compiled kernels; `planarloc warmup` compiles them again "
    "(about 3 minutes of CPU, spread over every core)"
)


@dataclass
class CacheEntry:
    """One cache: its folders and the files planarloc owns in them."""

    kind: str
    what: str
    folders: list[Path]
    files: list[Path]

    @property
    def size(self) -> int:
        return sum(_lsize(f) for f in self.files)


def _lsize(path: Path) -> int:
    """Bytes of a regular file, 0 for anything else (a symbolic link counts as itself, never its target)."""
    try:
        st = os.lstat(path)
    except OSError:
        return 0
    return st.st_size if stat.S_ISREG(st.st_mode) else 0


def _kernel_files() -> tuple[list[Path], list[Path]]:
    """numba's cache folders of planarloc's kernels and the index/data files in them."""
    from planarloc.compile import kernel_cache_files

    return kernel_cache_files()


def _walk(folder: Path) -> tuple[list[Path], list[Path]]:
    """``(entries, folders)`` below ``folder``: every file and symbolic link (never followed), and
    every real subfolder, deepest first."""
    entries: list[Path] = []
    folders: list[Path] = []
    for root, dirs, files in os.walk(folder, topdown=True, followlinks=False):
        here = Path(root)
        for d in dirs:
            (folders if not (here / d).is_symlink() else entries).append(here / d)
        entries += [here / f for f in files]
    return sorted(entries), sorted(folders, key=lambda p: len(p.parts), reverse=True)


def cache_entries() -> list[CacheEntry]:
    """Every cache with its folders and files (this user's folders only; nothing is created).

    Raises:
        UnsafeFolderError: a cache folder is a symbolic link or another user's.
    """
    out = []
    for kind, what in CACHES.items():
        folder = cache_dir(kind, create=False)
        files = _walk(folder)[0] if folder.is_dir() else []
        out.append(CacheEntry(kind, what, [folder], files))
    folders, files = _kernel_files()
    out.append(CacheEntry("kernels", KERNELS, folders, files))
    return out


def _size(n: int) -> str:
    return f"{n / 2**20:.1f} MB" if n >= 2**20 else f"{n / 2**10:.0f} KB"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "cache",
        "list or clean what planarloc caches (evaluate's maps, unpacked bags, kernels)",
        """List the caches — evaluate's maps and the images unpacked from ROS bags (in the temp folder,
                    TMPDIR) and numba's compiled kernels — with their folders, files and sizes, or remove
                    them. Everything in them is rebuilt when needed.""",
        [
            "planarloc cache list",
            "planarloc cache clean            # evaluate's maps and unpacked bags",
            "planarloc cache clean kernels    # then `planarloc warmup` compiles them again",
        ],
    )
    actions = p.add_subparsers(dest="cache_command", required=True)
    ls = add_command(
        actions,
        "list",
        "the caches, their folders and sizes (stdout)",
        "Print one line per cache: its name, folder, number of files and size, and what it holds.",
        ["planarloc cache list"],
        run_list,
    )
    ls.set_defaults(interrupted="interrupted; nothing was changed")
    clean = add_command(
        actions,
        "clean",
        "remove cached files (default: maps and bags)",
        "Remove the files of the given caches (default: maps and bags). Maps a running build holds are "
        "skipped and named.",
        ["planarloc cache clean", "planarloc cache clean maps kernels"],
        run_clean,
        interrupted="interrupted; the files removed so far are gone, the others kept",
    )
    clean.add_argument(
        "what", nargs="*", metavar="CACHE", help=f"{', '.join(KINDS)} or all (default: maps bags)"
    )


def run_list(args: argparse.Namespace) -> int:
    for e in cache_entries():
        where = ", ".join(str(f) for f in e.folders) or "(no compiled kernels)"
        info(f"{e.kind:<8} {where}: {len(e.files)} files, {_size(e.size)} — {e.what}")
    return 0


def run_clean(args: argparse.Namespace) -> int:
    what = set(args.what or ["maps", "bags"])
    unknown = sorted(what - {*KINDS, "all"})
    if unknown:
        raise ValueError(f"unknown cache {unknown[0]!r}: expected {', '.join(KINDS)} or all")
    if "all" in what:
        what = set(KINDS)
    for e in cache_entries():
        if e.kind not in what:
            continue
        removed, freed, busy, kept = 0, 0, [], 0
        for f in e.files:
            if (
                e.kind == "maps"
            ):  # a map goes with its side files, under its writer lock; nothing else is touched
                if f.suffix != ".db" or not _is_regular(f):
                    continue
                group = [p for p in (f, *sidecars(f)) if os.path.lexists(p)]
                try:
                    with MapWriterLock(f, timeout=0):
                        size = sum(_lsize(p) for p in group)
                        for p in group:
                            p.unlink(missing_ok=True)
                except MapBusyError:
                    busy.append(f)
                    continue
            elif os.path.lexists(f):
                size = _lsize(f)
                try:
                    f.unlink()  # a symbolic link is removed as a link: its target is left alone
                except FileNotFoundError:
                    continue
                except OSError as exc:
                    if exc.errno not in (errno.EACCES, errno.EPERM, errno.EROFS):
                        raise
                    kept += 1  # e.g. the warm kernels of a read-only install
                    continue
            else:
                continue
            removed += 1
            freed += size
        if e.kind != "kernels":
            for folder in e.folders:
                if folder.is_dir():
                    for d in _walk(folder)[1]:
                        try:
                            d.rmdir()
                        except OSError:
                            pass
        info(
            f"{e.kind:<8} {', '.join(str(f) for f in e.folders) or '-'}: removed {removed} "
            f"{'maps' if e.kind == 'maps' else 'files'}, {_size(freed)}"
        )
        for f in busy:
            note(f"kept {f}: a map build holds it")
        if kept:
            note(
                f"kept {kept} {e.kind} files that you may not remove "
                "(e.g. the kernels of a read-only install)"
            )
    return 0


def _is_regular(path: Path) -> bool:
    try:
        return stat.S_ISREG(os.lstat(path).st_mode)
    except OSError:
        return False
