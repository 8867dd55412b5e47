"""Absolute fixes of a stream's frames, computed in the calling thread or in a background worker.

A *fix job* is one frame (its gray pixels, camera and gravity) with the pose the stream predicted
for it; a *fix result* is what the single-frame localizer made of it, gated against that
prediction (:meth:`FixSolver.solve`): the map images nearest to a usable prediction first, then
global retrieval (VLAD, then again from the map images nearest to that fix) when there is no
usable prediction or the first attempt failed or was rejected. A fix is accepted when its
Mahalanobis distance to the prediction under the summed covariances passes the χ²(6) gate.

Two schedulers run the jobs for :class:`planarloc.localize.sequence.SequenceLocalizer`:

- :class:`ImmediateFixes` (``SequenceConfig.fixes = "wait"``): the job runs in the call that
  submits it, on the caller's :class:`Localizer`; its result is handed back ``fix_delay`` frames
  later. Deterministic: for tests and offline evaluation (``fix_every=1, fix_delay=0`` is the
  per-frame design: every frame waits for its own fix).
- :class:`BackgroundFixes` (``"background"``): one worker thread with its own
  :class:`Localizer` on the same map file (SQLite connections belong to one thread); at most one
  job in flight. SIFT (OpenCV) and the descriptor matching (matrix products) release the GIL for
  most of a fix's time, so the frame path keeps running while a fix is computed (the
  numba kernels of the absolute-pose RANSAC, a few ms of a fix, hold it).

An accepted fix (and a rejected global one) also brings the world points its frame sees
(:meth:`FixSolver.world_points`), tracked on through the frames that came since
(:func:`~planarloc.localize.tracking.track_through` over the stream's
:class:`~planarloc.localize.tracking.FrameHistory`; by the worker for background fixes), so that the stream
can go on tracking them from its current frame.

Fix jobs detect their features on the image downscaled to at most ``SequenceConfig.fix_resize_max``
pixels (640): SIFT doubles the image for its first octave, and on ``kitti_seq2`` (map every 4th
frame, the 2 map images nearest to each of the 38 other frames) half resolution takes 39 ms of
CPU for SIFT and 55 ms for the fix instead of 170 and 115 ms, with the same errors (median
1.3 cm, at most 3.3 cm, no failure); a fix comes back within one or two frames instead of six.

Covariance of a fix (the single-frame estimator's ``position_std_m`` is the std along its worst
axis): position ``(fix_std_scale · position_std_m)² I`` (floored at ``min_fix_std_m``); rotation
``σ_R² I`` with ``σ_R² = σ_px² / (f² N) + σ_map²`` — ``N`` bearings with ``σ_px`` pixel noise fix a
rotation to about ``σ_px / (f √N)`` radians, and the map's own rotation error ``σ_map``
(``RansacOptions.map_rotation_std_deg``) adds to it — floored at ``min_rotation_std_deg``, plus the
estimate's own rotation covariance (per axis) scaled like its position.
Order ``(rotation, camera centre)`` of the pose graph (docs/conventions.md, "Pose covariances").
"""

from __future__ import annotations

import atexit
import logging
import queue
import threading
import time
import weakref
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.stats import chi2

from planarloc.features.extract import Features, extract_features
from planarloc.geometry.camera import Camera
from planarloc.geometry.epipolar import triangulate_points
from planarloc.geometry.pose import Pose
from planarloc.geometry.pose_covariance import graph_covariance
from planarloc.localize.localizer import Localizer
from planarloc.localize.stream_config import SequenceConfig
from planarloc.localize.tracking import FrameHistory, TrackedPoints, TrackerOptions, track_through
from planarloc.robust.pair_matches import PairMatches
from planarloc.robust.pose_graph import so3_log
from planarloc.robust.result import PoseEstimate

logger = logging.getLogger(__name__)

#: world points of a fix triangulated between the query and a map image need this angle (degrees)
MIN_POINT_ANGLE_DEG = 2.0
#: a global fix matches this many retrieved map images first (the nearest-image fix refines
#: it): on KITTI (map every 4th frame) the fix and its refinement cost 64 instead of 116 ms of
#: CPU on ``kitti_seq1`` and 32 instead of 58 on ``kitti_seq2`` with the top 3 instead of the
#: top 5, with the same errors after refinement (median 1.3 vs 1.6 cm, 1.5 vs 1.5 cm)
GLOBAL_TOP_N = 3


