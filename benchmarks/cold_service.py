"""`planarloc serve` on an empty kernel cache: how long its first requests take, both ways in one run.

Protocol (KITTI seq 2, a map of every 4th image built first with the warm cache of this
environment; each server a new process on loopback with its own empty ``NUMBA_CACHE_DIR``):

1. ``PLANARLOC_COMPILE=auto`` (the default): the time to the banner; then one request per worker
   at once (different frames), timed each; the time until the shared detached compile has ended
   (``/healthz`` counts no worker running as Python any more: what an operator sees); then a
   request per worker again, compiled.
2. ``PLANARLOC_COMPILE=wait``: the time to the banner (the workers wait for the compile on every
   core), then the same requests.

Every served pose is compared with the poses of the same frames from a server on this
environment's warm cache (the same map, camera and seed): the largest difference is printed.

    python benchmarks/cold_service.py
    python benchmarks/cold_service.py --workers 2 --json cold_service.json
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _peer_pipeline as peer  # noqa: E402

from planarloc.client import Client  # noqa: E402
from planarloc.serve.launcher import start_server, stop_server  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
KITTI = REPO.parent / "shared" / "data" / "kitti_seq2"


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--kitti", type=Path, default=KITTI, help="a KITTI sequence (default: %(default)s)")
    p.add_argument("--workers", type=int, default=2, help="server workers (default: %(default)s)")
    p.add_argument("--json", type=Path, help="write the measurements here")
    args = p.parse_args(argv)
    if not (args.kitti / "image_l").is_dir():
        p.error(f"--kitti {args.kitti}: not a KITTI sequence (image_l/ missing)")
    if args.workers < 1:
        p.error("--workers must be >= 1")
    return args


def requests_at_once(url: str, frames: list[Path]) -> list[tuple[float, dict]]:
    """One request per frame, all at once (one thread each): (seconds, record) per frame."""
    out: list[tuple[float, dict] | None] = [None] * len(frames)

    def one(i: int) -> None:
        with Client(url, timeout=600.0) as client:
            t0 = time.perf_counter()
            record = client.localize(frames[i], map="kitti", seed=7)
            out[i] = (time.perf_counter() - t0, record)

    threads = [threading.Thread(target=one, args=(i,)) for i in range(len(frames))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if any(o is None for o in out):
        raise RuntimeError("a request failed (see the server's output above)")
    return out  # type: ignore[return-value]


def workers_as_python(url: str) -> int:
    """The workers that run as Python while the shared compile runs, as ``/healthz`` says."""
    with Client(url) as client:
        return int(client.health()["workers_as_python"])


def serve_cold(map_path: Path, frames: list[Path], workers: int, setting: str, root: Path) -> dict:
    """One server on an empty kernel cache with ``PLANARLOC_COMPILE=setting``."""
    cache = root / f"numba-{setting}"
    env = {"NUMBA_CACHE_DIR": str(cache), "PLANARLOC_COMPILE": setting, "OPENBLAS_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    url, proc = start_server(["--map", f"kitti={map_path}", "--workers", str(workers)], env=env)
    result: dict = {"setting": setting, "banner_s": time.perf_counter() - t0}
    try:
        result["as_python_at_banner"] = workers_as_python(url)
        first = requests_at_once(url, frames)
        result["first_s"] = [s for s, _ in first]
        t1 = time.perf_counter()
        while workers_as_python(url) > 0:
            time.sleep(0.5)
        result["compile_left_s"] = time.perf_counter() - t1
        after = requests_at_once(url, frames)
        result["after_s"] = [s for s, _ in after]
        result["records"] = [r for _, r in first + after]
        result["notices"] = [line for line in proc.output.text().splitlines() if "kernels" in line]
    finally:
        stop_server(proc)
    return result


def warm_records(map_path: Path, frames: list[Path], workers: int) -> list[dict]:
    url, proc = start_server(["--map", f"kitti={map_path}", "--workers", str(workers)])
    try:
        return [r for _, r in requests_at_once(url, frames)]
    finally:
        stop_server(proc)


def largest_difference(records: list[dict], warm: list[dict]) -> float:
    """The largest difference of the centres' coordinates between served and warm records (m)."""
    n = len(warm)
    diffs = [np.abs(np.asarray(r["t"]) - np.asarray(warm[i % n]["t"])) for i, r in enumerate(records)]
    return float(max(d.max() for d in diffs))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    import subprocess

    peer.print_header("# planarloc serve on an empty kernel cache")
    frames = sorted((args.kitti / "image_l").glob("*.png"))[1 : 1 + 2 * args.workers : 2][: args.workers]
    with tempfile.TemporaryDirectory(prefix="planarloc-cold-service-") as tmp:
        root = Path(tmp)
        map_path = root / "map.db"
        subprocess.run(
            [sys.executable, "-m", "planarloc.cli.main", "map", "build", str(args.kitti), "-f", "kitti"]
            + ["--every", "4", "--out", str(map_path)],
            check=True,
            capture_output=True,
        )
        warm = warm_records(map_path, frames, args.workers)
        runs = [serve_cold(map_path, frames, args.workers, s, root) for s in ("auto", "wait")]
    rows = []
    for run in runs:
        rows.append(
            [
                f"PLANARLOC_COMPILE={run['setting']}",
                f"{run['banner_s']:.1f} s",
                str(run["as_python_at_banner"]),
                " / ".join(f"{s:.1f}" for s in run["first_s"]) + " s",
                f"{run['compile_left_s']:.1f} s",
                " / ".join(f"{s:.2f}" for s in run["after_s"]) + " s",
                f"{largest_difference(run['records'], warm):.1e} m",
            ]
        )
        run["success"] = [r["success"] for r in run.pop("records")]
    print(
        peer.markdown_table(
            [
                "server",
                "to the banner",
                "workers as Python then (/healthz)",
                "first requests (one per worker, at once)",
                "compile left after them (until /healthz counts 0)",
                "requests after the compile",
                "poses vs warm, largest difference",
            ],
            rows,
            f"{args.workers} workers, {os.cpu_count()} cores, KITTI seq 2 frames {[f.name for f in frames]}",
        )
    )
    for run in runs:
        for line in run["notices"]:
            print(f"  [{run['setting']}] {line[:160]}")
    auto, wait = runs
    ready_auto = auto["banner_s"] + max(auto["first_s"])
    ready_wait = wait["banner_s"] + max(wait["first_s"])
    print(
        f"\nfirst answers after start: auto {ready_auto:.1f} s, wait {ready_wait:.1f} s "
        f"(ratio {ready_auto / ready_wait:.2f}); every request succeeded: "
        f"{all(all(r['success']) for r in runs)}"
    )
    print(peer.load_note())
    peer.write_json(args.json, {"runs": runs, "frames": [f.name for f in frames]})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
