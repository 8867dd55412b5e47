"""Structure-aware constraints without a pre-built 3D model ("tracks" mode).

A query keypoint matched in two or more retrieved references forms a track; since the
references' poses are known, the track's 3D point is triangulated from the reference
observations alone, and becomes a 2D-3D constraint on the query. This removes the scale
degeneracy of 2D-2D constraints when the query is collinear with the reference centres
(straight corridors and roads; see NOTES.md, KITTI measurement). Not in the paper.
"""

from __future__ import annotations

import numpy as np

from planarloc.geometry.epipolar import triangulate_points, triangulation_uncertainty
from planarloc.robust.problem import AbsolutePoseProblem

KEYPOINT_STD_PX = 1.0
"""Assumed localisation noise of a map keypoint (pixels, per axis): the covariance of every
point triangulated from map images (tracks here, local structure in the localizer)."""


def triangulate_tracks(
    problem: AbsolutePoseProblem, max_reproj_px: float, min_angle_deg: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Triangulate every query keypoint seen in two or more references.

    Query keypoints that already have a 2D-3D constraint (``problem.source3d`` rows: depth or
    local structure) are skipped: one constraint per query keypoint.

    For each track, all pairs of its reference observations are triangulated (midpoint) and
    the one with the widest triangulation angle whose point reprojects within
    ``max_reproj_px`` in both references, in front of both, is kept.

    Args:
        problem: flattened matches with ``query_ids`` (tracks need ids; -1 rows are ignored).
        max_reproj_px: reprojection tolerance in the two references, pixels.
        min_angle_deg: minimum triangulation angle.

    Returns:
        xq3d (T, 3) query rays, X3d (T, 3) world points, their covariance (T, 3, 3) (from
        ``KEYPOINT_STD_PX``), the two pairs (T, 2) whose references triangulated each and the
        points' motion under corrections of those references' poses (T, 2, 3, 6)
        (:func:`~planarloc.geometry.epipolar.triangulation_uncertainty`) of the accepted tracks.
    """
    none = (
        np.zeros((0, 3)),
        np.zeros((0, 3)),
        np.zeros((0, 3, 3)),
        np.zeros((0, 2), dtype=np.int64),
        np.zeros((0, 2, 3, 6)),
    )
    a, b = _track_observation_pairs(problem)
    if len(a) == 0:
        return none
    X, angle, err = _triangulate_observation_pairs(problem, a, b)
    ok = np.isfinite(X).all(axis=1) & (angle >= min_angle_deg) & (err <= max_reproj_px)
    if not ok.any():
        return none
    # Keep the widest-angle valid triangulation per track.
    track = problem.query_ids[a]
    cand = np.flatnonzero(ok)
    cand = cand[np.lexsort((-angle[cand], track[cand]))]
    first = np.r_[True, track[cand][1:] != track[cand][:-1]]
    keep = cand[first]
    pa, pb = problem.pair[a[keep]], problem.pair[b[keep]]
    cov, jac = triangulation_uncertainty(
        X[keep],
        (problem.ref_R[pa], problem.ref_t[pa]),
        (problem.ref_R[pb], problem.ref_t[pb]),
        problem.f_ref[pa],
        problem.f_ref[pb],
        KEYPOINT_STD_PX,
    )
    good = np.isfinite(cov).all(axis=(1, 2)) & np.isfinite(jac).all(axis=(1, 2, 3))
    keep, cov, jac = keep[good], cov[good], jac[good]
    views = np.stack([pa[good], pb[good]], axis=1).astype(np.int64)
    return (
        np.ascontiguousarray(problem.xq[a[keep]]),
        np.ascontiguousarray(X[keep]),
        np.ascontiguousarray(cov),
        np.ascontiguousarray(views),
        np.ascontiguousarray(jac),
    )


def _track_observation_pairs(problem: AbsolutePoseProblem) -> tuple[np.ndarray, np.ndarray]:
    """Match rows ``a``, ``b`` (K,) of every two observations of one track (the same query
    keypoint id) in different pairs; query keypoints with a 2D-3D constraint already
    (``problem.source3d``) are left out."""
    ids = problem.query_ids
    rows = np.flatnonzero(ids >= 0)
    src = problem.source3d[problem.source3d >= 0]
    if len(src):
        rows = rows[~np.isin(ids[rows], ids[src])]
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = rows[np.argsort(ids[rows], kind="stable")]
    sid = ids[order]
    starts = np.flatnonzero(np.r_[True, sid[1:] != sid[:-1]])
    ends = np.r_[starts[1:], len(sid)]
    a_idx, b_idx = [], []
    for s, e in zip(starts, ends):
        if e - s < 2:
            continue
        members = order[s:e]
        for i in range(len(members)):
            for j in range(i + 1, len(members)):
                if problem.pair[members[i]] != problem.pair[members[j]]:
                    a_idx.append(members[i])
                    b_idx.append(members[j])
    return np.asarray(a_idx, dtype=np.int64), np.asarray(b_idx, dtype=np.int64)


def _triangulate_observation_pairs(
    problem: AbsolutePoseProblem, a: np.ndarray, b: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoint triangulation of the reference observations ``a``, ``b`` (K,) of each track:
    world points (K, 3), triangulation angles (K,) in degrees and the larger reprojection error
    in the two references (K,) in pixels."""
    pa, pb = problem.pair[a], problem.pair[b]
    X = np.empty((len(a), 3))
    angle = np.empty(len(a))
    err = np.empty(len(a))
    for p1 in np.unique(pa):
        for p2 in np.unique(pb[pa == p1]):
            sel = (pa == p1) & (pb == p2)
            Ra, ta = problem.ref_R[p1], problem.ref_t[p1]
            Rb, tb = problem.ref_R[p2], problem.ref_t[p2]
            Xs, ang = triangulate_points((Ra, ta), (Rb, tb), problem.xr[a[sel]], problem.xr[b[sel]])
            X[sel], angle[sel] = Xs, ang
            e = np.zeros(sel.sum())
            for R, t, x, f in (
                (Ra, ta, problem.xr[a[sel]], problem.f_ref[p1]),
                (Rb, tb, problem.xr[b[sel]], problem.f_ref[p2]),
            ):
                Xc = Xs @ R.T + t
                with np.errstate(invalid="ignore", divide="ignore"):
                    d = (Xc[:, :2] / Xc[:, 2:3] - x[:, :2]) * f
                    e = np.maximum(e, np.hypot(d[:, 0], d[:, 1]))
            err[sel] = e
    return X, angle, err
