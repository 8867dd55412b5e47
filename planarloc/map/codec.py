"""How a map stores its rows as bytes: descriptor encodings, keypoint blobs, global descriptors,
poses, checksums.

A map has one **storage layout**, fixed when it is created (``meta.storage``; maps written before
layouts existed have none and are ``"full"``):

=============  ==========================================  ====================================
layout         keypoints                                   global descriptors
=============  ==========================================  ====================================
``full``       float32 (x, y, scale): 12 bytes each        float32 (D,)
``compact``    fixed point ``fixed``: about 4.7 bytes each 4 bits a value, or projected (below)
=============  ==========================================  ====================================

Descriptor encodings are stored per row (``descriptors.encoding``), so rows of any encoding can
be read from any map. Descriptors are always returned as float32 L2-normalised rows (zero rows
stay zero); ``encoding="auto"`` picks by layout and sign:

- ``klt`` (``compact``, non-negative descriptors such as RootSIFT): transform coding. The map's
  first image with at least :data:`KLT_MIN_FEATURES` descriptors fixes a basis — the mean and the
  leading principal axes of its descriptors, as many as hold 95 % of their variance (64 of 128 on
  KITTI) — stored once (:func:`encode_descriptor_basis`, blob
  :data:`planarloc.map.schema.DESCRIPTOR_BASIS_BLOB`, float16). Each descriptor is stored as its
  coordinates along those axes, rounded to multiples of :data:`KLT_STEP` (int8), column by
  column, Huffman-coded (zlib, ``Z_HUFFMAN_ONLY``): about 24 bytes per RootSIFT descriptor on
  KITTI, and 95 % of the ratio-test matches unchanged (BENCHMARKS.md, "Compact maps"; Goyal,
  "Theoretical foundations of transform coding", IEEE SPM 2001: uniform quantisation of the
  Karhunen-Loève coefficients with one step size). Decoding rebuilds ``mean + basis · codes · step``,
  clips negative values (RootSIFT has none) and re-normalises. An image whose descriptors keep
  less than 90 % of their centred energy in the basis (unlike the first image's), or that would
  decode a zero row, is stored as ``uint4``.
- ``uint4`` (``compact``, before the map has a basis, or the fallback above): the image's values
  scaled by ``15 / max`` (max over the image), rounded to 4-bit codes, packed two per byte and
  Huffman-coded: about 49 bytes per RootSIFT descriptor; error per value at most
  ``0.5 / 15 · max`` before the rows are re-normalised (which cancels the scale).
- ``uint8`` (``full``, non-negative; 1 byte per value): the same with ``255 / max``; error per
  value at most ``0.5 / 255 · max`` (≤ 1e-3 for RootSIFT).
- ``float16`` (signed descriptors, either layout; 2 bytes per value): relative error ≤ 2⁻¹¹.
- ``float32``: exact.

Keypoints (``full``): float32 little-endian, the N (x, y) pairs followed by the N scales.
Keypoints (``compact``, ``fixed``): a 16-byte header ``<B b 2x f f f`` = (mode, k, ox, oy, s0),
then for mode 1 the N (x, y) pairs as uint16 ``round((v − o) · 2^k)`` and the N scales as uint8
codes ``round(16 · log2(scale / s0))``, Huffman-coded (about 4.7 bytes per keypoint on KITTI:
SIFT's scales crowd the finest octaves; the position error is at most
``2^-(k+1)`` px, with k ≥ 3 so ≤ 1/16 px, and 1/64 px for KITTI's 1241-px-wide images; scales
within 2.2 %, which nothing computes with); for mode 0 (an image wider than 8191 px, or scales
not positive or spanning more than 2^16) the float32 layout follows the header.

Global descriptors (``meta.global_encoding``; absent: ``float32``): ``float32`` rows of D values;
``int4``: a float32 scale then D 4-bit codes, two per byte (``v ≈ scale · (c − 8)``, scale =
``max|v| / 7``, error ≤ ``max|v| / 14``); ``projected`` (compact maps with more than
:data:`PROJECT_ABOVE` images): each row holds the float16 coordinates of the image's vector in an
orthonormal basis (D, d) of the map's vectors' top-d subspace, stored once as the blob
:data:`planarloc.map.schema.GLOBAL_BASIS_BLOB` (:func:`encode_basis`). A query's similarity to a
map image is then ``(basisᵀ q) · coordinates``: 20,000 images search in about 1 ms instead of
60 ms, in 41 MB instead of 655 MB (BENCHMARKS.md, "Building scale").

A stored image row is checksummed by :func:`record_digest` (name, camera, pose and both blobs),
which ``planarloc map check`` re-computes.
"""

