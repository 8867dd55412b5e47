"""Build a map: extract local features of posed images, store them, index them for retrieval.

Building a map is inserting posed images (the paper's point: no 3D model). The build is
resumable: images already in the map are skipped, so re-running after a crash or Ctrl-C
continues; appending images to an existing map works the same way. Identity is by content
(:mod:`planarloc.pipeline.map_identity`): a changed pose is updated, a changed image file is
re-extracted, another dataset's image with a stored name is namespaced. The retrieval
vocabulary and the global descriptors are (re)computed when anything changed, then the map is
marked complete. Only one process builds a map at a time (the others wait, see
:mod:`planarloc.pipeline.map_lock`).

The map's gravity (:mod:`planarloc.pipeline.gravity`) is (re)computed at the end of every build
that changed the map from all its poses and stored in the meta keys ``gravity`` (the
:class:`GravityReport` as JSON) and ``world_down`` (the declared or user-given down direction,
if any).
"""

from __future__ import annotations

import dataclasses
import errno
import functools
import json
import logging
import os
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from planarloc.geometry.validation import InputError
from planarloc.pipeline.features import DEFAULT_FEATURE_CONFIG, FeatureConfig, Features, extract_features
from planarloc.pipeline.gravity import GravityReport, WorldDown, gravity_from_map_poses
from planarloc.pipeline.map_database import MapDatabase, settings_mismatch_error
from planarloc.pipeline.map_identity import file_sha256, plan_map_update
from planarloc.pipeline.posed_image import PosedImage
from planarloc.pipeline.retrieval import DEFAULT_NUM_WORDS, VladVocabulary, vlad_descriptor

logger = logging.getLogger(__name__)

VOCABULARY_BLOB = "retrieval/vlad_vocabulary"
GRAVITY_META = "gravity"
WORLD_DOWN_META = "world_down"
Progress = Callable[[str, int, int], None]  # (stage, done, total)
#: ``mapper(fn, items)`` -> ``fn(item)`` for each item, in order (like the builtin ``map``).
Mapper = Callable[[Callable[[PosedImage], Features], Sequence[PosedImage]], Iterable[Features]]


def read_gray(path: Path) -> np.ndarray:
    """Read an image file as (H, W) uint8; clear error when missing or unreadable."""
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise InputError(f"{path}: cannot read image (missing file or unsupported format)")
    return image


def feature_config_from_map(db: MapDatabase) -> FeatureConfig:
    """The FeatureConfig a map was built with (queries are extracted the same way, minus tilt)."""
    cfg = dict(db.config.get("features", {}))
    cfg.setdefault("resize_max", None)  # maps from before resize_max were extracted at full resolution
    if "tilts" in cfg:
        cfg["tilts"] = tuple(cfg["tilts"])
    return FeatureConfig(**cfg)


def check_num_words(num_words: object) -> int:
    """The VLAD vocabulary size as an int >= 1 (InputError otherwise)."""
    if isinstance(num_words, bool) or not isinstance(num_words, (int, np.integer)) or num_words < 1:
        raise InputError(f"num_words (--vocabulary-size): expected an integer >= 1, got {num_words!r}")
    return int(num_words)


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from a PNG header (24 bytes read), None for other or unreadable files."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")


def _hash_checked(image: PosedImage) -> str:
    """SHA-256 of an image file, after a cheap size check against its camera (PNG headers)."""
    size = png_size(image.path)
    if size is not None and size != (image.camera.width, image.camera.height):
        raise InputError(f"{image.path}: image is {size[0]}x{size[1]} but its camera is "
                         f"{image.camera.width}x{image.camera.height}; fix the dataset's intrinsics")
    return file_sha256(image.path)


def read_map_image(image: PosedImage) -> np.ndarray:
    """Read a map image as (H, W) uint8 and check it has its camera's size."""
    gray = read_gray(image.path)
    if gray.shape[:2] != (image.camera.height, image.camera.width):
        raise InputError(
            f"{image.path}: image is {gray.shape[1]}x{gray.shape[0]} but its camera is "
            f"{image.camera.width}x{image.camera.height}; fix the dataset's intrinsics"
        )
    return gray


def extract_image_features(image: PosedImage, features: FeatureConfig) -> Features:
    """Read a posed image's file and extract its local features (one map-building task)."""
    return extract_features(read_map_image(image), features)


def check_map_settings(path: str | Path, features: FeatureConfig, num_words: int) -> None:
    """Before any work: an existing map at ``path`` must have been built with these settings
    (an empty unfinished one is replaced by :func:`build_map`, so it passes)."""
    path = Path(path)
    if not path.exists():
        return
    with MapDatabase.open(path) as db:
        stored = db.config
        empty = db.num_images() == 0 and not db.is_complete
    config = _map_config(features, check_num_words(num_words))
    if not empty and json.dumps(stored, sort_keys=True) != json.dumps(config, sort_keys=True):
        raise settings_mismatch_error(path, stored, config)


