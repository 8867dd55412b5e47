"""Storage layouts: compact codecs (bounds, sizes, fallbacks, damage) on generated and real SIFT
descriptors, projected global descriptors, and maps written before compact maps
(``data/map_v1.db.gz``) opening unchanged."""

from __future__ import annotations

import gzip
import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import numpy as np
import pytest
from test_store import CONFIG, make_features, make_posed, rootsift

from planarloc.features.extract import Features
from planarloc.features.retrieval import GlobalIndex
from planarloc.localize.localizer import Localizer
from planarloc.map import store_write
from planarloc.map.codec import (
    decode_descriptor_basis,
    decode_descriptors,
    decode_keypoints,
    encode_descriptor_basis,
    encode_descriptors,
    encode_keypoints,
    fit_descriptor_basis,
)
from planarloc.map.integrity import check_map
from planarloc.map.schema import MapCorruptError
from planarloc.map.store import MapDatabase

DATA = Path(__file__).parent / "data"


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(3)


# ---- local descriptors ------------------------------------------------------------------------------
def test_uint4_error_bound_and_size(rng: np.random.Generator) -> None:
    d = rootsift(rng, 501)  # odd N·D: the last byte holds one code
    used, blob = encode_descriptors(d, "auto", "compact")
    assert used == "uint4" and len(blob) < 64 * len(d)  # Huffman-coded nibbles: < 4 bits per value
    back = decode_descriptors(blob, 501, 128, "uint4")
    # codes are round(d * 15 / max): before re-normalisation each value is within 0.5 / 15 * max
    step = d.max() / 15
    codes_back = back * (np.linalg.norm(np.round(d / step) * step, axis=1, keepdims=True))
    assert np.abs(codes_back - d).max() <= 0.5 * step + 1e-6
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-5)


def test_uint4_falls_back_to_uint8_rather_than_zero_rows(rng: np.random.Generator) -> None:
    d = np.full((3, 2000), 1.0 / np.sqrt(2000), dtype=np.float32)
    d[0, 0] = 5.0  # the image maximum: every other value rounds to code 0 in 4 bits
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    used, blob = encode_descriptors(d, "auto", "compact")
    assert used == "uint8"
    assert (np.linalg.norm(decode_descriptors(blob, 3, 2000, used), axis=1) > 0.99).all()


def test_compact_signed_descriptors_are_float16(rng: np.random.Generator) -> None:
    d = rootsift(rng, 10) * rng.choice([-1.0, 1.0], size=(10, 128)).astype(np.float32)
    assert encode_descriptors(d, "auto", "compact")[0] == "float16"
    with pytest.raises(ValueError, match="non-negative"):
        encode_descriptors(d, "uint4", "compact")


def test_damaged_uint4_blobs_are_map_errors(rng: np.random.Generator) -> None:
    _, blob = encode_descriptors(rootsift(rng, 20), "uint4")
    with pytest.raises(MapCorruptError, match="decompress"):
        decode_descriptors(blob[:-5] + b"xxxxx", 20, 128, "uint4")
    with pytest.raises(MapCorruptError, match="holds 1280 bytes, expected 1344"):
        decode_descriptors(blob, 21, 128, "uint4")


# ---- keypoints ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("width, step", [(1241, 2**-5), (640, 2**-6), (8000, 2**-3)])
def test_fixed_keypoints_error_bound(rng: np.random.Generator, width: int, step: float) -> None:
    kp = np.column_stack([rng.uniform(0, width - 1, 400), rng.uniform(-0.4, 375, 400)]).astype(np.float32)
    scales = rng.uniform(1.6, 80.0, 400).astype(np.float32)
    blob = encode_keypoints(kp, scales, "fixed")
    assert 16 + 4 * 400 < len(blob) <= 16 + 5 * 400 + 64  # positions, then at most a byte a scale (Huffman)
    kp2, s2 = decode_keypoints(blob, 400, "fixed")
    assert np.abs(kp2 - kp).max() <= step / 2 + 1e-4  # 1e-4: float32 rounding of the inputs
    assert np.all(np.abs(s2 / scales - 1) <= 2 ** (1 / 32) - 1 + 1e-6)  # 16 log-steps per octave


