"""Microseconds per solve for planarloc's minimal solvers, with PoseLib's Python bindings in the same run.

Usage::

    python benchmarks/solvers.py            # full run (~1-2 min on 2 cores)
    python benchmarks/solvers.py --quick    # fewer samples and repeats (~15 s)
    python benchmarks/solvers.py --json results.json

What is timed (generated data only, noise-free, seeded):

* single calls through the public Python API (input validation and ``Pose`` objects included),
  each **interleaved with its PoseLib peer**: every repetition runs our loop, then PoseLib's
  loop on the same samples, so that load from other processes hits both alike. Both are timed
  by wall clock (``perf_counter``) and by this process's CPU time (``process_time``); the
  ratio is printed per row for both clocks. ``abspose_2p2p`` / ``abspose_2p1p`` /
  ``abspose_up2p`` have no PoseLib peer and are timed alone;
* batched APIs, amortized per sample over M samples (100k for the 2-point solver);
* the numba kernels the RANSAC hypotheses call (``solve_planar_2p``, ``triangulate_scales``,
  ``scale_2p1p``), timed inside a compiled loop so that Python dispatch is not counted;
* PoseLib 2.0.x Python bindings ``relpose_upright_planar_2pt``, ``relpose_5pt``,
  ``relpose_8pt`` on the same samples (unit bearings: PoseLib's cheirality test assumes them).

Every timing repeats the whole loop k times and reports the best (minimum) and the median of
the per-call times (wall clock unless the column says CPU). Numba functions are compiled and
called once before timing. The load average is printed with the results because the machine
may be shared; on a loaded machine the median moves much more than the best.

PoseLib's README quotes ~0.12 µs for the C++ planar 2-point solver. That number is a
reference constant, **not measured here**, and is labelled so in the table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from planarloc.geometry.planar import rotation_from_yaw
from planarloc.geometry.pose import Pose
from planarloc.solvers.abspose_2p1p import abspose_2p1p, scale_2p1p
from planarloc.solvers.abspose_2p2p import abspose_2p2p, triangulate_scales
from planarloc.solvers.abspose_up2p import abspose_up2p
from planarloc.solvers.relpose_planar_2p import relpose_planar_2p, relpose_planar_2p_batch, solve_planar_2p

POSELIB_README_PLANAR_2PT_US = 0.12  # C++ figure from PoseLib's README: NOT measured here


@dataclass
class Row:
    name: str
    kind: str  # "single", "batch", "kernel", "peer", "reference"
    us_best: float
    us_median: float | None
    samples: int
    repeats: int
    peer: str | None = None  # name of the PoseLib row to compare with
    note: str = ""
    cpu_best: float | None = None  # process_time, µs per call (single calls only)
    cpu_median: float | None = None
    ratio_wall: float | None = None  # best ours / best peer of the same interleaved run
    ratio_cpu: float | None = None


# ---- data -------------------------------------------------------------------------------------


def planar_samples(rng: np.random.Generator, m: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(m, n, 3) query / reference rays ``(x, y, 1)`` of random planar scenes (paper Sec. V-A)."""
    out_q, out_r = [], []
    while sum(len(q) for q in out_q) < m:
        k = m
        theta, phi = rng.uniform(-np.pi, np.pi, (2, k))
        R = rotation_from_yaw(theta)
        t = -np.einsum("mij,mj->mi", R, np.stack([np.sin(phi), np.zeros(k), np.cos(phi)], 1))
        X = rng.uniform(-10, 10, (k, 16 * n, 3))
        Xr = np.einsum("mij,mkj->mki", R, X) + t[:, None]
        ok = (X[..., 2] > 0.5) & (Xr[..., 2] > 0.5)
        keep = ok.sum(1) >= n
        order = np.argsort(~ok, axis=1, kind="stable")[:, :n, None]
        X, Xr = np.take_along_axis(X, order, 1)[keep], np.take_along_axis(Xr, order, 1)[keep]
        out_q.append(X / X[..., 2:])
        out_r.append(Xr / Xr[..., 2:])
    return np.concatenate(out_q)[:m].copy(), np.concatenate(out_r)[:m].copy()


