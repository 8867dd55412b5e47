"""A process-wide hold of the BLAS library to one thread, shared by whoever asks for it."""

from __future__ import annotations

import threading


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
