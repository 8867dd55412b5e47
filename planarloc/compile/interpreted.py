"""Running planarloc's kernels as plain Python while they compile: a first pose in seconds.

On an empty kernel cache a first query compiles about 86 kernels: about 100 s of CPU on the
2 cores of a slow machine (``BENCHMARKS.md``, "First pose and compile time"), so 50 s of waiting
before the first pose even on every core. Every kernel is also a plain Python function (numba's
``py_func``, the same code), and run that way a whole KITTI query takes 16-17 s, most of it in
five kernels that loop over every match or every row of a refinement (MSAC scoring of planar and
relative hypotheses, the Sampson rows and IRLS normal equations of the refinements, the map
prior's pair blocks). Compiled in the process, those five cost 5-6 s of compile time and leave
about 6 s of Python: a first pose in about 12 s, without waiting for the rest.

:func:`interpreted_kernels` does this for the duration of a ``with`` block: every planarloc
dispatcher outside :data:`HOT_KERNELS` runs its ``py_func`` when called from Python (from code
outside the kernels, or from another kernel running as Python). Nothing else changes:

- A compiled kernel never goes through this: numba links its callees from their dispatchers'
  own compiled code, so a hot kernel compiles with its callees as usual and writes numba's cache.
- The swap is the class of each dispatcher object (``CPUDispatcher`` → :class:`_AsPython`, a
  subclass whose ``__call__`` runs ``py_func``), so every reference to a kernel (module globals,
  ``from ... import`` names elsewhere, kernels passed as arguments) follows it, and leaving the
  block restores the class: later calls dispatch to compiled code as before, at no extra cost.
- The results are the same computation in another order of floating-point operations: on KITTI
  the pose agrees with the compiled one to 1e-15, and ``tests/compile/test_interpreted.py``
  checks statuses and poses against the compiled estimator on generated scenes.

The front doors pair it with a compile in the background (:mod:`.background`) and leave the
block once that is done; ``planarloc localize --compile wait`` keeps the old behaviour
(compile everything first, on every core).
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

from numba.core.registry import CPUDispatcher

from planarloc.compile.dispatchers import planarloc_dispatchers

__all__ = ["HOT_KERNELS", "PythonKernels", "interpreted_kernels", "running_as_python"]

#: Kernels compiled in the process even while the others run as Python: the loops over every
#: match or residual row, where Python costs seconds per query (a cold KITTI query as Python:
#: MSAC scoring 4.9 s, map-prior pair blocks 3.2 s, Sampson rows 2.3 s, IRLS normal equations
#: 1.8 s of 17 s; compiled in the process: the two scorings 2.5 + 1.3 s, the pair blocks 0.7 s,
#: the Sampson rows 0.9 s, the normal equations 0.3 s; BENCHMARKS.md). The next largest
#: (Nistér's five-point batch 1.8 s as Python, 12 s to compile with its callees; the centre
#: covariance of points 0.5 s against 1.6 s) are cheaper as Python than compiled once.
HOT_KERNELS = (
    "planarloc.robust.scoring:msac_scores",
    "planarloc.robust.scoring:relative_msac_scores",
    "planarloc.robust.refinement:_sampson_rows",
    "planarloc.robust.refinement:irls_normal_equations",
    "planarloc.robust.map_prior:_pair_blocks",
)


class _AsPython(CPUDispatcher):
    """The class of a planarloc dispatcher inside :func:`interpreted_kernels`: a call from
    Python runs the kernel's Python function. numba's typing still sees a dispatcher, so a
    kernel compiled meanwhile links the compiled code of its callees as before."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        return self.py_func(*args, **kwargs)


_lock = threading.Lock()


def running_as_python() -> list[str]:
    """The kernels (``module:qualname``) that run as Python now (empty outside the block)."""
    return sorted(k for k, d in planarloc_dispatchers().items() if type(d) is _AsPython)


class PythonKernels:
    """Kernels swapped to run as Python (:func:`interpreted_kernels`); :meth:`end` swaps them
    back, once the compiled code is at hand (idempotent; the block's end calls it too)."""

    def __init__(self, hot: Iterable[str] = HOT_KERNELS) -> None:
        keep = set(hot)
        self._swapped: list[Any] = []
        with _lock:
            for key, d in planarloc_dispatchers().items():
                # A kernel another block swapped already stays that block's to restore.
                if key not in keep and type(d) is CPUDispatcher:
                    d.__class__ = _AsPython
                    self._swapped.append(d)

    @property
    def active(self) -> bool:
        return bool(self._swapped)

    def end(self) -> None:
        with _lock:
            for d in self._swapped:
                d.__class__ = CPUDispatcher
            self._swapped.clear()


@contextmanager
def interpreted_kernels(hot: Iterable[str] = HOT_KERNELS) -> Iterator[PythonKernels]:
    """Within: every planarloc kernel except ``hot`` runs as Python when called from Python;
    ``end()`` on the handle returns to compiled kernels before the block ends.

    Every kernel module is imported on entry, so kernels of modules imported later are covered
    too. Swapping is thread-safe; a call already running as Python finishes as Python, and its
    later calls of other kernels go to their compiled code."""
    kernels = PythonKernels(hot)
    try:
        yield kernels
    finally:
        kernels.end()
