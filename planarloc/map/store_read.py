"""Reading a map (:class:`~planarloc.map.store.MapDatabase`, which mixes this in): cameras, posed
images and poses, local features (cached, checksums verified), global descriptors and named blobs."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.map.codec import (
    DescriptorBasis,
    damaged_poses,
    decode_basis,
    decode_features,
    decode_global,
    global_row_problem,
    poses_from_columns,
    record_digest,
)
from planarloc.map.errors import MapKeyError
from planarloc.map.posed_image import PosedImage
from planarloc.map.schema import (
    BLOB_SHA_PREFIX,
    GLOBAL_BASIS_BLOB,
    IMAGE_COLUMNS,
    MapCorruptError,
    row_error,
)
from planarloc.map.store_state import MapState


class MapReading(MapState):
    """The reading methods of :class:`~planarloc.map.store.MapDatabase` (its connection and caches)."""

    if TYPE_CHECKING:  # MapDatabase's own helpers these methods call; for the type checker only

        def _has_sources(self) -> bool: ...
        def descriptor_basis(self) -> DescriptorBasis | None: ...
        def get_meta(self, key: str) -> str | None: ...

    def _camera(self, camera_id: int) -> Camera:
        if camera_id not in self._cameras:
            row = self._db.execute(
                "SELECT model, width, height, params FROM cameras WHERE id = ?", (camera_id,)
            ).fetchone()
            if row is None:
                raise MapCorruptError(
                    f"{self.path}: camera row {camera_id} is missing; run `planarloc map check`"
                )
            try:
                self._cameras[camera_id] = Camera(row[0], row[1], row[2], tuple(json.loads(row[3])))
            except (ValueError, TypeError) as exc:
                raise MapCorruptError(
                    f"{self.path}: camera row {camera_id} is damaged ({exc}); "
                    f"run `planarloc map check {self.path}`"
                ) from None
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
            row = self._db.execute(f"SELECT {IMAGE_COLUMNS} FROM images WHERE id = ?", (int(key),)).fetchone()
        else:
            row = self._db.execute(
                f"SELECT {IMAGE_COLUMNS} FROM images WHERE name = ?", (str(key),)
            ).fetchone()
        if row is None:
            raise MapKeyError(f"image {key!r} is not in map {self.path}")
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
        rows = self._db.execute(
            "SELECT id, name, qw, qx, qy, qz, tx, ty, tz FROM images ORDER BY id"
        ).fetchall()
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
        columns = [r[first : first + 7] for r in rows]
        bad = damaged_poses(columns)
        if bad.any():
            r = rows[int(np.argmax(bad))]
            raise row_error(
                self.path,
                f"{r[1]!r} (row id {r[0]})",
                "damaged pose (not a unit quaternion and finite translation)",
            )
        return poses_from_columns(columns)

    def _features_from_blobs(
        self, label: str, num: int, kp_blob: bytes, dim: int, encoding: str, desc_blob: bytes
    ) -> Features:
        try:
            return decode_features(
                num,
                kp_blob,
                dim,
                encoding,
                desc_blob,
                self._kp_layout,
                self.descriptor_basis() if encoding == "klt" else None,
            )
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
                raise MapKeyError(f"image id {image_id} is not in map {self.path}")
            raise row_error(
                self.path, f"{name[0]!r} (row id {image_id})", "its keypoints or descriptors are missing"
            )
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

    def _verify_record(self, image_id: int, blobs: Sequence[Any]) -> None:
        """Compare an image row with its stored checksum (maps without checksums: no-op); ``blobs``:
        the SQLite row ``(num, keypoint blob, dim, encoding, descriptor blob)``."""
        if not self._has_sources():
            return
        row = self._db.execute(
            "SELECT i.name, c.model, c.width, c.height, c.params, i.qw, i.qx, i.qy, i.qz, i.tx, i.ty, i.tz, "
            "s.record_sha256 FROM images i JOIN image_sources s ON s.image_id = i.id "
            "LEFT JOIN cameras c ON c.id = i.camera_id WHERE i.id = ?",
            (image_id,),
        ).fetchone()
        if row is None:
            return
        num, kp_blob, dim, encoding, desc_blob = blobs
        if record_digest(row[0], row[1:5], row[5:12], num, kp_blob, dim, encoding, desc_blob) != row[12]:
            raise row_error(
                self.path,
                f"{row[0]!r} (row id {image_id})",
                "checksum mismatch (name, camera, pose or features changed on disk)",
            )

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
        sums = (
            dict(
                self._db.execute(
                    "SELECT image_id, global_sha256 FROM image_sources WHERE global_sha256 IS NOT NULL"
                )
            )
            if self._has_sources()
            else {}
        )
        for image_id, _dim, data in rows:
            if image_id in sums and (
                not isinstance(data, bytes) or hashlib.sha256(data).hexdigest() != sums[image_id]
            ):
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
            raise row_error(
                self.path, f"blob {GLOBAL_BASIS_BLOB!r}", "missing (global descriptors are projected)"
            )
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
