"""Global image retrieval without downloaded weights: VLAD over RootSIFT.

The vocabulary is a k-means codebook trained on the map's own descriptors (faiss, seeded).
A VLAD vector sums, per visual word, the residuals of the descriptors assigned to it
(Jégou et al., "Aggregating local descriptors into a compact image representation", CVPR 2010),
then is normalised as in Arandjelović & Zisserman, "All about VLAD", CVPR 2013:
intra-normalisation (L2 per word), the signed power law ``sign(v)·|v|^α`` with α = 0.5
(Jégou et al., "Aggregating local image descriptors into compact codes", TPAMI 2012), and a
final L2 normalisation. Images are compared by
the dot product (cosine similarity) in a faiss ``IndexFlatIP``.

Large maps search a subspace: :func:`subspace_basis` gives an orthonormal basis (D, d) of the
top-d singular subspace of the map's vectors (uncentred PCA, no whitening), and
:class:`GlobalIndex` with ``basis`` compares ``basisᵀ q`` with the map's coordinates. For a map
of at most d images the subspace holds every map vector and the scores are exact; beyond, the
part of a vector outside the top-d subspace is dropped (Jégou et al., TPAMI 2012, Sec. 4: PCA
to a few hundred dimensions keeps VLAD's retrieval quality). The map store decides when
(:mod:`planarloc.map.codec`, ``projected``).

Not done (on purpose): PCA-whitening. It must be learned from the map, whose few hundred
images cannot estimate a covariance in k·D = 8192 dimensions beyond M − 1 components, and we
have no held-out place-recognition set here to show a gain; NetVLAD (the paper's choice) needs
weights we cannot download. hloc pair files can be used instead via :func:`retrieve_from_pairs`.
"""

from __future__ import annotations

import functools
import logging
import struct
from collections.abc import Mapping, Sequence

import faiss
import numpy as np
import scipy.linalg

from planarloc.geometry.validation import InputError, check_array

logger = logging.getLogger(__name__)

DEFAULT_NUM_WORDS = 64
DEFAULT_POWER = 0.5
DEFAULT_TOP_N = 5
KMEANS_ITERATIONS = 20
MAX_TRAIN_PER_WORD = 256  # faiss' own default subsampling cap, applied here with our seeded RNG

_MAGIC = b"PLVLAD01"
_HEADER = struct.Struct("<8sII")  # magic, k, D


def _check_descriptors(name: str, value: object, dim: int | None = None) -> np.ndarray:
    d = check_array(name, value, (None, dim), dtype=np.float32)
    return d


