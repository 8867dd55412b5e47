"""Local structure vs the triangulate + PnP peer, in one process on the same map images (issue 17).

The peer is what a user would write in 60 lines with OpenCV and PoseLib (NOTES.md, "Measured
here in December 2026"): OpenCV SIFT (4,000 features, RootSIFT), ``cv2.BFMatcher`` + Lowe's
ratio test (0.8); for every pair of the 5 retrieved map images: match, triangulate with their
known poses (``cv2.triangulatePoints``), keep the points in front of both cameras with a
reprojection error below 2 px in both; link the query's matches to the first image of each pair
to those points; PoseLib ``estimate_absolute_pose`` (LO-RANSAC PnP, 4 px). It has no failure
status: whatever pose it returns is evaluated.

planarloc runs with its defaults (``method="auto"``, ``structure="tracks"``: local structure
from the retrieved map images, VLAD top-5). The peer gets two retrievals: planarloc's own (the
very map images our estimator saw) and the oracle (the 5 map images nearest to the query's true
centre).

Per sequence and map spacing: success at the paper's three thresholds, successes beyond
1 m / 20° ("wrong"), broken promises (our successes farther than 3·position_std_m + 5 cm from
the truth; the peer makes no promise), median error, and time per query (features, retrieval,
matching and estimation; the peer's map features are extracted once and cached, like ours).

    python benchmarks/structure_peer.py                       # kitti_seq1 and kitti_seq2, map every 2 and 4
    python benchmarks/structure_peer.py --sequences kitti_seq1 --map-every 4 --json out.json
    python benchmarks/structure_peer.py --map-every 4 --seed 1    # our RANSAC seed (default 0)
"""

from __future__ import annotations

import argparse
import itertools
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _peer_pipeline as peer  # noqa: E402
from _datasets import build_or_reuse  # noqa: E402

from planarloc.evaluation.queries import THRESHOLDS, split_map_queries, threshold_name  # noqa: E402
from planarloc.features.extract import FeatureConfig, extract_features  # noqa: E402
from planarloc.features.images import read_gray  # noqa: E402
from planarloc.geometry.pose import Pose  # noqa: E402
from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.localize.localizer import Localizer, localizer_config  # noqa: E402
from planarloc.map.codec import DEFAULT_STORAGE, STORAGE_LAYOUTS  # noqa: E402
from planarloc.map.posed_image import PosedImage  # noqa: E402
from planarloc.map.store import MapDatabase  # noqa: E402

DATA_ROOT = Path(__file__).resolve().parents[2] / "shared" / "data"
SEQUENCES = ["kitti_seq1", "kitti_seq2"]
MAP_EVERY = [2, 4]
TOP_N = 5
RATIO = 0.8
TRIANGULATION_PX = 2.0
PNP_PX = 4.0
STD_MARGIN_M = 0.05


