"""Random multi-view planar scenes for tests and benchmarks (the paper's Sec. V-A protocol).

3D points uniform in ``[-10, 10]³``; upright cameras (y = gravity) at height 0 with centres
``x, z ∈ [-5, 5]`` and yaw ``∈ [-π, π]``; ``f = 800``, 1280×1080, principal point
(640, 540); each reference sees ``matches_per_pair`` points that the query sees too; pixel
noise; outliers made by projecting the point with a different random planar pose (the
authors' scripts). Query keypoint ids are the point ids, so a point matched in several
references forms a track.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from planarloc.geometry.camera import Camera
from planarloc.geometry.planar import rotation_from_yaw
from planarloc.geometry.pose import Pose
from planarloc.gravity.upright import upright_from_cam_rotation
from planarloc.robust.pair_matches import PairMatches

PAPER_CAMERA = Camera("PINHOLE", 1280, 1080, (800.0, 800.0, 640.0, 540.0))


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """A generated query with its matches to posed references.

    Attributes:
        query_camera: intrinsics of every camera.
        query_pose: ground-truth ``cam_from_world`` of the query.
        pairs: one :class:`PairMatches` per reference.
        points: (K, 3) world points (row = query keypoint id).
        is_outlier: one (N_k,) bool array per pair.
    """

    query_camera: Camera
    query_pose: Pose
    pairs: list[PairMatches]
    points: np.ndarray
    is_outlier: list[np.ndarray]


def random_planar_pose(rng: np.random.Generator, extent: float = 5.0, tilt_deg: float = 0.0) -> Pose:
    """Upright ``cam_from_world`` with centre (x, 0, z), x, z ∈ [-extent, extent], yaw ∈ [-π, π].

    ``tilt_deg`` > 0 adds random pitch and roll of that standard deviation (uneven floor)."""
    R = rotation_from_yaw(rng.uniform(-np.pi, np.pi))
    if tilt_deg > 0:
        from scipy.spatial.transform import Rotation

        pitch, roll = np.radians(rng.normal(0.0, tilt_deg, 2))
        R = Rotation.from_euler("xz", [pitch, roll]).as_matrix() @ R
    c = np.array([rng.uniform(-extent, extent), 0.0, rng.uniform(-extent, extent)])
    return Pose(R, -R @ c)


def gravity_world(scene: SyntheticScene, world_from_upright: Pose | None = None) -> np.ndarray:
    """(3,) gravity (down) in the scene's world frame: +y, rotated by ``world_from_upright``."""
    g = np.array([0.0, 1.0, 0.0])
    return g if world_from_upright is None else world_from_upright.R @ g


def _transform_world(scene: SyntheticScene, world_from_upright: Pose) -> SyntheticScene:
    """The same scene in another world frame: X' = W X + w, cam_from_world' = cam_from_world ∘ W⁻¹."""
    upright_from_world = world_from_upright.inverse()

    def move(p: Pose) -> Pose:
        return p @ upright_from_world

    W, w = world_from_upright.R, world_from_upright.t
    pairs = [
        replace(
            p,
            ref_pose=move(p.ref_pose),
            ref_points3d=None if p.ref_points3d is None else p.ref_points3d @ W.T + w,
        )
        for p in scene.pairs
    ]
    return SyntheticScene(
        scene.query_camera, move(scene.query_pose), pairs, scene.points @ W.T + w, scene.is_outlier
    )


def _project(
    camera: Camera, pose: Pose, X: np.ndarray, min_depth: float = 0.5
) -> tuple[np.ndarray, np.ndarray]:
    Xc = X @ pose.R.T + pose.t
    z = Xc[:, 2]
    uv = np.full((len(X), 2), np.nan)
    front = z > min_depth
    uv[front] = camera.img_from_cam(Xc[front])
    inside = (
        front & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    )
    return uv, inside


@dataclass(frozen=True)
class SceneSpec:
    """Settings of :func:`make_scene` (see its docstring for each field)."""

    num_refs: int = 5
    matches_per_pair: int = 100
    noise_px: float = 1.0
    outlier_ratio: float = 0.0
    camera: Camera = PAPER_CAMERA
    num_points: int = 4000
    collinear: bool = False
    ref_tilt_deg: float = 0.0
    with_depth: bool = False
    track_pool: float | None = None
    max_tries: int = 200
    mount_pitch_deg: float = 0.0
    mount_roll_deg: float = 0.0
    query_tilt_deg: float = 0.0
    query_height_m: float = 0.0
    world_from_upright: Pose | None = None
    with_gravity: bool = False


