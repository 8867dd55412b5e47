"""Calibration: planarloc's default localizer next to an hloc-style pipeline, same splits, same run
(issue 30).

Per data set, both pipelines localize every query of the same map / query split:

- **planarloc**: the default :class:`~planarloc.localize.localizer.Localizer` (``method="auto"``, its
  default structure mode, VLAD top-5 retrieval, no query gravity) on a map built from the map images
  (cached, ``_datasets.py``).
- **colmap-peer** (hloc's recipe, ``_colmap_peer.py``): planarloc's own feature extraction (OpenCV
  SIFT, RootSIFT descriptors, 4,000 features, images over 1600 px downscaled: the settings of hloc's
  ``sift`` configuration), extracted in full precision for the map images (not the map's compact
  copy) and shared with planarloc for the query; a COLMAP triangulation of the map images at their
  known poses (``pycolmap.triangulate_points``, poses fixed; map pairs: each map image with its 5
  nearest by centre, all pairs for maps of <= 12 images; mutual NN + ratio 0.8, known-pose epipolar
  verification at 4 px); per query, **the same top-5 map images planarloc retrieved**, mutual NN +
  ratio 0.8, 2D-3D correspondences through the triangulated map keypoints and
  ``pycolmap.estimate_and_refine_absolute_pose`` (12 px, hloc's default). A query fails when pycolmap
  returns no pose or fewer than 12 inliers (``--peer-min-inliers``).

Printed per data set and pipeline: queries, success at 0.25 m / 2° and 0.25 m / 10°, median position
error of the successes, successes beyond 1 m, time per query (features + retrieval + matching +
estimation, each pipeline's own; the maps' build times are printed apart) and the failures by status;
the calibration of the position standard deviation over the successes: median error / std (a
calibrated Gaussian gives about 1), share within 3 std + 5 cm, and the median std. For planarloc the
std is its ``position_std_m``; for the peer it is what its 2D-3D data alone say (pycolmap's pose
covariance scaled by the inliers' RMS reprojection error, the map points taken as exact:
``_colmap_peer.absolute_pose``), a reference, not a promise the peer makes. A second table
gives, per data set, the quantiles of error / std of planarloc's successes; ``--list-successes``
prints each success (data set, query, error, std, ratio, inliers); the galleries' queries are always
printed one by one (``--per-query``: every data set's).

Data sets: the names of ``trust.py`` (its loaders and splits: ``kitti-every4`` = map every 4th frame of
``kitti_seq2``, queries the rest; ``kitti1-*`` = ``kitti_seq1``; ``fountain_p11`` / ``entry_p10``: map
= even frames, queries = odd; the generated ``office-tilt*-pitch*``, ``pitched``, ``offplane``; the
cross-session ``fountain-to-entry``) and two generated two-session galleries (1600x1200 images,
f = 1200 px, rooms of textured walls and posters, perfect map poses, queries from another session
0.5 m to the side and 0.3 m lower): ``gallery`` (a 10 x 7 m room, 32 map frames about 0.5 m apart,
12 queries) and ``gallery-sparse`` (a 24 x 16 x 5 m hall, 10 map frames about 5 m apart, 6 queries).

    python benchmarks/calibration.py --quick                      # <= 2 minutes: self-check, 3 small sets
    python benchmarks/calibration.py --json calib.json            # the default data sets
    python benchmarks/calibration.py --datasets gallery kitti-every4 --list-successes
    python benchmarks/calibration.py --self-check                 # the pycolmap conventions only

``--self-check`` (also run first by ``--quick``) checks on noise-free synthetic data that the pose
conversions and ``pycolmap.estimate_and_refine_absolute_pose`` return the true ``cam_from_world`` to
1e-9, and that the whole peer (triangulation from posed map images + 2D-3D localization) returns it
to 1e-6 m (COLMAP stores keypoints as float32); the exit code is 1 when it fails, else 0.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _colmap_peer as colmap_peer  # noqa: E402
import _datasets as cache  # noqa: E402
import _peer_pipeline as peer  # noqa: E402
import trust  # noqa: E402

from planarloc.features.extract import Features, extract_features  # noqa: E402
from planarloc.features.images import read_gray  # noqa: E402
from planarloc.geometry.camera import Camera  # noqa: E402
from planarloc.geometry.pose import Pose, pose_errors  # noqa: E402
from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.localize.localizer import Localizer  # noqa: E402
from planarloc.map.posed_image import PosedImage  # noqa: E402
from planarloc.map.store import MapDatabase  # noqa: E402
from planarloc.synthetic.world.config import (  # noqa: E402
    CameraConfig,
    EffectsConfig,
    SceneConfig,
    TrajectoryConfig,
    WorldConfig,
)

DATA_ROOT = trust.DATA_ROOT
GALLERY, SPARSE_GALLERY = "gallery", "gallery-sparse"
GALLERY_FRAMES = (32, 12)
SPARSE_GALLERY_FRAMES = (10, 6)
WORLD_SEED = 0
DEFAULT_DATASETS = [
    "kitti-every4",
    "kitti-every2",
    "kitti1-every4",
    "kitti1-every2",
    "fountain_p11",
    "entry_p10",
    "office-tilt0-pitch0",
    "office-tilt1-pitch10",
    "pitched",
    GALLERY,
    SPARSE_GALLERY,
]
QUICK_DATASETS = ["fountain_p11", "entry_p10", "kitti-every4"]
THRESHOLDS = ((0.25, 2.0), (0.25, 10.0))
BEYOND_M = 1.0
PROMISE_SIGMAS, PROMISE_MARGIN_M = cache.PROMISE_SIGMAS, cache.PROMISE_MARGIN_M
PIPELINES = ("planarloc", "colmap-peer")
RATIO_QUANTILES = (0.1, 0.5, 0.9)


# ---- data sets ------------------------------------------------------------------------------------
def _two_session_hall(
    name: str, scene: SceneConfig, wall_margin: float, n_map: int, n_query: int
) -> WorldConfig:
    """A generated two-session world: 1600 x 1200 images at f = 1200, perfect map poses on a loop
    ``wall_margin`` from the walls, queries of another session passing 0.5 m to the side and
    0.3 m lower (with 1 px of image noise)."""
    return WorldConfig(
        name=name,
        camera=CameraConfig(width=1600, height=1200, fx=1200.0, fy=1200.0),
        scene=scene,
        trajectory=TrajectoryConfig(
            shape="loop",
            n_map=n_map,
            n_query=n_query,
            camera_height=1.2,
            wall_margin=wall_margin,
            lateral_offset=0.5,
            yaw_offset_deg=10.0,
            yaw_wobble_deg=5.0,
            query_height_drop=0.3,
        ),
        map_effects=EffectsConfig(),
        query_effects=EffectsConfig(noise_sigma=1.0),
    )


def gallery_config(n_map: int = GALLERY_FRAMES[0], n_query: int = GALLERY_FRAMES[1]) -> WorldConfig:
    """The two-session gallery: a 10 x 7 x 3 m room of textured walls with 24 posters."""
    scene = SceneConfig(
        kind="room", size_x=10.0, size_z=7.0, height=3.0, n_boxes=4, n_posters=24, px_per_m=300.0
    )
    return _two_session_hall(GALLERY, scene, 1.8, n_map, n_query)


def sparse_gallery_config(
    n_map: int = SPARSE_GALLERY_FRAMES[0], n_query: int = SPARSE_GALLERY_FRAMES[1]
) -> WorldConfig:
    """The gallery with deep views and wide baselines: a 24 x 16 x 5 m hall, 10 map images about
    5 m apart on a loop 4 m from the walls, 6 queries of another session."""
    scene = SceneConfig(
        kind="room", size_x=24.0, size_z=16.0, height=5.0, n_boxes=4, n_posters=40, px_per_m=150.0
    )
    return _two_session_hall(SPARSE_GALLERY, scene, 4.0, n_map, n_query)


GALLERIES: dict[str, Callable[[], WorldConfig]] = {
    GALLERY: gallery_config,
    SPARSE_GALLERY: sparse_gallery_config,
}


def dataset_names() -> list[str]:
    return [*trust.dataset_names(), *GALLERIES]


def load_dataset(name: str, args: argparse.Namespace, root: Path) -> trust.DataSet | None:
    """The data set ``name`` with trust.py's loaders and splits, or the gallery (rendered once)."""
    progress = peer.Progress()
    if name in GALLERIES:
        folder = cache.cached_world(
            GALLERIES[name](), WORLD_SEED, root, lambda d, n: progress(f"render {name}", d, n)
        )
        return trust.DataSet(
            name,
            read_dataset(folder / "map", "tum"),
            read_dataset(folder / "query", "tum"),
            None,
            str(folder),
        )
    ns = argparse.Namespace(world_frames=trust.WORLD_FRAMES, data_root=args.data_root)
    return trust.load_dataset(name, ns, root, progress)


