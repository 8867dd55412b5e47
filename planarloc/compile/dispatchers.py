"""planarloc's numba dispatchers: finding them by ``module:qualname``, and which kernels each calls."""

from __future__ import annotations

import dis
import importlib
import pkgutil
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # numba is imported when a function here runs, not when planarloc.compile is imported
    from numba.core.dispatcher import Dispatcher

#: The packages whose modules define planarloc's compiled kernels.
KERNEL_PACKAGES = ("geometry", "numerics", "solvers", "robust")


def dispatcher(key: str) -> Dispatcher[Any] | None:
    """The numba dispatcher ``module:qualname``, or None if there is none of that name."""
    from numba.core.dispatcher import Dispatcher

    module, _, qualname = key.partition(":")
    try:
        obj = importlib.import_module(module)
        for part in qualname.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError):
        return None
    return obj if isinstance(obj, Dispatcher) else None


def planarloc_dispatchers() -> dict[str, Dispatcher[Any]]:
    """Every numba dispatcher defined in planarloc's compiled layers, by ``module:qualname``."""
    from numba.core.dispatcher import Dispatcher

    out: dict[str, Dispatcher[Any]] = {}
    for package in KERNEL_PACKAGES:
        pkg = importlib.import_module(f"planarloc.{package}")
        for m in pkgutil.iter_modules(pkg.__path__):
            module = importlib.import_module(f"planarloc.{package}.{m.name}")
            for value in vars(module).values():
                if isinstance(value, Dispatcher) and value.py_func.__module__ == module.__name__:
                    out[f"{module.__name__}:{value.py_func.__qualname__}"] = value
    return out


def _direct_callees(d) -> set:
    """Dispatchers a kernel names in its bytecode (``f(...)`` and ``module.f(...)``)."""
    from numba.core.dispatcher import Dispatcher

    out, prev = set(), None
    for ins in dis.get_instructions(d.py_func):
        value = None
        if ins.opname == "LOAD_GLOBAL":
            value = d.py_func.__globals__.get(ins.argval)
        elif ins.opname in ("LOAD_ATTR", "LOAD_METHOD") and type(prev).__name__ == "module":
            value = getattr(prev, ins.argval, None)
        if isinstance(value, Dispatcher):
            out.add(value)
        prev = value
    return out


def kernel_dependencies(keys: Sequence[str]) -> dict[str, set[str]]:
    """For each kernel, the kernels among ``keys`` it calls, directly or through kernels compiled
    as part of it: those inlined into it (``inline="always"``) and those not among ``keys``
    (a kernel not handed out compiles in the process of its first caller, with its callees)."""
    dispatchers = {k: dispatcher(k) for k in keys}
    key_of = {d: k for k, d in dispatchers.items() if d is not None}
    memo: dict[object, set] = {}

    def calls(d, seen: frozenset) -> set:
        if d in memo:
            return memo[d]
        out = set()
        for c in _direct_callees(d):
            if c in seen:
                continue
            if c.targetoptions.get("inline") == "always" or c not in key_of:
                out |= calls(c, seen | {c})
            else:
                out.add(c)
        memo[d] = out
        return out

    return {
        k: ({key_of[c] for c in calls(d, frozenset({d})) if c in key_of} - {k}) if d is not None else set()
        for k, d in dispatchers.items()
    }