from __future__ import annotations

import hashlib
import json
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import DTypeLike
from scipy.spatial.transform import Rotation

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera, CameraModel
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array
from planarloc.map.schema import MapCorruptError

STORAGE_LAYOUTS = ("compact", "full")
#: The layout of new maps: ``compact`` keeps the single-frame recall and the promises of ``full``
#: maps on both shared KITTI sequences (map every 2nd and 4th, RANSAC seeds 0-4) and in every
#: setting of benchmarks/trust.py at a fifth of the bytes (BENCHMARKS.md, "Compact maps", and
#: "Trust"); ``full`` stays available.
DEFAULT_STORAGE = "compact"
DESCRIPTOR_ENCODINGS = ("auto", "uint4", "uint8", "float16", "float32")
KEYPOINT_LAYOUTS = {"full": "float32", "compact": "fixed"}
GLOBAL_ENCODINGS = ("float32", "int4", "projected")
#: Transform coding (``klt``): the quantisation step of the coordinates (descriptors have unit
#: norm), the share of the basis image's variance its axes hold, the fewest descriptors that fit
#: a basis, and the least share of an image's own energy the basis must hold to be used for it.
KLT_STEP = 0.025
KLT_VARIANCE = 0.95
KLT_MIN_FEATURES = 256
KLT_MIN_ENERGY = 0.90
#: Compact maps with more global descriptors than this store them projected (PROJECTED_DIM-D).
PROJECT_ABOVE = 2048
PROJECTED_DIM = 512
_DTYPE: dict[str, DTypeLike] = {"uint8": np.uint8, "float16": "<f2", "float32": "<f4"}
_ITEM_SIZE = {"uint8": 1, "float16": 2, "float32": 4}
_UINT4_LEVELS = 15
_KP_HEADER = struct.Struct(
    "<Bb2xfff"
)  # mode (0 float32, 1 fixed point), k, origin x, origin y, smallest scale
_SCALE_STEPS = 16.0  # log-scale codes per octave
_KP_MIN_SHIFT = 3  # fixed point only while the step 2^-k is at most 1/8 px
_BASIS_HEADER = struct.Struct("<8sII")  # magic, D, d
_BASIS_MAGIC = b"PLBASIS1"
_KLT_HEADER = struct.Struct("<8sIIf")  # magic, D, K, step
_KLT_MAGIC = b"PLKLT001"


def check_storage(storage: object) -> str:
    """``storage`` as one of :data:`STORAGE_LAYOUTS` (InputError otherwise)."""
    if storage not in STORAGE_LAYOUTS:
        raise InputError(f"storage: expected one of {', '.join(STORAGE_LAYOUTS)}, got {storage!r}")
    return str(storage)


def camera_key(camera: Camera) -> tuple[str, int, int, str]:
    """The ``cameras`` row of a camera: ``(model, width, height, params JSON)``."""
    return CameraModel(camera.model).value, camera.width, camera.height, json.dumps(list(camera.params))


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


def record_digest(
    name: str,
    camera_row: Sequence[object],
    pose7: Sequence[float],
    num: int,
    kp_blob: bytes,
    dim: int,
    encoding: str,
    desc_blob: bytes,
) -> str:
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


