"""Estimator adapters for the generic loop: one per hypothesis family.

* :class:`Planar2p1pEstimator` — the paper's 2p1p (Sec. IV-C): 2 matches of pair j, and the
  scale from the matches of the other pairs (a 1D consensus over all of them rather than one
  random match); in ``tracks`` mode the third datum may instead be a 2D-3D constraint.
* :class:`RelativePairEstimator` — 2p2p (Sec. IV-B) and the baselines 5p5p-Nistér,
  5p5p-Stewénius and 8p8p: a relative pose per pair from a minimal (or 8-point) sample,
  then Rcheck, triangulation, Pdcheck and the consistency check.

All share the scoring (MSAC over every match of every pair plus 2D-3D constraints), the local
optimisation (planar, then 6DoF: :mod:`planarloc.robust.local_optimization`) and the
refinement (robust 6DoF) of the problem. :class:`RectifiedHypotheses` runs a planar family on
gravity-levelled bearings (:mod:`planarloc.geometry.gravity`) and scores on the original ones.
What a refined pose's matches can tell about it lives in :mod:`planarloc.robust.observability`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import numpy as np

from planarloc.robust.consensus_scale import ConsensusSettings, consensus_2p1p
from planarloc.robust.hypotheses import (
    Hypotheses,
    RelativePoses,
    hypotheses_2p1p,
    hypotheses_p3p,
    hypotheses_up2p,
)
from planarloc.robust.local_optimization import (
    LocalOptimization,
    distinct_centres,
    level_plane,
    refine_planar_then_6dof,
)
from planarloc.robust.map_prior import refine_with_map_prior
from planarloc.robust.options import Method, RansacOptions
from planarloc.robust.problem import AbsolutePoseProblem
from planarloc.robust.refinement import (
    RefineSettings,
    StartPose,
    centre_covariance,
    refine_on_inliers,
    refine_pose,
)
from planarloc.robust.relative_stages import hypotheses_of_relative_samples, relative_samples
from planarloc.robust.result import RansacStatistics
from planarloc.robust.sampling import draw_pair_samples, draw_within_pairs
from planarloc.robust.scoring import errors_sq, msac_scores
from planarloc.robust.search_confidence import (
    inlier_ratios,
    missed_by_draws,
    missed_by_pairs,
    pair_sample_chance,
)
from planarloc.solvers.relpose_planar_2p import planar_2p_batch_unchecked

SIGMA_FLOOR_PX = 0.5  # lower bound of the pixel noise assumed for covariances
LO_WIDENING = 3.0  # local optimisation gathers inliers within LO_WIDENING * threshold
LO_PLANAR_ITERATIONS = 3  # local optimisation: LM iterations in the planar model's 3 DoF ...
LO_ITERATIONS = 2  # ... then in 6DoF
LO_MAX_DATA = 128  # local optimisation refines on at most about this many (strided) inliers
_IDENTITY = np.eye(3)
_FREE = np.zeros(6, dtype=np.bool_)


class ProblemEstimator:
    """Scoring, inliers and refinement shared by every hypothesis family."""

    sample_size = 3

    def __init__(self, problem: AbsolutePoseProblem, options: RansacOptions) -> None:
        self.p = problem
        self.options = options
        self.threshold_sq = options.threshold_px**2
        self.num_data = len(problem.xq) + len(problem.X3d)
        self.counters = np.zeros(5, dtype=np.int64)
        self._ref_centres = -np.einsum("pji,pj->pi", problem.ref_R, problem.ref_t)
        cos_level = float(np.cos(np.radians(options.planar_tolerance_deg)))
        self._local_optimization = LocalOptimization(
            self.refine_settings(LO_ITERATIONS, LO_WIDENING**2 * self.threshold_sq),
            LO_PLANAR_ITERATIONS,
            level_plane(problem.ref_R, cos_level),
            cos_level,
            LO_MAX_DATA,
        )

    def refine_settings(self, max_iterations: int, threshold_sq: float | None = None) -> RefineSettings:
        """The settings of this problem's refinements: ``max_iterations`` LM iterations on the data
        within ``threshold_sq`` (default τ²), loss scale τ, σ̂ floor :data:`SIGMA_FLOOR_PX` and the
        options' map prior (numbers as floats: one compiled signature)."""
        o = self.options
        return RefineSettings(
            float(self.threshold_sq if threshold_sq is None else threshold_sq),
            float(o.threshold_px),
            max_iterations,
            SIGMA_FLOOR_PX,
            math.radians(o.map_rotation_std_deg),
            float(o.map_position_std_m),
        )

    def score(self, R: np.ndarray, t: np.ndarray, bound: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        p = self.p
        return msac_scores(
            np.ascontiguousarray(R), np.ascontiguousarray(t), len(R), p.arrays, self.threshold_sq, bound
        )

    def distinct(self, R: np.ndarray, t: np.ndarray, Rb: np.ndarray, tb: np.ndarray) -> np.ndarray:
        """Which hypotheses (R (n, 3, 3), t (n, 3)) are distinct models from (Rb, tb): their
        centres differ by more than 10% of the distance to their nearest reference centre (the
        scatter of correct hypotheses is not; a pose slid along a weak direction is). (n,) bool."""
        return distinct_centres(R, t, -(tb @ Rb), self._ref_centres)

    def inliers(
        self, R: np.ndarray, t: np.ndarray, threshold_sq: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        th = self.threshold_sq if threshold_sq is None else threshold_sq
        e2d, e3d = errors_sq(R, t, self.p.arrays)
        return e2d < th, e3d < th

    def _refine(
        self,
        R: np.ndarray,
        c0: np.ndarray,
        in2d: np.ndarray,
        in3d: np.ndarray,
        max_iterations: int,
        B: np.ndarray = _IDENTITY,
        fixed: np.ndarray = _FREE,
        map_prior: bool = False,
    ) -> tuple:
        """Robust 6DoF refinement from ``(R, c0)`` on the given inliers (:func:`refine_pose`), or,
        with ``map_prior``, jointly with the reference poses under the options' map prior
        (:func:`planarloc.robust.map_prior.refine_with_map_prior`)."""
        start = StartPose(np.ascontiguousarray(R), np.ascontiguousarray(c0), B, fixed)  # c = c0 + B p
        idx2d, idx3d = np.flatnonzero(in2d), np.flatnonzero(in3d)
        refine = refine_with_map_prior if map_prior else refine_pose
        return refine(start, self.p.arrays, idx2d, idx3d, self.refine_settings(max_iterations))

    #: :meth:`_refine` under the map prior.
    _refine_with_map_prior = functools.partialmethod(_refine, map_prior=True)

    def _refine_on_inliers(
        self, R: np.ndarray, t: np.ndarray, threshold_sq: float, max_iterations: int
    ) -> tuple:
        settings = self.refine_settings(max_iterations, threshold_sq)
        return refine_on_inliers(np.ascontiguousarray(R), np.ascontiguousarray(t), self.p.arrays, settings)

    def refine_full(self, R: np.ndarray, t: np.ndarray, max_iterations: int) -> tuple:
        """Refine on the current inliers; returns (R, t, cov_center, sigma, cost, in2d, in3d)."""
        in2d, in3d = self.inliers(R, t)
        if in2d.sum() + in3d.sum() < 6:
            R2, t2, H, sigma, cost = self._refine(R, -R.T @ t, in2d, in3d, max_iterations)
            return R2, t2, centre_covariance(H, sigma), sigma, cost, in2d, in3d
        R2, t2, H, sigma, cost, in2d, in3d = self._refine_on_inliers(R, t, self.threshold_sq, max_iterations)
        return R2, t2, centre_covariance(H, sigma), sigma, cost, in2d, in3d

    def refine(self, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Local optimisation on the inliers of a widened threshold (3τ, the Cauchy loss at τ
        down-weights what it lets in), so that a hypothesis near the right basin gathers the
        constraints it first missed; the final refinement then works at τ. 3τ rather than
        2τ: +3 points of success at 20 matches per pair, 1.5 px noise, 60 % outliers (600
        scenes), where a noisy minimal-sample hypothesis misses many inliers.

        When the references are level with each other and the hypothesis is level with them
        (camera y axes within ``planar_tolerance_deg``: a planar hypothesis of a levelled
        problem), ``LO_PLANAR_ITERATIONS`` LM iterations first move it within the planar
        model (yaw, centre in the level plane): with few inliers and outliers let in at 3τ,
        the 3 extra DoF of a 6DoF step absorb outliers as tilt and height. Then
        ``LO_ITERATIONS`` 6DoF iterations on the inliers (3τ) of the planar optimum, which lets
        a slightly non-planar truth (uneven floor, mount) be reached. +1 to +2 points of
        success at 20 matches per pair and 60 % outliers (3000 scenes, BENCHMARKS.md)."""
        return refine_planar_then_6dof(
            np.ascontiguousarray(R), np.ascontiguousarray(t), self.p.arrays, self._local_optimization
        )

    def missed(self, in2d: np.ndarray, in3d: np.ndarray, samples: int) -> float:
        """The chance that ``samples`` samples drew none of the data a pose with inliers ``in2d``
        (N,), ``in3d`` (M,) (or more) rests on (:mod:`planarloc.robust.search_confidence`):
        here RANSAC's own bound, ``sample_size`` draws from all data at the pose's inlier ratio;
        the families refine it to how they sample."""
        ratio = (np.count_nonzero(in2d) + np.count_nonzero(in3d)) / max(self.num_data, 1)
        return missed_by_draws(ratio**self.sample_size, samples)

    def _flush(self, stats: RansacStatistics) -> None:
        c = self.counters
        stats.hypotheses += int(c[0])
        stats.rejected_rcheck += int(c[1])
        stats.rejected_pdcheck += int(c[2])
        stats.rejected_consistency += int(c[3])
        stats.rejected_degenerate += int(c[4])
        c[:] = 0


class Planar2p1pEstimator(ProblemEstimator):
    """The paper's 2p1p (Sec. IV-C) with Pdcheck; optional 2D-3D third datum.

    Without 2D-3D constraints (``structure="none"``) and ``consensus_scale`` (default), the
    scale comes from all matches of the other pairs instead of one random match
    (:meth:`_generate_consensus`; deviation from the paper, which draws the third match). With
    2D-3D constraints, or ``consensus_scale=False``, the paper's random third datum is used.
    """

    sample_size = 3

    top_k = 3  # relative poses kept per pair (consensus scale)
    peaks = 1  # scale maxima per relative pose
    max_votes = 128  # matches of the other pairs that vote for the scale (strided beyond)

    def __init__(
        self, problem: AbsolutePoseProblem, options: RansacOptions, consensus_scale: bool = True
    ) -> None:
        super().__init__(problem, options)
        self.use_3d = len(problem.X3d) > 0
        self.consensus_scale = consensus_scale
        self._any_eligible = bool((problem.counts >= 2).any())
        self._consensus = ConsensusSettings(
            self.threshold_sq, self.top_k, self.max_votes // 2, self.peaks, self.max_votes
        )

    def missed(self, in2d: np.ndarray, in3d: np.ndarray, samples: int) -> float:
        """Two inlier matches of map image j (drawn in proportion to its matches) make a good
        sample when the scale comes by consensus; a random third match must be an inlier too.
        In structure mode a third of the samples each take a 2D-2D third datum, a 2D-3D one, or
        two 2D-3D constraints (upright P2P)."""
        ratios, counts = inlier_ratios(in2d, self.p.offsets)
        p = pair_sample_chance(ratios, counts, 2)
        if not self.use_3d and self.consensus_scale:
            return missed_by_draws(p, samples)
        r2d = np.count_nonzero(in2d) / max(len(in2d), 1)
        if not self.use_3d:
            return missed_by_draws(p * r2d, samples)
        r3d = np.count_nonzero(in3d) / max(len(in3d), 1)
        third = samples // 3
        return (
            missed_by_draws(p * r2d, third) * missed_by_draws(p * r3d, third) * missed_by_draws(r3d**2, third)
        )

    def _generate_consensus(
        self, rng: np.random.Generator, n: int, stats: RansacStatistics
    ) -> tuple[np.ndarray, np.ndarray]:
        """2p1p with the third datum chosen by consensus instead of at random.

        The ``n`` minimal samples are pairs of matches of one reference (the pair drawn in
        proportion to its matches, as in the paper); their planar relative poses are scored on
        their own pair and the ``top_k`` best per pair kept (stage 1,
        :func:`~planarloc.robust.consensus_scale.planar_relative_candidates`). For each, eq. (18)
        is solved for every match of the other pairs at once: the scale ρ supported by the most of
        them is the hypothesis (:func:`~planarloc.robust.consensus_scale.hypotheses_2p1p_consensus`;
        both stages in one call, :func:`~planarloc.robust.consensus_scale.consensus_2p1p`). A
        random third match is an inlier with probability w; the consensus scale needs only some
        inliers among all the other pairs' matches, so at 60 % outliers the hypotheses are those of
        the all-inlier samples.
        """
        if not self._any_eligible:
            return np.zeros((0, 3, 3)), np.zeros((0, 3))
        R, t = consensus_2p1p(rng.random((n, 4)), self.p.arrays, self._consensus, self.counters)
        self._flush(stats)
        return R, t

    def generate(
        self, rng: np.random.Generator, n: int, stats: RansacStatistics
    ) -> tuple[np.ndarray, np.ndarray]:
        if not self.use_3d and self.consensus_scale:
            return self._generate_consensus(rng, n, stats)
        p = self.p
        u = rng.random((n, 5))
        samples = np.empty((n, 3), dtype=np.int64)
        pj = np.empty(n, dtype=np.int64)
        pk = np.empty(n, dtype=np.int64)
        draw_pair_samples(u, p.offsets, 2, 1, samples, pj, pk)
        third_3d = np.zeros(n, dtype=np.bool_)
        R_up = np.zeros((0, 3, 3))
        t_up = np.zeros((0, 3))
        if self.use_3d:
            # Structure mode: a third of the samples take the scale from a 2D-3D constraint,
            # a third are upright P2P samples of two 2D-3D constraints (no 2D-2D at all).
            kind = rng.integers(0, 3, n)
            kind[pk < 0] = 1 + (kind[pk < 0] % 2)
            third_3d = kind == 1
            samples[third_3d, 2] = rng.integers(0, len(p.X3d), third_3d.sum())
            up = np.flatnonzero((kind == 2) & (pj >= 0))
            if len(up) and len(p.X3d) >= 2:
                first = rng.integers(0, len(p.X3d), len(up))
                second = (first + rng.integers(1, len(p.X3d), len(up))) % len(p.X3d)
                s_up = np.stack([first, second], axis=1)
                upright = Hypotheses.empty(2 * len(up), self.counters)
                m_up = hypotheses_up2p(s_up, pj[up], p.arrays, upright)
                R_up, t_up = upright.first(m_up)
            keep = kind != 2
            samples, pj, pk, third_3d = samples[keep], pj[keep], pk[keep], third_3d[keep]
        ok = (pk >= 0) | third_3d
        samples, pj, pk, third_3d = samples[ok], pj[ok], pk[ok], third_3d[ok]
        found = Hypotheses.empty(2 * len(samples), self.counters)
        m = hypotheses_2p1p(samples, third_3d, pj, pk, p.arrays, found)
        self._flush(stats)
        R, t = found.first(m)
        return np.concatenate([R, R_up]), np.concatenate([t, t_up])


RelposeBatchSolver = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]


@functools.lru_cache(maxsize=64)
def _pairs_of_pairs(num_pairs: int) -> tuple[np.ndarray, np.ndarray]:
    """(j, k) index arrays of every two of ``num_pairs`` pairs, j < k (read-only; cached: numpy's
    ``triu_indices`` costs ~12 µs, a sizeable share of the short 6DoF check of a planar pose)."""
    j, k = np.triu_indices(num_pairs, 1)
    j.setflags(write=False)
    k.setflags(write=False)
    return j, k


def _baseline_solver(method: Method) -> tuple[int, RelposeBatchSolver]:
    if method == Method.P2P2:
        return 2, planar_2p_batch_unchecked
    if method == Method.NISTER:
        from planarloc.solvers.relpose_5p_nister import relpose_5p_nister_batch_unchecked

        return 5, relpose_5p_nister_batch_unchecked
    if method == Method.STEWENIUS:
        from planarloc.solvers.relpose_5p_stewenius import relpose_5p_stewenius_batch_unchecked

        return 5, relpose_5p_stewenius_batch_unchecked
    if method == Method.EIGHT:
        from planarloc.solvers.relpose_8p import relpose_8p_batch_unchecked

        return 8, relpose_8p_batch_unchecked
    raise ValueError(f"no relative-pose solver for {method}")


class RelativePairEstimator(ProblemEstimator):
    """2p2p and the 5p5p / 8p8p baselines, in the paper's two stages (Sec. IV-B).

    Stage 1, per pair: relative poses from ``n`` minimal samples of that pair, scored by
    MSAC over the pair's matches; the ``top_k`` best distinct ones are kept. Stage 2, for
    every two pairs (j, k): Rcheck (eq. 12), triangulation (eq. 13-15), Pdcheck and the
    consistency check on each combination of their kept relative poses. A stage-1 sample
    needs only ``m`` inliers of one pair (not ``2m`` across two pairs), which is what makes
    2p2p robust at high outlier rates.
    """

    top_k = 3

    def __init__(self, problem: AbsolutePoseProblem, options: RansacOptions, method: Method) -> None:
        super().__init__(problem, options)
        self.m, self.solver = _baseline_solver(method)
        self.sample_size = self.m
        self.cos_rcheck = float(np.cos(np.radians(options.rcheck_deg)))
        self.cos_consistency = float(np.cos(np.radians(options.consistency_deg)))
        self.fallback_3d = method == Method.P2P2 and len(problem.X3d) > 0
        self._planar = Planar2p1pEstimator(problem, options) if self.fallback_3d else None
        # 6DoF families with 2D-3D constraints also draw P3P samples (PoseLib's hybrid estimator
        # samples its 2D-3D and 2D-2D solvers side by side).
        self.p3p = method != Method.P2P2 and len(problem.X3d) >= 3
        self._pair_pairs = _pairs_of_pairs(problem.num_pairs)  # every two pairs (j < k), stage 2
        self._eligible = np.flatnonzero(problem.counts >= self.m).astype(np.int64)  # sampled in stage 1

    def missed(self, in2d: np.ndarray, in3d: np.ndarray, samples: int) -> float:
        """Stage 1 draws ``samples`` samples of ``m`` matches in every map image; a pose needs an
        all-inlier one in two images (stage 2 pairs them); with 2D-3D constraints, P3P samples
        (6DoF families) or 2p1p ones (2p2p) may find it as well."""
        ratios, counts = inlier_ratios(in2d, self.p.offsets)
        missed = missed_by_pairs(ratios, counts, self.m, samples)
        if self.p3p:
            missed *= missed_by_draws((np.count_nonzero(in3d) / max(len(in3d), 1)) ** 3, samples)
        if self._planar is not None:
            missed *= self._planar.missed(in2d, in3d, samples)
        return missed

    def generate(
        self, rng: np.random.Generator, n: int, stats: RansacStatistics
    ) -> tuple[np.ndarray, np.ndarray]:
        """Stage 1 (per map image of enough matches, ``n`` samples, up to ``top_k`` distinct best
        relative poses) and stage 2 (every two images' kept poses combined): the solver between
        two kernels of :mod:`planarloc.robust.relative_stages`."""
        p = self.p
        sample_pair, xq, xr = relative_samples(
            rng.random((len(self._eligible) * n, self.m)), p.arrays, self._eligible, n, self.m
        )
        R, t, valid = self.solver(xq, xr)
        pj, pk = self._pair_pairs
        R, t = hypotheses_of_relative_samples(
            RelativePoses(np.ascontiguousarray(R), np.ascontiguousarray(t), np.ascontiguousarray(valid)),
            sample_pair,
            self._eligible,
            n,
            p.arrays,
            self.threshold_sq,
            self.top_k,
            pj,
            pk,
            self.cos_rcheck,
            self.cos_consistency,
            self.counters,
        )
        self._flush(stats)
        if self._planar is not None:
            # Structure mode: the 2p relative pose of pair j with the scale from a 2D-3D
            # constraint survives collinear geometry, where eq. (15) is singular.
            R3, t3 = self._planar.generate(rng, n, stats)
            R, t = np.concatenate([R, R3]), np.concatenate([t, t3])
        if self.p3p:
            R3, t3 = self._generate_p3p(rng, n, stats)
            R, t = np.concatenate([R, R3]), np.concatenate([t, t3])
        return R, t

    def _generate_p3p(
        self, rng: np.random.Generator, n: int, stats: RansacStatistics
    ) -> tuple[np.ndarray, np.ndarray]:
        """P3P hypotheses from ``n`` samples of three distinct 2D-3D constraints."""
        p = self.p
        samples = np.empty((n, 3), dtype=np.int64)
        draw_within_pairs(
            rng.random((n, 3)),
            np.array([0, len(p.X3d)], dtype=np.int64),
            np.zeros(n, dtype=np.int64),
            3,
            samples,
        )
        found = Hypotheses.empty(4 * n, self.counters)
        m = hypotheses_p3p(samples, p.arrays, found)
        self._flush(stats)
        return found.first(m)


class RectifiedHypotheses:
    """A planar hypothesis family run on the gravity-levelled problem, scored on the original.

    ``hypotheses`` works on the same problem with query bearings ``U_q x``, reference
    bearings ``U_k x`` and reference poses ``U_k · ref_from_world`` (:func:`rectify_problem`),
    so upright frames are related by the planar model; a hypothesis ``upright_from_world`` of
    the query is returned as ``cam_from_world = U_qᵀ · upright_from_world``. Scoring, local
    optimisation (planar, then 6DoF, which refines a residual tilt away) and refinement are the
    original problem's (``scorer``).
    """

    def __init__(
        self,
        hypotheses: Planar2p1pEstimator | RelativePairEstimator,
        scorer: ProblemEstimator,
        upright_from_query: np.ndarray,
    ) -> None:
        self.hypotheses = hypotheses
        self.scorer = scorer
        self.p = scorer.p
        self.options = scorer.options
        self.sample_size = hypotheses.sample_size
        self.num_data = scorer.num_data
        self.Uq_T = np.ascontiguousarray(upright_from_query.T)

    def generate(
        self, rng: np.random.Generator, n: int, stats: RansacStatistics
    ) -> tuple[np.ndarray, np.ndarray]:
        R, t = self.hypotheses.generate(rng, n, stats)
        return np.ascontiguousarray(self.Uq_T @ R), np.ascontiguousarray(t @ self.Uq_T.T)

    def missed(self, in2d: np.ndarray, in3d: np.ndarray, samples: int) -> float:
        """The levelled family's (it draws the samples; the rows are the original problem's)."""
        return self.hypotheses.missed(in2d, in3d, samples)

    def __getattr__(
        self, name: str
    ):  # score, refine, inliers, distinct, _refine, refine_full: the original problem's
        return getattr(self.scorer, name)


def _rotate_rays(x: np.ndarray, U: np.ndarray) -> np.ndarray:
    """Rays ``U x`` rescaled to z = 1 (normalised coordinates of the levelled camera) where
    z stays clearly positive, so pixel-scaled errors keep their meaning."""
    y = x @ U.T if U.ndim == 2 else np.einsum("nij,nj->ni", U, x)
    z = y[:, 2:3]
    return np.ascontiguousarray(np.where(z > 0.05, y / np.where(z > 0.05, z, 1.0), y))


def rectify_problem(
    p: AbsolutePoseProblem, upright_from_query: np.ndarray, upright_from_refs: np.ndarray
) -> AbsolutePoseProblem:
    """The problem seen from gravity-levelled frames.

    Args:
        p: the original problem.
        upright_from_query: (3, 3) ``U_q`` of the query; upright_from_refs: (P, 3, 3) ``U_k``.

    Returns:
        a problem with ``xq ← U_q xq``, ``xr ← U_k xr`` (pair k), ``ref_R ← U_k ref_R``,
        ``ref_t ← U_k ref_t``, ``xq3d ← U_q xq3d``; world points unchanged.
    """
    Ur = upright_from_refs[p.pair]
    arrays = p.arrays._replace(
        xq=_rotate_rays(p.xq, upright_from_query),
        xr=_rotate_rays(p.xr, Ur),
        ref_R=np.ascontiguousarray(upright_from_refs @ p.ref_R),
        ref_t=np.ascontiguousarray(np.einsum("pij,pj->pi", upright_from_refs, p.ref_t)),
        xq3d=_rotate_rays(p.xq3d, upright_from_query) if len(p.xq3d) else p.xq3d,
    )
    return dataclasses.replace(p, arrays=arrays)