class _Mount:
    """Applies the spec's camera mount (pitch, roll), extra query tilt and height drop to an upright pose."""

    def __init__(self, spec: SceneSpec, rng: np.random.Generator):
        self.rng = rng
        self.tilted = (
            spec.mount_pitch_deg != 0.0
            or spec.mount_roll_deg != 0.0
            or spec.query_tilt_deg > 0
            or spec.query_height_m != 0.0
        )
        self.cam_from_upright = upright_from_cam_rotation(spec.mount_pitch_deg, spec.mount_roll_deg).T

    def __call__(self, pose: Pose, extra_tilt: float = 0.0, drop: float = 0.0) -> Pose:
        if not self.tilted:
            return pose
        R = self.cam_from_upright @ pose.R
        if extra_tilt > 0:
            pitch, roll = self.rng.normal(0.0, extra_tilt, 2)
            R = upright_from_cam_rotation(pitch, roll).T @ R
        c = pose.center + np.array([0.0, drop, 0.0])
        return Pose(R, -R @ c)


@dataclass(frozen=True)
class _Layout:
    """One attempt's query pose, pre-drawn reference poses (collinear scenes only) and world points."""

    query: Pose
    refs: list[Pose]
    points: np.ndarray


def _draw_layout(rng: np.random.Generator, spec: SceneSpec, mount: _Mount) -> _Layout:
    if spec.collinear:

        def pose_on_line(z: float) -> Pose:
            R = rotation_from_yaw(rng.uniform(-0.05, 0.05))
            return Pose(R, -R @ np.array([0.0, 0.0, z]))

        query = pose_on_line(rng.uniform(-1.0, 1.0))
        refs = [pose_on_line(rng.uniform(-4.0, 4.0)) for _ in range(spec.num_refs)]
        n = spec.num_points
        X = np.c_[rng.uniform(-10, 10, n), rng.uniform(-3, 3, n), rng.uniform(6, 30, n)]
        return _Layout(query, refs, X)
    query = mount(random_planar_pose(rng), spec.query_tilt_deg, spec.query_height_m)
    return _Layout(query, [], rng.uniform(-10.0, 10.0, (spec.num_points, 3)))


def _wrong_projection(rng: np.random.Generator, camera: Camera, X: np.ndarray) -> np.ndarray:
    """(2,) pixel of point ``X`` seen from a random wrong planar pose (an outlier), visible if possible.

    Vectorised over 20 attempted poses (Pose objects would validate each one)."""
    Rw = rotation_from_yaw(rng.uniform(-np.pi, np.pi, 20))
    cw = np.stack([rng.uniform(-5, 5, 20), np.zeros(20), rng.uniform(-5, 5, 20)], axis=1)
    Xc = np.einsum("kij,kj->ki", Rw, X - cw)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv_w = (Xc @ camera.K.T)[:, :2] / Xc[:, 2:3]
    ok = (
        (Xc[:, 2] > 0.5)
        & (uv_w[:, 0] >= 0)
        & (uv_w[:, 0] < camera.width)
        & (uv_w[:, 1] >= 0)
        & (uv_w[:, 1] < camera.height)
    )
    hit = np.flatnonzero(ok)
    return uv_w[hit[0]] if len(hit) else rng.uniform([0, 0], [camera.width, camera.height])


def _make_pair(
    rng: np.random.Generator,
    spec: SceneSpec,
    ref: Pose,
    X: np.ndarray,
    ids: np.ndarray,
    uv: tuple[np.ndarray, np.ndarray],
) -> tuple[PairMatches, np.ndarray]:
    """Noisy matches of points ``ids`` between query and ``ref`` (pixels ``uv``), with outliers."""
    m, camera = spec.matches_per_pair, spec.camera
    q = uv[0][ids] + rng.normal(0.0, spec.noise_px, (m, 2))
    r = uv[1][ids] + rng.normal(0.0, spec.noise_px, (m, 2))
    is_out = np.zeros(m, dtype=bool)
    n_out = int(round(spec.outlier_ratio * m))
    if n_out:
        out_idx = rng.choice(m, n_out, replace=False)
        is_out[out_idx] = True
        for i in out_idx:
            r[i] = _wrong_projection(rng, camera, X[ids[i]])
    X3 = X[ids].copy() if spec.with_depth else None
    if X3 is not None:
        X3[is_out] = np.nan
    return PairMatches(ref, camera, q, r, query_indices=ids, ref_points3d=X3), is_out