# ---- local descriptors -----------------------------------------------------------------------
def _huffman(data: bytes) -> bytes:
    coder = zlib.compressobj(6, zlib.DEFLATED, 15, 9, zlib.Z_HUFFMAN_ONLY)  # no LZ: codes hardly repeat
    return coder.compress(data) + coder.flush()


def _inflate(blob: bytes, size: int, what: str) -> bytes:
    try:
        data = zlib.decompress(blob)
    except zlib.error as exc:
        raise MapCorruptError(f"{what} blob does not decompress ({exc})") from None
    if len(data) != size:
        raise MapCorruptError(f"{what} blob holds {len(data)} bytes, expected {size}")
    return data


def _scaled_codes(descriptors: np.ndarray, levels: int) -> np.ndarray:
    """Codes ``round(d · levels / max)`` (one scale per image; decoding re-normalises rows)."""
    top = float(descriptors.max(initial=0.0))
    scaled = np.multiply(descriptors, np.float32(levels / top if top > 0 else 0.0))
    scaled += 0.5  # values are >= 0: truncation after +0.5 rounds to nearest
    return scaled.astype(np.uint8)


def _pack_nibbles(codes: np.ndarray) -> bytes:
    flat = codes.reshape(-1)
    if len(flat) % 2:
        flat = np.append(flat, np.uint8(0))
    return ((flat[0::2] << 4) | flat[1::2]).astype(np.uint8).tobytes()


def _unpack_nibbles(packed: bytes, count: int) -> np.ndarray:
    p = np.frombuffer(packed, dtype=np.uint8)
    codes = np.empty(2 * len(p), dtype=np.uint8)
    codes[0::2] = p >> 4
    codes[1::2] = p & 0x0F
    return codes[:count]


def _normalised(d: np.ndarray) -> np.ndarray:
    norm = np.sqrt(np.einsum("ij,ij->i", d, d))
    inv = np.divide(1.0, norm, out=np.zeros_like(norm), where=norm > 0)
    d *= inv[:, None]
    return d


@dataclass(frozen=True)
class DescriptorBasis:
    """The transform of ``klt`` rows: ``mean`` (D,), orthonormal ``axes`` (D, K), ``step``."""

    mean: np.ndarray
    axes: np.ndarray
    step: float

    def codes(self, descriptors: np.ndarray) -> np.ndarray:
        """(N, K) int8 coordinates of (N, D) descriptors, in multiples of ``step``."""
        y = (descriptors - self.mean) @ self.axes
        return np.clip(np.rint(y / self.step), -127, 127).astype(np.int8)

    def rebuild(self, codes: np.ndarray) -> np.ndarray:
        """(N, D) float32 descriptors from codes: non-negative, L2-normalised rows."""
        d = (codes.astype(np.float32) * np.float32(self.step)) @ self.axes.T + self.mean
        np.maximum(d, 0.0, out=d)
        return _normalised(d.astype(np.float32))


def fit_descriptor_basis(
    descriptors: np.ndarray, variance: float = KLT_VARIANCE, step: float = KLT_STEP
) -> DescriptorBasis:
    """The basis of ``klt`` rows from one image's (N, D) descriptors: their mean and the fewest
    principal axes that hold ``variance`` of their variance, rounded as stored (float16)."""
    x = descriptors.astype(np.float64)
    mean = x.mean(axis=0)
    w, v = np.linalg.eigh(np.cov((x - mean).T))
    w, v = w[::-1], v[:, ::-1]
    k = int(np.searchsorted(np.cumsum(w) / max(w.sum(), 1e-300), variance) + 1)
    k = min(max(k, 1), x.shape[1])
    return decode_descriptor_basis(encode_descriptor_basis(DescriptorBasis(mean, v[:, :k], step)))