def test_fixed_keeps_float32_when_it_cannot_hold_them(rng: np.random.Generator) -> None:
    for kp, scales in [
        (
            rng.uniform(0, 20000, (50, 2)).astype(np.float32),
            rng.uniform(1, 9, 50).astype(np.float32),
        ),  # too wide
        (
            rng.uniform(0, 600, (50, 2)).astype(np.float32),
            np.geomspace(1e-3, 1e3, 50).astype(np.float32),
        ),  # > 2^16
        (
            rng.uniform(0, 600, (50, 2)).astype(np.float32),
            np.linspace(-1, 9, 50).astype(np.float32),
        ),  # not > 0
    ]:
        blob = encode_keypoints(kp, scales, "fixed")
        assert len(blob) == 16 + 12 * 50
        kp2, s2 = decode_keypoints(blob, 50, "fixed")
        np.testing.assert_array_equal(kp2, kp)
        np.testing.assert_array_equal(s2, scales)
    empty = encode_keypoints(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), "fixed")
    assert [a.shape for a in decode_keypoints(empty, 0, "fixed")] == [(0, 2), (0,)]
    blob = encode_keypoints(kp[:10], np.ones(10, np.float32), "fixed")
    with pytest.raises(MapCorruptError, match="shorter than the 416 of 100 keypoints' positions"):
        decode_keypoints(blob, 100, "fixed")
    with pytest.raises(MapCorruptError, match="keypoint scale blob"):
        decode_keypoints(blob, 11, "fixed")  # the scale codes no longer hold 11 values


def test_fixed_keypoints_huffman_code_sift_like_scales(rng: np.random.Generator) -> None:
    # SIFT's scales crowd the finest octaves: the log-scale codes take well under a byte each
    kp = rng.uniform(0, 1200, (2000, 2)).astype(np.float32)
    scales = (1.6 * 2 ** rng.exponential(0.7, 2000)).astype(np.float32)
    blob = encode_keypoints(kp, scales, "fixed")
    assert len(blob) < 16 + 4 * 2000 + 0.75 * 2000
    _, s2 = decode_keypoints(blob, 2000, "fixed")
    assert np.all(np.abs(s2 / scales - 1) <= 2 ** (1 / 32) - 1 + 1e-6)


# ---- whole maps ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def sift_images() -> list[Features]:
    """Real RootSIFT of six KITTI-sized (1241 x 376) textured images: ~2,900 features each."""
    from textured_images import textured_image

    from planarloc.features.extract import FeatureConfig, extract_features

    rng = np.random.default_rng(1)
    return [extract_features(textured_image(rng, 376, 1241), FeatureConfig()) for _ in range(6)]


def test_transform_coding_of_real_sift(sift_images: list[Features]) -> None:
    basis = fit_descriptor_basis(sift_images[0].descriptors)
    assert basis.axes.shape[0] == 128 and 40 <= basis.axes.shape[1] <= 90  # 95 % of the variance (KITTI: 64)
    for f in sift_images[1:3]:
        used, blob = encode_descriptors(f.descriptors, "auto", "compact", basis)
        assert used == "klt" and len(blob) < 30 * len(f)  # KITTI: 24 bytes per descriptor
        back = decode_descriptors(blob, len(f), 128, "klt", basis)
        cos = np.einsum("ij,ij->i", back, f.descriptors)
        assert cos.mean() > 0.98 and cos.min() > 0.9 and (back >= 0).all()
        np.testing.assert_allclose(np.linalg.norm(back, axis=1), 1.0, atol=1e-5)
        # a descriptor's nearest neighbour among the decoded ones is mostly itself
        nearest = np.argmax(f.descriptors[:500] @ back.T, axis=1)
        assert np.mean(nearest == np.arange(500)) > 0.97
    # descriptors the basis does not describe (isotropic, unlike SIFT) keep the 4-bit codes
    assert encode_descriptors(rootsift(np.random.default_rng(0), 300), "auto", "compact", basis)[0] == "uint4"
    with pytest.raises(MapCorruptError, match="needs the map's 128-D descriptor basis, missing"):
        decode_descriptors(blob, len(f), 128, "klt")
    again = decode_descriptor_basis(encode_descriptor_basis(basis))
    assert np.array_equal(again.axes, basis.axes) and np.array_equal(again.mean, basis.mean)  # stored as used
    with pytest.raises(MapCorruptError, match="PLKLT001"):
        decode_descriptor_basis(b"nonsense")


