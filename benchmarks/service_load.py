"""Load and fault test of `planarloc serve` on a loopback port.

1. Starts ``planarloc serve`` (``--workers W --queue Q``) on a free 127.0.0.1 port with a map of a
   rendered office world (or ``--map``/``--queries``/``--camera`` for your data).
2. Closed-loop clients (each sends its next request when the previous one is answered) at 1, 2
   and 4 concurrent clients, ``--requests`` per client: throughput, p50 / p99 latency, statuses.
   Peer: the same queries localized in this process (``Localizer.localize``, no HTTP, one at a
   time, measured right before the server starts); the ratio of the 1-client p50 to it is the
   service's overhead (upload, multipart, queue, process hop, JSON).
3. Overload: 16 concurrent clients, no retries: every answer must be 200 or 503 (+ Retry-After).
4. Soak: 2 clients for ``--soak-seconds`` (bounded also by a request count); the RSS of the server
   and its workers is sampled every few seconds: memory must stay flat.
5. Fault: a worker is SIGKILLed while requests run on it: those requests must fail with a clean
   503, the pool must replace the worker, and the next requests must succeed.
6. Fleet sessions: ``--robots`` robots (default 4) stream the query trajectory concurrently, each
   in its own session (field ``session``, with ``stamp`` and wheel ``odometry``: the true motion
   with 1 % / 0.2° per-frame noise), each from another starting frame, closed loop, a 503 retried
   after its ``Retry-After``: every frame's status, its error against the ground truth, every
   HTTP status (none may be a 5xx other than 503), throughput and latency.

Every loop is bounded in count and time. Only loopback addresses are used.

    python benchmarks/service_load.py --json service.json
    python benchmarks/service_load.py --quick              # smaller counts, 20 s soak
    python benchmarks/service_load.py --only sessions      # the fleet sessions alone
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np
from scipy.spatial.transform import Rotation

from planarloc.geometry.pose import Pose, rotation_error_deg
from planarloc.io.datasets import read_dataset
from planarloc.io.text import T_XYZW, pose_text
from planarloc.io.tum import read_tum_trajectory
from planarloc.map.builder import build_map
from planarloc.serve.launcher import rss_bytes, start_server, stop_server, worker_pids
from planarloc.synthetic.world.export import generate
from planarloc.synthetic.world.presets import get_preset, shrunk


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", type=Path, help="map file (default: a rendered office world's map)")
    p.add_argument("--queries", type=Path, help="folder of query images (with --map)")
    p.add_argument("--camera", help="query camera 'MODEL W H PARAMS...' (with --map)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--queue", type=int, default=4)
    p.add_argument("--requests", type=int, default=12, help="requests per client per level (default: 12)")
    p.add_argument("--soak-seconds", type=float, default=120.0)
    p.add_argument("--quick", action="store_true", help="6 requests per client, 20 s soak")
    p.add_argument("--robots", type=int, default=4, help="concurrent robot sessions (default: 4)")
    p.add_argument(
        "--laps", type=int, default=2, help="times each robot streams the query trajectory (default: 2)"
    )
    p.add_argument("--only", choices=["sessions"], help="run only this part")
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    if args.quick:
        args.requests, args.soak_seconds = 6, 20.0
    if args.map and not (args.queries and args.camera):
        p.error("--map needs --queries and --camera")
    if args.only == "sessions" and args.map:
        p.error("--only sessions streams a rendered world (its ground truth and odometry); drop --map")
    return args


def prepare(args: argparse.Namespace, tmp: Path) -> tuple[Path, list[Path], str, Path | None]:
    """Map, query images, camera, and the rendered world (None with --map)."""
    if args.map:
        images = sorted(f for f in args.queries.iterdir() if f.suffix.lower() in (".png", ".jpg", ".jpeg"))
        return args.map, images, args.camera, None
    world = generate(shrunk(get_preset("office"), scale=1.0, n_map=24, n_query=12), tmp / "office", seed=0)
    map_path = build_map(read_dataset(world / "map", "tum"), tmp / "office.db")
    camera = (world / "query" / "camera.txt").read_text().splitlines()[-1]
    return map_path, sorted((world / "query" / "rgb").glob("*.png")), camera, world


def robot_streams(
    world: Path, robots: int, laps: int, seed: int = 0
) -> list[list[tuple[float, Path, Pose, Pose]]]:
    """Per robot: (stamp, image, true cam_from_world, odometry cam_from_odom) per frame. Robot k starts
    at frame 3k of the query trajectory and goes round it ``laps`` times; its odometry integrates
    the true motion with 1 % translation and 0.2° rotation noise per frame."""
    images = sorted((world / "query" / "rgb").glob("*.png"))
    times, world_from_cam = read_tum_trajectory(world / "query" / "groundtruth.txt")
    truth = [p.inverse() for p in world_from_cam]
    rng = np.random.default_rng(seed)
    out = []
    for k in range(robots):
        order = [(3 * k + i) % len(images) for i in range(laps * len(images))]
        frames, odom_from_cam = [], None
        for n, i in enumerate(order):
            if odom_from_cam is None:
                odom_from_cam = truth[i].inverse()
            else:
                step = truth[order[n - 1]] @ truth[i].inverse()  # prev_cam_from_cam, the true motion
                noise = Pose(
                    Rotation.from_rotvec(rng.normal(0, np.radians(0.2), 3)).as_matrix(),
                    step.t * rng.normal(0, 0.01, 3),
                )
                odom_from_cam = odom_from_cam @ Pose(step.R, step.t) @ noise
            frames.append((0.1 * (n + 1), images[i], truth[i], odom_from_cam.inverse()))
        out.append(frames)
    return out


def sessions_phase(url: str, camera: str, streams: list[list[tuple[float, Path, Pose, Pose]]]) -> dict:
    """Every robot streams its frames in its own session, concurrently (closed loop)."""
    statuses: dict[str, int] = {}
    per_robot: list[dict] = []
    latencies: list[float] = []
    lock = threading.Lock()
    start = threading.Barrier(len(streams))

    def robot(k: int) -> None:
        frames, errors, moves = [], [], []
        with httpx.Client(base_url=url, timeout=120) as http:
            start.wait()
            for stamp, image, truth, odometry in streams[k]:
                fields = {
                    "camera": camera,
                    "session": f"robot-{k}",
                    "stamp": repr(stamp),
                    "odometry": pose_text(odometry.inverse(), T_XYZW),
                }
                for _attempt in range(20):  # 503: wait Retry-After, bounded
                    t0 = time.perf_counter()
                    r = http.post(
                        "/v1/localize", files={"image": (image.name, image.read_bytes())}, data=fields
                    )
                    with lock:
                        statuses[str(r.status_code)] = statuses.get(str(r.status_code), 0) + 1
                    if r.status_code != 503:
                        break
                    time.sleep(float(r.headers.get("retry-after", "1")))
                if r.status_code != 200:
                    frames.append(f"http {r.status_code}")
                    continue
                with lock:
                    latencies.append(time.perf_counter() - t0)
                rec = r.json()
                frames.append(rec["status"])
                if rec["success"]:
                    est = Pose.from_quat_wxyz(rec["quat_wxyz"], rec["t"])
                    errors.append(float(np.linalg.norm(est.center - truth.center)))
                    moves.append(rotation_error_deg(est.R, truth.R))
        counts = {s: frames.count(s) for s in sorted(set(frames))}
        per_robot.append(
            {
                "robot": k,
                "frames": len(frames),
                "statuses": counts,
                "within_0.25m_10deg": int(sum(e <= 0.25 and a <= 10 for e, a in zip(errors, moves))),
                "max_error_m": max(errors) if errors else None,
            }
        )

    threads = [threading.Thread(target=robot, args=(k,)) for k in range(len(streams))]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join(1800)
    seconds = time.perf_counter() - t0
    frames = sum(r["frames"] for r in per_robot)
    return {
        "robots": len(streams),
        "frames": frames,
        "seconds": seconds,
        "frames_per_second": frames / seconds,
        "http_statuses": statuses,
        "fivexx_other_than_503": {k: v for k, v in statuses.items() if k.startswith("5") and k != "503"},
        "p50_s": float(np.percentile(latencies, 50)) if latencies else None,
        "p99_s": float(np.percentile(latencies, 99)) if latencies else None,
        "per_robot": sorted(per_robot, key=lambda r: r["robot"]),
    }


class Load:
    """Closed-loop clients against one server; records (status, latency, retry-after) per request."""

    def __init__(self, url: str, images: list[Path], camera: str) -> None:
        self.url, self.camera = url + "/v1/localize", camera
        self.payloads = [(p.name, p.read_bytes()) for p in images]

    def run(self, clients: int, requests: int, max_seconds: float) -> list[tuple[int, float, str | None]]:
        out: list[tuple[int, float, str | None]] = []
        lock = threading.Lock()
        deadline = time.monotonic() + max_seconds
        start = threading.Barrier(clients)

        def client(k: int) -> None:
            with httpx.Client(timeout=120) as http:
                start.wait()
                for i in range(requests):
                    if time.monotonic() > deadline:
                        break
                    name, data = self.payloads[(k * requests + i) % len(self.payloads)]
                    t0 = time.perf_counter()
                    try:
                        r = http.post(self.url, files={"image": (name, data)}, data={"camera": self.camera})
                        rec = (r.status_code, time.perf_counter() - t0, r.headers.get("retry-after"))
                    except httpx.TransportError as exc:
                        rec = (-1, time.perf_counter() - t0, type(exc).__name__)
                    with lock:
                        out.append(rec)

        threads = [threading.Thread(target=client, args=(k,)) for k in range(clients)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(max_seconds + 180)
        return out


def in_process_latency(map_path: Path, images: list[Path], camera: str, n: int) -> dict:
    """The peer: the same localization in this process, without the service."""
    from planarloc.features.images import read_gray
    from planarloc.localize.localizer import Localizer
    from planarloc.serve.requests import parse_camera_field

    loc, cam = Localizer(map_path), parse_camera_field(camera)
    loc.localize(read_gray(images[0]), cam)  # warm-up (numba cache, map pages)
    times = []
    for i in range(n):
        t0 = time.perf_counter()
        loc.localize(read_gray(images[i % len(images)]), cam)
        times.append(time.perf_counter() - t0)
    return {"requests": n, "p50_s": float(np.median(times))}


def level_stats(records: list[tuple[int, float, str | None]], seconds: float) -> dict:
    ok = [lat for s, lat, _ in records if s == 200]
    codes: dict[str, int] = {}
    for s, _, _ in records:
        codes[str(s)] = codes.get(str(s), 0) + 1
    return {
        "requests": len(records),
        "statuses": codes,
        "seconds": seconds,
        "throughput_per_s": len(ok) / seconds if seconds > 0 else None,
        "p50_s": float(np.percentile(ok, 50)) if ok else None,
        "p99_s": float(np.percentile(ok, 99)) if ok else None,
    }


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    report: dict = {
        "workers": args.workers,
        "queue": args.queue,
        "cpu_count": os.cpu_count(),
        "load_average_1min_start": os.getloadavg()[0],
    }
    with tempfile.TemporaryDirectory() as tmp:
        map_path, images, camera, world = prepare(args, Path(tmp))
        if args.only == "sessions":
            url, proc = start_server(
                ["--map", f"bench={map_path}", "--workers", str(args.workers), "--queue", str(args.queue)]
            )
            try:
                Load(url, images, camera).run(args.workers, 2, 120)  # warm-up: every worker has run a request
                report["sessions"] = run_sessions(url, camera, world, args)
            finally:
                stop_server(proc)
            return finish(report, args)
        report["in_process"] = peer = in_process_latency(map_path, images, camera, args.requests)
        print(
            f"in-process peer: p50 {peer['p50_s']:.3f} s per query ({peer['requests']} queries)", flush=True
        )
        url, proc = start_server(
            ["--map", f"bench={map_path}", "--workers", str(args.workers), "--queue", str(args.queue)]
        )
        try:
            load = Load(url, images, camera)
            load.run(args.workers, 2, 120)  # warm-up: every worker has run a request
            report["levels"] = {}
            for clients in (1, 2, 4):
                t0 = time.perf_counter()
                recs = load.run(clients, args.requests, 300)
                report["levels"][clients] = s = level_stats(recs, time.perf_counter() - t0)
                s["p50_over_in_process"] = s["p50_s"] / peer["p50_s"] if s["p50_s"] else None
                print(
                    f"{clients:2d} clients: {s['throughput_per_s']:.2f} req/s, p50 {s['p50_s']:.3f} s, "
                    f"p99 {s['p99_s']:.3f} s, statuses {s['statuses']}",
                    flush=True,
                )

            t0 = time.perf_counter()
            recs = load.run(16, 4, 300)
            s = level_stats(recs, time.perf_counter() - t0)
            bad = {k: v for k, v in s["statuses"].items() if k not in ("200", "503")}
            s["non_200_503"] = bad
            s["all_503_have_retry_after"] = all(ra is not None for st, _, ra in recs if st == 503)
            report["overload_16"] = s
            print(
                f"16 clients (overload): statuses {s['statuses']}, other than 200/503: {bad or 'none'}, "
                f"Retry-After on every 503: {s['all_503_have_retry_after']}",
                flush=True,
            )

            pids = [proc.pid, *worker_pids(proc.pid)]
            samples: list[tuple[float, int]] = [(0.0, rss_bytes(pids))]
            stop = threading.Event()

            def sample() -> None:
                t_start = time.monotonic()
                while not stop.wait(5.0):
                    samples.append(
                        (time.monotonic() - t_start, rss_bytes([proc.pid, *worker_pids(proc.pid)]))
                    )

            sampler = threading.Thread(target=sample)
            sampler.start()
            t0 = time.perf_counter()
            recs = load.run(2, 100_000, args.soak_seconds)
            stop.set()
            sampler.join()
            s = level_stats(recs, time.perf_counter() - t0)
            rss = [r for _, r in samples]
            half = max(1, len(rss) // 2)
            s.update(
                rss_start_mb=rss[0] / 2**20,
                rss_end_mb=rss[-1] / 2**20,
                rss_max_mb=max(rss) / 2**20,
                rss_second_half_growth_mb=(rss[-1] - rss[half]) / 2**20,
                rss_samples=len(rss),
            )
            report["soak"] = s
            print(
                f"soak {s['seconds']:.0f} s, 2 clients: {s['requests']} requests {s['statuses']}, RSS "
                f"{s['rss_start_mb']:.0f} -> {s['rss_end_mb']:.0f} MB (max {s['rss_max_mb']:.0f}, "
                f"second half "
                f"{s['rss_second_half_growth_mb']:+.1f} MB)",
                flush=True,
            )

            before = worker_pids(proc.pid)
            result: list = []
            fault = threading.Thread(target=lambda: result.extend(load.run(args.workers, 1, 120)))
            fault.start()
            time.sleep(0.3)  # both workers are running a request now
            os.kill(before[0], signal.SIGKILL)
            t_kill = time.perf_counter()
            fault.join()
            recovered = None
            while time.perf_counter() - t_kill < 120:
                h = httpx.get(url + "/healthz").json()
                if h["workers_alive"] == args.workers and set(worker_pids(proc.pid)) != set(before):
                    recovered = time.perf_counter() - t_kill
                    break
                time.sleep(0.1)
            after = level_stats(load.run(args.workers, 2, 120), 1.0)["statuses"]
            report["fault"] = {
                "in_flight_statuses": sorted(st for st, _, _ in result),
                "recovery_s": recovered,
                "after_statuses": after,
                "server_alive": proc.poll() is None,
                "worker_restarts": httpx.get(url + "/healthz").json()["worker_restarts"],
            }
            print(
                f"worker killed mid-request: in-flight answers {report['fault']['in_flight_statuses']}, "
                f"pool recovered in {recovered if recovered is None else round(recovered, 2)} s, "
                f"then {after}",
                flush=True,
            )
            if world is not None:
                report["sessions"] = run_sessions(url, camera, world, args)
        finally:
            stop_server(proc)
    return finish(report, args)


def run_sessions(url: str, camera: str, world: Path, args: argparse.Namespace) -> dict:
    s = sessions_phase(url, camera, robot_streams(world, args.robots, args.laps))
    print(
        f"{s['robots']} robot sessions on {args.workers} workers: {s['frames']} frames in {s['seconds']:.0f} "
        f"s ({s['frames_per_second']:.2f} frames/s), p50 {s['p50_s']:.3f} s, p99 {s['p99_s']:.3f} s, HTTP "
        f"{s['http_statuses']}, 5xx other than 503: {s['fivexx_other_than_503'] or 'none'}",
        flush=True,
    )
    for r in s["per_robot"]:
        print(
            f"  robot {r['robot']}: {r['statuses']}, {r['within_0.25m_10deg']} of {r['frames']} "
            "within 0.25 m / 10°, worst error "
            f"{r['max_error_m'] if r['max_error_m'] is None else round(r['max_error_m'], 3)} m",
            flush=True,
        )
    return s


def finish(report: dict, args: argparse.Namespace) -> int:
    report["load_average_1min_end"] = os.getloadavg()[0]
    print(
        f"machine load average (1 min): {report['load_average_1min_start']:.1f} at start, "
        f"{report['load_average_1min_end']:.1f} at the end, on {os.cpu_count()} cores"
    )
    if args.json:
        args.json.write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
