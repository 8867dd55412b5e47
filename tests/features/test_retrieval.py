"""VLAD retrieval on generated places, vocabulary serialisation, index search, hloc pairs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from textured_images import textured_image

from planarloc.features.extract import FeatureConfig, extract_features
from planarloc.features.retrieval import GlobalIndex, VladVocabulary, retrieve_from_pairs, vlad_descriptor
from planarloc.geometry.validation import InputError


def perturbed(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A revisit of the place: random perspective warp (corners moved up to 10 %), gain, offset, noise."""
    h, w = img.shape
    src = np.float32([[0, 0], [w, 0], [w, h], [0, h]])
    dst = (src + rng.uniform(-0.10, 0.10, (4, 2)) * [w, h]).astype(np.float32)
    out = cv2.warpPerspective(
        img, cv2.getPerspectiveTransform(src, dst), (w, h), borderMode=cv2.BORDER_REFLECT
    )
    out = out.astype(float) * rng.uniform(0.7, 1.3) + rng.uniform(-25, 25) + rng.normal(0.0, 4.0, out.shape)
    return np.clip(out, 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def places():
    rng = np.random.default_rng(0)
    cfg = FeatureConfig(max_features=400)
    maps = [textured_image(rng, 200, 260) for _ in range(16)]
    queries = [perturbed(m, rng) for m in maps]
    return [extract_features(m, cfg).descriptors for m in maps], [
        extract_features(q, cfg).descriptors for q in queries
    ]


def test_retrieval_finds_the_source_place(places):
    map_desc, query_desc = places
    vocab = VladVocabulary.train(map_desc, k=32, seed=0)
    index = GlobalIndex(np.stack([vlad_descriptor(vocab, d) for d in map_desc]))
    assert len(index) == 16 and index.dim == 32 * 128
    indices, scores = index.search(np.stack([vlad_descriptor(vocab, d) for d in query_desc]), top_n=5)
    assert indices.shape == scores.shape == (16, 5)
    assert np.mean(indices[:, 0] == np.arange(16)) >= 0.9
    assert np.all(np.diff(scores, axis=1) <= 1e-6)  # best first
    one_idx, one_scores = index.search(vlad_descriptor(vocab, query_desc[3]), top_n=2)
    assert one_idx.shape == (2,) and one_idx[0] == indices[3, 0]


def test_vocabulary_is_deterministic_and_round_trips(places):
    map_desc, _ = places
    a = VladVocabulary.train(map_desc[:6], k=16, seed=7)
    b = VladVocabulary.train(map_desc[:6], k=16, seed=7)
    c = VladVocabulary.train(map_desc[:6], k=16, seed=8)
    assert a.to_bytes() == b.to_bytes()
    assert a.to_bytes() != c.to_bytes()
    assert a.centroids.shape == (16, 128) and a.k == 16 and a.dim == 128
    back = VladVocabulary.from_bytes(a.to_bytes())
    assert np.array_equal(back.centroids, a.centroids)
    assert np.array_equal(vlad_descriptor(back, map_desc[0]), vlad_descriptor(a, map_desc[0]))
    with pytest.raises(InputError, match="truncated"):
        VladVocabulary.from_bytes(a.to_bytes()[:-4])
    with pytest.raises(InputError, match="header"):
        VladVocabulary.from_bytes(b"NOTVLAD!" + a.to_bytes()[8:])


def test_vlad_descriptor_properties():
    rng = np.random.default_rng(1)
    centroids = np.abs(rng.standard_normal((4, 8))).astype(np.float32)
    vocab = VladVocabulary(centroids)
    x = np.abs(rng.standard_normal((50, 8))).astype(np.float32)
    v = vlad_descriptor(vocab, x)
    assert v.shape == (32,) and v.dtype == np.float32
    assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-6)
    assert np.allclose(vlad_descriptor(vocab, x[::-1]), v, atol=1e-6)  # order-free
    # Intra-normalisation: with power = 1 every non-empty word block has the same norm.
    v1 = vlad_descriptor(vocab, x, power=1.0).reshape(4, 8)
    norms = np.linalg.norm(v1, axis=1)
    used = np.bincount(vocab.assign(x), minlength=4) > 0
    assert np.allclose(norms[used], norms[used][0]) and np.all(norms[~used] == 0)
    # Signed square root of the intra-normalised blocks.
    assert np.allclose(np.sign(v) * v**2 / np.sum(v**2), v1.ravel() / np.sum(np.abs(v1)), atol=1e-5)
    assert np.all(vlad_descriptor(vocab, np.zeros((0, 8), np.float32)) == 0)
    with pytest.raises(InputError, match=r"\(N, 8\)"):
        vlad_descriptor(vocab, np.zeros((5, 9), np.float32))
    with pytest.raises(InputError):
        vlad_descriptor(vocab, x, power=0.0)