class VladVocabulary:
    """k visual words (k-means centroids) of dimension D, for :func:`vlad_descriptor`.

    Attributes:
        centroids: (k, D) float32, read-only.
    """

    def __init__(self, centroids: object) -> None:
        c = check_array("centroids", centroids, (None, None), dtype=np.float32)
        if c.shape[0] < 1 or c.shape[1] < 1:
            raise InputError(f"centroids: expected shape (k >= 1, D >= 1), got {c.shape}")
        c = c.copy()
        c.setflags(write=False)
        self.centroids = c
        self._half_sq_norms = 0.5 * np.einsum("ij,ij->i", c, c)

    @property
    def k(self) -> int:
        return int(self.centroids.shape[0])

    @property
    def dim(self) -> int:
        """Descriptor dimension D (the VLAD vector has k·D entries)."""
        return int(self.centroids.shape[1])

    def __repr__(self) -> str:
        return f"VladVocabulary(k={self.k}, D={self.dim})"

    @classmethod
    def train(
        cls,
        descriptor_sets: Sequence[np.ndarray],
        k: int = DEFAULT_NUM_WORDS,
        seed: int = 0,
        niter: int = KMEANS_ITERATIONS,
    ) -> VladVocabulary:
        """Train the codebook by k-means on the pooled descriptors of the map images.

        Args:
            descriptor_sets: one (N_i, D) float array per map image (all with the same D).
            k: number of visual words.
            seed: seeds the subsampling (at most 256·k descriptors, drawn uniformly) and the
                k-means initialisation; the same inputs and seed give identical centroids.
            niter: k-means iterations.

        Raises:
            InputError: no descriptors, mixed dimensions, fewer descriptors than ``k``.
        """
        if int(k) < 1:
            raise InputError(f"k: expected >= 1 visual words, got {k}")
        k = int(k)
        sets = [np.asarray(s) for s in descriptor_sets]
        sets = [s for s in sets if s.size]
        if not sets:
            raise InputError(
                "descriptor_sets: no descriptors to train a vocabulary on; hint: extract map features first"
            )
        dim = sets[0].shape[1] if sets[0].ndim == 2 else None
        data = [_check_descriptors(f"descriptor_sets[{i}]", s, dim) for i, s in enumerate(sets)]
        x = np.concatenate(data)
        if len(x) < k:
            raise InputError(
                f"descriptor_sets: {len(x)} descriptors cannot train k = {k} words; "
                "hint: lower k or add map images"
            )
        rng = np.random.default_rng(seed)
        cap = MAX_TRAIN_PER_WORD * k
        if len(x) > cap:
            x = x[np.sort(rng.choice(len(x), size=cap, replace=False))]
        if len(x) < 39 * k:
            logger.warning(
                "training %d visual words on only %d descriptors; the vocabulary may be poor", k, len(x)
            )
        km = faiss.Kmeans(
            x.shape[1],
            k,
            niter=int(niter),
            seed=int(rng.integers(0, 2**31 - 1)),
            verbose=False,
            min_points_per_centroid=1,  # we warn ourselves instead of faiss printing to stderr
            max_points_per_centroid=MAX_TRAIN_PER_WORD,
        )
        km.train(np.ascontiguousarray(x, dtype=np.float32))
        logger.debug("trained %d visual words on %d descriptors", k, len(x))
        return cls(km.centroids)

    def assign(self, descriptors: object) -> np.ndarray:
        """Nearest word (L2) of each descriptor: (N, D) -> (N,) int64."""
        x = _check_descriptors("descriptors", descriptors, self.dim)
        if len(x) == 0:
            return np.zeros(0, dtype=np.int64)
        # argmin ‖x − c‖² = argmax (x·c − ‖c‖²/2)
        return np.argmax(x @ self.centroids.T - self._half_sq_norms, axis=1)

    def to_bytes(self) -> bytes:
        """Serialise: 8-byte magic ``PLVLAD01``, uint32 k, uint32 D (little endian), then the
        k·D float32 little-endian centroids, row-major."""
        return _HEADER.pack(_MAGIC, self.k, self.dim) + self.centroids.astype("<f4").tobytes()

    @classmethod
    def from_bytes(cls, data: bytes) -> VladVocabulary:
        """Inverse of :meth:`to_bytes`.

        Raises:
            InputError: wrong magic or length (not a planarloc VLAD vocabulary, or truncated).
        """
        data = bytes(data)
        if len(data) < _HEADER.size or data[:8] != _MAGIC:
            raise InputError(
                f"vocabulary bytes: missing the {_MAGIC!r} header; "
                "hint: the map was built by another tool or version"
            )
        _, k, dim = _HEADER.unpack_from(data)
        expected = _HEADER.size + 4 * k * dim
        if len(data) != expected:
            raise InputError(
                f"vocabulary bytes: expected {expected} bytes for k={k}, D={dim}, "
                f"got {len(data)} (truncated?)"
            )
        c = np.frombuffer(data, dtype="<f4", offset=_HEADER.size).reshape(k, dim).astype(np.float32)
        return cls(c)


