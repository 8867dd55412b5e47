"""Trust: is every reported success right, and does ``position_std_m`` bound its error? (issue 8)

Per data set, method and structure mode:

- success (%) at the paper's thresholds 0.25 m/10°, 0.5 m/10°, 1 m/20°;
- confident-wrong: successes off by 0.25 m or 10° or more; gate: successes off by more than
  1 m or 20° (never acceptable);
- the worst error of a success (translation and rotation, not necessarily the same query);
- calibration: share of the successes whose centre error is within 1, 2 and 3 ``position_std_m``,
  and within 3 std + 0.05 m (the issue's target: >= 95 %);
- the motion model of the successes (``planar`` / ``6dof``) when the estimator reports one.

Data sets (map / queries):

- generated ``office`` worlds (``planarloc.synthetic.world``, 640x480, seed 0) with both robots'
  cameras mounted at pitch 0 or 10° and a query floor tilt of 0, 1 or 3° (``office-tilt3-pitch10``:
  3° of per-frame pitch/roll jitter, cameras pitched 10° down); the ``pitched`` preset (map camera
  pitched 11°, query camera 14° and 1° roll) and the ``offplane`` preset (hand-held queries
  0.2–0.7 m lower, tilted up to 4°); map = map trajectory, queries = query trajectory;
- the shared KITTI sequences: ``kitti_seq2`` (a turn) as ``kitti-every4`` / ``kitti-every2`` and
  ``kitti_seq1`` (a straight road) as ``kitti1-every4`` / ``kitti1-every2``: map = every 4th (2nd)
  frame, queries the rest;
- the Strecha sets ``fountain_p11`` and ``entry_p10`` (kapture): map = even frames, queries = odd;
- one site, two captures (issue 17): ``fountain-to-entry`` (map = all of fountain_p11, queries =
  all of entry_p10, whose facade stands far in the background of the fountain images) and
  ``entry-to-fountain``.

Maps are RootSIFT unless ``--features NAME`` (e.g. ``xfeat``, with ``planarloc[learned]``);
``--coarse-keypoints N [N ...]`` adds one configuration per coarse-pass budget (0: none; default:
the type's, :attr:`planarloc.localize.localizer_config.LocalizerConfig.coarse_keypoints`).
Queries are localized with the default Localizer (VLAD top-5) and no query gravity, unless
``--query-gravity truth`` (generated worlds only: the true gravity of ``gravity.txt``; needs a
Localizer whose ``localize_features`` accepts ``gravity=``). Worlds and maps are cached under
``--cache-dir`` (default ``$TMPDIR/planarloc-bench``), keyed by content (``_datasets.py``).

``--quick`` (CI, a few minutes on 2 cores): ``office-tilt3-pitch10``, ``kitti-every4``,
``fountain_p11`` and ``fountain-to-entry`` with the default method and both structure modes; the exit code is
1 when any success is off by more than 1 m or 20° (each offending query is printed), 0 otherwise. Without
``--quick`` the exit code only reports crashes and bad options (2).

    python benchmarks/trust.py --quick
    python benchmarks/trust.py --json trust.json --markdown trust.md
    python benchmarks/trust.py --datasets office-tilt3-pitch0 offplane --methods 2p1p
    python benchmarks/trust.py --features xfeat --methods auto --coarse-keypoints 0 2048
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _datasets as cache  # noqa: E402
import _peer_pipeline as peer  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from planarloc.cli.console import progress_bar  # noqa: E402
from planarloc.evaluation.queries import (
    THRESHOLDS,
    config_label,
    query_result,
    split_map_queries,
    threshold_name,
)
from planarloc.features.extract import FeatureConfig, extract_features  # noqa: E402
from planarloc.features.images import read_gray  # noqa: E402
from planarloc.features.registry import DEFAULT_FEATURE_TYPE, FEATURE_TYPES  # noqa: E402
from planarloc.io.datasets import read_dataset  # noqa: E402
from planarloc.localize.localizer import Localizer, LocalizerConfig  # noqa: E402
from planarloc.map.posed_image import PosedImage  # noqa: E402
from planarloc.map.store import MapDatabase  # noqa: E402
from planarloc.robust.options import Method, RansacOptions  # noqa: E402
from planarloc.synthetic.world.export import read_gravity  # noqa: E402
from planarloc.synthetic.world.presets import get_preset, robot_variant  # noqa: E402

DATA_ROOT = Path(__file__).resolve().parents[2] / "shared" / "data"
AUTO = "auto"
HAS_AUTO = AUTO in {m.value for m in Method}
DEFAULT_METHODS = [m.value for m in Method]  # every method by name
QUICK_METHOD = AUTO if HAS_AUTO else "2p1p"
STRUCTURES = ["none", "tracks"]
SIGMAS = (1, 2, 3)
STD_MARGIN_M = 0.05
WORLD_SEED = 0
WORLD_FRAMES = (40, 30)  # map, query frames of a generated world (the office preset's)
FLOOR_TILTS_DEG = (0.0, 1.0, 3.0)
MOUNT_PITCHES_DEG = (0.0, 10.0)
QUICK_DATASETS = ["office-tilt3-pitch10", "kitti-every4", "fountain_p11", "fountain-to-entry"]
KITTI = {"kitti": "kitti_seq2", "kitti1": "kitti_seq1"}  # data set name prefix -> shared folder
CROSS_SESSION = {
    "fountain-to-entry": ("fountain_p11", "entry_p10"),
    "entry-to-fountain": ("entry_p10", "fountain_p11"),
}


# ---- data sets ------------------------------------------------------------------------------------
@dataclass
class DataSet:
    """Map and query images of one benchmark data set; ``gravity``: true query gravity by name, if known."""

    name: str
    map_images: list[PosedImage]
    queries: list[PosedImage]
    gravity: dict[str, np.ndarray] | None
    source: str


def world_configs(n_map: int, n_query: int) -> dict[str, object]:
    """Named WorldConfigs of the generated data sets."""

    def frames(config):
        return dataclasses.replace(
            config, trajectory=dataclasses.replace(config.trajectory, n_map=n_map, n_query=n_query)
        )

    office = frames(get_preset("office"))
    out = {}
    for pitch in MOUNT_PITCHES_DEG:
        for tilt in FLOOR_TILTS_DEG:
            config = robot_variant(office, tilt, pitch)
            out[config.name] = config
    for name in ("pitched", "offplane"):
        out[name] = frames(get_preset(name))
    return out


def dataset_names(world_frames: tuple[int, int] = WORLD_FRAMES) -> list[str]:
    return [
        *world_configs(*world_frames),
        *(f"{k}-every{e}" for k in KITTI for e in (4, 2)),
        "fountain_p11",
        "entry_p10",
        *CROSS_SESSION,
    ]


def load_dataset(
    name: str, args: argparse.Namespace, root: Path, update: Callable[[str, int, int], None]
) -> DataSet | None:
    """The data set ``name`` (rendered if needed), or None when its real data is not there."""
    worlds = world_configs(*args.world_frames)
    if name in worlds:
        folder = cache.cached_world(
            worlds[name], WORLD_SEED, root, lambda d, n: update(f"render {name}", d, n)
        )
        queries = read_dataset(folder / "query", "tum")
        g = read_gravity(folder / "query" / "gravity.txt")
        return DataSet(
            name,
            read_dataset(folder / "map", "tum"),
            queries,
            {q.name: g[Path(q.name).stem] for q in queries},
            str(folder),
        )
    if name in CROSS_SESSION:
        folders = [args.data_root / d for d in CROSS_SESSION[name]]
        missing = [f for f in folders if not f.is_dir()]
        if missing:
            peer.log(f"{name}: {missing[0]} not found, skipped")
            return None
        return DataSet(
            name,
            read_dataset(folders[0], "kapture"),
            read_dataset(folders[1], "kapture"),
            None,
            " -> ".join(str(f) for f in folders),
        )
    prefix, _, every_text = name.partition("-every")
    if prefix in KITTI and every_text.isdigit():
        folder, fmt, every = args.data_root / KITTI[prefix], "kitti", int(every_text)
    else:
        folder, fmt, every = args.data_root / name, "kapture", 2
    if not folder.is_dir():
        peer.log(f"{name}: {folder} not found, skipped")
        return None
    map_images, queries = split_map_queries(read_dataset(folder, fmt), every)
    return DataSet(name, map_images, queries, None, str(folder))


# ---- localization ---------------------------------------------------------------------------------
def localizer_takes_gravity() -> bool:
    return "gravity" in inspect.signature(Localizer.localize_features).parameters


def localize_all(
    db: MapDatabase,
    configs: Sequence[LocalizerConfig],
    data: DataSet,
    use_gravity: bool,
    update: Callable[[str, int, int], None],
) -> list[list[dict]]:
    """Per config, one dict per query: :class:`QueryResult` fields plus ``model``. Query features
    are extracted once per query; ``seconds`` is extraction plus that config's localization."""
    localizers = [Localizer(db, c) for c in configs]
    out: list[list[dict]] = [[] for _ in configs]
    for i, q in enumerate(data.queries):
        t0 = time.perf_counter()
        features = extract_features(read_gray(q.path), localizers[0].features)
        t_feat = time.perf_counter() - t0
        kwargs = {"gravity": data.gravity[q.name]} if use_gravity and data.gravity is not None else {}
        for loc, rows in zip(localizers, out, strict=True):
            t1 = time.perf_counter()
            est = loc.localize_features(features, q.camera, **kwargs)
            row = asdict(query_result(q, est, t_feat + time.perf_counter() - t1))
            rows.append({**row, "model": getattr(est, "model", "") or ""})
        update(f"localize {data.name}", i + 1, len(data.queries))
    return out


