"""evo's APE/RPE of localized queries agree with planarloc's own per-query errors."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from planarloc.geometry.pose import Pose, pose_errors

pytest.importorskip("evo")

from planarloc.evaluation.trajectory import evo_errors  # noqa: E402


def test_ape_equals_the_per_query_errors_and_rpe_the_step_errors():
    rng = np.random.default_rng(0)
    truth = [Pose(Rotation.from_rotvec(rng.normal(size=3)).as_matrix(), rng.normal(size=3)) for _ in range(6)]
    est = [
        Pose(
            Rotation.from_rotvec(rng.normal(size=3) * 0.05).as_matrix() @ p.R, p.t + rng.normal(size=3) * 0.1
        )
        for p in truth
    ]
    q = lambda ps: np.array([p.quat_wxyz for p in ps])  # noqa: E731
    c = lambda ps: np.array([p.center for p in ps])  # noqa: E731
    m = evo_errors(np.arange(6) * 0.1, c(est), q(est), c(truth), q(truth))
    ours = np.array([pose_errors(e, t) for e, t in zip(est, truth)])
    assert m["ape_translation_m"]["max"] == pytest.approx(ours[:, 0].max(), rel=1e-9)
    assert m["ape_translation_m"]["rmse"] == pytest.approx(np.sqrt(np.mean(ours[:, 0] ** 2)), rel=1e-9)
    assert m["ape_rotation_deg"]["max"] == pytest.approx(ours[:, 1].max(), rel=1e-6)
    assert m["rpe_translation_m"]["rmse"] > 0
    exact = evo_errors(np.arange(6) * 0.1, c(truth), q(truth), c(truth), q(truth))
    assert exact["ape_translation_m"]["max"] < 1e-9 and exact["rpe_translation_m"]["max"] < 1e-9
    assert evo_errors([], np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros((0, 4))) == {}
