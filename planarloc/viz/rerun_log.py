"""A Rerun recording (``.rrd``) of a localization run: map cameras, query estimates with their
uncertainty, ground truth and matches. Open it with ``rerun FILE.rrd``.

Needs the optional ``rerun-sdk`` package: ``pip install 'planarloc[rerun]'``.

Entities (timeline ``query`` = query number; the map is static):

    world/map/centers            all map camera centres (points) and their trajectory (line)
    world/map/cameras/<k>        up to ``MAX_MAP_FRUSTA`` map cameras as frusta (pinhole)
    world/query/estimate         the query's estimated camera (frustum) when localized
    world/query/uncertainty      sphere of radius = position std (worst axis) at the estimate
    world/query/truth            ground-truth camera centre, and a line to the estimate
    world/query/references       lines from the estimate (or truth) to the used map images
    query/image                  the query image with its matches: inliers green, outliers red

A stream (``localize --sequence``, ``evaluate --sequential``; :meth:`RerunLogger.log_frame`) uses
the timeline ``stamp`` (the frame's time in seconds):

    world/stream/estimate        the frame's camera (frustum) when it has a usable pose
    world/stream/uncertainty     the 3-sigma ellipsoid of its position (covariance, ROS order)
    world/stream/trajectory      the usable poses so far (line)
    world/stream/truth           ground-truth centre, and a line to the estimate
    stream/status                status, fix, motion, latency
    stream/image                 the frame
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError
from planarloc.map.posed_image import PosedImage
from planarloc.robust.pair_matches import PairMatches
from planarloc.robust.result import PoseEstimate

MAX_MAP_FRUSTA = 200
GREEN, RED, BLUE, GRAY, ORANGE = (26, 152, 80), (215, 48, 39), (49, 130, 189), (150, 150, 150), (253, 174, 97)


def _rerun():  # noqa: ANN202
    try:
        import rerun as rr
    except ImportError:
        raise InputError("--rerun needs the 'rerun-sdk' package: pip install 'planarloc[rerun]'") from None
    return rr


class RerunLogger:
    """Writes a Rerun recording to ``path``; :meth:`close` flushes it (``with closing(...)``)."""

    def __init__(self, path: Path | str, application_id: str = "planarloc") -> None:
        self.rr = _rerun()
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = self.rr.RecordingStream(application_id)
        self.rec.save(str(self.path))
        self.rec.log("world", self.rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)
        self._map_centers: dict[str, np.ndarray] = {}
        self._step = 0
        self._track: list[np.ndarray] = []

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()

    def _camera(
        self,
        entity: str,
        cam_from_world: Pose,
        camera: Camera,
        color: tuple[int, int, int],
        static: bool = False,
    ) -> None:
        rr = self.rr
        world_from_cam = cam_from_world.inverse()
        self.rec.log(
            entity, rr.Transform3D(translation=world_from_cam.t, mat3x3=world_from_cam.R), static=static
        )
        self.rec.log(
            entity,
            rr.Pinhole(
                image_from_camera=camera.K,
                resolution=[camera.width, camera.height],
                camera_xyz=rr.ViewCoordinates.RDF,
                image_plane_distance=0.3,
                color=color,
            ),
            static=static,
        )

    def _truth(self, entity: str, truth: Pose, anchor: np.ndarray | None) -> None:
        """The ground-truth centre at ``entity``, and a line to the estimate's centre ``anchor``."""
        rr = self.rr
        self.rec.log(entity, rr.Points3D([truth.center], colors=GREEN, radii=0.05))
        if anchor is not None:
            self.rec.log(f"{entity}/error", rr.LineStrips3D([[anchor, truth.center]], colors=RED))
        else:
            self.rec.log(f"{entity}/error", rr.Clear(recursive=False))

    def log_map(self, images: Sequence[PosedImage]) -> None:
        """The map cameras (static): all centres, and frusta of up to MAX_MAP_FRUSTA of them."""
        rr = self.rr
        centers = np.array([im.cam_from_world.center for im in images], dtype=float).reshape(-1, 3)
        self._map_centers.update({im.name: c for im, c in zip(images, centers)})
        self.rec.log("world/map/centers", rr.Points3D(centers, colors=GRAY, radii=0.02), static=True)
        if len(centers) > 1:
            self.rec.log("world/map/trajectory", rr.LineStrips3D([centers], colors=GRAY), static=True)
        step = max(1, -(-len(images) // MAX_MAP_FRUSTA))
        for k, im in enumerate(images[::step]):
            self._camera(f"world/map/cameras/{k}", im.cam_from_world, im.camera, GRAY, static=True)

    def log_query(
        self,
        name: str,
        image_path: Path | str | None,
        camera: Camera,
        estimate: PoseEstimate,
        truth: Pose | None = None,
        pairs: Sequence[PairMatches] = (),
        inliers: Sequence[np.ndarray | None] = (),
    ) -> None:
        """One query at the next step of the ``query`` timeline (``inliers[k]``: mask of
        ``pairs[k]``, None if not scored)."""
        rr = self.rr
        self.rec.set_time("query", sequence=self._step)
        self._step += 1
        self.rec.log("query/name", rr.TextDocument(f"{name}: {estimate.status} — {estimate.message}"))
        anchor = None
        if estimate.success and estimate.pose is not None:
            self._camera("world/query/estimate", estimate.pose, camera, BLUE)
            anchor = estimate.pose.center
            std = estimate.position_std_m
            if np.isfinite(std):
                self.rec.log(
                    "world/query/uncertainty",
                    rr.Ellipsoids3D(centers=[anchor], half_sizes=[[std, std, std]], colors=ORANGE),
                )
            else:
                self.rec.log("world/query/uncertainty", rr.Clear(recursive=False))
        else:
            self.rec.log("world/query/estimate", rr.Clear(recursive=True))
            self.rec.log("world/query/uncertainty", rr.Clear(recursive=False))
        if truth is not None:
            self._truth("world/query/truth", truth, anchor)
            anchor = anchor if anchor is not None else truth.center
        refs = [self._map_centers[n] for n in estimate.references if n in self._map_centers]
        if anchor is not None and refs:
            self.rec.log("world/query/references", rr.LineStrips3D([[anchor, c] for c in refs], colors=BLUE))
        if image_path is not None:
            self.rec.log("query/image", rr.EncodedImage(path=str(image_path)))
            q_in, q_out = [], []
            for k, p in enumerate(pairs):
                mask = inliers[k] if k < len(inliers) else None
                inl = mask if mask is not None else np.zeros(len(p.query_points), bool)
                q_in.append(p.query_points[inl])
                q_out.append(p.query_points[~inl])
            if pairs:
                self.rec.log(
                    "query/image/inliers", rr.Points2D(np.concatenate(q_in), colors=GREEN, radii=2.0)
                )
                self.rec.log(
                    "query/image/outliers", rr.Points2D(np.concatenate(q_out), colors=RED, radii=1.5)
                )

    def log_frame(
        self,
        name: str,
        record: dict,
        camera: Camera,
        image_path: Path | str | None = None,
        truth: Pose | None = None,
    ) -> None:
        """One frame of a stream, from its record (:func:`planarloc.localize.records.frame_record`),
        at its stamp."""
        rr = self.rr
        self.rec.set_time("stamp", duration=float(record["stamp"]))
        latency = (record.get("time_s") or {}).get("latency")
        self.rec.log(
            "stream/status",
            rr.TextDocument(
                f"{name}: {record['status']}, fix {record.get('fix_status')}, motion "
                f"{record.get('motion_source')}"
                + ("" if latency is None else f", latency {1e3 * float(latency):.0f} ms")
            ),
        )
        anchor = None
        if record.get("success"):
            pose = Pose.from_quat_wxyz(record["quat_wxyz"], record["t"])
            anchor = pose.center
            self._camera("world/stream/estimate", pose, camera, BLUE)
            self._track.append(anchor)
            self.rec.log("world/stream/trajectory", rr.LineStrips3D([np.array(self._track)], colors=BLUE))
            cov = np.array(record["covariance_xyz_rotvec"], dtype=float)[:3, :3]
            w, V = np.linalg.eigh(0.5 * (cov + cov.T))
            if np.all(np.isfinite(w)):
                if np.linalg.det(V) < 0:
                    V[:, 0] = -V[:, 0]
                q = Rotation.from_matrix(V).as_quat()  # x, y, z, w
                self.rec.log(
                    "world/stream/uncertainty",
                    rr.Ellipsoids3D(
                        centers=[anchor],
                        half_sizes=[3.0 * np.sqrt(np.maximum(w, 0.0))],
                        quaternions=[rr.Quaternion(xyzw=q)],
                        colors=ORANGE,
                    ),
                )
        else:
            self.rec.log("world/stream/estimate", rr.Clear(recursive=True))
            self.rec.log("world/stream/uncertainty", rr.Clear(recursive=False))
        if truth is not None:
            self._truth("world/stream/truth", truth, anchor)
        if image_path is not None:
            self.rec.log("stream/image", rr.EncodedImage(path=str(image_path)))
