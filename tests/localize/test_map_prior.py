"""Which map pose prior a query assumes: the map's measurement (planarloc.map.pose_accuracy) with
structure, never below the configured one on 2D-2D constraints alone."""

from __future__ import annotations

from pathlib import Path

import pytest

from planarloc.features.images import read_gray
from planarloc.geometry.pose import pose_errors
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import read_dataset
from planarloc.localize.localizer import CARRYING_3D_INLIERS, Localizer, LocalizerConfig
from planarloc.map.builder import build_map
from planarloc.map.pose_accuracy import MapPoseAccuracy
from planarloc.robust.covariance import _map_prior
from planarloc.robust.options import RansacOptions


@pytest.fixture(scope="module")
def tiny_map(tiny_world: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("prior") / "map.db"
    build_map(read_dataset(tiny_world / "map", "tum"), path)
    return path


def test_the_map_measures_its_exact_poses_and_tracks_queries_use_it(tiny_map: Path, tiny_world: Path) -> None:
    loc = Localizer(tiny_map)
    assert loc.pose_accuracy is not None and loc.pose_accuracy.rotation_std_deg < 0.05
    options = loc.ransac_options
    assert options.map_prior_measured and options.map_rotation_std_deg == loc.pose_accuracy.rotation_std_deg
    assert options.assumed_map_prior == (0.1, 0.02)  # the configured defaults, kept as the 2D-2D floor
    for q in read_dataset(tiny_world / "query", "tum")[:3]:
        est = loc.localize(read_gray(q.path), q.camera)
        if est.success:
            t_err, _ = pose_errors(est.pose, q.cam_from_world)
            assert t_err <= 3 * est.position_std_m + 0.05
            assert est.map_prior is not None
            if est.num_inliers_3d >= CARRYING_3D_INLIERS:
                assert est.map_prior[0] < 0.05
            else:
                assert "judged under the configured map prior" in est.message


def test_without_structure_the_measurement_only_raises_the_prior(tiny_map: Path) -> None:
    loc = Localizer(tiny_map, LocalizerConfig(ransac=RansacOptions(structure="none")))
    assert not loc.ransac_options.map_prior_measured
    assert loc.ransac_options.map_rotation_std_deg == 0.1 and loc.ransac_options.map_position_std_m == 0.02
    loc.pose_accuracy = MapPoseAccuracy(0.5, 0.1, 10, 0.3)  # a map whose poses disagree with its images
    assert loc.ransac_options.map_rotation_std_deg == 0.5 and loc.ransac_options.map_position_std_m == 0.1


def test_configured_prior_ignores_the_measurement(tiny_map: Path) -> None:
    loc = Localizer(tiny_map, LocalizerConfig(map_prior="configured"))
    assert loc.ransac_options == loc.config.ransac
    with pytest.raises(InputError, match="map_prior"):
        LocalizerConfig(map_prior="guessed")


def test_a_pose_on_2d2d_constraints_alone_keeps_the_assumed_prior_as_floor() -> None:
    measured = RansacOptions(
        map_rotation_std_deg=0.002,
        map_position_std_m=0.0003,
        map_prior_measured=True,
        assumed_map_prior=(0.1, 0.02),
    )
    assert _map_prior(measured, n3d=500) == (0.002, 0.0003)
    assert _map_prior(measured, n3d=0) == (0.1, 0.02)
    assumed = RansacOptions(map_rotation_std_deg=0.3, map_position_std_m=0.05)
    assert _map_prior(assumed, n3d=0) == (0.3, 0.05)
