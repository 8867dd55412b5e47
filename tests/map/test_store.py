"""MapDatabase: round trips, resumable and crash-safe builds, format errors, laziness, speed."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.features.extract import Features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.map.codec import decode_descriptors, encode_descriptors
from planarloc.map.posed_image import PosedImage
from planarloc.map.schema import SCHEMA_VERSION, MapFormatError
from planarloc.map.store import MapDatabase

CONFIG = {"extractor": "rootsift", "max_features": 4000, "tilt": True}
CAM_A = Camera("PINHOLE", 640, 480, (500.0, 501.0, 320.0, 240.0))
CAM_B = Camera("OPENCV", 1241, 376, (718.856, 718.856, 607.1928, 185.2157, -0.1, 0.01, 0.001, -0.002))


def rootsift(rng: np.random.Generator, n: int, d: int = 128) -> np.ndarray:
    x = np.sqrt(rng.gamma(0.5, size=(n, d)))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def make_features(rng: np.random.Generator, n: int, d: int = 128, signed: bool = False) -> Features:
    desc = rootsift(rng, n, d)
    if signed:
        desc = desc * rng.choice([-1.0, 1.0], size=desc.shape).astype(np.float32)
    return Features(
        keypoints=rng.uniform(0, 640, (n, 2)).astype(np.float32),
        descriptors=desc,
        scales=rng.uniform(1, 30, n).astype(np.float32),
    )


def make_posed(i: int, camera: Camera = CAM_A, rng: np.random.Generator | None = None) -> PosedImage:
    rng = rng or np.random.default_rng(i)
    pose = Pose(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3) * 5)
    return PosedImage(
        name=f"seq/{i:06d}.png",
        path=Path(f"/data/seq/{i:06d}.png"),
        cam_from_world=pose,
        camera=camera,
        index=i,
        timestamp=None if i % 2 else 100.0 + i / 10,
        depth_path=None if i % 3 else Path(f"/data/depth/{i:06d}.png"),
        depth_scale=1000.0,
    )


def assert_pose_close(a: Pose, b: Pose, tol: float = 1e-9) -> None:
    np.testing.assert_allclose(a.R, b.R, atol=tol)
    np.testing.assert_allclose(a.t, b.t, atol=tol)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(7)


# What each storage layout promises on a round trip: keypoint error (px, for a 640 px extent),
# relative scale error, descriptor error per value and the least cosine of a row with its original
# (RootSIFT-like rows; compact: 4-bit or transform-coded, see planarloc.map.codec).
ROUND_TRIP_TOL = {"full": (0.0, 0.0, 2e-3, 0.9999), "compact": (1 / 128, 2 ** (1 / 32) - 1, 0.08, 0.97)}


@pytest.mark.parametrize("storage", ["compact", "full"])
def test_round_trip(tmp_path: Path, rng: np.random.Generator, storage: str) -> None:
    path = tmp_path / "maps" / "map.db"
    posed = [make_posed(i, CAM_A if i < 3 else CAM_B) for i in range(5)]
    feats = [make_features(rng, n) for n in (50, 0, 300, 7, 120)]
    kp_tol, scale_rtol, desc_tol, cosine = ROUND_TRIP_TOL[storage]
    with MapDatabase.create(path, CONFIG, storage=storage) as db:
        ids = [db.add_image(p, f) for p, f in zip(posed, feats)]
        assert not db.is_complete
        db.mark_complete()
        assert db.is_complete
    assert len(set(ids)) == 5

    with MapDatabase.open(path) as db:
        assert db.config == CONFIG and db.storage == storage
        assert db.is_complete and db.num_images() == 5 and db.descriptor_dim == 128
        assert db.image_names() == [p.name for p in posed]
        assert db.get_meta("schema_version") == str(SCHEMA_VERSION)
        assert db.get_meta("created_by") == "planarloc"
        assert db.has_image("seq/000002.png") and not db.has_image("nope.png")
        # cameras are deduplicated by parameters
        assert db._db.execute("SELECT COUNT(*) FROM cameras").fetchone()[0] == 2
        poses = db.load_all_poses()
        for p, f, image_id in zip(posed, feats, ids):
            assert_pose_close(db.get_pose(p.name), p.cam_from_world)
            assert_pose_close(poses[p.name], p.cam_from_world)
            assert db.get_camera(p.name) == p.camera
            _assert_same_record(db.get_posed_image(image_id), p)
            for key in (p.name, image_id):
                got = db.get_features(key)
                assert got.keypoints.dtype == got.descriptors.dtype == got.scales.dtype == np.float32
                assert got.descriptors.shape == f.descriptors.shape
                np.testing.assert_allclose(got.keypoints, f.keypoints, rtol=0, atol=kp_tol)
                np.testing.assert_allclose(got.scales, f.scales, rtol=scale_rtol + 1e-6, atol=0)
                np.testing.assert_allclose(got.descriptors, f.descriptors, atol=desc_tol)
                assert np.all(np.einsum("ij,ij->i", got.descriptors, f.descriptors) >= cosine)
                if len(got):
                    np.testing.assert_allclose(np.linalg.norm(got.descriptors, axis=1), 1.0, atol=1e-5)
            assert db.num_features(p.name) == len(f)
        streamed = list(db.iter_features())
        assert [s[0] for s in streamed] == ids and [s[1] for s in streamed] == db.image_names()
        with pytest.raises(KeyError, match="nope.png"):
            db.get_pose("nope.png")
        with pytest.raises(InputError, match="read-only"):
            db.add_image(make_posed(9), feats[0])


def _assert_same_record(a: PosedImage, b: PosedImage) -> None:
    assert a.name == b.name and a.path == b.path and a.camera == b.camera and a.index == b.index
    assert a.timestamp == b.timestamp and a.depth_path == b.depth_path and a.depth_scale == b.depth_scale
    assert_pose_close(a.cam_from_world, b.cam_from_world)


@pytest.mark.parametrize("encoding", ["uint8", "float16", "float32"])
def test_descriptor_codecs(encoding: str, rng: np.random.Generator) -> None:
    d = rootsift(rng, 200)
    used, blob = encode_descriptors(d, encoding)
    assert used == encoding
    back = decode_descriptors(blob, 200, 128, used)
    tol = {"uint8": 2e-3, "float16": 1e-3, "float32": 1e-7}[encoding]
    np.testing.assert_allclose(back, d, atol=tol)
    assert len(blob) == 200 * 128 * {"uint8": 1, "float16": 2, "float32": 4}[encoding]
    # true matches (noisy copies) are still each other's nearest neighbours
    q = d[:50] + rng.normal(scale=0.02, size=(50, 128)).astype(np.float32)
    assert np.array_equal(np.argmax(q @ back.T, axis=1), np.arange(50))


def test_signed_descriptors_auto_float16(tmp_path: Path, rng: np.random.Generator) -> None:
    f = make_features(rng, 40, d=64, signed=True)
    with MapDatabase.create(tmp_path / "m.db", CONFIG) as db:
        db.add_image(make_posed(0), f)
        assert db._db.execute("SELECT encoding FROM descriptors").fetchone()[0] == "float16"
        np.testing.assert_allclose(db.get_features(0 + 1).descriptors, f.descriptors, atol=1e-3)
    with MapDatabase.create(tmp_path / "u.db", CONFIG, descriptor_encoding="uint8") as db:
        with pytest.raises(InputError, match="non-negative"):
            db.add_image(make_posed(0), f)
        assert db.num_images() == 0


def test_resume_skips_existing_and_append(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "map.db"
    feats = {i: make_features(rng, 30) for i in range(6)}
    with MapDatabase.create(path, CONFIG) as db:
        first = [db.add_image(make_posed(i), feats[i]) for i in range(3)]
        db.mark_complete()
    # re-running the build: existing names are skipped (same ids, nothing rewritten)
    with MapDatabase.open_or_create(path, CONFIG) as db:
        assert db.is_complete
        other = make_features(rng, 5)
        assert [db.add_image(make_posed(i), other) for i in range(3)] == first
        assert db.num_features(make_posed(0).name) == 30
        # appending new images makes the map incomplete until mark_complete()
        db.add_image(make_posed(3), feats[3])
        assert not db.is_complete
    with MapDatabase.open(path, "a") as db:
        db.add_image(make_posed(4), feats[4])
        db.mark_complete()
    with MapDatabase.open(path) as db:
        assert db.num_images() == 5 and db.is_complete
        np.testing.assert_allclose(
            db.get_features(make_posed(4).name).keypoints, feats[4].keypoints, atol=1 / 64
        )


def test_open_or_create_refuses_other_config(tmp_path: Path) -> None:
    with MapDatabase.create(tmp_path / "m.db", CONFIG) as db:
        db.add_image(make_posed(0), make_features(np.random.default_rng(0), 10))
    with pytest.raises(
        InputError, match=r"built with another feature config \(tilt: map has true, given false\)"
    ):
        MapDatabase.open_or_create(tmp_path / "m.db", {**CONFIG, "tilt": False})
    with pytest.raises(InputError, match="already exists"):
        MapDatabase.create(tmp_path / "m.db", CONFIG)
    MapDatabase.create(tmp_path / "m.db", {"tilt": False}, overwrite=True).close()
    with MapDatabase.open(tmp_path / "m.db") as db:
        assert db.config == {"tilt": False}


def test_empty_unfinished_map_with_other_config_is_replaced(tmp_path: Path) -> None:
    MapDatabase.create(tmp_path / "m.db", CONFIG).close()  # a build that failed before its first image
    with MapDatabase.open_or_create(tmp_path / "m.db", {"tilt": False}) as db:
        assert db.config == {"tilt": False} and db.num_images() == 0


class _Boom(Exception):
    pass


def test_crash_mid_build_leaves_consistent_map(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "map.db"
    feats = make_features(rng, 100)
    with pytest.raises(_Boom), MapDatabase.create(path, CONFIG) as db:
        for i in range(10):
            if i == 4:
                raise _Boom("extractor crashed")
            db.add_image(make_posed(i), feats)
    with MapDatabase.open(path) as db:
        assert not db.is_complete
        assert db.num_images() == 4
        for name in db.image_names():
            assert len(db.get_features(name)) == 100


def test_interrupt_inside_transaction_rolls_back(
    tmp_path: Path, rng: np.random.Generator, monkeypatch
) -> None:
    """Ctrl-C between the image row and its features must not leave a half-written image."""
    path = tmp_path / "map.db"
    db = MapDatabase.create(path, CONFIG)
    db.add_image(make_posed(0), make_features(rng, 10))
    real = MapDatabase._camera_id

    def camera_then_interrupt(self, conn, camera, pending):  # type: ignore[no-untyped-def]
        cam_id = real(self, conn, camera, pending)
        conn.execute(
            "INSERT INTO images (name, camera_id, qw, qx, qy, qz, tx, ty, tz, frame_index, depth_scale) "
            "VALUES ('half', ?, 1, 0, 0, 0, 0, 0, 0, 0, 1)",
            (cam_id,),
        )
        raise KeyboardInterrupt

    monkeypatch.setattr(MapDatabase, "_camera_id", camera_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        db.add_image(make_posed(1, CAM_B), make_features(rng, 10))
    monkeypatch.undo()
    assert db.num_images() == 1 and not db.has_image("half")
    # the camera inserted in the rolled-back transaction is not cached as existing
    db.add_image(make_posed(2, CAM_B), make_features(rng, 10))
    assert db.get_camera(make_posed(2).name) == CAM_B
    db.close()
    conn = sqlite3.connect(path)
    assert conn.execute("SELECT COUNT(*) FROM images").fetchone()[0] == 2
    conn.close()


def test_not_a_map_errors(tmp_path: Path) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("this is not a database\n" * 50)
    other = tmp_path / "other.db"
    conn = sqlite3.connect(other)
    conn.execute("CREATE TABLE cameras (id INTEGER)")
    conn.commit()
    conn.close()
    foreign = tmp_path / "foreign.db"
    conn = sqlite3.connect(foreign)
    conn.execute("CREATE TABLE meta (key TEXT, value TEXT)")
    conn.execute("INSERT INTO meta VALUES ('created_by', 'colmap')")
    conn.commit()
    conn.close()
    for path, why in [(text, "not an SQLite database"), (other, "meta table"), (foreign, "colmap")]:
        for mode in ("r", "a"):
            with pytest.raises(MapFormatError, match="is not a planarloc map") as info:
                MapDatabase.open(path, mode)
            assert str(path) in str(info.value) and why in str(info.value)
    with pytest.raises(MapFormatError, match="no such map file"):
        MapDatabase.open(tmp_path / "missing.db")
    assert issubclass(MapFormatError, ValueError)


def test_newer_schema_asks_to_upgrade(tmp_path: Path) -> None:
    path = tmp_path / "future.db"
    MapDatabase.create(path, CONFIG).close()
    conn = sqlite3.connect(path)
    conn.execute("UPDATE meta SET value = ? WHERE key = 'schema_version'", (str(SCHEMA_VERSION + 1),))
    conn.commit()
    conn.close()
    with pytest.raises(MapFormatError, match="upgrade planarloc"):
        MapDatabase.open(path)
    conn = sqlite3.connect(path)
    conn.execute("UPDATE meta SET value = '0' WHERE key = 'schema_version'")
    conn.commit()
    conn.close()
    with pytest.raises(MapFormatError, match="rebuild the map"):
        MapDatabase.open(path)


@pytest.mark.parametrize("storage", ["full", "compact"])
def test_global_descriptors_blobs_meta(tmp_path: Path, rng: np.random.Generator, storage: str) -> None:
    with MapDatabase.create(tmp_path / "m.db", CONFIG, storage=storage) as db:
        ids = [db.add_image(make_posed(i), make_features(rng, 5)) for i in range(4)]
        ids0, empty = db.get_global_descriptors()
        assert ids0.shape == (0,) and empty.shape == (0, 0)
        g = rng.normal(size=(4, 16)).astype(np.float32)
        db.set_global_descriptors((ids, g))
        got_ids, got = db.get_global_descriptors()
        np.testing.assert_array_equal(got_ids, ids)
        # full: as given; compact: 4 bits a value with one scale per vector, within max|v| / 14
        tol = 0.0 if storage == "full" else np.abs(g).max(axis=1, keepdims=True) / 14 * (1 + 1e-6)
        assert np.all(np.abs(got - g) <= tol)
        db.set_global_descriptors({make_posed(1).name: np.zeros(16)})
        assert np.all(db.get_global_descriptors()[1][1] == 0)
        with pytest.raises(InputError, match="16-D"):
            db.set_global_descriptors({ids[0]: np.zeros(8)})
        with pytest.raises(KeyError):
            db.set_global_descriptors({"unknown.png": np.zeros(16)})
        db.put_blob("vocabulary", b"\x00\x01binary")
        assert db.get_blob("vocabulary") == b"\x00\x01binary" and db.get_blob("missing") is None
        db.set_meta("note", "built on robot 3")
        with pytest.raises(InputError, match="managed"):
            db.set_meta("schema_version", "7")
    with MapDatabase.open(tmp_path / "m.db") as db:
        assert db.get_blob("vocabulary") == b"\x00\x01binary" and db.blob_keys() == ["vocabulary"]
        assert db.get_meta("note") == "built on robot 3"


def test_bad_features_rejected(tmp_path: Path, rng: np.random.Generator) -> None:
    with MapDatabase.create(tmp_path / "m.db", CONFIG) as db:
        f = make_features(rng, 10)
        with pytest.raises(InputError, match="scales"):
            db.add_image(make_posed(0), Features(f.keypoints, f.descriptors, f.scales[:5]))
        bad = f.keypoints.copy()
        bad[3, 1] = np.nan
        with pytest.raises(InputError, match="NaN"):
            db.add_image(make_posed(0), Features(bad, f.descriptors, f.scales))
        db.add_image(make_posed(0), f)
        with pytest.raises(InputError, match="128-D"):
            db.add_image(make_posed(1), make_features(rng, 10, d=64))
        assert db.num_images() == 1


def test_lazy_open_and_cache(tmp_path: Path, rng: np.random.Generator) -> None:
    with MapDatabase.create(tmp_path / "m.db", CONFIG) as db:
        for i in range(6):
            db.add_image(make_posed(i), make_features(rng, 20))
    with MapDatabase.open(tmp_path / "m.db", cache_size=2) as db:
        assert len(db._cache) == 0  # nothing loaded at open
        a = db.get_features(1)
        assert db.get_features(1) is a  # cached
        assert not a.descriptors.flags.writeable
        db.get_features(2)
        db.get_features(3)
        assert list(db._cache) == [2, 3]


def test_poses_are_built_once_while_the_map_is_unchanged(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "map.db"
    with MapDatabase.create(path, CONFIG) as db:
        for i in range(3):
            db.add_image(make_posed(i), make_features(rng, 20))
    with MapDatabase.open(path) as reader:
        first = {p.name: p.cam_from_world for p in reader.posed_images()}
        again = reader.load_all_poses()
        assert all(again[n] is first[n] for n in first)  # the same objects: validated once
        with MapDatabase.open(path, "a") as writer:  # another connection commits: poses are read again
            writer.add_image(make_posed(3), make_features(rng, 20))
        after = reader.load_all_poses()
        assert len(after) == 4
        assert_pose_close(after[make_posed(3).name], make_posed(3).cam_from_world)
        moved = Pose.identity()
        with sqlite3.connect(path) as conn:  # a pose rewritten in place (same id)
            conn.execute(
                "UPDATE images SET qw = 1, qx = 0, qy = 0, qz = 0, tx = 0, ty = 0, tz = 0 WHERE name = ?",
                (make_posed(0).name,),
            )
        assert_pose_close(reader.load_all_poses()[make_posed(0).name], moved)
        assert_pose_close(reader.posed_images()[0].cam_from_world, moved)
