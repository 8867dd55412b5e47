"""Visual-odometry relative pose: planar and 6DoF motion, model choice, outliers, failures."""

from __future__ import annotations

import numpy as np
import pytest

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose, rotation_error_deg
from planarloc.geometry.validation import InputError
from planarloc.robust.pose_graph import so3_exp
from planarloc.robust.relative_pose import estimate_relative_pose

CAM = Camera("PINHOLE", 640, 480, (500.0, 500.0, 320.0, 240.0))


def _matches(
    b_from_a: Pose, rng: np.random.Generator, n: int = 150, outliers: float = 0.3, noise: float = 0.5
):
    X = np.column_stack([rng.uniform(-4, 4, n), rng.uniform(-2, 2, n), rng.uniform(4, 12, n)])
    Xb = b_from_a.transform(X)
    pa = X[:, :2] / X[:, 2:] * 500 + [320, 240]
    pb = Xb[:, :2] / Xb[:, 2:] * 500 + [320, 240]
    pa += rng.normal(0, noise, pa.shape)
    pb += rng.normal(0, noise, pb.shape)
    k = int(outliers * n)
    pb[:k] = rng.uniform([0, 0], [640, 480], (k, 2))
    return pa, pb


@pytest.mark.parametrize("model", ["planar", "auto"])
def test_planar_motion_is_recovered_with_outliers(model: str) -> None:
    rng = np.random.default_rng(0)
    truth = Pose.from_center(so3_exp([[0, 0.15, 0]])[0], [0.2, 0, 1.0])
    pa, pb = _matches(truth, rng)
    est = estimate_relative_pose(CAM, CAM, pa, pb, model=model)
    assert est.success and est.model == "planar"
    assert rotation_error_deg(est.pose.R, truth.R) < 0.3
    assert est.pose.t @ (truth.t / np.linalg.norm(truth.t)) > np.cos(np.radians(2))
    assert est.inliers[:45].sum() <= 2 and est.inliers[45:].mean() > 0.9


def test_auto_switches_to_6dof_when_the_motion_is_not_planar() -> None:
    rng = np.random.default_rng(1)
    truth = Pose.from_center(so3_exp([[0.08, 0.1, 0.05]])[0], [0.3, -0.4, 1.0])
    pa, pb = _matches(truth, rng, outliers=0.1)
    est = estimate_relative_pose(CAM, CAM, pa, pb, model="auto")
    assert est.success and est.model == "6dof"
    assert rotation_error_deg(est.pose.R, truth.R) < 0.5
    planar = estimate_relative_pose(CAM, CAM, pa, pb, model="planar")
    assert not planar.success or planar.num_inliers < est.num_inliers / 1.15


def test_failures_are_statuses_and_bad_input_is_an_error() -> None:
    rng = np.random.default_rng(2)
    est = estimate_relative_pose(CAM, CAM, rng.uniform(0, 400, (8, 2)), rng.uniform(0, 400, (8, 2)))
    assert not est.success and est.status == "too_few_matches" and est.pose is None
    est = estimate_relative_pose(
        CAM, CAM, rng.uniform(0, 400, (80, 2)), rng.uniform(0, 400, (80, 2)), model="planar"
    )
    assert not est.success and est.status == "too_few_inliers"
    with pytest.raises(InputError, match="model"):
        estimate_relative_pose(CAM, CAM, np.zeros((20, 2)), np.zeros((20, 2)), model="5pt")
    with pytest.raises(InputError, match="points_b"):
        estimate_relative_pose(CAM, CAM, np.zeros((20, 2)), np.zeros((19, 2)))


def test_each_model_of_auto_gets_its_own_iteration_budget() -> None:
    """``auto`` runs the 6DoF search with the full ``min_iterations`` after the planar one (a
    shared counter left it the planar search's leftovers, none when the planar used them all);
    when the planar inliers are so many that 6DoF cannot reach the margin, it is skipped."""
    from planarloc.robust.options import RansacOptions

    rng = np.random.default_rng(3)
    truth = Pose.from_center(so3_exp([[0.08, 0.1, 0.05]])[0], [0.3, -0.4, 1.0])
    pa, pb = _matches(truth, rng, outliers=0.3)
    opts = RansacOptions(min_iterations=300, max_iterations=300)
    est = estimate_relative_pose(CAM, CAM, pa, pb, model="auto", options=opts)
    assert est.success and est.model == "6dof" and est.stats.iterations == 600
    planar = Pose.from_center(so3_exp([[0, 0.15, 0]])[0], [0.2, 0, 1.0])
    pa, pb = _matches(planar, rng, outliers=0.0, noise=0.1)
    est = estimate_relative_pose(CAM, CAM, pa, pb, model="auto", options=opts)
    assert (
        est.success
        and est.model == "planar"
        and est.stats.searches_skipped == 1
        and est.stats.iterations == 300
    )


def test_minimal_samples_are_distinct_and_uniform() -> None:
    from planarloc.robust.relative_pose import distinct_samples

    s = distinct_samples(np.random.default_rng(0), 20000, 7, 5)
    assert s.shape == (20000, 5) and all(len(set(row)) == 5 for row in s[:2000])
    counts = np.bincount(s.ravel(), minlength=7) / s.size
    np.testing.assert_allclose(counts, 1 / 7, atol=0.01)
    with pytest.raises(InputError, match="at least 5"):
        distinct_samples(np.random.default_rng(0), 3, 4, 5)
