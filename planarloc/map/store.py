"""The map store: posed images with their local and global features, in one SQLite file.

:class:`MapDatabase` creates, opens, reads and writes maps (schema in :mod:`planarloc.map.schema`,
byte layouts in :mod:`planarloc.map.codec`; its reading methods in :mod:`planarloc.map.store_read`,
its writing methods in :mod:`planarloc.map.store_write`). Every image is added in its own transaction (image
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
import json
import logging
import os
import sqlite3
from collections import OrderedDict
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Self, TypedDict

import numpy as np

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.map import schema
from planarloc.map.codec import (
    DEFAULT_STORAGE,
    DESCRIPTOR_ENCODINGS,
    GLOBAL_ENCODINGS,
    KEYPOINT_LAYOUTS,
    STORAGE_LAYOUTS,
    DescriptorBasis,
    check_storage,
)
from planarloc.map.errors import MapKeyError
from planarloc.map.lock import MapWriterLock
from planarloc.map.schema import (
    BLOB_SHA_PREFIX,
    RESERVED_META,
    SOURCES_TABLE,
    MapCorruptError,
    MapFormatError,
)
from planarloc.map.settings import canonical_json, settings_mismatch_error
from planarloc.map.store_read import MapReading
from planarloc.map.store_write import MapWriting

if TYPE_CHECKING:
    from typing_extensions import Unpack  # typing.Unpack is Python 3.12+

logger = logging.getLogger(__name__)

DEFAULT_CACHE_SIZE = 16


class CreateOptions(TypedDict, total=False):
    """The keyword options of :meth:`MapDatabase.create` that :meth:`MapDatabase.open_or_create` passes on
    (not ``overwrite``: it opens an existing map)."""

    descriptor_encoding: str
    storage: str
    cache_size: int
    lock_timeout: float | None


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
        raise MapCorruptError(
            f"{path}: damaged map file (SQLite quick_check: {first}); run `planarloc map check "
            f"{path}` and rebuild the map"
        )
    if state is not None:
        _PAGES_SOUND.add(state)


class MapDatabase(MapReading, MapWriting):
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

    def __init__(
        self,
        conn: sqlite3.Connection,
        path: Path,
        writable: bool,
        cache_size: int,
        lock: MapWriterLock | None = None,
    ) -> None:
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
            raise MapCorruptError(
                f"{path}: meta.storage {self._storage!r} / meta.global_encoding "
                f"{self._global_encoding!r} unknown; run `planarloc map check {path}`"
            )
        self._kp_layout = KEYPOINT_LAYOUTS[self._storage]
        self._basis: DescriptorBasis | None = None  # of klt rows, read on first use
        self._poses: tuple[tuple[int, int], dict[int, Pose]] | None = None  # (map version, {id: pose})
        try:
            self._dim: int | None = int(meta["descriptor_dim"]) if "descriptor_dim" in meta else None
            self._config: dict = json.loads(meta.get("config", "{}"))
        except (ValueError, TypeError) as exc:
            raise MapCorruptError(
                f"{path}: damaged meta table ({exc}); run `planarloc map check {path}`"
            ) from None
        if not isinstance(self._config, dict):
            raise MapCorruptError(
                f"{path}: meta.config is not a JSON object; run `planarloc map check {path}`"
            )

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
                f"descriptor_encoding: expected one of {', '.join(DESCRIPTOR_ENCODINGS)}, got "
                f"{descriptor_encoding!r}"
            )
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = _lock or MapWriterLock(path, timeout=lock_timeout)
        lock.acquire()
        try:
            return cls._create_locked(
                path, config_json, descriptor_encoding, storage, overwrite, cache_size, lock
            )
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _create_locked(
        cls,
        path: Path,
        config_json: str,
        descriptor_encoding: str,
        storage: str,
        overwrite: bool,
        cache_size: int,
        lock: MapWriterLock,
    ) -> MapDatabase:
        given, path = (
            path,
            Path(os.path.realpath(path)),
        )  # through a symbolic link: the file it names (the lock's)
        if path.exists():
            if not overwrite:
                raise InputError(
                    f"{given} already exists; open it with MapDatabase.open(path, mode='a') to append, "
                    "or pass overwrite=True to replace it"
                )
            path.unlink()
        for side in schema.sidecars(path):
            side.unlink(missing_ok=True)
        for stale in path.parent.glob(
            f".{path.name}.*.creating*"
        ):  # left by a killed create (we hold the lock)
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
        cls,
        path: str | os.PathLike,
        mode: Literal["r", "a"] = "r",
        *,
        cache_size: int = DEFAULT_CACHE_SIZE,
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
        cls, path: str | os.PathLike, config: Mapping[str, object], **create_options: Unpack[CreateOptions]
    ) -> MapDatabase:
        """Open ``path`` for appending if it exists (resume), else :meth:`create` it.

        Raises:
            InputError: the existing map was built with a different ``config`` — mixing
                features of two configurations in one map would silently break matching.
        """
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        timeout = create_options.pop("lock_timeout", None)
        lock = MapWriterLock(path, timeout=timeout)
        lock.acquire()  # exists-or-create must be decided by one writer at a time
        try:
            if not path.exists():
                return cls.create(path, config, _lock=lock, **create_options)
            db = cls._open_locked(path, "a", int(create_options.get("cache_size", DEFAULT_CACHE_SIZE)), lock)
        except BaseException:
            lock.release()
            raise
        if canonical_json(db.config) != canonical_json(config):
            if db.num_images() == 0 and not db.is_complete:
                # An empty, unfinished map (a build that failed before its first image) holds
                # nothing to lose: start it again with the new configuration.
                held, db._lock = db._lock, None
                db.close()
                logger.warning("%s: replacing an empty unfinished map built with other settings", path)
                try:
                    return cls.create(path, config, overwrite=True, _lock=held, **create_options)
                except BaseException:
                    if held is not None:
                        held.release()
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
            self._conn = None  # type: ignore[assignment]  # closed: typed as open for the methods using it
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

    # ---- reading -------------------------------------------------------------------------------
    def _find_id(self, name: str) -> int | None:
        row = self._db.execute("SELECT id FROM images WHERE name = ?", (name,)).fetchone()
        return None if row is None else int(row[0])

    def _resolve_id(self, key: str | int) -> int:
        if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            if self._db.execute("SELECT 1 FROM images WHERE id = ?", (int(key),)).fetchone() is None:
                raise MapKeyError(f"image id {int(key)} is not in map {self.path}")
            return int(key)
        image_id = self._find_id(str(key))
        if image_id is None:
            raise MapKeyError(f"image {key!r} is not in map {self.path}")
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
