"""The map file's schema: tables, meta and blob keys, versions, and opening a file as a map.

A map is an embedded SQLite database (stdlib :mod:`sqlite3`). Schema (version 1)::

    meta(key TEXT PRIMARY KEY, value TEXT)
        schema_version   '1'
        created_by       'planarloc'
        planarloc_version, created_at (ISO 8601 UTC)
        config           JSON of the feature configuration given at creation (map.settings)
        descriptor_encoding  'auto' | 'uint4' | 'uint8' | 'float16' | 'float32' (map.codec; rows
                         also 'klt', with the blob codec/descriptor_basis)
        storage          'compact' | 'full': the layout of keypoints and global descriptors
                         (map.codec); absent in maps from before layouts: 'full'
        global_encoding  'float32' | 'int4' | 'projected' (map.codec); absent: 'float32'
        descriptor_dim   D, set by the first image with features
        build_complete   '1' after mark_complete(), '0' while (re)building or appending
        blob_sha256/<key>  SHA-256 of each blob (checked when it is read)
        gravity, world_down  the map's gravity (map.gravity)
        ... any other key set with set_meta()
    cameras(id INTEGER PRIMARY KEY, model TEXT, width INTEGER, height INTEGER,
            params TEXT  -- JSON list, COLMAP order;  UNIQUE(model, width, height, params))
    images(id INTEGER PRIMARY KEY, name TEXT UNIQUE, camera_id -> cameras.id,
           qw, qx, qy, qz, tx, ty, tz REAL  -- cam_from_world, x_cam = R x_world + t
           frame_index INTEGER, timestamp REAL NULL, path TEXT NULL,
           depth_path TEXT NULL, depth_scale REAL)
    keypoints(image_id PRIMARY KEY -> images.id, num INTEGER,
              data BLOB  -- 'full': float32 little-endian: N*2 keypoint coords (x0 y0 x1 y1 ...)
                         -- followed by N scales; 'compact': fixed point (map.codec))
    descriptors(image_id PRIMARY KEY -> images.id, num INTEGER, dim INTEGER,
                encoding TEXT, data BLOB  -- N*D values, row-major (map.codec)
    global_descriptors(image_id PRIMARY KEY -> images.id, dim INTEGER,
                       data BLOB  -- (dim,) in meta.global_encoding (map.codec))
    blobs(key TEXT PRIMARY KEY, data BLOB)   -- retrieval vocabulary, bases of the codecs, any bytes
    image_sources(image_id PRIMARY KEY -> images.id,
                  content_sha256 TEXT NULL  -- SHA-256 of the source image file's bytes
                  record_sha256 TEXT        -- SHA-256 of the stored row (map.codec.record_digest)
                  global_sha256 TEXT NULL   -- SHA-256 of its global descriptor blob
      (added in 0.x without a schema bump: older maps lack it and are upgraded on append)

:func:`connect` opens a file (read-only media included) and :func:`validate` tells a planarloc
map from any other file; :func:`open_connection` does both, for readers that want raw rows
(:mod:`planarloc.map.integrity`).
"""

from __future__ import annotations

import os
import sqlite3
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from planarloc.geometry.validation import InputError

SCHEMA_VERSION = 1
CREATED_BY = "planarloc"
#: SQLite ``application_id`` of planarloc maps ("PLOC"), so that ``file(1)`` can tell them apart.
APPLICATION_ID = 0x504C4F43
BLOB_SHA_PREFIX = "blob_sha256/"
#: The retrieval vocabulary's blob key.
VOCABULARY_BLOB = "retrieval/vlad_vocabulary"
#: The basis of projected global descriptors (``meta.global_encoding = 'projected'``).
GLOBAL_BASIS_BLOB = "retrieval/global_basis"
#: The transform of ``klt`` descriptor rows (compact maps; map.codec).
DESCRIPTOR_BASIS_BLOB = "codec/descriptor_basis"
#: Meta keys of the map's gravity (:mod:`planarloc.map.gravity`).
GRAVITY_META = "gravity"
WORLD_DOWN_META = "world_down"
#: Meta keys only :class:`~planarloc.map.store.MapDatabase` itself writes.
RESERVED_META = frozenset(
    {
        "schema_version",
        "created_by",
        "config",
        "descriptor_encoding",
        "descriptor_dim",
        "build_complete",
        "storage",
        "global_encoding",
    }
)

SOURCES_TABLE = """CREATE TABLE IF NOT EXISTS image_sources (
        image_id INTEGER PRIMARY KEY REFERENCES images(id) ON DELETE CASCADE,
        content_sha256 TEXT, record_sha256 TEXT NOT NULL, global_sha256 TEXT)"""
