"""The estimator's input: matches between the query and one reference image with a known pose."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.pose import Pose
from planarloc.geometry.validation import InputError, check_array


def unit_gravity(name: str, gravity: object) -> np.ndarray:
    """(3,) unit vector from a finite, non-zero (3,) gravity direction; InputError otherwise."""
    g = check_array(name, gravity, (3,))
    n = float(np.linalg.norm(g))
    if not n > 1e-9:
        raise InputError(f"{name}: expected a non-zero gravity direction (gx, gy, gz), got {g.tolist()}")
    return g / n


@dataclass(frozen=True, eq=False)
class PairMatches:
    """2D-2D matches between the query and one retrieved reference image.

    Attributes:
        ref_pose: the reference's ``cam_from_world`` (known from the map).
        ref_camera: the reference's intrinsics.
        query_points: (N, 2) pixel coordinates of the matched query keypoints.
        ref_points: (N, 2) pixel coordinates of the matched reference keypoints.
        query_indices: (N,) ids of the query keypoints, or None. The same id in several
            pairs means the same query keypoint, which links matches into tracks
            (``structure="tracks"``). Must be unique within one pair.
        ref_points3d: (N, 3) world points of the matched reference keypoints where they are
            known (depth, or local structure triangulated from the retrieved map images), NaN
            rows elsewhere; or None. Each becomes a 2D-3D constraint on the query.
        ref_points3d_cov: (N, 3, 3) covariance (m²) of ``ref_points3d`` (NaN rows where there
            is no point), or None for exact points. Propagated into the query's position
            uncertainty (a point triangulated at a small angle is uncertain in depth).
        ref_points3d_partner: (N,) the other map image each point of ``ref_points3d`` was
            triangulated with: an index into the list of pairs given to the estimator, or a value
            >= its length for a map image that is not among them (equal values: the same image);
            -1 where the point does not depend on map poses (or there is none). None: no point
            does.
        ref_points3d_pose_jac: (N, 2, 3, 6) motion of each point under corrections ``(ω, d)`` of
            the pose of this reference (``[:, 0]``) and of its partner (``[:, 1]``): rotation
            ``R' = Exp(ω) R`` (radians, camera frame) and centre shift ``d`` (metres, world), as in
            :func:`~planarloc.geometry.epipolar.triangulation_uncertainty`; rows without a
            partner are ignored. Given with ``ref_points3d_partner``. The map's pose uncertainty
            (``RansacOptions.map_rotation_std_deg``, ``map_position_std_m``) moves all points of
            one map image together, and this is how the query's position inherits it.
        ref_gravity: (3,) direction of gravity (pointing down) in the reference camera frame,
            or None for an upright reference (camera y-axis = gravity, the paper's assumption).
            Normalised on construction. The planar solvers run on bearings rotated so that
            this direction becomes the camera y-axis (docs/conventions.md, "Gravity").

    Raises:
        InputError: on shape mismatches, non-finite pixels, or a ``ref_pose`` that is not a Pose.
    """

    ref_pose: Pose
    ref_camera: Camera
    query_points: np.ndarray
    ref_points: np.ndarray
    query_indices: np.ndarray | None = None
    ref_points3d: np.ndarray | None = None
    ref_gravity: np.ndarray | None = None
    ref_points3d_cov: np.ndarray | None = None
    ref_points3d_partner: np.ndarray | None = None
    ref_points3d_pose_jac: np.ndarray | None = None

    def __post_init__(self) -> None:
        _check_pose_and_camera(self.ref_pose, self.ref_camera)
        q = check_array("PairMatches.query_points", self.query_points, (None, 2))
        n = len(q)
        r = check_array("PairMatches.ref_points", self.ref_points, (n, 2))
        object.__setattr__(self, "query_points", q)
        object.__setattr__(self, "ref_points", r)
        if self.query_indices is not None:
            object.__setattr__(self, "query_indices", _checked_query_indices(self.query_indices, n))
        X = None if self.ref_points3d is None else _checked_points3d(self.ref_points3d, n)
        object.__setattr__(self, "ref_points3d", X)
        if self.ref_points3d_cov is not None:
            if X is None:
                raise InputError("PairMatches.ref_points3d_cov: given without ref_points3d")
            object.__setattr__(self, "ref_points3d_cov", _checked_points3d_cov(self.ref_points3d_cov, X))
        if (self.ref_points3d_partner is None) != (self.ref_points3d_pose_jac is None):
            raise InputError(
                "PairMatches.ref_points3d_partner and ref_points3d_pose_jac: give both or neither"
            )
        if self.ref_points3d_partner is not None:
            if X is None:
                raise InputError("PairMatches.ref_points3d_partner: given without ref_points3d")
            partner, jac = _checked_partners(self.ref_points3d_partner, self.ref_points3d_pose_jac, X)
            object.__setattr__(self, "ref_points3d_partner", partner)
            object.__setattr__(self, "ref_points3d_pose_jac", jac)

        if self.ref_gravity is not None:
            object.__setattr__(self, "ref_gravity", unit_gravity("PairMatches.ref_gravity", self.ref_gravity))

    def __len__(self) -> int:
        return len(self.query_points)


def _check_pose_and_camera(ref_pose: object, ref_camera: object) -> None:
    """InputError unless ``ref_pose`` is a Pose and ``ref_camera`` a Camera."""
    if not isinstance(ref_pose, Pose):
        raise InputError(f"PairMatches.ref_pose: expected a planarloc.Pose, got {type(ref_pose).__name__}")
    if not isinstance(ref_camera, Camera):
        raise InputError(
            f"PairMatches.ref_camera: expected a planarloc.Camera, got {type(ref_camera).__name__}"
        )


def _checked_query_indices(query_indices: object, n: int) -> np.ndarray:
    """(n,) int64 query keypoint ids: whole numbers, unique within the pair."""
    raw = check_array("PairMatches.query_indices", query_indices, (n,), dtype=np.float64)
    ids = raw.astype(np.int64)
    if np.any(ids != raw):  # 2.5 would silently become keypoint 2 (another track)
        bad = int(np.argmax(ids != raw))
        raise InputError(f"PairMatches.query_indices: expected whole numbers, got {raw[bad]} at index {bad}")
    if len(np.unique(ids)) != n:
        raise InputError("PairMatches.query_indices: ids must be unique within one pair")
    return ids


def _checked_points3d(ref_points3d: object, n: int) -> np.ndarray:
    """(n, 3) world points: rows all finite or all NaN (no point), never inf."""
    X = check_array("PairMatches.ref_points3d", ref_points3d, (n, 3), finite=False)
    if np.any(np.isinf(X)):
        raise InputError("PairMatches.ref_points3d: contains inf; use NaN rows for missing depth")
    partial = np.isnan(X).any(axis=1) & ~np.isnan(X).all(axis=1)
    if partial.any():
        raise InputError("PairMatches.ref_points3d: rows must be all finite or all NaN")
    return X


def _checked_points3d_cov(ref_points3d_cov: object, X: np.ndarray) -> np.ndarray:
    """(n, 3, 3) covariances of the points ``X`` (n, 3): finite, symmetric and of non-negative
    trace where ``X`` has a point."""
    C = check_array("PairMatches.ref_points3d_cov", ref_points3d_cov, (len(X), 3, 3), finite=False)
    has = ~np.isnan(X[:, 0])
    if not np.isfinite(C[has]).all():
        raise InputError("PairMatches.ref_points3d_cov: must be finite where ref_points3d has a point")
    sym = C[has]
    if np.any(np.abs(sym - sym.transpose(0, 2, 1)) > 1e-9 * (1.0 + np.abs(sym).max(initial=0.0))) or np.any(
        np.einsum("nii->n", sym) < 0
    ):
        raise InputError(
            "PairMatches.ref_points3d_cov: expected symmetric positive semi-definite (3, 3) covariances"
        )
    return C


def _checked_partners(
    ref_points3d_partner: object, ref_points3d_pose_jac: object, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(n,) int64 partner map images (whole numbers >= -1) and their (n, 2, 3, 6) pose Jacobians
    of the points ``X`` (n, 3), finite where a point has a partner."""
    n = len(X)
    raw = check_array("PairMatches.ref_points3d_partner", ref_points3d_partner, (n,), dtype=np.float64)
    partner = raw.astype(np.int64)
    if np.any(partner != raw) or np.any(partner < -1):
        bad = int(np.argmax((partner != raw) | (partner < -1)))
        raise InputError(
            f"PairMatches.ref_points3d_partner: expected whole numbers >= -1, got {raw[bad]} at index {bad}"
        )
    jac = check_array("PairMatches.ref_points3d_pose_jac", ref_points3d_pose_jac, (n, 2, 3, 6), finite=False)
    used = (partner >= 0) & ~np.isnan(X[:, 0])
    if not np.isfinite(jac[used]).all():
        raise InputError("PairMatches.ref_points3d_pose_jac: must be finite where a point has a partner")
    return partner, jac
