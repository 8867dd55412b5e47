"""The localization service over HTTP (optional extra ``planarloc[serve]``; Ray Serve: ``planarloc[ray]``).

:mod:`~planarloc.serve.requests` validates requests and sorts errors into the client's (4xx) and
the server's (500), :mod:`~planarloc.serve.form` reads their multipart forms as they stream in
(limits for every transfer encoding, body timeout, upload budget), :mod:`~planarloc.serve.worker`
does the CPU work in worker processes, :mod:`~planarloc.serve.worker_pool` bounds and schedules it
and watches the processes, :mod:`~planarloc.serve.sessions` keeps one stream per robot,
:mod:`~planarloc.serve.map_watch` refuses maps changed on disk, :mod:`~planarloc.serve.metrics`
counts it all and :mod:`~planarloc.serve.app` is the FastAPI app of ``planarloc serve``;
:mod:`~planarloc.serve.ray_serve` deploys the same API on Ray Serve. The service never imports the
CLI: it builds the same :class:`~planarloc.localize.localizer.LocalizerConfig` with
:func:`~planarloc.localize.localizer.localizer_config` and writes the same records.
"""