STATEMENTS = (
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
    SOURCES_TABLE,
)
TABLES = ("meta", "cameras", "images", "keypoints", "descriptors", "global_descriptors", "blobs")
IMAGE_COLUMNS = (
    "id, name, camera_id, qw, qx, qy, qz, tx, ty, tz, frame_index, timestamp, path, depth_path, depth_scale"
)


class MapFormatError(InputError):
    """A file is not a planarloc map, or one this version of planarloc cannot read."""


class MapCorruptError(MapFormatError):
    """A row of a map is damaged (wrong blob length, undecodable values, checksum mismatch)."""


def row_error(path: Path, image: str, what: str) -> MapCorruptError:
    """The error for a damaged row of the map at ``path`` (names it and what to do)."""
    return MapCorruptError(
        f"{path}: image {image}: {what}; run `planarloc map check {path}` and rebuild the map"
    )


def has_map_header(path: Path) -> bool:
    """True if the file starts like a planarloc map (SQLite header with our application_id)."""
    try:
        with open(path, "rb") as f:
            head = f.read(72)
    except OSError:
        return False
    return head[:16] == b"SQLite format 3\x00" and int.from_bytes(head[68:72], "big") == APPLICATION_ID


def sidecars(path: Path) -> list[Path]:
    """SQLite's side files of a database file (``-wal``, ``-shm``, ``-journal``)."""
    return [path.with_name(path.name + suffix) for suffix in ("-wal", "-shm", "-journal")]


def connect(path: Path, writable: bool) -> sqlite3.Connection:
    """An SQLite connection to ``path`` (``mode=rw`` or read-only).

    A map still in WAL mode needs to create ``-shm`` next to it, even to read: on read-only
    media it is opened ``immutable``, which is exact as long as no ``-wal`` holds commits that
    are not yet in the main file (otherwise :class:`MapFormatError` says what to do).
    """
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
            return conn  # not a database at all: validate() names it
    except sqlite3.OperationalError:
        if os.access(path.parent, os.W_OK) and os.access(path, os.W_OK):
            raise
    wal = path.with_name(path.name + "-wal")
    if wal.is_file() and wal.stat().st_size > 0:
        raise MapFormatError(
            f"{path}: the map is read-only and its write-ahead log {wal.name} holds unmerged commits; "
            "open it once where its folder is writable (e.g. `planarloc map info`) to merge them"
        )
    return sqlite3.connect(f"{base}?mode=ro&immutable=1", uri=True, isolation_level=None)


def validate(conn: sqlite3.Connection, path: Path) -> None:
    """Raise :class:`MapFormatError` unless ``conn`` holds a planarloc map this version reads."""
    try:
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    except sqlite3.DatabaseError as exc:
        if has_map_header(path):
            raise MapCorruptError(f"{path}: damaged planarloc map ({exc}); rebuild it") from None
        raise MapFormatError(f"{path} is not a planarloc map (not an SQLite database: {exc})") from None
    if "meta" not in tables:
        raise MapFormatError(
            f"{path} is not a planarloc map (SQLite database without a planarloc meta table)"
        )
    try:
        meta = dict(conn.execute("SELECT key, value FROM meta WHERE key IN ('created_by', 'schema_version')"))
    except sqlite3.DatabaseError as exc:
        raise MapFormatError(f"{path} is not a planarloc map (unreadable meta table: {exc})") from None
    if meta.get("created_by") != CREATED_BY:
        raise MapFormatError(
            f"{path} is not a planarloc map (meta.created_by is {meta.get('created_by')!r}, expected "
            f"{CREATED_BY!r})"
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
    missing = [t for t in TABLES if t not in tables]
    if missing:
        raise MapFormatError(f"{path} is not a planarloc map (missing table(s): {', '.join(missing)})")


def open_connection(path: str | os.PathLike, writable: bool = False) -> sqlite3.Connection:
    """A connection to the planarloc map at ``path``, validated (the caller closes it).

    Raises:
        MapFormatError: no such file, not a planarloc map, or one of another schema version.
        MapCorruptError: the file is a damaged map.
    """
    path = Path(path)
    if not path.is_file():
        raise MapFormatError(f"{path}: no such map file" + (" (it is a folder)" if path.is_dir() else ""))
    try:
        conn = connect(path, writable)
    except sqlite3.Error as exc:
        raise MapFormatError(f"{path}: cannot open map ({exc})") from None
    with closed_on_error(conn, path):
        validate(conn, path)
    return conn


@contextmanager
def closed_on_error(conn: sqlite3.Connection, path: Path) -> Iterator[None]:
    """Close ``conn`` if the block fails; an SQLite error there means a damaged map file."""
    try:
        yield
    except sqlite3.DatabaseError as exc:
        conn.close()
        raise MapCorruptError(f"{path}: damaged map file ({exc}); run `planarloc map check {path}`") from None
    except BaseException:
        conn.close()
        raise