def encode_descriptor_basis(basis: DescriptorBasis) -> bytes:
    """``PLKLT001``, uint32 D, uint32 K, float32 step, then the (D, K + 1) float16 matrix
    ``[mean | axes]``, row-major."""
    D, K = basis.axes.shape
    data = np.column_stack([basis.mean, basis.axes]).astype("<f2")
    return _KLT_HEADER.pack(_KLT_MAGIC, D, K, float(basis.step)) + data.tobytes()


def decode_descriptor_basis(data: bytes) -> DescriptorBasis:
    """Inverse of :func:`encode_descriptor_basis`.

    Raises:
        MapCorruptError: wrong magic, length or values.
    """
    if len(data) < _KLT_HEADER.size or data[:8] != _KLT_MAGIC:
        raise MapCorruptError("descriptor basis: missing its PLKLT001 header")
    _, D, K, step = _KLT_HEADER.unpack_from(data)
    if len(data) != _KLT_HEADER.size + 2 * D * (K + 1) or not 0 < K <= D or not step > 0:
        raise MapCorruptError(f"descriptor basis: {len(data)} bytes for D = {D}, K = {K}, step = {step}")
    m = np.frombuffer(data, dtype="<f2", offset=_KLT_HEADER.size).reshape(D, K + 1).astype(np.float32)
    if not np.isfinite(m).all():
        raise MapCorruptError("descriptor basis: non-finite values")
    return DescriptorBasis(np.ascontiguousarray(m[:, 0]), np.ascontiguousarray(m[:, 1:]), float(step))


def _klt_blob(descriptors: np.ndarray, basis: DescriptorBasis) -> bytes | None:
    """The ``klt`` blob, or None when the basis does not suit these descriptors (see the module
    docstring)."""
    if descriptors.shape[1] != basis.axes.shape[0]:
        return None
    centred = descriptors - basis.mean
    energy = float(np.einsum("ij,ij->", centred, centred))
    inside = centred @ basis.axes
    if energy > 0 and float(np.einsum("ij,ij->", inside, inside)) < KLT_MIN_ENERGY * energy:
        return None
    codes = basis.codes(descriptors)
    if len(codes) and not (basis.rebuild(codes).max(axis=1) > 0).all():
        return None
    return _huffman(np.ascontiguousarray(codes.T).tobytes())  # column by column: one axis' values together


def encode_descriptors(
    descriptors: np.ndarray, encoding: str, storage: str = "full", basis: DescriptorBasis | None = None
) -> tuple[str, bytes]:
    """Encode (N, D) float32 descriptors.

    Args:
        descriptors: (N, D) float32 rows.
        encoding: one of :data:`DESCRIPTOR_ENCODINGS`; ``"auto"`` picks ``klt`` (``storage=
            "compact"`` with a ``basis`` that suits them), else ``uint4`` (compact) or ``uint8``
            (``"full"``) for non-negative descriptors, else ``float16``.
        storage: the map's layout (only used by ``"auto"``).
        basis: the map's descriptor basis (:func:`fit_descriptor_basis`), if it has one.

    Returns:
        (the encoding used, the blob).
    """
    nonneg = descriptors.size == 0 or bool(descriptors.min() >= 0)
    if encoding == "auto":
        if storage == "compact" and nonneg and basis is not None:
            blob = _klt_blob(descriptors, basis)
            if blob is not None:
                return "klt", blob
        encoding = ("uint4" if storage == "compact" else "uint8") if nonneg else "float16"
    if encoding in ("uint4", "uint8") and not nonneg:
        raise InputError(
            f"descriptors: the {encoding} encoding needs non-negative descriptors (e.g. RootSIFT); "
            "create the map with descriptor_encoding='float16' or 'auto'"
        )
    if encoding == "uint4":
        codes = _scaled_codes(descriptors, _UINT4_LEVELS)
        if len(codes) and bool(((codes.max(axis=1) == 0) & (descriptors.max(axis=1) > 0)).any()):
            encoding = "uint8"  # a non-zero row would decode as zero: keep more levels for this image
        else:
            return "uint4", _huffman(_pack_nibbles(codes))
    if encoding == "uint8":
        # One scale per image (not per row: 2.5x faster, and rows are L2-normalised so every
        # row keeps at least 255 / sqrt(D) levels); decoding re-normalises, so it is not stored.
        return "uint8", _scaled_codes(descriptors, 255).tobytes()
    if encoding == "float16":
        return "float16", descriptors.astype("<f2").tobytes()
    if encoding == "float32":
        return "float32", descriptors.astype("<f4").tobytes()
    raise InputError(
        f"descriptor encoding: expected one of {', '.join(DESCRIPTOR_ENCODINGS)}, got {encoding!r}"
    )


