"""Flattened, validated arrays of one absolute-pose problem (what the numba kernels consume)."""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from numba import njit

from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.robust.pair_matches import PairMatches


class ProblemArrays(NamedTuple):
    """The arrays of one absolute-pose problem that the numba kernels read, as one named record
    (numba compiles a ``NamedTuple`` of arrays as one argument). All matches of one query are
    concatenated over pairs (pair ``p`` owns rows ``offsets[p]:offsets[p+1]``).

    Attributes:
        xq, xr: (N, 3) normalized homogeneous query / reference points (undistorted).
        pair: (N,) pair index of each match.
        offsets: (P + 1,) row offsets of the pairs.
        f_query: (4,) pixel scales of the query's errors: (fx, fy) of the 2D-2D (Sampson)
            errors, then (fx, fy)·s of the 2D-3D reprojection errors, with ``s = τ / τ₃``
            (:meth:`AbsolutePoseProblem.with_reprojection_threshold`) so that every kernel's one
            threshold τ and loss scale apply to a reprojection error at τ₃ (default s = 1).
        f_ref: (P, 2) reference focal lengths.
        ref_R, ref_t: (P, 3, 3), (P, 3) reference ``cam_from_world``.
        xq3d: (M, 3) query rays of 2D-3D constraints; X3d: (M, 3) their world points.
    """

    xq: np.ndarray
    xr: np.ndarray
    pair: np.ndarray
    offsets: np.ndarray
    f_query: np.ndarray
    f_ref: np.ndarray
    ref_R: np.ndarray
    ref_t: np.ndarray
    xq3d: np.ndarray
    X3d: np.ndarray


@njit(cache=True)
def with_references(prob: ProblemArrays, ref_R: np.ndarray, ref_t: np.ndarray) -> ProblemArrays:
    """``prob`` with other reference poses (the map prior's nuisance refinement)."""
    return ProblemArrays(
        prob.xq, prob.xr, prob.pair, prob.offsets, prob.f_query, prob.f_ref, ref_R, ref_t, prob.xq3d, prob.X3d
    )


