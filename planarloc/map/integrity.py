"""Check a map file row by row: what ``planarloc map check`` (and ``map info``) run.

Checks, in order: SQLite's ``PRAGMA integrity_check`` (pages, indexes, free lists); the meta
table (config JSON, descriptor dimension); every camera row (a valid model and size); every
image row (finite unit quaternion and translation, existing camera, keypoint and descriptor
rows present, blob lengths matching their counts, finite decoded values, and the stored
record checksum: name, camera, pose and both blobs); every global descriptor (length,
finite); the retrieval vocabulary (decodes). Each problem is one line naming the row.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from planarloc.features.retrieval import VladVocabulary
from planarloc.geometry.camera import Camera
from planarloc.map.codec import (
    KEYPOINT_LAYOUTS,
    DescriptorBasis,
    decode_basis,
    decode_descriptor_basis,
    decode_features,
    decode_global,
    global_row_problem,
    record_digest,
)
from planarloc.map.schema import (
    BLOB_SHA_PREFIX,
    DESCRIPTOR_BASIS_BLOB,
    GLOBAL_BASIS_BLOB,
    VOCABULARY_BLOB,
    MapFormatError,
    open_connection,
)

MAX_PROBLEMS = 50


@dataclass
class MapCheckReport:
    """Result of :func:`check_map`: ``problems`` is empty for a sound map."""

    path: Path
    num_images: int = 0
    complete: bool = False
    problems: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def add(self, problem: str) -> None:
        if len(self.problems) < MAX_PROBLEMS:
            self.problems.append(problem)
        elif len(self.problems) == MAX_PROBLEMS:
            self.problems.append("... (more problems not listed)")


def check_map(path: str | Path, progress: Callable[[int, int], None] | None = None) -> MapCheckReport:
    """Check every row of the map at ``path``.

    Args:
        path: the map file.
        progress: optional ``(done, total)`` callback over the image rows.

    Returns:
        A :class:`MapCheckReport` (problems as one line each, naming table and row).

    Raises:
        MapFormatError: the file is not a planarloc map at all (cannot be opened as one).
    """
    path = Path(path)
    report = MapCheckReport(path)
    conn = open_connection(path)
    try:
        try:
            rows = conn.execute("PRAGMA integrity_check(20)").fetchall()
            if [r[0] for r in rows] != ["ok"]:
                for (msg,) in rows:
                    for line in str(msg).splitlines():
                        if line.strip() and not line.startswith("*** in database"):
                            report.add(f"SQLite integrity_check: {line.strip()}")
        except sqlite3.DatabaseError as exc:
            report.add(f"SQLite integrity_check: {exc}")
        try:
            _check_rows(conn, report, progress)
        except sqlite3.DatabaseError as exc:
            report.add(f"reading the map failed: {exc}")
    finally:
        conn.close()
    return report


def _check_rows(
    conn: sqlite3.Connection, report: MapCheckReport, progress: Callable[[int, int], None] | None
) -> None:
    meta = _check_meta(conn, report)
    cameras = _check_cameras(conn, report)
    has_sources = (
        conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'image_sources'").fetchone()
        is not None
    )
    digests, global_sums = {}, {}
    if has_sources:
        for image_id, rec, glob in conn.execute(
            "SELECT image_id, record_sha256, global_sha256 FROM image_sources"
        ):
            digests[image_id], global_sums[image_id] = rec, glob
    _check_images(
        conn, report, _MapContext(meta, cameras, digests, _descriptor_basis(conn, report)), progress
    )
    _check_global_descriptors(conn, report, meta, global_sums)
    _check_blobs(conn, report, meta)


@dataclass(frozen=True)
class _MapContext:
    """What checking an image row needs: meta, the valid cameras by id, recorded digests,
    the descriptor basis."""

    meta: dict
    cameras: dict[int, tuple]
    digests: dict
    basis: DescriptorBasis | None


def _check_meta(conn: sqlite3.Connection, report: MapCheckReport) -> dict:
    """The meta table as a dict; flags an unreadable config or descriptor dimension."""
    meta = dict(conn.execute("SELECT key, value FROM meta"))
    report.complete = meta.get("build_complete") == "1"
    try:
        cfg = json.loads(meta.get("config", "{}"))
        if not isinstance(cfg, dict):
            raise ValueError("not a JSON object")
    except ValueError as exc:
        report.add(f"meta.config: not valid JSON ({exc})")
    dim_meta = meta.get("descriptor_dim")
    if dim_meta is not None and not dim_meta.isdigit():
        report.add(f"meta.descriptor_dim: {dim_meta!r} is not an integer")
    return meta


def _check_cameras(conn: sqlite3.Connection, report: MapCheckReport) -> dict[int, tuple]:
    """The cameras that parse, by id (their raw row); flags the others."""
    cameras: dict[int, tuple] = {}
    for cam_id, model, w, h, params in conn.execute("SELECT id, model, width, height, params FROM cameras"):
        try:
            Camera(model, w, h, tuple(json.loads(params)))
            cameras[cam_id] = (model, w, h, params)
        except (ValueError, TypeError) as exc:
            report.add(f"cameras row {cam_id}: damaged ({exc})")
    return cameras


def _check_images(
    conn: sqlite3.Connection,
    report: MapCheckReport,
    ctx: _MapContext,
    progress: Callable[[int, int], None] | None,
) -> None:
    """Every image row with its keypoints and descriptors: name, camera, pose, features, checksum."""
    total = int(conn.execute("SELECT COUNT(*) FROM images").fetchone()[0])
    report.num_images = total
    names_seen: set[str] = set()
    cursor = conn.execute(
        "SELECT i.id, i.name, i.camera_id, i.qw, i.qx, i.qy, i.qz, i.tx, i.ty, i.tz, "
        "k.num, k.data, d.num, d.dim, d.encoding, d.data FROM images i "
        "LEFT JOIN keypoints k ON k.image_id = i.id "
        "LEFT JOIN descriptors d ON d.image_id = i.id ORDER BY i.id"
    )
    for done, row in enumerate(cursor, 1):
        image_id, name, cam_id = row[0], row[1], row[2]
        where = f"images row {image_id} ({name!r})"
        if not isinstance(name, str) or name in names_seen:
            report.add(f"{where}: bad or duplicate name")
        names_seen.add(str(name))
        if cam_id not in ctx.cameras:
            report.add(f"{where}: camera {cam_id} is missing or damaged")
        for problem in _image_row_problems(row, ctx):
            report.add(f"{where}: {problem}")
        if progress:
            progress(done, total)


def _image_row_problems(row: tuple, ctx: _MapContext) -> list[str]:
    """What is wrong with an image row's pose, features or checksum (one line each)."""
    image_id, name, cam_id = row[0], row[1], row[2]
    pose7, (kp_num, kp_blob, d_num, dim, encoding, d_blob) = row[3:10], row[10:]
    problems = []
    try:
        p = np.asarray(pose7, dtype=float)
        if not np.isfinite(p).all() or abs(np.linalg.norm(p[:4]) - 1.0) > 1e-6:
            raise ValueError("not a finite unit quaternion and translation")
    except (ValueError, TypeError) as exc:
        problems.append(f"damaged pose ({exc})")
    if kp_blob is None or d_blob is None:
        problems.append("keypoint or descriptor row missing")
    elif not isinstance(kp_blob, bytes) or not isinstance(d_blob, bytes):
        problems.append("feature data is not a blob")
    else:
        problem = _check_features(kp_num, kp_blob, d_num, dim, encoding, d_blob, ctx.meta, ctx.basis)
        if problem:
            problems.append(problem)
        elif image_id in ctx.digests and cam_id in ctx.cameras:
            digest = record_digest(name, ctx.cameras[cam_id], pose7, kp_num, kp_blob, dim, encoding, d_blob)
            if digest != ctx.digests[image_id]:
                problems.append("checksum mismatch (name, camera, pose or features changed on disk)")
    return problems


