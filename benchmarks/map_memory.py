"""Map memory: a 1,000-image map opens and serves queries in at most 1 GB.

1. Builds a synthetic map quickly, without images: ``MapDatabase.create`` + ``add_image`` with
   random RootSIFT-like features (4000 per image: non-negative, L1-normalised then square-rooted,
   so every row has unit L2 norm, as RootSIFT), posed along a random planar trajectory
   (yaw + x-z translation, camera height fixed), PINHOLE 640x480 cameras; then
   :func:`planarloc.map.builder.index_map` (VLAD vocabulary + global descriptors).
2. In a FRESH subprocess: opens the map with ``Localizer`` and localizes a few queries made
   from map images' features (keypoints moved by 1 px noise, descriptors perturbed and
   re-normalised) with ``localize_features`` — the pose result does not matter here, the
   work does (retrieval, matching against 5 map images of 4000 features, estimation).
   Reports the subprocess's peak RSS (``ru_maxrss``) and the time to open.

    python benchmarks/map_memory.py                       # 1000 images, temporary map
    python benchmarks/map_memory.py --map /tmp/m1000.db   # keep the map and reuse it next time
    python benchmarks/map_memory.py --storage full        # the layout of maps before compact ones
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _peer_pipeline as peer  # noqa: E402

from planarloc.map.codec import DEFAULT_STORAGE, STORAGE_LAYOUTS  # noqa: E402

LIMIT_GB = 1.0
CAMERA = ("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--images", type=int, default=1000, help="map images (default: %(default)s)")
    p.add_argument("--features", type=int, default=4000, help="features per image (default: %(default)s)")
    p.add_argument(
        "--queries", type=int, default=5, help="queries served by the subprocess (default: %(default)s)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the random map (default: %(default)s)")
    p.add_argument(
        "--storage",
        choices=STORAGE_LAYOUTS,
        default=DEFAULT_STORAGE,
        help="storage layout of the map (planarloc.map.codec; default: %(default)s)",
    )
    p.add_argument(
        "--map",
        type=Path,
        help="map file to build, or to reuse if it is complete with the same size (default: temporary)",
    )
    p.add_argument("--json", type=Path, help="write the measurements here")
    p.add_argument("--child", type=Path, help=argparse.SUPPRESS)  # internal: the fresh process
    return p.parse_args(argv)


# ---- the synthetic map ------------------------------------------------------------------------------
def rootsift_like(rng: np.random.Generator, n: int, dim: int = 128) -> np.ndarray:
    """(n, dim) float32 rows like RootSIFT: sqrt of an L1-normalised sparse non-negative histogram."""
    h = rng.random((n, dim), dtype=np.float32)
    h *= h  # skew towards small values, as SIFT histograms
    h *= h
    h /= h.sum(axis=1, keepdims=True)
    np.sqrt(h, out=h)
    h /= np.linalg.norm(h, axis=1, keepdims=True)  # already ~1; exact to float32 precision
    return h


def planar_trajectory(rng: np.random.Generator, n: int, step_m: float = 0.5):
    """``cam_from_world`` poses of a random planar walk: y down, camera 1 m above the floor (y = -1)."""
    from planarloc.geometry.pose import Pose

    yaw, c = 0.0, np.array([0.0, -1.0, 0.0])
    poses = []
    for _ in range(n):
        yaw += rng.normal(0.0, 0.15)
        R = np.array([[np.cos(yaw), 0.0, -np.sin(yaw)], [0.0, 1.0, 0.0], [np.sin(yaw), 0.0, np.cos(yaw)]])
        poses.append(Pose.from_center(R, c))
        c = c + step_m * R.T @ np.array([0.0, 0.0, 1.0])  # move along the viewing direction
    return poses


def build_random_map(
    path: Path, num_images: int, num_features: int, seed: int, storage: str = DEFAULT_STORAGE
) -> dict:
    from planarloc.features.extract import FeatureConfig, Features
    from planarloc.geometry.camera import Camera
    from planarloc.map.builder import index_map
    from planarloc.map.posed_image import PosedImage
    from planarloc.map.store import MapDatabase

    rng = np.random.default_rng(seed)
    camera = Camera(*CAMERA)
    features_cfg = FeatureConfig(max_features=num_features)
    # The same config layout as build_map writes, so the Localizer reads the feature settings back.
    config = {
        "features": dataclasses.asdict(features_cfg),
        "feature_name": features_cfg.name,
        "retrieval": {"type": "vlad", "num_words": 64},
        "synthetic": "benchmarks/map_memory.py",
    }
    t0 = time.perf_counter()
    with MapDatabase.create(path, config, overwrite=True, storage=storage) as db:
        for i, pose in enumerate(planar_trajectory(rng, num_images)):
            kp = rng.random((num_features, 2), dtype=np.float32) * np.float32([CAMERA[1], CAMERA[2]])
            scales = rng.uniform(2.0, 30.0, num_features).astype(np.float32)
            f = Features(kp, rootsift_like(rng, num_features), scales)
            db.add_image(
                PosedImage(f"synthetic/{i:06d}.png", Path(f"synthetic/{i:06d}.png"), pose, camera, i), f
            )
            progress("add images", i + 1, num_images)
        t1 = time.perf_counter()
        index_map(db, progress=progress)
        db.mark_complete()
    t2 = time.perf_counter()
    return {"add_images_seconds": t1 - t0, "index_seconds": t2 - t1}


def map_is_reusable(path: Path, num_images: int, storage: str = DEFAULT_STORAGE) -> bool:
    from planarloc.map.store import MapDatabase

    if not path.is_file():
        return False
    try:
        with MapDatabase.open(path) as db:
            return (
                db.is_complete
                and db.num_images() == num_images
                and "synthetic" in db.config
                and db.storage == storage
            )
    except Exception:  # noqa: BLE001 - anything unreadable is rebuilt
        return False


# ---- the fresh process ---------------------------------------------------------------------------------
def rss_mb(field: str) -> float:
    """VmRSS / VmHWM of this process from /proc (Linux), in MB; NaN elsewhere."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def child(map_path: Path, num_queries: int, seed: int) -> int:
    """Open the map, serve queries, print one JSON line with the measurements."""
    out: dict = {}
    from planarloc.features.extract import Features
    from planarloc.localize.localizer import Localizer

    out["rss_after_imports_mb"] = rss_mb("VmRSS")
    t0 = time.perf_counter()
    loc = Localizer(map_path)
    out["open_seconds"] = time.perf_counter() - t0
    out["rss_after_open_mb"] = rss_mb("VmRSS")
    rng = np.random.default_rng(seed + 1)
    names = loc.db.image_names()
    queries = []
    for k, i in enumerate(rng.choice(len(names) - 1, num_queries, replace=False)):
        # Half of the features of map image i and half of image i + 1, perturbed: two references
        # get matches, so retrieval, matching and the robust estimator all run.
        a, b = loc.db.get_features(names[i]), loc.db.get_features(names[i + 1])
        half = len(a) // 2
        kp = np.concatenate([a.keypoints[:half], b.keypoints[half:]])
        d = np.concatenate([a.descriptors[:half], b.descriptors[half:]])
        d = np.abs(d + rng.normal(0.0, 0.003, d.shape).astype(np.float32))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        feats = Features(
            kp + rng.normal(0.0, 1.0, kp.shape).astype(np.float32),
            d,
            np.concatenate([a.scales[:half], b.scales[half:]]),
        )
        camera = loc.db.get_camera(names[i])
        t1 = time.perf_counter()
        est = loc.localize_features(feats, camera)
        queries.append(
            {
                "source": names[i],
                "seconds": time.perf_counter() - t1,
                "status": est.status,
                "references": est.references,
                "source_retrieved": names[i] in est.references,
                "time_s": dict(est.stats.time_s),
            }
        )
        print(
            f"  query {k + 1}/{num_queries}: {est.status}, {queries[-1]['seconds']:.2f} s",
            file=sys.stderr,
            flush=True,
        )
    out["queries"] = queries
    out["rss_end_mb"] = rss_mb("VmRSS")
    out["vm_hwm_mb"] = rss_mb("VmHWM")
    out["ru_maxrss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB
    print(json.dumps(out))
    return 0


# ---- driver -----------------------------------------------------------------------------------------------
def child_command(script: str, path: Path, args: argparse.Namespace, *options: str) -> list[str]:
    """The command of the fresh process that opens the map at ``path`` (``script``'s ``--child``)."""
    return [
        sys.executable,
        str(Path(script).resolve()),
        "--child",
        str(path),
        "--queries",
        str(args.queries),
        *options,
        "--seed",
        str(args.seed),
    ]


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.child is not None:
        return child(args.child, args.queries, args.seed)
    t_start = time.perf_counter()
    peer.print_header(
        f"# Map memory: {args.images} images x {args.features} random RootSIFT-like features, "
        f"{args.storage} storage, {args.queries} queries in a fresh process"
    )
    tmp = None if args.map else tempfile.TemporaryDirectory(prefix="planarloc-memory-")
    path = args.map or Path(tmp.name) / f"random-{args.images}.db"
    report: dict = {
        "images": args.images,
        "features_per_image": args.features,
        "storage": args.storage,
        "code": peer.code_version(),
        "load_average_start": peer.load_average(),
    }
    try:
        if map_is_reusable(path, args.images, args.storage):
            peer.log(f"reusing {path}")
            report["build"] = None
        else:
            report["build"] = build_random_map(path, args.images, args.features, args.seed, args.storage)
        size_mb = sum(p.stat().st_size for p in path.parent.glob(path.name + "*")) / 2**20
        report["map_file_mb"] = size_mb
        peer.log("opening the map in a fresh process")
        cmd = child_command(__file__, path, args)
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
        if proc.returncode != 0:
            print(f"the subprocess failed with exit code {proc.returncode}: {' '.join(cmd)}")
            return proc.returncode
        res = json.loads(proc.stdout.strip().splitlines()[-1])
        report["child"] = res
        load = peer.load_average()
    finally:
        if tmp is not None:
            tmp.cleanup()
    b = report["build"]
    q_s = [q["seconds"] for q in res["queries"]]
    rows = [
        [
            "map file",
            f"{size_mb:.0f} MB ({args.images} images x {args.features} features, uint8 descriptors)",
        ],
        [
            "build (add images + index_map)",
            "reused" if b is None else f"{b['add_images_seconds']:.0f} s + {b['index_seconds']:.0f} s",
        ],
        ["open (Localizer(map))", f"{res['open_seconds']:.2f} s"],
        ["query (localize_features, 5 map images)", f"median {np.median(q_s):.2f} s (n = {len(q_s)})"],
        ["query statuses", ", ".join(sorted({q["status"] for q in res["queries"]}))],
        [
            "source image among the retrieved",
            f"{sum(q['source_retrieved'] for q in res['queries'])}/{len(q_s)}",
        ],
        ["RSS after imports", f"{res['rss_after_imports_mb']:.0f} MB"],
        ["RSS after open", f"{res['rss_after_open_mb']:.0f} MB"],
        ["RSS after the queries", f"{res['rss_end_mb']:.0f} MB"],
        ["peak RSS (ru_maxrss)", f"{res['ru_maxrss_mb']:.0f} MB"],
    ]
    print()
    print(peer.markdown_table(["measure", "value"], rows, "Serving a 1,000-image map from a fresh process"))
    print(f"{peer.load_note()}")
    peak_gb = res["ru_maxrss_mb"] / 1024.0
    ok = peak_gb <= LIMIT_GB
    report["target"] = {"pass": ok, "peak_rss_gb": peak_gb, "limit_gb": LIMIT_GB}
    print()
    print("## Target")
    print(
        peer.verdict(
            ok,
            f"peak RSS {res['ru_maxrss_mb']:.0f} MB = {peak_gb:.2f} GB of the process that opens "
            f"the {args.images}-image map and serves {len(q_s)} queries (limit {LIMIT_GB:g} GB)",
        )
    )
    report["seconds"] = time.perf_counter() - t_start
    report["load_average_end"] = load
    peer.write_json(args.json, report)
    return 0


progress = peer.Progress()

if __name__ == "__main__":
    sys.exit(main())