@dataclass(frozen=True, eq=False)
class AbsolutePoseProblem:
    """One query's problem: the kernels' arrays and what only Python reads.

    The fields of :attr:`arrays` read as the problem's own (``problem.xq``, ``problem.ref_R``, ...).

    Attributes:
        arrays: the arrays the kernels read (:class:`ProblemArrays`: matches, pairs, focal
            lengths, reference poses, 2D-3D constraints).
        query_ids: (N,) query keypoint ids (-1 when unknown).
        source3d: (M,) -1 for a triangulated track, else the match row whose reference
            gave it (depth or local structure).
        X3d_cov: (M, 3, 3) covariance of the world points (m²; zeros for exact points).
        X3d_views: (M, 2) the map images each world point was triangulated from: a pair index
            (< P), or an id >= P of a map image that is not among the pairs (equal ids, the same
            image); -1 -1 for a point that does not depend on the map's poses.
        X3d_pose_jac: (M, 2, 3, 6) the point's motion under pose corrections ``(ω, d)`` of those
            two map images (:func:`~planarloc.geometry.epipolar.triangulation_uncertainty`;
            zeros where ``X3d_views`` is -1).
    """

    arrays: ProblemArrays
    query_ids: np.ndarray
    source3d: np.ndarray
    X3d_cov: np.ndarray
    X3d_views: np.ndarray
    X3d_pose_jac: np.ndarray

    def __post_init__(self) -> None:
        # The fields of ``arrays`` as plain attributes of the problem (``problem.xq``, ...): as fast
        # to read as fields, which Python loops over the matches do.
        for name, value in zip(ProblemArrays._fields, self.arrays):
            object.__setattr__(self, name, value)

    if TYPE_CHECKING:

        def __getattr__(self, name: str) -> np.ndarray: ...  # those attributes, for the type checker

    @property
    def num_pairs(self) -> int:
        return len(self.offsets) - 1

    @cached_property
    def counts(self) -> np.ndarray:
        """(P,) matches per pair."""
        return np.diff(self.offsets)

    def with_reprojection_threshold(self, ratio: float) -> AbsolutePoseProblem:
        """This problem with 2D-3D errors scaled by ``ratio`` = τ / τ₃ (2D-2D threshold over the
        2D-3D one): kernels that threshold at τ then threshold reprojection errors at τ₃."""
        f = self.f_query.copy()
        f[2:] = f[:2] * float(ratio)
        return dataclasses.replace(self, arrays=self.arrays._replace(f_query=f))

    def points_only(self) -> AbsolutePoseProblem:
        """This problem with its 2D-3D constraints alone (no 2D-2D match in any pair): a search
        on it is judged by the constraints that fix the position, not by 2D-2D ones that may
        not (:func:`planarloc.robust.absolute_pose.estimate_absolute_pose`)."""
        return dataclasses.replace(
            self,
            arrays=self.arrays._replace(
                xq=np.zeros((0, 3)),
                xr=np.zeros((0, 3)),
                pair=np.zeros(0, dtype=np.int64),
                offsets=np.zeros_like(self.offsets),
            ),
            query_ids=np.zeros(0, dtype=np.int64),
        )

    def with_points3d(
        self,
        xq3d: np.ndarray,
        X3d: np.ndarray,
        source3d: np.ndarray,
        X3d_cov: np.ndarray | None = None,
        X3d_views: np.ndarray | None = None,
        X3d_pose_jac: np.ndarray | None = None,
    ) -> AbsolutePoseProblem:
        """This problem with more 2D-3D constraints appended (``X3d_cov`` None: exact points;
        ``X3d_views`` and ``X3d_pose_jac`` None: points that do not depend on the map's poses)."""
        m = len(X3d)
        cov = np.zeros((m, 3, 3)) if X3d_cov is None else X3d_cov
        views = np.full((m, 2), -1, dtype=np.int64) if X3d_views is None else X3d_views
        jac = np.zeros((m, 2, 3, 6)) if X3d_pose_jac is None else X3d_pose_jac
        return AbsolutePoseProblem(
            self.arrays._replace(
                xq3d=np.ascontiguousarray(np.vstack([self.xq3d, xq3d])),
                X3d=np.ascontiguousarray(np.vstack([self.X3d, X3d])),
            ),
            self.query_ids,
            np.concatenate([self.source3d, source3d]).astype(np.int64),
            np.ascontiguousarray(np.concatenate([self.X3d_cov, cov])),
            np.ascontiguousarray(np.concatenate([self.X3d_views, views]).astype(np.int64)),
            np.ascontiguousarray(np.concatenate([self.X3d_pose_jac, jac])),
        )


