"""Shared benchmark code: the OpenCV + PoseLib peer pipeline, and the plumbing of the scripts.

The peer is what a user would write without planarloc: OpenCV SIFT, ``cv2.BFMatcher`` with
Lowe's ratio test, and PoseLib's ``estimate_generalized_relative_pose`` (6DoF, 2D-2D
constraints only) with the retrieved map images as a generalized camera.

PoseLib convention used here (checked on a synthetic scene: the returned pose equals the
query's ``cam_from_world`` to 1e-12): rig 1 = the map images, each with extrinsic = its
``cam_from_world`` (so the rig frame is the world), rig 2 = the query alone with the identity
extrinsic; PoseLib returns ``rig2_from_rig1`` = ``query_from_world``.

Not part of the package: benchmarks sit on top of it and may import anything.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from planarloc.evaluation.queries import THRESHOLDS, threshold_name
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.map.posed_image import PosedImage

try:
    import poselib
except ImportError:  # the peer is optional: `pip install -e ".[bench]"`
    poselib = None

LOAD_WARNING = 1.5
"""1-minute load average above which timings are flagged as unreliable."""


# ---- PoseLib ------------------------------------------------------------------------------------
def have_poselib() -> bool:
    return poselib is not None


def poselib_version() -> str | None:
    if poselib is None:
        return None
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("poselib")
    except PackageNotFoundError:
        return getattr(poselib, "__version__", "?")


def poselib_camera(camera: Camera) -> dict:
    """A planarloc Camera as PoseLib's camera dict (same COLMAP model names and parameter order)."""
    return {
        "model": camera.model.value,
        "width": camera.width,
        "height": camera.height,
        "params": list(camera.params),
    }


def poselib_pose(pose: Pose):
    """A planarloc Pose (``b_from_a``) as a PoseLib CameraPose (same ``x_b = R x_a + t``)."""
    p = poselib.CameraPose()
    p.R, p.t = np.asarray(pose.R), np.asarray(pose.t)
    return p


@dataclass
class PeerMatches:
    """Matches between the query and one reference, in pixels: (N, 2) each."""

    ref_pose: Pose
    ref_camera: Camera
    query_px: np.ndarray
    ref_px: np.ndarray


@dataclass
class PeerResult:
    """Outcome of the peer on one query. ``pose`` is None when PoseLib was not run."""

    pose: Pose | None
    num_inliers: int
    seconds: float
    info: dict


def generalized_relative_pose(
    query_camera: Camera,
    pairs: Sequence[PeerMatches],
    ransac_opt: dict | None = None,
    bundle_opt: dict | None = None,
    min_matches: int = 6,
) -> PeerResult:
    """PoseLib ``estimate_generalized_relative_pose`` of the query against ``pairs``.

    Pairs with no match are left out (PoseLib needs none of them). With fewer than
    ``min_matches`` matches in total (its minimal sample is 6) the peer is not run and
    ``pose`` is None. ``ransac_opt`` / ``bundle_opt`` default to PoseLib's own defaults.
    PoseLib has no failure status: whatever pose it returns is evaluated.
    """
    if poselib is None:
        raise RuntimeError("poselib is not installed: pip install -e '.[bench]'")
    used = [p for p in pairs if len(p.query_px) > 0]
    if sum(len(p.query_px) for p in used) < min_matches:
        return PeerResult(None, 0, 0.0, {})
    matches = []
    for k, p in enumerate(used):
        m = poselib.PairwiseMatches()
        m.cam_id1, m.cam_id2 = k, 0
        m.x1 = np.asarray(p.ref_px, dtype=np.float64)
        m.x2 = np.asarray(p.query_px, dtype=np.float64)
        matches.append(m)
    t0 = time.perf_counter()
    pose, info = poselib.estimate_generalized_relative_pose(
        matches,
        [poselib_pose(p.ref_pose) for p in used],
        [poselib_camera(p.ref_camera) for p in used],
        [poselib_pose(Pose.identity())],
        [poselib_camera(query_camera)],
        dict(ransac_opt or {}),
        dict(bundle_opt or {}),
    )
    seconds = time.perf_counter() - t0
    return PeerResult(
        Pose(pose.R, pose.t),
        int(info.get("num_inliers", 0)),
        seconds,
        {k: v for k, v in info.items() if k != "inliers"},
    )


# ---- OpenCV -------------------------------------------------------------------------------------
def opencv_sift(max_features: int) -> cv2.SIFT:
    """Plain OpenCV SIFT with its defaults except the number of features."""
    return cv2.SIFT_create(nfeatures=int(max_features))


def sift_features(sift: cv2.SIFT, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 2) float32 keypoints and (N, 128) float32 SIFT descriptors of a grayscale image."""
    kps, desc = sift.detectAndCompute(gray, None)
    if not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32)
    return np.array([k.pt for k in kps], dtype=np.float32), desc


def bf_ratio_match(matcher: cv2.BFMatcher, dq: np.ndarray, dr: np.ndarray, ratio: float = 0.8) -> np.ndarray:
    """(K, 2) int (query, reference) indices kept by ``knnMatch(k=2)`` + Lowe's ratio test."""
    if len(dq) < 1 or len(dr) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    out = [
        (m.queryIdx, m.trainIdx)
        for m, n in (p for p in matcher.knnMatch(dq, dr, k=2) if len(p) == 2)
        if m.distance < ratio * n.distance
    ]
    return np.array(out, dtype=np.int64).reshape(-1, 2)


