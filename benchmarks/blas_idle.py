"""Feature extraction right after matching, with OpenBLAS's default idle spin and with planarloc's.

OpenBLAS keeps its threads spinning for ``2**OPENBLAS_THREAD_TIMEOUT`` cycles after each call
(default 28, about 0.1 s). A localization matches with BLAS and then extracts the next query's
features with OpenCV's or torch's threads, which then share the cores with spinning ones.
planarloc sets the variable to 20 before numpy loads (:mod:`planarloc.numerics.blas_threads`).

Each setting runs in its own process (OpenBLAS reads the variable once, when it loads), on the
same frames, in the same run; per feature type, mean milliseconds of:

- extraction alone (frames back to back), and right after a query's matching (one query matched
  against 5 other frames, ``match_query_to_refs``, then the timed extraction of the next frame);
- matching alone, and right after an extraction;
- a query, extraction then matching, as a localization does them.

The last column is the default's time over planarloc's. Data: frames of the shared KITTI
``kitti_seq1`` (``--data``) if present, else generated textured images of the same size.

    python benchmarks/blas_idle.py
    python benchmarks/blas_idle.py --features rootsift --timeouts 28 20 4 --json blas_idle.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti_seq1"
OPENBLAS_DEFAULT = 28


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example: python benchmarks/blas_idle.py --features rootsift xfeat --json blas_idle.json",
    )
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="KITTI sequence (default: %(default)s)")
    p.add_argument(
        "--features", nargs="+", default=["rootsift", "xfeat"], help="types (default: %(default)s)"
    )
    p.add_argument(
        "--timeouts",
        nargs="+",
        type=int,
        default=[OPENBLAS_DEFAULT, 20],
        help="OPENBLAS_THREAD_TIMEOUT values, the first is the reference (default: %(default)s)",
    )
    p.add_argument("--frames", type=int, default=10, help="timed frames (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=3, help="rounds, the best is kept (default: %(default)s)")
    p.add_argument("--json", type=Path, help="write the results here")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def _frames(data: Path, count: int):
    import cv2
    import numpy as np

    files = sorted((data / "image_l").glob("*.png")) if data.is_dir() else []
    if len(files) >= count + 5:
        return [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in files[: count + 5]], f"KITTI {data.name}"
    rng = np.random.default_rng(0)
    images = []
    for _ in range(count + 5):  # smoothed noise at three scales: corners and blobs for any detector
        img = np.zeros((376, 1241), np.float32)
        for s in (3, 9, 27):
            img += cv2.GaussianBlur(rng.normal(size=img.shape).astype(np.float32), (0, 0), s) * s
        images.append(cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8))
    return images, "generated textured images"


def _measure(args: argparse.Namespace) -> dict:
    """In a child process: the timings of every feature type under this process's setting."""
    from planarloc.features.extract import FeatureConfig, extract_features
    from planarloc.features.matching import match_query_to_refs

    images, source = _frames(args.data, args.frames)
    out: dict = {"timeout": os.environ.get("OPENBLAS_THREAD_TIMEOUT"), "source": source, "types": {}}
    for kind in args.features:
        config = FeatureConfig(kind=kind)
        try:
            refs = [extract_features(im, config) for im in images[:5]]
        except Exception as exc:  # noqa: BLE001 - a learned type without its extra: skipped, said why
            out["types"][kind] = {"skipped": f"{type(exc).__name__}: {exc}"}
            continue
        frames = images[5:]
        feats = [extract_features(im, config) for im in frames]
        match_query_to_refs(feats[0], refs, kind=kind)  # warm
        best: dict[str, float] = {}
        for _ in range(args.rounds):
            times = dict.fromkeys(("extract", "extract_after_match", "match", "match_after"), 0.0)
            for im in frames:
                t = time.perf_counter()
                extract_features(im, config)
                times["extract"] += time.perf_counter() - t
            for im, f in zip(frames, feats):
                match_query_to_refs(f, refs, kind=kind)
                t = time.perf_counter()
                extract_features(im, config)
                times["extract_after_match"] += time.perf_counter() - t
            for f in feats:
                t = time.perf_counter()
                match_query_to_refs(f, refs, kind=kind)
                times["match"] += time.perf_counter() - t
            for im, f in zip(frames, feats):
                extract_features(im, config)
                t = time.perf_counter()
                match_query_to_refs(f, refs, kind=kind)
                times["match_after"] += time.perf_counter() - t
            for k, v in times.items():
                best[k] = min(best.get(k, float("inf")), 1000.0 * v / len(frames))
        best["query"] = best["extract_after_match"] + best["match_after"]
        out["types"][kind] = best
    return out


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.child:
        print(json.dumps(_measure(args)))
        return 0
    results = []
    for timeout in args.timeouts:
        env = dict(os.environ, OPENBLAS_THREAD_TIMEOUT=str(timeout))
        env.pop("GOTO_THREAD_TIMEOUT", None)
        cmd = [sys.executable, __file__, "--child", "--data", str(args.data), "--features", *args.features]
        cmd += ["--frames", str(args.frames), "--rounds", str(args.rounds)]
        print(f"OPENBLAS_THREAD_TIMEOUT={timeout}: measuring ...", file=sys.stderr, flush=True)
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            print(done.stderr, file=sys.stderr)
            return 1
        results.append(json.loads(done.stdout.strip().splitlines()[-1]))
    load = os.getloadavg()
    print(f"{results[0]['source']}, {args.frames} frames, best of {args.rounds} rounds; ms per frame")
    print("timeout  type       extract  after matching   matching  after extraction   query  default / this")
    reference = results[0]["types"]
    for r in results:
        for kind, t in r["types"].items():
            if "skipped" in t:
                print(f"{r['timeout']:>7}  {kind:<9}  skipped: {t['skipped']}")
                continue
            ratio = reference[kind]["query"] / t["query"]
            print(
                f"{r['timeout']:>7}  {kind:<9} {t['extract']:8.1f} {t['extract_after_match']:15.1f}"
                f" {t['match']:10.1f} {t['match_after']:17.1f} {t['query']:7.1f}  {ratio:.2f}x"
            )
    print(
        f"load average at end: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f} (1/5/15 min, {os.cpu_count()} cores)"
    )
    if args.json:
        record = {"args": {k: str(v) for k, v in vars(args).items()}, "results": results}
        args.json.write_text(json.dumps(record))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
