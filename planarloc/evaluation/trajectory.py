"""Trajectory errors of the localized queries computed by evo (Grupp, "evo", 2017).

planarloc's own numbers (success rates at the paper's thresholds, median errors) come from
:mod:`planarloc.evaluation.queries`. This module adds what evo already computes — absolute
and relative pose errors (APE, RPE) — by calling evo as a library on the same poses that
``evaluate --tum DIR`` writes, so that ``evo_ape tum DIR/groundtruth.txt DIR/estimate.txt``
prints the same APE. No alignment (no ``-a``/``-s``): estimates and ground truth are in the
map's world frame, and aligning would hide localization errors.

evo is optional: ``pip install 'planarloc[evo]'``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from planarloc.geometry.validation import InputError


def _evo():  # noqa: ANN202
    try:
        from evo.core import metrics, sync, trajectory
    except ImportError:
        raise InputError("APE/RPE need the 'evo' package: pip install 'planarloc[evo]'") from None
    return metrics, sync, trajectory


def _trajectory(
    trajectory_mod,
    timestamps: np.ndarray,
    centers: np.ndarray,  # noqa: ANN001, ANN202
    quat_wxyz_cam_from_world: np.ndarray,
):
    # world_from_cam: position = centre, rotation = inverse of cam_from_world (conjugate quaternion)
    q = np.asarray(quat_wxyz_cam_from_world, dtype=float) * np.array([1.0, -1.0, -1.0, -1.0])
    return trajectory_mod.PoseTrajectory3D(
        positions_xyz=np.asarray(centers, dtype=float),
        orientations_quat_wxyz=q,
        timestamps=np.asarray(timestamps, dtype=float),
    )


def evo_errors(
    timestamps: Sequence[float] | np.ndarray,
    estimate_centers: np.ndarray,
    estimate_quat_wxyz: np.ndarray,
    truth_centers: np.ndarray,
    truth_quat_wxyz: np.ndarray,
) -> dict:
    """APE (translation in m, rotation angle in degrees) and RPE (translation between
    consecutive localized queries, m) as evo computes them.

    Args:
        timestamps: (N,) seconds, strictly increasing.
        estimate_centers, truth_centers: (N, 3) camera centres in the world (metres).
        estimate_quat_wxyz, truth_quat_wxyz: (N, 4) ``cam_from_world`` rotations (w, x, y, z).

    Returns:
        ``{"ape_translation_m": stats, "ape_rotation_deg": stats, "rpe_translation_m": stats}``
        with evo's statistics (rmse, mean, median, std, min, max, sse); RPE is None for fewer
        than 2 poses. Empty dict for N = 0.
    """
    metrics, _sync, trajectory = _evo()
    ts = np.asarray(timestamps, dtype=float).reshape(-1)
    if len(ts) == 0:
        return {}
    est = _trajectory(trajectory, ts, estimate_centers, estimate_quat_wxyz)
    ref = _trajectory(trajectory, ts, truth_centers, truth_quat_wxyz)
    out: dict[str, dict[str, float] | None] = {}
    for key, relation in (
        ("ape_translation_m", metrics.PoseRelation.translation_part),
        ("ape_rotation_deg", metrics.PoseRelation.rotation_angle_deg),
    ):
        ape = metrics.APE(relation)
        ape.process_data((ref, est))
        out[key] = {k: float(v) for k, v in ape.get_all_statistics().items()}
    if len(ts) >= 2:
        rpe = metrics.RPE(metrics.PoseRelation.translation_part, delta=1, delta_unit=metrics.Unit.frames)
        rpe.process_data((ref, est))
        out["rpe_translation_m"] = {k: float(v) for k, v in rpe.get_all_statistics().items()}
    else:
        out["rpe_translation_m"] = None
    return out