class TriangulatePnPPeer:
    """The peer: SIFT + ratio test, triangulation between map-image pairs, PoseLib PnP."""

    def __init__(self, max_features: int = 4000) -> None:
        self.sift = peer.opencv_sift(max_features)
        self.matcher = cv2.BFMatcher(cv2.NORM_L2)
        self._features: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def _extract(self, image: PosedImage) -> tuple[np.ndarray, np.ndarray]:
        """RootSIFT keypoints and descriptors of one image."""
        kp, d = peer.sift_features(self.sift, cv2.imread(str(image.path), cv2.IMREAD_GRAYSCALE))
        return kp, np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12)).astype(np.float32)

    def features(self, image: PosedImage) -> tuple[np.ndarray, np.ndarray]:
        """Features of a map image, extracted once (like a map's stored features)."""
        if image.name not in self._features:
            self._features[image.name] = self._extract(image)
        return self._features[image.name]

    @staticmethod
    def _projection(image: PosedImage) -> np.ndarray:
        return image.camera.K @ np.hstack([image.cam_from_world.R, image.cam_from_world.t[:, None]])

    def _pair_points(self, a: PosedImage, b: PosedImage) -> dict[int, np.ndarray]:
        """Map keypoint of a -> world point, triangulated with b and checked in both views."""
        ka, da = self.features(a)
        kb, db = self.features(b)
        m = peer.bf_ratio_match(self.matcher, da, db, RATIO)
        if len(m) == 0:
            return {}
        Xh = cv2.triangulatePoints(
            self._projection(a), self._projection(b), ka[m[:, 0]].T.astype(float), kb[m[:, 1]].T.astype(float)
        )
        X = (Xh[:3] / Xh[3]).T
        ok = np.ones(len(X), dtype=bool)
        for image, kp in ((a, ka[m[:, 0]]), (b, kb[m[:, 1]])):
            Xc = X @ image.cam_from_world.R.T + image.cam_from_world.t
            uv = Xc @ image.camera.K.T
            with np.errstate(invalid="ignore", divide="ignore"):
                uv = uv[:, :2] / uv[:, 2:]
            ok &= (Xc[:, 2] > 0) & (np.linalg.norm(uv - kp, axis=1) < TRIANGULATION_PX)
        return {int(i): X[j] for j, i in enumerate(m[:, 0]) if ok[j]}

    def localize(self, query: PosedImage, refs: Sequence[PosedImage]) -> Pose | None:
        kq, dq = self._extract(query)
        x2d, X3d = [], []
        query_matches: dict[str, np.ndarray] = {}
        for a, b in itertools.combinations(refs, 2):
            points = self._pair_points(a, b)
            if a.name not in query_matches:
                query_matches[a.name] = peer.bf_ratio_match(self.matcher, dq, self.features(a)[1], RATIO)
            for qi, ai in query_matches[a.name]:
                X = points.get(int(ai))
                if X is not None:
                    x2d.append(kq[qi])
                    X3d.append(X)
        if len(x2d) < 4:
            return None
        pose, _ = peer.poselib.estimate_absolute_pose(
            np.asarray(x2d, dtype=float),
            np.asarray(X3d, dtype=float),
            peer.poselib_camera(query.camera),
            {"max_reproj_error": PNP_PX},
            {},
        )
        return Pose(pose.R, pose.t)


def summarise(rows: Sequence[dict], with_std: bool) -> dict:
    n = len(rows)
    e = np.array([(r["t_err"], r["r_err"]) for r in rows], dtype=float).reshape(-1, 2)
    ok = np.array([r["success"] for r in rows], dtype=bool)
    success = {
        threshold_name(t, r): 100.0 * float((ok & (e[:, 0] < t) & (e[:, 1] < r)).sum()) / max(n, 1)
        for t, r in THRESHOLDS
    }
    wrong = int((ok & ~((e[:, 0] <= 1.0) & (e[:, 1] <= 20.0))).sum())
    broken = None
    if with_std:
        std = np.array([r["std"] for r in rows], dtype=float)
        broken = int((ok & (e[:, 0] > 3.0 * std + STD_MARGIN_M)).sum())
    return {
        "queries": n,
        "success": success,
        "wrong_beyond_1m_20deg": wrong,
        "broken_promises": broken,
        "median_error_m": float(np.median(e[ok, 0])) if ok.any() else None,
        "seconds_per_query": float(np.mean([r["seconds"] for r in rows])) if n else None,
        "failures": dict(Counter(r["status"] for r in rows if not r["success"])),
    }


