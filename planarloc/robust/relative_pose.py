"""Robust relative pose between two images of the same camera stream (visual odometry).

Hypotheses come from the planar 2-point solver (paper Sec. IV-A: rotation about the camera
y-axis, translation in the x–z plane) or, for the 6DoF model, from Nistér's 5-point solver; both
run in the generic MSAC loop (:func:`planarloc.robust.ransac.ransac`) and are scored by the
Sampson error in pixels. ``model="auto"`` runs both and keeps the planar pose unless the 6DoF
pose explains clearly more matches (the planar model does not hold: a slope, a bump, a
camera that is not upright).

The translation of a relative pose from 2D-2D matches has no scale: it is returned with unit
norm. The scale comes from elsewhere (wheel odometry or absolute fixes).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from numba import njit

from planarloc.geometry.camera import Camera
from planarloc.geometry.epipolar import essential_from_relpose, sampson_error_sq
from planarloc.geometry.epipolar_kernels import essential_into, sampson_sq
from planarloc.geometry.pose import Pose
from planarloc.geometry.so3 import so3_exp
from planarloc.geometry.validation import InputError, check_array
from planarloc.robust.options import RansacOptions
from planarloc.robust.ransac import ransac
from planarloc.robust.result import RansacStatistics
from planarloc.robust.scoring import msac_add
from planarloc.robust.status import Status

#: the 6DoF model replaces the planar one only if it has this many times its inliers
SIX_DOF_MARGIN = 1.15
MODELS = ("planar", "6dof", "auto")
#: refinement uses at most this many inliers, evenly spread over the match list, and this many steps
REFINE_MAX_POINTS, REFINE_ITERATIONS = 60, 5


@dataclass
class RelativePoseEstimate:
    """Result of :func:`estimate_relative_pose`.

    Attributes:
        pose: ``b_from_a`` with unit-norm translation, or None when not ``success``.
        success: a supported pose was found.
        status: a :class:`Status`: ``success``, ``too_few_matches`` or ``too_few_inliers`` (a
            string of a member's value is converted to that member).
        model: ``"planar"`` or ``"6dof"`` (empty on failure).
        inliers: (N,) bool over the input matches.
        num_inliers: inlier count.
        stats: RANSAC counters and times.
    """

    pose: Pose | None
    success: bool
    status: Status
    model: str = ""
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    num_inliers: int = 0
    stats: RansacStatistics = field(default_factory=RansacStatistics)

    def __post_init__(self) -> None:
        status = Status.of(self.status)
        if isinstance(status, Status):  # else a status made outside the estimators, kept as given
            self.status = status


class RayPairs(NamedTuple):
    """N matched rays of two images, as one record (also for the kernels): xa, xb (N, 3)
    normalized homogeneous rays of image a and image b, and fa, fb (2,) the focal lengths
    (fx, fy) of their cameras, the pixel scales of the Sampson errors."""

    xa: np.ndarray
    xb: np.ndarray
    fa: np.ndarray
    fb: np.ndarray

    def subset(self, rows: np.ndarray) -> RayPairs:
        """The ray pairs ``rows`` (an index or mask) of the same two cameras."""
        return RayPairs(self.xa[rows], self.xb[rows], self.fa, self.fb)


def _sampson_sq(R: np.ndarray, t: np.ndarray, rays: RayPairs) -> np.ndarray:
    """(K, N) squared Sampson errors in pixels of K poses ``b_from_a`` on N ray pairs."""
    xa, xb, fa, fb = rays
    return np.stack([sampson_error_sq(E, xa, xb, fa, fb) for E in essential_from_relpose(R, t)])


@njit(cache=True, error_model="numpy", nogil=True)
def _msac_kernel(
    R: np.ndarray, t: np.ndarray, rays: RayPairs, threshold_sq: float, bound: float
) -> tuple[np.ndarray, np.ndarray]:
    """MSAC costs (K,) and inlier counts (K,) of K poses ``b_from_a`` on N ray pairs.

    A pose's scoring stops once its cost exceeds ``bound`` or the lowest cost of this call so
    far: its cost and count are then partial (a lower bound and a count that cannot win)."""
    xa, xb, fa, fb = rays
    K = R.shape[0]
    cost = np.zeros(K)
    count = np.zeros(K, dtype=np.int64)
    E = np.empty((3, 3))
    best = bound
    for k in range(K):
        essential_into(R[k], t[k], E)
        c, n = 0.0, 0
        for i in range(xa.shape[0]):
            c, n = msac_add(c, n, sampson_sq(E, xa[i], xb[i], fa[0], fa[1], fb[0], fb[1]), threshold_sq)
            if c > best:
                break
        cost[k] = c
        count[k] = n
        if c < best:
            best = c
    return cost, count


def distinct_samples(rng: np.random.Generator, n: int, num_data: int, size: int) -> np.ndarray:
    """(n, size) minimal samples of ``size`` distinct indices in ``0..num_data-1``, uniform.

    Rows with a repeated index are drawn again (with 2-5 of hundreds of tracks, a few in a
    hundred): O(n · size) instead of ranking n × num_data random numbers.
    """
    if num_data < size:
        raise InputError(f"distinct_samples: need at least {size} data, got {num_data}")
    out = rng.integers(0, num_data, (n, size))
    while True:
        srt = np.sort(out, axis=1)
        bad = np.flatnonzero((srt[:, 1:] == srt[:, :-1]).any(axis=1))
        if not len(bad):
            return out
        out[bad] = rng.integers(0, num_data, (len(bad), size))


class _RelativeEstimator:
    """Adapter of one minimal relative-pose solver to the generic loop."""

    #: the batch solver: (S, m, 3) rays of both cameras -> ``b_from_a`` R, t and valid flags per sample
    solver: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]

    def __init__(self, rays: RayPairs, model: str, threshold_px: float) -> None:
        self.rays = rays
        self.num_data = len(rays.xa)
        self.threshold_sq = threshold_px**2
        if model == "planar":
            from planarloc.solvers.relpose_planar_2p import planar_2p_batch_unchecked

            self.sample_size, self.solver = 2, planar_2p_batch_unchecked
        else:
            from planarloc.solvers.relpose_5p_nister import relpose_5p_nister_batch

            self.sample_size, self.solver = 5, relpose_5p_nister_batch

    def generate(
        self, rng: np.random.Generator, n: int, stats: RansacStatistics
    ) -> tuple[np.ndarray, np.ndarray]:
        samples = distinct_samples(rng, n, self.num_data, self.sample_size)
        R, t, valid = self.solver(self.rays.xa[samples], self.rays.xb[samples])  # b_from_a ("ref_from_query")
        stats.hypotheses += int(valid.sum())
        return np.asarray(R)[valid], np.asarray(t)[valid]

    def distinct(self, R: np.ndarray, t: np.ndarray, Rb: np.ndarray, tb: np.ndarray) -> np.ndarray:
        """Which relative poses (R (n, 3, 3), t (n, 3)) differ from (Rb, tb): rotations more than
        1° or translation directions more than 2° apart. (n,) bool."""
        cos_r = ((R * Rb).sum(axis=(1, 2)) - 1.0) / 2.0  # tr(R Rbᵀ)
        nn = np.linalg.norm(t, axis=1) * np.linalg.norm(tb)
        cos_t = np.where(nn > 0, t @ tb / np.where(nn > 0, nn, 1.0), 1.0)
        return (cos_r < np.cos(np.radians(1.0))) | (cos_t < np.cos(np.radians(2.0)))

    def score(self, R: np.ndarray, t: np.ndarray, bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        return _msac_kernel(
            np.ascontiguousarray(R, dtype=float),
            np.ascontiguousarray(t, dtype=float),
            self.rays,
            self.threshold_sq,
            float(bound),
        )

    def refine(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gauss-Newton on the Sampson errors (pixels) of the inliers, in the model's own
        parameters (planar: yaw and heading of the translation; 6DoF: rotation and direction);
        a step is kept only when it lowers the cost. The Jacobian is by forward differences,
        all perturbed poses scored in one batch."""
        e = _sampson_sq(R[None], t[None], self.rays)[0]
        inl = e < self.threshold_sq
        if inl.sum() < 2 * self.sample_size:
            return R, t
        idx = np.flatnonzero(inl)
        idx = idx[np.linspace(0, len(idx) - 1, min(len(idx), REFINE_MAX_POINTS)).astype(int)]
        rays = self.rays.subset(idx)
        planar = self.sample_size == 2
        p = 2 if planar else 5
        B = None if planar else direction_basis(t)

        def poses(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            """(K, p) parameter vectors -> K poses around (R, t)."""
            if B is None:  # planar
                Ry = so3_exp(np.stack([np.zeros(len(X)), X[:, 0], np.zeros(len(X))], axis=1))
                Rt = so3_exp(np.stack([np.zeros(len(X)), X[:, 1], np.zeros(len(X))], axis=1))
                return Ry @ R, Rt @ t
            tt = t[None] + X[:, 3:] @ B.T
            return so3_exp(X[:, :3]) @ R, tt / np.linalg.norm(tt, axis=1, keepdims=True)

        def residuals(X: np.ndarray) -> np.ndarray:
            return np.sqrt(_sampson_sq(*poses(X), rays))

        x, h = np.zeros(p), 1e-6
        r = residuals(x[None])[0]
        for _ in range(REFINE_ITERATIONS):
            r_all = residuals(np.concatenate([x[None], x[None] + h * np.eye(p)]))
            J = (r_all[1:] - r_all[0]).T / h
            try:
                step = np.linalg.lstsq(J, -r_all[0], rcond=None)[0]
            except np.linalg.LinAlgError:
                break
            r_new = residuals((x + step)[None])[0]
            if not r_new @ r_new < r @ r:
                break
            x, r = x + step, r_new
            if np.max(np.abs(step)) < 1e-7:
                break
        Rr, tr = poses(x[None])
        return Rr[0], tr[0]


def direction_basis(u: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal directions perpendicular to the unit vector ``u`` (deterministic)."""
    u = np.asarray(u, float) / np.linalg.norm(u)
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    b1 = np.cross(u, a)
    b1 /= np.linalg.norm(b1)
    return np.stack([b1, np.cross(u, b1)], axis=1)


def _depths_positive(R: np.ndarray, t: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> int:
    """How many rays pairs triangulate in front of both cameras (midpoint depths λ_a, λ_b > 0 of
    ``λ_b x_b = λ_a R x_a + t``)."""
    a = xa @ R.T
    b = xb
    aa, bb, ab = np.einsum("ni,ni->n", a, a), np.einsum("ni,ni->n", b, b), np.einsum("ni,ni->n", a, b)
    at, bt = a @ t, b @ t
    den = aa * bb - ab**2
    ok = den > 1e-12
    la = (ab * bt - bb * at) / np.where(ok, den, 1.0)
    lb = (aa * bt - ab * at) / np.where(ok, den, 1.0)
    return int(np.sum(ok & (la > 0) & (lb > 0)))


def estimate_relative_pose(
    camera_a: Camera,
    camera_b: Camera,
    points_a: object,
    points_b: object,
    model: str = "auto",
    options: RansacOptions | None = None,
    min_inliers: int = 15,
) -> RelativePoseEstimate:
    """Relative pose ``b_from_a`` from N pixel matches between image a and image b.

    Args:
        camera_a, camera_b: intrinsics of the two images.
        points_a, points_b: (N, 2) matching pixels.
        model: ``"planar"`` (2-point solver, paper Sec. IV-A), ``"6dof"`` (5-point) or
            ``"auto"`` (both; the 6DoF pose only if it has ``SIX_DOF_MARGIN`` times the planar
            inliers).
        options: RANSAC options (threshold in pixels, iterations, seed); the absolute-pose
            checks in them do not apply here. Default: ``RansacOptions(min_iterations=50,
            max_iterations=300)``.
        min_inliers: fewer inliers is ``too_few_inliers``.

    Returns:
        :class:`RelativePoseEstimate` with a unit-norm translation.

    Example:
        >>> est = estimate_relative_pose(cam, cam, px_prev, px_cur)   # doctest: +SKIP
        >>> est.pose.R if est.success else est.status                   # doctest: +SKIP
    """
    if model not in MODELS:
        raise InputError(f"model: expected one of {MODELS}, got {model!r}")
    pa = check_array("points_a", points_a, (None, 2))
    pb = check_array("points_b", points_b, (len(pa), 2))
    options = options or RansacOptions(min_iterations=50, max_iterations=300)
    options = replace(options, local_optimization=False)
    ok = np.isfinite(camera_a.cam_from_img(pa)).all(axis=1) & np.isfinite(camera_b.cam_from_img(pb)).all(
        axis=1
    )
    idx = np.flatnonzero(ok)
    inliers = np.zeros(len(pa), dtype=bool)
    if len(idx) < max(min_inliers, 5):
        return RelativePoseEstimate(None, False, Status.TOO_FEW_MATCHES, inliers=inliers)
    xa, xb = camera_a.bearings_from_img(pa[idx]), camera_b.bearings_from_img(pb[idx])
    rays = RayPairs(xa, xb, np.asarray(camera_a.focal, dtype=float), np.asarray(camera_b.focal, dtype=float))
    stats = RansacStatistics()
    best: tuple[str, np.ndarray, np.ndarray, int] | None = None
    for m in ("planar", "6dof") if model == "auto" else (model,):
        if m == "6dof" and best is not None and SIX_DOF_MARGIN * best[3] >= len(idx):
            stats.searches_skipped += 1  # more inliers than there are matches: 6DoF cannot win
            continue
        est = _RelativeEstimator(rays, m, options.threshold_px)
        own = RansacStatistics()  # each model gets its own iteration budget
        out = ransac(est, options, np.random.default_rng(options.seed), own)
        stats.merge(own)
        if out.R is None or out.t is None:  # both or neither
            continue
        if best is None or out.num_inliers > SIX_DOF_MARGIN * best[3]:
            best = (m, out.R, out.t, out.num_inliers)
    if best is None or best[3] < min_inliers:
        return RelativePoseEstimate(
            None,
            False,
            Status.TOO_FEW_INLIERS,
            inliers=inliers,
            stats=stats,
            num_inliers=0 if best is None else best[3],
        )
    m, R, t, _ = best
    R, t = _RelativeEstimator(rays, m, options.threshold_px).refine(R, t)
    e = _sampson_sq(R[None], t[None], rays)[0]
    inl = e < options.threshold_px**2
    # The minimal sample's cheirality decides the sign of t on 2 or 5 points, which is fragile
    # under forward motion (distant points); all inliers vote.
    if _depths_positive(R, -t, xa[inl], xb[inl]) > _depths_positive(R, t, xa[inl], xb[inl]):
        t = -t
    inliers[idx] = inl
    return RelativePoseEstimate(
        Pose(R, t / np.linalg.norm(t)), True, Status.SUCCESS, m, inliers, int(inliers.sum()), stats
    )
