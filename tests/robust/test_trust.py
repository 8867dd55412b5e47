"""Trust: gravity-levelled planar solvers, method auto, and no confident wrong pose on tilted or
off-plane queries (issue: never confidently wrong)."""

from dataclasses import replace

import numpy as np
import pytest
from hard_protocol import hard_protocol_scene
from scipy.spatial.transform import Rotation

from planarloc.geometry.pose import Pose, pose_errors
from planarloc.geometry.validation import InputError
from planarloc.robust.absolute_pose import estimate_absolute_pose
from planarloc.robust.options import RansacOptions
from planarloc.robust.pair_matches import PairMatches
from planarloc.synthetic.scenes import gravity_world, make_scene

PERFECT_MAP = dict(map_rotation_std_deg=0.0, map_position_std_m=0.0)


def _gravity_scene(seed: int, **tilts: float) -> tuple:
    """(scene, W): a noise-free scene of 4 references, 60 matches each, with every image's gravity,
    in a world frame W (``world_from_upright``, random for ``seed``) not gravity-aligned; ``tilts``:
    the mount and query tilt angles of :func:`make_scene` (deg)."""
    W = Pose(Rotation.random(random_state=seed).as_matrix(), np.array([3.0, -1.0, 2.0]))
    rng = np.random.default_rng(seed)
    kw = dict(num_refs=4, matches_per_pair=60, noise_px=0.0, world_from_upright=W, with_gravity=True)
    return make_scene(rng, **kw, **tilts), W


@pytest.mark.parametrize("method", ["2p1p", "2p2p", "auto"])
def test_mounted_pitch_in_a_rotated_world_is_exact(method: str) -> None:
    # Every camera pitched 10° and rolled 3°, world frame not gravity-aligned: with each
    # reference's gravity the planar solvers run on levelled bearings and recover the pose.
    for seed in range(3):
        sc, _W = _gravity_scene(seed, mount_pitch_deg=10.0, mount_roll_deg=3.0)
        est = estimate_absolute_pose(sc.query_camera, sc.pairs, method, RansacOptions(**PERFECT_MAP))
        assert est.success, est.message
        assert est.model == "planar"
        t_err, r_err = pose_errors(est.pose, sc.query_pose)
        assert t_err < 1e-6 and r_err < 1e-4  # degrees: arccos resolution near 0


def test_query_gravity_from_an_imu_is_used() -> None:
    # The query is tilted 3° more than the map: given its true gravity, 2p1p stays planar-exact.
    sc, W = _gravity_scene(4, mount_pitch_deg=8.0, query_tilt_deg=3.0)
    g_q = sc.query_pose.R @ gravity_world(sc, W)
    est = estimate_absolute_pose(
        sc.query_camera, sc.pairs, "2p1p", RansacOptions(**PERFECT_MAP), query_gravity=g_q
    )
    assert est.success and est.model == "planar", est.message
    t_err, r_err = pose_errors(est.pose, sc.query_pose)
    assert t_err < 1e-6 and r_err < 1e-4  # degrees: arccos resolution near 0


@pytest.mark.parametrize(
    ("condition", "planar_failures"),
    [
        # 3° of tilt is within reach of the planar search on some scenes: a pose within its
        # uncertainty, or one of the two statuses that say why not.
        (dict(query_tilt_deg=3.0), ("planar_model_violated", "degenerate_scale")),
        # 0.5 m off the map's plane, or a 10° pitch without gravity: the planar model cannot hold.
        (dict(query_height_m=0.5), ("planar_model_violated",)),
        (dict(mount_pitch_deg=10.0), ("planar_model_violated",)),
    ],
)
def test_auto_falls_back_to_6dof_and_explicit_planar_is_never_confidently_wrong(
    condition: dict, planar_failures: tuple
) -> None:
    # Tilted query, query below the map's plane, or a pitched mount without gravity: the
    # planar model does not hold. auto localizes every one; the paper's 2p1p either returns a
    # pose within its uncertainty or says that the planar model is violated.
    auto_ok = 0
    for seed in range(8):
        rng = np.random.default_rng(100 + seed)
        sc = make_scene(rng, num_refs=5, matches_per_pair=100, noise_px=1.0, outlier_ratio=0.3, **condition)
        est = estimate_absolute_pose(sc.query_camera, sc.pairs, "auto", RansacOptions(**PERFECT_MAP))
        if est.success:
            t_err, r_err = pose_errors(est.pose, sc.query_pose)
            assert t_err <= 3 * est.position_std_m + 0.05 and r_err < 1.0, (seed, t_err, est.position_std_m)
            auto_ok += 1
        planar = estimate_absolute_pose(sc.query_camera, sc.pairs, "2p1p", RansacOptions(**PERFECT_MAP))
        if planar.success:
            t_err, r_err = pose_errors(planar.pose, sc.query_pose)
            assert t_err <= 3 * planar.position_std_m + 0.05 and r_err < 1.0, (
                seed,
                t_err,
                planar.position_std_m,
            )
        else:
            assert planar.status in planar_failures, (seed, planar.status)
    assert auto_ok == 8


