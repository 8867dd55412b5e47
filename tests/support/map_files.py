"""Map files as the map tests make and damage them.

- :func:`map_build_argv`: the `planarloc map build` arguments of a small map of a TUM folder.
- :func:`held_writer_lock`: another process holding a map's writer lock.
- :func:`garbage_in_the_middle`: random bytes over a page-sized block in the middle of a file.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np

SMALL_VOCABULARY = ("--vocabulary-size", "16")  # a map build's options for a tiny world


def map_build_argv(images: Path, out: Path, *options: object) -> list:
    """`planarloc map build IMAGES -f tum --out OUT OPTIONS` (a TUM folder ``images``)."""
    return ["map", "build", images, "-f", "tum", "--out", out, *options]


@contextlib.contextmanager
def held_writer_lock(path: Path) -> Iterator[subprocess.Popen]:
    """Starts a process that takes the writer lock of the map ``path``, yields it once it holds the
    lock (its ``pid`` is the one error messages name) and releases the lock on exit (closes its stdin)."""
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from planarloc.map.lock import MapWriterLock; "
            f"lock = MapWriterLock({str(path)!r}); lock.acquire(); print('held', flush=True); "
            "sys.stdin.read()",
        ],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        yield holder
    finally:
        holder.stdin.close()
        holder.wait(30)


def garbage_in_the_middle(path: Path) -> None:
    """Overwrites 8192 bytes in the middle of the file (more than 3 such blocks long) with random bytes."""
    data = bytearray(path.read_bytes())
    assert len(data) > 3 * 8192
    mid = len(data) // 2
    data[mid : mid + 8192] = np.random.default_rng(0).integers(0, 256, 8192, dtype=np.uint8).tobytes()
    path.write_bytes(bytes(data))
