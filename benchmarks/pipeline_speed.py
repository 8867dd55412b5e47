"""Pipeline speed on this machine: ours and the plain OpenCV + PoseLib way, in the same process.

(a) Map build time per image, without and with tilt augmentation (``build_map``: feature
    extraction + storage, then the VLAD index; the features-only time is reported as well).
(b) Localization time per query, end to end (features + retrieval + matching to 5 map images +
    estimation), per stage from ``PoseEstimate.stats.time_s``; default LocalizerConfig
    (2p1p, structure none) and structure tracks.
(d) 1080p queries: the same queries upscaled to 1920x1080's pixel count (2.07 MP, aspect kept,
    camera scaled alike), localized
    end to end with the default ``FeatureConfig.resize_max`` (detection at 1600 px, keypoints
    mapped back) and with ``resize_max=None`` (full resolution), against the same map.
(c) The peer on the same queries and the same 5 map images our retrieval picked: OpenCV SIFT
    (same max features) + ``cv2.BFMatcher`` knnMatch ratio test (0.8) + PoseLib
    ``estimate_generalized_relative_pose`` with its default options. Map-side peer features
    are extracted beforehand (they are the peer's "map build").

Data: the KITTI sequence (map = even frames, queries = odd) if present, else the generated
``office`` world. One untimed warm-up query first (numba compilation, caches).
Targets: build <= 150 ms per image (no tilt), localize <= 300 ms per query.
The 1-minute load average is printed with every measurement; above 1.5 the timings are
inflated by other jobs and are flagged.

    python benchmarks/pipeline_speed.py --json speed.json
    python benchmarks/pipeline_speed.py --synthetic --queries 10
    python benchmarks/pipeline_speed.py --blas-threads 1     # single-threaded BLAS (see BENCHMARKS.md)
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

# isort: off
import planarloc  # noqa: F401 - first, before numpy: OpenBLAS's idle spin as `planarloc` sets it

# isort: on
import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _peer_pipeline as peer  # noqa: E402

from planarloc.evaluation.queries import split_map_queries  # noqa: E402
from planarloc.features.extract import FeatureConfig, extract_features  # noqa: E402
from planarloc.features.images import read_gray  # noqa: E402
from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.localize.localizer import Localizer, LocalizerConfig  # noqa: E402
from planarloc.map.builder import build_map
from planarloc.map.store import MapDatabase  # noqa: E402
from planarloc.robust.options import RansacOptions  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_seq2"
TARGET_BUILD_MS = 150.0
TARGET_LOCALIZE_MS = 300.0
PEER_RATIO = 0.8
OUR_STAGES = ("features", "retrieval", "matching", "estimation")
ESTIMATION_DETAIL = (
    "structure",
    "problem setup",
    "hypotheses",
    "scoring",
    "local_optimization",
    "refinement",
    "degeneracy_check",
)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--data", type=Path, default=DEFAULT_DATA, help="KITTI sequence folder (default: %(default)s)"
    )
    p.add_argument(
        "--synthetic", action="store_true", help="use the generated office world even if KITTI is present"
    )
    p.add_argument("--queries", type=int, default=12, help="queries to time (default: %(default)s)")
    p.add_argument("--no-tilt", action="store_true", help="skip the (about 3x slower) tilt-augmented build")
    p.add_argument(
        "--work-dir",
        type=Path,
        help="where the generated world is kept (default: a temporary folder); maps are always rebuilt",
    )
    p.add_argument(
        "--blas-threads",
        type=int,
        help="re-run with OPENBLAS_NUM_THREADS / OMP_NUM_THREADS set to N (default: the library's)",
    )
    p.add_argument("--json", type=Path, help="write all timings here")
    return p.parse_args(argv)


BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def reexec_with_blas_threads(n: int, argv: list[str] | None) -> None:
    """BLAS reads its thread count when numpy loads: restart this script with the variables set."""
    env = dict(os.environ)
    if all(env.get(k) == str(n) for k in BLAS_ENV):
        return
    env.update({k: str(n) for k in BLAS_ENV})
    args = sys.argv[1:] if argv is None else argv
    os.execve(sys.executable, [sys.executable, str(Path(__file__).resolve()), *args], env)


def load_data(args: argparse.Namespace, work: Path):
    """(label, map images, query images)."""
    if not args.synthetic and (args.data / "poses.txt").is_file():
        images = read_dataset(args.data, "kitti")
        map_images, queries = split_map_queries(images, 2)
        return f"KITTI {args.data.name} (map every 2)", map_images, queries
    if not args.synthetic:
        peer.log(f"KITTI data not found at {args.data}: using the generated office world")
    from planarloc.synthetic.world.export import generate

    world = generate(
        "office", work / "world-office-seed0", seed=0, progress=lambda d, n: progress("render world", d, n)
    )
    return "generated office world", read_dataset(world / "map", "tum"), read_dataset(world / "query", "tum")


def spread(values: list[float]) -> dict:
    v = np.asarray(values, dtype=float)
    return {
        "median": float(np.median(v)),
        "mean": float(v.mean()),
        "min": float(v.min()),
        "max": float(v.max()),
        "n": len(v),
    }


def time_build(map_images, path: Path, features: FeatureConfig) -> dict:
    """Features-only time per image, then a full build_map (features + storage + VLAD index)."""
    feature_s, feature_cpu = [], []
    for i, im in enumerate(map_images):
        gray = read_gray(im.path)
        t0, c0 = time.perf_counter(), time.process_time()
        extract_features(gray, features)
        feature_s.append(time.perf_counter() - t0)
        feature_cpu.append(time.process_time() - c0)
        progress(f"features only ({'tilt' if features.tilt else 'no tilt'})", i + 1, len(map_images))
    load_before = peer.load_average()
    t0, c0 = time.perf_counter(), time.process_time()
    build_map(map_images, path, features, progress=progress)
    total, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {
        "features": features.name,
        "images": len(map_images),
        "build_seconds": total,
        "build_ms_per_image": 1000 * total / len(map_images),
        "build_cpu_ms_per_image": 1000 * cpu / len(map_images),
        "features_ms_per_image": 1000 * float(np.median(feature_s)),
        "features_cpu_ms_per_image": 1000 * float(np.median(feature_cpu)),
        "load_average": [load_before, peer.load_average()],
    }


def our_stage_times(est) -> dict:
    t = est.stats.time_s
    estimation = t.get("total", 0.0)
    out = {
        "features": t.get("features", 0.0),
        "retrieval": t.get("retrieval", 0.0),
        "matching": t.get("matching", 0.0),
        "estimation": estimation,
        "end_to_end": t["end_to_end"],
    }
    detail = {
        k: t.get(k, 0.0)
        for k in (
            "structure",
            "hypotheses",
            "scoring",
            "local_optimization",
            "refinement",
            "degeneracy_check",
        )
    }
    detail["problem setup"] = t.get("setup", 0.0) - t.get("structure", 0.0)
    out.update({f"estimation/{k}": v for k, v in detail.items()})
    return out


class PeerPipeline:
    """OpenCV SIFT + BFMatcher ratio test + PoseLib generalized relative pose."""

    def __init__(self, max_features: int, map_images) -> None:
        self.sift = peer.opencv_sift(max_features)
        self.matcher = cv2.BFMatcher(cv2.NORM_L2)
        self.posed = {m.name: m for m in map_images}
        self.map_features: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def prepare(self, names) -> None:
        for n in names:
            if n not in self.map_features:
                self.map_features[n] = peer.sift_features(self.sift, read_gray(self.posed[n].path))

    def localize(self, gray: np.ndarray, camera, references) -> tuple[dict, peer.PeerResult]:
        t0 = time.perf_counter()
        kq, dq = peer.sift_features(self.sift, gray)
        t1 = time.perf_counter()
        pairs = []
        for n in references:
            kr, dr = self.map_features[n]
            m = peer.bf_ratio_match(self.matcher, dq, dr, PEER_RATIO)
            p = self.posed[n]
            pairs.append(peer.PeerMatches(p.cam_from_world, p.camera, kq[m[:, 0]], kr[m[:, 1]]))
        t2 = time.perf_counter()
        res = peer.generalized_relative_pose(camera, pairs)
        t3 = time.perf_counter()
        return {
            "features": t1 - t0,
            "retrieval": 0.0,
            "matching": t2 - t1,
            "estimation": t3 - t2,
            "end_to_end": t3 - t0,
        }, res


def time_1080p(map_path: Path, chosen, maps: Path) -> dict:
    """End-to-end localization of the chosen queries upscaled to 1920x1080, default
    ``resize_max`` and full resolution; the first query is a warm-up."""
    out = {}
    with MapDatabase.open(map_path) as db:
        for label, resize in (
            ("resize_max 1600 (default)", FeatureConfig().resize_max),
            ("full resolution", None),
        ):
            loc = Localizer(db, LocalizerConfig())
            loc.features = dataclasses.replace(loc.features, resize_max=resize)
            feats, ends, cpus, ok = [], [], [], 0
            for i, q in enumerate(chosen):
                gray = read_gray(q.path)
                s = np.sqrt(1920 * 1080 / (gray.shape[0] * gray.shape[1]))  # 1080p pixel count, aspect kept
                size = (round(gray.shape[1] * s), round(gray.shape[0] * s))
                sx, sy = size[0] / gray.shape[1], size[1] / gray.shape[0]
                big = cv2.resize(gray, size, interpolation=cv2.INTER_CUBIC)
                c0, t0 = time.process_time(), time.perf_counter()
                est = loc.localize(big, q.camera.scaled(sx, sy))
                wall, cpu = time.perf_counter() - t0, time.process_time() - c0
                if i == 0:
                    continue
                feats.append(our_stage_times(est)["features"])
                ends.append(wall)
                cpus.append(cpu)
                e = peer.errors_of(est.pose if est.success else None, q.cam_from_world)
                ok += int(np.isfinite(e[0]) and e[0] < 0.25 and e[1] < 10)
                progress(f"1080p ({label})", i, len(chosen) - 1)
            out[label] = {
                "features": float(np.median(feats)),
                "end_to_end": float(np.median(ends)),
                "end_to_end_cpu": float(np.median(cpus)),
                "success": ok,
                "queries": len(ends),
            }
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.blas_threads is not None:
        reexec_with_blas_threads(args.blas_threads, argv)
    t_start = time.perf_counter()
    tmp = tempfile.TemporaryDirectory(prefix="planarloc-speed-")
    work = args.work_dir or Path(tmp.name)
    work.mkdir(parents=True, exist_ok=True)
    report: dict = {"code": peer.code_version(), "load_average_start": peer.load_average()}
    try:
        label, map_images, queries = load_data(args, work)
        h, w = read_gray(map_images[0].path).shape
        threads = {k: os.environ.get(k) for k in BLAS_ENV if os.environ.get(k)}
        peer.print_header(
            f"# Pipeline speed: {label}, {len(map_images)} map images, {w}x{h}; {args.queries} queries "
            f"(+1 warm-up); OpenCV {cv2.__version__}, PoseLib {peer.poselib_version() or 'not installed'}",
            f"threads: OpenCV {cv2.getNumThreads()}, BLAS "
            f"{', '.join(f'{k}={v}' for k, v in threads.items()) or 'library default'}",
        )
        report.update(
            {
                "data": label,
                "image_size": [w, h],
                "thread_env": threads,
                "opencv_threads": cv2.getNumThreads(),
            }
        )
        maps = Path(tmp.name)

        # (a) map build
        builds = []
        for tilt in [False] if args.no_tilt else [False, True]:
            features = FeatureConfig(tilt=tilt)
            builds.append(time_build(map_images, maps / f"speed-{features.name}.db", features))
        rows = [
            [
                b["features"],
                b["images"],
                f"{b['features_ms_per_image']:.0f}",
                f"{b['build_ms_per_image']:.0f}",
                f"{b['features_cpu_ms_per_image']:.0f}",
                f"{b['build_cpu_ms_per_image']:.0f}",
                f"{b['load_average'][0][0]:.2f} → {b['load_average'][1][0]:.2f}",
            ]
            for b in builds
        ]
        print()
        print(
            peer.markdown_table(
                [
                    "features",
                    "images",
                    "features only [ms/image]",
                    "build_map [ms/image]",
                    "features only, CPU [ms/image]",
                    "build_map, CPU [ms/image]",
                    "load (1 min)",
                ],
                rows,
                "(a) Map build time per image (wall clock; CPU = process time, all threads)",
            )
        )
        report["build"] = builds

        # (b) ours, (c) peer, same queries and references
        step = max(1, len(queries) // max(args.queries + 1, 1))
        chosen = queries[::step][: args.queries + 1]
        plain = maps / f"speed-{FeatureConfig().name}.db"
        have_peer = peer.have_poselib()
        with MapDatabase.open(plain) as db:
            locs = {
                s: Localizer(db, LocalizerConfig(ransac=RansacOptions(structure=s)))
                for s in ("none", "tracks")
            }
            pipe = PeerPipeline(FeatureConfig().max_features, map_images)
            times: dict[str, list[dict]] = {"ours none": [], "ours tracks": [], "peer": []}
            errors: dict[str, list] = {k: [] for k in times}
            load_before = peer.load_average()
            for i, q in enumerate(chosen):
                gray = read_gray(q.path)
                ests = {}
                cpu = {}
                for s, loc in locs.items():
                    c0 = time.process_time()
                    ests[s] = loc.localize(gray, q.camera)
                    cpu[f"ours {s}"] = time.process_time() - c0
                refs = ests["none"].references  # the map images our pipeline used
                if have_peer:
                    pipe.prepare(refs)
                    c0 = time.process_time()
                    pt, pres = pipe.localize(gray, q.camera, refs)
                    cpu["peer"] = time.process_time() - c0
                if i == 0:
                    continue  # warm-up
                for s, est in ests.items():
                    times[f"ours {s}"].append({**our_stage_times(est), "end_to_end_cpu": cpu[f"ours {s}"]})
                    errors[f"ours {s}"].append(
                        peer.errors_of(est.pose if est.success else None, q.cam_from_world)
                    )
                if have_peer:
                    times["peer"].append({**pt, "end_to_end_cpu": cpu["peer"]})
                    errors["peer"].append(peer.errors_of(pres.pose, q.cam_from_world))
                progress("localize (ours x2 + peer)", i, len(chosen) - 1)
            load_after = peer.load_average()
        if not have_peer:
            del times["peer"], errors["peer"]
            peer.log("poselib is not installed (pip install -e '.[bench]'): no peer timings")

        med = {
            k: {stage: float(np.median([t[stage] for t in v])) for stage in v[0]} for k, v in times.items()
        }
        stages = [*OUR_STAGES, "end_to_end", "end_to_end_cpu"]
        headers = ["stage", *[f"{k} [ms]" for k in times]]
        if have_peer:
            headers += ["ours none / peer", "ours tracks / peer"]
        rows = []
        for st in stages:
            row = [st.replace("_", " ").replace(" cpu", ", CPU time")] + [
                f"{1000 * med[k][st]:.1f}" for k in times
            ]
            if have_peer:
                for k in ("ours none", "ours tracks"):
                    row.append("-" if med["peer"][st] == 0 else f"{med[k][st] / med['peer'][st]:.2f}")
            rows.append(row)
        print()
        print(
            peer.markdown_table(
                headers,
                rows,
                f"(b, c) Localization time per query, median of {len(chosen) - 1} "
                f"queries (5 map images each)",
            )
        )
        detail_rows = [
            [f"estimation: {d}"]
            + [f"{1000 * med[k][f'estimation/{d}']:.1f}" for k in ("ours none", "ours tracks")]
            for d in ESTIMATION_DETAIL
        ]
        print()
        print(
            peer.markdown_table(
                ["stage", "ours none [ms]", "ours tracks [ms]"],
                detail_rows,
                "Estimation broken down (median ms per query)",
            )
        )
        acc_rows = []
        for k, errs in errors.items():
            e = np.array(errs, dtype=float)
            ok = np.isfinite(e[:, 0])
            acc_rows.append(
                [
                    k,
                    f"{int(ok.sum())}/{len(e)}",
                    f"{int(((e[:, 0] < 0.25) & (e[:, 1] < 10)).sum())}/{len(e)}",
                    peer.fmt_num(float(np.median(e[ok, 0])) if ok.any() else None),
                ]
            )
        print()
        print(
            peer.markdown_table(
                ["pipeline", "pose returned", "within 0.25 m/10°", "median t [m]"],
                acc_rows,
                "Accuracy on the timed queries (context only)",
            )
        )
        print(f"load average during localization: {load_before[0]:.2f} → {load_after[0]:.2f} (1 min)")
        report["localize"] = {
            "queries": [q.name for q in chosen[1:]],
            "median_seconds": med,
            "per_query_seconds": times,
            "errors": errors,
            "load_average": [load_before, load_after],
        }

        report["localize_1080p"] = hd = time_1080p(plain, chosen, maps)
        rows = [
            [
                k,
                f"{1000 * v['features']:.0f}",
                f"{1000 * v['end_to_end']:.0f}",
                f"{1000 * v['end_to_end_cpu']:.0f}",
                f"{v['success']}/{v['queries']}",
            ]
            for k, v in hd.items()
        ]
        print()
        print(
            peer.markdown_table(
                [
                    "2.07 MP query",
                    "features [ms]",
                    "end to end [ms]",
                    "end to end, CPU [ms]",
                    "within 0.25 m/10°",
                ],
                rows,
                "(d) 1080p-sized queries (2.07 MP, upscaled, camera scaled), median per query",
            )
        )

        print()
        print("## Targets")
        b0 = builds[0]["build_ms_per_image"]
        loc_ms = 1000 * med["ours none"]["end_to_end"]
        verdicts = [
            (
                b0 <= TARGET_BUILD_MS,
                f"map build {b0:.0f} ms/image without tilt (target <= {TARGET_BUILD_MS:g})",
            ),
            (
                loc_ms <= TARGET_LOCALIZE_MS,
                f"localize {loc_ms:.0f} ms/query end to end, default config (target <= "
                f"{TARGET_LOCALIZE_MS:g})",
            ),
        ]
        for ok, text in verdicts:
            print(peer.verdict(ok, text))
        report["targets"] = [{"pass": ok, "target": text} for ok, text in verdicts]
        print(peer.load_note("at end"))
        if max(load_before[0], load_after[0], report["load_average_start"][0]) > peer.LOAD_WARNING:
            print(
                f"WARNING: the machine was loaded (1-min load > {peer.LOAD_WARNING} on {os.cpu_count()} "
                "CPUs) during the measurement; re-run on an idle machine before quoting these numbers"
            )
    finally:
        tmp.cleanup()
    report["seconds"] = time.perf_counter() - t_start
    report["load_average_end"] = peer.load_average()
    peer.write_json(args.json, report)
    return 0


progress = peer.Progress()

if __name__ == "__main__":
    sys.exit(main())
