"""Map building and evaluation on a Ray cluster (optional extra ``planarloc[ray]``).

- Map building: feature extraction of every map image runs as Ray tasks
  (:meth:`RayBackend.map`, passed to :func:`planarloc.map.builder.build_map` as its
  ``mapper``); the driver writes the map in input order, so the map holds the same content as a
  local build (same features, same vocabulary seed, same retrieval index).
- Evaluation: one actor per CPU opens the map read-only once and localizes queries
  (:meth:`RayBackend.evaluate`); the RANSAC seed is per query, so poses equal a local run's.

Requirements on a multi-machine cluster: planarloc installed on every node (same version), and
the dataset images and the map file on a path every node can read (shared file system); the
map is written by the driver only. Without an address, a local Ray instance is started for the
duration of the command and shut down after it.

Example:
    >>> with RayBackend("auto") as ray_backend:                                      # doctest: +SKIP
    ...     build_map(images, "map.db", mapper=ray_backend.map)
    ...     results = ray_backend.evaluate("map.db", LocalizerConfig(), queries)
"""

from __future__ import annotations

import logging
import re
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from planarloc.evaluation.queries import QueryResult, evaluate_query
from planarloc.extras import require
from planarloc.localize.localizer import Localizer, LocalizerConfig
from planarloc.map.posed_image import PosedImage

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")
LOCAL = "local"
_ADDRESS = re.compile(r"^(auto|local|(ray://)?[A-Za-z0-9_.\-\[\]:]+:\d{1,5})$")


def check_address(address: str | None) -> str | None:
    """``None``/``"local"`` (start a local instance), ``"auto"``, ``HOST:PORT`` or ``ray://HOST:PORT``."""
    if address is None or address == LOCAL:
        return None
    if not _ADDRESS.match(address):
        raise ValueError(
            f"--ray {address!r}: not a Ray address (auto, HOST:PORT or ray://HOST:PORT); write "
            "--ray=ADDRESS, or put a bare --ray after the positional arguments"
        )
    return address


def _apply(fn: Callable[[T], R], item: T) -> R:
    return fn(item)


class _QueryEvaluator:
    """Ray actor: a Localizer on the map, opened read-only once per actor."""

    def __init__(self, map_path: str, configs: Sequence[LocalizerConfig]) -> None:
        base = Localizer(Path(map_path), configs[0])
        self.localizers = [base.with_config(c) for c in configs]  # one open map and index

    def evaluate(
        self, query: PosedImage, pairs: dict[str, list[str]] | None, gravity: np.ndarray | None = None
    ) -> list[QueryResult]:
        return evaluate_query(self.localizers, query, pairs, gravity=gravity)


class RayBackend:
    """A connection to a Ray cluster (a local one when ``address`` is None or ``"local"``).

    Args:
        address: cluster address (see :func:`check_address`).
        num_cpus: CPUs of a local instance (default: all); ignored when connecting to a cluster.
    """

    def __init__(self, address: str | None = None, num_cpus: int | None = None) -> None:
        self.ray = require("ray", "ray")
        address = check_address(address)
        self._owns = not self.ray.is_initialized()
        if self._owns:
            kwargs: dict[str, Any] = {
                "include_dashboard": False,
                "logging_level": logging.WARNING,
                "log_to_driver": False,
            }
            if address is None:
                kwargs["num_cpus"] = num_cpus
            self.ray.init(address=address, **kwargs)
        self.num_cpus = max(1, int(self.ray.cluster_resources().get("CPU", 1)))

    def __enter__(self) -> RayBackend:
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def shutdown(self) -> None:
        """Disconnect (and stop the local instance this backend started)."""
        if self._owns and self.ray.is_initialized():
            self.ray.shutdown()
        self._owns = False

    def map(self, fn: Callable[[T], R], items: Iterable[T], window: int | None = None) -> Iterator[R]:
        """``fn(item)`` for each item as Ray tasks, yielded in input order.

        At most ``window`` tasks (default: 2 per cluster CPU) are in flight, so the driver holds a
        bounded number of results however many items there are. A task's exception is re-raised.
        """
        remote = self.ray.remote(_apply)
        fn_ref = self.ray.put(fn)
        window = window or 2 * self.num_cpus
        pending: deque = deque()
        for item in items:
            pending.append(remote.remote(fn_ref, item))
            if len(pending) >= window:
                yield self.ray.get(pending.popleft())
        while pending:
            yield self.ray.get(pending.popleft())

    def evaluate_configs(
        self,
        map_path: str | Path,
        configs: Sequence[LocalizerConfig],
        queries: Sequence[PosedImage],
        pairs: dict[str, list[str]] | None = None,
        progress: Callable[[int, int], None] | None = None,
        *,
        gravity: dict[str, np.ndarray] | None = None,
    ) -> list[list[QueryResult]]:
        """Like :func:`planarloc.evaluation.queries.evaluate_configs`, with one actor per CPU."""
        from ray.util import ActorPool

        actor = self.ray.remote(num_cpus=1)(_QueryEvaluator)
        n = max(1, min(self.num_cpus, len(queries)))
        actors = [actor.remote(str(Path(map_path).resolve()), list(configs)) for _ in range(n)]
        out: list[list[QueryResult]] = [[] for _ in configs]
        try:
            for i, per_config in enumerate(
                ActorPool(actors).map(
                    lambda a, q: a.evaluate.remote(
                        q, pairs, None if gravity is None else gravity.get(q.name)
                    ),
                    list(queries),
                )
            ):
                for results, r in zip(out, per_config):
                    results.append(r)
                if progress:
                    progress(i + 1, len(queries))
        finally:
            for a in actors:  # free their CPUs now, not when garbage collected
                self.ray.kill(a)
        return out

    def evaluate(
        self,
        map_path: str | Path,
        config: LocalizerConfig,
        queries: Sequence[PosedImage],
        pairs: dict[str, list[str]] | None = None,
        progress: Callable[[int, int], None] | None = None,
        *,
        gravity: dict[str, np.ndarray] | None = None,
    ) -> list[QueryResult]:
        """Localize every query on the cluster and compare with its ground truth."""
        return self.evaluate_configs(map_path, [config], queries, pairs, progress, gravity=gravity)[0]


@contextmanager
def ray_session(address: str | None) -> Iterator[RayBackend | None]:
    """A :class:`RayBackend` for the CLI's ``--ray [ADDRESS]``, or None when the option was not given."""
    if address is None:
        yield None
        return
    with RayBackend(address) as backend:
        yield backend