def general_samples(rng: np.random.Generator, m: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(m, n, 3) rays of random 6-DoF scenes (rotation up to ~30°, points 2-20 m in front)."""
    from scipy.spatial.transform import Rotation

    R = Rotation.from_rotvec(rng.normal(0, 0.3, (m, 3))).as_matrix()
    t = rng.normal(0, 1, (m, 3))
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    X = np.concatenate([rng.uniform(-4, 4, (m, n, 2)), rng.uniform(4, 20, (m, n, 1))], axis=2)
    Xr = np.einsum("mij,mkj->mki", R, X) + t[:, None]
    Xr[..., 2] = np.maximum(Xr[..., 2], 0.5)  # rare: keep a valid ray (sample is then just noisy)
    return X / X[..., 2:], Xr / Xr[..., 2:]


def unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


# ---- timing -----------------------------------------------------------------------------------


def time_loop(fn: Callable[[int], object], n: int, repeats: int) -> tuple[float, float]:
    """Best and median µs per call of ``fn(i)`` over i = 0..n-1, repeated ``repeats`` times."""
    per = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for i in range(n):
            fn(i)
        per.append((time.perf_counter() - t0) / n * 1e6)
    return min(per), statistics.median(per)


def time_interleaved(
    ours: Callable[[int], object], peer: Callable[[int], object] | None, n: int, repeats: int
) -> tuple[list[float], list[float], list[float], list[float]]:
    """Per-call µs of ``ours(i)`` and ``peer(i)`` (i = 0..n-1), alternating per repetition.

    Returns the lists (wall ours, CPU ours, wall peer, CPU peer), one entry per repetition
    (the peer lists are empty without a peer).
    """
    wall, cpu, peer_wall, peer_cpu = [], [], [], []
    for _ in range(repeats):
        for fn, w, c in ((ours, wall, cpu), (peer, peer_wall, peer_cpu)):
            if fn is None:
                continue
            c0, t0 = time.process_time(), time.perf_counter()
            for i in range(n):
                fn(i)
            t1, c1 = time.perf_counter(), time.process_time()
            w.append((t1 - t0) / n * 1e6)
            c.append((c1 - c0) / n * 1e6)
    return wall, cpu, peer_wall, peer_cpu


def time_batch(fn: Callable[[], object], n: int, repeats: int) -> tuple[float, float, float]:
    """Best and median wall µs and best CPU µs per sample of ``fn()`` over n samples."""
    per, cpu = [], []
    for _ in range(repeats):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        t1, c1 = time.perf_counter(), time.process_time()
        per.append((t1 - t0) / n * 1e6)
        cpu.append((c1 - c0) / n * 1e6)
    return min(per), statistics.median(per), min(cpu)


@njit  # not cached: a cached caller would keep a stale copy of an edited solver (solvers_1ac.py uses it too)
def loop_planar_2p(xq, xr, reps):
    th = np.empty(2)
    ph = np.empty(2)
    total = 0
    for _ in range(reps):
        for i in range(xq.shape[0]):
            total += solve_planar_2p(xq[i], xr[i], th, ph)
    return total


@njit(cache=True)
def _loop_triangulate_scales(t1, t2, b, reps):
    acc = 0.0
    for _ in range(reps):
        for i in range(t1.shape[0]):
            r1, r2, _ = triangulate_scales(t1[i], t2[i], b[i])
            acc += r1 + r2
    return acc


@njit(cache=True)
def _loop_scale_2p1p(a, b, y, x2, reps):
    acc = 0.0
    for _ in range(reps):
        for i in range(a.shape[0]):
            acc += scale_2p1p(a[i], b[i], y[i], x2[i])
    return acc


def time_kernel(
    fn: Callable[..., object], args: tuple, n: int, repeats: int, reps: int = 1
) -> tuple[float, float]:
    fn(*[a[:2] for a in args], 1)  # compile / load from cache
    per = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(*args, reps)
        per.append((time.perf_counter() - t0) / (n * reps) * 1e6)
    return min(per), statistics.median(per)


# ---- the benchmark ----------------------------------------------------------------------------


def run(quick: bool) -> tuple[list[Row], dict]:
    rng = np.random.default_rng(0)
    n_single = 500 if quick else 3000
    n_batch_2p = 20_000 if quick else 100_000
    n_batch_5p = 2_000 if quick else 10_000
    reps = 3 if quick else 7
    rows: list[Row] = []

    def add(name, kind, best_med, samples, repeats=reps, peer=None, note=""):
        best, med = best_med[:2]
        rows.append(
            Row(
                name,
                kind,
                best,
                med,
                samples,
                repeats,
                peer,
                note,
                cpu_best=best_med[2] if len(best_med) > 2 else None,
            )
        )
        print(f"  {name:<46s} {best:10.3f} µs (median {med:.3f})", file=sys.stderr, flush=True)

    def add_single(name, ours, peer_name=None, peer=None, n=n_single):
        """Our single call interleaved with its PoseLib peer (if any); one row each."""
        wall, cpu, pwall, pcpu = time_interleaved(ours, peer, n, reps)
        row = Row(
            f"{name} (single)",
            "single",
            min(wall),
            statistics.median(wall),
            n,
            reps,
            cpu_best=min(cpu),
            cpu_median=statistics.median(cpu),
        )
        rows.append(row)
        msg = f"  {row.name:<46s} {row.us_best:10.3f} µs wall, {row.cpu_best:.3f} CPU"
        if peer is not None:
            prow = Row(
                f"{peer_name} (with {name})",
                "peer",
                min(pwall),
                statistics.median(pwall),
                n,
                reps,
                note="Python binding, interleaved",
                cpu_best=min(pcpu),
                cpu_median=statistics.median(pcpu),
            )
            row.peer = prow.name
            row.ratio_wall = row.us_best / prow.us_best
            row.ratio_cpu = row.cpu_best / prow.cpu_best
            rows.append(prow)
            msg += f"   vs {peer_name} {prow.us_best:.3f} / {prow.cpu_best:.3f}: "
            msg += f"ratio {row.ratio_wall:.2f} wall, {row.ratio_cpu:.2f} CPU"
        print(msg, file=sys.stderr, flush=True)
        return row

    # -- planar 2-point ---------------------------------------------------------------------
    try:
        import poselib

        poselib_version = getattr(poselib, "__version__", "?")
    except ImportError:
        poselib = None
        poselib_version = None
    xq2, xr2 = planar_samples(rng, n_batch_2p, 2)
    uq2, ur2 = unit(xq2), unit(xr2)
    relpose_planar_2p(xq2[0], xr2[0])
    relpose_planar_2p_batch(xq2[:4], xr2[:4])
    peer_2p = None
    if poselib is not None:
        peer_2p = poselib.relpose_upright_planar_2pt
        peer_2p(uq2[0], ur2[0])
    single_2p = add_single(
        "relpose_planar_2p",
        lambda i: relpose_planar_2p(xq2[i], xr2[i]),
        "poselib.relpose_upright_planar_2pt",
        None if peer_2p is None else lambda i: peer_2p(uq2[i], ur2[i]),
    )
    add(
        "relpose_planar_2p_batch (per sample)",
        "batch",
        time_batch(lambda: relpose_planar_2p_batch(xq2, xr2), n_batch_2p, reps),
        n_batch_2p,
        peer=single_2p.peer,
    )
    th, ph = np.empty(2), np.empty(2)
    add(
        "solve_planar_2p kernel (numba dispatch)",
        "kernel",
        time_loop(lambda i: solve_planar_2p(xq2[i], xr2[i], th, ph), n_single, reps),
        n_single,
        note="called from Python: includes numba dispatch",
    )
    add(
        "solve_planar_2p kernel (in numba loop)",
        "kernel",
        time_kernel(loop_planar_2p, (xq2, xr2), n_batch_2p, reps),
        n_batch_2p,
        peer="PoseLib C++ planar 2pt (README)",
        note="what RANSAC hypotheses call",
    )
    rows.append(
        Row(
            "PoseLib C++ planar 2pt (README)",
            "reference",
            POSELIB_README_PLANAR_2PT_US,
            None,
            0,
            0,
            note="NOT MEASURED: constant quoted from PoseLib's README",
        )
    )

    # -- absolute pose ----------------------------------------------------------------------
    from planarloc.synthetic.scenes import random_planar_pose

    cases = []
    while len(cases) < n_single:
        query, ref, ref2 = random_planar_pose(rng), random_planar_pose(rng), random_planar_pose(rng)
        rel, rel2 = ref @ query.inverse(), ref2 @ query.inverse()
        rel = Pose(rel.R, rel.t / np.linalg.norm(rel.t))
        rel2 = Pose(rel2.R, rel2.t / np.linalg.norm(rel2.t))
        X = rng.uniform(-10, 10, 3)
        Yq, Y2 = query.transform(X[None])[0], ref2.transform(X[None])[0]
        if Yq[2] < 0.5 or Y2[2] < 0.5:
            continue
        cases.append((rel, rel2, ref, ref2, Yq / Yq[2], Y2 / Y2[2]))
    abspose_2p2p(*cases[0][:4])
    abspose_2p1p(cases[0][0], cases[0][2], cases[0][3], cases[0][4], cases[0][5])
    add_single("abspose_2p2p", lambda i: abspose_2p2p(*cases[i][:4]))
    add_single(
        "abspose_2p1p",
        lambda i: abspose_2p1p(cases[i][0], cases[i][2], cases[i][3], cases[i][4], cases[i][5]),
    )
    up2p = []  # (2, 3) query rays and their points in an upright frame
    while len(up2p) < n_single:
        query = random_planar_pose(rng)
        X = rng.uniform(-10, 10, (2, 3))
        Xc = query.transform(X)
        if np.all(Xc[:, 2] > 0.5):
            up2p.append((Xc / Xc[:, 2:], X))
    abspose_up2p(*up2p[0])
    add_single("abspose_up2p", lambda i: abspose_up2p(*up2p[i]))
    t1 = np.array([c[0].t for c in cases])
    t2 = np.array([c[0].R @ c[1].R.T @ c[1].t for c in cases])
    b = np.array([(c[2] @ c[3].inverse()).t for c in cases])
    add(
        "triangulate_scales kernel (in numba loop)",
        "kernel",
        time_kernel(_loop_triangulate_scales, (t1, t2, b), len(cases), reps, reps=200),
        len(cases) * 200,
        note="2p2p scales, eq. 13-15",
    )
    j2j = [c[3] @ c[2].inverse() for c in cases]
    a = np.array([p.R @ c[0].t for p, c in zip(j2j, cases)])
    bb = np.array([p.t for p in j2j])
    y = np.array([p.R @ c[0].R @ c[4] for p, c in zip(j2j, cases)])
    x2 = np.array([c[5] for c in cases])
    add(
        "scale_2p1p kernel (in numba loop)",
        "kernel",
        time_kernel(_loop_scale_2p1p, (a, bb, y, x2), len(cases), reps, reps=200),
        len(cases) * 200,
        note="2p1p scale, eq. 18",
    )

    # -- general relative pose --------------------------------------------------------------
    xq5, xr5 = general_samples(rng, n_batch_5p, 5)
    xq8, xr8 = general_samples(rng, n_batch_5p, 8)
    general = [
        (
            "relpose_5p_nister",
            "relpose_5p_nister_batch",
            "planarloc.solvers.relpose_5p_nister",
            xq5,
            xr5,
            "poselib.relpose_5pt",
        ),
        (
            "relpose_5p_stewenius",
            "relpose_5p_stewenius_batch",
            "planarloc.solvers.relpose_5p_stewenius",
            xq5,
            xr5,
            "poselib.relpose_5pt",
        ),
        ("relpose_8p", "relpose_8p_batch", "planarloc.solvers.relpose_8p", xq8, xr8, "poselib.relpose_8pt"),
    ]
    for single_name, batch_name, module, xq, xr, peer in general:
        try:
            mod = __import__(module, fromlist=[single_name, batch_name])
            single, batch = getattr(mod, single_name), getattr(mod, batch_name)
        except (ImportError, AttributeError) as exc:
            print(f"  {single_name}: unavailable ({exc})", file=sys.stderr)
            continue
        single(xq[0], xr[0])
        batch(xq[:4], xr[:4])
        uq, ur = unit(xq), unit(xr)
        peer_fn = None
        if poselib is not None:
            f = getattr(poselib, peer.split(".")[1])
            f(uq[0], ur[0])
            peer_fn = lambda i, f=f, uq=uq, ur=ur: f(uq[i], ur[i])  # noqa: E731
        row = add_single(
            single_name, lambda i, single=single, xq=xq, xr=xr: single(xq[i], xr[i]), peer, peer_fn
        )
        add(
            f"{batch_name} (per sample)",
            "batch",
            time_batch(lambda: batch(xq, xr), len(xq), reps),
            len(xq),
            peer=row.peer,
        )

    meta = {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": __import__("numba").__version__,
        "poselib": poselib_version,
        "machine": platform.machine(),
        "cpu_count": os.cpu_count(),
        "quick": quick,
    }
    return rows, meta


def format_table(rows: list[Row], load_before, load_after, meta) -> str:
    by_name = {r.name: r for r in rows}
    lines = [
        "planarloc solver benchmark — µs per solve (best of k repeats; median in brackets)",
        f"load average (1, 5, 15 min) before: {load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f}"
        f"   after: {load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f}"
        f"   on {meta['cpu_count']} CPUs",
        "",
        f"{'solver':<52s} {'kind':<9s} {'best µs':>9s} {'(median)':>10s} {'CPU µs':>8s} {'samples':>8s}"
        f"  {'ours/PoseLib wall':>17s} {'CPU':>5s}  vs",
        "-" * 140,
    ]
    for r in rows:
        med = f"({r.us_median:.3f})" if r.us_median is not None else "—"
        cpu = f"{r.cpu_best:8.3f}" if r.cpu_best is not None else f"{'':8s}"
        ratio, ratio_cpu, vs = "", "", ""
        if r.peer and r.peer in by_name:
            p = by_name[r.peer]
            ratio = f"{r.ratio_wall if r.ratio_wall is not None else r.us_best / p.us_best:17.2f}"
            if r.ratio_cpu is not None:
                ratio_cpu = f"{r.ratio_cpu:5.2f}"
            elif r.cpu_best is not None and p.cpu_best is not None:
                ratio_cpu = f"{r.cpu_best / p.cpu_best:5.2f}"
            vs = r.peer
        samples = str(r.samples) if r.samples else "—"
        lines.append(
            f"{r.name:<52s} {r.kind:<9s} {r.us_best:9.3f} {med:>10s} {cpu} {samples:>8s}  {ratio:>17s}"
            f" {ratio_cpu:>5s}  {vs}"
        )
        if r.note:
            lines.append(f"{'':<46s}   ↳ {r.note}")
    lines += [
        "",
        "ratios: best ours / best PoseLib (Python binding unless the row says README). Single calls of the",
        "Python APIs include input validation and Pose construction and are interleaved with their PoseLib",
        "peer per repetition (wall and CPU ratios from the same run); batch rows are amortized per sample",
        "and compared with the peer's single call (wall with wall, CPU with CPU).",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples and repeats")
    parser.add_argument("--json", metavar="OUT", help="also write the results as JSON to OUT")
    args = parser.parse_args(argv)
    load_before = os.getloadavg()
    rows, meta = run(args.quick)
    load_after = os.getloadavg()
    print(format_table(rows, load_before, load_after, meta))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump(
                {
                    "meta": meta,
                    "loadavg_before": load_before,
                    "loadavg_after": load_after,
                    "poselib_readme_planar_2pt_us_not_measured": POSELIB_README_PLANAR_2PT_US,
                    "rows": [asdict(r) for r in rows],
                },
                fh,
                indent=2,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