# ---- retrieval by ground truth --------------------------------------------------------------------
def oracle_references(query: PosedImage, map_images: Sequence[PosedImage], k: int = 5) -> list[str]:
    """Names of the ``k`` map images whose ground-truth centres are nearest to the query's."""
    centres = np.array([m.cam_from_world.center for m in map_images])
    d = np.linalg.norm(centres - query.cam_from_world.center, axis=1)
    return [map_images[i].name for i in np.argsort(d, kind="stable")[:k]]


# ---- evaluation of poses that have no planarloc status (the peer) --------------------------------
def success_rates(errors: Sequence[tuple[float, float]]) -> dict[str, float]:
    """Percent of queries within each of the paper's thresholds; NaN errors count as failures."""
    n = max(len(errors), 1)
    e = np.array(errors, dtype=float).reshape(-1, 2)
    return {
        threshold_name(t, r): 100.0 * float(((e[:, 0] < t) & (e[:, 1] < r)).sum()) / n for t, r in THRESHOLDS
    }


def errors_of(pose: Pose | None, truth: Pose) -> tuple[float, float]:
    return pose_errors(pose, truth) if pose is not None else (float("nan"), float("nan"))


# ---- plumbing of the benchmark scripts --------------------------------------------------------------
def code_version() -> dict:
    """Which planarloc was measured: git HEAD, uncommitted files, and a hash of the package sources
    (the package is installed editable, so uncommitted edits are what runs)."""
    import hashlib
    import subprocess

    import planarloc

    pkg = Path(planarloc.__file__).resolve().parent
    h = hashlib.sha1()
    for f in sorted(pkg.rglob("*.py")):
        h.update(f.relative_to(pkg).as_posix().encode())
        h.update(f.read_bytes())
    out = {"planarloc_version": planarloc.__version__, "source_sha1": h.hexdigest()[:12]}
    try:
        git = ["git", "-C", str(pkg.parent)]
        out["git_head"] = subprocess.run(
            [*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True
        ).stdout.strip()
        status = subprocess.run(
            [*git, "status", "--porcelain", "--", "planarloc"], capture_output=True, text=True, check=True
        ).stdout
        out["uncommitted_files"] = len(status.splitlines())
    except (OSError, subprocess.CalledProcessError):
        pass
    return out


def code_note() -> str:
    v = code_version()
    git = (
        f", git {v['git_head']} + {v.get('uncommitted_files', 0)} uncommitted file(s)"
        if "git_head" in v
        else ""
    )
    return f"planarloc {v['planarloc_version']} (sources sha1 {v['source_sha1']}{git})"


def load_average() -> tuple[float, float, float]:
    return os.getloadavg()


def load_note(label: str = "") -> str:
    """One line with the load average, and a warning when timings are not to be trusted."""
    la = load_average()
    text = (
        f"load average{(' ' + label) if label else ''}: {la[0]:.2f} {la[1]:.2f} {la[2]:.2f} "
        f"(1/5/15 min, {os.cpu_count()} CPUs)"
    )
    if la[0] > LOAD_WARNING:
        text += f"  WARNING: machine loaded (> {LOAD_WARNING}), timings are inflated by other jobs"
    return text


def print_header(*lines: str) -> None:
    """A run's heading on stdout: its own ``lines``, then which planarloc runs and the load at start."""
    for line in lines:
        print(line)
    print(code_note())
    print(load_note("at start"))


def log(message: str) -> None:
    """Progress and notes go to stderr; tables and verdicts to stdout."""
    print(message, file=sys.stderr, flush=True)


class Progress:
    """``update(stage, done, total)`` that prints a line on stderr at most every ``every`` seconds."""

    def __init__(self, every: float = 5.0) -> None:
        self.every = every
        self._last: dict[str, float] = {}
        self._start: dict[str, float] = {}

    def __call__(self, stage: str, done: int, total: int) -> None:
        now = time.perf_counter()
        self._start.setdefault(stage, now)
        if done >= total or now - self._last.get(stage, 0.0) >= self.every:
            self._last[stage] = now
            log(f"  {stage}: {done}/{total} ({now - self._start[stage]:.0f} s)")


def markdown_table(headers: Sequence[str], rows: Sequence[Sequence[object]], title: str | None = None) -> str:
    """A GitHub markdown table (copied as is into BENCHMARKS.md)."""
    cells = [[str(h) for h in headers]] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(headers))]
    lines = [f"**{title}**", ""] if title else []
    fmt = lambda r: "| " + " | ".join(c.ljust(w) for c, w in zip(r, widths)) + " |"  # noqa: E731
    lines.append(fmt(cells[0]))
    lines.append("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    lines += [fmt(r) for r in cells[1:]]
    return "\n".join(lines)


def verdict(ok: bool, text: str) -> str:
    return f"{'PASS' if ok else 'FAIL'}  {text}"


def write_json(path: Path | None, data: object) -> None:
    if path is None:
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1, default=_json_default))
    log(f"wrote {path}")


def _json_default(o: object) -> object:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def fmt_pct(v: float | None) -> str:
    return "-" if v is None else f"{v:.1f}%"


def fmt_num(v: float | None, digits: int = 3) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"
