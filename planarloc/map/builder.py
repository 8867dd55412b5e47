"""Build a map: extract local features of posed images, store them, index them for retrieval.

Building a map is inserting posed images (the paper's point: no 3D model). The build is
resumable: images already in the map are skipped, so re-running after a crash or Ctrl-C
continues; appending images to an existing map works the same way. Identity is by content
(:mod:`planarloc.map.identity`): a changed pose is updated, a changed image file is
re-extracted, another dataset's image with a stored name is namespaced. The retrieval
vocabulary and the global descriptors are (re)computed when anything changed, then the map is
marked complete, and its gravity is stored (:mod:`planarloc.map.gravity`). Only one process
builds a map at a time (the others wait, see :mod:`planarloc.map.lock`).

Before new images go into a map that already holds some, a few of them are matched against it
(:mod:`planarloc.map.frame_check`): images whose poses are in another world frame (e.g. another
sequence that also starts at "first camera frame") are refused with
:class:`~planarloc.map.frame_check.UnrelatedFramesError` and the map is not touched, unless
``allow_unrelated_frames`` (then a warning says what was found). A new or empty map skips the check.

An image that cannot go into the map — missing or unreadable, truncated or damaged
(:func:`planarloc.features.images.image_problem`), undecodable, or of another size than its
camera — is left out and reported (``skipped``, default: a warning each); the build goes on with
the others. Only when no image is usable does the build fail (before the map is touched).
"""

from __future__ import annotations

import errno
import functools
import hashlib
import json
import logging
import os
import sqlite3
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TypedDict, Unpack

import numpy as np

from planarloc.features import learned
from planarloc.features.extract import DEFAULT_FEATURE_CONFIG, FeatureConfig, Features, extract_features
from planarloc.features.images import ImageFormatError, image_problem, image_size_from_header, read_gray
from planarloc.features.retrieval import DEFAULT_NUM_WORDS, VladVocabulary, vlad_descriptor
from planarloc.geometry.validation import InputError
from planarloc.gravity.world import WorldDown
from planarloc.map.codec import DEFAULT_STORAGE
from planarloc.map.frame_check import (
    DEFAULT_FRAME_CHECK,
    FrameCheck,
    UnrelatedFramesError,
    check_appended_frames,
)
from planarloc.map.gravity import (
    declared_world_down,
    resolve_world_down,
    store_map_gravity,
    world_down_changes,
)
from planarloc.map.identity import MapUpdatePlan, plan_map_update
from planarloc.map.lock import MapWriterLock, writer_of
from planarloc.map.pose_accuracy import measure_map_accuracy, store_accuracy
from planarloc.map.posed_image import PosedImage
from planarloc.map.schema import GRAVITY_META, VOCABULARY_BLOB, MapFormatError
from planarloc.map.settings import check_num_words, map_config, settings_mismatch_error
from planarloc.map.std_calibration import mark_std_calibration_stale
from planarloc.map.store import MapDatabase

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]  # (stage, done, total)
#: ``skipped(image, reason)``: an image left out of the map, and why (one line).
Skipped = Callable[[PosedImage, str], None]
#: ``mapper(fn, items)`` -> ``fn(item)`` for each item, in order (like the builtin ``map``).
Mapper = Callable[
    [Callable[[PosedImage], "Features | str"], Sequence[PosedImage]], Iterable["Features | str"]
]


def _hash_checked(image: PosedImage) -> str:
    """SHA-256 of an image file, after cheap checks: a whole PNG/JPEG file, of its camera's size
    (from the header).

    Raises:
        InputError: the file is missing, unreadable, truncated, damaged or of another size.
    """
    try:
        data = Path(image.path).read_bytes()
    except OSError as exc:
        raise InputError(f"{image.path}: cannot read image ({exc.strerror or exc})") from None
    problem = image_problem(data)
    if problem is not None:
        raise InputError(f"{image.path}: {problem}")
    size: tuple[int, int] | None
    try:
        _fmt, w, h = image_size_from_header(data)
        size = (w, h)
    except ImageFormatError:
        size = None  # another format: its size is checked once it is decoded
    if size is not None and size != (image.camera.width, image.camera.height):
        raise InputError(
            f"{image.path}: image is {size[0]}x{size[1]} but its camera is "
            f"{image.camera.width}x{image.camera.height}; fix the dataset's intrinsics"
        )
    return hashlib.sha256(data).hexdigest()


def _hash_or_reason(image: PosedImage) -> tuple[str | None, str | None]:
    try:
        return _hash_checked(image), None
    except InputError as exc:
        return None, str(exc)