def test_auto_reports_the_model() -> None:
    rng = np.random.default_rng(3)
    sc = make_scene(rng, num_refs=4, matches_per_pair=80, noise_px=0.5, query_height_m=0.8)
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, "auto", RansacOptions(**PERFECT_MAP))
    assert est.success and est.model == "6dof" and est.to_dict()["model"] == "6dof"
    rng = np.random.default_rng(3)
    sc = make_scene(rng, num_refs=4, matches_per_pair=80, noise_px=0.5)
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, "auto", RansacOptions(**PERFECT_MAP))
    assert est.success and est.model == "planar"


def test_a_reference_with_a_wrong_pose_is_caught() -> None:
    # One of four map poses is 1.5 m off: the references disagree; the estimator must not
    # report a pose outside its uncertainty (it may drop the bad reference or fail).
    for seed in range(4):
        rng = np.random.default_rng(20 + seed)
        sc = make_scene(rng, num_refs=4, matches_per_pair=80, noise_px=0.5)
        bad = sc.pairs[1]
        moved = Pose(bad.ref_pose.R, bad.ref_pose.t + bad.ref_pose.R @ np.array([1.5, 0.0, 0.0]))
        pairs = [
            sc.pairs[0],
            PairMatches(moved, bad.ref_camera, bad.query_points, bad.ref_points),
            *sc.pairs[2:],
        ]
        est = estimate_absolute_pose(sc.query_camera, pairs, "auto", RansacOptions(**PERFECT_MAP))
        if est.success:  # the bad reference dropped
            t_err, _ = pose_errors(est.pose, sc.query_pose)
            assert t_err <= 3 * est.position_std_m + 0.05, (seed, t_err, est.position_std_m)
        else:  # the status a wrong map pose earns (README, "What a success promises")
            assert est.status == "inconsistent_references", est.status


def test_one_supporting_reference_is_not_a_pose() -> None:
    rng = np.random.default_rng(5)
    sc = make_scene(rng, num_refs=3, matches_per_pair=80, noise_px=0.5)
    # Only the first reference keeps its true matches; the others are pure noise.
    pairs = [sc.pairs[0]] + [
        PairMatches(p.ref_pose, p.ref_camera, p.query_points, rng.uniform(0, 1000, p.ref_points.shape))
        for p in sc.pairs[1:]
    ]
    est = estimate_absolute_pose(sc.query_camera, pairs, "2p1p", RansacOptions(**PERFECT_MAP))
    assert not est.success and est.pose is None
    assert est.status == "single_reference", est.status