def _map_config(features: FeatureConfig, num_words: int) -> dict:
    return {"features": dataclasses.asdict(features), "feature_name": features.name,
            "retrieval": {"type": "vlad", "num_words": int(num_words)}}


def build_map(
    images: Sequence[PosedImage],
    path: str | Path,
    features: FeatureConfig = DEFAULT_FEATURE_CONFIG,
    num_words: int = DEFAULT_NUM_WORDS,
    seed: int = 0,
    progress: Progress | None = None,
    workers: int | None = None,
    lock_timeout: float | None = None,
    notify: Callable[[str], None] | None = None,
    mapper: Mapper | None = None,
) -> Path:
    """Create (or resume / append to) the map at ``path`` from posed images.

    Args:
        images: posed map images (e.g. from :func:`planarloc.io.datasets.read_dataset`).
        path: the map file (SQLite).
        features: local feature settings; ``features.tilt`` enables the paper's tilt
            augmentation for map images. Must equal the settings of an existing map.
        num_words: VLAD vocabulary size.
        seed: seeds the vocabulary training.
        progress: optional ``(stage, done, total)`` callback.
        workers: feature extraction threads (default: one per core).
        lock_timeout: seconds to wait while another process builds the same map (None: wait).
        notify: receives one line per identity action (updated poses, re-extracted or
            namespaced images); default: logged as warnings.
        mapper: runs the feature extraction instead of the threads: ``mapper(fn, images)`` yields
            ``fn(image)`` in input order (e.g. :func:`planarloc.distributed.ray_backend.RayBackend.map`).

    Returns:
        The map path.

    Raises:
        InputError: an existing map built with different settings, unreadable images, an
            image whose size differs from its camera's, images that declare a different world
            gravity than the map, bad options (checked before any work).
        MapBusyError: another process still builds the map after ``lock_timeout``.
    """
    path = Path(path)
    num_words = check_num_words(num_words)
    if not isinstance(features, FeatureConfig):
        raise InputError(f"features: expected a FeatureConfig, got {type(features).__name__}")
    images = list(images)
    if not images:
        raise InputError(f"{path}: no images to build the map from")
    if not all(isinstance(im, PosedImage) for im in images):
        raise InputError("images: expected PosedImage records (e.g. from planarloc.io.datasets.read_dataset)")
    config = _map_config(features, num_words)
    declared = declared_world_down(images)
    n_workers = workers or os.cpu_count() or 1
    with ThreadPoolExecutor(max_workers=n_workers) as pool:
        hashes = []
        for i, h in enumerate(pool.map(_hash_checked, images)):  # reads every file once, before any work
            hashes.append(h)
            if progress:
                progress("check images", i + 1, len(images))
        try:
            db = MapDatabase.open_or_create(path, config, lock_timeout=lock_timeout)
        except OSError as exc:
            if exc.errno not in (errno.EACCES, errno.EPERM, errno.EROFS) or not path.is_file():
                raise
            _check_read_only_map_is_current(path, config, images, hashes, exc)
            return path
        with db:
            resolve_world_down(db, declared)  # a contradicting declaration fails before any work
            plan = plan_map_update(db, images, hashes)
            for line in plan.summary_lines(path):
                if notify is not None:
                    notify(line)
                else:
                    logger.warning("%s", line)
            if plan.keep:
                logger.info("%s: %d of %d images already in the map, resuming", path, len(plan.keep), len(images))
            for record, sha in plan.update:
                db.update_image_record(record.name, record, sha)
            todo = plan.replace + plan.add
            # Reading and SIFT run in worker threads (OpenCV releases the GIL) or on the given
            # mapper (e.g. a Ray cluster); the database is written in this thread, in order, one
            # transaction per image (resumable).
            extract = functools.partial(extract_image_features, features=features)
            extracted = (mapper or pool.map)(extract, [record for record, _ in todo])
            for i, feats in enumerate(extracted):
                record, sha = todo[i]
                if db.has_image(record.name):  # replaced: old features out, new in, one image at a time
                    db.remove_image(record.name)
                db.add_image(record, feats, content_sha256=sha)
                if progress:
                    progress("features", i + 1, len(todo))
            if plan.changes_map or not db.is_complete or db.get_blob(VOCABULARY_BLOB) is None:
                index_map(db, num_words=num_words, seed=seed, progress=progress)
                store_map_gravity(db, declared)
                db.mark_complete()
            elif db.get_meta(GRAVITY_META) is None or (declared is not None and db.get_meta(WORLD_DOWN_META) is None):
                store_map_gravity(db, declared)  # a map built before gravity was stored
    return path