def read_map_image(image: PosedImage) -> np.ndarray:
    """Read a map image as (H, W) uint8 and check it has its camera's size."""
    gray = read_gray(image.path)
    if gray.shape[:2] != (image.camera.height, image.camera.width):
        raise InputError(
            f"{image.path}: image is {gray.shape[1]}x{gray.shape[0]} but its camera is "
            f"{image.camera.width}x{image.camera.height}; fix the dataset's intrinsics"
        )
    return gray


def extract_image_features(image: PosedImage, features: FeatureConfig) -> Features | str:
    """Read a posed image's file and extract its local features (one map-building task); an image
    that cannot be read gives the reason instead (a string: it is left out of the map)."""
    try:
        gray = read_map_image(image)
    except InputError as exc:
        return str(exc)
    return extract_features(gray, features)


def check_map_settings(path: str | Path, features: FeatureConfig, num_words: int) -> None:
    """Before any work: an existing map at ``path`` must have been built with these settings
    (an empty unfinished one is replaced by :func:`build_map`, so it passes). A map that another
    process is writing now is not read: it may be half-created, and :func:`build_map` waits for
    that writer and checks the settings under the lock."""
    path = Path(path)
    if not path.exists() or writer_of(path) is not None:
        return
    try:
        with MapDatabase.open(path) as db:
            stored = db.config
            empty = db.num_images() == 0 and not db.is_complete
    except (MapFormatError, sqlite3.OperationalError):
        if writer_of(path) is not None:  # a writer started meanwhile: build_map waits for it
            return
        raise
    config = map_config(features, check_num_words(num_words))
    if not empty and json.dumps(stored, sort_keys=True) != json.dumps(config, sort_keys=True):
        raise settings_mismatch_error(path, stored, config)