def run_sequence(
    folder: Path,
    map_every: int,
    root: Path,
    progress: peer.Progress,
    seed: int = 0,
    storage: str = DEFAULT_STORAGE,
) -> dict:
    images = read_dataset(folder, "kitti")
    map_images, queries = split_map_queries(images, map_every)
    by_name = {m.name: m for m in map_images}
    path = root / f"{folder.name}-every{map_every}-{storage}.db"
    build_or_reuse(map_images, path, FeatureConfig(), reuse=True, storage=storage)
    the_peer = TriangulatePnPPeer()
    ours, peer_ours, peer_oracle = [], [], []
    with MapDatabase.open(path) as db:
        loc = Localizer(db, localizer_config(seed=seed))
        for i, q in enumerate(queries):
            t0 = time.perf_counter()
            est = loc.localize(read_gray(q.path), q.camera)
            t1 = time.perf_counter()
            te, re = peer.errors_of(est.pose if est.success else None, q.cam_from_world)
            ours.append(
                {
                    "name": q.name,
                    "success": bool(est.success),
                    "status": est.status,
                    "t_err": te,
                    "r_err": re,
                    "std": est.position_std_m,
                    "seconds": t1 - t0,
                }
            )
            for rows, refs in (
                (
                    peer_ours,
                    est.references or loc.retrieve(extract_features(read_gray(q.path), loc.features)),
                ),
                (peer_oracle, peer.oracle_references(q, map_images, TOP_N)),
            ):
                t2 = time.perf_counter()
                pose = the_peer.localize(q, [by_name[r] for r in refs])
                te, re = peer.errors_of(pose, q.cam_from_world)
                rows.append(
                    {
                        "name": q.name,
                        "success": pose is not None,
                        "status": "no_pose" if pose is None else "success",
                        "t_err": te,
                        "r_err": re,
                        "seconds": time.perf_counter() - t2,
                    }
                )
            progress(f"{folder.name} every {map_every}", i + 1, len(queries))
    return {
        "sequence": folder.name,
        "map_every": map_every,
        "map_images": len(map_images),
        "queries": len(queries),
        "planarloc": summarise(ours, True),
        "peer_our_retrieval": summarise(peer_ours, False),
        "peer_oracle_retrieval": summarise(peer_oracle, False),
        "per_query": {
            "planarloc": ours,
            "peer_our_retrieval": peer_ours,
            "peer_oracle_retrieval": peer_oracle,
        },
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--sequences", nargs="+", default=SEQUENCES, help="folders under --data-root (KITTI layout)"
    )
    p.add_argument("--map-every", nargs="+", type=int, default=MAP_EVERY, help="map = every N-th frame")
    p.add_argument("--data-root", type=Path, default=DATA_ROOT)
    p.add_argument("--json", type=Path)
    p.add_argument(
        "--storage",
        choices=STORAGE_LAYOUTS,
        default=DEFAULT_STORAGE,
        help="layout of the maps (default: %(default)s, the library's)",
    )
    p.add_argument("--seed", type=int, default=0, help="RANSAC seed of planarloc (default 0, the library's)")
    p.add_argument(
        "--cache-dir", type=Path, default=Path(tempfile.gettempdir()) / "planarloc-bench" / "structure"
    )
    args = p.parse_args(argv)
    if not peer.have_poselib():
        p.error("the peer needs PoseLib: pip install -e '.[bench]'")
    args.cache_dir.mkdir(parents=True, exist_ok=True)
    print(peer.code_note())
    print(peer.load_note("at start"))
    print(f"planarloc RANSAC seed {args.seed}")
    results = []
    progress = peer.Progress()
    for name in args.sequences:
        folder = args.data_root / name
        if not folder.is_dir():
            peer.log(f"{folder} not found, skipped")
            continue
        for every in args.map_every:
            results.append(run_sequence(folder, every, args.cache_dir, progress, args.seed, args.storage))
    heads = [
        "sequence",
        "map",
        "who",
        *[threshold_name(t, r) for t, r in THRESHOLDS],
        "> 1m/20°",
        "broken promises",
        "median [m]",
        "s/query",
        "failures",
    ]
    rows = []
    for r in results:
        for who, key in (
            ("planarloc (auto, tracks)", "planarloc"),
            ("peer, our retrieval", "peer_our_retrieval"),
            ("peer, oracle top-5", "peer_oracle_retrieval"),
        ):
            s = r[key]
            rows.append(
                [
                    r["sequence"],
                    f"every {r['map_every']}",
                    who,
                    *[peer.fmt_pct(v) for v in s["success"].values()],
                    str(s["wrong_beyond_1m_20deg"]),
                    "-" if s["broken_promises"] is None else str(s["broken_promises"]),
                    peer.fmt_num(s["median_error_m"]),
                    peer.fmt_num(s["seconds_per_query"], 2),
                    ", ".join(f"{k} {v}" for k, v in s["failures"].items()) or "-",
                ]
            )
    print(
        peer.markdown_table(
            heads, rows, "Local structure vs triangulate + PnP (success within the thresholds)"
        )
    )
    for r in results:
        gap = (
            r["peer_our_retrieval"]["success"][threshold_name(*THRESHOLDS[0])]
            - r["planarloc"]["success"][threshold_name(*THRESHOLDS[0])]
        )
        print(
            peer.verdict(
                gap <= 1.0 and r["planarloc"]["wrong_beyond_1m_20deg"] == 0,
                f"{r['sequence']} every {r['map_every']}: planarloc within 1 point of the peer at "
                f"{threshold_name(*THRESHOLDS[0])} (gap {gap:+.1f}) with no success beyond 1 m / 20°",
            )
        )
    print(peer.load_note("at end"))
    peer.write_json(args.json, {"code": peer.code_version(), "seed": args.seed, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
