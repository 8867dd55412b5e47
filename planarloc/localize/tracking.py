"""Frame-to-frame tracking for streams: corners tracked by pyramidal Lucas-Kanade, the relative
pose of the two frames from the tracks, and the metric scale of that motion from world points.

This is the cheap part of :class:`planarloc.localize.sequence.SequenceLocalizer`'s frame path
(about 30 ms of CPU for a 1241×376 frame, against ~270 ms for SIFT, matching and an absolute
fix at full resolution): corners are detected on a grid over the previous frame (Shi-Tomasi, a few per cell so
that they spread over the whole image), tracked into the current frame by
``cv2.calcOpticalFlowPyrLK`` and fed to :func:`planarloc.robust.relative_pose.estimate_relative_pose`
(planar 2-point and 5-point hypotheses, Sampson error in pixels).

Lucas-Kanade tracks are precise (a fraction of a pixel) but some are consistently wrong
(foliage, repeated texture): with the absolute-pose threshold of 2 px a wrong forward motion
can win over the true one on KITTI. The relative pose is therefore scored with a 1 px threshold
and at least 300 samples (:data:`VO_MIN_ITERATIONS`): on ``kitti_seq2``/``kitti_seq1`` (map every
4th frame, the 37 motions between the other frames) the direction of travel is then off by
0.7° median and 3.6° at most.

A relative pose from 2D-2D tracks has no scale, and a speed measured over absolute fixes that
arrive every few frames lags behind a car that brakes or accelerates (KITTI: 9.5 to 12.7 m/s in
2 s). The metric part comes from **tracked world points**: the inlier keypoints of an absolute fix
whose 3D points the map knows (its local structure or depth) are tracked from frame to frame,
forward and backward (a track that does not come back to within ``FB_MAX_ERROR_PX`` is dropped:
keypoints are blobs, not corners, and drift), and each frame's camera centre is solved from
them with the rotation of the prediction (:func:`center_from_points`). On ``kitti_seq2`` and
``kitti_seq1`` this centre is within 0.15 m of the truth for 5 frames after the fix in 9 of 10
cases (the truth's rotation given).

References:
    Lucas, Kanade, "An Iterative Image Registration Technique with an Application to Stereo
    Vision", IJCAI 1981; Bouguet, "Pyramidal Implementation of the Lucas Kanade Feature Tracker",
    Intel 2000 (``cv2.calcOpticalFlowPyrLK``); Shi, Tomasi, "Good Features to Track", CVPR 1994.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.epipolar import essential_from_relpose
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_integer, check_positive
from planarloc.robust.options import RansacOptions
from planarloc.robust.pose_graph import so3_exp
from planarloc.robust.relative_pose import RelativePoseEstimate, direction_basis, estimate_relative_pose
from planarloc.robust.status import Status

#: a grid cell is about this many pixels wide and high (corners are spread over the cells)
CELL_PX = 120
#: Shi-Tomasi quality level (fraction of the best corner's score) and minimum corner distance
CORNER_QUALITY, CORNER_MIN_DISTANCE_PX = 0.01, 8
#: minimal samples of the relative-pose RANSAC on tracks (see the module docstring)
VO_MIN_ITERATIONS, VO_MAX_ITERATIONS = 300, 1000
#: the residual std behind a relative pose's covariance: at least this (pixels), times this
MIN_TRACK_STD_PX, TRACK_STD_INFLATION = 0.3, 2.0
#: forward-backward check of tracked world points (pixels)
FB_MAX_ERROR_PX = 0.5
#: a pose from tracked points needs this many inlier points and this inlier fraction
MIN_POINTS, MIN_POINT_INLIER_FRACTION = 20, 0.6
#: PnP on tracked points: inlier threshold (pixels) and RANSAC iterations
PNP_THRESHOLD_PX, PNP_ITERATIONS = 2.0, 100


@dataclass(frozen=True)
class TrackerOptions:
    """Settings of :class:`FrameTracker` (``SequenceConfig`` holds the stream's).

    Attributes:
        corners: corners detected per frame (at most; spread over cells of ~``CELL_PX`` pixels).
        window_px: Lucas-Kanade window (square, pixels). 11: on ``kitti_seq2``/``kitti_seq1`` (the 74
            motions between the streamed frames) tracking the corners takes 6 ms of CPU instead
            of 15 with a window of 15, and the direction of travel is off by 0.55° median, 3.5°
            at most (0.59°, 2.6° with 15; the rotation 0.21° at most, 0.25° with 15).
        levels: pyramid levels above the image (4: motions up to ~150 px, KITTI at 2 m/frame).
        threshold_px: inlier threshold of the relative pose on the tracks (Sampson error, px).
        model: ``"planar"``, ``"6dof"`` or ``"auto"`` (:func:`estimate_relative_pose`).
        min_inliers: fewer inlier tracks: no relative pose.
        min_inlier_ratio: inlier tracks below this fraction of the tracked corners: no relative
            pose (Lucas-Kanade lost the motion, e.g. a fast turn: on a generated office world with
            16-52° between frames the "poses" it gave had 5-16 % inliers and were 28-53° off;
            KITTI's motions have 50-80 %).
    """

    corners: int = 480
    window_px: int = 11
    levels: int = 4
    threshold_px: float = 1.0
    model: str = "auto"
    min_inliers: int = 20
    min_inlier_ratio: float = 0.3

    def __post_init__(self) -> None:
        for name in ("corners", "window_px", "levels", "min_inliers"):
            check_integer(f"TrackerOptions.{name}", getattr(self, name), 0 if name == "levels" else 3)
        check_positive("TrackerOptions.threshold_px", self.threshold_px)
        if not 0 <= self.min_inlier_ratio < 1:
            raise InputError(
                f"TrackerOptions.min_inlier_ratio: expected a fraction in [0, 1), got "
                f"{self.min_inlier_ratio!r}"
            )


def detect_corners(gray: np.ndarray, count: int) -> np.ndarray:
    """(N, 2) float32 Shi-Tomasi corners of a gray image, at most ``count``, spread over a grid
    of cells of about ``CELL_PX`` pixels (the best few of each cell)."""
    h, w = gray.shape[:2]
    cols, rows = max(1, round(w / CELL_PX)), max(1, round(h / CELL_PX))
    per_cell = max(1, count // (cols * rows))
    out = []
    for r in range(rows):
        y0, y1 = r * h // rows, (r + 1) * h // rows
        for c in range(cols):
            x0, x1 = c * w // cols, (c + 1) * w // cols
            found = cv2.goodFeaturesToTrack(
                gray[y0:y1, x0:x1], per_cell, CORNER_QUALITY, CORNER_MIN_DISTANCE_PX
            )
            if found is not None:
                out.append(found.reshape(-1, 2) + np.array([x0, y0], dtype=np.float32))
    return np.concatenate(out).astype(np.float32) if out else np.zeros((0, 2), np.float32)


def track_points(
    prev: np.ndarray, cur: np.ndarray, points: np.ndarray, options: TrackerOptions
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``points`` (N, 2) of ``prev`` tracked into ``cur``: ``(found (N,) bool, (N, 2) float32)``.

    Points tracked outside the image are not found.
    """
    if len(points) == 0:
        return np.zeros(0, bool), np.zeros((0, 2), np.float32)
    win = int(options.window_px)
    nxt, status, _ = cv2.calcOpticalFlowPyrLK(
        prev,
        cur,
        np.ascontiguousarray(points, np.float32).reshape(-1, 1, 2),
        None,
        winSize=(win, win),
        maxLevel=int(options.levels),
    )
    nxt = nxt.reshape(-1, 2)
    h, w = cur.shape[:2]
    found = (status.ravel() == 1) & np.isfinite(nxt).all(axis=1)
    found &= (nxt[:, 0] >= 0) & (nxt[:, 0] <= w - 1) & (nxt[:, 1] >= 0) & (nxt[:, 1] <= h - 1)
    return found, nxt


def track_checked(
    prev: np.ndarray, cur: np.ndarray, points: np.ndarray, options: TrackerOptions
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`track_points` with a forward-backward check: a point is found only when tracking
    it back lands within ``FB_MAX_ERROR_PX`` of where it started."""
    found, nxt = track_points(prev, cur, points, options)
    if found.any():
        back_found, back = track_points(cur, prev, nxt, options)
        found &= back_found & (
            np.linalg.norm(back - np.asarray(points, np.float32), axis=1) < FB_MAX_ERROR_PX
        )
    return found, nxt


@dataclass(frozen=True, eq=False)
class TrackedPoints:
    """World points seen in one frame: their pixels there and their 3D positions.

    Attributes:
        stamp: the frame's stamp.
        pixels: (N, 2) float32 pixels in that frame.
        points: (N, 3) world points.
        hops: frames they were tracked through since they were measured.
    """

    stamp: float
    pixels: np.ndarray
    points: np.ndarray
    hops: int = 0

    def __len__(self) -> int:
        return len(self.pixels)

    def subset(self, keep: np.ndarray, stamp: float, pixels: np.ndarray) -> TrackedPoints:
        """The points ``keep`` seen at ``pixels`` (all N rows) in the next frame, of ``stamp``."""
        return TrackedPoints(stamp, np.asarray(pixels, np.float32)[keep], self.points[keep], self.hops + 1)


def track_through(
    frames: list[tuple[float, np.ndarray]], points: TrackedPoints, options: TrackerOptions
) -> TrackedPoints:
    """``points`` tracked (:func:`track_checked`) through ``frames`` (``(stamp, gray)`` in order,
    the first being the points' own frame); returns them in the last frame (those still found)."""
    cur = points
    for (_, prev), (stamp, gray) in zip(frames, frames[1:]):
        if len(cur) == 0 or prev.shape != gray.shape:
            return TrackedPoints(stamp, np.zeros((0, 2), np.float32), np.zeros((0, 3)))
        found, nxt = track_checked(prev, gray, cur.pixels, options)
        cur = cur.subset(found, stamp, nxt)
    return cur


def pose_from_points(
    prior: Pose, points: np.ndarray, rays: np.ndarray, focal: float
) -> tuple[Pose, int] | None:
    """The camera pose from world points seen along rays (PnP).

    ``cv2.solvePnPRansac`` with the AP3P minimal solver (Ke, Roumeliotis, CVPR 2017) on
    undistorted normalized coordinates, so that every camera model works, then
    Levenberg-Marquardt on its inliers (``cv2.solvePnPRefineLM``); inliers within
    ``PNP_THRESHOLD_PX`` pixels of the refined pose. A minimal solver instead of iterative
    PnP on every sample: 0.4 instead of 1.2 ms on 200 points with 15 % outliers, and the
    stream gates the result against its prediction anyway.

    Args:
        prior: the predicted ``cam_from_world`` (points behind it are not used).
        points: (N, 3) world points.
        rays: (N, 2) their undistorted normalized coordinates in the camera.
        focal: the focal length in pixels (for the threshold).

    Returns:
        ``(cam_from_world, inliers)``, or None when fewer than ``MIN_POINTS`` points (or under
        ``MIN_POINT_INLIER_FRACTION`` of them) agree.
    """
    X = np.asarray(points, dtype=float).reshape(-1, 3)
    x = np.asarray(rays, dtype=float).reshape(-1, 2)
    ok = np.isfinite(x).all(axis=1) & np.isfinite(X).all(axis=1) & (prior.transform(X)[:, 2] > 0)
    if ok.sum() < MIN_POINTS:
        return None
    X, x = X[ok], x[ok]
    threshold = PNP_THRESHOLD_PX / focal
    found, rvec, tvec, inliers = cv2.solvePnPRansac(
        X,
        x,
        np.eye(3),
        None,
        iterationsCount=PNP_ITERATIONS,
        reprojectionError=threshold,
        confidence=0.999,
        flags=cv2.SOLVEPNP_AP3P,
    )
    if not found or inliers is None or len(inliers) < MIN_POINTS:
        return None
    idx = inliers.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(X[idx], x[idx], np.eye(3), None, rvec, tvec)
    R, _ = cv2.Rodrigues(rvec)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(tvec))):
        return None
    U, _, Vt = np.linalg.svd(R)
    pose = Pose(U @ Vt, tvec.ravel())
    Xc = pose.transform(X)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(Xc[:, :2] / Xc[:, 2:] - x, axis=1)
    n = int(np.sum((Xc[:, 2] > 0) & (err < threshold)))
    if n < MIN_POINTS or n < MIN_POINT_INLIER_FRACTION * len(X):
        return None
    return pose, n


#: a view break needs the tracked corners to have moved at least this far (median, pixels): a
#: robot standing still sees no parallax and fits no relative pose either
BREAK_MIN_FLOW_PX = 2.0
#: ... and the expected rotation since the previous frame to be below this (degrees): a turn
#: faster than the tracker follows also fits no relative pose
BREAK_MAX_ROTATION_DEG = 10.0


def view_broken(tracked: Tracked, min_tracks: int, expected_rotation_deg: float | None) -> bool:
    """Whether the view changed more than any motion explains: the rotation expected since the
    previous frame (``expected_rotation_deg``, from wheel odometry; None: nothing tells, so a turn
    too fast for the tracker cannot be told from a jump) is small, yet the previous frame's
    corners were lost (``too_few_matches``), or at least ``min_tracks`` were followed and moved
    (``BREAK_MIN_FLOW_PX``) but too few fit one relative pose (``too_few_inliers``). A robot
    carried away (a kidnap) looks like this. Standing still (no flow) or a fast turn is not a
    break; a frame too fast for the tracker is, and costs frames until the next fix, never a
    wrong pose."""
    rel = tracked.relative
    if rel is None or rel.success:
        return False
    if expected_rotation_deg is not None and expected_rotation_deg >= BREAK_MAX_ROTATION_DEG:
        return False
    if (
        rel.status == "too_few_matches"
    ):  # the corners of a textured frame were lost (blank frames never get here)
        return True
    return (
        rel.status == "too_few_inliers"
        and tracked.tracks >= min_tracks
        and tracked.flow_px >= BREAK_MIN_FLOW_PX
    )


#: a frame whose pixels vary less than this (std, grey levels) has nothing to track or match
BLANK_PIXEL_STD = 2.0


def is_blank(gray: np.ndarray) -> bool:
    """Whether a frame is blank: black, white or uniform (lens cap, a dropped exposure, a
    driver's filler frame); its pixel std is below ``BLANK_PIXEL_STD`` grey levels."""
    _, std = cv2.meanStdDev(gray)
    return float(std.ravel()[0]) < BLANK_PIXEL_STD


def points_pose_covariance(
    cam_from_world: Pose, points: np.ndarray, rays: np.ndarray, ray_std: float
) -> np.ndarray | None:
    """The (6, 6) pose-graph covariance ``(ω, δc)`` of a pose from world points (PnP), measured
    from the points' geometry: ``σ² (JᵀJ)⁻¹`` with ``J`` the Jacobian of the normalized
    reprojections (2N, 6) and ``σ`` the larger of ``ray_std`` and the residuals' own RMS (with
    6 degrees of freedom taken out). Points far away and bunched together give a large std along
    the viewing direction; a spread, near set a small one.

    Args:
        cam_from_world: the pose.
        points: (N, 3) world points (the inliers).
        rays: (N, 2) their undistorted normalized coordinates.
        ray_std: the measurement noise of a ray (normalized units, e.g. pixels / focal).

    Returns:
        (6, 6), or None with fewer than 4 points in front of the camera or a singular geometry.
    """
    Xc = cam_from_world.transform(np.asarray(points, dtype=float).reshape(-1, 3))
    x = np.asarray(rays, dtype=float).reshape(-1, 2)
    ok = Xc[:, 2] > 1e-6
    Xc, x = Xc[ok], x[ok]
    if len(Xc) < 4:
        return None
    z = Xc[:, 2]
    proj = Xc[:, :2] / z[:, None]
    # d proj / d Xc: (N, 2, 3)
    P = np.zeros((len(Xc), 2, 3))
    P[:, 0, 0] = P[:, 1, 1] = 1.0 / z
    P[:, :, 2] = -proj / z[:, None]
    # Xc' = exp([ω]×) Xc  → d Xc / d ω = −[Xc]×;  Xc = R (X − c) → d Xc / d c = −R
    skew = np.zeros((len(Xc), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -Xc[:, 2], Xc[:, 1], -Xc[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = Xc[:, 2], -Xc[:, 1], Xc[:, 0]
    J = np.concatenate([P @ -skew, P @ -cam_from_world.R], axis=2).reshape(-1, 6)
    dof = max(2 * len(Xc) - 6, 1)
    sigma = max(float(ray_std), float(np.sqrt(np.sum((proj - x) ** 2) / dof)))
    try:
        cov = np.linalg.inv(J.T @ J) * sigma**2
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)):
        return None
    return 0.5 * (cov + cov.T)


#: a pose from fewer tracked points than this has its std scaled by sqrt(this / inliers)
POINT_FIX_FULL_SUPPORT = 60


def tracked_points_covariance(
    pose: Pose,
    points: np.ndarray,
    rays: np.ndarray,
    focal: float,
    inliers: int,
    hops: int,
    *,
    pixel_std: float,
    min_std_m: float,
    rotation_std_deg: float,
    std_per_frame: float,
) -> np.ndarray:
    """The (6, 6) pose-graph covariance of a pose from tracked map points (:func:`pose_from_points`).

    The geometry's own (:func:`points_pose_covariance` on the points within ``PNP_THRESHOLD_PX``:
    far, bunched points are weak along the view) plus a floor of ``min_std_m`` and
    ``rotation_std_deg`` (the points' own errors are shared by all of them and do not show in the
    residuals), both grown by ``g = (1 + std_per_frame · hops) · sqrt(max(1, 60 / inliers))``:
    tracks drift with each frame they are followed through, and few points are weak.

    Args:
        pose: the PnP pose (``cam_from_world``).
        points: (N, 3) world points; rays: (N, 2) their normalized coordinates.
        focal: focal length (pixels); inliers: the PnP inliers; hops: frames the points were tracked.
    """
    grow = (1.0 + std_per_frame * hops) * np.sqrt(max(1.0, POINT_FIX_FULL_SUPPORT / max(inliers, 1)))
    cov = np.diag([np.radians(rotation_std_deg) ** 2] * 3 + [min_std_m**2] * 3)
    Xc = pose.transform(points)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.linalg.norm(Xc[:, :2] / Xc[:, 2:] - rays, axis=1)
    keep = (Xc[:, 2] > 0) & (err < PNP_THRESHOLD_PX / focal)
    measured = points_pose_covariance(pose, points[keep], rays[keep], pixel_std / focal)
    if measured is not None:
        cov = cov + measured
    return cov * grow**2


class FrameHistory:
    """The last frames of a stream, ``(stamp, gray)`` in order, shared with a fix worker: the
    stream appends, a worker reads a snapshot (a new list each time, never changed in place)."""

    def __init__(self, size: int) -> None:
        self.size = int(size)
        self._frames: list[tuple[float, np.ndarray]] = []

    def append(self, stamp: float, gray: np.ndarray) -> None:
        self._frames = (self._frames + [(float(stamp), gray)])[-self.size :]

    def clear(self) -> None:
        self._frames = []

    def since(self, stamp: float) -> list[tuple[float, np.ndarray]]:
        """The frames from the one of ``stamp`` on (empty if it is no longer kept)."""
        frames = self._frames
        for k, (s, _) in enumerate(frames):
            if s == stamp:
                return frames[k:]
        return []


def _signed_sampson(R: np.ndarray, t: np.ndarray, xa: np.ndarray, xb: np.ndarray, focal: float) -> np.ndarray:
    """(N,) signed Sampson distances (pixels) of ``x_bᵀ E x_a = 0`` for ``E = [t]× R``."""
    E = essential_from_relpose(R, t)
    Ex, Etx = xa @ E.T, xb @ E
    num = np.einsum("ni,ni->n", xb, Ex)
    return focal * num / np.sqrt(Ex[:, 0] ** 2 + Ex[:, 1] ** 2 + Etx[:, 0] ** 2 + Etx[:, 1] ** 2)


def relative_pose_covariance(
    rel: RelativePoseEstimate, camera_a: Camera, camera_b: Camera, points_a: np.ndarray, points_b: np.ndarray
) -> np.ndarray | None:
    """(5, 5) covariance of a relative pose ``b_from_a`` from its inlier tracks: of ``(δ, β)``
    with ``R' = exp([δ]×) R`` and the direction of camera b's centre in camera a's frame
    ``u' ∝ u + B β`` (``B``: (3, 2) orthonormal, ⊥ ``u``, from :func:`direction_basis`).

    Gauss-Newton: ``σ² (JᵀJ)⁻¹`` with ``J`` the derivatives of the signed Sampson distances
    (pixels) and ``σ`` their robust std (at least ``MIN_TRACK_STD_PX``) times
    ``TRACK_STD_INFLATION``. A small baseline next to a rotation is where 2D-2D motion is
    ambiguous (a yaw and a sideways step move distant points alike); the covariance says so
    instead of the fixed std of a good case. None when it cannot be computed.
    """
    if rel.pose is None:
        return None
    m = np.asarray(rel.inliers, bool)
    xa = np.concatenate(
        [camera_a.cam_from_img(np.asarray(points_a, float)[m]), np.ones((int(m.sum()), 1))], axis=1
    )
    xb = np.concatenate(
        [camera_b.cam_from_img(np.asarray(points_b, float)[m]), np.ones((int(m.sum()), 1))], axis=1
    )
    if len(xa) < 6:
        return None
    focal = float(np.mean(camera_b.focal))
    R0 = np.asarray(rel.pose.R, float)
    u0 = rel.pose.inverse().t
    B = direction_basis(u0)

    def residuals(p: np.ndarray) -> np.ndarray:
        R = so3_exp(p[None, :3])[0] @ R0
        u = u0 + B @ p[3:]
        return _signed_sampson(R, -R @ (u / np.linalg.norm(u)), xa, xb, focal)

    r0 = residuals(np.zeros(5))
    h = 1e-6
    J = np.stack([(residuals(h * e) - r0) / h for e in np.eye(5)], axis=1)
    sigma = TRACK_STD_INFLATION * max(1.4826 * float(np.median(np.abs(r0))), MIN_TRACK_STD_PX)
    try:
        cov = sigma**2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)):
        return None
    return 0.5 * (cov + cov.T)


@dataclass(frozen=True)
class Tracked:
    """The outcome of :meth:`FrameTracker.track` for one frame.

    Attributes:
        relative: the relative pose ``cur_from_prev`` (unit translation) or its failure; None
            when the motion was not estimated.
        tracks: corners tracked from the previous frame.
        points: the world points still tracked into this frame, or None.
        covariance: (5, 5) covariance of ``relative`` (:func:`relative_pose_covariance`), or None.
        flow_px: the median displacement of the tracked corners (pixels).
    """

    relative: RelativePoseEstimate | None
    tracks: int = 0
    points: TrackedPoints | None = None
    covariance: np.ndarray | None = None
    flow_px: float = 0.0


class FrameTracker:
    """Tracks corners (for the relative pose) and world points (for the position) from frame to
    frame.

    Args:
        options: :class:`TrackerOptions`.

    Example:
        >>> tracker = FrameTracker(TrackerOptions())                       # doctest: +SKIP
        >>> tracker.track(gray0, camera, 0.0)                             # first frame: no motion
        >>> out = tracker.track(gray1, camera, 0.1)                       # doctest: +SKIP
        >>> out.relative.pose if out.relative.success else out.relative.status   # doctest: +SKIP
    """

    def __init__(self, options: TrackerOptions | None = None) -> None:
        self.options = options or TrackerOptions()
        self._ransac = RansacOptions(
            threshold_px=self.options.threshold_px,
            min_iterations=VO_MIN_ITERATIONS,
            max_iterations=VO_MAX_ITERATIONS,
        )
        self.reset()

    def reset(self) -> None:
        """Forget the previous frame and the points."""
        self._prev: tuple[np.ndarray, Camera, np.ndarray] | None = None
        self.points: TrackedPoints | None = None

    def set_points(self, points: TrackedPoints | None) -> None:
        """World points seen in the last frame given to :meth:`track` (``points.stamp``); the
        next calls track them."""
        self.points = points

    def track(self, gray: np.ndarray, camera: Camera, stamp: float, estimate_motion: bool = True) -> Tracked:
        """Track the previous frame's corners and points into ``gray`` (taken with ``camera`` at
        ``stamp``), estimate the relative pose (unless ``estimate_motion`` is False: e.g. wheel
        odometry gives it), and detect this frame's corners for the next call."""
        out = Tracked(None)
        prev = self._prev
        if prev is not None and prev[0].shape != gray.shape:  # another image size: nothing to track
            prev, self.points = None, None
        if prev is not None:
            if self.points is not None and len(self.points):
                found, nxt = track_checked(prev[0], gray, self.points.pixels, self.options)
                self.points = self.points.subset(found, stamp, nxt)
            if estimate_motion:
                image, prev_camera, corners = prev
                found, nxt = track_points(image, gray, corners, self.options)
                rel = estimate_relative_pose(
                    prev_camera,
                    camera,
                    corners[found].astype(float),
                    nxt[found].astype(float),
                    model=self.options.model,
                    options=self._ransac,
                    min_inliers=self.options.min_inliers,
                )
                if rel.success and rel.num_inliers < self.options.min_inlier_ratio * found.sum():
                    rel = RelativePoseEstimate(
                        None,
                        False,
                        Status.TOO_FEW_INLIERS,
                        inliers=rel.inliers,
                        num_inliers=rel.num_inliers,
                        stats=rel.stats,
                    )
                cov = (
                    relative_pose_covariance(rel, prev_camera, camera, corners[found], nxt[found])
                    if rel.success
                    else None
                )
                flow = (
                    float(np.median(np.linalg.norm(nxt[found] - corners[found], axis=1)))
                    if found.any()
                    else 0.0
                )
                out = Tracked(rel, int(found.sum()), covariance=cov, flow_px=flow)
        elif self.points is not None and self.points.stamp != stamp:
            self.points = None
        self._prev = (gray, camera, detect_corners(gray, self.options.corners))
        return Tracked(out.relative, out.tracks, self.points, out.covariance, out.flow_px)
