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
      ``unauthorized``, ``worker_died``).
    - ``planarloc_queue_admitted`` / ``planarloc_workers_busy``: gauges read at scrape time.
    - ``planarloc_worker_restarts_total``.
    """

    def __init__(self, pool_state) -> None:  # pool_state: object with admitted, busy, restarts
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
        admitted = prom.Gauge(
            "planarloc_queue_admitted", "requests running or waiting", registry=self.registry
        )
        busy = prom.Gauge("planarloc_workers_busy", "workers running a request", registry=self.registry)
        restarts = prom.Gauge(
            "planarloc_worker_restarts_total", "worker processes replaced after dying", registry=self.registry
        )
        admitted.set_function(lambda: pool_state.admitted)
        busy.set_function(lambda: pool_state.busy)
        restarts.set_function(lambda: pool_state.restarts)
        self._prom = prom

    def observe(self, endpoint: str, code: int, seconds: float) -> None:
        self.requests.labels(endpoint, str(code)).inc()
        self.latency.labels(endpoint).observe(seconds)

    def render(self) -> tuple[bytes, str]:
        """The exposition text and its content type."""
        return self._prom.generate_latest(self.registry), self._prom.CONTENT_TYPE_LATEST
