"""Build a map: extract local features of posed images, store them, index them for retrieval.

Building a map is inserting posed images (the paper's point: no 3D model). The build is
resumable: images already in the map are skipped, so re-running after a crash or Ctrl-C
continues; appending images to an existing map works the same way. The retrieval
vocabulary and the global descriptors are (re)computed at the end, then the map is marked
complete.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from planarloc.geometry.validation import InputError
from planarloc.pipeline.features import DEFAULT_FEATURE_CONFIG, FeatureConfig, extract_features
from planarloc.pipeline.map_database import MapDatabase
from planarloc.pipeline.posed_image import PosedImage
from planarloc.pipeline.retrieval import DEFAULT_NUM_WORDS, VladVocabulary, vlad_descriptor

logger = logging.getLogger(__name__)

VOCABULARY_BLOB = "retrieval/vlad_vocabulary"
Progress = Callable[[str, int, int], None]  # (stage, done, total)


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

    Returns:
        The map path.

    Raises:
        InputError: an existing map built with different settings, unreadable images.
    """
    path = Path(path)
    config = _map_config(features, num_words)
    with MapDatabase.open_or_create(path, config) as db:
        todo = [im for im in images if not db.has_image(im.name)]
        if len(todo) < len(images):
            logger.info("%s: %d of %d images already in the map, resuming", path, len(images) - len(todo), len(images))
        # Reading and SIFT run in worker threads (OpenCV releases the GIL); the database is
        # written in this thread, in order, one transaction per image (resumable).
        with ThreadPoolExecutor(max_workers=workers or os.cpu_count() or 1) as pool:
            for i, feats in enumerate(pool.map(lambda im: extract_features(read_gray(im.path), features), todo)):
                db.add_image(todo[i], feats)
                if progress:
                    progress("features", i + 1, len(todo))
        index_map(db, num_words=num_words, seed=seed, progress=progress)
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
