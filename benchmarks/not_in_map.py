"""``not_in_map`` on real data: queries from places a map does not hold, and queries it does.

Two kinds of runs on the shared data (issue 32):

- **elsewhere**: every query comes from a place the map does not hold — kitti_seq1's road against
  a map of kitti_seq2's and the reverse, fountain_p11 against a map of entry_p10 and the reverse
  (two Strecha scenes; whether they share any façade is not documented). Wanted: no success, and
  ``not_in_map`` for as many as the data allow.
- **held**: the map is every 2nd frame of a set, the queries the others. Wanted: no query called
  ``not_in_map`` (a wrong status would send the user to map a place the map holds).

Each run prints queries, successes, ``not_in_map`` and the other statuses, and how many successes
are wrong beyond 0.25 m / 10° (and beyond 1 m) where the truth is in the map's frame.

    python benchmarks/not_in_map.py [--json not_in_map.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

from planarloc.geometry.pose import pose_errors
from planarloc.io.datasets import read_dataset
from planarloc.localize.localizer import Localizer, localizer_config
from planarloc.map.builder import build_map

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SETS = {"kitti_seq1": "kitti", "kitti_seq2": "kitti", "fountain_p11": "kapture", "entry_p10": "kapture"}
ELSEWHERE = [
    ("kitti_seq2", "kitti_seq1"),
    ("kitti_seq1", "kitti_seq2"),
    ("entry_p10", "fountain_p11"),
    ("fountain_p11", "entry_p10"),
]


def run(label: str, kind: str, map_images: list, queries: list, folder: Path, truth_in_frame: bool) -> dict:
    path = build_map(map_images, folder / f"{label}.db")
    loc = Localizer(path, localizer_config(structure="tracks"))
    statuses: Counter[str] = Counter()
    wrong = beyond = 0
    t0 = time.perf_counter()
    for q in queries:
        est = loc.localize(q.path, q.camera)
        statuses[str(est.status)] += 1
        if est.success and truth_in_frame:
            t, r = pose_errors(est.pose, q.cam_from_world)
            wrong += not (t < 0.25 and r < 10.0)
            beyond += not (t < 1.0 and r < 20.0)
    n = len(queries)
    out = {
        "label": label,
        "kind": kind,
        "queries": n,
        "success": statuses.get("success", 0),
        "not_in_map": statuses.get("not_in_map", 0),
        "statuses": dict(statuses),
        "wrong_successes": wrong if truth_in_frame else None,
        "beyond_1m": beyond if truth_in_frame else None,
        "seconds_per_query": (time.perf_counter() - t0) / max(n, 1),
    }
    other = ", ".join(f"{k} {v}" for k, v in sorted(statuses.items()) if k not in ("success", "not_in_map"))
    print(
        f"{label:34s} {kind:9s} {n:3d} queries  success {out['success']:3d}  not_in_map "
        f"{out['not_in_map']:3d}  wrong {out['wrong_successes']}  other: {other or '-'}  "
        f"({out['seconds_per_query']:.2f} s/query)",
        flush=True,
    )
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--json", type=Path, help="write the results here")
    args = p.parse_args(argv)
    if not SHARED.is_dir():
        print(f"no shared data at {SHARED}", file=sys.stderr)
        return 2
    data = {name: read_dataset(SHARED / name, fmt) for name, fmt in SETS.items()}
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for map_set, query_set in ELSEWHERE:
            results.append(
                run(
                    f"{query_set} vs map of {map_set}",
                    "elsewhere",
                    data[map_set],
                    data[query_set],
                    folder,
                    truth_in_frame=False,
                )
            )
        for name, images in data.items():
            results.append(
                run(f"{name} (map every 2nd)", "held", images[::2], images[1::2], folder, truth_in_frame=True)
            )
    elsewhere = [r for r in results if r["kind"] == "elsewhere"]
    held = [r for r in results if r["kind"] == "held"]
    print(
        f"elsewhere: {sum(r['not_in_map'] for r in elsewhere)} of {sum(r['queries'] for r in elsewhere)} "
        f"queries not_in_map, {sum(r['success'] for r in elsewhere)} successes; held: "
        f"{sum(r['not_in_map'] for r in held)} of {sum(r['queries'] for r in held)} queries called "
        f"not_in_map, {sum(r['wrong_successes'] for r in held)} wrong successes"
    )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1) + "\n")
    return 0 if all(r["success"] == 0 for r in elsewhere) and all(r["not_in_map"] == 0 for r in held) else 1


if __name__ == "__main__":
    np.seterr(all="ignore")
    raise SystemExit(main())