# ---- one query, both pipelines ----------------------------------------------------------------------
@dataclass
class _Run:
    """What a worker needs (inherited through fork): the map, the built peer, the queries."""

    map_path: Path
    the_peer: colmap_peer.ColmapPeer
    queries: list[PosedImage]
    localizer: Localizer | None = None


_RUN: _Run | None = None


def _localizer() -> Localizer:
    assert _RUN is not None
    if _RUN.localizer is None:
        _RUN.localizer = Localizer(MapDatabase.open(_RUN.map_path, mode="r"))
        _RUN.localizer.warm_up()
    return _RUN.localizer


def _worker_init(single_thread: bool) -> None:
    if single_thread:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)


def _errors(pose: Pose | None, truth: Pose) -> tuple[float | None, float | None]:
    """(metres, degrees) of ``pose`` against ``truth``; None without a pose (JSON has no NaN)."""
    return tuple(float(v) for v in pose_errors(pose, truth)) if pose is not None else (None, None)


def _finite(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def localize_one(index: int) -> tuple[dict, dict]:
    """(planarloc record, peer record) of query ``index`` of the current run."""
    assert _RUN is not None
    loc, q = _localizer(), _RUN.queries[index]
    t0 = time.perf_counter()
    features = extract_features(read_gray(q.path), loc.features)
    t1 = time.perf_counter()
    refs = loc.retrieve(features)
    t2 = time.perf_counter()
    est = loc.localize_features(features, q.camera, refs)
    t3 = time.perf_counter()
    got = _RUN.the_peer.localize(features, q.camera, refs)
    t4 = time.perf_counter()
    shared = (t1 - t0) + (t2 - t1)  # features and retrieval: both pipelines pay them
    err = _errors(est.pose if est.success else None, q.cam_from_world)
    unreliable = (
        _errors(est.unreliable_pose, q.cam_from_world)[0] if est.unreliable_pose is not None else None
    )
    ours = {
        "name": q.name,
        "success": bool(est.success),
        "status": str(est.status),
        "error_m": err[0],
        "error_deg": err[1],
        "std_m": _finite(est.position_std_m),
        "num_inliers": int(est.num_inliers),
        "num_inliers_3d": int(est.num_inliers_3d),
        "model": est.model,
        "seconds": shared + t3 - t2,
        "references": list(refs),
        "used_references": list(est.references),
        "unreliable_error_m": unreliable,
        "map_prior": list(prior) if (prior := getattr(est, "map_prior", None)) is not None else None,
    }
    perr = _errors(got.pose, q.cam_from_world)
    few = got.info.get("pose_with_few_inliers")
    theirs = {
        "name": q.name,
        "success": bool(got.success),
        "status": got.status,
        "error_m": perr[0],
        "error_deg": perr[1],
        "std_m": _finite(got.position_std_m),
        "num_inliers": int(got.num_inliers),
        "num_correspondences": int(got.num_correspondences),
        "seconds": shared + t4 - t3,
        "references": list(refs),
        "reprojection_rms_px": _finite(got.info.get("reprojection_rms_px", np.nan)),
        "few_inliers_error_m": _errors(few, q.cam_from_world)[0] if few is not None else None,
    }
    return ours, theirs


def map_features_extractor(loc_features) -> Callable[[PosedImage], Features]:
    return lambda im: extract_features(read_gray(im.path), loc_features)


def run_dataset(data: trust.DataSet, args: argparse.Namespace, root: Path) -> dict:
    global _RUN
    map_path, build_s = cache.cached_map(data.map_images, data.name, root, progress=peer.Progress())
    loc = Localizer(MapDatabase.open(map_path, mode="r"))
    warm_s = loc.warm_up()
    t0 = time.perf_counter()
    the_peer = colmap_peer.ColmapPeer(
        data.map_images, map_features_extractor(loc.features), min_inliers=args.peer_min_inliers
    ).build()
    peer_build_s = time.perf_counter() - t0
    peer.log(
        f"{data.name}: colmap peer map: {the_peer.model.stats} "
        f"({peer_build_s:.1f} s incl. feature extraction)"
    )
    queries = data.queries[: args.max_queries] if args.max_queries else data.queries
    # a forked worker opens its own map (an sqlite connection must not cross a fork)
    _RUN = _Run(map_path, the_peer, queries, loc if args.jobs == 1 else None)
    progress = peer.Progress()
    rows: list[tuple[dict, dict]] = []
    t0 = time.perf_counter()
    if args.jobs > 1 and len(queries) > 1:
        with ProcessPoolExecutor(
            args.jobs, mp_context=get_context("fork"), initializer=_worker_init, initargs=(True,)
        ) as pool:
            for i, row in enumerate(pool.map(localize_one, range(len(queries)))):
                rows.append(row)
                progress(f"localize {data.name}", i + 1, len(queries))
    else:
        for i in range(len(queries)):
            rows.append(localize_one(i))
            progress(f"localize {data.name}", i + 1, len(queries))
    _RUN = None
    loc.db.close()
    seconds = time.perf_counter() - t0
    peer.log(
        f"{data.name}: {len(data.map_images)} map / {len(queries)} queries, "
        f"planarloc map build {build_s:.0f} s"
        f"{' (cached)' if build_s == 0 else ''}, warm-up {warm_s:.1f} s, peer map {peer_build_s:.1f} s, "
        f"localization {seconds:.0f} s; {peer.load_note()}"
    )
    per_pipeline = {"planarloc": [r[0] for r in rows], "colmap-peer": [r[1] for r in rows]}
    return {
        "dataset": data.name,
        "source": data.source,
        "map_images": len(data.map_images),
        "queries": len(queries),
        "planarloc_map_build_s": build_s,
        "peer_map": the_peer.model.stats,
        "peer_map_build_s": peer_build_s,
        "metrics": {k: metrics(v, with_std=True) for k, v in per_pipeline.items()},
        "per_query": per_pipeline,
    }


# ---- metrics ----------------------------------------------------------------------------------------
def threshold_label(t: float, r: float) -> str:
    return f"{t:g}m/{r:g}°"


def metrics(rows: Sequence[dict], with_std: bool) -> dict:
    """Success, errors and (``with_std``) the calibration of ``std_m`` over one pipeline's records."""
    n = len(rows)
    ok = np.array([r["success"] for r in rows], dtype=bool)
    t = np.array([r["error_m"] for r in rows], dtype=float)
    rot = np.array([r["error_deg"] for r in rows], dtype=float)
    k = int(ok.sum())
    with np.errstate(invalid="ignore"):
        success = {
            threshold_label(tt, rr): 100.0 * float((ok & (t < tt) & (rot < rr)).sum()) / max(n, 1)
            for tt, rr in THRESHOLDS
        }
        out = {
            "queries": n,
            "localized": k,
            "success": success,
            "median_error_m": float(np.median(t[ok])) if k else None,
            "median_error_deg": float(np.median(rot[ok])) if k else None,
            "beyond_1m": int((ok & ~(t <= BEYOND_M)).sum()),
            "failures": dict(Counter(r["status"] for r in rows if not r["success"])),
            "seconds_per_query": float(np.mean([r["seconds"] for r in rows])) if n else None,
        }
        if with_std:
            std = np.array([r["std_m"] for r in rows], dtype=float)
            ratio = t[ok] / std[ok]
            out["median_error_over_std"] = float(np.median(ratio)) if k else None
            out["error_over_std_quantiles"] = (
                (
                    {f"p{int(100 * p)}": float(np.quantile(ratio, p)) for p in RATIO_QUANTILES}
                    | {"max": float(ratio.max())}
                )
                if k
                else None
            )
            kept = t <= PROMISE_SIGMAS * std + PROMISE_MARGIN_M  # NaN (no std): broken
            out["within_3std_5cm"] = 100.0 * float((kept & ok).sum()) / k if k else None
            out["median_std_m"] = float(np.median(std[ok])) if k else None
            out["broken_promises"] = [
                r["name"] for r, o, w in zip(rows, ok, kept, strict=True) if o and not w
            ]
    return out


# ---- output ------------------------------------------------------------------------------------------
HEADERS = [
    "data",
    "pipeline",
    "queries",
    *[f"≤ {threshold_label(t, r)}" for t, r in THRESHOLDS],
    "median err [m]",
    "> 1 m",
    "median err/σ",
    "≤ 3σ+5cm",
    "median σ [m]",
    "failures",
    "s/query",
]


def table_rows(result: dict) -> list[list[str]]:
    out = []
    for who in PIPELINES:
        m = result["metrics"][who]
        failures = ", ".join(f"{k} {v}" for k, v in sorted(m["failures"].items())) or "-"
        out.append(
            [
                result["dataset"],
                who,
                str(m["queries"]),
                *[peer.fmt_pct(v) for v in m["success"].values()],
                peer.fmt_num(m["median_error_m"], 4),
                str(m["beyond_1m"]),
                peer.fmt_num(m["median_error_over_std"], 3),
                peer.fmt_pct(m["within_3std_5cm"]),
                peer.fmt_num(m["median_std_m"], 4),
                failures,
                peer.fmt_num(m["seconds_per_query"], 2),
            ]
        )
    return out


RATIO_HEADERS = [
    "data",
    "successes",
    "err/σ p10",
    "p50",
    "p90",
    "max",
    "median err [m]",
    "median σ [m]",
    "broken promises",
    "peer map: points",
    "track",
    "reproj [px]",
    "build [s]",
]


def ratio_row(result: dict) -> list[str]:
    m, pm = result["metrics"]["planarloc"], result["peer_map"]
    q = m["error_over_std_quantiles"] or {}
    return [
        result["dataset"],
        str(m["localized"]),
        *[peer.fmt_num(q.get(k), 3) for k in ("p10", "p50", "p90", "max")],
        peer.fmt_num(m["median_error_m"], 4),
        peer.fmt_num(m["median_std_m"], 4),
        str(len(m["broken_promises"])),
        str(pm["points3D"]),
        peer.fmt_num(pm["mean_track_length"], 2),
        peer.fmt_num(pm["mean_reprojection_error_px"], 2),
        peer.fmt_num(result["peer_map_build_s"], 1),
    ]


def query_lines(result: dict) -> list[str]:
    """Both pipelines' outcome for every query of one data set."""
    lines = []
    for ours, theirs in zip(
        result["per_query"]["planarloc"], result["per_query"]["colmap-peer"], strict=True
    ):
        extra = (
            f", unreliable pose {ours['unreliable_error_m']:.3f} m off"
            if ours["unreliable_error_m"] is not None
            else ""
        )
        lines.append(
            f"  {result['dataset']} {ours['name']}: planarloc {ours['status']} ({ours['model'] or '-'}), "
            f"err {_fmt(ours['error_m'])} m / {_fmt(ours['error_deg'], 2)}°, "
            f"std {_fmt(ours['std_m'])} m, "
            f"inliers {ours['num_inliers']} 2D-2D / {ours['num_inliers_3d']} 2D-3D{extra} | peer "
            f"{theirs['status']}, err {_fmt(theirs['error_m'])} m / {_fmt(theirs['error_deg'], 2)}°, "
            f"{theirs['num_inliers']} of {theirs['num_correspondences']} 2D-3D inliers"
        )
    return lines


def success_lines(result: dict) -> list[str]:
    """One line per planarloc success: data set, query, error, std, error / std."""
    out = []
    for r in result["per_query"]["planarloc"]:
        if r["success"]:
            ratio = r["error_m"] / r["std_m"] if r["std_m"] else None
            out.append(
                f"  {result['dataset']} {r['name']}: err {r['error_m']:.4f} m, "
                f"std {_fmt(r['std_m'], 4)} m, "
                f"err/std {_fmt(ratio)}, inliers {r['num_inliers']} / "
                f"{r['num_inliers_3d']} 3D, model {r['model'] or '-'}"
            )
    return out


def _fmt(v: float | None, digits: int = 3) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"  # None: JSON's missing number


# ---- the self-check ----------------------------------------------------------------------------------
def self_check(verbose: bool = True) -> list[str]:
    """Failures (empty: passed) of the peer's conventions on noise-free synthetic data:
    the Pose <-> Rigid3d round trip and pycolmap's absolute pose to 1e-9, the whole peer
    (triangulation at the given map poses, matching, PnP) to 1e-6 m and 1e-5°."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    camera = Camera("PINHOLE", 640, 480, (500.0, 510.0, 321.0, 239.0))
    points = rng.uniform([-4.0, -2.0, 5.0], [4.0, 2.0, 12.0], size=(600, 3))
    desc = rng.normal(size=(len(points), 128)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)

    def pose(center: Sequence[float], rotvec_deg: Sequence[float]) -> Pose:
        R = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
        return Pose.from_center(R, np.asarray(center, float))

    def observe(p: Pose) -> Features:
        Xc = points @ p.R.T + p.t
        front = Xc[:, 2] > 0.1
        uv = np.full((len(points), 2), -1.0)
        uv[front] = camera.img_from_cam(Xc[front])
        inside = front & np.all((uv >= 0) & (uv < [camera.width, camera.height]), axis=1)
        idx = rng.permutation(np.flatnonzero(inside))
        return Features(uv[idx], desc[idx], np.ones(len(idx), np.float32))

    failures = []
    query = pose([0.3, 0.15, 0.4], [2.0, 9.0, -1.5])
    back = colmap_peer.pose_from_rigid3d(colmap_peer.rigid3d_from_pose(query))
    rigid = colmap_peer.rigid3d_from_pose(query)
    d_conv = max(
        np.abs(back.R - query.R).max(),
        np.abs(back.t - query.t).max(),
        np.abs(np.asarray(rigid.matrix()) - query.matrix).max(),
    )
    if not d_conv < 1e-9:
        failures.append(f"Pose <-> pycolmap.Rigid3d round trip off by {d_conv:.2e}")
    Xc = points @ query.R.T + query.t
    front = Xc[:, 2] > 0.1
    got = colmap_peer.absolute_pose(camera.img_from_cam(Xc[front]), points[front], camera)
    if got is None:
        failures.append("pycolmap.estimate_and_refine_absolute_pose found no pose on exact data")
    else:
        d_pnp = max(np.abs(got.pose.R - query.R).max(), np.abs(got.pose.t - query.t).max())
        if not d_pnp < 1e-9:
            failures.append(f"pycolmap absolute pose on exact data off by {d_pnp:.2e} (R, t entries)")
    maps = [
        PosedImage(
            f"map/{i}.png",
            Path(f"/nonexistent/map/{i}.png"),
            pose([0.6 * i - 2.0, 0.05 * (i % 3), 0.1 * i], [1.0 * (i % 2), 4.0 * i - 12.0, 0.5]),
            camera,
            i,
        )
        for i in range(7)
    ]
    feats = {m.name: observe(m.cam_from_world) for m in maps}
    the_peer = colmap_peer.split_peer(maps, feats)
    est = the_peer.localize(observe(query), camera, [m.name for m in maps[:5]])
    if not est.success:
        failures.append(f"the peer failed on noise-free data: {est.status}")
    else:
        t_err, r_err = pose_errors(est.pose, query)
        if not (t_err < 1e-6 and r_err < 1e-5):
            failures.append(f"the peer on noise-free data is {t_err:.2e} m / {r_err:.2e}° off")
        if verbose:
            peer.log(
                f"self-check: round trip {d_conv:.1e}, peer end to end {t_err:.1e} m / {r_err:.1e}° "
                f"({est.num_inliers} inliers, map {the_peer.model.stats['points3D']} points, reprojection "
                f"{the_peer.model.stats['mean_reprojection_error_px']:.1e} px)"
            )
    return failures


# ---- main ---------------------------------------------------------------------------------------------
def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    trust.add_datasets_option(p, " ".join(DEFAULT_DATASETS), QUICK_DATASETS, dataset_names())
    p.add_argument("--quick", action="store_true", help="the self-check, then a small subset (<= 2 minutes)")
    p.add_argument(
        "--self-check",
        action="store_true",
        help="only check the pycolmap conventions on synthetic data (exit 1 on failure)",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="worker processes over the queries of a data set (default 1: clean timings)",
    )
    p.add_argument("--max-queries", type=int, help="first N queries of each data set")
    p.add_argument(
        "--peer-min-inliers",
        type=int,
        default=colmap_peer.MIN_INLIERS,
        help="the peer fails below this many PnP inliers (default: %(default)s)",
    )
    p.add_argument(
        "--list-successes", action="store_true", help="print every planarloc success with its error / std"
    )
    p.add_argument("--per-query", action="store_true", help="print both pipelines' outcome for every query")
    cache.add_cache_options(p, DATA_ROOT, "rendered worlds and planarloc maps")
    p.add_argument("--json", type=Path, help="write the metrics and per-query records here")
    args = p.parse_args(argv)
    args.datasets = args.datasets or (QUICK_DATASETS if args.quick else DEFAULT_DATASETS)
    trust.check_datasets(p, args.datasets, dataset_names())
    if args.jobs < 1:
        p.error(f"--jobs: expected >= 1, got {args.jobs}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if not colmap_peer.have_pycolmap():
        print("the peer needs pycolmap: pip install -e '.[bench]'", file=sys.stderr)
        return 2
    t_start = time.perf_counter()
    print(peer.code_note())
    print(f"pycolmap {colmap_peer.pycolmap_version()}; {os.cpu_count()} CPUs, --jobs {args.jobs}")
    print(peer.load_note("at start"))
    if args.self_check or args.quick:
        failures = self_check()
        print(
            peer.verdict(
                not failures,
                "self-check: pycolmap conventions on noise-free data"
                + ("" if not failures else ": " + "; ".join(failures)),
            )
        )
        if failures or args.self_check:
            return 1 if failures else 0
    root = cache.cache_root(args.cache_dir)
    results, skipped = [], []
    for name in args.datasets:
        data = load_dataset(name, args, root)
        if data is None:
            skipped.append(name)
            continue
        result = run_dataset(data, args, root)
        results.append(result)
        peer.log("\n".join("| " + " | ".join(r) + " |" for r in table_rows(result)))
    title = "planarloc (default Localizer) vs the hloc-style COLMAP peer, same splits and top-5 pairs"
    print(peer.markdown_table(HEADERS, [row for r in results for row in table_rows(r)], title))
    print()
    print(
        peer.markdown_table(
            RATIO_HEADERS,
            [ratio_row(r) for r in results],
            "planarloc's successes: error / position_std_m, and the peer's triangulated map",
        )
    )
    for r in results:
        if r["dataset"] in GALLERIES or args.per_query:
            print(f"\nper query, {r['dataset']}:")
            print("\n".join(query_lines(r)))
    if args.list_successes:
        print("\nplanarloc successes:")
        for r in results:
            print("\n".join(success_lines(r)))
    if skipped:
        print(f"skipped (data not found under {args.data_root}): {', '.join(skipped)}")
    seconds = time.perf_counter() - t_start
    print(f"total {seconds:.0f} s; {peer.load_note('at end')}")
    peer.write_json(
        args.json,
        {
            "args": vars(args),
            "code": peer.code_version(),
            "pycolmap": colmap_peer.pycolmap_version(),
            "seconds": seconds,
            "skipped": skipped,
            "peer": {
                "ratio": colmap_peer.RATIO,
                "verify_px": colmap_peer.VERIFY_PX,
                "pnp_px": colmap_peer.PNP_PX,
                "neighbours": colmap_peer.NEIGHBOURS,
                "exhaustive_up_to": colmap_peer.EXHAUSTIVE_UP_TO,
                "min_inliers": args.peer_min_inliers,
            },
            "results": results,
        },
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
