"""Writing a map (:class:`~planarloc.map.store.MapDatabase`, which mixes this in): images with their
features and their records, global descriptors and their projection basis, named blobs. Every write
is one transaction of the writable database that holds the writer lock (see :mod:`planarloc.map.store`)."""

from __future__ import annotations

import hashlib
import logging
import sqlite3
from collections.abc import Mapping, Sequence
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING

import numpy as np

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError, check_array
from planarloc.map.codec import (
    KLT_MIN_FEATURES,
    PROJECT_ABOVE,
    PROJECTED_DIM,
    DescriptorBasis,
    camera_key,
    check_features,
    decode_descriptor_basis,
    encode_basis,
    encode_descriptor_basis,
    encode_descriptors,
    encode_global,
    encode_keypoints,
    fit_descriptor_basis,
    pose_columns,
    record_digest,
)
from planarloc.map.posed_image import PosedImage
from planarloc.map.schema import (
    BLOB_SHA_PREFIX,
    DESCRIPTOR_BASIS_BLOB,
    GLOBAL_BASIS_BLOB,
    IMAGE_COLUMNS,
    MapCorruptError,
    row_error,
)
from planarloc.map.store_state import MapState

logger = logging.getLogger("planarloc.map.store")  # the store's logger, as before the split


class MapWriting(MapState):
    """The writing methods of :class:`~planarloc.map.store.MapDatabase` (its connection, caches and
    transactions)."""

    if TYPE_CHECKING:  # MapDatabase's own helpers these methods call; for the type checker only

        def _require_writable(self) -> None: ...
        def _transaction(self) -> AbstractContextManager[sqlite3.Connection]: ...
        def _find_id(self, name: str) -> int | None: ...
        def get_posed_image(self, key: str | int) -> PosedImage: ...
        def global_basis(self) -> np.ndarray | None: ...
        def get_blob(self, key: str) -> bytes | None: ...

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
        if cam_id is None:
            raise sqlite3.DatabaseError(f"cameras: no row id for {key}")
        pending[key] = cam_id
        return int(cam_id)

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
        if (
            basis is None
            and self._storage == "compact"
            and self._encoding == "auto"
            and n >= KLT_MIN_FEATURES
            and bool(desc.min() >= 0)
        ):
            basis = new_basis = fit_descriptor_basis(desc)  # the map's first image with enough features
        encoding, desc_blob = encode_descriptors(desc, self._encoding, self._storage, basis)
        kp_blob = encode_keypoints(kp, scales, self._kp_layout)
        pose7 = pose_columns(posed.cam_from_world)
        digest = record_digest(
            posed.name, camera_key(posed.camera), pose7, n, kp_blob, dim, encoding, desc_blob
        )
        pending: dict = {}
        with self._transaction() as conn:
            if new_basis is not None and encoding == "klt":
                self._put_blob(conn, DESCRIPTOR_BASIS_BLOB, encode_descriptor_basis(new_basis))
            cam_id = self._camera_id(conn, posed.camera, pending)
            image_id = conn.execute(
                f"INSERT INTO images ({IMAGE_COLUMNS}) "
                "VALUES (NULL, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
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
        if image_id is None:
            raise sqlite3.DatabaseError(f"images: no row id for {posed.name!r}")
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
        row = (
            self._db.execute(
                "SELECT i.path, s.content_sha256 FROM images i "
                "LEFT JOIN image_sources s ON s.image_id = i.id WHERE i.name = ?",
                (name,),
            ).fetchone()
            if self._has_sources()
            else self._db.execute("SELECT path, NULL FROM images WHERE name = ?", (name,)).fetchone()
        )
        return None if row is None else (row[0], row[1])

    def _has_sources(self) -> bool:
        if self._sources is None:
            self._sources = (
                self._db.execute(
                    "SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'image_sources'"
                ).fetchone()
                is not None
            )
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
            "ON d.image_id = k.image_id WHERE k.image_id = ?",
            (image_id,),
        ).fetchone()
        digest = record_digest(name, camera_key(posed.camera), pose7, num, kp_blob, dim, encoding, desc_blob)
        pending: dict = {}
        with self._transaction() as conn:
            cam_id = self._camera_id(conn, posed.camera, pending)
            conn.execute(
                "UPDATE images SET camera_id = ?, qw = ?, qx = ?, qy = ?, qz = ?, tx = ?, ty = ?, tz = ?, "
                "path = ?, timestamp = ?, depth_path = ?, depth_scale = ? WHERE id = ?",
                (
                    cam_id,
                    *pose7,
                    str(posed.path),
                    None if posed.timestamp is None else float(posed.timestamp),
                    None if posed.depth_path is None else str(posed.depth_path),
                    float(posed.depth_scale),
                    image_id,
                ),
            )
            old_sha = conn.execute(
                "SELECT content_sha256 FROM image_sources WHERE image_id = ?", (image_id,)
            ).fetchone()
            conn.execute(
                "INSERT OR REPLACE INTO image_sources (image_id, content_sha256, record_sha256) "
                "VALUES (?, ?, ?)",
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
            dim = (
                basis.shape[0]
                if basis is not None
                else self._db.execute("SELECT dim FROM global_descriptors LIMIT 1").fetchone()[0]
            )
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
                conn.execute(
                    "INSERT OR REPLACE INTO meta (key, value) VALUES ('global_encoding', ?)", (encoding,)
                )
            conn.executemany(
                "INSERT OR REPLACE INTO global_descriptors (image_id, dim, data) VALUES (?, ?, ?)", rows
            )
            conn.executemany(
                "UPDATE image_sources SET global_sha256 = ? WHERE image_id = ?",
                [(hashlib.sha256(r[2]).hexdigest(), r[0]) for r in rows],
            )
        self._global_encoding = encoding

    @staticmethod
    def _store_basis(conn: sqlite3.Connection, basis: np.ndarray | None) -> None:
        """Write (or remove) the projection basis blob inside the caller's transaction."""
        if basis is None:
            conn.execute("DELETE FROM blobs WHERE key = ?", (GLOBAL_BASIS_BLOB,))
            conn.execute("DELETE FROM meta WHERE key = ?", (BLOB_SHA_PREFIX + GLOBAL_BASIS_BLOB,))
            return
        MapWriting._put_blob(conn, GLOBAL_BASIS_BLOB, encode_basis(basis))

    def put_blob(self, key: str, data: bytes) -> None:
        """Store (replace) a named binary blob, e.g. a retrieval vocabulary or index."""
        with self._transaction() as conn:
            self._put_blob(conn, str(key), bytes(data))

    @staticmethod
    def _put_blob(conn: sqlite3.Connection, key: str, data: bytes) -> None:
        """Write a blob and its checksum inside the caller's transaction."""
        conn.execute("INSERT OR REPLACE INTO blobs (key, data) VALUES (?, ?)", (key, data))
        conn.execute(
            "INSERT OR REPLACE INTO meta (key, value) VALUES (?, ?)",
            (BLOB_SHA_PREFIX + key, hashlib.sha256(data).hexdigest()),
        )