def pose_difference(a: Pose, b: Pose) -> np.ndarray:
    """(6,) ``(log(R_a R_bᵀ), c_a − c_b)``: ``a`` in the tangent space of ``b`` (pose-graph order)."""
    return np.concatenate([so3_log((a.R @ b.R.T)[None])[0], a.center - b.center])


def mahalanobis_sq(a: Pose, cov_a: np.ndarray, b: Pose, cov_b: np.ndarray) -> float:
    """Squared Mahalanobis distance of two independent pose estimates (covariances (6, 6),
    :func:`pose_difference` order)."""
    e = pose_difference(a, b)
    S = cov_a + cov_b
    try:
        return float(e @ np.linalg.solve(S, e))
    except np.linalg.LinAlgError:
        return float("inf")


@dataclass(frozen=True)
class FixAttempt:
    """One absolute fix of a frame: the single-frame estimate, its covariance (None: failed or
    without a usable std), the retrieval that gave its references, its distance to the prediction."""

    estimate: PoseEstimate
    covariance: np.ndarray | None
    global_retrieval: bool
    mahalanobis_sq: float = float("nan")
    pairs: list[PairMatches] | None = None  # the matches it was estimated from (``estimate.references``)

    @property
    def pose(self) -> Pose:
        if self.estimate.pose is None:
            raise ValueError("a failed fix has no pose")
        return self.estimate.pose

    def report(self) -> dict:
        """The entry of ``SequenceEstimate.rejected``."""
        return {
            "center": [float(v) for v in self.pose.center],
            "mahalanobis_sq": self.mahalanobis_sq,
            "retrieval": "global" if self.global_retrieval else "local",
        }


@dataclass
class FixOutcome:
    """What the absolute fixes of one frame gave: the accepted pose and covariance (None: no
    fix accepted), the rejected attempts, the last estimate tried and its status
    (``"accepted"``, ``"rejected"``, ``"failed"`` or ``"none"``)."""

    accepted: tuple[Pose, np.ndarray] | None = None
    rejected: list[FixAttempt] = field(default_factory=list)
    last: PoseEstimate | None = None
    last_pairs: list[PairMatches] | None = None  # the matches ``last`` was estimated from
    status: str = "none"
    mahalanobis_sq: float = float("nan")
    global_retrieval: bool = False


@dataclass(frozen=True, eq=False)
class FixJob:
    """One frame to fix.

    Attributes:
        stamp: the frame's stamp (names its node in the stream's window).
        image: (H, W) uint8 gray pixels.
        camera: the frame's intrinsics.
        gravity: (3,) unit gravity in the camera frame, or None.
        prediction: the frame's predicted ``cam_from_world`` and its (6, 6) covariance (pose-graph
            order), or None (nothing to predict from: the stream starts).
        usable: the prediction may choose the map images to match (its position std is at most
            ``SequenceConfig.lost_std_m`` and no kidnap is suspected); else global retrieval.
        position_std_m: the prediction's position std (worst axis).
        generation: the stream's generation (a reset discards older results).
    """

    stamp: float
    image: np.ndarray
    camera: Camera
    gravity: np.ndarray | None
    prediction: tuple[Pose, np.ndarray] | None
    usable: bool
    position_std_m: float
    generation: int = 0


@dataclass(frozen=True, eq=False)
class FixResult:
    """A job's outcome: :class:`FixOutcome`, the world points its frame sees (those of an
    accepted fix, or of a rejected global one, from which a confirmed kidnap re-initialises;
    tracked on to the latest frame they could be: ``points.stamp``), the seconds it took (wall and
    CPU of its thread)."""

    stamp: float
    outcome: FixOutcome
    points: TrackedPoints | None
    seconds: float
    generation: int
    cpu_s: float = 0.0

    def tracked_to(self, history: FrameHistory, options: TrackerOptions) -> FixResult:
        """The result with its points tracked on through the frames ``history`` holds after theirs."""
        if self.points is None:
            return self
        frames = history.since(self.points.stamp)
        if len(frames) < 2:
            return self
        return FixResult(
            self.stamp,
            self.outcome,
            track_through(frames, self.points, options),
            self.seconds,
            self.generation,
            self.cpu_s,
        )