def _store(path: Path, features: list[Features], storage: str) -> None:
    rng = np.random.default_rng(2)
    with MapDatabase.create(path, CONFIG, storage=storage) as db:
        ids = [db.add_image(make_posed(i), f) for i, f in enumerate(features)]
        g = rng.normal(size=(len(ids), 8192)).astype(np.float32)
        db.set_global_descriptors((ids, g / np.linalg.norm(g, axis=1, keepdims=True)))


def test_compact_map_is_under_100_kb_per_kitti_sized_image(
    tmp_path: Path, sift_images: list[Features]
) -> None:
    """~2,900 RootSIFT features per image (KITTI: 1,450 and 3,030) and an 8192-D VLAD vector."""
    sizes = {}
    for storage in ("compact", "full"):
        _store(tmp_path / f"{storage}.db", sift_images, storage)
        sizes[storage] = (tmp_path / f"{storage}.db").stat().st_size / len(sift_images)
        assert check_map(tmp_path / f"{storage}.db").ok
    with MapDatabase.open(tmp_path / "compact.db") as db:
        encodings = [r[0] for r in db._db.execute("SELECT encoding FROM descriptors ORDER BY image_id")]
        assert encodings == ["klt"] * len(sift_images) and db.descriptor_basis() is not None
        f = db.get_features(make_posed(3).name)
        assert np.einsum("ij,ij->i", f.descriptors, sift_images[3].descriptors).mean() > 0.98
    assert sizes["compact"] < 100_000 and sizes["full"] > 3.5 * sizes["compact"]


