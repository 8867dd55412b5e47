"""Running planarloc on a cluster (optional extra ``planarloc[ray]``): :mod:`~planarloc.distributed.ray_backend`
for map building and evaluation, :mod:`~planarloc.distributed.ray_serve` for a fleet-facing deployment."""