# ---- metrics --------------------------------------------------------------------------------------
def beyond(rows: Sequence[dict], t_max: float, r_max: float) -> list[dict]:
    """Successes off by more than ``t_max`` metres or ``r_max`` degrees."""
    return [
        r
        for r in rows
        if r["success"] and not (r["translation_error_m"] <= t_max and r["rotation_error_deg"] <= r_max)
    ]


def trust_metrics(rows: Sequence[dict]) -> dict:
    """Success, confident-wrong, worst error and calibration of one data set x config.

    ``rows``: per-query dicts with ``success``, ``translation_error_m``, ``rotation_error_deg``,
    ``position_std_m`` (and optionally ``status``, ``model``). Percentages are of all queries
    (success) or of the successes (calibration; None without successes).
    """
    n = len(rows)
    ok = np.array([bool(r["success"]) for r in rows], dtype=bool)
    t = np.array([r["translation_error_m"] for r in rows], dtype=float)
    rot = np.array([r["rotation_error_deg"] for r in rows], dtype=float)
    std = np.array([r["position_std_m"] for r in rows], dtype=float)
    success = {
        threshold_name(tt, rr): 100.0 * float((ok & (t < tt) & (rot < rr)).sum()) / max(n, 1)
        for tt, rr in THRESHOLDS
    }
    wrong = [
        r
        for r in rows
        if r["success"]
        and not (r["translation_error_m"] < cache.WRONG_T and r["rotation_error_deg"] < cache.WRONG_R)
    ]
    gate = beyond(rows, cache.GATE_T, cache.GATE_R)
    k = int(ok.sum())

    def share(mask: np.ndarray) -> float | None:
        return 100.0 * float((mask & ok).sum()) / k if k else None

    with np.errstate(invalid="ignore"):
        calibration = {f"within_{s}std": share(t <= s * std) for s in SIGMAS}
        calibration["within_3std_plus_5cm"] = share(t <= 3 * std + STD_MARGIN_M)
        # a calibrated std gives about 1 (0.5-1.5 for the worst-axis std of a 2D-3D error)
        calibration["median_error_over_std"] = float(np.median(t[ok] / std[ok])) if k else None
    return {
        "queries": n,
        "localized": k,
        "success": success,
        "confident_wrong": len(wrong),
        "confident_wrong_queries": [r["name"] for r in wrong],
        "beyond_gate": len(gate),
        "worst_translation_error_m": float(t[ok].max()) if k else None,
        "worst_rotation_error_deg": float(rot[ok].max()) if k else None,
        "median_position_std_m": float(np.median(std[ok])) if k else None,
        "calibration": calibration,
        "models": dict(Counter(r.get("model", "") or "-" for r in rows if r["success"])),
        "status_counts": dict(Counter(r.get("status", "") for r in rows)),
        "seconds_per_query": (
            float(np.mean([r["seconds"] for r in rows])) if n and "seconds" in rows[0] else None
        ),
    }


