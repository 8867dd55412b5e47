"""Bad input fails with ValueError before any work; too few matches is a status, not an error."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import planarloc.robust.absolute_pose as absolute_pose_module
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import RansacOptions, Structure
from planarloc.robust.pair_matches import PairMatches
from planarloc.synthetic.scenes import PAPER_CAMERA

ALL_METHODS = ("2p1p", "2p2p", "5p5p-nister", "5p5p-stewenius", "8p8p")


@pytest.fixture
def no_work(monkeypatch):
    """Make any RANSAC or triangulation work fail the test: errors must come first."""

    def forbidden(*args, **kwargs):
        raise AssertionError("work started before the input was validated")

    monkeypatch.setattr(absolute_pose_module, "ransac", forbidden)
    monkeypatch.setattr(absolute_pose_module, "triangulate_tracks", forbidden)


@pytest.fixture
def small_scene(scene):
    return scene(0, num_refs=3, matches_per_pair=20, noise_px=1.0)


def pair_like(p: PairMatches, **changes) -> PairMatches:
    fields = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}
    fields.update(changes)
    return PairMatches(**fields)


# ---- PairMatches / Pose construction -------------------------------------------------------
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("field", ["query_points", "ref_points"])
def test_non_finite_pixels_rejected(small_scene, field: str, bad: float) -> None:
    p = small_scene.pairs[0]
    x = getattr(p, field).copy()
    x[3, 1] = bad
    with pytest.raises(ValueError, match=field):
        pair_like(p, **{field: x})


def test_mismatched_lengths_rejected(small_scene) -> None:
    p = small_scene.pairs[0]
    with pytest.raises(ValueError, match="ref_points"):
        pair_like(p, ref_points=p.ref_points[:-1])


@pytest.mark.parametrize("shape", [(20, 3), (20,), (2, 20)])
def test_wrong_point_shape_rejected(small_scene, shape) -> None:
    p = small_scene.pairs[0]
    with pytest.raises(ValueError, match="expected shape"):
        pair_like(p, query_points=np.zeros(shape))


def test_duplicate_query_indices_rejected(small_scene) -> None:
    p = small_scene.pairs[0]
    ids = np.arange(len(p))
    ids[5] = ids[6]
    with pytest.raises(ValueError, match="unique"):
        pair_like(p, query_indices=ids)


def test_query_indices_length_rejected(small_scene) -> None:
    p = small_scene.pairs[0]
    with pytest.raises(ValueError, match="query_indices"):
        pair_like(p, query_indices=np.arange(len(p) + 1))


def test_partial_or_infinite_depth_rejected(small_scene) -> None:
    p = small_scene.pairs[0]
    X = np.ones((len(p), 3))
    X[2, 0] = np.nan  # one coordinate missing
    with pytest.raises(ValueError, match="ref_points3d"):
        pair_like(p, ref_points3d=X)
    X = np.ones((len(p), 3))
    X[2] = np.inf
    with pytest.raises(ValueError, match="ref_points3d"):
        pair_like(p, ref_points3d=X)


@pytest.mark.parametrize(
    "R",
    [2.0 * np.eye(3), np.diag([1.0, 1.0, -1.0]), np.ones((3, 3)), np.eye(3) + 1e-3, np.full((3, 3), np.nan)],
)
def test_non_rotation_pose_rejected(R: np.ndarray) -> None:
    with pytest.raises(ValueError):
        Pose(R, np.zeros(3))


def test_pair_needs_pose_and_camera(small_scene) -> None:
    p = small_scene.pairs[0]
    with pytest.raises(ValueError, match="ref_pose"):
        pair_like(p, ref_pose=p.ref_pose.matrix)
    with pytest.raises(ValueError, match="ref_camera"):
        pair_like(p, ref_camera=PAPER_CAMERA.K)


# ---- estimate_absolute_pose arguments --------------------------------------------------------
def test_single_pair_rejected(small_scene, no_work) -> None:
    with pytest.raises(ValueError, match="at least 2"):
        estimate_absolute_pose(small_scene.query_camera, small_scene.pairs[:1])


def test_empty_list_rejected(small_scene, no_work) -> None:
    with pytest.raises(ValueError, match="at least 2"):
        estimate_absolute_pose(small_scene.query_camera, [])


@pytest.mark.parametrize("bad", ["not a pair", None, 3, np.zeros((20, 2))])
def test_non_pair_entries_rejected(small_scene, no_work, bad) -> None:
    with pytest.raises(ValueError, match=r"pairs\[1\]"):
        estimate_absolute_pose(small_scene.query_camera, [small_scene.pairs[0], bad, small_scene.pairs[2]])


def test_bare_pair_or_generator_rejected(small_scene, no_work) -> None:
    with pytest.raises(ValueError, match="list of PairMatches"):
        estimate_absolute_pose(small_scene.query_camera, small_scene.pairs[0])
    with pytest.raises(ValueError, match="list of PairMatches"):
        estimate_absolute_pose(small_scene.query_camera, (p for p in small_scene.pairs))


def test_query_camera_type_rejected(small_scene, no_work) -> None:
    with pytest.raises(ValueError, match="query_camera"):
        estimate_absolute_pose(PAPER_CAMERA.K, small_scene.pairs)


@pytest.mark.parametrize("method", ["3p", "", "2P1P ", None, 5])
def test_unknown_method_rejected(small_scene, no_work, method) -> None:
    with pytest.raises(ValueError, match="method"):
        estimate_absolute_pose(small_scene.query_camera, small_scene.pairs, method)


@pytest.mark.parametrize("options", [{"max_iterations": 10}, "fast", 100])
def test_options_type_rejected(small_scene, no_work, options) -> None:
    with pytest.raises(ValueError, match="options"):
        estimate_absolute_pose(small_scene.query_camera, small_scene.pairs, "2p1p", options)


@pytest.mark.parametrize("options", [{}, 0, ""])
def test_falsy_options_rejected(small_scene, options) -> None:
    with pytest.raises(ValueError, match="options"):
        estimate_absolute_pose(small_scene.query_camera, small_scene.pairs, "2p1p", options)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(min_iterations=200, max_iterations=100), "min_iterations"),
        (dict(min_iterations=0), "min_iterations"),
        (dict(threshold_px=-1.0), "threshold_px"),
        (dict(threshold_px=0.0), "threshold_px"),
        (dict(threshold_px=float("nan")), "threshold_px"),
        (dict(rcheck_deg=-2.0), "rcheck_deg"),
        (dict(consistency_deg=0.0), "consistency_deg"),
        (dict(max_position_std_m=-0.1), "max_position_std_m"),
        (dict(confidence=1.0), "confidence"),
        (dict(confidence=0.0), "confidence"),
        (dict(structure="points"), "structure"),
        (dict(structure=None), "structure"),
    ],
)
def test_bad_options_rejected(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        RansacOptions(**kwargs)


def _unvalidated(kwargs: dict, consequence: str):
    """Options that used to be accepted silently (``consequence``); now rejected up front."""
    return pytest.param(kwargs, id=",".join(kwargs))


@pytest.mark.parametrize(
    "kwargs",
    [
        _unvalidated(
            dict(max_iterations=2.5, min_iterations=1),
            "ransac.py then loops forever once 0 < max_iterations - iterations < 1 (batch of int(0.5) = 0)",
        ),
        _unvalidated(
            dict(seed=-1), "numpy raises 'expected non-negative integer' only inside estimate_absolute_pose"
        ),
        _unvalidated(dict(seed=1.5), "numpy raises TypeError (not ValueError) inside estimate_absolute_pose"),
        _unvalidated(dict(threshold_px=float("inf")), "every match becomes an inlier, silently"),
        _unvalidated(dict(min_inliers=-3), "the min_inliers check can never fail"),
    ],
)
def test_invalid_options_rejected_at_construction(kwargs: dict) -> None:
    with pytest.raises(ValueError):
        RansacOptions(**kwargs)


def test_options_accept_enum_and_string_structure() -> None:
    assert RansacOptions(structure="tracks").structure is Structure.TRACKS
    assert RansacOptions(structure=Structure.NONE).structure is Structure.NONE


# ---- too few matches: a status, not an exception --------------------------------------------
def _truncated(sc, n: int) -> list[PairMatches]:
    return [
        pair_like(
            p, query_points=p.query_points[:n], ref_points=p.ref_points[:n], query_indices=p.query_indices[:n]
        )
        for p in sc.pairs
    ]


@pytest.mark.parametrize(
    "method, n",
    [("2p1p", 1), ("2p2p", 1), ("5p5p-nister", 4), ("5p5p-stewenius", 4), ("8p8p", 7), ("2p1p", 0)],
)
def test_too_few_matches_is_a_status(small_scene, no_work, method: str, n: int) -> None:
    est = estimate_absolute_pose(
        small_scene.query_camera, _truncated(small_scene, n), method, RansacOptions(structure="none")
    )  # the 2D-2D minimal samples
    assert not est.success and est.pose is None
    assert est.status == "too_few_matches"
    assert [len(m) for m in est.inliers] == [n] * 3


def test_too_few_matches_in_one_pair_only(small_scene, no_work) -> None:
    """2p2p needs two matches in each of two pairs: one pair with 2 and the others with 1 is too few."""
    pairs = _truncated(small_scene, 1)
    p = small_scene.pairs[0]
    pairs[0] = pair_like(
        p, query_points=p.query_points[:2], ref_points=p.ref_points[:2], query_indices=p.query_indices[:2]
    )
    est = estimate_absolute_pose(small_scene.query_camera, pairs, "2p2p", RansacOptions(structure="none"))
    assert est.status == "too_few_matches"


def test_other_camera_model_is_accepted(scene) -> None:
    """SIMPLE_PINHOLE with the same intrinsics describes the same camera."""
    sc = scene(0, num_refs=3, matches_per_pair=30, noise_px=0.0)
    cam = Camera("SIMPLE_PINHOLE", 1280, 1080, (800.0, 640.0, 540.0))
    est = estimate_absolute_pose(
        cam, sc.pairs, "2p1p", RansacOptions(max_iterations=100, min_iterations=100, structure="none")
    )
    assert est.success
    assert np.linalg.norm(est.pose.center - sc.query_pose.center) < 1e-6