class FixSolver:
    """Computes fix jobs against one map (module docstring).

    Args:
        localizer: the single-frame localizer (its map and configuration).
        config: the stream's :class:`~planarloc.localize.sequence.SequenceConfig`.
    """

    def __init__(self, localizer: Localizer, config: SequenceConfig) -> None:
        self.localizer = localizer
        self.config = config
        posed = localizer.map_images
        self._map_names = [p.name for p in posed]
        self._map_centers = np.array([p.cam_from_world.center for p in posed]).reshape(-1, 3)
        self._map_R = np.array([p.cam_from_world.R for p in posed]).reshape(-1, 3, 3)
        self.gate = float(chi2.ppf(config.gate_probability, 6))
        self._map_rotation_std = np.radians(localizer.ransac_options.map_rotation_std_deg)
        limit = config.fix_resize_max
        own = localizer.features.resize_max
        self.features = (
            localizer.features
            if limit is None or (own is not None and own <= limit)
            else replace(localizer.features, resize_max=limit)
        )

    def references_near(self, pose: Pose, position_std_m: float) -> list[str] | None:
        """The ``local_top_n`` map images nearest to ``pose`` (distance plus 1 m per 30° of
        viewing-direction difference); None when fewer than 2 qualify (use global retrieval)."""
        cfg = self.config
        dist = np.linalg.norm(self._map_centers - pose.center, axis=1)
        cos = (np.einsum("nij,ij->n", self._map_R, pose.R) - 1.0) / 2.0
        angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        ok = (dist <= max(cfg.local_radius_m, 3.0 * position_std_m)) & (angle <= cfg.local_max_angle_deg)
        idx = np.flatnonzero(ok)
        if len(idx) < 2:
            return None
        score = dist[idx] + angle[idx] / 30.0
        return [self._map_names[i] for i in idx[np.argsort(score)[: cfg.local_top_n]]]

    def fix_covariance(self, est: PoseEstimate, camera: Camera) -> np.ndarray | None:
        """(6, 6) covariance of a successful fix (module docstring), None if it has no usable std."""
        cfg = self.config
        std = float(est.position_std_m)
        if not np.isfinite(std):
            return None
        scale = cfg.fix_std_scale if int(est.num_inliers_3d) >= cfg.min_inliers_3d else cfg.fix_std_scale_2d
        pos = max(scale * std, cfg.min_fix_std_m)
        n = max(int(est.num_inliers) + int(est.num_inliers_3d), 1)
        f = float(np.mean(camera.focal))
        rot = np.sqrt((cfg.pixel_std / f) ** 2 / n + self._map_rotation_std**2)
        rot = max(rot, np.radians(cfg.min_rotation_std_deg))
        cov = np.diag([rot**2] * 3 + [pos**2] * 3)
        if est.covariance is not None and est.pose is not None and np.all(np.isfinite(est.covariance)):
            # the estimate's own rotation covariance, per axis (yaw is usually the best known)
            cov[:3, :3] += scale**2 * graph_covariance(est.pose, est.covariance)[:3, :3]
        return cov

    def _fix(
        self, features: Features, camera: Camera, references: list[str] | None, gravity: np.ndarray | None
    ) -> tuple[PoseEstimate, list[PairMatches]]:
        """Single-frame fix from ``references``; with None, global retrieval followed by a
        second estimate from the map images nearest to the first (nearer references, better
        conditioned geometry: on KITTI the 2 nearest map images give 2-5x smaller errors than
        the VLAD top 5), kept when it lies within ``refix_radius_m`` of the first. Global
        retrieval matches the ``GLOBAL_TOP_N`` most similar map images first, all ``top_n`` of
        the localizer only when that fails. Returns the estimate and the matches it came from."""
        localize = self.localizer.localize_pairs
        if references is None and self.localizer.config.top_n > GLOBAL_TOP_N:
            est, pairs = localize(
                features, camera, self.localizer.retrieve(features, GLOBAL_TOP_N), gravity=gravity
            )
            if not est.success or est.pose is None:
                est, pairs = localize(features, camera, None, gravity=gravity)
        else:
            est, pairs = localize(features, camera, references, gravity=gravity)
        if references is not None or not est.success or est.pose is None:
            return est, pairs
        near = self.references_near(est.pose, 0.0)
        cov = self.fix_covariance(est, camera)
        if near is None or cov is None or set(near) <= set(est.references):
            return est, pairs
        again, again_pairs = localize(features, camera, near, gravity=gravity)
        if again.success and again.pose is not None:
            cov2 = self.fix_covariance(again, camera)
            if (
                cov2 is not None
                and np.linalg.norm(again.pose.center - est.pose.center) <= self.config.refix_radius_m
            ):
                return again, again_pairs
        return est, pairs

    def attempts(
        self, features: Features, camera: Camera, gravity: np.ndarray | None, job: FixJob
    ) -> FixOutcome:
        """A fix from the map images near a usable prediction, else (or when it is rejected or
        fails) from global retrieval; the first that passes the gate is accepted."""
        near = (
            self.references_near(job.prediction[0], job.position_std_m)
            if job.usable and job.prediction
            else None
        )
        out = FixOutcome()
        for references in ([near] if near is not None else []) + [None]:  # None: global retrieval
            out.global_retrieval |= references is None
            est, pairs = self._fix(features, camera, references, gravity)
            out.last, out.last_pairs = est, pairs
            pose = est.pose if est.success else None
            cov = self.fix_covariance(est, camera) if pose is not None else None
            if pose is None or cov is None:
                out.status = "failed"
                continue
            if job.prediction is None:
                out.accepted, out.status = (pose, cov), "accepted"
                break
            out.mahalanobis_sq = mahalanobis_sq(pose, cov, *job.prediction)
            if out.mahalanobis_sq <= self.gate:
                out.accepted, out.status = (pose, cov), "accepted"
                break
            out.status = "rejected"
            out.rejected.append(FixAttempt(est, cov, references is None, out.mahalanobis_sq, pairs))
        return out

    def world_points(
        self,
        features: Features,
        camera: Camera,
        est: PoseEstimate,
        stamp: float,
        pairs: list[PairMatches] | None = None,
    ) -> TrackedPoints | None:
        """The fix's inlier query keypoints and their world points: the map's 3D points (local
        structure, depth) where it has them, else triangulated between the query (at the fix)
        and the map image (at least ``MIN_POINT_ANGLE_DEG`` apart); one per keypoint. None if
        the matches cannot be recovered. ``pairs``: the matches ``est`` came from (matched
        again when None)."""
        if est.pose is None:
            return None
        if pairs is None:
            pairs, names = self.localizer.pairs_for(
                features, est.references, camera, keypoint_budget=est.keypoint_budget
            )
            if names != list(est.references):
                return None
        if len(est.inliers) != len(pairs):
            return None
        ids, pixels, points = [], [], []
        for pair, mask in zip(pairs, est.inliers):
            m = np.asarray(mask, bool)
            if len(m) != len(pair.query_points) or not m.any():
                continue
            X, angle = triangulate_points(
                (est.pose.R, est.pose.t),
                (pair.ref_pose.R, pair.ref_pose.t),
                camera.bearings_from_img(pair.query_points[m]),
                pair.ref_camera.bearings_from_img(pair.ref_points[m]),
            )
            X[~(angle >= MIN_POINT_ANGLE_DEG)] = np.nan
            if pair.ref_points3d is not None:
                known = np.isfinite(pair.ref_points3d[m]).all(axis=1)
                X[known] = pair.ref_points3d[m][known]
            ok = np.isfinite(X).all(axis=1)
            qi = pair.query_indices[m] if pair.query_indices is not None else np.full(int(m.sum()), -1)
            ids.append(qi[ok])
            pixels.append(pair.query_points[m][ok])
            points.append(X[ok])
        if not ids:
            return None
        ids_all = np.concatenate(ids)
        _, first = np.unique(ids_all, return_index=True)
        keep = np.sort(first) if (ids_all >= 0).all() else np.arange(len(ids_all))
        return TrackedPoints(
            stamp, np.concatenate(pixels)[keep].astype(np.float32), np.concatenate(points)[keep]
        )

    def solve(self, job: FixJob) -> FixResult:
        """Run one job: features, the attempts, and the world points of an accepted fix."""
        t0, cpu0 = time.perf_counter(), time.thread_time()
        features = extract_features(job.image, self.features)
        outcome = self.attempts(features, job.camera, job.gravity, job)
        points = None
        if outcome.accepted is not None and outcome.last is not None:
            points = self.world_points(features, job.camera, outcome.last, job.stamp, outcome.last_pairs)
        elif outcome.rejected and outcome.rejected[-1].global_retrieval:  # a kidnap may restart from it
            last = outcome.rejected[-1]
            points = self.world_points(features, job.camera, last.estimate, job.stamp, last.pairs)
        return FixResult(
            job.stamp, outcome, points, time.perf_counter() - t0, job.generation, time.thread_time() - cpu0
        )


