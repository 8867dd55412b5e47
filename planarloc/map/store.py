"""The map store: posed images with their local and global features, in one SQLite file.

:class:`MapDatabase` creates, opens, reads and writes maps (schema in :mod:`planarloc.map.schema`,
byte layouts in :mod:`planarloc.map.codec`). Every image is added in its own transaction (image
row, keypoints and descriptors together), so a build that crashes or is interrupted leaves a
consistent map holding every image committed so far; re-running the build skips the images
already present (resumable). ``build_complete`` is set only by :meth:`MapDatabase.mark_complete`.
Reading is lazy: opening a map reads only its metadata, features are fetched per image on demand
(with a small LRU cache).

Durability: ``synchronous=NORMAL`` with WAL: a process crash never loses a committed image and
never corrupts the map; a power failure may lose the last few commits but leaves it consistent.

Opening checks the file's pages (SQLite ``quick_check``, :func:`_check_pages`), so a damaged file
is refused at once rather than when a damaged row is read; `planarloc map check` checks every row.

Writers take turns: opening for writing (``create``, ``open(mode="a")``) takes the map's
:class:`~planarloc.map.lock.MapWriterLock` (a waiting writer is told the owner's PID) and holds it
until :meth:`MapDatabase.close`. :meth:`MapDatabase.mark_complete` checkpoints the WAL and leaves
WAL mode, so a finished map is one self-contained file that opens from read-only media; a map that
is still in WAL mode is opened ``immutable`` when its folder is read-only.
"""

from __future__ import annotations

import datetime as dt
import errno
import hashlib
import json
import logging
import os
import sqlite3
from collections import OrderedDict
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Literal, Self

import numpy as np

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array
from planarloc.map import schema
from planarloc.map.codec import (
    DEFAULT_STORAGE,
    DESCRIPTOR_ENCODINGS,
    GLOBAL_ENCODINGS,
    KEYPOINT_LAYOUTS,
    PROJECT_ABOVE,
    PROJECTED_DIM,
    STORAGE_LAYOUTS,
    camera_key,
    KLT_MIN_FEATURES,
    DescriptorBasis,
    check_features,
    check_storage,
    damaged_poses,
    decode_basis,
    decode_descriptor_basis,
    decode_features,
    decode_global,
    encode_basis,
    encode_descriptor_basis,
    encode_descriptors,
    encode_global,
    encode_keypoints,
    fit_descriptor_basis,
    global_row_problem,
    pose_columns,
    poses_from_columns,
    record_digest,
)
from planarloc.map.lock import MapWriterLock
from planarloc.map.posed_image import PosedImage
from planarloc.map.schema import (
    BLOB_SHA_PREFIX,
    DESCRIPTOR_BASIS_BLOB,
    GLOBAL_BASIS_BLOB,
    IMAGE_COLUMNS,
    RESERVED_META,
    SOURCES_TABLE,
    MapCorruptError,
    MapFormatError,
    row_error,
)
from planarloc.map.settings import canonical_json, settings_mismatch_error

logger = logging.getLogger(__name__)

DEFAULT_CACHE_SIZE = 16


#: Map files whose pages this process found sound: (device, inode, size, mtime, ctime, WAL size, WAL mtime).
_PAGES_SOUND: set[tuple] = set()


def _file_state(path: Path) -> tuple | None:
    try:
        st = os.stat(path)
    except OSError:
        return None
    try:
        wal = os.stat(path.with_name(path.name + "-wal"))
        wal_state = (wal.st_size, wal.st_mtime_ns)
    except OSError:
        wal_state = (0, 0)
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns, *wal_state)


def _check_pages(conn: sqlite3.Connection, path: Path) -> None:
    """Refuse a damaged map file at open: SQLite's ``PRAGMA quick_check`` reads every page once and
    checks the b-trees, free lists and overflow chains (not the contents of blobs: their checksums
    are checked when they are read, and `planarloc map check` checks every row). About 1 ms per MB
    with the file in the page cache (60 ms for a 59 MB map); done once per process for an unchanged
    file (its inode, size, modification and change times).

    Raises:
        MapCorruptError: a page is damaged (e.g. bytes overwritten in the middle of the file).
    """
    state = _file_state(path)
    if state is not None and state in _PAGES_SOUND:
        return
    rows = conn.execute("PRAGMA quick_check(1)").fetchall()
    if [r[0] for r in rows] != ["ok"]:
        first = " ".join(str(rows[0][0]).split()) if rows else "no answer"
        raise MapCorruptError(f"{path}: damaged map file (SQLite quick_check: {first}); run `planarloc map check "
                              f"{path}` and rebuild the map")
    if state is not None:
        _PAGES_SOUND.add(state)


