"""The map: posed images with their local and global features, in one SQLite file.

A map is an embedded SQLite database (stdlib :mod:`sqlite3`) in WAL journal mode. Every image
is added in its own transaction (image row, keypoints and descriptors together), so a build
that crashes or is interrupted leaves a consistent map holding every image committed so far;
re-running the build skips the images already present (resumable). ``build_complete`` is set
only by :meth:`MapDatabase.mark_complete`. Reading is lazy: opening a map reads only its
metadata, features are fetched per image on demand (with a small LRU cache).

Schema (version 1)::

    meta(key TEXT PRIMARY KEY, value TEXT)
        schema_version   '1'
        created_by       'planarloc'
        planarloc_version, created_at (ISO 8601 UTC)
        config           JSON of the feature configuration given to create() (e.g. tilt flag)
        descriptor_encoding  'auto' | 'uint8' | 'float16' | 'float32' (see below)
        descriptor_dim   D, set by the first image with features
        build_complete   '1' after mark_complete(), '0' while (re)building or appending
        blob_sha256/<key>  SHA-256 of each blob (checked when it is read)
        ... any other key set with set_meta()
    cameras(id INTEGER PRIMARY KEY, model TEXT, width INTEGER, height INTEGER,
            params TEXT  -- JSON list, COLMAP order;  UNIQUE(model, width, height, params))
    images(id INTEGER PRIMARY KEY, name TEXT UNIQUE, camera_id -> cameras.id,
           qw, qx, qy, qz, tx, ty, tz REAL  -- cam_from_world, x_cam = R x_world + t
           frame_index INTEGER, timestamp REAL NULL, path TEXT NULL,
           depth_path TEXT NULL, depth_scale REAL)
    keypoints(image_id PRIMARY KEY -> images.id, num INTEGER,
              data BLOB  -- float32 little-endian: N*2 keypoint coords (x0 y0 x1 y1 ...)
                         -- followed by N scales)
    descriptors(image_id PRIMARY KEY -> images.id, num INTEGER, dim INTEGER,
                encoding TEXT, data BLOB  -- N*D values, row-major, see encodings)
    global_descriptors(image_id PRIMARY KEY -> images.id, dim INTEGER,
                       data BLOB  -- float32 (D,))
    blobs(key TEXT PRIMARY KEY, data BLOB)   -- retrieval vocabulary / index, any bytes
    image_sources(image_id PRIMARY KEY -> images.id,
                  content_sha256 TEXT NULL  -- SHA-256 of the source image file's bytes
                  record_sha256 TEXT        -- SHA-256 of the stored row: name, camera, pose,
                                            -- keypoint and descriptor blobs (see record_digest)
                  global_sha256 TEXT NULL   -- SHA-256 of its global descriptor blob
      (added in 0.x without a schema bump: older maps lack it and are upgraded on append)

Descriptor encodings (descriptors are always returned as float32, L2-normalised rows):

- ``uint8`` (default for non-negative descriptors such as RootSIFT; 1 byte per value): the
  image's descriptors are scaled by ``255 / max`` (max over the image) and rounded. Decoding
  re-normalises each row, which cancels the scale, so none is stored. The error per value is at
  most ``0.5 / 255 · max`` (≤ 1e-3 for RootSIFT, whose values rarely exceed 0.4) — far below
  descriptor distances; nearest neighbours of true matches are unchanged.
- ``float16`` (default if a row has negative values; 2 bytes per value): relative error ≤ 2⁻¹¹.
- ``float32``: exact.

Durability: ``synchronous=NORMAL`` with WAL: a process crash never loses a committed image and
never corrupts the map; a power failure may lose the last few commits but leaves it consistent.

Writers take turns: opening for writing (``create``, ``open(mode="a")``) takes the map's
:class:`~planarloc.pipeline.map_lock.MapWriterLock` (a waiting writer is told the owner's PID)
and holds it until :meth:`MapDatabase.close`. :meth:`MapDatabase.mark_complete` checkpoints the
WAL and leaves WAL mode, so a finished map is one self-contained file that opens from read-only
media; a map that is still in WAL mode is opened ``immutable`` when its folder is read-only.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import sqlite3
import struct
from collections import OrderedDict
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Literal, Self

import numpy as np
from scipy.spatial.transform import Rotation

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array
from planarloc.pipeline.features import Features
from planarloc.pipeline.map_lock import MapWriterLock
from planarloc.pipeline.posed_image import PosedImage

logger = logging.getLogger(__name__)

SCHEMA_VERSION = 1
CREATED_BY = "planarloc"
#: SQLite ``application_id`` of planarloc maps ("PLOC"), so that ``file(1)`` can tell them apart.
APPLICATION_ID = 0x504C4F43
DESCRIPTOR_ENCODINGS = ("auto", "uint8", "float16", "float32")
DEFAULT_CACHE_SIZE = 16
BLOB_SHA_PREFIX = "blob_sha256/"
_RESERVED_META = frozenset(
    {"schema_version", "created_by", "config", "descriptor_encoding", "descriptor_dim", "build_complete"}
)

_SOURCES_TABLE = """CREATE TABLE IF NOT EXISTS image_sources (
        image_id INTEGER PRIMARY KEY REFERENCES images(id) ON DELETE CASCADE,
        content_sha256 TEXT, record_sha256 TEXT NOT NULL, global_sha256 TEXT)"""
_SCHEMA = [
    "CREATE TABLE meta (key TEXT PRIMARY KEY NOT NULL, value TEXT NOT NULL)",
    """CREATE TABLE cameras (
        id INTEGER PRIMARY KEY, model TEXT NOT NULL, width INTEGER NOT NULL, height INTEGER NOT NULL,
        params TEXT NOT NULL, UNIQUE (model, width, height, params))""",
    """CREATE TABLE images (
        id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE,
        camera_id INTEGER NOT NULL REFERENCES cameras(id),
        qw REAL NOT NULL, qx REAL NOT NULL, qy REAL NOT NULL, qz REAL NOT NULL,
        tx REAL NOT NULL, ty REAL NOT NULL, tz REAL NOT NULL,
        frame_index INTEGER NOT NULL, timestamp REAL, path TEXT, depth_path TEXT,
        depth_scale REAL NOT NULL)""",
    """CREATE TABLE keypoints (
        image_id INTEGER PRIMARY KEY REFERENCES images(id) ON DELETE CASCADE,
        num INTEGER NOT NULL, data BLOB NOT NULL)""",
    """CREATE TABLE descriptors (
        image_id INTEGER PRIMARY KEY REFERENCES images(id) ON DELETE CASCADE,
        num INTEGER NOT NULL, dim INTEGER NOT NULL, encoding TEXT NOT NULL, data BLOB NOT NULL)""",
    """CREATE TABLE global_descriptors (
        image_id INTEGER PRIMARY KEY REFERENCES images(id) ON DELETE CASCADE,
        dim INTEGER NOT NULL, data BLOB NOT NULL)""",
    "CREATE TABLE blobs (key TEXT PRIMARY KEY NOT NULL, data BLOB NOT NULL)",
    _SOURCES_TABLE,
]
_TABLES = ("meta", "cameras", "images", "keypoints", "descriptors", "global_descriptors", "blobs")
_IMAGE_COLUMNS = (
    "id, name, camera_id, qw, qx, qy, qz, tx, ty, tz, frame_index, timestamp, path, depth_path, depth_scale"
)


class MapFormatError(InputError):
    """A file is not a planarloc map, or one this version of planarloc cannot read."""


class MapCorruptError(MapFormatError):
    """A row of a map is damaged (wrong blob length, undecodable values, checksum mismatch)."""


def record_digest(name: str, camera_key: Sequence[object], pose7: Sequence[float], num: int,
                  kp_blob: bytes, dim: int, encoding: str, desc_blob: bytes) -> str:
    """SHA-256 (hex) of one stored image row: what ``planarloc map check`` re-computes.

    Args:
        name: image name.
        camera_key: ``(model, width, height, params JSON)`` of its camera row.
        pose7: ``(qw, qx, qy, qz, tx, ty, tz)`` as stored (float64).
        num, kp_blob, dim, encoding, desc_blob: the keypoint and descriptor rows.
    """
    h = hashlib.sha256()
    h.update(name.encode("utf-8") + b"\0")
    h.update(json.dumps([str(c) for c in camera_key]).encode() + b"\0")
    h.update(struct.pack("<7d", *(float(v) + 0.0 for v in pose7)))  # + 0.0: SQLite stores -0.0 as 0
    h.update(struct.pack("<qq", int(num), int(dim)) + encoding.encode() + b"\0")
    h.update(bytes(kp_blob))
    h.update(bytes(desc_blob))
    return h.hexdigest()


def _blob_error(path: Path, image: str, what: str) -> MapCorruptError:
    return MapCorruptError(f"{path}: image {image}: {what}; run `planarloc map check {path}` and rebuild the map")


# ---- descriptor codecs ------------------------------------------------------------------------
def encode_descriptors(descriptors: np.ndarray, encoding: str) -> tuple[str, bytes]:
    """Encode (N, D) float32 descriptors; ``encoding="auto"`` picks uint8 if all are >= 0.

    Returns:
        (the encoding used, the blob).
    """
    nonneg = descriptors.size == 0 or bool(descriptors.min() >= 0)
    if encoding == "auto":
        encoding = "uint8" if nonneg else "float16"
    if encoding == "uint8":
        if not nonneg:
            raise InputError(
                "descriptors: the uint8 encoding needs non-negative descriptors (e.g. RootSIFT); "
                "create the map with descriptor_encoding='float16' or 'auto'"
            )
        # One scale per image (not per row: 2.5x faster, and rows are L2-normalised so every
        # row keeps at least 255 / sqrt(D) levels); decoding re-normalises, so it is not stored.
        top = float(descriptors.max(initial=0.0))
        scaled = np.multiply(descriptors, np.float32(255.0 / top if top > 0 else 0.0))
        scaled += 0.5  # values are >= 0: truncation after +0.5 rounds to nearest
        return "uint8", scaled.astype(np.uint8).tobytes()
    if encoding == "float16":
        return "float16", descriptors.astype("<f2").tobytes()
    if encoding == "float32":
        return "float32", descriptors.astype("<f4").tobytes()
    raise InputError(
        f"descriptor encoding: expected one of {', '.join(DESCRIPTOR_ENCODINGS)}, got {encoding!r}"
    )


def decode_descriptors(blob: bytes, num: int, dim: int, encoding: str) -> np.ndarray:
    """Decode a descriptor blob to (num, dim) float32 L2-normalised rows (zero rows stay zero)."""
    if encoding not in _ITEM_SIZE:
        raise MapCorruptError(f"descriptor encoding {encoding!r} is not one of uint8, float16, float32")
    if num < 0 or dim < 0 or len(blob) != num * dim * _ITEM_SIZE[encoding]:
        raise MapCorruptError(
            f"descriptor blob is {len(blob)} bytes, expected {max(num * dim, 0) * _ITEM_SIZE[encoding]} "
            f"for {num} x {dim} {encoding} values"
        )
    d = np.frombuffer(blob, dtype=_DTYPE[encoding]).reshape(num, dim).astype(np.float32)
    norm = np.sqrt(np.einsum("ij,ij->i", d, d))
    inv = np.divide(1.0, norm, out=np.zeros_like(norm), where=norm > 0)
    d *= inv[:, None]
    return d


_DTYPE = {"uint8": np.uint8, "float16": "<f2", "float32": "<f4"}
_ITEM_SIZE = {"uint8": 1, "float16": 2, "float32": 4}


def _canonical_json(config: Mapping[str, object]) -> str:
    if not isinstance(config, Mapping):
        raise InputError(f"config: expected a dict, got {type(config).__name__}")
    try:
        return json.dumps(dict(config), sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise InputError(f"config: must be JSON-serialisable ({exc})") from None


def _flatten(config: Mapping[str, object], prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for k, v in config.items():
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def config_diff(stored: Mapping[str, object], given: Mapping[str, object]) -> str:
    """``key: map has X, given Y`` for every differing (nested) key, e.g. ``features.tilt``."""
    a, b = _flatten(stored), _flatten(given)
    diffs = [f"{k}: map has {json.dumps(a.get(k))}, given {json.dumps(b.get(k))}"
             for k in sorted(set(a) | set(b))
             if json.dumps(a.get(k)) != json.dumps(b.get(k)) and not k.endswith("feature_name")]
    return "; ".join(diffs) or "feature config differs"


def settings_mismatch_error(path: Path, stored: Mapping[str, object], given: Mapping[str, object]) -> InputError:
    """The error for building into a map made with other settings (names the differing keys)."""
    return InputError(f"{path} was built with another feature config ({config_diff(stored, dict(given))}); use a "
                      "new map file, or the map's settings to resume or extend it")


def _poses_from_columns(rows: Sequence[Sequence[float]]) -> list[Pose]:
    """Poses from rows ``(qw, qx, qy, qz, tx, ty, tz)``, converting all quaternions at once."""
    if not rows:
        return []
    a = np.asarray(rows, dtype=float)
    R = Rotation.from_quat(a[:, [1, 2, 3, 0]]).as_matrix()
    return [Pose(Ri, ti) for Ri, ti in zip(R, a[:, 4:])]


def _has_map_header(path: Path) -> bool:
    """True if the file starts like a planarloc map (SQLite header with our application_id)."""
    try:
        with open(path, "rb") as f:
            head = f.read(72)
    except OSError:
        return False
    return head[:16] == b"SQLite format 3\x00" and int.from_bytes(head[68:72], "big") == APPLICATION_ID


def _sidecars(path: Path) -> list[Path]:
    return [path.with_name(path.name + suffix) for suffix in ("-wal", "-shm", "-journal")]


class MapDatabase:
    """A planarloc map file (schema and storage in the module docstring).

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
        try:
            self._dim: int | None = int(meta["descriptor_dim"]) if "descriptor_dim" in meta else None
            self._config: dict = json.loads(meta.get("config", "{}"))
        except (ValueError, TypeError) as exc:
            raise MapCorruptError(f"{path}: damaged meta table ({exc}); run `planarloc map check {path}`") from None
        if not isinstance(self._config, dict):
            raise MapCorruptError(f"{path}: meta.config is not a JSON object; run `planarloc map check {path}`")

    # ---- opening -------------------------------------------------------------------------------
    @staticmethod
    def _connect(path: Path, writable: bool) -> sqlite3.Connection:
        base = path.absolute().as_uri()
        if writable:
            return sqlite3.connect(f"{base}?mode=rw", uri=True, isolation_level=None, timeout=60.0)
        try:
            conn = sqlite3.connect(f"{base}?mode=ro", uri=True, isolation_level=None, timeout=60.0)
            try:
                conn.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()
                return conn
            except sqlite3.OperationalError:
                conn.close()
                raise
            except sqlite3.DatabaseError:
                return conn  # not a database at all: _validate names it
        except sqlite3.OperationalError:
            # A map still in WAL mode needs to create '-shm' next to it, even to read. On
            # read-only media open it immutable, which is exact as long as no '-wal' holds
            # commits that are not yet in the main file.
            if os.access(path.parent, os.W_OK) and os.access(path, os.W_OK):
                raise
        wal = path.with_name(path.name + "-wal")
        if wal.is_file() and wal.stat().st_size > 0:
            raise MapFormatError(
                f"{path}: the map is read-only and its write-ahead log {wal.name} holds unmerged commits; "
                "open it once where its folder is writable (e.g. `planarloc map info`) to merge them"
            )
        return sqlite3.connect(f"{base}?mode=ro&immutable=1", uri=True, isolation_level=None)

    @classmethod
    def create(
        cls,
        path: str | os.PathLike,
        config: Mapping[str, object],
        *,
        descriptor_encoding: str = "auto",
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
            descriptor_encoding: ``"auto"`` (uint8 for non-negative descriptors, else
                float16), ``"uint8"``, ``"float16"`` or ``"float32"``.
            overwrite: replace an existing file instead of raising.
            cache_size: number of images whose features :meth:`get_features` keeps in memory.
            lock_timeout: seconds to wait for another writer of the same file (None: for ever).

        Raises:
            InputError: the file exists (and not ``overwrite``), bad config or encoding.
            MapBusyError: another process is writing the file (after ``lock_timeout``).
        """
        path = Path(path)
        config_json = _canonical_json(config)
        if descriptor_encoding not in DESCRIPTOR_ENCODINGS:
            raise InputError(
                f"descriptor_encoding: expected one of {', '.join(DESCRIPTOR_ENCODINGS)}, got {descriptor_encoding!r}"
            )
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = _lock or MapWriterLock(path, timeout=lock_timeout)
        lock.acquire()
        try:
            return cls._create_locked(path, config_json, descriptor_encoding, overwrite, cache_size, lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def _create_locked(cls, path: Path, config_json: str, descriptor_encoding: str, overwrite: bool,
                       cache_size: int, lock: MapWriterLock) -> MapDatabase:
        if path.exists():
            if not overwrite:
                raise InputError(
                    f"{path} already exists; open it with MapDatabase.open(path, mode='a') to append, "
                    "or pass overwrite=True to replace it"
                )
            path.unlink()
        for side in _sidecars(path):
            side.unlink(missing_ok=True)
        for stale in path.parent.glob(f".{path.name}.*.creating*"):  # left by a killed create (we hold the lock)
            stale.unlink(missing_ok=True)

        from planarloc import __version__

        meta = {
            "schema_version": str(SCHEMA_VERSION),
            "created_by": CREATED_BY,
            "planarloc_version": __version__,
            "created_at": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
            "config": config_json,
            "descriptor_encoding": descriptor_encoding,
            "build_complete": "0",
        }
        # Build the schema in a temporary file and rename it: a crash never leaves a half-made map.
        tmp = path.with_name(f".{path.name}.{os.getpid()}.creating")
        for p in (tmp, *_sidecars(tmp)):
            p.unlink(missing_ok=True)
        conn = sqlite3.connect(tmp, isolation_level=None)
        try:
            conn.execute("PRAGMA page_size = 16384")
            conn.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            conn.execute("BEGIN")
            for stmt in _SCHEMA:
                conn.execute(stmt)
            conn.executemany("INSERT INTO meta (key, value) VALUES (?, ?)", meta.items())
            conn.execute("COMMIT")
            conn.execute("PRAGMA journal_mode = WAL")
        finally:
            conn.close()
        os.replace(tmp, path)
        return cls._open_locked(path, "a", cache_size, lock)

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
        try:
            conn = cls._connect(path, writable=mode == "a")
        except sqlite3.Error as exc:
            raise MapFormatError(f"{path}: cannot open map ({exc})") from None
        try:
            cls._validate(conn, path)
            if mode == "a":
                conn.execute("PRAGMA journal_mode = WAL")
                conn.execute("PRAGMA synchronous = NORMAL")
                conn.execute(_SOURCES_TABLE)
            conn.execute("PRAGMA foreign_keys = ON")
            return cls(conn, path, mode == "a", cache_size, lock)
        except sqlite3.DatabaseError as exc:
            conn.close()
            raise MapCorruptError(f"{path}: damaged map file ({exc}); run `planarloc map check {path}`") from None
        except BaseException:
            conn.close()
            raise

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
        if _canonical_json(db.config) != _canonical_json(config):
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

    @staticmethod
    def _validate(conn: sqlite3.Connection, path: Path) -> None:
        try:
            tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        except sqlite3.DatabaseError as exc:
            if _has_map_header(path):
                raise MapCorruptError(f"{path}: damaged planarloc map ({exc}); rebuild it") from None
            raise MapFormatError(f"{path} is not a planarloc map (not an SQLite database: {exc})") from None
        if "meta" not in tables:
            raise MapFormatError(
                f"{path} is not a planarloc map (SQLite database without a planarloc meta table)"
            )
        try:
            meta = dict(
                conn.execute("SELECT key, value FROM meta WHERE key IN ('created_by', 'schema_version')")
            )
        except sqlite3.DatabaseError as exc:
            raise MapFormatError(f"{path} is not a planarloc map (unreadable meta table: {exc})") from None
        if meta.get("created_by") != CREATED_BY:
            raise MapFormatError(
                f"{path} is not a planarloc map (meta.created_by is {meta.get('created_by')!r}, expected {CREATED_BY!r})"
            )
        try:
            version = int(meta["schema_version"])
        except (KeyError, ValueError):
            raise MapFormatError(
                f"{path} is not a planarloc map (schema_version {meta.get('schema_version')!r} is not an integer)"
            ) from None
        if version > SCHEMA_VERSION:
            raise MapFormatError(
                f"{path} has map schema version {version}, but this planarloc reads versions up to "
                f"{SCHEMA_VERSION}; upgrade planarloc (pip install -U planarloc) to read it"
            )
        if version < SCHEMA_VERSION:
            raise MapFormatError(
                f"{path} has map schema version {version}, older than any this planarloc reads "
                f"({SCHEMA_VERSION}); rebuild the map"
            )
        missing = [t for t in _TABLES if t not in tables]
        if missing:
            raise MapFormatError(f"{path} is not a planarloc map (missing table(s): {', '.join(missing)})")

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
                (_dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),),
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
        if key in _RESERVED_META or key.startswith(BLOB_SHA_PREFIX):
            raise InputError(f"meta key {key!r} is managed by MapDatabase and cannot be set directly")
        with self._transaction() as conn:
            conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)", (key, str(value)))

    # ---- writing -------------------------------------------------------------------------------
    def _camera_id(self, conn: sqlite3.Connection, camera: Camera, pending: dict) -> int:
        key = (camera.model.value, camera.width, camera.height, json.dumps(list(camera.params)))
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
                build can tell a changed image from the same one (see ``map_identity``).

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
        kp = check_array("features.keypoints", features.keypoints, (None, 2), dtype=np.float32)
        n = len(kp)
        desc = check_array("features.descriptors", features.descriptors, (n, None), dtype=np.float32)
        scales = check_array("features.scales", features.scales, (n,), dtype=np.float32)
        dim = desc.shape[1]
        if dim == 0:
            raise InputError("features.descriptors: expected shape (N, D) with D >= 1, got D = 0")
        if self._dim is not None and dim != self._dim:
            raise InputError(f"features.descriptors: this map stores {self._dim}-D descriptors, got {dim}-D")
        encoding, desc_blob = encode_descriptors(desc, self._encoding)
        kp_blob = np.concatenate([kp.reshape(-1), scales]).astype("<f4").tobytes()
        pose = posed.cam_from_world
        q, t = pose.quat_wxyz, pose.t
        pose7 = [*map(float, q), *map(float, t)]
        cam_key = (posed.camera.model.value, posed.camera.width, posed.camera.height,
                   json.dumps(list(posed.camera.params)))
        digest = record_digest(posed.name, cam_key, pose7, n, kp_blob, dim, encoding, desc_blob)
        pending: dict = {}
        with self._transaction() as conn:
            cam_id = self._camera_id(conn, posed.camera, pending)
            image_id = conn.execute(
                f"INSERT INTO images ({_IMAGE_COLUMNS}) VALUES (NULL, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    posed.name,
                    cam_id,
                    *map(float, q),
                    *map(float, t),
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
        return int(image_id)

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
        q, t = posed.cam_from_world.quat_wxyz, posed.cam_from_world.t
        pose7 = [*map(float, q), *map(float, t)]
        cam_key = (posed.camera.model.value, posed.camera.width, posed.camera.height,
                   json.dumps(list(posed.camera.params)))
        num, kp_blob, dim, encoding, desc_blob = self._db.execute(
            "SELECT k.num, k.data, d.dim, d.encoding, d.data FROM keypoints k JOIN descriptors d "
            "ON d.image_id = k.image_id WHERE k.image_id = ?", (image_id,)
        ).fetchone()
        digest = record_digest(name, cam_key, pose7, num, kp_blob, dim, encoding, desc_blob)
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
                Stored as float32 as given (normalise before if the retrieval needs it).

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
        existing = self._db.execute("SELECT dim FROM global_descriptors LIMIT 1").fetchone()
        replace_all = existing is not None and mat.shape[1] != existing[0]
        if replace_all:
            stored = {r[0] for r in self._db.execute("SELECT image_id FROM global_descriptors")}
            if not stored <= set(ids):
                raise InputError(
                    f"global descriptors: the map stores {existing[0]}-D vectors, got {mat.shape[1]}-D; "
                    "give new vectors for all images to change the dimension"
                )
        rows = [(i, mat.shape[1], v.astype("<f4").tobytes()) for i, v in zip(ids, mat)]
        with self._transaction() as conn:
            if replace_all:
                conn.execute("DELETE FROM global_descriptors")
            conn.executemany(
                "INSERT OR REPLACE INTO global_descriptors (image_id, dim, data) VALUES (?, ?, ?)", rows
            )
            conn.executemany("UPDATE image_sources SET global_sha256 = ? WHERE image_id = ?",
                             [(hashlib.sha256(r[2]).hexdigest(), r[0]) for r in rows])

    def put_blob(self, key: str, data: bytes) -> None:
        """Store (replace) a named binary blob, e.g. a retrieval vocabulary or index."""
        data = bytes(data)
        with self._transaction() as conn:
            conn.execute("INSERT OR REPLACE INTO blobs (key, data) VALUES (?, ?)", (str(key), data))
            conn.execute("INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)",
                         (BLOB_SHA_PREFIX + str(key), hashlib.sha256(data).hexdigest()))

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
                raise _blob_error(self.path, f"{name!r} (row id {row[0]})", f"damaged pose ({exc})") from None
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
                f"SELECT {_IMAGE_COLUMNS} FROM images WHERE id = ?", (int(key),)
            ).fetchone()
        else:
            row = self._db.execute(
                f"SELECT {_IMAGE_COLUMNS} FROM images WHERE name = ?", (str(key),)
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
        rows = self._db.execute(f"SELECT {_IMAGE_COLUMNS} FROM images ORDER BY id").fetchall()
        poses = self._poses_checked(rows, 3)
        return [self._posed_from_row(r, pose) for r, pose in zip(rows, poses)]

    def load_all_poses(self) -> dict[str, Pose]:
        """``{name: cam_from_world}`` of all images, in id order."""
        rows = self._db.execute("SELECT id, name, qw, qx, qy, qz, tx, ty, tz FROM images ORDER BY id").fetchall()
        return dict(zip((r[1] for r in rows), self._poses_checked(rows, 2)))

    def _poses_checked(self, rows: Sequence[tuple], first: int) -> list[Pose]:
        """Poses of rows whose columns ``first:first + 7`` are (qw..tz); damaged rows are named."""
        vals = np.asarray([r[first:first + 7] for r in rows], dtype=float).reshape(-1, 7)
        norms = np.linalg.norm(vals[:, :4], axis=1)
        bad = ~np.isfinite(vals).all(axis=1) | (np.abs(norms - 1.0) > 1e-6)
        if bad.any():
            r = rows[int(np.argmax(bad))]
            raise _blob_error(self.path, f"{r[1]!r} (row id {r[0]})", "damaged pose (not a unit quaternion "
                              "and finite translation)")
        return _poses_from_columns([r[first:first + 7] for r in rows])

    def _features_from_blobs(self, label: str, num: int, kp_blob: bytes, dim: int, encoding: str,
                             desc_blob: bytes) -> Features:
        if not isinstance(kp_blob, bytes) or not isinstance(desc_blob, bytes):
            raise _blob_error(self.path, label, "feature data is not a blob")
        if num < 0 or len(kp_blob) != 12 * num:
            raise _blob_error(self.path, label, f"keypoint blob is {len(kp_blob)} bytes, expected {12 * max(num, 0)} "
                              f"for {num} keypoints")
        try:
            descriptors = decode_descriptors(desc_blob, num, dim, encoding)
        except MapCorruptError as exc:
            raise _blob_error(self.path, label, str(exc)) from None
        flat = np.frombuffer(kp_blob, dtype="<f4")
        keypoints = flat[: 2 * num].reshape(num, 2).astype(np.float32)
        scales = flat[2 * num :].astype(np.float32)
        if not (np.isfinite(keypoints).all() and np.isfinite(scales).all() and np.isfinite(descriptors).all()):
            raise _blob_error(self.path, label, "non-finite keypoints or descriptors")
        for a in (keypoints, scales, descriptors):
            a.setflags(write=False)
        return Features(keypoints, descriptors, scales)

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
            raise _blob_error(self.path, f"{name[0]!r} (row id {image_id})", "its keypoints or descriptors are missing")
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
            raise _blob_error(self.path, f"{row[0]!r} (row id {image_id})",
                              "checksum mismatch (name, camera, pose or features changed on disk)")

    def get_global_descriptors(self) -> tuple[np.ndarray, np.ndarray]:
        """All stored global descriptors.

        Returns:
            (M,) int64 image ids (ascending) and (M, D) float32 descriptors; (0,), (0, 0) if none.
        """
        rows = self._db.execute(
            "SELECT image_id, dim, data FROM global_descriptors ORDER BY image_id"
        ).fetchall()
        sums = dict(self._db.execute("SELECT image_id, global_sha256 FROM image_sources "
                                     "WHERE global_sha256 IS NOT NULL")) if self._has_sources() else {}
        for image_id, _dim, data in rows:
            if image_id in sums and (not isinstance(data, bytes) or hashlib.sha256(data).hexdigest() != sums[image_id]):
                raise _blob_error(self.path, f"row id {image_id}", "global descriptor checksum mismatch")
        if not rows:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 0), dtype=np.float32)
        ids = np.array([r[0] for r in rows], dtype=np.int64)
        for image_id, dim, data in rows:
            if dim != rows[0][1] or not isinstance(data, bytes) or len(data) != 4 * dim:
                raise _blob_error(self.path, f"row id {image_id}", f"global descriptor blob is "
                                  f"{len(data) if isinstance(data, bytes) else 'not a blob'} bytes, "
                                  f"expected {4 * rows[0][1]}")
        mat = np.frombuffer(b"".join(r[2] for r in rows), dtype="<f4").reshape(len(rows), rows[0][1])
        return ids, mat.astype(np.float32)

    def get_blob(self, key: str) -> bytes | None:
        """A named blob, or None if it was never stored."""
        row = self._db.execute("SELECT data FROM blobs WHERE key = ?", (str(key),)).fetchone()
        if row is None:
            return None
        data = row[0]
        if not isinstance(data, bytes):
            raise _blob_error(self.path, f"blob {key!r}", "not a blob")
        expected = self.get_meta(BLOB_SHA_PREFIX + str(key))
        if expected is not None and hashlib.sha256(data).hexdigest() != expected:
            raise _blob_error(self.path, f"blob {key!r}", "checksum mismatch (damaged on disk)")
        return data

    def blob_keys(self) -> list[str]:
        return [r[0] for r in self._db.execute("SELECT key FROM blobs ORDER BY key")]