class ImmediateFixes:
    """Fixes in the calling thread; a result is handed back ``delay`` frames after its job,
    its points tracked on to the latest frame of ``history``."""

    def __init__(self, solver: FixSolver, delay: int, history: FrameHistory, options: TrackerOptions) -> None:
        self.solver = solver
        self.delay = int(delay)
        self._history, self._options = history, options
        self._pending: list[tuple[int, FixResult]] = []

    @property
    def busy(self) -> bool:
        return bool(self._pending)

    def submit(self, job: FixJob, frame: int) -> None:
        self._pending.append((frame + self.delay, self.solver.solve(job)))

    def collect(self, frame: int, wait: bool = False) -> list[FixResult]:
        """Results due at ``frame`` (all pending with ``wait``)."""
        due = [r.tracked_to(self._history, self._options) for d, r in self._pending if wait or d <= frame]
        self._pending = [(d, r) for d, r in self._pending if not (wait or d <= frame)]
        return due

    def solve_now(self, job: FixJob) -> FixResult:
        return self.solver.solve(job).tracked_to(self._history, self._options)

    def discard(self) -> None:
        """Forget the results not handed back yet (the stream was reset)."""
        self._pending = []

    def close(self) -> None:
        self._pending = []


#: workers still running; stopped at exit (a daemon thread killed inside OpenCV aborts the process)
_WORKERS: weakref.WeakSet[BackgroundFixes] = weakref.WeakSet()