# ---- output ---------------------------------------------------------------------------------------
HEADERS = [
    "data",
    "method",
    "structure",
    "queries",
    *[threshold_name(t, r) for t, r in THRESHOLDS],
    "confident wrong",
    "> 1m/20°",
    "worst t [m]",
    "worst R [°]",
    "≤ 1σ",
    "≤ 2σ",
    "≤ 3σ",
    "≤ 3σ+5cm",
    "median err/σ",
    "models",
    "s/query",
]


def table_row(result: dict) -> list[str]:
    m = result["metrics"]
    cal = m["calibration"]
    models = ", ".join(f"{k} {v}" for k, v in sorted(m["models"].items()) if k != "-") or "-"
    return [
        result["dataset"],
        result["method"],
        result["structure"],
        str(m["queries"]),
        *[peer.fmt_pct(v) for v in m["success"].values()],
        str(m["confident_wrong"]),
        str(m["beyond_gate"]),
        peer.fmt_num(m["worst_translation_error_m"], 2),
        peer.fmt_num(m["worst_rotation_error_deg"], 1),
        *[peer.fmt_pct(cal[f"within_{s}std"]) for s in SIGMAS],
        peer.fmt_pct(cal["within_3std_plus_5cm"]),
        peer.fmt_num(cal.get("median_error_over_std"), 2),
        models,
        peer.fmt_num(m["seconds_per_query"], 2),
    ]


