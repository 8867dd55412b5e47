"""`planarloc cache list|clean`: what planarloc keeps that it can rebuild, where, and how much.

Three caches:

- ``maps``: the maps `evaluate` builds when no ``--map`` is given (keyed by the map images and
  settings; :func:`planarloc.map.settings.cache_dir`);
- ``bags``: images unpacked from ROS bags (``--format rosbag`` without ``image_dir``);
- ``kernels``: numba's compiled kernels (``*.nbi``/``*.nbc``, next to planarloc's modules, or
  in ``NUMBA_CACHE_DIR``); `planarloc warmup` rebuilds them.

``clean`` removes ``maps`` and ``bags`` unless told which. A map that a running build holds
(its writer lock) is skipped and named.
"""

from __future__ import annotations

import argparse
import shutil
from dataclasses import dataclass
from pathlib import Path

from planarloc.cli.commands import add_command
from planarloc.cli.console import info, note
from planarloc.map.lock import MapBusyError, MapWriterLock
from planarloc.map.schema import sidecars
from planarloc.map.settings import CACHES, cache_dir

KINDS = (*CACHES, "kernels")
KERNELS = "numba's compiled kernels; `planarloc warmup` compiles them again (about 3 minutes of CPU, spread over every core)"


@dataclass
class CacheEntry:
    """One cache: its folders and the files planarloc owns in them."""

    kind: str
    what: str
    folders: list[Path]
    files: list[Path]

    @property
    def size(self) -> int:
        return sum(f.stat().st_size for f in self.files if f.is_file())


def _kernel_files() -> tuple[list[Path], list[Path]]:
    """numba's cache folders of planarloc's kernels and the index/data files in them."""
    from planarloc.cli.warmup_command import kernel_cache_files

    return kernel_cache_files()


def cache_entries() -> list[CacheEntry]:
    """Every cache with its folders and files."""
    out = []
    for kind, what in CACHES.items():
        folder = cache_dir(kind)
        files = sorted(p for p in folder.rglob("*") if p.is_file()) if folder.is_dir() else []
        out.append(CacheEntry(kind, what, [folder], files))
    folders, files = _kernel_files()
    out.append(CacheEntry("kernels", KERNELS, folders, files))
    return out


def _size(n: int) -> str:
    return f"{n / 2**20:.1f} MB" if n >= 2**20 else f"{n / 2**10:.0f} KB"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(sub, "cache", "list or clean what planarloc caches (evaluate's maps, unpacked bags, kernels)",
                    """List the caches — evaluate's maps and the images unpacked from ROS bags (in the temp folder,
                    TMPDIR) and numba's compiled kernels — with their folders, files and sizes, or remove them.
                    Everything in them is rebuilt when needed.""",
                    ["planarloc cache list", "planarloc cache clean            # evaluate's maps and unpacked bags",
                     "planarloc cache clean kernels    # then `planarloc warmup` compiles them again"])
    actions = p.add_subparsers(dest="cache_command", required=True)
    ls = add_command(actions, "list", "the caches, their folders and sizes (stdout)",
                     "Print one line per cache: its name, folder, number of files and size, and what it holds.",
                     ["planarloc cache list"], run_list)
    ls.set_defaults(interrupted="interrupted; nothing was changed")
    clean = add_command(actions, "clean", "remove cached files (default: maps and bags)",
                        "Remove the files of the given caches (default: maps and bags). Maps a running build holds are "
                        "skipped and named.", ["planarloc cache clean", "planarloc cache clean maps kernels"],
                        run_clean, interrupted="interrupted; the files removed so far are gone, the others kept")
    clean.add_argument("what", nargs="*", metavar="CACHE", help=f"{', '.join(KINDS)} or all (default: maps bags)")


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
        removed, freed, busy = 0, 0, []
        for f in e.files:
            if e.kind == "maps":  # a map goes with its side files, under its writer lock
                if f.suffix != ".db" or not f.is_file():
                    continue
                group = [p for p in (f, *sidecars(f)) if p.is_file()]
                try:
                    with MapWriterLock(f, timeout=0):
                        size = sum(p.stat().st_size for p in group)
                        for p in group:
                            p.unlink(missing_ok=True)
                except MapBusyError:
                    busy.append(f)
                    continue
            elif f.is_file():
                size = f.stat().st_size
                f.unlink(missing_ok=True)
            else:
                continue
            removed += 1
            freed += size
        if e.kind == "bags":
            for folder in e.folders:
                for d in sorted((d for d in folder.glob("*") if d.is_dir()), reverse=True):
                    shutil.rmtree(d, ignore_errors=True)
        info(f"{e.kind:<8} {', '.join(str(f) for f in e.folders) or '-'}: removed {removed} "
             f"{'maps' if e.kind == 'maps' else 'files'}, {_size(freed)}")
        for f in busy:
            note(f"kept {f}: a map build holds it")
    return 0