@atexit.register
def _stop_workers() -> None:
    for worker in list(_WORKERS):
        worker.close()


class BackgroundFixes:
    """Fixes in one worker thread with its own :class:`Localizer` (module docstring).

    An exception raised by a job (e.g. a damaged map) is raised again by the next
    :meth:`collect` or :meth:`solve_now` in the calling thread. :meth:`close` stops the thread
    (also done at interpreter exit for workers left open).
    """

    def __init__(
        self, localizer: Localizer, config: SequenceConfig, history: FrameHistory, options: TrackerOptions
    ) -> None:
        self._path = localizer.db.path
        self._localizer_config = localizer.config
        self._config = config
        self._history, self._options = history, options
        self._jobs: queue.Queue[FixJob | None] = queue.Queue()
        self._results: queue.Queue[FixResult | BaseException] = queue.Queue()
        self._in_flight = 0
        self._warm = threading.Event()  # set once the worker's localizer has warmed up (or failed to open)
        self._thread = threading.Thread(target=self._run, name="planarloc-fixes", daemon=True)
        self._thread.start()
        _WORKERS.add(self)

    def _run(self) -> None:
        try:
            solver = FixSolver(Localizer(self._path, self._localizer_config), self._config)
            # Its own localizer's first query is ~10x slower than the next (kernels, the map
            # images' pair matches): paid now, while the caller opens its camera, not by a frame.
            solver.localizer.warm_up()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            self._results.put(exc)
            return
        finally:
            self._warm.set()
        while True:
            job = self._jobs.get()
            if job is None:
                return
            try:
                self._results.put(solver.solve(job).tracked_to(self._history, self._options))
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
                logger.debug("fix job failed: %s", exc)
                self._results.put(exc)

    @property
    def busy(self) -> bool:
        return self._in_flight > 0

    def wait_warm(self, timeout: float | None = None) -> bool:
        """Wait until the worker's localizer has warmed up; False on timeout."""
        return self._warm.wait(timeout)

    def submit(self, job: FixJob, frame: int) -> None:
        if not self._thread.is_alive():
            self._take(block=False)  # the worker's error, if it left one
            raise RuntimeError("the fix worker has stopped")
        self._in_flight += 1
        self._jobs.put(job)

    def _take(self, block: bool) -> list[FixResult]:
        """The results in the queue (with ``block``: until none is in flight)."""
        out = []
        while not self._results.empty() or (block and self._in_flight > 0):
            item = self._results.get()
            self._in_flight = max(0, self._in_flight - 1)
            if isinstance(item, BaseException):
                raise item
            out.append(item)
        return out

    def collect(self, frame: int, wait: bool = False) -> list[FixResult]:
        """The results that have arrived (with ``wait``: also the one in flight)."""
        return self._take(block=wait)

    def discard(self) -> None:
        """Nothing to do: a result still in flight comes back with an old generation and is dropped."""

    def solve_now(self, job: FixJob) -> FixResult:
        """Run ``job`` and wait for it (results still in flight are dropped: the caller has
        no window for them)."""
        self._take(block=True)
        self.submit(job, 0)
        return self._take(block=True)[-1]

    def close(self) -> None:
        _WORKERS.discard(self)
        if self._thread.is_alive():
            self._jobs.put(None)
            self._thread.join(timeout=30.0)
