"""Evaluate localization against ground truth: the paper's success thresholds (Sec. V-B).

A query succeeds at ``(τ_t, τ_R)`` when the estimator returned a pose (``success``) whose
camera centre is within ``τ_t`` metres and whose rotation is within ``τ_R`` degrees of the
ground truth. A failed query is a failure at every threshold — it is never replaced by the
nearest map pose.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from planarloc.features.extract import Features, extract_features
from planarloc.features.retrieval import retrieve_from_pairs
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.geometry.validation import InputError
from planarloc.gravity.world import gravity_in_camera
from planarloc.localize.localizer import Localizer, LocalizerConfig
from planarloc.localize.records import error_record, query_record
from planarloc.map.posed_image import PosedImage
from planarloc.map.schema import MapFormatError
from planarloc.map.settings import cache_dir
from planarloc.map.store import MapDatabase
from planarloc.robust.options import parse_method, parse_structure
from planarloc.robust.result import PoseEstimate

#: ``on_estimate(localizer, query, features, estimate)`` callback of :func:`evaluate_configs`.
OnEstimate = Callable[[Localizer, PosedImage, Features, PoseEstimate], None]
THRESHOLDS: tuple[tuple[float, float], ...] = ((0.25, 10.0), (0.5, 10.0), (1.0, 20.0))
#: the schema of :func:`summarize`'s JSON (``docs/schema/evaluation.schema.json``)
SCHEMA = "planarloc.evaluation/1"


def threshold_name(t: float, r: float) -> str:
    return f"{t:g}m/{r:g}deg"


def center_tuple(center: np.ndarray) -> tuple[float, float, float]:
    """A (3,) camera centre as a tuple of Python floats (a result's field)."""
    return float(center[0]), float(center[1]), float(center[2])


def quat_wxyz_tuple(quat_wxyz: np.ndarray) -> tuple[float, float, float, float]:
    """A (4,) quaternion (w, x, y, z) as a tuple of Python floats (a result's field)."""
    return float(quat_wxyz[0]), float(quat_wxyz[1]), float(quat_wxyz[2]), float(quat_wxyz[3])


@dataclass(frozen=True)
class QueryResult:
    """Outcome of one query: errors are NaN when no pose was returned.

    Poses are ``cam_from_world``: ``*_quat_wxyz`` its rotation, ``*_center`` the camera centre
    in the world. ``references``: the map images whose matches reached the estimator.
    ``timestamp``: the query's, in seconds (None if its format has none).
    """

    name: str
    status: str
    success: bool
    translation_error_m: float
    rotation_error_deg: float
    position_std_m: float  # the estimate's std along its worst axis
    num_inliers: int  # 2D-2D inlier matches
    num_inliers_3d: int  # 2D-3D inlier constraints (tracks / depth)
    seconds: float  # wall time of features, retrieval, matching and estimation
    estimate_center: tuple[float, float, float] | None
    truth_center: tuple[float, float, float]
    timestamp: float | None = None
    estimate_quat_wxyz: tuple[float, float, float, float] | None = None
    truth_quat_wxyz: tuple[float, float, float, float] | None = None
    references: tuple[str, ...] = ()
    #: why a query failed: the estimator's message, or why it could not be processed (status "error")
    reason: str = ""
    #: the query's fix record (:func:`planarloc.localize.records.query_record`), as ``localize`` writes it
    record: dict = field(default_factory=dict, compare=False, repr=False)

    def to_dict(self) -> dict:
        """The evaluation's entry of this query: its fix record (docs/schema/record.schema.json)
        with the ground truth (``truth_quat_wxyz``, ``truth_center``), the errors (null without
        a pose) and ``seconds``."""
        return {
            **with_truth(self),
            "seconds": self.seconds,
        }


def with_truth(entry: Any) -> dict:
    """The record of an evaluated query or frame ``entry`` (its ``record``) with its evaluation
    (docs/schema/record.schema.json, "evaluation_fields"): the true ``cam_from_world`` rotation and
    centre (``truth_quat_wxyz``, ``truth_center``) and the errors (``translation_error_m``,
    ``rotation_error_deg``: NaN without a pose, ``null`` once written)."""
    return {
        **entry.record,
        "truth_quat_wxyz": None if entry.truth_quat_wxyz is None else list(entry.truth_quat_wxyz),
        "truth_center": list(entry.truth_center),
        "translation_error_m": entry.translation_error_m,
        "rotation_error_deg": entry.rotation_error_deg,
    }


def split_map_queries(
    images: Sequence[PosedImage], map_every: int
) -> tuple[list[PosedImage], list[PosedImage]]:
    """Map = frames with ``index % map_every == 0``, queries = the others (the issues' protocol)."""
    if map_every < 2:
        raise ValueError(f"map_every must be >= 2 (otherwise there are no queries), got {map_every}")
    return [i for i in images if i.index % map_every == 0], [i for i in images if i.index % map_every != 0]


class PoseComparison(NamedTuple):
    """An estimate against the truth: its errors (NaN without an estimate) and its centre and
    rotation as written to the records (None without)."""

    translation_error_m: float
    rotation_error_deg: float
    center: tuple[float, float, float] | None
    quat_wxyz: tuple[float, float, float, float] | None


def compared(pose: Pose | None, truth: Pose) -> PoseComparison:
    """:class:`PoseComparison` of the estimated ``pose`` (None: no pose) with ``truth``."""
    if pose is None:
        return PoseComparison(float("nan"), float("nan"), None, None)
    t_err, r_err = pose_errors(pose, truth)
    return PoseComparison(t_err, r_err, center_tuple(pose.center), quat_wxyz_tuple(pose.quat_wxyz))


def query_result(
    query: PosedImage, est: PoseEstimate, seconds: float, gravity: Iterable[float] | None = None
) -> QueryResult:
    cmp = compared(est.pose if est.success else None, query.cam_from_world)
    return QueryResult(
        query.name,
        est.status,
        bool(est.success),
        cmp.translation_error_m,
        cmp.rotation_error_deg,
        float(est.position_std_m),
        int(est.num_inliers),
        int(est.num_inliers_3d),
        seconds,
        cmp.center,
        center_tuple(query.cam_from_world.center),
        query.timestamp,
        cmp.quat_wxyz,
        quat_wxyz_tuple(query.cam_from_world.quat_wxyz),
        tuple(est.references),
        reason="" if est.success else est.message,
        record=query_record(query.name, est, gravity, stamp=query.timestamp),
    )


def _error_result(query: PosedImage, seconds: float, reason: str) -> QueryResult:
    """A query that could not be processed: failed, status ``"error"``, with the reason."""
    nan = float("nan")
    return QueryResult(
        query.name,
        "error",
        False,
        nan,
        nan,
        nan,
        0,
        0,
        seconds,
        None,
        center_tuple(query.cam_from_world.center),
        query.timestamp,
        None,
        quat_wxyz_tuple(query.cam_from_world.quat_wxyz),
        reason=reason,
        record=error_record(query.name, reason, stamp=query.timestamp, seconds=seconds),
    )


def summarize(results: Sequence[QueryResult], method: str, structure: str, **extra: object) -> dict:
    """The evaluation JSON: success rates (percent) at the paper's thresholds, median errors of
    the localized queries, failures and time per query."""
    n = len(results)
    t = np.array([r.translation_error_m for r in results], dtype=float)
    rot = np.array([r.rotation_error_deg for r in results], dtype=float)
    ok = np.array([r.success for r in results], dtype=bool)
    success = {}
    for tt, rr in THRESHOLDS:
        hit = ok & (t < tt) & (rot < rr)
        success[threshold_name(tt, rr)] = 100.0 * float(hit.sum()) / max(n, 1)
    statuses: dict[str, int] = {}
    for r in results:
        statuses[r.status] = statuses.get(r.status, 0) + 1
    return {
        "schema": SCHEMA,
        "method": method,
        "structure": structure,
        "queries": n,
        "success": success,
        "localized": int(ok.sum()),
        "median_translation_error_m": float(np.median(t[ok])) if ok.any() else None,
        "median_rotation_error_deg": float(np.median(rot[ok])) if ok.any() else None,
        "failed_queries": int((~ok).sum()),
        "status_counts": statuses,
        "seconds_per_query": float(np.mean([r.seconds for r in results])) if n else None,
        **extra,
        "per_query": [r.to_dict() for r in results],
    }


def gravity_from_truth(queries: Sequence[PosedImage], g_world: object | None = None) -> dict[str, np.ndarray]:
    """A simulated IMU: each query's true gravity in its camera frame, ``R_gt · world_down``.

    Args:
        queries: posed query images (ground truth in the map's world frame).
        g_world: (3,) down direction for queries whose dataset declares none (e.g. the map's
            estimated gravity); None: such queries get no gravity.

    Returns:
        ``{query name: (3,) unit gravity (down) in the query camera frame}``: the declared
        ``world_down`` (generated worlds, KITTI, OpenLORIS, ``up=``) where there is one, else
        ``g_world``.
    """
    out = {}
    for q in queries:
        down: object | None = q.world_down.direction if q.world_down is not None else None
        down = g_world if down is None else down
        if down is not None:
            out[q.name] = gravity_in_camera(q.cam_from_world, down)
    return out


def evaluate_queries(
    localizer: Localizer,
    queries: Sequence[PosedImage],
    progress: Callable[[int, int], None] | None = None,
    pairs: dict[str, list[str]] | None = None,
    on_estimate: OnEstimate | None = None,
    *,
    gravity: dict[str, np.ndarray] | None = None,
) -> list[QueryResult]:
    """Localize every query image and compare with its ground truth (``on_estimate``, ``gravity``:
    see :func:`evaluate_configs`)."""
    return evaluate_configs(
        localizer, [localizer.config], queries, progress, pairs, on_estimate, gravity=gravity
    )[0]


def evaluate_configs(
    map_db: MapDatabase | Localizer,
    configs: Sequence[LocalizerConfig],
    queries: Sequence[PosedImage],
    progress: Callable[[int, int], None] | None = None,
    pairs: dict[str, list[str]] | None = None,
    on_estimate: OnEstimate | None = None,
    *,
    gravity: dict[str, np.ndarray] | None = None,
) -> list[list[QueryResult]]:
    """Localize every query with each configuration, extracting its features only once.

    ``on_estimate(localizer, query, features, estimate)``, if given, is called after each
    estimate (plots, recordings); it does not count in ``seconds``. ``gravity`` optionally gives
    queries their (3,) gravity in the camera frame (``{query name: g}``, e.g.
    :func:`gravity_from_truth`); the others get None (mounted like the map cameras).

    Returns:
        one list of :class:`QueryResult` per configuration. ``seconds`` of a result is the
        feature extraction time plus that configuration's retrieval, matching and estimation.
    """
    base = map_db if isinstance(map_db, Localizer) else Localizer(map_db, configs[0])
    localizers = [base.with_config(c) for c in configs]  # one open map and index for all
    out: list[list[QueryResult]] = [[] for _ in configs]
    for i, q in enumerate(queries):
        for results, r in zip(
            out,
            evaluate_query(
                localizers, q, pairs, on_estimate, gravity=None if gravity is None else gravity.get(q.name)
            ),
        ):
            results.append(r)
        if progress:
            progress(i + 1, len(queries))
    return out


def evaluate_query(
    localizers: Sequence[Localizer],
    query: PosedImage,
    pairs: dict[str, list[str]] | None = None,
    on_estimate: OnEstimate | None = None,
    *,
    gravity: np.ndarray | None = None,
) -> list[QueryResult]:
    """Localize one query with each localizer (same map), extracting its features once
    (``on_estimate`` and ``gravity``: see :func:`evaluate_configs`, here for this query).

    One bad query (unreadable, wrong size, not in the pairs file) is a failed query with its
    reason (status ``error``) and the batch goes on; a damaged map raises (it would fail every
    query).
    """
    t0 = time.perf_counter()
    try:
        prepared = localizers[0].prepare(query.path, query.camera, name=query.name, gravity=gravity)
        features = extract_features(prepared.image, localizers[0].features)
    except MapFormatError:
        raise
    except InputError as exc:
        return [_error_result(query, time.perf_counter() - t0, str(exc)) for _ in localizers]
    t_feat = time.perf_counter() - t0
    results = []
    for loc in localizers:
        t1 = time.perf_counter()
        try:
            refs = retrieve_from_pairs(pairs, query.name, loc.config.top_n) if pairs is not None else None
            est = loc.localize_features(features, query.camera, refs, gravity=prepared.gravity)
        except MapFormatError:
            raise
        except InputError as exc:
            results.append(_error_result(query, t_feat + time.perf_counter() - t1, str(exc)))
            continue
        results.append(query_result(query, est, t_feat + time.perf_counter() - t1, prepared.gravity))
        if on_estimate is not None:
            on_estimate(loc, query, features, est)
    return results


def config_label(config: LocalizerConfig) -> tuple[str, str]:
    """``(method, structure)`` of ``config`` as their names (``("auto", "tracks")``)."""
    # The configuration holds the members (its __post_init__ parses); the fields' types also admit a name.
    return parse_method(config.method).value, parse_structure(config.ransac.structure).value


def default_map_path(
    dataset_root: Path,
    map_every: int,
    feature_name: str,
    map_images: Sequence[PosedImage] = (),
    settings: str = "",
) -> Path:
    """Where `evaluate` caches the map it builds: next to nothing the user owns.

    The key covers the map images' content as far as it is cheap to know — names, file paths
    and sizes, poses, cameras — and ``settings`` (e.g. the vocabulary size): a dataset whose
    poses were edited gets a new map instead of a stale one. (Changed image bytes of the same
    size are caught by the build itself, which compares SHA-256 hashes.)
    """
    import hashlib
    import os

    h = hashlib.sha1(f"{Path(dataset_root).resolve()}|{map_every}|{feature_name}|{settings}".encode())
    for im in map_images:
        try:
            size = os.stat(im.path).st_size
        except OSError:
            size = -1
        pose = im.cam_from_world
        h.update(f"|{im.name}|{Path(im.path).absolute()}|{size}|{im.camera}".encode())
        h.update(np.concatenate([pose.R.ravel(), pose.t]).astype("<f8").tobytes())
    key = h.hexdigest()[:12]
    return cache_dir("maps") / f"{Path(dataset_root).name}-every{map_every}-{key}.db"
