"""The localization service (``planarloc serve``, optional extra ``planarloc[serve]``).

:mod:`~planarloc.serve.requests` validates requests, :mod:`~planarloc.serve.worker` does the CPU
work in worker processes, :mod:`~planarloc.serve.worker_pool` bounds and schedules it,
:mod:`~planarloc.serve.metrics` counts it and :mod:`~planarloc.serve.app` is the FastAPI app.
"""
