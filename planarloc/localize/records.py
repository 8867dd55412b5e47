"""Per-query localization records: the JSON `planarloc localize` writes for each query and
`planarloc serve` returns for each request (one function, so both are identical).

Schema: ``{"name": <query name>, **PoseEstimate.to_dict()}`` — ``success``, ``status``,
``message``, ``num_inliers``, ..., and for a returned pose ``quat_wxyz`` (w, x, y, z) and ``t``
of ``cam_from_world`` (x_cam = R·x_world + t).
"""

from __future__ import annotations

from planarloc.robust.result import PoseEstimate


def query_record(name: str, estimate: PoseEstimate, gravity: object | None = None) -> dict:
    """The JSON-serialisable record of one localized (or failed) query; ``query_gravity`` is the
    gravity prior it was given (None: assumed mounted like the map cameras)."""
    g = None if gravity is None else [float(v) for v in gravity]
    return {"name": name, **estimate.to_dict(), "query_gravity": g}


def query_record_filename(name: str) -> str:
    """File name of a query's record inside a ``--json-dir`` (sub-folders flattened with ``__``)."""
    return name.replace("/", "__") + ".json"