def _check_global_descriptors(
    conn: sqlite3.Connection, report: MapCheckReport, meta: dict, global_sums: dict
) -> None:
    """Global descriptor rows: encoding, finite values, checksum, no orphans."""
    global_encoding = meta.get("global_encoding", "float32")
    for image_id, gdim, data in conn.execute("SELECT image_id, dim, data FROM global_descriptors"):
        problem = global_row_problem(data, gdim, global_encoding)
        if problem is not None:
            report.add(f"global_descriptors row {image_id}: {problem}")
        elif not np.isfinite(decode_global([data], gdim, global_encoding)).all():
            report.add(f"global_descriptors row {image_id}: non-finite values")
        elif global_sums.get(image_id) not in (None, hashlib.sha256(data).hexdigest()):
            report.add(f"global_descriptors row {image_id}: checksum mismatch")
    orphans = conn.execute(
        "SELECT COUNT(*) FROM global_descriptors WHERE image_id NOT IN (SELECT id FROM images)"
    )
    if (n := orphans.fetchone()[0]) > 0:
        report.add(f"global_descriptors: {n} row(s) of images that are not in the map")


def _check_blobs(conn: sqlite3.Connection, report: MapCheckReport, meta: dict) -> None:
    """Blob checksums, the global projection basis, the vocabulary, and completeness."""
    for key, data in conn.execute("SELECT key, data FROM blobs"):
        expected = meta.get(BLOB_SHA_PREFIX + str(key))
        if not isinstance(data, bytes):
            report.add(f"blobs row {key!r}: not a blob")
        elif expected is not None and hashlib.sha256(data).hexdigest() != expected:
            report.add(f"blobs row {key!r}: checksum mismatch")
    if meta.get("global_encoding", "float32") == "projected":
        basis = conn.execute("SELECT data FROM blobs WHERE key = ?", (GLOBAL_BASIS_BLOB,)).fetchone()
        try:
            if basis is None:
                raise MapFormatError("missing, but the global descriptors are projected on it")
            decode_basis(basis[0])
        except MapFormatError as exc:
            report.add(f"blobs row {GLOBAL_BASIS_BLOB!r}: {exc}")
    vocab = conn.execute("SELECT data FROM blobs WHERE key = ?", (VOCABULARY_BLOB,)).fetchone()
    if vocab is not None:
        try:
            VladVocabulary.from_bytes(vocab[0])
        except (ValueError, TypeError) as exc:
            report.add(f"blobs row {VOCABULARY_BLOB!r}: {exc}")
    elif report.complete:
        report.add("the map is marked complete but has no retrieval vocabulary")
    total = report.num_images
    if report.complete and total:
        n_global = conn.execute("SELECT COUNT(*) FROM global_descriptors").fetchone()[0]
        if n_global != total:
            report.add(f"the map is marked complete but {total - n_global} image(s) lack a global descriptor")


