"""What numba's on-disk cache holds of planarloc's kernels: the kernels it misses, whether
kernels compiled elsewhere reach this process, and its files (``*.nbi``, ``*.nbc``)."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from planarloc.compile.dispatchers import dispatcher, planarloc_dispatchers
from planarloc.compile.manifest import Manifest
from planarloc.compile.signatures import numba_types, parse_signature

logger = logging.getLogger(__name__)


def missing_kernels(keys: Iterable[str], manifest: Manifest) -> list[str]:
    """The kernels among ``keys`` with a signature that numba's cache does not hold for this
    machine (numba's cache index, read as ``Dispatcher.compile`` reads it). If the cache cannot
    be inspected (another numba version), none are reported missing: numba compiles lazily."""
    names = numba_types()
    out = []
    try:
        for key in keys:
            # Any: numba's private cache API below (Dispatcher._cache, CPUContext.codegen) is not in its stubs
            d: Any = dispatcher(key)
            if d is None:
                continue
            cache = d._cache
            if not hasattr(cache, "_cache_file"):  # not a cache=True kernel
                continue
            index = cache._cache_file._load_index()
            codegen = d.targetctx.codegen()
            for text in manifest.kernels[key].signatures:
                sig = parse_signature(text, names)
                if sig is not None and cache._index_key(sig, codegen) not in index:
                    out.append(key)
                    break
    except Exception as exc:  # noqa: BLE001 - numba internals changed: behave as before (lazy)
        logger.info("cannot inspect numba's cache (%s); kernels compile on first use", exc)
        return []
    return out


def kernels_persist(key: str) -> bool:
    """Whether kernels compiled in worker processes would reach this one (through numba's cache)."""
    from planarloc.numerics.kernel_cache import kernels_persist as cache_keeps

    d: Any = dispatcher(key)  # Any: Dispatcher._cache is numba's private API, not in its stubs
    return d is not None and cache_keeps(d._cache)


def kernel_cache_files() -> tuple[list[Path], list[Path]]:
    """numba's cache folders of planarloc's kernels, and the index and data files (``*.nbi``,
    ``*.nbc``) of planarloc's modules in them."""
    from planarloc.numerics.kernel_cache import cache_folders

    folders, files = set(), set()
    for d in planarloc_dispatchers().values():
        cache = getattr(d, "_cache", None)
        if not hasattr(cache, "_cache_file"):  # not a cache=True kernel
            continue
        base = d.py_func.__module__.rpartition(".")[2]
        for path in cache_folders(cache):  # a read-only install: its __pycache__ and this user's folders
            folders.add(Path(path))
            files |= {
                f
                for f in Path(path).glob(f"{base}.*")
                if f.suffix in (".nbi", ".nbc") and f.is_file() and not f.is_symlink()
            }
    return sorted(folders), sorted(files)