def test_training_errors():
    with pytest.raises(InputError, match="no descriptors"):
        VladVocabulary.train([np.zeros((0, 128), np.float32)])
    with pytest.raises(InputError, match="cannot train"):
        VladVocabulary.train([np.ones((10, 128), np.float32)], k=64)
    with pytest.raises(InputError):
        VladVocabulary.train([np.ones((100, 128), np.float32), np.ones((100, 64), np.float32)], k=4)


def test_global_index_search_edge_cases():
    rng = np.random.default_rng(2)
    d = rng.standard_normal((3, 6)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    index = GlobalIndex(d)
    idx, scores = index.search(d[1], top_n=10)  # clipped to the index size
    assert idx.shape == (3,) and idx[0] == 1 and scores[0] == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(InputError, match=r"\(6,\)"):
        index.search(np.zeros(5, np.float32))
    with pytest.raises(InputError):
        index.search(d[0], top_n=0)
    with pytest.raises(InputError):
        GlobalIndex(np.zeros((0, 6), np.float32))


def test_retrieve_from_pairs():
    pairs = {"q/1.png": ["db/5.png", "db/2.png", "db/5.png", "db/9.png"], "q/2.png": ["db/1.png"]}
    assert retrieve_from_pairs(pairs, "q/1.png", top_n=2) == ["db/5.png", "db/2.png"]
    assert retrieve_from_pairs(pairs, "q/1.png", top_n=5) == ["db/5.png", "db/2.png", "db/9.png"]
    assert retrieve_from_pairs(pairs, "q/2.png") == ["db/1.png"]
    with pytest.raises(InputError, match="q/3.png"):
        retrieve_from_pairs(pairs, "q/3.png")


def test_subspace_basis_matches_the_svd_and_is_exact_for_small_maps() -> None:
    from planarloc.features.retrieval import subspace_basis

    rng = np.random.default_rng(5)
    # 600 vectors in 256-D: a 12-D signal plus noise; the top-12 subspace is the SVD's
    x = rng.normal(size=(600, 12)) @ rng.normal(size=(12, 256)) + 0.05 * rng.normal(size=(600, 256))
    x = x.astype(np.float32)
    basis = subspace_basis(x, 12, max_rows=400)  # estimated from a sample of 400 rows
    np.testing.assert_allclose(basis.T @ basis, np.eye(12), atol=1e-5)
    vt = np.linalg.svd(x.astype(np.float64), full_matrices=False)[2][:12]
    cosines = np.linalg.svd(vt @ basis, compute_uv=False)  # principal angles between the subspaces
    assert cosines.min() > 0.999
    # at most d vectors: the basis spans them all, so dot products with any query are unchanged
    few = x[:9]
    b = subspace_basis(few, 12)
    assert b.shape == (256, 9)
    q = rng.normal(size=(5, 256)).astype(np.float32)
    np.testing.assert_allclose((q @ b) @ (few @ b).T, q @ few.T, rtol=1e-4, atol=1e-3)
    idx, _ = GlobalIndex(few @ b, basis=b).search(q, 3)
    np.testing.assert_array_equal(idx, np.argsort(-(q @ few.T), axis=1)[:, :3])
    with pytest.raises(InputError, match="basis"):
        GlobalIndex(few @ b, basis=b[:, :4])