def _descriptor_basis(conn: sqlite3.Connection, report: MapCheckReport) -> DescriptorBasis | None:
    row = conn.execute("SELECT data FROM blobs WHERE key = ?", (DESCRIPTOR_BASIS_BLOB,)).fetchone()
    if row is None:
        return None
    try:
        return decode_descriptor_basis(row[0] if isinstance(row[0], bytes) else b"")
    except MapFormatError as exc:
        report.add(f"blobs row {DESCRIPTOR_BASIS_BLOB!r}: {exc}")
        return None


def _check_features(
    kp_num: object,
    kp_blob: bytes,
    d_num: object,
    dim: object,
    encoding: object,
    d_blob: bytes,
    meta: dict,
    basis: DescriptorBasis | None,
) -> str | None:
    if not (isinstance(kp_num, int) and isinstance(d_num, int) and isinstance(dim, int)):
        return "damaged feature counts"
    if not isinstance(encoding, str):
        return "damaged feature counts"
    if kp_num != d_num:
        return f"{kp_num} keypoints but {d_num} descriptors"
    if meta.get("descriptor_dim") not in (None, str(dim)):
        return f"descriptor dimension {dim}, the map's is {meta.get('descriptor_dim')}"
    try:
        decode_features(
            kp_num,
            kp_blob,
            dim,
            encoding,
            d_blob,
            KEYPOINT_LAYOUTS.get(meta.get("storage", "full"), "?"),
            basis,
        )
    except MapFormatError as exc:
        return str(exc)
    return None