def test_bad_gravity_is_a_clear_error() -> None:
    rng = np.random.default_rng(0)
    sc = make_scene(rng, num_refs=2, matches_per_pair=30)
    with pytest.raises(InputError, match="query_gravity"):
        estimate_absolute_pose(sc.query_camera, sc.pairs, query_gravity=[0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="query_gravity"):
        estimate_absolute_pose(sc.query_camera, sc.pairs, query_gravity=[np.nan, 1.0, 0.0])
    with pytest.raises(InputError, match="ref_gravity"):
        PairMatches(
            sc.pairs[0].ref_pose,
            sc.query_camera,
            sc.pairs[0].query_points,
            sc.pairs[0].ref_points,
            ref_gravity=[0.0, 1.0],
        )


@pytest.mark.parametrize("tilt_deg", [1.0, 3.0])
def test_returned_pose_never_costs_more_than_the_refined_truth(tilt_deg: float) -> None:
    # Residual pitch/roll of the query (uneven floor): the search must not lose the basin of
    # the truth, i.e. the returned pose's MSAC cost is at most that of the ground truth
    # refined on the same matches (up to the refinement's convergence tolerance).
    from planarloc.robust.estimators import Planar2p1pEstimator
    from planarloc.robust.problem import build_problem

    options = RansacOptions(**PERFECT_MAP)
    for seed in range(6):
        rng = np.random.default_rng(300 + seed)
        sc = make_scene(
            rng, num_refs=5, matches_per_pair=100, noise_px=1.0, outlier_ratio=0.4, query_tilt_deg=tilt_deg
        )
        est = estimate_absolute_pose(sc.query_camera, sc.pairs, "auto", options)
        assert est.pose is not None or est.unreliable_pose is not None, est.status
        pose = est.pose if est.pose is not None else est.unreliable_pose
        scorer = Planar2p1pEstimator(build_problem(sc.query_camera, sc.pairs), options)
        R, t = sc.query_pose.R, sc.query_pose.t
        for _ in range(3):
            R, t, *_ = scorer.refine_full(R, t, 20)
        truth_cost = scorer.score(R[None], t[None])[0][0]
        returned_cost = scorer.score(pose.R[None], pose.t[None])[0][0]
        assert returned_cost <= truth_cost * 1.01 + 1e-6, (seed, returned_cost, truth_cost)


# ---- runner-up answers (ambiguous_pose) -----------------------------------------------------------
def _refined(centre, score, n=20):
    from planarloc.robust.final_refinement import RefinedPose

    c = np.asarray(centre, dtype=float)
    return RefinedPose(
        np.eye(3), -c, np.eye(3) * 1e-4, 1.0, score, score, np.ones(n, bool), np.zeros(0, bool)
    )


class _Scorer:
    threshold_sq = 4.0


def test_rival_distance_margin_in_inliers() -> None:
    from planarloc.robust.rivals import MAX_ALTERNATIVE_REFINEMENTS, RIVAL_MARGIN_INLIERS, rival_distance

    ref = _refined([0, 0, 0], 100.0)
    margin = RIVAL_MARGIN_INLIERS * _Scorer.threshold_sq
    far = (np.eye(3), -np.array([1.0, 0, 0]))
    calls = []  # the start's centre x and quick, per refinement

    def refine_to(centre, score):
        def refine(R, t, quick):
            calls.append((float(-t[0]), quick))
            return _refined(centre, score)

        return refine

    # A runner-up refining 1 m away within the margin is a rival: its distance bounds the std.
    d = rival_distance(_Scorer(), ref, [(*far, 100.0 + margin)], refine_to([1, 0, 0], 100 + margin), 0.2)
    assert d == pytest.approx(1.0)
    # Beyond the margin after refinement, or back at the best pose: no rival.
    assert (
        rival_distance(_Scorer(), ref, [(*far, 100.0)], refine_to([1, 0, 0], 100 + 1.5 * margin), 0.2) == 0.0
    )
    assert rival_distance(_Scorer(), ref, [(*far, 100.0)], refine_to([0.05, 0, 0], 100.0), 0.2) == 0.0
    # Far in cost before refinement, or already near: never refined.
    calls.clear()
    assert rival_distance(_Scorer(), ref, [(*far, 100.0 + 3 * margin)], refine_to([1, 0, 0], 100), 0.2) == 0
    assert (
        rival_distance(_Scorer(), ref, [(np.eye(3), np.zeros(3), 100.0)], refine_to([1, 0, 0], 100), 0.2) == 0
    )
    assert not calls
    # At most MAX_ALTERNATIVE_REFINEMENTS runner-ups are refined, cheapest first; one whose quick
    # look lands beyond twice the margin is not refined in full.
    many = [
        (np.eye(3), -np.array([1.0 + k, 0, 0]), 100.0 + k) for k in range(MAX_ALTERNATIVE_REFINEMENTS + 2)
    ]
    assert rival_distance(_Scorer(), ref, many[::-1], refine_to([1, 0, 0], 100 + 3 * margin), 0.2) == 0.0
    assert calls == [(1.0 + k, True) for k in range(MAX_ALTERNATIVE_REFINEMENTS)]


@pytest.mark.parametrize("case", [(2, 4, 77), (3, 3, 56), (1, 4, 86)])
def test_few_inliers_far_runner_up_is_not_a_confident_success(case) -> None:
    """Scenes (3 references x 20 matches, 1.5 px noise, 40-60 % outliers) where 2p1p used to
    report success 0.2-0.3 m off with a std of 0.04 m: a runner-up pose explained the matches
    within two inliers' worth of MSAC cost."""
    seed, ri, trial = case
    sc, opts = hard_protocol_scene(seed, 1, ri, trial, matches=20)
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, "2p1p", replace(opts, cross_check=False))
    if est.success:
        err, _ = pose_errors(est.pose, sc.query_pose)
        assert err <= 3 * est.position_std_m + 0.05, (err, est.position_std_m)
    else:  # the status of a runner-up pose explaining the matches about as well
        assert est.status == "ambiguous_pose", est.status