def test_projected_global_descriptors_search_like_the_full_vectors(
    tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(store_write, "PROJECT_ABOVE", 8)  # the writer projects
    monkeypatch.setattr(store_write, "PROJECTED_DIM", 6)
    basis_true = np.linalg.qr(rng.normal(size=(64, 5)))[0]  # the 12 vectors span 5 of the 64 dimensions
    vectors = (rng.normal(size=(12, 5)) @ basis_true.T).astype(np.float32)
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    path = tmp_path / "p.db"
    with MapDatabase.create(path, CONFIG, storage="compact") as db:
        ids = [db.add_image(make_posed(i), make_features(rng, 3)) for i in range(12)]
        db.set_global_descriptors((ids, vectors))
        assert db.get_meta("global_encoding") == "projected"
    assert check_map(path).ok
    queries = (rng.normal(size=(20, 64))).astype(np.float32)
    with MapDatabase.open(path) as db:
        got_ids, coords = db.get_global_descriptors()
        basis = db.global_basis()
    assert coords.shape == (12, 5) and basis.shape == (64, 5)  # rank 5 < PROJECTED_DIM: the exact span
    exact, projected = GlobalIndex(vectors), GlobalIndex(coords, basis=basis)
    (i1, s1), (i2, s2) = exact.search(queries, 4), projected.search(queries, 4)
    np.testing.assert_array_equal(i1, i2)
    np.testing.assert_allclose(s1, s2, atol=2e-3)  # float16 coordinates
    # vectors given later for some images are projected on the stored basis
    with MapDatabase.open(path, "a") as db:
        db.set_global_descriptors({ids[0]: vectors[1]})
        np.testing.assert_allclose(db.get_global_descriptors()[1][0], coords[1], atol=1e-3)
        with pytest.raises(ValueError, match="64-D vectors, got 5-D"):
            db.set_global_descriptors({ids[0]: coords[1]})
    with sqlite3.connect(path) as conn:  # a damaged basis is named by map check and by the reader
        conn.execute("UPDATE blobs SET data = substr(data, 1, 100) WHERE key = 'retrieval/global_basis'")
    assert any("retrieval/global_basis" in p for p in check_map(path).problems)
    with MapDatabase.open(path) as db, pytest.raises(MapCorruptError, match="global_basis"):
        db.global_basis()


def test_damaged_compact_rows_are_named(tmp_path: Path, sift_images: list[Features]) -> None:
    path = tmp_path / "c.db"
    _store(path, sift_images[:2], "compact")
    with sqlite3.connect(path) as conn:
        conn.execute("UPDATE global_descriptors SET data = substr(data, 1, 10) WHERE image_id = 2")
    assert any("global_descriptors row 2" in p and "4100" in p for p in check_map(path).problems)
    with MapDatabase.open(path) as db, pytest.raises(MapCorruptError, match="row id 2"):
        db.get_global_descriptors()
    with sqlite3.connect(path) as conn:  # klt rows without their basis cannot be read: named, not guessed
        conn.execute("UPDATE blobs SET data = substr(data, 1, 30) WHERE key = 'codec/descriptor_basis'")
    assert any("codec/descriptor_basis" in p for p in check_map(path).problems)
    with MapDatabase.open(path) as db, pytest.raises(MapCorruptError, match="descriptor_basis"):
        db.get_features(1)


# ---- maps written before compact maps ------------------------------------------------------------------
@pytest.fixture
def v1_map(tmp_path: Path) -> Path:
    path = tmp_path / "map_v1.db"
    with gzip.open(DATA / "map_v1.db.gz", "rb") as src, open(path, "wb") as dst:
        shutil.copyfileobj(src, dst)
    return path


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def test_new_maps_are_compact_unless_full_is_asked_for(tmp_path: Path) -> None:
    with MapDatabase.create(tmp_path / "default.db", CONFIG) as db:
        assert db.storage == "compact" and db.get_meta("storage") == "compact"
    with MapDatabase.create(tmp_path / "full.db", CONFIG, storage="full") as db:
        assert db.storage == "full"
    with MapDatabase.open(tmp_path / "default.db") as db:
        assert db.storage == "compact"


def test_map_written_before_compact_maps_reads_exactly_as_then(v1_map: Path) -> None:
    expected = json.loads((DATA / "map_v1.json").read_text())
    assert check_map(v1_map).ok
    with MapDatabase.open(v1_map) as db:
        assert db.storage == "full" and db.get_meta("storage") is None and db.global_basis() is None
        for name, rec in expected["images"].items():
            f = db.get_features(name)
            assert len(f) == rec["num"]
            assert {k: _digest(getattr(f, k)) for k in rec["sha256"]} == rec["sha256"]
        ids, g = db.get_global_descriptors()
        assert ids.tolist() == expected["global"]["ids"] and _digest(g) == expected["global"]["sha256"]
    loc = Localizer(v1_map)  # opens and retrieves as before: every map image finds itself first
    for name in expected["images"]:
        assert loc.retrieve(loc.db.get_features(name), top_n=1) == [name]


def test_appending_to_an_old_map_keeps_its_layout(v1_map: Path, rng: np.random.Generator) -> None:
    f = make_features(rng, 40)
    with MapDatabase.open(v1_map, "a") as db:
        db.add_image(make_posed(9), f)
    with MapDatabase.open(v1_map) as db:
        got = db.get_features(make_posed(9).name)
        np.testing.assert_array_equal(got.keypoints, f.keypoints)  # float32, as the map's other rows
        assert db._db.execute("SELECT encoding FROM descriptors WHERE image_id = 5").fetchone()[0] == "uint8"
    assert check_map(v1_map).ok
