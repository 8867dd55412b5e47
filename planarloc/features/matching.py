"""Descriptor matching: mutual nearest neighbours + ratio test against the first far neighbour.

Descriptors are L2-normalised (RootSIFT), so the squared L2 distance is ``2 − 2·s`` with
``s`` the dot product, and all nearest-neighbour questions are answered from the similarity
matrix ``S = D_q · D_rᵀ`` computed by one BLAS matrix product per block of query rows.

Why numpy and not faiss: both compute the same float32 GEMM, but faiss needs two exhaustive
searches (query→ref top-k, ref→query top-1 for the mutual check) and ships an older OpenBLAS.
Measured on the 2-core development machine (faiss-cpu 1.15.1, numpy 2.4 / OpenBLAS 0.3.31,
4000×4000 RootSIFT, interleaved runs on a loaded machine): this matcher 270–300 ms, of which
the GEMM alone 185–200 ms; ``faiss.knn`` k=2 + reverse k=1: 490–510 ms, k=16: 600 ms. Unloaded,
the GEMM is ≈ 37 ms (≈ 110 GFLOP/s), which bounds any exact float32 matcher on that machine.
Why numpy's passes over each similarity block and not one compiled pass per row: a numba kernel
that takes the row maximum, the column maxima and the FGINN neighbour in one pass (the block
stays in cache) was 1.6–2.8× slower per query than these SIMD reductions on KITTI RootSIFT and
XFeat maps (same matches; its loops do not vectorise), so it was not kept.

Ratio test: Lowe's test compares the nearest neighbour with the second nearest. With a
tilt-augmented map (:mod:`planarloc.features.tilt`) the same scene point is usually detected in
several tilts, so the second nearest neighbour is often a copy of the first and the plain test
rejects good matches (measured on a KITTI frame pair: the tilted pool kept 280 matches where the
plain features kept 337). We therefore use the *first geometrically inconsistent nearest
neighbour* (FGINN rule of Mishkin, Matas & Perdoch, "MODS: Fast and robust method for two-view
matching", CVIU 2015): the second neighbour is the best reference feature at least
``fginn_radius`` pixels away from the first one. With it the tilted pool kept 363 matches (plain
features: 340); on plain features FGINN and Lowe agree within 1 % of the matches.
``fginn_radius=0`` gives Lowe's test exactly.

Feature types (:mod:`planarloc.features.registry`): ``rootsift`` and ``xfeat`` use this
descriptor matcher (XFeat's own matcher is mutual nearest neighbours, XFeat paper Sec. 3.3;
the ratio test is kept: on learned descriptors too it removes the ambiguous matches of repeated
structure). ``aliked-lightglue`` and ``xfeat-lighterglue`` match a query with their LightGlue
(:func:`match_query_to_refs` with that ``kind``, :func:`planarloc.features.learned.lightglue_matches`).
Matches between two map images (local structure, frame checks) use the descriptor matcher for
every type.
"""

from __future__ import annotations

import logging
import threading
import weakref
from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from planarloc.features.extract import Features
from planarloc.features.registry import DEFAULT_FEATURE_TYPE, feature_type
from planarloc.geometry.validation import InputError

logger = logging.getLogger(__name__)

DEFAULT_RATIO = 0.8
"""Lowe's ratio on L2 distances (Lowe, IJCV 2004, Sec. 7.1)."""

DEFAULT_FGINN_RADIUS = 10.0
"""Pixels (reference image) within which a neighbour counts as a copy of the first one."""

_BLOCK_ELEMENTS = 1 << 23  # similarity block of at most 8M floats (32 MB), whatever the pool size

# The similarity block is reused across calls (per thread): a fresh 32 MB array is mapped and
# page-faulted on every call, which cost as much as the GEMM itself (4000 x 4000 XFeat
# descriptors, 2 cores: 43 ms per call with a fresh block against 29 ms reused). It is kept: 32 MB.
_block = threading.local()


def _similarity_buffer(elements: int) -> np.ndarray:
    buf = getattr(_block, "buf", None)
    if buf is None or buf.size < elements:
        buf = np.empty(max(elements, 1 << 20), dtype=np.float32)
        _block.buf = buf
    return buf


# Neighbour lists of reference keypoints, per Features object and radius: a map image is matched
# against many queries, so the KD-tree pass is done once.
_near_cache: weakref.WeakKeyDictionary[Features, dict[float, tuple[np.ndarray, np.ndarray]]] = (
    weakref.WeakKeyDictionary()
)


# Descriptors of read-only Features already validated: a map image's features are decoded once
# (read-only arrays, :func:`planarloc.map.codec.decode_features`) and matched against every query
# and, in local structure, against the other retrieved map images, so their norm check ran once per
# pair: 1,700 checks for 38 KITTI queries, 5 ms of a query's 220 (XFeat, 4,000 keypoints).
_validated: weakref.WeakKeyDictionary[Features, np.ndarray] = weakref.WeakKeyDictionary()


