"""Running map building and evaluation on a Ray cluster (optional extra ``planarloc[ray]``):
:mod:`~planarloc.distributed.ray_backend`. The fleet-facing Ray Serve deployment of the service
is :mod:`planarloc.serve.ray_serve`."""