@pytest.mark.parametrize("case", [(7, 1, 4, 4), (33, 0, 4, 58), (21, 0, 4, 129), (11, 1, 4, 30)])
def test_a_restart_that_lands_inside_the_promise_still_bounds_the_std(case) -> None:
    """Hard-protocol scenes (3 references, 1.5 px noise, 60 % outliers, 50 or 20 matches) where
    `auto` reported success 0.2-0.4 m off with a std of 0.04-0.1 m: the true pose's basin lay
    0.15-0.7 m away along the weakest axis at a cost within the margin, and the restarts landed
    between the two, inside the old promise, where they were ignored. A pose the data support as
    well, wherever it lies, is a lower bound on the std."""
    seed, mi, ri, trial = case
    sc, opts = hard_protocol_scene(seed, mi, ri, trial, matches=(50, 20)[mi])
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, "auto", opts)
    if est.success:
        err, _ = pose_errors(est.pose, sc.query_pose)
        assert err <= 3 * est.position_std_m + 0.05, (err, est.position_std_m, est.message)
    else:
        assert est.status in ("ambiguous_pose", "degenerate_scale"), est.status


def test_basin_margins_rival_and_near() -> None:
    """Restarts within one inlier's worth of cost are rivals wherever they land; for a pose on few
    inliers, those within :data:`NEAR_BASIN_MARGIN_INLIERS` inliers' worth and within the largest
    std of a success widen the std only."""
    from planarloc.robust.final_refinement import Restart
    from planarloc.robust.rivals import (
        NEAR_BASIN_BELOW_INLIERS,
        NEAR_BASIN_MARGIN_INLIERS,
        RESTART_MARGIN_INLIERS,
        basin_distance,
    )

    tight = RESTART_MARGIN_INLIERS * _Scorer.threshold_sq
    near = NEAR_BASIN_MARGIN_INLIERS * _Scorer.threshold_sq

    class Refiner:
        def __init__(self, *landings: Restart) -> None:
            self.landings = list(landings)

        def restarts(self, ref, step_m):
            return self.landings

    ref, few, many = _refined([0, 0, 0], 100.0), NEAR_BASIN_BELOW_INLIERS - 1, NEAR_BASIN_BELOW_INLIERS

    def basins(n: int, *landings: Restart):
        return basin_distance(_Scorer(), ref, Refiner(*landings), 0.2, n, 0.3)

    assert basins(few) == (0.0, 0.0)  # no restart (no usable normal matrix)
    # Within the tight margin, or below the pose's cost: a rival at any distance.
    assert basins(many, Restart(tight, 0.5), Restart(-3.0, 0.7)) == (0.7, 0.0)
    # Between the margins: widens a pose on few inliers, within the largest std of a success only.
    assert basins(few, Restart(0.5 * (tight + near), 0.15), Restart(near, 0.25)) == (0.0, 0.25)
    assert basins(few, Restart(near, 0.45)) == (0.0, 0.0)
    assert basins(many, Restart(near, 0.25)) == (0.0, 0.0)
    assert basins(few, Restart(near * 1.01, 0.25)) == (0.0, 0.0)


@pytest.mark.parametrize("case", [(1, 1, 3, 10), (5, 1, 2, 112), (11, 1, 4, 100), (21, 1, 4, 23)])
def test_a_near_basin_widens_the_std_of_a_weak_pose(case) -> None:
    """Hard-protocol scenes (3 references x 20 matches, 1.5 px noise, 40-60 % outliers) where
    `auto` reported success 0.24-0.33 m off with a std of 0.05-0.07 m, planar poses on 21-28
    inliers that absorbed outliers: a restart landed 0.13-0.25 m away next to the true pose, 1.4-3.5
    inliers' worth of cost above the answer (beyond the rival margin of one). A fifth such scene,
    seed 33 (1, 4, 152), is now refused: a runner-up of its search lands in a basin within one
    inlier's worth (tests/robust/test_pool_basins.py)."""
    seed, mi, ri, trial = case
    sc, opts = hard_protocol_scene(seed, mi, ri, trial, matches=20)
    est = estimate_absolute_pose(sc.query_camera, sc.pairs, "auto", opts)
    assert est.success, est.message  # widened, not refused
    err, _ = pose_errors(est.pose, sc.query_pose)
    assert err <= 3 * est.position_std_m + 0.05, (err, est.position_std_m)
