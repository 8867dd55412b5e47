"""Shared benchmark code for end-to-end runs: cached worlds and maps, wrong-pose counts, summary cells.

Used by ``kitti.py``, ``world_presets.py`` and ``trust.py``. Caches live under one folder
(by default ``$TMPDIR/planarloc-bench``) and are keyed by content:

- worlds: ``worlds/<name>-<sha1 of config and seed>``; :func:`planarloc.synthetic.world.generate`
  itself reuses a complete generation of the same config and seed.
- maps: ``maps/<label>-<sha1>.db`` where the hash covers the map images (names, files' sizes and
  modification times, poses, cameras), the feature settings, the storage layout and the sources of the code
  that builds maps (``planarloc/geometry``, ``planarloc/io``, ``planarloc/features``, ``planarloc/gravity``
  and ``planarloc/map``), so an edit of the map code rebuilds them and an edit of the estimator
  (or of ``planarloc/localize``, ``planarloc/evaluation``) does not. A map's std calibration
  (:mod:`planarloc.localize.held_out`), which the estimator's code decides, is measured again
  when that code changed (its key is stored in the map).

Not part of the package: benchmarks sit on top of it and may import anything.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import _peer_pipeline as peer
import numpy as np

import planarloc
from planarloc.evaluation.queries import THRESHOLDS, threshold_name
from planarloc.features.extract import FeatureConfig
from planarloc.localize.held_out import calibrate_map_std
from planarloc.map.builder import build_map
from planarloc.map.codec import DEFAULT_STORAGE
from planarloc.map.posed_image import PosedImage
from planarloc.map.store import MapDatabase
from planarloc.synthetic.world.config import WorldConfig
from planarloc.synthetic.world.export import generate

WRONG_T, WRONG_R = 0.25, 10.0
"""A success off by at least this much (metres, degrees) is *confident-but-wrong*."""
GATE_T, GATE_R = 1.0, 20.0
"""A success off by more than this is never acceptable (the CI gate of ``trust.py --quick``)."""

_MAP_CODE = ("geometry", "io", "features", "gravity", "map")
_NOT_MAP_CODE: set[str] = set()
_CALIBRATION_KEY_META = "benchmark_calibration_code"


def is_wrong(q: dict, t_max: float = WRONG_T, r_max: float = WRONG_R) -> bool:
    """True unless per-query result ``q`` is within ``t_max`` metres and ``r_max`` degrees (NaN: wrong)."""
    return not (q["translation_error_m"] < t_max and q["rotation_error_deg"] < r_max)


def confident_wrong(summary: dict, t_max: float = WRONG_T, r_max: float = WRONG_R) -> list[str]:
    """Names of the queries of an evaluation summary reported as success but off by >= (t_max, r_max)."""
    return [q["name"] for q in summary["per_query"] if q["success"] and is_wrong(q, t_max, r_max)]


PROMISE_SIGMAS, PROMISE_MARGIN_M = 3.0, 0.05
"""A success farther from the truth than ``PROMISE_SIGMAS · position_std_m + PROMISE_MARGIN_M``
is a broken promise."""


def broken_promises(summary: dict) -> list[str]:
    """Names of the queries of an evaluation summary reported as success but farther from the
    truth than their own uncertainty allows (``PROMISE_SIGMAS`` position stds + ``PROMISE_MARGIN_M``)."""
    return [
        q["name"]
        for q in summary["per_query"]
        if q["success"]
        and not q["translation_error_m"] <= PROMISE_SIGMAS * q["position_std_m"] + PROMISE_MARGIN_M
    ]


SUMMARY_HEADERS = [
    "structure",
    *[threshold_name(t, r) for t, r in THRESHOLDS],
    "median t [m]",
    "median R [°]",
    "failed",
    "degenerate",
    "confident wrong",
    "s/query",
]
"""The columns of :func:`summary_cells`."""


def summary_cells(s: dict) -> list[str]:
    """An evaluation summary as table cells, under ``SUMMARY_HEADERS``."""
    return [
        s["structure"],
        *[peer.fmt_pct(v) for v in s["success"].values()],
        peer.fmt_num(s["median_translation_error_m"]),
        peer.fmt_num(s["median_rotation_error_deg"], 2),
        f"{s['failed_queries']}/{s['queries']}",
        str(s["status_counts"].get("degenerate_scale", 0)),
        str(len(confident_wrong(s))),
        peer.fmt_num(s["seconds_per_query"], 2),
    ]


def cache_root(path: Path | None = None) -> Path:
    """The cache folder (created): ``path`` or ``$TMPDIR/planarloc-bench``."""
    root = Path(path) if path is not None else Path(tempfile.gettempdir()) / "planarloc-bench"
    root.mkdir(parents=True, exist_ok=True)
    return root


def add_cache_options(p: argparse.ArgumentParser, data_root: Path, kept: str) -> None:
    """``--data-root`` (the shared real data, by default ``data_root``) and ``--cache-dir`` (``kept`` says
    what is kept there; by default :func:`cache_root`'s folder)."""
    p.add_argument(
        "--data-root", type=Path, default=data_root, help="shared real data (default: %(default)s)"
    )
    p.add_argument("--cache-dir", type=Path, help=f"{kept} (default: $TMPDIR/planarloc-bench)")


def content_key(*parts: object) -> str:
    """12 hex digits of the sha1 of the JSON of ``parts`` (anything ``str()`` can render)."""
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


def map_code_key() -> str:
    """Hash of the sources that determine a built map (see the module docstring)."""
    return _code_key(_MAP_CODE)


def _code_key(subpackages: Sequence[str]) -> str:
    pkg = Path(planarloc.__file__).resolve().parent
    h = hashlib.sha1()
    for sub in subpackages:
        for f in sorted((pkg / sub).rglob("*.py")):
            rel = f.relative_to(pkg).as_posix()
            if rel not in _NOT_MAP_CODE:
                h.update(rel.encode())
                h.update(f.read_bytes())
    return h.hexdigest()[:12]


def images_key(images: Sequence[PosedImage]) -> list:
    """What identifies a list of posed images: names, file sizes and times, poses, cameras."""
    out = []
    for im in images:
        st = Path(im.path).stat()
        pose = im.cam_from_world
        out.append(
            [
                im.name,
                str(im.path),
                st.st_size,
                st.st_mtime_ns,
                np.asarray(pose.R).round(12).tolist(),
                np.asarray(pose.t).round(12).tolist(),
                im.camera.model.value,
                list(im.camera.params),
            ]
        )
    return out


def build_or_reuse(
    map_images: Sequence[PosedImage],
    path: Path,
    features: FeatureConfig,
    reuse: bool,
    progress: Callable[[str, int, int], None] | None = None,
    storage: str = DEFAULT_STORAGE,
) -> float:
    """Build (or, with ``reuse``, reuse a complete) map at ``path`` in the ``storage`` layout
    (:mod:`planarloc.map.codec`); returns the build time in seconds (0 when reused). Without
    ``reuse``, or when the file holds another layout, an existing file is deleted first."""
    if path.exists() and reuse:
        with MapDatabase.open(path) as db:
            reuse = db.storage == storage
    if path.exists() and not reuse:
        for p in (path, *(path.with_name(path.name + s) for s in ("-wal", "-shm"))):
            p.unlink(missing_ok=True)
    if path.exists():
        with MapDatabase.open(path) as db:
            complete = db.is_complete and db.num_images() == len(map_images)
            calibrated = db.get_meta(_CALIBRATION_KEY_META) == calibration_code_key()
        if complete:
            peer.log(f"reusing {path}")
            if not calibrated:  # cached before the std calibration, or the localizer changed since
                _calibrate(path, progress)
            return 0.0
    peer.log(f"building {path.name}: {len(map_images)} images, features {features.name}, storage {storage}")
    t0 = time.perf_counter()
    build_map(map_images, path, features, progress=progress or peer.Progress(), storage=storage)
    _calibrate(path, progress)  # as `planarloc map build` does
    return time.perf_counter() - t0


def calibration_code_key() -> str:
    """Hash of the sources that determine a map's std calibration (the localizer's)."""
    return _code_key(("geometry", "numerics", "solvers", "robust", "features", "map", "localize"))


def _calibrate(path: Path, progress: Callable[[str, int, int], None] | None) -> None:
    calibrate_map_std(path, progress=progress or peer.Progress())
    with MapDatabase.open(path, mode="a") as db:
        db.set_meta(_CALIBRATION_KEY_META, calibration_code_key())


def cached_map(
    map_images: Sequence[PosedImage],
    label: str,
    root: Path,
    features: FeatureConfig | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    storage: str = DEFAULT_STORAGE,
) -> tuple[Path, float]:
    """The map of ``map_images`` under ``root/maps``, keyed by content; (path, build seconds or 0)."""
    features = features or FeatureConfig()
    key = content_key(images_key(map_images), features.name, storage, map_code_key())
    path = root / "maps" / f"{label}-{key}.db"
    path.parent.mkdir(parents=True, exist_ok=True)
    return path, build_or_reuse(map_images, path, features, reuse=True, progress=progress, storage=storage)


def cached_world(
    config: WorldConfig, seed: int, root: Path, progress: Callable[[int, int], None] | None = None
) -> Path:
    """The rendered world of ``config`` and ``seed`` under ``root/worlds`` (rendered once)."""
    out = root / "worlds" / f"{config.name}-{content_key(config.to_dict(), seed)}"
    return generate(config, out, seed=seed, progress=progress)
