"""Sequential localization on a rendered stream with a kidnap and dropped frames."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from planarloc.evaluation.sequence import evaluate_stream, summarize_sequence
from planarloc.features.images import read_gray
from planarloc.geometry.pose import Pose, pose_errors
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import read_dataset
from planarloc.localize.localizer import Localizer, LocalizerConfig
from planarloc.localize.sequence import SequenceConfig, SequenceLocalizer
from planarloc.map.builder import build_map
from planarloc.robust.options import RansacOptions
from planarloc.robust.result import PoseEstimate
from planarloc.synthetic.stream import make_stream, stream_order
from planarloc.synthetic.world.export import generate
from planarloc.synthetic.world.presets import get_preset, shrunk

PERFECT_MAP = {"map_rotation_std_deg": 0.0, "map_position_std_m": 0.0}


@pytest.fixture(scope="module")
def stream_world(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list]:
    """office at 320x240: 16 map frames, 14 query frames around the loop (~1 m, ~25° apart)."""
    root = generate(shrunk(get_preset("office"), scale=0.5, n_map=16, n_query=14),
                    tmp_path_factory.mktemp("world") / "office", seed=0)
    path = root.parent / "map.db"
    build_map(read_dataset(root / "map", "tum"), path)
    return path, read_dataset(root / "query", "tum")


def _stream(queries: list):
    # kidnap after frame 5 to frame 9 and back to 5 later; frames 2 and 10 dropped
    return make_stream(queries, stream_order(len(queries), kidnap_at=5, skip=4, drop=[2, 10]),
                       np.random.default_rng(0))


def _run(map_path: Path, frames: list, structure: str, odometry: bool, **config) -> list:
    loc = Localizer(map_path, LocalizerConfig(ransac=RansacOptions(structure=structure, **PERFECT_MAP)))
    seq = SequenceLocalizer(loc, SequenceConfig(**{"fixes": "wait", **config}))
    return evaluate_stream(seq, [f.image for f in frames], [f.stamp for f in frames],
                           [f.odometry for f in frames] if odometry else None, [f.kidnapped for f in frames])


@pytest.mark.parametrize("structure, odometry", [("tracks", True), ("none", False)])
def test_stream_with_kidnap_and_dropped_frames(stream_world: tuple, structure: str, odometry: bool) -> None:
    map_path, queries = stream_world
    frames = _stream(queries)
    assert [f.kidnapped for f in frames].count(True) == 2
    results = _run(map_path, frames, structure, odometry)
    summary = summarize_sequence(results)
    assert summary["frames"] == len(frames) == 12
    assert summary["frames_with_pose"] == 12                    # every frame gets a pose
    assert summary["confident_wrong"] == 0
    reloc = summary["relocalization"]
    assert reloc["start"]["frames"] == 0
    assert reloc["max_frames_after_kidnap"] is not None and reloc["max_frames_after_kidnap"] <= 2
    # the kidnap frames are the only failures; each one reports the contradicting fix it rejected
    for r in results:
        if r.kidnapped:
            assert r.fix_status == "rejected" and r.status in ("predicted", "lost")
        elif r.status == "localized":
            assert r.translation_error_m < 0.35 and r.rotation_error_deg < 10
    assert summary["success"]["0.25m/10deg"] >= 100 * 9 / 12


def test_outlier_fix_is_rejected_and_the_stream_continues(stream_world: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    map_path, queries = stream_world
    frames = make_stream(queries, list(range(6)), np.random.default_rng(1))
    loc = Localizer(map_path, LocalizerConfig(ransac=RansacOptions(structure="tracks", **PERFECT_MAP)))
    seq = SequenceLocalizer(loc, SequenceConfig(fixes="wait"))
    real = loc.localize_features
    calls = {"n": 0}

    def wrong_at_frame_3(features, camera, references=None, **kw):
        est = real(features, camera, references, **kw)
        if calls["frame"] == 3 and est.success:   # a confident fix 2 m off
            shifted = Pose.from_center(est.pose.R, est.pose.center + [2.0, 0, 0])
            est = PoseEstimate(shifted, True, "success", "injected", est.inliers, est.num_inliers,
                               est.num_inliers_3d, est.iterations, 0.02)
        return est

    monkeypatch.setattr(loc, "localize_features", wrong_at_frame_3)
    out = []
    for k, f in enumerate(frames):
        calls["frame"] = k
        out.append(seq.step(read_gray(f.image.path), f.image.camera, f.stamp, f.odometry))
    bad = out[3]
    assert bad.fix_status == "rejected" and bad.status == "predicted" and bad.kidnap_suspected
    assert len(bad.rejected) == 2 and all(r["mahalanobis_sq"] > 22 for r in bad.rejected)
    assert pose_errors(bad.pose, frames[3].image.cam_from_world)[0] < 0.2   # the outlier was not used
    assert out[4].status == "localized" and not out[4].reinitialized      # one outlier is not a kidnap
    assert all(e.status == "localized" for k, e in enumerate(out) if k != 3)


def test_without_fixes_the_prediction_grows_until_lost(stream_world: tuple, monkeypatch: pytest.MonkeyPatch) -> None:
    map_path, queries = stream_world
    frames = make_stream(queries, list(range(8)), np.random.default_rng(2))
    loc = Localizer(map_path)
    seq = SequenceLocalizer(loc, SequenceConfig(lost_std_m=0.2, fixes="wait"))
    first = seq.step(read_gray(frames[0].image.path), frames[0].image.camera, frames[0].stamp, frames[0].odometry)
    assert first.status == "localized" and first.motion_source == "none", (first.status, first.position_std_m)
    monkeypatch.setattr(loc, "localize_features", lambda *a, **k: PoseEstimate(None, False, "too_few_matches", "x", []))
    stds, statuses = [], []
    for f in frames[1:]:
        est = seq.step(read_gray(f.image.path), f.image.camera, f.stamp, f.odometry)
        assert est.pose is not None and est.fix_status == "failed" and est.motion_source == "odometry"
        stds.append(est.position_std_m)
        statuses.append(est.status)
    assert np.all(np.diff(stds) > 0)
    assert statuses[0] == "predicted" and statuses[-1] == "lost"
    assert all(s == "lost" for s in statuses[statuses.index("lost"):])


def test_bad_input_is_an_error(stream_world: tuple) -> None:
    map_path, queries = stream_world
    seq = SequenceLocalizer(Localizer(map_path))
    image = read_gray(queries[0].path)
    with pytest.raises(InputError, match="camera"):
        seq.step(image, "PINHOLE", 0.0)
    with pytest.raises(InputError, match="odometry"):
        seq.step(image, queries[0].camera, 0.0, odometry=np.eye(4))
    with pytest.raises(InputError, match="stamp"):
        seq.step(image, queries[0].camera, float("nan"))
    with pytest.raises(InputError, match="window"):
        SequenceConfig(window=1)
    with pytest.raises(InputError, match="vo_model"):
        SequenceConfig(vo_model="5pt")
    with pytest.raises(InputError, match="localizer"):
        SequenceLocalizer("map.db")


def test_retrieval_prior_prefers_map_images_near_the_prediction(stream_world: tuple) -> None:
    map_path, queries = stream_world
    loc = Localizer(map_path)
    seq = SequenceLocalizer(loc, SequenceConfig(local_top_n=3))
    posed = {p.name: p.cam_from_world for p in loc.db.posed_images()}
    q = queries[4].cam_from_world
    refs = seq.references_near(q, 0.1)
    assert len(refs) == 3
    dist = {n: np.linalg.norm(p.center - q.center) for n, p in posed.items()}
    assert max(dist[r] for r in refs) <= sorted(dist.values())[5]          # among the nearest
    far = Pose.from_center(q.R, q.center + [100.0, 0, 0])
    assert seq.references_near(far, 0.1) is None                           # nothing near: global retrieval
    assert seq.references_near(far, 40.0) is not None                      # an uncertain prediction widens the radius
