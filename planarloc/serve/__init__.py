"""The localization service over HTTP (optional extra ``planarloc[serve]``; Ray Serve: ``planarloc[ray]``).

:mod:`~planarloc.serve.requests` validates requests, :mod:`~planarloc.serve.form` reads their
multipart forms, :mod:`~planarloc.serve.worker` does the CPU work in worker processes,
:mod:`~planarloc.serve.worker_pool` bounds and schedules it, :mod:`~planarloc.serve.metrics` counts
it and :mod:`~planarloc.serve.app` is the FastAPI app of ``planarloc serve``;
:mod:`~planarloc.serve.ray_serve` deploys the same API on Ray Serve. The service never imports the
CLI: it builds the same :class:`~planarloc.localize.localizer.LocalizerConfig` with
:func:`~planarloc.localize.localizer.localizer_config` and writes the same records.
"""