def build_map(
    images: Sequence[PosedImage],
    path: str | Path,
    features: FeatureConfig = DEFAULT_FEATURE_CONFIG,
    num_words: int = DEFAULT_NUM_WORDS,
    seed: int = 0,
    progress: Progress | None = None,
    notify: Callable[[str], None] | None = None,
    skipped: Skipped | None = None,
    storage: str = DEFAULT_STORAGE,
    allow_unrelated_frames: bool = False,
    **run: Unpack[BuildRun],
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
        notify: receives one line per identity action (updated poses, re-extracted or
            namespaced images); default: logged as warnings.
        storage: the layout of a new map, ``"compact"`` (default: about a fifth of the size of
            ``"full"``; :mod:`planarloc.map.codec`) or ``"full"``; an existing map keeps its own.
        skipped: receives each image left out of the map (missing, unreadable, truncated,
            damaged, undecodable, or of another size than its camera) and the reason; default:
            logged as warnings. The build goes on with the other images.
        allow_unrelated_frames: append images to a non-empty map even when their world frame
            looks unrelated to the map's (:mod:`planarloc.map.frame_check`); the finding is then
            reported through ``notify`` (default: a logged warning) instead of raised.
        **run: how the build runs (:class:`BuildRun`: ``workers``, ``lock_timeout``, ``mapper``).

    Returns:
        The map path.

    Raises:
        InputError: an existing map built with different settings, no usable image at all,
            images that declare a different world gravity than the map, bad options (checked
            before any work).
        UnrelatedFramesError: (an InputError) the images to append share no matches with the
            map or contradict its poses, and not ``allow_unrelated_frames``; the map file is
            left as it was.
        MapBusyError: another process still builds the map after ``lock_timeout``.
    """
    path = Path(path)
    unknown = sorted(set(run) - set(BuildRun.__annotations__))
    if unknown:
        raise TypeError(f"build_map() got unexpected keyword argument(s): {', '.join(unknown)}")
    workers, lock_timeout, mapper = run.get("workers"), run.get("lock_timeout"), run.get("mapper")
    num_words = check_num_words(num_words)
    if not isinstance(features, FeatureConfig):
        raise InputError(f"features: expected a FeatureConfig, got {type(features).__name__}")
    learned.load_backend(features.kind)  # a learned type's packages: a missing extra fails before any work
    images = list(images)
    if not images:
        raise InputError(f"{path}: no images to build the map from")
    if not all(isinstance(im, PosedImage) for im in images):
        raise InputError("images: expected PosedImage records (e.g. from planarloc.io.datasets.read_dataset)")
    config = map_config(features, num_words)
    declared = declared_world_down(images)
    skip: Skipped = skipped or _log_skipped
    tell: Callable[[str], None] = notify or _log_line

    with ThreadPoolExecutor(max_workers=workers or os.cpu_count() or 1) as pool:
        checked = _hash_images(images, pool, progress)
        bad = [(im, reason) for im, (_, reason) in zip(images, checked) if reason is not None]
        if len(bad) == len(images):
            raise InputError(
                f"{path}: none of the {len(images)} images can go into the map; the first: {bad[0][1]}"
            )
        for im, reason in bad:
            skip(im, reason)
        images = [im for im, (sha, _) in zip(images, checked) if sha is not None]
        hashes = [sha for sha, _ in checked if sha is not None]
        ready: dict[Path, Features | str] = {}  # features extracted by the frame check, kept for stage 2
        finding = _check_frames(path, config, images, hashes, features, declared, lock_timeout, pool, ready)
        if finding is not None and not finding[0].related:
            _unrelated_frames(path, *finding, allow_unrelated_frames, tell)
        try:
            db = MapDatabase.open_or_create(path, config, lock_timeout=lock_timeout, storage=storage)
        except OSError as exc:
            if exc.errno not in (errno.EACCES, errno.EPERM, errno.EROFS) or not path.is_file():
                raise
            _check_read_only_map_is_current(path, config, images, hashes, exc)
            return path
        with db:
            resolve_world_down(db, declared)  # a contradicting declaration fails before any work
            plan = plan_map_update(db, images, hashes)
            for line in plan.summary_lines(path):
                tell(line)
            if plan.keep:
                logger.info(
                    "%s: %d of %d images already in the map, resuming", path, len(plan.keep), len(images)
                )
            _store_images(db, plan, features, mapper or pool.map, progress, skip, ready)
            if db.num_images() == 0:
                raise InputError(
                    f"{path}: none of the {len(images) + len(bad)} images could be decoded; see the "
                    "reasons above"
                )
            _finish(db, plan, declared, num_words, seed, progress)
    return path


class BuildRun(TypedDict, total=False):
    """How :func:`build_map` runs (keyword arguments, all optional)."""

    #: feature extraction threads (default: one per core)
    workers: int | None
    #: seconds to wait while another process builds the same map (None: wait)
    lock_timeout: float | None
    #: runs the feature extraction instead of the threads: ``mapper(fn, images)`` yields
    #: ``fn(image)`` in input order (e.g. :func:`planarloc.distributed.ray_backend.RayBackend.map`)
    mapper: Mapper | None


def _log_skipped(image: PosedImage, reason: str) -> None:
    logger.warning("%s: left out of the map: %s", image.name, reason)


def _log_line(line: str) -> None:
    logger.warning("%s", line)


def _unrelated_frames(
    path: Path, frames: FrameCheck, num_new: int, allow: bool, tell: Callable[[str], None]
) -> None:
    """New images whose world frame looks unrelated to the map's: refused (the map unchanged),
    or with ``allow`` told and appended."""
    line = f"{path}: the {num_new} new images look unrelated to the map's world frame: {frames.summary()}"
    if not allow:
        raise UnrelatedFramesError(
            f"{line}; if they are another sequence with its own origin, build a "
            "separate map; to append them anyway, run `planarloc map build` with "
            "--allow-unrelated-frames (allow_unrelated_frames=True); the map is "
            "unchanged"
        )
    tell(f"{line}; appending them anyway (allow_unrelated_frames)")


def _hash_images(
    images: Sequence[PosedImage], pool: ThreadPoolExecutor, progress: Progress | None
) -> list[tuple[str | None, str | None]]:
    """Stage 1: every image file read once (whole, size checked, SHA-256), before the map is
    touched: ``(sha256, None)`` or ``(None, reason)`` per image."""
    out = []
    for i, checked in enumerate(pool.map(_hash_or_reason, images)):
        out.append(checked)
        if progress:
            progress("check images", i + 1, len(images))
    return out


def _store_images(
    db: MapDatabase,
    plan: MapUpdatePlan,
    features: FeatureConfig,
    mapper: Mapper,
    progress: Progress | None,
    skip: Skipped,
    ready: dict[Path, Features | str] | None = None,
) -> None:
    """Stage 2: the plan's pose updates, then the new and changed images' features.

    Reading and SIFT run in worker threads (OpenCV releases the GIL) or on the given mapper (e.g.
    a Ray cluster), except for the images in ``ready`` (by file path: extracted already, by the
    frame check); the database is written in this thread, in order, one transaction per image
    (resumable)."""
    for record, sha in plan.update:
        db.update_image_record(record.name, record, sha)
    todo = plan.replace + plan.add
    done = [(ready or {}).get(Path(r.path)) for r, _ in todo]  # decided once: ``fresh`` follows the others
    rest = [r for (r, _), d in zip(todo, done) if d is None]
    fresh = iter(mapper(functools.partial(extract_image_features, features=features), rest))
    for i, (record, sha) in enumerate(todo):
        got = done[i]
        feats = got if got is not None else next(fresh)
        if isinstance(feats, str):  # unreadable after all (e.g. a damaged JPEG): left out, the rest goes on
            skip(record, feats)
            continue
        if db.has_image(record.name):  # replaced: old features out, new in, one image at a time
            db.remove_image(record.name)
        db.add_image(record, feats, content_sha256=sha)
        if progress:
            progress("features", i + 1, len(todo))


def _check_frames(
    path: Path,
    config: dict,
    images: Sequence[PosedImage],
    hashes: Sequence[str],
    features: FeatureConfig,
    declared: WorldDown | None,
    lock_timeout: float | None,
    pool: ThreadPoolExecutor,
    ready: dict[Path, Features | str],
) -> tuple[FrameCheck, int] | None:
    """Before the map is opened for writing: do the images it would add share its world frame
    (:func:`planarloc.map.frame_check.check_appended_frames`)? The finding and the number of
    images the build would add, or None when there is nothing to
    check: no map yet, an empty map, another feature configuration (refused or replaced later),
    no new image, or a map this process cannot lock (a read-only folder: the build says so later).

    The map is read through a read-only connection while this process holds its writer lock (so
    no other build changes it meanwhile), and the file is not written: a refused build leaves it
    byte for byte as it was. Features extracted for the check go into ``ready``."""
    if not path.is_file():
        return None
    lock = MapWriterLock(path, timeout=lock_timeout)
    try:
        lock.acquire()
    except OSError as exc:
        if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
            return None
        raise
    try:
        if not path.is_file():  # removed while waiting for another writer
            return None
        with MapDatabase.open(path) as db:
            if db.num_images() == 0 or json.dumps(db.config, sort_keys=True) != json.dumps(
                config, sort_keys=True
            ):
                return None
            resolve_world_down(db, declared)  # a contradicting gravity declaration fails first, as it did
            new = [record for record, _ in plan_map_update(db, images, hashes).add]
            if not new:
                return None

            def extract(image: PosedImage) -> Features | str:
                ready[Path(image.path)] = extract_image_features(image, features)
                return ready[Path(image.path)]

            found = check_appended_frames(db, new, extract, DEFAULT_FRAME_CHECK, mapper=pool.map)
    finally:
        lock.release()
    return found, len(new)


def _finish(
    db: MapDatabase,
    plan: MapUpdatePlan,
    declared: WorldDown | None,
    num_words: int,
    seed: int,
    progress: Progress | None,
) -> None:
    """Stage 3: when anything changed (or the last build did not finish), the retrieval index,
    the map's gravity and how well its poses agree with its images
    (:mod:`planarloc.map.pose_accuracy`), its std calibration marked due, then the map is marked
    complete; a map built before gravity was stored gets it."""
    if plan.changes_map or not db.is_complete or db.get_blob(VOCABULARY_BLOB) is None:
        index_map(db, num_words=num_words, seed=seed, progress=progress)
        store_map_gravity(db, declared)
        store_accuracy(db, measure_map_accuracy(db, progress=progress))
        mark_std_calibration_stale(db)  # measured on the held-out images by the localizer's layer
        db.mark_complete()
    elif db.get_meta(GRAVITY_META) is None or world_down_changes(db, declared):  # e.g. up= given for this map
        store_map_gravity(db, declared)


def _check_read_only_map_is_current(
    path: Path, config: dict, images: Sequence[PosedImage], hashes: Sequence[str], exc: OSError
) -> None:
    """A map that cannot be written (read-only media) is fine if it already is this build."""
    with MapDatabase.open(path) as db:
        if json.dumps(db.config, sort_keys=True) != json.dumps(config, sort_keys=True):
            raise settings_mismatch_error(path, db.config, config)
        plan = plan_map_update(db, images, hashes)
        if db.is_complete and not plan.changes_map:
            logger.info("%s: read-only and already complete with these images; nothing to do", path)
            return
    need = len(plan.add) + len(plan.replace) + len(plan.update)
    raise InputError(
        f"{path}: cannot write the map ({exc.strerror}: {exc.filename}) but {need} image(s) must be "
        "added or updated; copy it to a writable location or build a new map there"
    )


def index_map(
    db: MapDatabase, num_words: int = DEFAULT_NUM_WORDS, seed: int = 0, progress: Progress | None = None
) -> None:
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