def decode_descriptors(
    blob: bytes, num: int, dim: int, encoding: str, basis: DescriptorBasis | None = None
) -> np.ndarray:
    """Decode a descriptor blob to (num, dim) float32 L2-normalised rows (zero rows stay zero);
    ``klt`` rows need the map's ``basis``."""
    if encoding not in ("klt", "uint4") and encoding not in _ITEM_SIZE:
        raise MapCorruptError(
            f"descriptor encoding {encoding!r} is not one of klt, uint4, uint8, float16, float32"
        )
    if num < 0 or dim < 0:
        raise MapCorruptError(f"descriptor row has {num} x {dim} values")
    if encoding == "klt":
        if basis is None or basis.axes.shape[0] != dim:
            raise MapCorruptError(
                f"a klt descriptor row needs the map's {dim}-D descriptor basis, "
                f"{'missing' if basis is None else 'of another dimension'}"
            )
        k = basis.axes.shape[1]
        codes = np.frombuffer(_inflate(blob, num * k, "klt descriptor"), dtype=np.int8).reshape(k, num)
        return basis.rebuild(codes.T)
    if encoding == "uint4":
        packed = _inflate(blob, (num * dim + 1) // 2, "uint4 descriptor")
        return _normalised(_unpack_nibbles(packed, num * dim).reshape(num, dim).astype(np.float32))
    if len(blob) != num * dim * _ITEM_SIZE[encoding]:
        raise MapCorruptError(
            f"descriptor blob is {len(blob)} bytes, expected {num * dim * _ITEM_SIZE[encoding]} "
            f"for {num} x {dim} {encoding} values"
        )
    return _normalised(np.frombuffer(blob, dtype=_DTYPE[encoding]).reshape(num, dim).astype(np.float32))


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


# ---- keypoints --------------------------------------------------------------------------------
def _fixed_point(keypoints: np.ndarray, scales: np.ndarray) -> bytes | None:
    """The ``fixed`` payload (header + uint16 pairs + Huffman-coded log-scales), None if it
    cannot hold them."""
    origin = np.floor(keypoints.min(axis=0)) if len(keypoints) else np.zeros(2, dtype=np.float32)
    extent = float((keypoints - origin).max(initial=0.0))
    k = min(16, int(np.floor(np.log2(65535.0 / extent)))) if extent > 0 else 16
    if k < _KP_MIN_SHIFT or not (np.isfinite(scales).all() and (scales > 0).all()):
        return None
    s0 = float(scales.min(initial=1.0))
    c = np.rint(_SCALE_STEPS * np.log2(scales / np.float32(s0))) if len(scales) else np.zeros(0)
    if c.max(initial=0) > 255:
        return None
    q = np.rint((keypoints - origin) * np.float32(2.0**k)).astype("<u2")
    return (
        _KP_HEADER.pack(1, k, float(origin[0]), float(origin[1]), s0)
        + q.tobytes()
        + _huffman(c.astype(np.uint8).tobytes())
    )


def encode_keypoints(keypoints: np.ndarray, scales: np.ndarray, layout: str = "float32") -> bytes:
    """The keypoint blob of (N, 2) keypoints and (N,) scales in ``layout`` (``float32`` or
    ``fixed``, see the module docstring)."""
    raw = np.concatenate([keypoints.reshape(-1), scales]).astype("<f4").tobytes()
    if layout == "float32":
        return raw
    if layout != "fixed":
        raise InputError(f"keypoint layout: expected float32 or fixed, got {layout!r}")
    fixed = _fixed_point(keypoints.astype(np.float32), scales.astype(np.float32))
    return fixed if fixed is not None else _KP_HEADER.pack(0, 0, 0.0, 0.0, 0.0) + raw


def decode_keypoints(blob: bytes, num: int, layout: str = "float32") -> tuple[np.ndarray, np.ndarray]:
    """(num, 2) keypoints and (num,) scales (float32) from a keypoint blob.

    Raises:
        MapCorruptError: a blob of the wrong length or header for ``num`` keypoints.
    """
    if num < 0:
        raise MapCorruptError(f"keypoint row has {num} keypoints")
    if layout == "fixed":
        if len(blob) < _KP_HEADER.size:
            raise MapCorruptError(f"keypoint blob is {len(blob)} bytes, shorter than its header")
        mode, k, ox, oy, s0 = _KP_HEADER.unpack_from(blob)
        body = blob[_KP_HEADER.size :]
        if mode == 1:
            if len(body) < 4 * num or not 0 <= k <= 16:
                raise MapCorruptError(
                    f"fixed-point keypoint blob is {len(blob)} bytes (k = {k}), shorter than "
                    f"the {_KP_HEADER.size + 4 * num} of {num} keypoints' positions"
                )
            q = np.frombuffer(body, dtype="<u2", count=2 * num).reshape(num, 2).astype(np.float32)
            keypoints = q * np.float32(2.0**-k) + np.array([ox, oy], dtype=np.float32)
            codes = np.frombuffer(_inflate(body[4 * num :], num, "keypoint scale"), dtype=np.uint8).astype(
                np.float32
            )
            return keypoints, (np.float32(s0) * np.exp2(codes / np.float32(_SCALE_STEPS))).astype(np.float32)
        if mode != 0:
            raise MapCorruptError(f"keypoint blob has an unknown mode {mode}")
        blob = body
    elif layout != "float32":
        raise MapCorruptError(f"keypoint layout {layout!r} is not float32 or fixed")
    if len(blob) != 12 * num:
        raise MapCorruptError(f"keypoint blob is {len(blob)} bytes, expected {12 * num} for {num} keypoints")
    flat = np.frombuffer(blob, dtype="<f4")
    return flat[: 2 * num].reshape(num, 2).astype(np.float32), flat[2 * num :].astype(np.float32)


def decode_features(
    num: int,
    kp_blob: object,
    dim: int,
    encoding: str,
    desc_blob: object,
    keypoint_layout: str,
    basis: DescriptorBasis | None = None,
) -> Features:
    """Features (read-only float32 arrays) from a keypoint and a descriptor row; ``keypoint_layout``:
    the map's (:data:`KEYPOINT_LAYOUTS` of its storage), ``basis``: its descriptor basis, for ``klt`` rows.

    Raises:
        MapCorruptError: blobs of the wrong type or length, or non-finite values (what is wrong,
            without the row: the caller names it).
    """
    if not isinstance(kp_blob, bytes) or not isinstance(desc_blob, bytes):
        raise MapCorruptError("feature data is not a blob")
    keypoints, scales = decode_keypoints(kp_blob, num, keypoint_layout)
    descriptors = decode_descriptors(desc_blob, num, dim, encoding, basis)
    if not (np.isfinite(keypoints).all() and np.isfinite(scales).all() and np.isfinite(descriptors).all()):
        raise MapCorruptError("non-finite keypoints or descriptors")
    for a in (keypoints, scales, descriptors):
        a.setflags(write=False)
    return Features(keypoints, descriptors, scales)


# ---- global descriptors -----------------------------------------------------------------------
def encode_global(vectors: np.ndarray, encoding: str) -> list[bytes]:
    """One blob per row of (M, D) float32 vectors: ``float32``, ``int4`` (scale + 4-bit codes) or
    ``projected`` (the rows are coordinates, stored as float16)."""
    if encoding == "float32":
        return [v.astype("<f4").tobytes() for v in vectors]
    if encoding == "projected":
        return [v.astype("<f2").tobytes() for v in vectors]
    if encoding != "int4":
        raise InputError(
            f"global descriptor encoding: expected one of {', '.join(GLOBAL_ENCODINGS)}, got {encoding!r}"
        )
    top = np.abs(vectors).max(axis=1, initial=0.0) if vectors.size else np.zeros(len(vectors))
    scale = np.where(top > 0, top / 7.0, 1.0).astype("<f4")
    codes = (np.clip(np.rint(vectors / scale[:, None]), -7, 7) + 8).astype(np.uint8)
    return [s.tobytes() + _pack_nibbles(row) for s, row in zip(scale, codes)]


def global_row_problem(data: object, dim: object, encoding: str) -> str | None:
    """What is wrong with one stored global descriptor (its blob, its ``dim``), None if nothing."""
    if encoding not in GLOBAL_ENCODINGS:
        return f"global descriptor encoding {encoding!r} is not one of {', '.join(GLOBAL_ENCODINGS)}"
    if not isinstance(dim, int) or dim < 1:
        return f"global descriptor dimension {dim!r} is not a positive integer"
    size = {"float32": 4 * dim, "projected": 2 * dim, "int4": 4 + (dim + 1) // 2}[encoding]
    if not isinstance(data, bytes) or len(data) != size:
        got = f"{len(data)} bytes" if isinstance(data, bytes) else "not a blob"
        return f"global descriptor blob is {got}, expected {size} for {dim} {encoding} values"
    return None


def decode_global(blobs: Sequence[bytes], dim: int, encoding: str) -> np.ndarray:
    """(M, dim) float32 from stored global descriptor blobs (:func:`encode_global`) that passed
    :func:`global_row_problem`; the caller checks that the values are finite."""
    data = b"".join(blobs)
    if encoding == "int4":
        rows = np.frombuffer(data, dtype=np.uint8).reshape(len(blobs), 4 + (dim + 1) // 2)
        scale = rows[:, :4].copy().view("<f4").astype(np.float32)
        codes = _unpack_nibbles(rows[:, 4:].tobytes(), len(blobs) * 2 * ((dim + 1) // 2))
        codes = codes.reshape(len(blobs), -1)[:, :dim].astype(np.float32) - 8.0
        return codes * scale
    dtype = "<f4" if encoding == "float32" else "<f2"
    return np.frombuffer(data, dtype=dtype).reshape(len(blobs), dim).astype(np.float32)


def encode_basis(basis: np.ndarray) -> bytes:
    """A projection basis (D, d) as bytes: magic ``PLBASIS1``, uint32 D, uint32 d (little endian),
    then the D·d float32 values, row-major."""
    return _BASIS_HEADER.pack(_BASIS_MAGIC, *basis.shape) + basis.astype("<f4").tobytes()


def decode_basis(data: bytes) -> np.ndarray:
    """Inverse of :func:`encode_basis`: a (D, d) float32 array.

    Raises:
        MapCorruptError: wrong magic or length.
    """
    if len(data) < _BASIS_HEADER.size or data[:8] != _BASIS_MAGIC:
        raise MapCorruptError("global descriptor basis: missing its PLBASIS1 header")
    _, D, d = _BASIS_HEADER.unpack_from(data)
    if len(data) != _BASIS_HEADER.size + 4 * D * d:
        raise MapCorruptError(
            f"global descriptor basis: {len(data)} bytes, expected "
            f"{_BASIS_HEADER.size + 4 * D * d} for {D} x {d}"
        )
    basis = np.frombuffer(data, dtype="<f4", offset=_BASIS_HEADER.size).reshape(D, d).astype(np.float32)
    if not np.isfinite(basis).all():
        raise MapCorruptError("global descriptor basis: non-finite values")
    return basis