@functools.cache
def _blas_controller():
    """The process's ``threadpoolctl`` controller (found once: inspecting the loaded libraries
    takes ~0.1 ms, a limit through it ~5 µs)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


def _one_blas_thread():
    """Context in which BLAS runs on one thread.

    One image's VLAD products are small: OpenBLAS' threads spin waiting for a busy core and cost
    more than they share (0.73 ms with one thread against 49 ms with two, 2 cores at load 12;
    benchmarks/map_scale.py: retrieval 9.3 ms per query with one thread, 123 ms with two)."""
    return _blas_controller().limit(limits=1, user_api="blas")


def vlad_descriptor(vocab: VladVocabulary, descriptors: object, power: float = DEFAULT_POWER) -> np.ndarray:
    """VLAD vector of one image.

    Args:
        vocab: visual words (k, D).
        descriptors: (N, D) local descriptors of the image (RootSIFT).
        power: exponent α of the signed power law; 1 disables it.

    Returns:
        (k·D,) float32 with unit L2 norm (all zeros when the image has no descriptors).

    References:
        Jégou et al., CVPR 2010 (VLAD); Arandjelović & Zisserman, CVPR 2013
        (intra-normalisation); Jégou et al., TPAMI 2012 (power law).
    """
    if not 0.0 < power <= 1.0:
        raise InputError(f"power: expected 0 < power <= 1, got {power}")
    x = _check_descriptors("descriptors", descriptors, vocab.dim)
    k, dim = vocab.k, vocab.dim
    if len(x) == 0:
        return np.zeros(k * dim, dtype=np.float32)
    with _one_blas_thread():
        words = vocab.assign(x)
        one_hot = np.zeros((len(x), k), dtype=np.float32)
        one_hot[np.arange(len(x)), words] = 1.0
        counts = one_hot.sum(axis=0)
        v = one_hot.T @ x - counts[:, None] * vocab.centroids  # (k, D) sums of residuals
    norms = np.linalg.norm(v, axis=1, keepdims=True)
    v = np.divide(v, norms, out=np.zeros_like(v), where=norms > 0)  # intra-normalisation
    if power != 1.0:
        v = np.sign(v) * np.abs(v) ** power
    v = v.ravel()
    n = np.linalg.norm(v)
    return (v / n).astype(np.float32) if n > 0 else v.astype(np.float32)


def _orthonormal(y: np.ndarray) -> np.ndarray:
    """Orthonormal columns spanning ``y``'s (numerically non-null) range: CholeskyQR2 (Fukaya et
    al. 2014: two Cholesky-QR passes; LAPACK's Householder QR of a tall 8192 x 522 matrix costs
    10x more), through the Gram matrix' eigenvectors when ``y`` is rank deficient."""
    for _ in range(2):
        g = y.T.astype(np.float64) @ y.astype(np.float64)
        try:
            r = scipy.linalg.cholesky(g, lower=False)
            y = scipy.linalg.solve_triangular(r, y.T.astype(np.float64), trans="T", lower=False).T.astype(
                np.float32
            )
        except np.linalg.LinAlgError:
            w, v = np.linalg.eigh(g)
            keep = w > w[-1] * 1e-10
            y = y @ (v[:, keep] / np.sqrt(w[keep])).astype(np.float32)
    return y


def subspace_basis(
    vectors: object, dim: int, seed: int = 0, max_rows: int = 4096, power_iterations: int = 2
) -> np.ndarray:
    """Orthonormal basis (D, d) of the top-``dim`` right singular subspace of (M, D) vectors.

    Args:
        vectors: (M, D) float32, e.g. the VLAD vectors of a map's images.
        dim: d, the subspace dimension (clipped to min(M, D)).
        seed: seeds the row sample and the random test matrix.
        max_rows: at most this many rows (a uniform sample) estimate the subspace.
        power_iterations: subspace iterations of the randomized range finder.

    Returns:
        (D, d) float32 with orthonormal columns, in order of decreasing singular value (fewer
        than d when the vectors span fewer dimensions).

    References:
        Halko, Martinsson & Tropp, "Finding structure with randomness", SIAM Review 2011,
        Alg. 4.4 (randomized subspace iteration) and Alg. 5.1 (direct SVD), applied to Xᵀ;
        10 extra test vectors (their Sec. 4.2). Exact (up to rounding) when M ≤ d.
    """
    x = check_array("vectors", vectors, (None, None), dtype=np.float32)
    if x.shape[0] < 1 or x.shape[1] < 1 or int(dim) < 1:
        raise InputError(f"vectors: expected shape (M >= 1, D >= 1) and dim >= 1, got {x.shape} and {dim}")
    rng = np.random.default_rng(seed)
    if len(x) > max_rows:
        x = x[np.sort(rng.choice(len(x), size=max_rows, replace=False))]
    d = min(int(dim), *x.shape)
    if len(x) <= d + 10:  # few rows: the exact thin SVD is cheap
        _, sv, vt = np.linalg.svd(x, full_matrices=False)
        d = min(d, int(np.sum(sv > sv[0] * 1e-6)))  # without the directions x does not span
        return np.ascontiguousarray(vt[:d].T, dtype=np.float32)
    q = _orthonormal(
        x.T @ rng.standard_normal((len(x), d + 10), dtype=np.float32)
    )  # (D, d + 10): range of Xᵀ
    for _ in range(power_iterations):
        q = _orthonormal(x.T @ _orthonormal(x @ q))
    b = x @ q
    u, _, _ = np.linalg.svd(b.T @ b)  # (d + 10)²: the left singular vectors of qᵀ Xᵀ
    return np.ascontiguousarray((q @ u[:, :d]), dtype=np.float32)