def rich_table(results: Sequence[dict], title: str) -> Table:
    table = Table(title=title, show_lines=False)
    for h in HEADERS:
        table.add_column(
            h,
            justify="left" if h in ("data", "method", "structure", "models") else "right",
            no_wrap=h in ("data", "method"),
        )
    for r in results:
        m = r["metrics"]
        style = "bold red" if m["beyond_gate"] else ("yellow" if m["confident_wrong"] else None)
        table.add_row(*table_row(r), style=style)
    return table


def offending_lines(results: Sequence[dict]) -> list[str]:
    """One line per success off by more than 1 m or 20°."""
    out = []
    for r in results:
        for q in beyond(r["per_query"], cache.GATE_T, cache.GATE_R):
            out.append(
                f"{r['dataset']} {r['method']} {r['structure']}: query {q['name']} reported success "
                f"({q['status']}, model {q['model'] or '-'}) but is "
                f"{q['translation_error_m']:.2f} m / "
                f"{q['rotation_error_deg']:.1f}° off, position_std_m {q['position_std_m']:.3f}"
            )
    return out


def report_end(console: Console, args: argparse.Namespace, t0: float, skipped: list, results: list) -> None:
    """The closing line (total time since ``t0``, load) and the JSON: arguments, code, time, what was skipped,
    results."""
    seconds = time.perf_counter() - t0
    console.print(f"total {seconds:.0f} s; {peer.load_note('at end')}")
    peer.write_json(
        args.json,
        {
            "args": dict(vars(args)),
            "code": peer.code_version(),
            "seconds": seconds,
            "skipped": skipped,
            "results": results,
        },
    )


# ---- main -----------------------------------------------------------------------------------------
def add_datasets_option(p: argparse.ArgumentParser, default: str, quick: list[str], known: list[str]) -> None:
    """``--datasets``: names out of ``known``; the help tells the ``default`` and the ``quick`` ones."""
    p.add_argument(
        "--datasets",
        nargs="+",
        metavar="NAME",
        help=f"data sets (default: {default}; --quick: {' '.join(quick)}); choose from {' '.join(known)}",
    )


def check_datasets(p: argparse.ArgumentParser, names: list[str], known: list[str]) -> None:
    """Exit with a usage error unless every data set of ``names`` is ``known``."""
    unknown = [d for d in names if d not in known]
    if unknown:
        p.error(f"--datasets: unknown {' '.join(unknown)}; choose from {' '.join(known)}")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    all_methods = [m.value for m in Method]
    add_datasets_option(p, "all", QUICK_DATASETS, dataset_names())
    p.add_argument(
        "--methods",
        nargs="+",
        choices=all_methods,
        help=f"solvers (default: {' '.join(DEFAULT_METHODS)}; --quick: {QUICK_METHOD})",
    )
    p.add_argument(
        "--structures",
        nargs="+",
        default=STRUCTURES,
        choices=STRUCTURES,
        help="structure modes (default: both)",
    )
    p.add_argument(
        "--query-gravity",
        choices=["none", "truth"],
        default="none",
        help="pass each query's true gravity to the Localizer (generated worlds only; default: none)",
    )
    p.add_argument(
        "--world-frames",
        nargs=2,
        type=int,
        default=list(WORLD_FRAMES),
        metavar=("MAP", "QUERY"),
        help="frames of a generated world (default: %(default)s)",
    )
    cache.add_cache_options(p, DATA_ROOT, "rendered worlds and maps, reused when their content matches")
    p.add_argument(
        "--quick",
        action="store_true",
        help="CI gate: 3 data sets, default method; exit 1 on any success beyond 1 m or 20°",
    )
    p.add_argument(
        "--features",
        default=DEFAULT_FEATURE_TYPE,
        choices=list(FEATURE_TYPES),
        help="the maps' feature type (default: %(default)s; the learned ones need their extra)",
    )
    p.add_argument(
        "--coarse-keypoints",
        nargs="+",
        type=int,
        metavar="N",
        help="the localizer's coarse pass, one configuration per value (0: none; default: the type's)",
    )
    p.add_argument("--json", type=Path, help="write all metrics and per-query results here")
    p.add_argument("--markdown", type=Path, help="write the table as markdown (for BENCHMARKS.md)")
    args = p.parse_args(argv)
    if args.coarse_keypoints is not None and min(args.coarse_keypoints) < 0:
        p.error(f"--coarse-keypoints: expected N >= 0, got {args.coarse_keypoints}")
    args.coarse_keypoints = args.coarse_keypoints or [None]
    args.world_frames = tuple(args.world_frames)
    if min(args.world_frames) < 2:
        p.error(f"--world-frames: need at least 2 map and 2 query frames, got {args.world_frames}")
    known = dataset_names(args.world_frames)
    args.datasets = args.datasets or (QUICK_DATASETS if args.quick else known)
    check_datasets(p, args.datasets, known)
    args.methods = args.methods or ([QUICK_METHOD] if args.quick else DEFAULT_METHODS)
    if args.query_gravity == "truth" and not localizer_takes_gravity():
        p.error("--query-gravity truth: this Localizer.localize_features has no gravity argument")
    return args


