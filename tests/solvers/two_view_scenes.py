"""Random two-view scenes shared by the relative-pose solver tests (generated data only)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def random_relpose(rng, planar=False, max_angle=1.0, min_baseline=0.3):
    """ref_from_query (R, t): general 6DoF, or planar (yaw about y, t in the x-z plane)."""
    if planar:
        R = Rotation.from_rotvec([0.0, rng.uniform(-max_angle, max_angle), 0.0]).as_matrix()
        phi = rng.uniform(-np.pi, np.pi)
        t = -R @ (rng.uniform(min_baseline, 2.0) * np.array([np.sin(phi), 0.0, np.cos(phi)]))
    else:
        axis = rng.normal(size=3)
        R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * rng.uniform(0.0, max_angle)).as_matrix()
        t = rng.normal(size=3)
        t *= rng.uniform(min_baseline, 2.0) / np.linalg.norm(t)
    return R, t


def make_scene(rng, n=5, planar=False, noise=0.0, max_angle=1.0, R=None, t=None):
    """Points uniform in [-10, 10]³ (query frame) with depth > 0.5 in both cameras.

    Returns normalized homogeneous x_query, x_ref (n, 3), the true R and unit t.
    """
    if R is None:
        R, t = random_relpose(rng, planar, max_angle)
    X = np.empty((0, 3))
    while len(X) < n:
        P = rng.uniform(-10.0, 10.0, size=(8 * n, 3))
        Q = P @ R.T + t
        X = np.vstack([X, P[(P[:, 2] > 0.5) & (Q[:, 2] > 0.5)]])
    X = X[:n]
    Y = X @ R.T + t
    xq, xr = X / X[:, 2:], Y / Y[:, 2:]
    if noise > 0:
        xq[:, :2] += rng.normal(scale=noise, size=(n, 2))
        xr[:, :2] += rng.normal(scale=noise, size=(n, 2))
    return xq, xr, R, t / np.linalg.norm(t)


def pose_error(pose, R, t):
    return max(np.abs(pose.R - R).max(), np.abs(pose.t - t).max())


def unit_relpose(ref_cam_from_world, query_cam_from_world):
    """``ref_from_query`` with its translation scaled to unit length, and the true scale ρ."""
    from planarloc.geometry.pose import Pose

    rel = ref_cam_from_world @ query_cam_from_world.inverse()
    rho = float(np.linalg.norm(rel.t))
    return Pose(rel.R, rel.t / rho), rho


def e_distance(A, B):
    """Distance of two essential matrices up to scale and sign."""
    A = A / np.linalg.norm(A)
    B = B / np.linalg.norm(B)
    return min(np.abs(A - B).max(), np.abs(A + B).max())


def unit(x):
    """The rows of ``x`` (n, 3) scaled to unit length (bearings)."""
    return x / np.linalg.norm(x, axis=1, keepdims=True)
