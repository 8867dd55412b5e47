"""Evaluate localization against ground truth: the paper's success thresholds (Sec. V-B).

A query succeeds at ``(τ_t, τ_R)`` when the estimator returned a pose (``success``) whose
camera centre is within ``τ_t`` metres and whose rotation is within ``τ_R`` degrees of the
ground truth. A failed query is a failure at every threshold — it is never replaced by the
nearest map pose.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from planarloc.geometry.pose import pose_errors
from planarloc.geometry.validation import InputError
from planarloc.pipeline.localizer import Localizer, LocalizerConfig
from planarloc.pipeline.map_builder import read_gray
from planarloc.pipeline.map_database import MapDatabase, MapFormatError
from planarloc.pipeline.posed_image import PosedImage
from planarloc.robust.result import PoseEstimate

THRESHOLDS: tuple[tuple[float, float], ...] = ((0.25, 10.0), (0.5, 10.0), (1.0, 20.0))


def threshold_name(t: float, r: float) -> str:
    return f"{t:g}m/{r:g}deg"


@dataclass(frozen=True)
class QueryResult:
    """Outcome of one query: errors are NaN when no pose was returned."""

    name: str
    status: str
    success: bool
    translation_error_m: float
    rotation_error_deg: float
    position_std_m: float
    num_inliers: int
    num_inliers_3d: int
    seconds: float
    estimate_center: tuple[float, float, float] | None
    truth_center: tuple[float, float, float]
    reason: str = ""  # why a query could not be processed (status "error"), e.g. unreadable image


def split_map_queries(images: Sequence[PosedImage], map_every: int) -> tuple[list[PosedImage], list[PosedImage]]:
    """Map = frames with ``index % map_every == 0``, queries = the others (the issues' protocol)."""
    if map_every < 2:
        raise ValueError(f"map_every must be >= 2 (otherwise there are no queries), got {map_every}")
    return [i for i in images if i.index % map_every == 0], [i for i in images if i.index % map_every != 0]


def query_result(query: PosedImage, est: PoseEstimate, seconds: float) -> QueryResult:
    if est.success and est.pose is not None:
        t_err, r_err = pose_errors(est.pose, query.cam_from_world)
        c = tuple(float(v) for v in est.pose.center)
    else:
        t_err, r_err, c = float("nan"), float("nan"), None
    return QueryResult(query.name, est.status, bool(est.success), t_err, r_err, float(est.position_std_m),
                       int(est.num_inliers), int(est.num_inliers_3d), seconds, c,
                       tuple(float(v) for v in query.cam_from_world.center))


def _error_result(query: PosedImage, seconds: float, reason: str) -> QueryResult:
    """A query that could not be processed: failed, status ``"error"``, with the reason."""
    nan = float("nan")
    return QueryResult(query.name, "error", False, nan, nan, nan, 0, 0, seconds, None,
                       tuple(float(v) for v in query.cam_from_world.center), reason)


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
        "per_query": [asdict(r) for r in results],
    }


def evaluate_queries(
    localizer: Localizer,
    queries: Sequence[PosedImage],
    progress: Callable[[int, int], None] | None = None,
    pairs: dict[str, list[str]] | None = None,
) -> list[QueryResult]:
    """Localize every query image and compare with its ground truth."""
    return evaluate_configs(localizer.db, [localizer.config], queries, progress, pairs)[0]


def evaluate_configs(
    map_db: MapDatabase,
    configs: Sequence[LocalizerConfig],
    queries: Sequence[PosedImage],
    progress: Callable[[int, int], None] | None = None,
    pairs: dict[str, list[str]] | None = None,
) -> list[list[QueryResult]]:
    """Localize every query with each configuration, extracting its features only once.

    Returns:
        one list of :class:`QueryResult` per configuration. ``seconds`` of a result is the
        feature extraction time plus that configuration's retrieval, matching and estimation.
    """
    from planarloc.pipeline.features import extract_features
    from planarloc.pipeline.retrieval import retrieve_from_pairs

    localizers = [Localizer(map_db, c) for c in configs]
    out: list[list[QueryResult]] = [[] for _ in configs]
    for i, q in enumerate(queries):
        t0 = time.perf_counter()
        # One bad query (unreadable, wrong size, not in the pairs file) is a failed query with its
        # reason and the batch goes on; a damaged map stops it (it would fail every query).
        try:
            image = read_gray(q.path)
            if image.shape[:2] != (q.camera.height, q.camera.width):
                raise InputError(f"{q.path}: image is {image.shape[1]}x{image.shape[0]} but its camera is "
                                 f"{q.camera.width}x{q.camera.height}")
            features = extract_features(image, localizers[0].features)
        except MapFormatError:
            raise
        except InputError as exc:
            for results in out:
                results.append(_error_result(q, time.perf_counter() - t0, str(exc)))
            if progress:
                progress(i + 1, len(queries))
            continue
        t_feat = time.perf_counter() - t0
        for loc, results in zip(localizers, out):
            t1 = time.perf_counter()
            try:
                refs = retrieve_from_pairs(pairs, q.name, loc.config.top_n) if pairs is not None else None
                est = loc.localize_features(features, q.camera, refs)
            except MapFormatError:
                raise
            except InputError as exc:
                results.append(_error_result(q, t_feat + time.perf_counter() - t1, str(exc)))
                continue
            results.append(query_result(q, est, t_feat + time.perf_counter() - t1))
        if progress:
            progress(i + 1, len(queries))
    return out


def config_label(config: LocalizerConfig) -> tuple[str, str]:
    method = getattr(config.method, "value", config.method)
    structure = getattr(config.ransac.structure, "value", config.ransac.structure)
    return str(method), str(structure)


def default_map_path(dataset_root: Path, map_every: int, feature_name: str,
                     map_images: Sequence[PosedImage] = (), settings: str = "") -> Path:
    """Where `evaluate` caches the map it builds: next to nothing the user owns.

    The key covers the map images' content as far as it is cheap to know — names, file paths
    and sizes, poses, cameras — and ``settings`` (e.g. the vocabulary size): a dataset whose
    poses were edited gets a new map instead of a stale one. (Changed image bytes of the same
    size are caught by the build itself, which compares SHA-256 hashes.)
    """
    import hashlib
    import os
    import tempfile

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
    return Path(tempfile.gettempdir()) / "planarloc-maps" / f"{Path(dataset_root).name}-every{map_every}-{key}.db"
