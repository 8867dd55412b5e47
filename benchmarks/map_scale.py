"""Building scale: maps of 1,000 to 20,000 images — open time, retrieval time, memory, Ray builds.

1. For each size N (``--sizes``), builds a map through the real store and builder functions:
   ``MapDatabase.create`` (default, compact storage) + ``add_image`` with generated RootSIFT-like
   features (``--features`` per image, like KITTI's ~1450) along a random planar walk
   (benchmarks/map_memory.py's builder), then :func:`planarloc.map.builder.index_map` (VLAD
   vocabulary, global descriptors: projected on a 512-D basis above 2,048 images) and
   ``mark_complete``. Maps are kept in ``--dir`` and reused when complete.
2. In a FRESH process per size: ``Localizer(map)`` (timed: the open), then ``--queries`` queries
   made from map images' features (half of image i and half of image i + 1, perturbed) go
   through ``Localizer.retrieve`` (timed: VLAD of the query + the search, and the search alone);
   ``--serve`` of them are localized end to end (``localize_features``: retrieval, matching to 5
   map images, estimation) while the process' peak RSS is recorded (kernels compiled ahead).
3. Map-build throughput with ``--ray`` on a local Ray instance with 1 CPU against 2 (``build_map``
   with ``RayBackend(num_cpus=...)``), the same images also built with local threads (the peer in
   the same run): KITTI frames of ``--ray-data`` (benchmarks may read ``../shared``; skipped if
   absent or ``--no-ray``).

Targets at the largest size: open ≤ 2 s, retrieval ≤ 10 ms per query, RSS ≤ 1 GB.

    python benchmarks/map_scale.py --json scale.json                         # 1,000, 5,000, 20,000 images
    python benchmarks/map_scale.py --sizes 1000 --no-ray                     # quick
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _peer_pipeline as peer  # noqa: E402
from map_memory import build_random_map, child_command, map_is_reusable, rss_mb  # noqa: E402

TARGET_OPEN_S, TARGET_RETRIEVAL_MS, TARGET_RSS_GB = 2.0, 10.0, 1.0
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--sizes", type=int, nargs="+", default=[1000, 5000, 20000], help="map sizes (default: %(default)s)"
    )
    p.add_argument("--features", type=int, default=1500, help="features per image (default: %(default)s)")
    p.add_argument(
        "--queries", type=int, default=50, help="retrieval queries per size (default: %(default)s)"
    )
    p.add_argument("--serve", type=int, default=5, help="of them localized end to end (default: %(default)s)")
    p.add_argument("--dir", type=Path, help="keep the maps here and reuse them (default: temporary)")
    p.add_argument(
        "--ray-data",
        type=Path,
        nargs="+",
        default=[SHARED / "kitti_seq1", SHARED / "kitti_seq2"],
        help="KITTI sequences whose frames the Ray builds extract (default: ../shared/data/kitti_seq1, 2)",
    )
    p.add_argument("--no-ray", action="store_true", help="skip the Ray build throughput")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", type=Path, help="write the measurements here")
    p.add_argument("--child", type=Path, help=argparse.SUPPRESS)  # internal: the fresh process
    return p.parse_args(argv)


# ---- building ---------------------------------------------------------------------------------------
def reusable(path: Path, num_images: int, num_features: int) -> bool:
    """A complete generated map of this size and feature count (map_memory.py's builder)."""
    from planarloc.map.store import MapDatabase

    if not map_is_reusable(path, num_images):
        return False
    with MapDatabase.open(path) as db:
        return db.config["features"]["max_features"] == num_features


# ---- the fresh process ------------------------------------------------------------------------------
def query_features(loc, name_a: str, name_b: str, rng: np.random.Generator):
    """Half of the features of map image a and half of b, perturbed (1 px, descriptor noise)."""
    from planarloc.features.extract import Features

    a, b = loc.db.get_features(name_a), loc.db.get_features(name_b)
    half = len(a) // 2
    kp = np.concatenate([a.keypoints[:half], b.keypoints[half:]])
    d = np.abs(
        np.concatenate([a.descriptors[:half], b.descriptors[half:]]) + rng.normal(0, 0.003, (len(kp), 128))
    )
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    return Features(
        (kp + rng.normal(0, 1.0, kp.shape)).astype(np.float32),
        d,
        np.concatenate([a.scales[:half], b.scales[half:]]),
    )


def child(map_path: Path, num_queries: int, num_serve: int, seed: int) -> int:
    from planarloc.features.retrieval import vlad_descriptor
    from planarloc.localize.localizer import Localizer

    out: dict = {"rss_after_imports_mb": rss_mb("VmRSS")}
    t0 = time.perf_counter()
    loc = Localizer(map_path)
    out["open_s"] = time.perf_counter() - t0
    out["rss_after_open_mb"] = rss_mb("VmRSS")
    out["projected"] = loc.db.global_basis() is not None
    rng = np.random.default_rng(seed + 1)
    names = loc.db.image_names()
    picks = rng.choice(len(names) - 1, num_queries, replace=False)
    retrieval, search, found = [], [], 0
    camera = loc.db.get_camera(names[0])
    served = []
    for k, i in enumerate(picks):
        feats = query_features(loc, names[i], names[i + 1], rng)
        t1 = time.perf_counter()
        refs = loc.retrieve(feats)
        retrieval.append(time.perf_counter() - t1)
        vlad = vlad_descriptor(loc.vocabulary, feats.descriptors)
        t2 = time.perf_counter()
        loc.index.search(vlad, loc.config.top_n)
        search.append(time.perf_counter() - t2)
        found += names[i] in refs
        if k < num_serve:
            t3 = time.perf_counter()
            est = loc.localize_features(feats, camera)
            served.append({"seconds": time.perf_counter() - t3, "status": est.status})
    out.update(
        retrieval_ms=[1e3 * s for s in retrieval],
        search_ms=[1e3 * s for s in search],
        source_retrieved=found / num_queries,
        served=served,
        rss_end_mb=rss_mb("VmRSS"),
        vm_hwm_mb=rss_mb("VmHWM"),
        ru_maxrss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    )
    print(json.dumps(out))
    return 0


BLAS_ENV = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def measure(path: Path, args: argparse.Namespace, blas_threads: int | None) -> dict:
    """The fresh process' measurements, with BLAS' default threads (None) or ``blas_threads``."""
    cmd = child_command(__file__, path, args, "--serve", str(args.serve))
    env = {k: v for k, v in os.environ.items() if k not in BLAS_ENV}
    if blas_threads is not None:
        env.update({k: str(blas_threads) for k in BLAS_ENV})
    proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"the measuring process failed (exit code {proc.returncode}): {' '.join(cmd)}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# ---- Ray ----------------------------------------------------------------------------------------------
def ray_throughput(data: list[Path], workdir: Path) -> dict | None:
    """Images per second of build_map on the frames of ``data``: threads, Ray with 1 and 2 CPUs."""
    try:
        import ray  # noqa: F401 - only whether it is installed
    except ImportError:
        peer.log("Ray is not installed (pip install 'planarloc[ray]'): skipping the Ray builds")
        return None
    from planarloc.distributed.ray_backend import RayBackend
    from planarloc.io.datasets import read_dataset
    from planarloc.map.builder import build_map

    if not all(d.is_dir() for d in data):
        peer.log(f"no KITTI data at {', '.join(map(str, data))}: skipping the Ray builds")
        return None
    images = []
    for d in data:
        images += [dataclasses.replace(im, name=f"{d.name}/{im.name}") for im in read_dataset(d, "kitti")]
    out: dict = {"images": len(images)}
    runs = [("threads (no Ray)", None), ("ray, 1 CPU", 1), ("ray, 2 CPUs", 2)]
    for label, cpus in runs:
        path = workdir / f"ray-{cpus or 0}.db"
        path.unlink(missing_ok=True)
        peer.log(f"map build of {len(images)} KITTI frames: {label}")
        if cpus is None:
            t0 = time.perf_counter()
            build_map(images, path, progress=progress)
            out[label] = {"seconds": time.perf_counter() - t0}
            continue
        with RayBackend(None, num_cpus=cpus) as backend:
            t0 = time.perf_counter()
            build_map(images, path, progress=progress, mapper=backend.map)
            out[label] = {"seconds": time.perf_counter() - t0}
    for label, _ in runs:
        out[label]["images_per_s"] = len(images) / out[label]["seconds"]
    return out


# ---- driver ------------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.child is not None:
        return child(args.child, args.queries, args.serve, args.seed)
    t_start = time.perf_counter()
    peer.print_header(
        f"# Building scale: maps of {', '.join(f'{n:,}' for n in args.sizes)} generated images x "
        f"{args.features} RootSIFT-like features; {args.queries} queries each in a fresh process"
    )
    from planarloc.cli.warmup_command import compile_ahead
    from planarloc.compile import steps_for
    from planarloc.localize.localizer import LocalizerConfig

    compile_ahead(steps_for([LocalizerConfig()]))  # the measured processes load the kernels, never compile
    tmp = None if args.dir else tempfile.TemporaryDirectory(prefix="planarloc-scale-")
    root = args.dir or Path(tmp.name)
    root.mkdir(parents=True, exist_ok=True)
    report: dict = {
        "features_per_image": args.features,
        "code": peer.code_version(),
        "sizes": {},
        "load_average_start": peer.load_average(),
    }
    try:
        for n in args.sizes:
            path = root / f"scale-{n}-{args.features}.db"
            entry: dict = {}
            if reusable(path, n, args.features):
                peer.log(f"reusing {path}")
            else:
                entry["build"] = build_random_map(path, n, args.features, args.seed)
            entry["map_file_mb"] = path.stat().st_size / 2**20
            peer.log(f"{n} images: measuring in a fresh process")
            entry["child"] = measure(path, args, None)
            entry["child_blas1"] = measure(path, args, 1)  # the peer: one BLAS thread (see BENCHMARKS.md)
            report["sizes"][n] = entry
        report["ray"] = None if args.no_ray else ray_throughput(args.ray_data, root)
    finally:
        if tmp is not None:
            tmp.cleanup()
    rows = []
    for n, e in report["sizes"].items():
        c, c1, b = e["child"], e["child_blas1"], e.get("build")
        rows.append(
            [
                f"{n:,}",
                f"{e['map_file_mb']:.0f} MB ({1024 * e['map_file_mb'] / n:.0f} KB/image)",
                "reused" if b is None else f"{b['add_images_seconds']:.0f} + {b['index_seconds']:.0f} s",
                "512-D projection" if c["projected"] else "8192-D int4",
                f"{c['open_s']:.2f} s",
                f"{np.median(c['retrieval_ms']):.1f} ms ({np.percentile(c['retrieval_ms'], 90):.1f})",
                f"{np.median(c1['retrieval_ms']):.1f} ms ({np.percentile(c1['retrieval_ms'], 90):.1f})",
                f"{np.median(c['search_ms']):.2f} ms",
                f"{100 * c['source_retrieved']:.0f} %",
                f"{np.median([s['seconds'] for s in c['served']]):.2f} s" if c["served"] else "-",
                f"{c['rss_after_open_mb']:.0f} / {c['vm_hwm_mb']:.0f} MB",
            ]
        )
    print()
    print(
        peer.markdown_table(
            [
                "images",
                "map file",
                "build (add + index)",
                "global descriptors",
                "open",
                "retrieval median (p90)",
                "same, 1 BLAS thread",
                "search alone",
                "source retrieved",
                "query end to end",
                "RSS after open / peak",
            ],
            rows,
            "Maps of generated images served from a fresh process",
        )
    )
    ray = report.get("ray")
    if ray:
        print()
        print(
            peer.markdown_table(
                ["build", "seconds", "images/s"],
                [
                    [k, f"{v['seconds']:.1f}", f"{v['images_per_s']:.2f}"]
                    for k, v in ray.items()
                    if isinstance(v, dict)
                ],
                f"Map-build throughput, {ray['images']} KITTI frames",
            )
        )
        print(
            "Ray 2 CPUs / 1 CPU: "
            f"{ray['ray, 2 CPUs']['images_per_s'] / ray['ray, 1 CPU']['images_per_s']:.2f}x"
        )
    report["load_average_end"] = peer.load_average()
    print(peer.load_note())
    largest = report["sizes"][max(report["sizes"])]["child"]
    checks = [
        (
            largest["open_s"] <= TARGET_OPEN_S,
            f"open {largest['open_s']:.2f} s (target ≤ {TARGET_OPEN_S:g} s)",
        ),
        (
            np.median(largest["retrieval_ms"]) <= TARGET_RETRIEVAL_MS,
            f"retrieval {np.median(largest['retrieval_ms']):.1f} ms per query (target ≤ "
            f"{TARGET_RETRIEVAL_MS:g} ms)",
        ),
        (
            largest["vm_hwm_mb"] / 1024 <= TARGET_RSS_GB,
            f"peak RSS {largest['vm_hwm_mb']:.0f} MB while serving (target ≤ {TARGET_RSS_GB:g} GB)",
        ),
    ]
    print()
    print(f"## Targets ({max(report['sizes']):,} images)")
    for ok, text in checks:
        print(peer.verdict(ok, text))
    one = report["sizes"][max(report["sizes"])]["child_blas1"]
    print(
        f"(with one BLAS thread: retrieval {np.median(one['retrieval_ms']):.1f} ms per query, open "
        f"{one['open_s']:.2f} s, peak RSS {one['vm_hwm_mb']:.0f} MB)"
    )
    report["targets"] = [{"pass": ok, "text": text} for ok, text in checks]
    report["seconds"] = time.perf_counter() - t_start
    peer.write_json(args.json, report)
    return 0


progress = peer.Progress()

if __name__ == "__main__":
    sys.exit(main())
