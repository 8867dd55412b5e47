"""Prometheus metrics of the service (``GET /metrics``), in a registry of their own per app."""

from __future__ import annotations

from planarloc.extras import require

#: Latency buckets (seconds): a localization takes ~0.05-2 s; queueing can add more.
LATENCY_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)


class ServiceMetrics:
    """Counters and histograms of one service instance.

    - ``planarloc_requests_total{endpoint, code}``: HTTP responses by route and status code.
    - ``planarloc_request_seconds{endpoint}``: latency histogram.
    - ``planarloc_localize_total{status}``: localization outcomes (``success``, ``too_few_matches``...).
    - ``planarloc_rejected_total{reason}``: requests refused (``overloaded``, ``bad_request``,
      ``too_large``, ``timeout``, ``unauthorized``, ``worker_died``, ``map_changed``,
      ``session_gone``, ``server_fault``).
    - ``planarloc_queue_admitted`` / ``planarloc_workers_busy`` / ``planarloc_workers_alive``: gauges
      read at scrape time (``workers_alive`` asks the processes then, as ``/healthz`` does).
    - ``planarloc_workers_as_python``: workers answering as Python (slower) because the kernel
      cache was empty and the compile they share still runs (0 once it has ended).
    - ``planarloc_worker_restarts_total``, ``planarloc_worker_deaths_total``.
    - ``planarloc_map_ok{map}``: 1 while the map file is the version the server started with, 0
      once it was deleted, replaced or modified (checked at scrape time).
    - ``planarloc_sessions`` (open) and ``planarloc_sessions_evicted_total{reason}`` (``idle``,
      ``limit``, ``worker_died``, ``fault``).
    """

    def __init__(self, service) -> None:  # service: planarloc.serve.app.Service (pool, watch, sessions)
        prom = require("prometheus_client", "serve")
        prom.disable_created_metrics()  # no *_created series: counters and histograms only
        self.registry = prom.CollectorRegistry()
        self.requests = prom.Counter(
            "planarloc_requests", "HTTP responses", ["endpoint", "code"], registry=self.registry
        )
        self.latency = prom.Histogram(
            "planarloc_request_seconds",
            "request latency",
            ["endpoint"],
            buckets=LATENCY_BUCKETS,
            registry=self.registry,
        )
        self.outcomes = prom.Counter(
            "planarloc_localize", "localization outcomes", ["status"], registry=self.registry
        )
        self.rejected = prom.Counter(
            "planarloc_rejected", "refused requests", ["reason"], registry=self.registry
        )
        pool, watch, sessions = service.pool, service.watch, service.sessions
        gauges = {
            "planarloc_queue_admitted": ("requests running or waiting", lambda: pool.admitted),
            "planarloc_workers_busy": ("workers running a request", lambda: pool.busy),
            "planarloc_workers_alive": (
                "worker processes alive with their maps open",
                lambda: sum(pool.alive()),
            ),
            "planarloc_workers_as_python": (
                "workers running their kernels as Python while the shared compile runs",
                pool.as_python,
            ),
            "planarloc_worker_restarts_total": (
                "worker processes replaced after dying",
                lambda: pool.restarts,
            ),
            "planarloc_worker_deaths_total": ("worker processes that died", lambda: pool.deaths),
            "planarloc_sessions": ("open sessions", lambda: sessions.count),
        }
        for name, (doc, fn) in gauges.items():
            prom.Gauge(name, doc, registry=self.registry).set_function(fn)
        map_ok = prom.Gauge(
            "planarloc_map_ok", "1 while the map file is the version served", ["map"], registry=self.registry
        )
        for name in watch.paths:
            map_ok.labels(name).set_function(lambda name=name: float(watch.check(name) is None))
        evicted = prom.Gauge(
            "planarloc_sessions_evicted_total", "sessions evicted or lost", ["reason"], registry=self.registry
        )
        for reason in ("idle", "limit", "worker_died", "fault"):
            evicted.labels(reason).set_function(lambda reason=reason: sessions.evicted.get(reason, 0))
        self._prom = prom

    def observe(self, endpoint: str, code: int, seconds: float) -> None:
        self.requests.labels(endpoint, str(code)).inc()
        self.latency.labels(endpoint).observe(seconds)

    def render(self) -> tuple[bytes, str]:
        """The exposition text and its content type."""
        return self._prom.generate_latest(self.registry), self._prom.CONTENT_TYPE_LATEST
