"""The planar one-affine-correspondence solver against our planar 2-point solver, in one run.

Usage::

    python benchmarks/solvers_1ac.py            # full run (~1 min on 2 cores)
    python benchmarks/solvers_1ac.py --quick    # fewer samples and repeats

What is measured (generated data only, seeded):

* **time**, interleaved per repetition (1ac loop, then 2p loop on the same scenes) so that load
  from other processes hits both alike; best and median of k repetitions, wall clock:
  - single calls through the public API (validation and ``Pose`` objects included),
  - the batched APIs per sample (M samples in one call),
  - the compiled kernels (``solve_planar_1ac`` / ``solve_planar_2p``) in a compiled loop;
* **accuracy under noise** (median rotation error and translation-direction error, degrees):
  - 1ac with noise on the affine frame: the true local affine rotated by N(0, σ_angle) and
    scaled by exp(N(0, σ_scale)) (in pixels, both cameras f = 500 px), plus pixel noise on the
    point;
  - 1ac with the *SIFT model error*: the true affine replaced by its nearest similarity (what
    orientation + scale can express) before the same noise;
  - 2p with pixel noise on both points (the closest of its ≤ 2 solutions to the truth, as a
    RANSAC loop would find it).
  Scenes: the paper's protocol (θ, φ uniform, unit baseline, points in [-10, 10]³ in front of
  both cameras) restricted to a 90° field of view; the point lies on a patch with a random normal
  facing the query camera;
* **RANSAC draws** for 99 % confidence at 40 % inliers: ``ceil(log(0.01) / log(1 - w^s))``.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

from planarloc.geometry.planar import relpose_from_planar_params
from planarloc.solvers.relpose_planar_1ac import (
    relpose_planar_1ac,
    relpose_planar_1ac_batch,
    solve_planar_1ac,
)
from planarloc.solvers.relpose_planar_2p import relpose_planar_2p, relpose_planar_2p_batch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from solvers import loop_planar_2p  # noqa: E402

F_PX = 500.0  # focal length of both cameras for the noise models, pixels


def scenes(rng: np.random.Generator, m: int, fov_tan: float = 1.0):
    """m planar scenes, each with 2 points; point 0 has its true local affine map (normalized).

    Returns R (m, 3, 3), t (m, 3), xq, xr (m, 2, 3) rays (x, y, 1), A (m, 2, 2)."""
    out = []
    while len(out) < m:
        pose = relpose_from_planar_params(*rng.uniform(-np.pi, np.pi, 2))
        X = rng.uniform(-10.0, 10.0, (64, 3))
        Xr = X @ pose.R.T + pose.t
        ok = (X[:, 2] > 0.1) & (Xr[:, 2] > 0.1)
        ok &= (np.abs(X[:, :2]) < fov_tan * X[:, 2:]).all(1) & (np.abs(Xr[:, :2]) < fov_tan * Xr[:, 2:]).all(
            1
        )
        if ok.sum() < 2:
            continue
        X = X[ok][:2]
        xq = X / X[:, 2:]
        n = rng.normal(size=3)
        n -= 1.5 * np.linalg.norm(n) * xq[0] / np.linalg.norm(xq[0])  # face the query camera
        n /= np.linalg.norm(n)
        H = pose.R + np.outer(pose.t, n) / (n @ X[0])
        y = H @ xq[0]
        x0 = y / y[2]
        A = (H[:2, :2] - np.outer(x0[:2], H[2, :2])) / y[2]
        Xr0 = X @ pose.R.T + pose.t
        out.append((pose.R, pose.t, xq, Xr0 / Xr0[:, 2:], A))
    return [np.array(v) for v in zip(*out)]


# ---- timing ---------------------------------------------------------------------------------


@njit  # not cached: a cached caller would keep a stale copy of an edited solver
def _kernel_loop_1ac(xq, xr, A, reps):
    sol = np.empty(3)
    total = 0
    for _ in range(reps):
        for i in range(xq.shape[0]):
            total += solve_planar_1ac(xq[i], xr[i], A[i], sol)
    return total


def interleaved(fn_a, fn_b, per: int, k: int) -> tuple[list[float], list[float]]:
    """k repetitions of (fn_a, fn_b), µs per item (``per`` items per call)."""
    ta, tb = [], []
    for _ in range(k):
        t0 = time.perf_counter()
        fn_a()
        t1 = time.perf_counter()
        fn_b()
        t2 = time.perf_counter()
        ta.append((t1 - t0) / per * 1e6)
        tb.append((t2 - t1) / per * 1e6)
    return ta, tb


def row(name: str, ta: list[float], tb: list[float]) -> str:
    ba, bb = min(ta), min(tb)
    ma, mb = statistics.median(ta), statistics.median(tb)
    return f"{name:<26} {ba:9.3f} {ma:9.3f} | {bb:9.3f} {mb:9.3f} | {ba / bb:6.2f}x {ma / mb:6.2f}x"


def timing(rng: np.random.Generator, quick: bool) -> None:
    n_single = 2000 if quick else 10000
    n_batch = 20000 if quick else 100000
    k = 5 if quick else 11
    _R, _t, xq, xr, A = scenes(rng, n_single)
    xq1, xr1, A1 = np.ascontiguousarray(xq[:, 0]), np.ascontiguousarray(xr[:, 0]), np.ascontiguousarray(A)
    xq2, xr2 = np.ascontiguousarray(xq), np.ascontiguousarray(xr)
    # warm up (compile) every path
    relpose_planar_1ac(xq1[0], xr1[0], A1[0])
    relpose_planar_2p(xq2[0], xr2[0])
    relpose_planar_1ac_batch(xq1[:10], xr1[:10], A1[:10])
    relpose_planar_2p_batch(xq2[:10], xr2[:10])
    _kernel_loop_1ac(xq1[:10], xr1[:10], A1[:10], 1)
    loop_planar_2p(xq2[:10], xr2[:10], 1)

    def single_1ac() -> None:
        for i in range(n_single):
            relpose_planar_1ac(xq1[i], xr1[i], A1[i])

    def single_2p() -> None:
        for i in range(n_single):
            relpose_planar_2p(xq2[i], xr2[i])

    reps = n_batch // n_single
    Bq1, Br1, BA = np.tile(xq1, (reps, 1)), np.tile(xr1, (reps, 1)), np.tile(A1, (reps, 1, 1))
    Bq2, Br2 = np.tile(xq2, (reps, 1, 1)), np.tile(xr2, (reps, 1, 1))
    kreps = 20
    print(f"timing: µs per sample, best and median of {k}; load average {os.getloadavg()[0]:.2f}")
    print(
        f"{'':<26} {'1ac best':>9} {'1ac med':>9} | {'2p best':>9} {'2p med':>9} | ratio 1ac/2p (best, med)"
    )
    print(row(f"single call (n={n_single})", *interleaved(single_1ac, single_2p, n_single, k)))
    print(
        row(
            f"batch API (M={len(Bq1)})",
            *interleaved(
                lambda: relpose_planar_1ac_batch(Bq1, Br1, BA),
                lambda: relpose_planar_2p_batch(Bq2, Br2),
                len(Bq1),
                k,
            ),
        )
    )
    print(
        row(
            "compiled kernel",
            *interleaved(
                lambda: _kernel_loop_1ac(xq1, xr1, A1, kreps),
                lambda: loop_planar_2p(xq2, xr2, kreps),
                n_single * kreps,
                k,
            ),
        )
    )


# ---- accuracy -------------------------------------------------------------------------------


def rot2(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def nearest_similarity(A: np.ndarray) -> np.ndarray:
    a = 0.5 * (A[:, 0, 0] + A[:, 1, 1])
    b = 0.5 * (A[:, 1, 0] - A[:, 0, 1])
    return np.stack([np.stack([a, -b], -1), np.stack([b, a], -1)], -2)


def errors(Rs: np.ndarray, ts: np.ndarray, valid: np.ndarray, R: np.ndarray, t: np.ndarray):
    """Rotation and translation-direction errors (deg) of the closest valid solution; NaN if none."""
    cos_r = (np.einsum("mkij,mij->mk", Rs, R) - 1.0) / 2.0
    er = np.degrees(np.arccos(np.clip(cos_r, -1.0, 1.0)))
    et = np.degrees(np.arccos(np.clip(np.einsum("mki,mi->mk", ts, t), -1.0, 1.0)))
    score = np.where(valid, er + et, np.inf)
    best = np.argmin(score, axis=1)
    idx = np.arange(len(R))
    ok = np.isfinite(score[idx, best])
    return np.where(ok, er[idx, best], np.nan), np.where(ok, et[idx, best], np.nan)


def summary(er: np.ndarray, et: np.ndarray) -> str:
    ok = np.isfinite(er)
    return (
        f"{np.median(er[ok]):8.3f} {np.median(et[ok]):8.3f} {np.percentile(et[ok], 90):8.2f} "
        f"{100 * (1 - ok.mean()):6.1f}%"
    )


def accuracy(rng: np.random.Generator, quick: bool) -> None:
    m = 4000 if quick else 20000
    R, t, xq, xr, A = scenes(rng, m)
    print(
        f"\naccuracy: {m} scenes, f = {F_PX:.0f} px; median rotation error, median and 90th percentile "
        "translation-direction error (deg), no-solution rate"
    )
    print(f"{'solver / noise':<44} {'rot med':>8} {'t med':>8} {'t p90':>8} {'none':>7}")

    def px_noise(x: np.ndarray, sigma: float) -> np.ndarray:
        out = x.copy()
        out[..., :2] += rng.normal(scale=sigma / F_PX, size=x[..., :2].shape)
        return out

    for sigma in (0.0, 0.5, 1.0, 2.0):
        Rs, ts, valid = relpose_planar_2p_batch(px_noise(xq, sigma), px_noise(xr, sigma))
        print(f"{f'2p, pixel noise {sigma} px':<44} " + summary(*errors(Rs, ts, valid, R, t)))
    grid = (
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 1.0),
        (0.0, 0.02, 0.0),
        (1.0, 0.0, 0.0),
        (1.0, 0.02, 1.0),
        (3.0, 0.05, 1.0),
        (5.0, 0.10, 1.0),
        (10.0, 0.20, 1.0),
    )
    for model in ("true affine", "SIFT similarity"):
        base = A if model == "true affine" else nearest_similarity(A)
        for s_ang, s_sc, s_px in grid if model == "true affine" else grid[:1] + grid[4:]:
            noisy = (
                np.exp(rng.normal(scale=s_sc, size=m))[:, None, None]
                * rot2(np.radians(rng.normal(scale=s_ang, size=m)))
                @ base
            )
            q, r = px_noise(xq[:, 0], s_px), px_noise(xr[:, 0], s_px)
            label = f"1ac, {model}, {s_ang:g}° / {100 * s_sc:g}% / {s_px:g} px"
            Rs, ts, valid, _ = relpose_planar_1ac_batch(q, r, noisy)
            print(f"{label:<44} " + summary(*errors(Rs, ts, valid, R, t)))
            if model == "true affine" and 0 < s_ang + s_sc + s_px and s_ang + s_sc < 3:
                Rs, ts, valid = authors_1ac_cs(q, r, noisy)
                print(
                    f"{'  authors 1AC_CS (no cone projection)':<44} " + summary(*errors(Rs, ts, valid, R, t))
                )


def authors_1ac_cs(xq: np.ndarray, xr: np.ndarray, A: np.ndarray):
    """Reference: Guan et al.'s ``1AC_CS`` in numpy (least right singular vector of M, each pair
    put on its circle). It leaves the sign of t open, so both signs are returned and the closest
    is scored (no cheirality: its no-solution rate is 0 by construction)."""
    u1, v1, u2, v2 = xq[:, 0], xq[:, 1], xr[:, 0], xr[:, 1]
    a00, a01, a10, a11 = A[:, 0, 0], A[:, 0, 1], A[:, 1, 0], A[:, 1, 1]
    z, o = np.zeros_like(u1), np.ones_like(u1)
    M = np.stack(
        [
            np.stack([v1, v1 * u2, v2, -u1 * v2], -1),
            np.stack([z, a00 * v1, a10, -(a10 * u1 + v2)], -1),
            np.stack([o, a01 * v1 + u2, a11, -a11 * u1], -1),
        ],
        1,
    )
    M /= np.linalg.norm(M, axis=2, keepdims=True)
    x = np.linalg.svd(M)[2][:, 3]
    phi = np.arctan2(x[:, 2], x[:, 3])
    theta = np.arctan2(x[:, 0], x[:, 1]) + phi
    Rs = np.stack([relpose_from_planar_params(a, b).R for a, b in zip(theta, phi)])[:, None].repeat(2, 1)
    ts = np.stack([relpose_from_planar_params(a, b).t for a, b in zip(theta, phi)])
    return Rs, np.stack([ts, -ts], 1), np.ones((len(x), 2), bool)


def ransac_draws() -> None:
    print("\nRANSAC draws for 99 % confidence at 40 % inliers, ceil(log(0.01) / log(1 - 0.4^s)):")
    for s, what in (
        (1, "1ac (relative pose, 1 affine correspondence)"),
        (2, "2p (relative pose, 2 points)"),
        (2, "1ac1p (absolute, 1 AC + 1 point)"),
        (3, "2p1p (absolute, 3 points)"),
    ):
        n = math.ceil(math.log(0.01) / math.log(1 - 0.4**s))
        print(f"  s = {s}: {n:3d} draws   {what}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer samples and repetitions")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    timing(rng, args.quick)
    accuracy(rng, args.quick)
    ransac_draws()


if __name__ == "__main__":
    main()
