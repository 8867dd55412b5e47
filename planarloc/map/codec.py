"""How a map stores its rows as bytes: descriptor encodings, keypoint blobs, poses, checksums.

Descriptor encodings (descriptors are always returned as float32, L2-normalised rows):

- ``uint8`` (default for non-negative descriptors such as RootSIFT; 1 byte per value): the
  image's descriptors are scaled by ``255 / max`` (max over the image) and rounded. Decoding
  re-normalises each row, which cancels the scale, so none is stored. The error per value is at
  most ``0.5 / 255 · max`` (≤ 1e-3 for RootSIFT, whose values rarely exceed 0.4) — far below
  descriptor distances; nearest neighbours of true matches are unchanged.
- ``float16`` (default if a row has negative values; 2 bytes per value): relative error ≤ 2⁻¹¹.
- ``float32``: exact.

Keypoints: float32 little-endian, the N (x, y) pairs followed by the N scales (12 bytes per
keypoint). A stored image row is checksummed by :func:`record_digest` (name, camera, pose and
both blobs), which ``planarloc map check`` re-computes.
"""

from __future__ import annotations

import hashlib
import json
import struct
from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array
from planarloc.map.schema import MapCorruptError

DESCRIPTOR_ENCODINGS = ("auto", "uint8", "float16", "float32")
_DTYPE = {"uint8": np.uint8, "float16": "<f2", "float32": "<f4"}
_ITEM_SIZE = {"uint8": 1, "float16": 2, "float32": 4}


def camera_key(camera: Camera) -> tuple[str, int, int, str]:
    """The ``cameras`` row of a camera: ``(model, width, height, params JSON)``."""
    return camera.model.value, camera.width, camera.height, json.dumps(list(camera.params))


def pose_columns(pose: Pose) -> list[float]:
    """The stored ``(qw, qx, qy, qz, tx, ty, tz)`` of a ``cam_from_world`` pose."""
    return [*map(float, pose.quat_wxyz), *map(float, pose.t)]


def poses_from_columns(rows: Sequence[Sequence[float]]) -> list[Pose]:
    """Poses from rows ``(qw, qx, qy, qz, tx, ty, tz)``, converting all quaternions at once."""
    if not rows:
        return []
    a = np.asarray(rows, dtype=float)
    R = Rotation.from_quat(a[:, [1, 2, 3, 0]]).as_matrix()
    return [Pose(Ri, ti) for Ri, ti in zip(R, a[:, 4:])]


def damaged_poses(rows: Sequence[Sequence[float]]) -> np.ndarray:
    """(N,) True where a stored pose is not a finite unit quaternion and translation."""
    vals = np.asarray(rows, dtype=float).reshape(-1, 7)
    norms = np.linalg.norm(vals[:, :4], axis=1)
    return ~np.isfinite(vals).all(axis=1) | (np.abs(norms - 1.0) > 1e-6)


def record_digest(name: str, camera_row: Sequence[object], pose7: Sequence[float], num: int,
                  kp_blob: bytes, dim: int, encoding: str, desc_blob: bytes) -> str:
    """SHA-256 (hex) of one stored image row: what ``planarloc map check`` re-computes.

    Args:
        name: image name.
        camera_row: ``(model, width, height, params JSON)`` of its camera row (:func:`camera_key`).
        pose7: ``(qw, qx, qy, qz, tx, ty, tz)`` as stored (float64).
        num, kp_blob, dim, encoding, desc_blob: the keypoint and descriptor rows.
    """
    h = hashlib.sha256()
    h.update(name.encode("utf-8") + b"\0")
    h.update(json.dumps([str(c) for c in camera_row]).encode() + b"\0")
    h.update(struct.pack("<7d", *(float(v) + 0.0 for v in pose7)))  # + 0.0: SQLite stores -0.0 as 0
    h.update(struct.pack("<qq", int(num), int(dim)) + encoding.encode() + b"\0")
    h.update(bytes(kp_blob))
    h.update(bytes(desc_blob))
    return h.hexdigest()


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


def check_features(features: Features, dim: int | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keypoints (N, 2), descriptors (N, D) and scales (N,) of features to store, checked
    (``dim``: the map's descriptor dimension, None while it has none)."""
    kp = check_array("features.keypoints", features.keypoints, (None, 2), dtype=np.float32)
    n = len(kp)
    desc = check_array("features.descriptors", features.descriptors, (n, None), dtype=np.float32)
    scales = check_array("features.scales", features.scales, (n,), dtype=np.float32)
    if desc.shape[1] == 0:
        raise InputError("features.descriptors: expected shape (N, D) with D >= 1, got D = 0")
    if dim is not None and desc.shape[1] != dim:
        raise InputError(f"features.descriptors: this map stores {dim}-D descriptors, got {desc.shape[1]}-D")
    return kp, desc, scales


def encode_keypoints(keypoints: np.ndarray, scales: np.ndarray) -> bytes:
    """The keypoint blob of (N, 2) keypoints and (N,) scales."""
    return np.concatenate([keypoints.reshape(-1), scales]).astype("<f4").tobytes()


def decode_features(num: int, kp_blob: object, dim: int, encoding: str, desc_blob: object) -> Features:
    """Features (read-only float32 arrays) from a keypoint and a descriptor row.

    Raises:
        MapCorruptError: blobs of the wrong type or length, or non-finite values (what is wrong,
            without the row: the caller names it).
    """
    if not isinstance(kp_blob, bytes) or not isinstance(desc_blob, bytes):
        raise MapCorruptError("feature data is not a blob")
    if num < 0 or len(kp_blob) != 12 * num:
        raise MapCorruptError(f"keypoint blob is {len(kp_blob)} bytes, expected {12 * max(num, 0)} "
                              f"for {num} keypoints")
    descriptors = decode_descriptors(desc_blob, num, dim, encoding)
    flat = np.frombuffer(kp_blob, dtype="<f4")
    keypoints = flat[: 2 * num].reshape(num, 2).astype(np.float32)
    scales = flat[2 * num :].astype(np.float32)
    if not (np.isfinite(keypoints).all() and np.isfinite(scales).all() and np.isfinite(descriptors).all()):
        raise MapCorruptError("non-finite keypoints or descriptors")
    for a in (keypoints, scales, descriptors):
        a.setflags(write=False)
    return Features(keypoints, descriptors, scales)
