"""Running planarloc on a cluster (optional extra ``planarloc[ray]``).

:mod:`~planarloc.distributed.ray_backend`: map building and evaluation on Ray;
:mod:`~planarloc.distributed.ray_serve`: a fleet-facing Ray Serve deployment of the localizer.
"""