def _try_scene(rng: np.random.Generator, spec: SceneSpec, mount: _Mount) -> SyntheticScene | None:
    """One attempt at a scene in the upright world frame; None when too few points are co-visible."""
    layout = _draw_layout(rng, spec, mount)
    X, camera, m = layout.points, spec.camera, spec.matches_per_pair
    uv_q, vis_q = _project(camera, layout.query, X)
    if vis_q.sum() < m:
        return None
    if spec.track_pool is not None:
        # The query detects a limited set of keypoints; references re-observe them, so
        # the same query keypoint is matched in several pairs (tracks).
        pool = rng.choice(
            np.flatnonzero(vis_q), min(int(vis_q.sum()), int(spec.track_pool * m)), replace=False
        )
        vis_q = np.zeros_like(vis_q)
        vis_q[pool] = True
    pairs: list[PairMatches] = []
    outl: list[np.ndarray] = []
    tries = 0
    while len(pairs) < spec.num_refs and tries < 50:
        tries += 1
        ref = (
            layout.refs[len(pairs)]
            if spec.collinear
            else mount(random_planar_pose(rng, tilt_deg=spec.ref_tilt_deg))
        )
        uv_r, vis_r = _project(camera, ref, X)
        common = np.flatnonzero(vis_q & vis_r)
        if len(common) < m:
            if spec.collinear:
                break
            continue
        ids = rng.choice(common, m, replace=False)
        pair, is_out = _make_pair(rng, spec, ref, X, ids, (uv_q, uv_r))
        pairs.append(pair)
        outl.append(is_out)
    if len(pairs) < spec.num_refs:
        return None
    return SyntheticScene(camera, layout.query, pairs, X, outl)


def make_scene(rng: np.random.Generator, spec: SceneSpec | None = None, **overrides) -> SyntheticScene:
    """Generate one scene of the paper's synthetic protocol.

    Args:
        rng: seeded generator.
        spec: the settings; None uses :class:`SceneSpec` defaults. Keyword ``overrides``
            (any :class:`SceneSpec` field) replace fields of ``spec``, e.g.
            ``make_scene(rng, num_refs=3, outlier_ratio=0.5)``.

    Settings (fields of :class:`SceneSpec`):
        num_refs: reference views, each co-visible with the query.
        matches_per_pair: matches per query-reference pair (inliers + outliers).
        noise_px: std of Gaussian pixel noise added to every keypoint.
        outlier_ratio: fraction of matches per pair that are outliers.
        camera: intrinsics of every camera; num_points: world points drawn per attempt;
            max_tries: attempts before giving up (RuntimeError).
        collinear: all camera centres on the world z-axis with small yaw (a straight corridor
            or road: the position along it is unobservable from 2D-2D constraints).
        ref_tilt_deg: pitch/roll noise of the references (uneven floor).
        with_depth: fill ``ref_points3d`` with the true points (reference depth maps).
        track_pool: if set, the query keypoints are a random subset of
            ``track_pool * matches_per_pair`` visible points, so pairs share query keypoints
            (as with real matching); None draws every pair from all visible points.
        mount_pitch_deg, mount_roll_deg: every camera (query and references) is mounted with
            this pitch (looking down for > 0) and roll (:mod:`planarloc.gravity.upright`).
        query_tilt_deg: the query gets an extra random pitch and roll of this standard
            deviation (uneven floor, handheld camera) that the map does not share.
        query_height_m: the query centre is this far below (> 0) the references' plane.
        world_from_upright: a rigid transform applied to the whole scene afterwards, so the
            world frame is not gravity-aligned (as with SfM reconstructions).
        with_gravity: fill each pair's ``ref_gravity`` with the true gravity direction.
            The query's true gravity is ``query_pose.R @ gravity_world(scene, world_from_upright)``.
    """
    spec = replace(spec or SceneSpec(), **overrides)
    mount = _Mount(spec, rng)
    for _ in range(spec.max_tries):
        scene = _try_scene(rng, spec, mount)
        if scene is None:
            continue
        if spec.world_from_upright is not None:
            scene = _transform_world(scene, spec.world_from_upright)
        if spec.with_gravity:
            g = gravity_world(scene, spec.world_from_upright)
            scene.pairs[:] = [replace(p, ref_gravity=p.ref_pose.R @ g) for p in scene.pairs]
        return scene
    raise RuntimeError("could not generate a scene with enough co-visible points; lower matches_per_pair")