class GlobalIndex:
    """Exact cosine-similarity search over global descriptors (faiss ``IndexFlatIP``).

    Args:
        descriptors: (M, D) float32 global descriptors of the map images, unit L2 norm
            (e.g. from :func:`vlad_descriptor`); row ``i`` is map image ``i``. With ``basis``:
            (M, d) coordinates of those descriptors in the basis.
        basis: optional (D, d) orthonormal basis (:func:`subspace_basis`); queries are projected
            on it (``basisᵀ q``) before the search.
    """

    def __init__(self, descriptors: object, basis: object | None = None) -> None:
        d = check_array("descriptors", descriptors, (None, None), dtype=np.float32)
        if d.shape[0] < 1 or d.shape[1] < 1:
            raise InputError(f"descriptors: expected shape (M >= 1, D >= 1), got {d.shape}")
        self._basis = (
            None if basis is None else check_array("basis", basis, (None, d.shape[1]), dtype=np.float32)
        )
        self._index = faiss.IndexFlatIP(d.shape[1])
        self._index.add(d)

    def __len__(self) -> int:
        return int(self._index.ntotal)

    @property
    def dim(self) -> int:
        """The dimension of the query descriptors (D; the basis' rows when projected)."""
        return int(self._index.d if self._basis is None else self._basis.shape[0])

    def search(self, query_desc: object, top_n: int = DEFAULT_TOP_N) -> tuple[np.ndarray, np.ndarray]:
        """The ``top_n`` most similar map images.

        Args:
            query_desc: (D,) one query or (Q, D) a batch.
            top_n: neighbours per query (clipped to the index size).

        Returns:
            ``(indices, scores)``: (n,) int64 and (n,) float32 for a (D,) query, (Q, n) for a
            batch, with n = min(top_n, M); best first, scores are dot products.
        """
        if int(top_n) < 1:
            raise InputError(f"top_n: expected >= 1, got {top_n}")
        q = check_array("query_desc", query_desc, dtype=np.float32)
        given_shape = q.shape
        single = q.ndim == 1
        if single:
            q = q[None]
        if q.ndim != 2 or q.shape[1] != self.dim:
            raise InputError(
                f"query_desc: expected shape ({self.dim},) or (Q, {self.dim}), got {given_shape}"
            )
        n = min(int(top_n), len(self))
        if self._basis is not None:
            q = q @ self._basis
        scores, indices = self._index.search(np.ascontiguousarray(q), n)
        indices = indices.astype(np.int64)
        return (indices[0], scores[0]) if single else (indices, scores)


def retrieve_from_pairs(
    pairs: Mapping[str, Sequence[str]], query_name: str, top_n: int = DEFAULT_TOP_N
) -> list[str]:
    """The first ``top_n`` database names listed for ``query_name`` in an hloc pairs mapping.

    Args:
        pairs: ``{query_name: [db_name, ...]}`` in file order (hloc writes retrieval pairs best
            first); parsing the file is done by the io layer.
        query_name: the query image name as written in the pairs file.
        top_n: number of names to return (fewer if the file lists fewer); duplicates are
            dropped, keeping the first occurrence.

    Raises:
        InputError: the query has no entry (with the closest hint we can give).
    """
    if int(top_n) < 1:
        raise InputError(f"top_n: expected >= 1, got {top_n}")
    if query_name not in pairs:
        raise InputError(
            f"pairs: no retrieval pairs for query {query_name!r} ({len(pairs)} queries listed); "
            "hint: names must match the pairs file exactly, including sub-directories"
        )
    out: list[str] = []
    for name in pairs[query_name]:
        if name not in out:
            out.append(name)
            if len(out) == int(top_n):
                break
    return out
