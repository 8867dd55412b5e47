"""How long OpenBLAS's idle threads spin, and a process-wide hold of the BLAS library to one thread.

OpenBLAS keeps its worker threads spinning after each call, for ``2**OPENBLAS_THREAD_TIMEOUT``
CPU cycles (its default: 28, about 0.1 s), in case another call follows. Any other thread pool
that runs in that time shares the cores with them: on the 2-core development machine, an XFeat
extraction right after a query's matching took 109-132 ms instead of 42 ms, and a RootSIFT one
(OpenCV's threads) 130 instead of 100 ms (``benchmarks/blas_idle.py``). A localization alternates
exactly so: features, matching (BLAS), estimation, the next query's features. So planarloc
shortens that spin to ``2**20`` cycles (well under a millisecond) — the back-to-back products of
one matching still find the threads awake — by setting ``OPENBLAS_THREAD_TIMEOUT`` before numpy
loads OpenBLAS (:func:`shorten_openblas_spin`, the first thing ``planarloc/__init__.py`` does). A
value set by the user is kept. OpenBLAS reads it once, when it loads: a program that imported
numpy before planarloc keeps the default unless it sets the variable itself (``export
OPENBLAS_THREAD_TIMEOUT=20``); the ``planarloc`` command, the service and the ROS 2 node import
planarloc first.

This module is imported before numpy: it must not import it.
"""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import MutableMapping

OPENBLAS_IDLE_TIMEOUT = 20
"""``OPENBLAS_THREAD_TIMEOUT`` planarloc sets: OpenBLAS threads spin ``2**20`` cycles (about 0.4 ms
at 2.5 GHz) after a call, then sleep. Measured the same from 4 to 22 on the development machine
(extraction right after matching as fast as alone, matching as fast as with the default)."""

_TIMEOUT_VARIABLES = ("OPENBLAS_THREAD_TIMEOUT", "GOTO_THREAD_TIMEOUT")  # OpenBLAS reads either


def shorten_openblas_spin(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Set ``OPENBLAS_THREAD_TIMEOUT`` to :data:`OPENBLAS_IDLE_TIMEOUT` unless the user set it (or
    ``GOTO_THREAD_TIMEOUT``); child processes inherit it.

    Returns:
        whether it takes effect in this process: False when the user chose a value, or numpy (and
        with it OpenBLAS) is already loaded.
    """
    if any(name in environ for name in _TIMEOUT_VARIABLES):
        return False
    environ["OPENBLAS_THREAD_TIMEOUT"] = str(OPENBLAS_IDLE_TIMEOUT)
    return "numpy" not in sys.modules


class SingleThreadBlas:
    """Holds the BLAS library to one thread while anyone who asked for it holds it.

    OpenBLAS threads spin while they wait for work: on a 2-core machine they take the cores a
    stream's frame path and its fix worker need, and the pose graph's small products gain nothing
    from them. The limit is process-wide (``threadpoolctl``); the last holder to release it
    restores the earlier setting.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._users = 0
        self._limit: object | None = None

    def hold(self) -> None:
        with self._lock:
            if self._users == 0:
                from threadpoolctl import threadpool_limits

                self._limit = threadpool_limits(limits=1, user_api="blas")
            self._users += 1

    def release(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0 and self._limit is not None:
                self._limit.restore_original_limits()  # type: ignore[attr-defined]
                self._limit = None


#: the one hold of this process
BLAS_ONE_THREAD = SingleThreadBlas()
