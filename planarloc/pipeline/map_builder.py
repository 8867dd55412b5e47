"""Build a map: extract local features of posed images, store them, index them for retrieval.

Building a map is inserting posed images (the paper's point: no 3D model). The build is
resumable: images already in the map are skipped, so re-running after a crash or Ctrl-C
continues; appending images to an existing map works the same way. The retrieval
vocabulary and the global descriptors are (re)computed at the end, then the map is marked
complete.

The map's gravity (:mod:`planarloc.pipeline.gravity`) is (re)computed at the end of every build
from all its poses and stored in the meta keys ``gravity`` (the :class:`GravityReport` as JSON)
and ``world_down`` (the declared or user-given down direction, if any).
"""

from __future__ import annotations

import dataclasses
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
from planarloc.pipeline.map_database import MapDatabase
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


def extract_image_features(image: PosedImage, features: FeatureConfig) -> Features:
    """Read a posed image's file and extract its local features (one map-building task)."""
    return extract_features(read_gray(image.path), features)


def feature_config_from_map(db: MapDatabase) -> FeatureConfig:
    """The FeatureConfig a map was built with (queries are extracted the same way, minus tilt)."""
    cfg = dict(db.config.get("features", {}))
    if "tilts" in cfg:
        cfg["tilts"] = tuple(cfg["tilts"])
    return FeatureConfig(**cfg)


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
        mapper: runs the feature extraction instead of the threads: ``mapper(fn, images)`` yields
            ``fn(image)`` in input order (e.g. :func:`planarloc.distributed.ray_backend.RayBackend.map`).

    Returns:
        The map path.

    Raises:
        InputError: an existing map built with different settings, unreadable images, images
            that declare a different world gravity than the map.
    """
    path = Path(path)
    config = _map_config(features, num_words)
    declared = declared_world_down(images)
    with MapDatabase.open_or_create(path, config) as db:
        resolve_world_down(db, declared)  # a contradicting declaration fails before any work
        todo = [im for im in images if not db.has_image(im.name)]
        if len(todo) < len(images):
            logger.info("%s: %d of %d images already in the map, resuming", path, len(images) - len(todo), len(images))
        # Reading and SIFT run in worker threads (OpenCV releases the GIL) or on the given mapper
        # (e.g. a Ray cluster); the database is written in this thread, in order, one transaction
        # per image (resumable).
        extract = functools.partial(extract_image_features, features=features)
        with ThreadPoolExecutor(max_workers=workers or os.cpu_count() or 1) as pool:
            for i, feats in enumerate((mapper or pool.map)(extract, todo)):
                db.add_image(todo[i], feats)
                if progress:
                    progress("features", i + 1, len(todo))
        index_map(db, num_words=num_words, seed=seed, progress=progress)
        store_map_gravity(db, declared)
        db.mark_complete()
    return path


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