def _immutable(a: np.ndarray) -> bool:
    """Nothing can write ``a`` without first making it writeable again: a read-only array that owns
    its data, a read-only view of one, or of ``bytes``."""
    base: object = a
    while isinstance(base, np.ndarray):
        if base.flags.writeable:
            return False
        if base.base is None:
            return True
        base = base.base
    return isinstance(base, bytes)


def _check_features(name: str, f: object) -> tuple[np.ndarray, np.ndarray]:
    if not isinstance(f, Features):
        raise InputError(f"{name}: expected a Features object, got {type(f).__name__}")
    cached = _validated.get(f)
    if cached is not None:
        return cached, f.keypoints
    d, kp = f.descriptors, f.keypoints
    if not isinstance(d, np.ndarray) or d.ndim != 2:
        raise InputError(f"{name}.descriptors: expected shape (N, D), got {np.shape(d)}")
    if not isinstance(kp, np.ndarray) or kp.ndim != 2 or kp.shape[1] != 2 or len(kp) != len(d):
        raise InputError(
            f"{name}.keypoints: expected shape ({len(d)}, 2) to match the descriptors, got {np.shape(kp)}"
        )
    d = np.ascontiguousarray(d, dtype=np.float32)
    if len(d):
        norms_sq = np.einsum("ij,ij->i", d, d)
        bad = np.abs(norms_sq - 1.0) > 1e-3
        if not np.all(np.isfinite(norms_sq)) or bad.any():
            i = int(np.argmax(bad | ~np.isfinite(norms_sq)))
            raise InputError(
                f"{name}.descriptors: rows must be L2-normalised, "
                f"row {i} has norm {np.sqrt(norms_sq[i]):.4g}; "
                "hint: build Features with planarloc.features.extract.extract_features"
            )
    if _immutable(f.descriptors) and _immutable(kp):
        _validated[f] = d
    return d, kp