def run_dataset(data: DataSet, args: argparse.Namespace, root: Path, update) -> list[dict]:
    features = FeatureConfig(kind=args.features)
    label = data.name if args.features == DEFAULT_FEATURE_TYPE else f"{data.name}-{args.features}"
    map_path, build_s = cache.cached_map(data.map_images, label, root, features=features, progress=update)
    configs = [
        LocalizerConfig(method=m, ransac=RansacOptions(structure=s), coarse_keypoints=c)
        for m in args.methods
        for s in args.structures
        for c in args.coarse_keypoints
    ]
    t0 = time.perf_counter()
    with MapDatabase.open(map_path) as db:
        rows = localize_all(db, configs, data, args.query_gravity == "truth", update)
    eval_s = time.perf_counter() - t0
    peer.log(
        f"{data.name}: {len(data.map_images)} map / {len(data.queries)} queries, "
        f"map build {build_s:.0f} s"
        f"{' (cached)' if build_s == 0 else ''}, localization {eval_s:.0f} s; {peer.load_note()}"
    )
    return [
        {
            "dataset": data.name,
            "source": data.source,
            "method": config_label(c)[0]
            + ("" if c.coarse_keypoints is None else f" coarse={c.coarse_keypoints}"),
            "features": args.features,
            "structure": config_label(c)[1],
            "map_images": len(data.map_images),
            "queries": len(data.queries),
            "query_gravity": args.query_gravity if data.gravity is not None else "none",
            "metrics": trust_metrics(r),
            "per_query": r,
        }
        for c, r in zip(configs, rows, strict=True)
    ]


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t_start = time.perf_counter()
    console = Console(width=200)
    root = cache.cache_root(args.cache_dir)
    title = (
        f"Trust: {', '.join(args.methods)}; structures {', '.join(args.structures)}; VLAD top-5; "
        f"query gravity {args.query_gravity}"
    )
    console.print(f"# {title}")
    console.print(peer.code_note())
    console.print(peer.load_note("at start"))
    results: list[dict] = []
    skipped: list[str] = []
    with progress_bar() as update:
        for name in args.datasets:
            data = load_dataset(name, args, root, update)
            if data is None:
                skipped.append(name)
                continue
            rows = run_dataset(data, args, root, update)
            results += rows
            # Long runs: each data set's rows as soon as they are measured (markdown, on stderr).
            peer.log("\n".join("| " + " | ".join(table_row(r)) + " |" for r in rows))
    console.print(rich_table(results, title))
    if skipped:
        console.print(f"skipped (data not found under {args.data_root}): {', '.join(skipped)}")
    markdown = peer.markdown_table(HEADERS, [table_row(r) for r in results], title)
    if args.markdown:
        args.markdown.write_text(markdown + "\n")
        peer.log(f"wrote {args.markdown}")
    offending = offending_lines(results)
    report_end(console, args, t_start, skipped, results)
    if offending:
        console.print(
            f"[bold red]{len(offending)} success(es) beyond {cache.GATE_T:g} m or {cache.GATE_R:g}°:"
        )
        for line in offending:
            print(line)
    else:
        console.print(f"no success beyond {cache.GATE_T:g} m or {cache.GATE_R:g}°")
    return 1 if args.quick and offending else 0


if __name__ == "__main__":
    sys.exit(main())