@njit(cache=True)
def _affine_rays(pixels: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    out = np.empty((pixels.shape[0], 3))
    for i in range(pixels.shape[0]):
        out[i, 0] = (pixels[i, 0] - cx) / fx
        out[i, 1] = (pixels[i, 1] - cy) / fy
        out[i, 2] = 1.0
    return out


def _rays(camera: Camera, pixels: np.ndarray) -> np.ndarray:
    """(N, 3) rays ``(x, y, 1)`` of validated (N, 2) pixels (``PairMatches`` checked them).

    Cameras without distortion take the direct affine map in one compiled call:
    ``Camera.bearings_from_img`` re-validates its input and stacks, which costs more than the
    arithmetic for the few hundred points of one query."""
    if camera.has_distortion:
        return camera.bearings_from_img(pixels)
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    return _affine_rays(pixels, float(fx), float(fy), float(cx), float(cy))


def _check_rays(rays: np.ndarray, offsets: np.ndarray, name: str) -> None:
    """InputError naming the first pixel whose undistortion did not converge (NaN ray)."""
    if np.isfinite(rays.sum()):
        return
    bad = int(np.flatnonzero(~np.isfinite(rays).all(axis=1))[0])
    p_idx = int(np.searchsorted(offsets, bad, side="right") - 1)
    raise InputError(
        f"pairs[{p_idx}].{name}[{bad - int(offsets[p_idx])}]: pixel outside the valid range of the camera's "
        "distortion model (undistortion does not converge); drop such keypoints or check the intrinsics"
    )


def build_problem(query_camera: Camera, pairs: Sequence[PairMatches]) -> AbsolutePoseProblem:
    """Validate the estimator's input and flatten it.

    Raises:
        InputError: not a Camera, not a sequence of PairMatches, or fewer than two pairs.
    """
    if not isinstance(query_camera, Camera):
        raise InputError(f"query_camera: expected a planarloc.Camera, got {type(query_camera).__name__}")
    if isinstance(pairs, PairMatches) or not isinstance(pairs, Sequence):
        raise InputError("pairs: expected a list of PairMatches (one per retrieved reference image)")
    for i, p in enumerate(pairs):
        if not isinstance(p, PairMatches):
            raise InputError(f"pairs[{i}]: expected PairMatches, got {type(p).__name__}")
    if len(pairs) < 2:
        raise InputError(
            f"pairs: need matches to at least 2 reference images to fix the scale, got {len(pairs)}; "
            "hint: retrieve more reference images (top-n >= 2)"
        )
    xq3, X3, src, cov3, views3, jac3 = [], [], [], [], [], []
    counts = [len(p.query_points) for p in pairs]
    offsets = np.array([0, *itertools.accumulate(counts)], dtype=np.int64)
    # One undistortion call for all query points (same camera); references may differ.
    xq_all = _rays(query_camera, np.concatenate([p.query_points for p in pairs]))
    _check_rays(xq_all, offsets, "query_points")
    cam0 = pairs[0].ref_camera
    if all(p.ref_camera is cam0 or p.ref_camera == cam0 for p in pairs):  # one map camera: one call
        xr_all = _rays(cam0, np.concatenate([p.ref_points for p in pairs]))
    else:
        xr_all = np.concatenate(
            [_rays(p.ref_camera, p.ref_points) if len(p) else np.zeros((0, 3)) for p in pairs]
        )
    for p_idx, p in enumerate(pairs):
        base, n = int(offsets[p_idx]), counts[p_idx]
        if p.ref_points3d is not None and n:
            has = ~np.isnan(p.ref_points3d[:, 0])
            xq3.append(xq_all[base : base + n][has])
            X3.append(p.ref_points3d[has])
            src.append(base + np.flatnonzero(has))
            k = int(has.sum())
            cov3.append(np.zeros((k, 3, 3)) if p.ref_points3d_cov is None else p.ref_points3d_cov[has])
            views, jac = np.full((k, 2), -1, dtype=np.int64), np.zeros((k, 2, 3, 6))
            if p.ref_points3d_partner is not None and p.ref_points3d_pose_jac is not None:  # both or neither
                partner = p.ref_points3d_partner[has]
                dep = partner >= 0
                views[dep, 0], views[dep, 1] = p_idx, partner[dep]
                jac[dep] = p.ref_points3d_pose_jac[has][dep]
            views3.append(views)
            jac3.append(jac)
    _check_rays(xr_all, offsets, "ref_points")
    pair = np.repeat(np.arange(len(pairs), dtype=np.int64), counts)
    if all(p.query_indices is None for p in pairs):
        qids = np.full(len(xq_all), -1, dtype=np.int64)
    else:
        qids = np.concatenate(
            [
                p.query_indices if p.query_indices is not None else np.full(len(p), -1, dtype=np.int64)
                for p in pairs
            ]
        ).astype(np.int64)
    arrays = ProblemArrays(
        xq=xq_all,
        xr=xr_all,
        pair=pair,
        offsets=offsets,
        f_query=np.asarray(query_camera.focal * 2, dtype=float),
        f_ref=np.asarray([p.ref_camera.focal for p in pairs], dtype=float),
        ref_R=np.array([p.ref_pose.R for p in pairs]),
        ref_t=np.array([p.ref_pose.t for p in pairs]),
        xq3d=np.ascontiguousarray(np.vstack(xq3)) if xq3 else np.zeros((0, 3)),
        X3d=np.ascontiguousarray(np.vstack(X3)) if X3 else np.zeros((0, 3)),
    )
    return AbsolutePoseProblem(
        arrays=arrays,
        query_ids=qids,
        source3d=np.concatenate(src).astype(np.int64) if src else np.zeros(0, dtype=np.int64),
        X3d_cov=np.ascontiguousarray(np.concatenate(cov3)) if cov3 else np.zeros((0, 3, 3)),
        X3d_views=np.ascontiguousarray(np.concatenate(views3))
        if views3
        else np.zeros((0, 2), dtype=np.int64),
        X3d_pose_jac=np.ascontiguousarray(np.concatenate(jac3)) if jac3 else np.zeros((0, 2, 3, 6)),
    )
