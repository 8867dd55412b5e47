"""Feature types side by side (issue 33): RootSIFT, XFeat and ALIKED + LightGlue in the same run.

Per feature type (``--features``; a type whose packages do not load is skipped with the reason)
and data set, with the default Localizer (VLAD top-5, default method and structure mode, the
type's coarse pass: ``--coarse-keypoints 0`` measures without it):

- extraction: mean milliseconds per query image (``extract_features`` on the read image) and per
  map image (the map build's extraction, tilt-free: the build time / map images, cached maps: -);
- matching: mean milliseconds per query to match it against its 5 retrieved map images (the
  type's own matcher, :func:`planarloc.features.matching.match_query_to_refs`, timed inside the
  localization; both passes where a coarse pass fails), and per image pair;
- the rest of a localization: retrieval, local structure and robust estimation, mean ms per query;
- seconds per query: extraction + localization (retrieval, matching, robust estimation);
- success (%) at 0.25 m / 10°, 0.5 m / 10° and 1 m / 20°; confident-wrong: successes off by
  0.25 m or 10° or more; broken promises: successes off by more than 3·std + 5 cm; beyond 1 m:
  successes more than 1 m off; coarse pass: the queries its pose answered.

Timings are of warm code: before the timed queries, the first query is extracted and localized
once by a Localizer that is then dropped (torch's first inference, numba kernels and map
decoding would otherwise add 0.5-1 s to one query of each type, tens of ms to the mean).

Data sets (``benchmarks/trust.py``'s loaders): the shared KITTI ``kitti1-every4`` (kitti_seq1, a
straight road) and ``kitti-every4`` (kitti_seq2, a turn): map = every 4th frame, queries the rest;
the Strecha sets ``fountain_p11`` and ``entry_p10`` (map = even frames, queries = odd); and the
cross-session cases ``fountain-to-entry`` / ``entry-to-fountain`` (map = all of one set, queries =
all of the other). Maps are cached under ``--cache-dir`` keyed by content and feature settings.

Threads follow the machine (torch: one per core this process may use; OpenCV and BLAS: their
defaults); ``--torch-threads N`` sets torch's (``PLANARLOC_TORCH_THREADS``: on a loaded machine one
thread is several times faster, see :mod:`planarloc.features.learned`). ``aliked-lightglue`` needs torchvision
built for the installed torch: measure it in its own venv, e.g.::

    python benchmarks/features.py                                  # rootsift and xfeat (main venv)
    python benchmarks/features.py --datasets kitti1-every4 fountain_p11 --features rootsift xfeat
    /tmp/aliked-venv/bin/python benchmarks/features.py --features rootsift aliked-lightglue
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path

# isort: off
import planarloc  # noqa: F401 - first, before numpy: OpenBLAS's idle spin as `planarloc` sets it

# isort: on
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _datasets as cache  # noqa: E402
import _peer_pipeline as peer  # noqa: E402
import trust  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from planarloc.cli.console import progress_bar  # noqa: E402
from planarloc.evaluation.queries import query_result  # noqa: E402
from planarloc.extras import MissingExtraError  # noqa: E402
from planarloc.features import learned  # noqa: E402
from planarloc.features.extract import FeatureConfig, extract_features  # noqa: E402
from planarloc.features.images import read_gray  # noqa: E402
from planarloc.features.registry import FEATURE_TYPES  # noqa: E402
from planarloc.localize import query_matches as matches_module  # noqa: E402
from planarloc.localize.localizer import Localizer, LocalizerConfig  # noqa: E402
from planarloc.map.store import MapDatabase  # noqa: E402

DATASETS = [
    "kitti1-every4",
    "kitti-every4",
    "fountain_p11",
    "entry_p10",
    "fountain-to-entry",
    "entry-to-fountain",
]
HEADERS = [
    "data",
    "features",
    "queries",
    "extract ms (query)",
    "extract ms (map)",
    "match ms (5 refs)",
    "match ms/pair",
    "rest ms (query)",
    "s/query",
    "0.25m/10°",
    "0.5m/10°",
    "1m/20°",
    "confident wrong",
    "broken promises",
    "> 1 m",
    "median t [m]",
    "coarse pass",
]


class TimedMatcher:
    """``match_query_to_refs`` of the Localizer, timed: seconds and image pairs of each call."""

    def __init__(self) -> None:
        self.calls: list[tuple[float, int]] = []
        self._inner = matches_module.match_query_to_refs

    def __call__(self, q, refs, *args, **kwargs):
        t0 = time.perf_counter()
        out = self._inner(q, refs, *args, **kwargs)
        self.calls.append((time.perf_counter() - t0, len(refs)))
        return out


def run_type(
    kind: str,
    data: trust.DataSet,
    root: Path,
    update: Callable[[str, int, int], None],
    stride: int = 1,
    budget: int | None = None,
    coarse: int | None = None,
) -> dict:
    """Build (or reuse) the map of ``data`` with feature type ``kind`` (``budget`` keypoints per
    image, default the type's) and localize every ``stride``-th query (``coarse``: the
    localizer's ``coarse_keypoints``, default the type's)."""
    features = FeatureConfig(kind=kind) if budget is None else FeatureConfig(kind=kind, max_features=budget)
    map_path, build_s = cache.cached_map(
        data.map_images, f"{data.name}-{kind}", root, features=features, progress=update
    )
    config = LocalizerConfig(coarse_keypoints=coarse)
    rows, t_extract, coarse_answers = [], [], 0
    queries = data.queries[::stride]
    timed = TimedMatcher()
    matches_module.match_query_to_refs = timed
    try:
        with MapDatabase.open(map_path) as db:
            warm = Localizer(db, config)
            first = extract_features(read_gray(queries[0].path), warm.features)
            warm.localize_features(first, queries[0].camera)
            del warm
            timed.calls.clear()
            loc = Localizer(db, config)
            for i, q in enumerate(queries):
                gray = read_gray(q.path)
                t0 = time.perf_counter()
                f = extract_features(gray, loc.features)
                t_feat = time.perf_counter() - t0
                t1 = time.perf_counter()
                est = loc.localize_features(f, q.camera)
                t_loc = time.perf_counter() - t1
                coarse_answers += est.keypoint_budget > 0
                t_extract.append(t_feat)
                rows.append(asdict(query_result(q, est, t_feat + t_loc)))
                update(f"{kind} {data.name}", i + 1, len(queries))
    finally:
        matches_module.match_query_to_refs = timed._inner
    t_match = [t for t, _ in timed.calls]
    t_localize = [r["seconds"] - t for r, t in zip(rows, t_extract)]
    pairs = [n for _, n in timed.calls]
    m = trust.trust_metrics(rows)
    ok = [r for r in rows if r["success"]]
    return {
        "dataset": data.name,
        "features": kind,
        "feature_name": features.name,
        "queries": len(rows),
        "map_images": len(data.map_images),
        "build_s": build_s,
        "extract_ms_query": 1000 * float(np.mean(t_extract)),
        "extract_ms_map": 1000 * build_s / len(data.map_images) if build_s else None,
        # every query's matching calls (a coarse pass that fails is followed by a full one)
        "match_ms_query": 1000 * float(np.sum(t_match)) / max(1, len(rows)) if t_match else None,
        "match_ms_pair": 1000 * float(np.sum(t_match)) / max(1, int(np.sum(pairs))),
        "rest_ms_query": 1000 * (float(np.sum(t_localize)) - float(np.sum(t_match))) / max(1, len(rows)),
        "seconds_per_query": m["seconds_per_query"],
        "success": m["success"],
        "confident_wrong": m["confident_wrong"],
        "confident_wrong_queries": m["confident_wrong_queries"],
        "beyond_1m": sum(r["translation_error_m"] > 1.0 for r in ok),
        # a success promises its error within 3 std + 5 cm (benchmarks/trust.py)
        "broken_promises": [
            r["name"] for r in ok if r["translation_error_m"] > 3.0 * r["position_std_m"] + trust.STD_MARGIN_M
        ],
        "median_translation_error_m": float(np.median([r["translation_error_m"] for r in ok]))
        if ok
        else None,
        "status_counts": m["status_counts"],
        "coarse_answers": coarse_answers,  # answered by the coarse pass
        "per_query": rows,
    }


def table_row(r: dict) -> list[str]:
    return [
        r["dataset"],
        r["features"],
        str(r["queries"]),
        peer.fmt_num(r["extract_ms_query"], 0),
        peer.fmt_num(r["extract_ms_map"], 0),
        peer.fmt_num(r["match_ms_query"], 0),
        peer.fmt_num(r["match_ms_pair"], 0),
        peer.fmt_num(r["rest_ms_query"], 0),
        peer.fmt_num(r["seconds_per_query"], 3),
        *[peer.fmt_pct(v) for v in r["success"].values()],
        str(r["confident_wrong"]),
        str(len(r["broken_promises"])),
        str(r["beyond_1m"]),
        peer.fmt_num(r["median_translation_error_m"], 3),
        f"{r['coarse_answers']} of {r['queries']}",
    ]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--features",
        nargs="+",
        default=["rootsift", "xfeat", "aliked-lightglue"],
        choices=list(FEATURE_TYPES),
        help="feature types (default: all; rootsift is always measured)",
    )
    p.add_argument(
        "--datasets", nargs="+", default=DATASETS, choices=DATASETS, help="data sets (default: all)"
    )
    cache.add_cache_options(p, trust.DATA_ROOT, "maps, reused when their content matches")
    p.add_argument(
        "--query-stride",
        type=int,
        default=1,
        metavar="K",
        help="localize every K-th query only (a subset for slow types; default: all)",
    )
    p.add_argument(
        "--torch-threads",
        type=int,
        metavar="N",
        help="torch's threads for the learned types (default: PLANARLOC_TORCH_THREADS, else one per core)",
    )
    p.add_argument(
        "--max-features",
        nargs="+",
        default=[],
        metavar="KIND=N",
        help="keypoint budget of a feature type, e.g. xfeat=2048 (default: FeatureConfig's)",
    )
    p.add_argument(
        "--coarse-keypoints",
        type=int,
        metavar="N",
        help="the localizer's coarse pass for every type, 0 = none (default: each type's: xfeat 2048)",
    )
    p.add_argument("--json", type=Path, help="write all metrics and per-query results here")
    p.add_argument("--markdown", type=Path, help="write the table as markdown")
    args = p.parse_args(argv)
    if args.coarse_keypoints is not None and args.coarse_keypoints < 0:
        p.error(f"--coarse-keypoints: expected N >= 0, got {args.coarse_keypoints}")
    args.features = ["rootsift", *[k for k in args.features if k != "rootsift"]]
    budgets = {}
    for item in args.max_features:
        kind, _, n = item.partition("=")
        if kind not in FEATURE_TYPES or not n.isdigit() or int(n) < 1:
            p.error(f"--max-features: expected KIND=N with KIND in {list(FEATURE_TYPES)}, got {item!r}")
        budgets[kind] = int(n)
    args.budgets = budgets
    args.world_frames = trust.WORLD_FRAMES  # trust.load_dataset reads it (generated worlds are not used here)
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.torch_threads is not None:
        os.environ[learned.THREADS_ENV] = str(args.torch_threads)
    t_start = time.perf_counter()
    console = Console(width=200)
    root = cache.cache_root(args.cache_dir)
    title = "Feature types: default Localizer (VLAD top-5)" + (
        f", every {args.query_stride}th query" if args.query_stride > 1 else ""
    )
    console.print(f"# {title}")
    console.print(peer.code_note())
    console.print(peer.load_note("at start"))
    console.print(f"torch threads: {os.environ.get(learned.THREADS_ENV) or 'one per core'}")
    kinds, skipped = [], []
    for kind in args.features:
        try:
            learned.load_backend(kind)
            kinds.append(kind)
        except MissingExtraError as exc:
            skipped.append(f"{kind}: {exc}")
            peer.log(f"skipping {kind}: {exc}")
    results: list[dict] = []
    with progress_bar() as update:
        for name in args.datasets:
            data = trust.load_dataset(name, args, root, update)
            if data is None:
                skipped.append(f"{name}: data not found under {args.data_root}")
                continue
            for kind in kinds:
                r = run_type(
                    kind, data, root, update, args.query_stride, args.budgets.get(kind), args.coarse_keypoints
                )
                results.append(r)
                peer.log("| " + " | ".join(table_row(r)) + " |")
    table = Table(title=title)
    for h in HEADERS:
        table.add_column(h, justify="left" if h in ("data", "features") else "right")
    for r in results:
        table.add_row(*table_row(r))
    console.print(table)
    for line in skipped:
        console.print(f"skipped: {line}")
    markdown = peer.markdown_table(HEADERS, [table_row(r) for r in results], title)
    if args.markdown:
        args.markdown.write_text(markdown + "\n")
    trust.report_end(console, args, t_start, skipped, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