def _check_read_only_map_is_current(path: Path, config: dict, images: Sequence[PosedImage], hashes: Sequence[str],
                                    exc: OSError) -> None:
    """A map that cannot be written (read-only media) is fine if it already is this build."""
    with MapDatabase.open(path) as db:
        if json.dumps(db.config, sort_keys=True) != json.dumps(config, sort_keys=True):
            raise settings_mismatch_error(path, db.config, config)
        plan = plan_map_update(db, images, hashes)
        if db.is_complete and not plan.changes_map:
            logger.info("%s: read-only and already complete with these images; nothing to do", path)
            return
    need = len(plan.add) + len(plan.replace) + len(plan.update)
    raise InputError(f"{path}: cannot write the map ({exc.strerror}: {exc.filename}) but {need} image(s) must be "
                     "added or updated; copy it to a writable location or build a new map there")


def index_map(db: MapDatabase, num_words: int = DEFAULT_NUM_WORDS, seed: int = 0,
              progress: Progress | None = None) -> None:
    """Train the VLAD vocabulary on the map's descriptors and store every image's VLAD vector."""
    ids = db.image_ids()
    if not ids:
        raise InputError(f"{db.path}: the map has no images")
    rng = np.random.default_rng(seed)
    # Subsample per image so vocabulary training memory stays bounded on large maps.
    per_image = max(64, (256 * num_words) // len(ids) + 1)
    sample = []
    for _id, _name, f in db.iter_features():
        d = f.descriptors
        if len(d) > per_image:
            d = d[rng.choice(len(d), per_image, replace=False)]
        sample.append(d)
    k = int(min(num_words, max(1, sum(len(s) for s in sample) // 8)))
    vocab = VladVocabulary.train(sample, k=k, seed=seed)
    db.put_blob(VOCABULARY_BLOB, vocab.to_bytes())
    keys, vecs = [], []
    for i, (image_id, _name, f) in enumerate(db.iter_features()):
        keys.append(image_id)
        vecs.append(vlad_descriptor(vocab, f.descriptors))
        if progress:
            progress("retrieval index", i + 1, len(ids))
    db.set_global_descriptors((keys, np.stack(vecs)))


def declared_world_down(images: Sequence[PosedImage]) -> WorldDown | None:
    """The ``world_down`` the images declare (all must agree), or None if none declares one."""
    found = {im.world_down for im in images if im.world_down is not None}
    if len(found) > 1:
        raise InputError("the images declare different world gravity directions: "
                         + "; ".join(f"{w.direction} ({w.detail})" for w in found)
                         + "; hint: pass the dataset option up=... for all of them")
    return next(iter(found), None)


def resolve_world_down(db: MapDatabase, declared: WorldDown | None) -> tuple[WorldDown | None, WorldDown | None]:
    """``(stored, to use)`` world down of a map given the new images' declaration (rules in
    :func:`store_map_gravity`); InputError on a contradiction."""
    raw = db.get_meta(WORLD_DOWN_META)
    stored = WorldDown.from_dict(json.loads(raw)) if raw else None
    if declared is None:
        return stored, stored
    if stored is None or declared.source == "option":
        return stored, declared
    if stored.source == "declared" and not np.allclose(stored.direction, declared.direction, atol=1e-9):
        raise InputError(
            f"{db.path}: the map's world has down = {stored.direction} ({stored.detail}) but the new images "
            f"declare {declared.direction} ({declared.detail}); hint: pass the dataset option up=...")
    return stored, stored


def store_map_gravity(db: MapDatabase, declared: WorldDown | None = None) -> GravityReport:
    """Compute the map's gravity from all its poses and store it (meta ``gravity``).

    Args:
        db: a writable map with at least one image.
        declared: the down direction the images being added declare. A user's ``up=``
            (``source="option"``) replaces what the map stores; a format's declaration must
            agree with a stored one of the same kind, and never replaces a stored option.

    Returns:
        The stored :class:`GravityReport`.

    Raises:
        InputError: a declaration that contradicts the map's (different world frames).
    """
    stored, use = resolve_world_down(db, declared)
    if use is not None and use != stored:
        db.set_meta(WORLD_DOWN_META, json.dumps(use.to_dict()))
    _, report = gravity_from_map_poses(list(db.load_all_poses().values()), use)
    db.set_meta(GRAVITY_META, json.dumps(report.to_dict()))
    for w in report.warnings:
        logger.warning("%s: %s", db.path, w)
    return report


def map_gravity(db: MapDatabase) -> GravityReport:
    """The map's stored gravity; computed from its poses (not stored) for maps built before it was."""
    raw = db.get_meta(GRAVITY_META)
    if raw:
        return GravityReport.from_dict(json.loads(raw))
    logger.info("%s: the map stores no gravity (built by an older planarloc); estimating it from its poses",
                db.path)
    raw_down = db.get_meta(WORLD_DOWN_META)
    declared = WorldDown.from_dict(json.loads(raw_down)) if raw_down else None
    return gravity_from_map_poses(list(db.load_all_poses().values()), declared)[1]