def _near_lists(f: Features, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists ``nbr[ptr[j]:ptr[j+1]]`` of reference features within ``radius`` px of ``j`` (incl. j)."""
    per_radius = _near_cache.setdefault(f, {})
    if radius in per_radius:
        return per_radius[radius]
    n = len(f)
    self_idx = np.arange(n)
    if radius > 0 and n > 1:
        pairs = cKDTree(np.asarray(f.keypoints, dtype=np.float64)).query_pairs(radius, output_type="ndarray")
        src = np.concatenate([self_idx, pairs[:, 0], pairs[:, 1]])
        dst = np.concatenate([self_idx, pairs[:, 1], pairs[:, 0]])
        order = np.argsort(src, kind="stable")
        src, dst = src[order], dst[order]
    else:
        src, dst = self_idx, self_idx
    ptr = np.searchsorted(src, np.arange(n + 1))
    per_radius[radius] = (ptr, dst)
    return ptr, dst


def _match_checked(
    dq: np.ndarray, r: Features, dr: np.ndarray, ratio: float | None, mutual: bool, fginn_radius: float
) -> np.ndarray:
    n, m = len(dq), len(dr)
    if n == 0 or m == 0:
        return np.zeros((0, 2), dtype=np.int64)
    j1 = np.empty(n, dtype=np.int64)
    s1 = np.empty(n, dtype=np.float32)
    s2 = np.full(n, -np.inf, dtype=np.float32)
    colmax = np.full(m, -np.inf, dtype=np.float32) if mutual else None
    if ratio is not None:
        ptr, nbr = _near_lists(r, fginn_radius)
    rows_per_block = max(1, min(n, _BLOCK_ELEMENTS // m))
    buf = _similarity_buffer(rows_per_block * m)[: rows_per_block * m].reshape(rows_per_block, m)
    drT = dr.T
    for start in range(0, n, rows_per_block):
        stop = min(n, start + rows_per_block)
        S = buf[: stop - start]
        np.matmul(dq[start:stop], drT, out=S)  # (b, m) cosine similarities
        if colmax is not None:
            np.maximum(colmax, S.max(axis=0), out=colmax)
        rows = np.arange(stop - start)
        best = S.argmax(axis=1)
        j1[start:stop] = best
        s1[start:stop] = S[rows, best]
        if ratio is not None and m > 1:
            # Mask the first neighbour and every reference feature within fginn_radius of it,
            # then the row maximum is the first geometrically inconsistent neighbour.
            counts = ptr[best + 1] - ptr[best]
            offsets = np.repeat(ptr[best] - (np.cumsum(counts) - counts), counts) + np.arange(counts.sum())
            S[np.repeat(rows, counts), nbr[offsets]] = -np.inf
            s2[start:stop] = S.max(axis=1)
    keep = np.ones(n, dtype=bool)
    if colmax is not None:
        keep &= s1 >= colmax[j1]  # the query is (one of) the best for its reference feature
    if ratio is not None:
        # L2 distances of unit vectors: d = sqrt(2 - 2 s); no second neighbour -> d2 = inf.
        d1 = np.sqrt(np.maximum(2.0 - 2.0 * s1.astype(np.float64), 0.0))
        d2 = np.sqrt(np.maximum(2.0 - 2.0 * s2.astype(np.float64), 0.0))
        keep &= d1 < ratio * d2
    qi = np.flatnonzero(keep)
    return np.stack([qi, j1[qi]], axis=1).astype(np.int64, copy=False)


def _check_params(ratio: float | None, fginn_radius: float) -> None:
    if ratio is not None and not 0.0 < ratio <= 1.0:
        raise InputError(f"ratio: expected 0 < ratio <= 1 or None (no ratio test), got {ratio}")
    if not fginn_radius >= 0.0:
        raise InputError(f"fginn_radius: expected >= 0 pixels, got {fginn_radius}")


def match_features(
    q: Features,
    r: Features,
    ratio: float | None = DEFAULT_RATIO,
    mutual: bool = True,
    fginn_radius: float = DEFAULT_FGINN_RADIUS,
) -> np.ndarray:
    """Match query features to reference features.

    A pair ``(i, j)`` is kept when ``j`` is the nearest reference descriptor of query ``i``,
    ``i`` is the nearest query descriptor of ``j`` (``mutual``), and
    ``‖d_i − d_j‖ < ratio · ‖d_i − d_k‖`` where ``k`` is the nearest reference descriptor whose
    keypoint lies at least ``fginn_radius`` pixels from keypoint ``j`` (FGINN; 0 = Lowe's second
    nearest neighbour).

    Args:
        q: query features, N descriptors (N, D) with unit L2 norm.
        r: reference features, M descriptors (M, D), same D; keypoints (M, 2) in pixels.
        ratio: ratio-test threshold on L2 distances; ``None`` disables the test.
        mutual: keep only mutual nearest neighbours (ties count as mutual).
        fginn_radius: pixels in the reference image, see above.

    Returns:
        (K, 2) int64 array of ``(query_idx, ref_idx)``, sorted by query index; each query index
        appears at most once. Empty (0, 2) when either side has no features.

    Raises:
        InputError: descriptor dimensions differ, descriptors not L2-normalised, bad parameters.

    Example:
        >>> d = np.eye(3, 128, dtype=np.float32)
        >>> kp = np.array([[0, 0], [50, 0], [100, 0]], dtype=np.float32)
        >>> ref = Features(kp, d, np.ones(3, np.float32))
        >>> query = Features(kp[::-1].copy(), d[::-1].copy(), np.ones(3, np.float32))
        >>> match_features(query, ref).tolist()   # query i <-> reference 2 - i
        [[0, 2], [1, 1], [2, 0]]
    """
    _check_params(ratio, fginn_radius)
    dq, _ = _check_features("q", q)
    dr, _ = _check_features("r", r)
    if len(dq) and len(dr) and dq.shape[1] != dr.shape[1]:
        raise InputError(
            f"descriptor dimensions differ: query D = {dq.shape[1]}, reference D = {dr.shape[1]}; "
            "hint: extract query and map features with the same FeatureConfig"
        )
    return _match_checked(dq, r, dr, ratio, mutual, fginn_radius)


def match_query_to_refs(
    q: Features,
    refs: Sequence[Features],
    ratio: float | None = DEFAULT_RATIO,
    mutual: bool = True,
    fginn_radius: float = DEFAULT_FGINN_RADIUS,
    kind: str = DEFAULT_FEATURE_TYPE,
) -> list[np.ndarray]:
    """Match one query against several references (e.g. the retrieved map images).

    The query is validated once. Query indices refer to the same query keypoints in every
    returned array, so a query keypoint matched in several references can be linked.

    Args:
        q: query features (N descriptors, D dims).
        refs: K reference Features, each with D-dimensional descriptors.
        ratio, mutual, fginn_radius: as in :func:`match_features` (descriptor matcher).
        kind: the feature type of query and references (the map's ``FeatureConfig.kind``); its
            matcher (:data:`planarloc.features.registry.FEATURE_TYPES`) is used: LightGlue for
            ``aliked-lightglue``, LighterGlue for ``xfeat-lighterglue`` (then ``ratio``,
            ``mutual`` and ``fginn_radius`` do not apply).

    Returns:
        K arrays of shape (M_k, 2), int64 ``(query_idx, ref_idx)``.
    """
    _check_params(ratio, fginn_radius)
    matcher = feature_type(kind, "kind").matcher
    dq, _ = _check_features("q", q)
    out = []
    for k, r in enumerate(refs):
        dr, _ = _check_features(f"refs[{k}]", r)
        if len(dq) and len(dr) and dq.shape[1] != dr.shape[1]:
            raise InputError(
                f"descriptor dimensions differ: query D = {dq.shape[1]}, refs[{k}] D = {dr.shape[1]}; "
                "hint: extract query and map features with the same FeatureConfig"
            )
        if matcher == "lightglue":
            from planarloc.features import learned  # torch: only for the learned types

            out.append(learned.lightglue_matches(q.keypoints, dq, r.keypoints, dr, kind))
        else:
            out.append(_match_checked(dq, r, dr, ratio, mutual, fginn_radius))
    logger.debug("matched %d query features to %d references: %s", len(dq), len(out), [len(m) for m in out])
    return out