class MapDatabase:
    """A planarloc map file (schema in :mod:`planarloc.map.schema`).

    Create with :meth:`create`, open with :meth:`open` (``mode="r"`` read-only, ``"a"`` to
    append / resume a build) or :meth:`open_or_create`; use as a context manager. An instance
    belongs to the thread that opened it (sqlite3 rule); other threads or processes open the
    same file themselves — WAL lets any number of readers run while one writer appends.

    Example:
        >>> with MapDatabase.create("map.db", {"features": "rootsift", "tilt": True}) as db:  # doctest: +SKIP
        ...     for posed in frames:
        ...         if not db.has_image(posed.name):
        ...             db.add_image(posed, extract(posed.path))
        ...     db.mark_complete()
        >>> with MapDatabase.open("map.db") as db:                                           # doctest: +SKIP
        ...     feats = db.get_features("image_l/000012.png")
    """

    def __init__(self, conn: sqlite3.Connection, path: Path, writable: bool, cache_size: int,
                 lock: MapWriterLock | None = None) -> None:
        # Use create()/open(); the connection must hold a validated planarloc map.
        self._conn = conn
        self._lock = lock
        self._sources: bool | None = None
        self.path = path
        self.writable = writable
        self._cache: OrderedDict[int, Features] = OrderedDict()
        self._cache_size = int(cache_size)
        self._camera_ids: dict[tuple, int] = {}
        self._cameras: dict[int, Camera] = {}
        meta = dict(conn.execute("SELECT key, value FROM meta"))
        self._encoding = meta.get("descriptor_encoding", "auto")
        self._storage = meta.get("storage", "full")  # maps from before storage layouts
        self._global_encoding = meta.get("global_encoding", "float32")
        if self._storage not in STORAGE_LAYOUTS or self._global_encoding not in GLOBAL_ENCODINGS:
            raise MapCorruptError(f"{path}: meta.storage {self._storage!r} / meta.global_encoding "
                                  f"{self._global_encoding!r} unknown; run `planarloc map check {path}`")
        self._kp_layout = KEYPOINT_LAYOUTS[self._storage]
        self._basis: DescriptorBasis | None = None  # of klt rows, read on first use
        self._poses: tuple[tuple[int, int], dict[int, Pose]] | None = None  # (map version, {id: pose})
        try:
            self._dim: int | None = int(meta["descriptor_dim"]) if "descriptor_dim" in meta else None
            self._config: dict = json.loads(meta.get("config", "{}"))
        except (ValueError, TypeError) as exc:
            raise MapCorruptError(f"{path}: damaged meta table ({exc}); run `planarloc map check {path}`") from None
        if not isinstance(self._config, dict):
            raise MapCorruptError(f"{path}: meta.config is not a JSON object; run `planarloc map check {path}`")

    # ---- opening -------------------------------------------------------------------------------
    @classmethod
    def create(
        cls,
        path: str | os.PathLike,
        config: Mapping[str, object],
        *,
        descriptor_encoding: str = "auto",
        storage: str = DEFAULT_STORAGE,
        overwrite: bool = False,
        cache_size: int = DEFAULT_CACHE_SIZE,
        lock_timeout: float | None = None,
        _lock: MapWriterLock | None = None,
    ) -> MapDatabase:
        """Create a new, empty map and open it for appending.

        Args:
            path: the map file to create (parent directories are created).
            config: feature configuration (JSON-serialisable dict, e.g. extractor name,
                ``tilt`` flag, number of features), stored in ``meta.config``.
            descriptor_encoding: ``"auto"`` (``klt``, else ``uint4``, in compact maps, ``uint8`` in
                full ones, for non-negative descriptors; else float16), ``"uint4"``, ``"uint8"``,
                ``"float16"`` or ``"float32"`` (:mod:`planarloc.map.codec`).
            storage: ``"compact"`` (default: about 29 bytes per RootSIFT feature, 4 KB per
                global descriptor; ≤ 100 KB per KITTI image) or ``"full"`` (the layout of maps
                before compact ones: 140 bytes per feature, 32 KB per global descriptor).
            overwrite: replace an existing file instead of raising.
            cache_size: number of images whose features :meth:`get_features` keeps in memory.
            lock_timeout: seconds to wait for another writer of the same file (None: for ever).

        Raises:
            InputError: the file exists (and not ``overwrite``), bad config or encoding.
            MapBusyError: another process is writing the file (after ``lock_timeout``).
        """
        path = Path(path)
        config_json = canonical_json(config)
        storage = check_storage(storage)
        if descriptor_encoding not in DESCRIPTOR_ENCODINGS:
            raise InputError(
                f"descriptor_encoding: expected one of {', '.join(DESCRIPTOR_ENCODINGS)}, got {descriptor_encoding!r}"
            )
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = _lock or MapWriterLock(path, timeout=lock_timeout)
        lock.acquire()
        try:
            return cls._create_locked(path, config_json, descriptor_encoding, storage, overwrite, cache_size, lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _create_locked(cls, path: Path, config_json: str, descriptor_encoding: str, storage: str, overwrite: bool,
                       cache_size: int, lock: MapWriterLock) -> MapDatabase:
        given, path = path, Path(os.path.realpath(path))  # through a symbolic link: the file it names (the lock's)
        if path.exists():
            if not overwrite:
                raise InputError(
                    f"{given} already exists; open it with MapDatabase.open(path, mode='a') to append, "
                    "or pass overwrite=True to replace it"
                )
            path.unlink()
        for side in schema.sidecars(path):
            side.unlink(missing_ok=True)
        for stale in path.parent.glob(f".{path.name}.*.creating*"):  # left by a killed create (we hold the lock)
            stale.unlink(missing_ok=True)

        from planarloc.version import __version__

        meta = {
            "schema_version": str(schema.SCHEMA_VERSION),
            "created_by": schema.CREATED_BY,
            "planarloc_version": __version__,
            "created_at": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            "config": config_json,
            "descriptor_encoding": descriptor_encoding,
            "storage": storage,
            "global_encoding": "float32" if storage == "full" else "int4",
            "build_complete": "0",
        }
        # Build the schema in a temporary file and rename it: a crash never leaves a half-made map.
        tmp = path.with_name(f".{path.name}.{os.getpid()}.creating")
        for p in (tmp, *schema.sidecars(tmp)):
            p.unlink(missing_ok=True)
        conn = sqlite3.connect(tmp, isolation_level=None)
        try:
            conn.execute("PRAGMA page_size = 1024")  # blobs fill whole overflow pages: small pages waste less
            conn.execute(f"PRAGMA application_id = {schema.APPLICATION_ID}")
            conn.execute("BEGIN")
            for stmt in schema.STATEMENTS:
                conn.execute(stmt)
            conn.executemany("INSERT INTO meta (key, value) VALUES (?, ?)", meta.items())
            conn.execute("COMMIT")
            conn.execute("PRAGMA journal_mode = WAL")
        finally:
            conn.close()
        os.replace(tmp, path)
        return cls._open_locked(given, "a", cache_size, lock)

    @classmethod
    def open(
        cls, path: str | os.PathLike, mode: Literal["r", "a"] = "r", *, cache_size: int = DEFAULT_CACHE_SIZE,
        lock_timeout: float | None = None,
    ) -> MapDatabase:
        """Open an existing map.

        Args:
            path: the map file.
            mode: ``"r"`` read-only, ``"a"`` read-write (append images, resume a build).
            cache_size: number of images whose features :meth:`get_features` keeps in memory.
            lock_timeout: ``mode="a"`` only: seconds to wait for another writer (None: for ever).

        Raises:
            MapFormatError: the file does not exist, is not a planarloc map, or has a newer
                (or unknown older) schema version.
            MapBusyError: ``mode="a"`` and another process is writing it (after ``lock_timeout``).

        An incomplete map (interrupted build) opens normally; check :attr:`is_complete`.
        """
        path = Path(path)
        if mode not in ("r", "a"):
            raise InputError(f"mode: expected 'r' (read-only) or 'a' (append), got {mode!r}")
        if not path.is_file():
            raise MapFormatError(f"{path}: no such map file" + (" (it is a folder)" if path.is_dir() else ""))
        if mode == "r":
            return cls._open_locked(path, "r", cache_size, None)
        lock = MapWriterLock(path, timeout=lock_timeout)
        lock.acquire()
        try:
            return cls._open_locked(path, "a", cache_size, lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _open_locked(cls, path: Path, mode: str, cache_size: int, lock: MapWriterLock | None) -> MapDatabase:
        if not path.is_file():
            raise MapFormatError(f"{path}: no such map file (it was removed while waiting for its writer)")
        if mode == "a" and not os.access(path, os.W_OK):  # SQLite would open it read-only and fail at a write
            raise PermissionError(errno.EACCES, "the map file is read-only", str(path))
        conn = schema.open_connection(path, writable=mode == "a")
        with schema.closed_on_error(conn, path):
            _check_pages(conn, path)
            if mode == "a":
                conn.execute("PRAGMA journal_mode = WAL")
                conn.execute("PRAGMA synchronous = NORMAL")
                conn.execute(SOURCES_TABLE)
            conn.execute("PRAGMA foreign_keys = ON")
            return cls(conn, path, mode == "a", cache_size, lock)

    @classmethod
    def open_or_create(
        cls, path: str | os.PathLike, config: Mapping[str, object], **create_options: object
    ) -> MapDatabase:
        """Open ``path`` for appending if it exists (resume), else :meth:`create` it.

        Raises:
            InputError: the existing map was built with a different ``config`` — mixing
                features of two configurations in one map would silently break matching.
        """
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        timeout = create_options.pop("lock_timeout", None)
        lock = MapWriterLock(path, timeout=timeout)  # type: ignore[arg-type]
        lock.acquire()  # exists-or-create must be decided by one writer at a time
        try:
            if not path.exists():
                return cls.create(path, config, _lock=lock, **create_options)  # type: ignore[arg-type]
            db = cls._open_locked(path, "a", int(create_options.get("cache_size", DEFAULT_CACHE_SIZE)), lock)
        except BaseException:
            lock.release()
            raise
        if canonical_json(db.config) != canonical_json(config):
            if db.num_images() == 0 and not db.is_complete:
                # An empty, unfinished map (a build that failed before its first image) holds
                # nothing to lose: start it again with the new configuration.
                lock, db._lock = db._lock, None
                db.close()
                logger.warning("%s: replacing an empty unfinished map built with other settings", path)
                try:
                    return cls.create(path, config, overwrite=True, _lock=lock, **create_options)  # type: ignore[arg-type]
                except BaseException:
                    if lock is not None:
                        lock.release()
                    raise
            stored = db.config
            db.close()
            raise settings_mismatch_error(path, stored, config)
        return db

    # ---- lifetime ------------------------------------------------------------------------------
    def close(self) -> None:
        """Close the connection (idempotent). Committed images are already on disk."""
        if self._conn is not None:
            if self.writable and not self._conn.in_transaction:
                try:  # a complete map is left as one file that opens from read-only media
                    if self.is_complete:
                        self._leave_wal()
                except sqlite3.Error:
                    pass
            self._conn.close()
            self._conn = None  # type: ignore[assignment]
            self._cache.clear()
        if self._lock is not None:
            self._lock.release()
            self._lock = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._conn is None else f"{self.num_images()} images, complete={self.is_complete}"
        return f"MapDatabase({str(self.path)!r}, {'a' if self.writable else 'r'}, {state})"

    @property
    def _db(self) -> sqlite3.Connection:
        if self._conn is None:
            raise InputError(f"map {self.path} is closed")
        return self._conn

    def _require_writable(self) -> None:
        if not self.writable:
            raise InputError(f"map {self.path} is open read-only; open it with mode='a' to modify it")

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        """One atomic write transaction; rolled back on any exception (also KeyboardInterrupt)."""
        self._require_writable()
        conn = self._db
        conn.execute("BEGIN IMMEDIATE")
        try:
            yield conn
        except BaseException:
            if conn.in_transaction:
                conn.execute("ROLLBACK")
            raise
        conn.execute("COMMIT")

    # ---- metadata ------------------------------------------------------------------------------
    @property
    def config(self) -> dict:
        """The feature configuration given at creation (a copy)."""
        return json.loads(json.dumps(self._config))

    @property
    def is_complete(self) -> bool:
        """True once :meth:`mark_complete` ran and no image was added since."""
        return self.get_meta("build_complete") == "1"

    @property
    def storage(self) -> str:
        """The map's storage layout, ``"compact"`` or ``"full"`` (:mod:`planarloc.map.codec`)."""
        return self._storage

    @property
    def descriptor_dim(self) -> int | None:
        """Descriptor dimension D of the map, None while no image has features."""
        return self._dim

    def mark_complete(self) -> None:
        """Flag the build as finished (call after the last image and retrieval index).

        Also merges the write-ahead log into the file and leaves WAL mode, so that the finished
        map is a single file that opens from read-only media (re-opened with ``mode="a"`` it
        switches back to WAL)."""
        with self._transaction() as conn:
            conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('build_complete', '1')")
            conn.execute(
                "INSERT OR REPLACE INTO meta (key, value) VALUES ('completed_at', ?)",
                (dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),),
            )
        self._leave_wal()

    def _leave_wal(self) -> None:
        conn = self._db
        conn.execute("PRAGMA busy_timeout = 2000")  # never hang on a reader: WAL mode is also fine
        try:
            conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchall()
            conn.execute("PRAGMA journal_mode = DELETE").fetchall()
        except sqlite3.OperationalError as exc:  # a reader holds the WAL open: it stays in WAL mode
            logger.info("%s: stays in WAL mode (%s)", self.path, exc)
        finally:
            conn.execute("PRAGMA busy_timeout = 60000")

    def get_meta(self, key: str) -> str | None:
        """A meta value, None if absent."""
        row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else row[0]

    def set_meta(self, key: str, value: str) -> None:
        """Store a free-form meta value (the keys managed by planarloc are refused)."""
        if key in RESERVED_META or key.startswith(BLOB_SHA_PREFIX):
            raise InputError(f"meta key {key!r} is managed by MapDatabase and cannot be set directly")
        with self._transaction() as conn:
            conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, str(value)))

    # ---- writing -------------------------------------------------------------------------------
    def _camera_id(self, conn: sqlite3.Connection, camera: Camera, pending: dict) -> int:
        key = camera_key(camera)
        if key in self._camera_ids:
            return self._camera_ids[key]
        row = conn.execute(
            "SELECT id FROM cameras WHERE model = ? AND width = ? AND height = ? AND params = ?", key
        ).fetchone()
        cam_id = (
            row[0]
            if row is not None
            else conn.execute(
                "INSERT INTO cameras (model, width, height, params) VALUES (?, ?, ?, ?)", key
            ).lastrowid
        )
        pending[key] = cam_id
        return cam_id

    def add_image(self, posed: PosedImage, features: Features, *, content_sha256: str | None = None) -> int:
        """Add one image with its local features in one transaction; skip it if present.

        Args:
            posed: the image record (name must be unique in the map).
            features: its local features: keypoints (N, 2), descriptors (N, D), scales (N,),
                D equal for all images of the map. N = 0 is allowed.
            content_sha256: SHA-256 (hex) of the source image file, stored so that a later
                build can tell a changed image from the same one (see :mod:`planarloc.map.identity`).

        Returns:
            The image id (the existing one if an image with this name is already stored —
            this makes builds resumable).

        Raises:
            InputError: read-only map, bad feature shapes or values, descriptor dimension
                different from the map's.
        """
        self._require_writable()
        if not isinstance(posed, PosedImage):
            raise InputError(f"add_image: expected a PosedImage, got {type(posed).__name__}")
        existing = self._find_id(posed.name)
        if existing is not None:
            logger.debug("%s: image %r already in the map (id %d); skipped", self.path, posed.name, existing)
            return existing
        kp, desc, scales = check_features(features, self._dim)
        n, dim = desc.shape
        basis, new_basis = self.descriptor_basis(), None
        if basis is None and self._storage == "compact" and self._encoding == "auto" and n >= KLT_MIN_FEATURES \
                and bool(desc.min() >= 0):
            basis = new_basis = fit_descriptor_basis(desc)  # the map's first image with enough features
        encoding, desc_blob = encode_descriptors(desc, self._encoding, self._storage, basis)
        kp_blob = encode_keypoints(kp, scales, self._kp_layout)
        pose7 = pose_columns(posed.cam_from_world)
        digest = record_digest(posed.name, camera_key(posed.camera), pose7, n, kp_blob, dim, encoding, desc_blob)
        pending: dict = {}
        with self._transaction() as conn:
            if new_basis is not None and encoding == "klt":
                self._put_blob(conn, DESCRIPTOR_BASIS_BLOB, encode_descriptor_basis(new_basis))
            cam_id = self._camera_id(conn, posed.camera, pending)
            image_id = conn.execute(
                f"INSERT INTO images ({IMAGE_COLUMNS}) VALUES (NULL, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    posed.name,
                    cam_id,
                    *pose7,
                    int(posed.index),
                    None if posed.timestamp is None else float(posed.timestamp),
                    str(posed.path),
                    None if posed.depth_path is None else str(posed.depth_path),
                    float(posed.depth_scale),
                ),
            ).lastrowid
            conn.execute(
                "INSERT INTO keypoints (image_id, num, data) VALUES (?, ?, ?)", (image_id, n, kp_blob)
            )
            conn.execute(
                "INSERT INTO descriptors (image_id, num, dim, encoding, data) VALUES (?, ?, ?, ?, ?)",
                (image_id, n, dim, encoding, desc_blob),
            )
            conn.execute(
                "INSERT INTO image_sources (image_id, content_sha256, record_sha256) VALUES (?, ?, ?)",
                (image_id, content_sha256, digest),
            )
            if self._dim is None:
                conn.execute(
                    "INSERT OR REPLACE INTO meta (key, value) VALUES ('descriptor_dim', ?)", (str(dim),)
                )
            conn.execute("UPDATE meta SET value = '0' WHERE key = 'build_complete' AND value != '0'")
        self._camera_ids.update(pending)
        self._dim = dim
        if new_basis is not None and encoding == "klt":
            self._basis = new_basis
        return int(image_id)

    def descriptor_basis(self) -> DescriptorBasis | None:
        """The transform of the map's ``klt`` descriptor rows (:mod:`planarloc.map.codec`), None
        while it has none."""
        if self._basis is None:
            data = self.get_blob(DESCRIPTOR_BASIS_BLOB)
            if data is not None:
                try:
                    self._basis = decode_descriptor_basis(data)
                except MapCorruptError as exc:
                    raise row_error(self.path, f"blob {DESCRIPTOR_BASIS_BLOB!r}", str(exc)) from None
        return self._basis

    def image_source(self, name: str) -> tuple[str | None, str | None] | None:
        """``(stored path, content SHA-256)`` of image ``name`` (None entries when unknown);
        None if no image has this name."""
        row = self._db.execute(
            "SELECT i.path, s.content_sha256 FROM images i LEFT JOIN image_sources s ON s.image_id = i.id "
            "WHERE i.name = ?", (name,)
        ).fetchone() if self._has_sources() else self._db.execute(
            "SELECT path, NULL FROM images WHERE name = ?", (name,)
        ).fetchone()
        return None if row is None else (row[0], row[1])

    def _has_sources(self) -> bool:
        if self._sources is None:
            self._sources = self._db.execute(
                "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'image_sources'"
            ).fetchone() is not None
        return self._sources

    def update_image_record(self, name: str, posed: PosedImage, content_sha256: str | None = None) -> None:
        """Replace the pose, path and (if given) content hash of a stored image, keeping its
        features (for a corrected pose file or a moved dataset). Marks the build incomplete.

        Raises:
            KeyError: no image ``name``; InputError: read-only map or a different camera size.
        """
        image_id = self._resolve_id(name)
        old = self.get_posed_image(image_id)
        if (old.camera.width, old.camera.height) != (posed.camera.width, posed.camera.height):
            raise InputError(f"{self.path}: image {name}: the camera size changed; rebuild its features")
        pose7 = pose_columns(posed.cam_from_world)
        num, kp_blob, dim, encoding, desc_blob = self._db.execute(
            "SELECT k.num, k.data, d.dim, d.encoding, d.data FROM keypoints k JOIN descriptors d "
            "ON d.image_id = k.image_id WHERE k.image_id = ?", (image_id,)
        ).fetchone()
        digest = record_digest(name, camera_key(posed.camera), pose7, num, kp_blob, dim, encoding, desc_blob)
        pending: dict = {}
        with self._transaction() as conn:
            cam_id = self._camera_id(conn, posed.camera, pending)
            conn.execute(
                "UPDATE images SET camera_id = ?, qw = ?, qx = ?, qy = ?, qz = ?, tx = ?, ty = ?, tz = ?, "
                "path = ?, timestamp = ?, depth_path = ?, depth_scale = ? WHERE id = ?",
                (cam_id, *pose7, str(posed.path), None if posed.timestamp is None else float(posed.timestamp),
                 None if posed.depth_path is None else str(posed.depth_path), float(posed.depth_scale), image_id),
            )
            old_sha = conn.execute(
                "SELECT content_sha256 FROM image_sources WHERE image_id = ?", (image_id,)).fetchone()
            conn.execute(
                "INSERT OR REPLACE INTO image_sources (image_id, content_sha256, record_sha256) VALUES (?, ?, ?)",
                (image_id, content_sha256 or (old_sha[0] if old_sha else None), digest),
            )
            conn.execute("UPDATE meta SET value = '0' WHERE key = 'build_complete' AND value != '0'")
        self._camera_ids.update(pending)
        self._cameras.pop(cam_id, None)

    def remove_image(self, name: str) -> None:
        """Delete an image with its features and global descriptor. Marks the build incomplete.

        Raises:
            KeyError: no image ``name``; InputError: read-only map.
        """
        image_id = self._resolve_id(name)
        with self._transaction() as conn:
            for table in ("keypoints", "descriptors", "global_descriptors", "image_sources"):
                conn.execute(f"DELETE FROM {table} WHERE image_id = ?", (image_id,))
            conn.execute("DELETE FROM images WHERE id = ?", (image_id,))
            conn.execute("UPDATE meta SET value = '0' WHERE key = 'build_complete' AND value != '0'")
        self._cache.pop(image_id, None)

    def set_global_descriptors(
        self, descriptors: Mapping[str | int, object] | tuple[Sequence[int | str], object]
    ) -> None:
        """Store global (retrieval) descriptors, replacing earlier ones of the same images.

        Args:
            descriptors: ``{image name or id: (D,) vector}`` or ``(keys, (M, D) array)``.
                Normalise before if the retrieval needs it.

        How they are stored (:mod:`planarloc.map.codec`): as given (float32) in a ``full`` map;
        in a ``compact`` one with 4 bits a value (each within ``max|v| / 14``), and, when vectors of
        all images are given and there are more than ``PROJECT_ABOVE`` (2048) of them, as their
        coordinates in the top-512 subspace of these vectors (:meth:`global_basis`); vectors
        given later for some of the images are projected on that basis.

        Raises:
            InputError: unknown image, inconsistent dimensions, non-finite values.
            KeyError: an image name or id is not in the map.
        """
        if isinstance(descriptors, tuple):
            keys, arr = descriptors
            keys = list(keys)
            mat = check_array("global descriptors", arr, (len(keys), None), dtype=np.float32)
        else:
            keys = list(descriptors)
            if not keys:
                return
            mat = check_array(
                "global descriptors",
                [np.asarray(descriptors[k]).reshape(-1) for k in keys],
                (len(keys), None),
                dtype=np.float32,
            )
        ids = [self._resolve_id(k) for k in keys]
        if len(set(ids)) != len(ids):
            raise InputError("global descriptors: an image is given more than once")
        stored = {r[0] for r in self._db.execute("SELECT image_id FROM global_descriptors")}
        replace_all = stored <= set(ids)
        basis = self.global_basis()
        if not replace_all:
            dim = basis.shape[0] if basis is not None else self._db.execute(
                "SELECT dim FROM global_descriptors LIMIT 1").fetchone()[0]
            if mat.shape[1] != dim:
                raise InputError(
                    f"global descriptors: the map stores {dim}-D vectors, got {mat.shape[1]}-D; "
                    "give new vectors for all images to change the dimension"
                )
            encoding = self._global_encoding
        elif self._storage == "full":
            encoding, basis = "float32", None
        elif len(ids) > PROJECT_ABOVE and mat.shape[1] > PROJECTED_DIM:
            from planarloc.features.retrieval import subspace_basis

            encoding, basis = "projected", subspace_basis(mat, PROJECTED_DIM)
        else:
            encoding, basis = "int4", None
        values = mat @ basis if encoding == "projected" else mat
        rows = [(i, values.shape[1], blob) for i, blob in zip(ids, encode_global(values, encoding))]
        with self._transaction() as conn:
            if replace_all:
                conn.execute("DELETE FROM global_descriptors")
                self._store_basis(conn, basis if encoding == "projected" else None)
                conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('global_encoding', ?)", (encoding,))
            conn.executemany(
                "INSERT OR REPLACE INTO global_descriptors (image_id, dim, data) VALUES (?, ?, ?)", rows
            )
            conn.executemany("UPDATE image_sources SET global_sha256 = ? WHERE image_id = ?",
                             [(hashlib.sha256(r[2]).hexdigest(), r[0]) for r in rows])
        self._global_encoding = encoding

    @staticmethod
    def _store_basis(conn: sqlite3.Connection, basis: np.ndarray | None) -> None:
        """Write (or remove) the projection basis blob inside the caller's transaction."""
        if basis is None:
            conn.execute("DELETE FROM blobs WHERE key = ?", (GLOBAL_BASIS_BLOB,))
            conn.execute("DELETE FROM meta WHERE key = ?", (BLOB_SHA_PREFIX + GLOBAL_BASIS_BLOB,))
            return
        MapDatabase._put_blob(conn, GLOBAL_BASIS_BLOB, encode_basis(basis))

    def put_blob(self, key: str, data: bytes) -> None:
        """Store (replace) a named binary blob, e.g. a retrieval vocabulary or index."""
        with self._transaction() as conn:
            self._put_blob(conn, str(key), bytes(data))

    @staticmethod
    def _put_blob(conn: sqlite3.Connection, key: str, data: bytes) -> None:
        """Write a blob and its checksum inside the caller's transaction."""
        conn.execute("INSERT OR REPLACE INTO blobs (key, data) VALUES (?, ?)", (key, data))
        conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)",
                     (BLOB_SHA_PREFIX + key, hashlib.sha256(data).hexdigest()))

    # ---- reading -------------------------------------------------------------------------------
    def _find_id(self, name: str) -> int | None:
        row = self._db.execute("SELECT id FROM images WHERE name = ?", (name,)).fetchone()
        return None if row is None else int(row[0])

    def _resolve_id(self, key: str | int) -> int:
        if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            if self._db.execute("SELECT 1 FROM images WHERE id = ?", (int(key),)).fetchone() is None:
                raise KeyError(f"image id {int(key)} is not in map {self.path}")
            return int(key)
        image_id = self._find_id(str(key))
        if image_id is None:
            raise KeyError(f"image {key!r} is not in map {self.path}")
        return image_id

    def has_image(self, name: str) -> bool:
        """True if an image of this name is stored."""
        return self._find_id(name) is not None

    def image_id(self, name: str) -> int:
        """The id of image ``name`` (KeyError if absent)."""
        return self._resolve_id(str(name))

    def image_names(self) -> list[str]:
        """Names of all images, in id (insertion) order."""
        return [r[0] for r in self._db.execute("SELECT name FROM images ORDER BY id")]

    def image_ids(self) -> list[int]:
        """Ids of all images, ascending."""
        return [r[0] for r in self._db.execute("SELECT id FROM images ORDER BY id")]

    def num_images(self) -> int:
        return int(self._db.execute("SELECT COUNT(*) FROM images").fetchone()[0])

    def num_features(self, key: str | int) -> int:
        """Number of local features of an image (without loading them)."""
        image_id = self._resolve_id(key)
        return int(
            self._db.execute("SELECT num FROM keypoints WHERE image_id = ?", (image_id,)).fetchone()[0]
        )

    def _camera(self, camera_id: int) -> Camera:
        if camera_id not in self._cameras:
            row = self._db.execute(
                "SELECT model, width, height, params FROM cameras WHERE id = ?", (camera_id,)
            ).fetchone()
            if row is None:
                raise MapCorruptError(f"{self.path}: camera row {camera_id} is missing; run `planarloc map check`")
            try:
                self._cameras[camera_id] = Camera(row[0], row[1], row[2], tuple(json.loads(row[3])))
            except (ValueError, TypeError) as exc:
                raise MapCorruptError(f"{self.path}: camera row {camera_id} is damaged ({exc}); "
                                      f"run `planarloc map check {self.path}`") from None
        return self._cameras[camera_id]

    def _posed_from_row(self, row: tuple, pose: Pose | None = None) -> PosedImage:
        _, name, cam_id, qw, qx, qy, qz, tx, ty, tz, index, ts, path, depth_path, depth_scale = row
        if pose is None:
            try:
                pose = Pose.from_quat_wxyz([qw, qx, qy, qz], [tx, ty, tz])
            except (ValueError, TypeError) as exc:
                raise row_error(self.path, f"{name!r} (row id {row[0]})", f"damaged pose ({exc})") from None
        return PosedImage(
            name=name,
            path=Path(path) if path is not None else Path(name),
            cam_from_world=pose,
            camera=self._camera(cam_id),
            index=int(index),
            timestamp=ts,
            depth_path=None if depth_path is None else Path(depth_path),
            depth_scale=float(depth_scale),
        )

    def _image_row(self, key: str | int) -> tuple:
        if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            row = self._db.execute(
                f"SELECT {IMAGE_COLUMNS} FROM images WHERE id = ?", (int(key),)
            ).fetchone()
        else:
            row = self._db.execute(
                f"SELECT {IMAGE_COLUMNS} FROM images WHERE name = ?", (str(key),)
            ).fetchone()
        if row is None:
            raise KeyError(f"image {key!r} is not in map {self.path}")
        return row

    def get_posed_image(self, key: str | int) -> PosedImage:
        """The stored record of an image (by name or id)."""
        return self._posed_from_row(self._image_row(key))

    def get_pose(self, key: str | int) -> Pose:
        """``cam_from_world`` of an image (by name or id)."""
        return self._posed_from_row(self._image_row(key)).cam_from_world

    def get_camera(self, key: str | int) -> Camera:
        """Intrinsics of an image (by name or id)."""
        return self._camera(self._image_row(key)[2])

    def posed_images(self) -> list[PosedImage]:
        """All image records (no features), in id order."""
        rows = self._db.execute(f"SELECT {IMAGE_COLUMNS} FROM images ORDER BY id").fetchall()
        poses = self._poses_of(rows, 3)
        return [self._posed_from_row(r, pose) for r, pose in zip(rows, poses)]

    def load_all_poses(self) -> dict[str, Pose]:
        """``{name: cam_from_world}`` of all images, in id order."""
        rows = self._db.execute("SELECT id, name, qw, qx, qy, qz, tx, ty, tz FROM images ORDER BY id").fetchall()
        return dict(zip((r[1] for r in rows), self._poses_of(rows, 2)))

    def _poses_of(self, rows: Sequence[tuple], first: int) -> list[Pose]:
        """:meth:`_poses_checked`, reusing the poses already built while the map is unchanged (no
        commit by this connection or another one since): the localizer reads all 20,000 poses of a
        building-scale map twice when it opens (its images, then the map's gravity)."""
        conn = self._db
        version = (int(conn.execute("PRAGMA data_version").fetchone()[0]), conn.total_changes)
        if self._poses is None or self._poses[0] != version:
            self._poses = (version, {})
        known = self._poses[1]
        new = [r for r in rows if r[0] not in known]
        known.update(zip((r[0] for r in new), self._poses_checked(new, first)))
        return [known[r[0]] for r in rows]

    def _poses_checked(self, rows: Sequence[tuple], first: int) -> list[Pose]:
        """Poses of rows whose columns ``first:first + 7`` are (qw..tz); damaged rows are named."""
        columns = [r[first:first + 7] for r in rows]
        bad = damaged_poses(columns)
        if bad.any():
            r = rows[int(np.argmax(bad))]
            raise row_error(self.path, f"{r[1]!r} (row id {r[0]})", "damaged pose (not a unit quaternion "
                            "and finite translation)")
        return poses_from_columns(columns)

    def _features_from_blobs(self, label: str, num: int, kp_blob: bytes, dim: int, encoding: str,
                             desc_blob: bytes) -> Features:
        try:
            return decode_features(num, kp_blob, dim, encoding, desc_blob, self._kp_layout,
                                   self.descriptor_basis() if encoding == "klt" else None)
        except MapCorruptError as exc:
            raise row_error(self.path, label, str(exc)) from None

    def get_features(self, key: str | int) -> Features:
        """Local features of one image (by name or id), fetched on demand, LRU-cached.

        Returns:
            :class:`Features` with read-only float32 arrays; descriptors L2-normalised.
        """
        image_id = self._resolve_id(key) if not isinstance(key, (int, np.integer)) else int(key)
        cached = self._cache.get(image_id)
        if cached is not None:
            self._cache.move_to_end(image_id)
            return cached
        row = self._db.execute(
            "SELECT k.num, k.data, d.dim, d.encoding, d.data FROM keypoints k JOIN descriptors d "
            "ON d.image_id = k.image_id WHERE k.image_id = ?",
            (image_id,),
        ).fetchone()
        if row is None:
            name = self._db.execute("SELECT name FROM images WHERE id = ?", (image_id,)).fetchone()
            if name is None:
                raise KeyError(f"image id {image_id} is not in map {self.path}")
            raise row_error(self.path, f"{name[0]!r} (row id {image_id})", "its keypoints or descriptors are missing")
        feats = self._features_from_blobs(f"row id {image_id}", *row)
        self._verify_record(image_id, row)
        if self._cache_size > 0:
            self._cache[image_id] = feats
            if len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return feats

    def iter_features(self) -> Iterator[tuple[int, str, Features]]:
        """Stream ``(image id, name, Features)`` of all images in id order (one in memory at a time)."""
        cursor = self._db.execute(
            "SELECT i.id, i.name, k.num, k.data, d.dim, d.encoding, d.data FROM images i "
            "JOIN keypoints k ON k.image_id = i.id JOIN descriptors d ON d.image_id = i.id ORDER BY i.id"
        )
        for image_id, name, *blobs in cursor:
            feats = self._features_from_blobs(f"{name!r} (row id {image_id})", *blobs)
            self._verify_record(image_id, blobs)
            yield int(image_id), name, feats

    def _verify_record(self, image_id: int, blobs: Sequence[object]) -> None:
        """Compare an image row with its stored checksum (maps without checksums: no-op)."""
        if not self._has_sources():
            return
        row = self._db.execute(
            "SELECT i.name, c.model, c.width, c.height, c.params, i.qw, i.qx, i.qy, i.qz, i.tx, i.ty, i.tz, "
            "s.record_sha256 FROM images i JOIN image_sources s ON s.image_id = i.id "
            "LEFT JOIN cameras c ON c.id = i.camera_id WHERE i.id = ?", (image_id,)).fetchone()
        if row is None:
            return
        num, kp_blob, dim, encoding, desc_blob = blobs
        if record_digest(row[0], row[1:5], row[5:12], num, kp_blob, dim, encoding, desc_blob) != row[12]:
            raise row_error(self.path, f"{row[0]!r} (row id {image_id})",
                              "checksum mismatch (name, camera, pose or features changed on disk)")

    def get_global_descriptors(self) -> tuple[np.ndarray, np.ndarray]:
        """All stored global descriptors.

        Returns:
            (M,) int64 image ids (ascending) and (M, D) float32 descriptors; (0,), (0, 0) if none.
            In a map with a projection basis (:meth:`global_basis`), the (M, d) coordinates of
            the descriptors in that basis.
        """
        rows = self._db.execute(
            "SELECT image_id, dim, data FROM global_descriptors ORDER BY image_id"
        ).fetchall()
        sums = dict(self._db.execute("SELECT image_id, global_sha256 FROM image_sources "
                                     "WHERE global_sha256 IS NOT NULL")) if self._has_sources() else {}
        for image_id, _dim, data in rows:
            if image_id in sums and (not isinstance(data, bytes) or hashlib.sha256(data).hexdigest() != sums[image_id]):
                raise row_error(self.path, f"row id {image_id}", "global descriptor checksum mismatch")
        if not rows:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 0), dtype=np.float32)
        ids = np.array([r[0] for r in rows], dtype=np.int64)
        for image_id, dim, data in rows:
            problem = global_row_problem(data, dim, self._global_encoding)
            if problem is None and dim != rows[0][1]:
                problem = f"global descriptor of {dim} values, the others have {rows[0][1]}"
            if problem is not None:
                raise row_error(self.path, f"row id {image_id}", problem)
        mat = decode_global([r[2] for r in rows], rows[0][1], self._global_encoding)
        finite = np.isfinite(mat).all(axis=1)
        if not finite.all():
            raise row_error(self.path, f"row id {ids[np.argmin(finite)]}", "non-finite global descriptor")
        return ids, mat

    def global_basis(self) -> np.ndarray | None:
        """The (D, d) orthonormal basis the global descriptors are coordinates in, or None when
        they are stored whole (see :meth:`set_global_descriptors`)."""
        if self._global_encoding != "projected":
            return None
        data = self.get_blob(GLOBAL_BASIS_BLOB)
        if data is None:
            raise row_error(self.path, f"blob {GLOBAL_BASIS_BLOB!r}", "missing (global descriptors are projected)")
        try:
            return decode_basis(data)
        except MapCorruptError as exc:
            raise row_error(self.path, f"blob {GLOBAL_BASIS_BLOB!r}", str(exc)) from None

    def get_blob(self, key: str) -> bytes | None:
        """A named blob, or None if it was never stored."""
        row = self._db.execute("SELECT data FROM blobs WHERE key = ?", (str(key),)).fetchone()
        if row is None:
            return None
        data = row[0]
        if not isinstance(data, bytes):
            raise row_error(self.path, f"blob {key!r}", "not a blob")
        expected = self.get_meta(BLOB_SHA_PREFIX + str(key))
        if expected is not None and hashlib.sha256(data).hexdigest() != expected:
            raise row_error(self.path, f"blob {key!r}", "checksum mismatch (damaged on disk)")
        return data

    def blob_keys(self) -> list[str]:
        return [r[0] for r in self._db.execute("SELECT key FROM blobs ORDER BY key")]
