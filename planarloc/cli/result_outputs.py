"""Outputs for robotics tools shared by `localize` and `evaluate`: TUM trajectories for evo,
APE/RPE from evo, match plots (``--plot-matches``) and a Rerun recording (``--rerun``)."""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from planarloc.cli.console import info, note
from planarloc.features.extract import Features, extract_features
from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.io.output import StagedFiles
from planarloc.io.results import query_timestamp
from planarloc.io.tum import tum_trajectory_text
from planarloc.localize.localizer import Localizer
from planarloc.map.posed_image import PosedImage
from planarloc.robust.result import PoseEstimate


def add_output_args(p: argparse.ArgumentParser, tum_help: str) -> None:
    g = p.add_argument_group("outputs for robotics tools")
    g.add_argument("--tum", type=Path, metavar="PATH", help=tum_help)
    g.add_argument(
        "--plot-matches",
        type=Path,
        metavar="DIR",
        help="write per query a PNG: the query beside each reference image, inlier matches green, "
        "outliers red, and the error when ground truth is known (paper Fig. 9)",
    )
    g.add_argument(
        "--rerun",
        type=Path,
        metavar="FILE.rrd",
        help="log map cameras, estimates with uncertainty, ground truth and matches to a Rerun "
        "recording (needs: pip install 'planarloc[rerun]'; view with `rerun FILE.rrd`)",
    )


class EstimateOutputs:
    """Match plots and Rerun logging of each estimate (either may be off)."""

    def __init__(self, plot_dir: Path | None, rerun_path: Path | None) -> None:
        from planarloc.viz.matches import MatchPlotter

        self.plotter = MatchPlotter(plot_dir) if plot_dir is not None else None
        self.rerun = None
        if rerun_path is not None:
            from planarloc.viz.rerun_log import RerunLogger

            self.rerun = RerunLogger(rerun_path)
        self._map_logged = False

    @property
    def active(self) -> bool:
        return self.plotter is not None or self.rerun is not None

    def add(
        self,
        loc: Localizer,
        name: str,
        path: Path,
        camera: Camera,
        estimate: PoseEstimate,
        truth: Pose | None = None,
        features: Features | None = None,
    ) -> None:
        if not self.active:
            return
        from planarloc.viz.matches import query_pairs

        if features is None:
            features = extract_features(loc.prepare(path, camera).image, loc.features)
        if self.plotter is not None:
            self.plotter.plot(loc, name, path, camera, features, estimate, truth)
        if self.rerun is not None:
            if not self._map_logged:
                self.rerun.log_map(loc.map_images)
                self._map_logged = True
            pairs, inliers = query_pairs(loc, features, camera, estimate)
            self.rerun.log_query(name, path, camera, estimate, truth, pairs, inliers)

    def __call__(self, loc: Localizer, query: PosedImage, features: Features, estimate: PoseEstimate) -> None:
        self.add(loc, query.name, query.path, query.camera, estimate, query.cam_from_world, features)

    def close(self) -> None:
        if self.rerun is not None:
            self.rerun.close()
            info(f"wrote {self.rerun.path}")
        if self.plotter is not None and self.plotter.written:
            info(f"wrote {len(self.plotter.written)} match plots to {self.plotter.out_dir}/")


def _world_from_cam(quat_wxyz: Sequence[float], center: Sequence[float]) -> Pose:
    """From a ``cam_from_world`` rotation (w, x, y, z) and the camera centre."""
    return Pose(Pose.from_quat_wxyz(quat_wxyz, np.zeros(3)).R.T, np.asarray(center, dtype=float))


def _tum_rows(
    results: Sequence, source_stamps: Mapping[str, float | None] | None = None
) -> tuple[np.ndarray, list]:
    """The localized results in time order with their TUM times: the source's stamp of each query
    (``source_stamps``, by name) when the source has one for every one of them, else the result's
    own (:func:`planarloc.io.results.query_timestamp`)."""
    found = {r.name: source_stamps.get(r.name) for r in results if r.success} if source_stamps else {}
    use_source = bool(found) and all(t is not None for t in found.values())
    rows = sorted(
        (query_timestamp(r.name, found[r.name] if use_source else r.timestamp, i), r)
        for i, r in enumerate(results)
        if r.success
    )
    ts = np.array([t for t, _ in rows])
    if len(ts) > 1 and np.any(np.diff(ts) <= 0):
        dup = ts[1:][np.diff(ts) <= 0][0]
        raise ValueError(
            f"--tum: two localized queries share the timestamp {dup:.6f}; TUM files need unique times"
        )
    return ts, [r for _, r in rows]


def write_evaluation_tum(
    out_dir: Path, results: Sequence, source_stamps: Mapping[str, float | None] | None = None
) -> dict:
    """``out_dir/estimate.txt`` and ``out_dir/groundtruth.txt`` (localized queries only), and
    evo's APE/RPE of them (``{}`` if nothing was localized; a note if evo is missing).
    ``source_stamps``: the dataset's time of each query by name, for results timed otherwise
    (a simulated stream's clock); the files then carry the dataset's times."""
    ts, rows = _tum_rows(results, source_stamps)
    est = [_world_from_cam(r.estimate_quat_wxyz, r.estimate_center) for r in rows]
    gt = [_world_from_cam(r.truth_quat_wxyz, r.truth_center) for r in rows]
    out_dir = Path(out_dir)
    both = StagedFiles()  # the pair is replaced together, or neither
    both.add(out_dir / "estimate.txt", tum_trajectory_text(out_dir / "estimate.txt", ts, est))
    both.add(out_dir / "groundtruth.txt", tum_trajectory_text(out_dir / "groundtruth.txt", ts, gt))
    both.commit()
    info(
        f"wrote {out_dir}/estimate.txt and groundtruth.txt ({len(rows)} localized queries); "
        f"try: evo_ape tum {out_dir}/groundtruth.txt {out_dir}/estimate.txt"
    )
    if not rows:
        return {}
    try:
        from planarloc.evaluation.trajectory import evo_errors

        metrics = evo_errors(
            ts,
            np.array([r.estimate_center for r in rows]),
            np.array([r.estimate_quat_wxyz for r in rows]),
            np.array([r.truth_center for r in rows]),
            np.array([r.truth_quat_wxyz for r in rows]),
        )
    except ValueError as exc:  # evo not installed: the files are still useful
        note(str(exc))
        return {"note": str(exc)}
    ape, rpe = metrics["ape_translation_m"], metrics["rpe_translation_m"]
    info(
        f"evo: APE translation rmse {ape['rmse']:.3f} m (max {ape['max']:.3f} m), APE rotation rmse "
        f"{metrics['ape_rotation_deg']['rmse']:.2f}°"
        + (f", RPE translation rmse {rpe['rmse']:.3f} m" if rpe else "")
    )
    return metrics
