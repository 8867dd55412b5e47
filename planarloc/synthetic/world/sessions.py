"""Build the map and query recording sessions of a world from a config and a seed.

Randomness comes from ``numpy.random.SeedSequence(seed)`` split into independent streams
(static scene textures, box layout, query rearrangement, per-session tilt and noise), so
one seed reproduces everything byte for byte, and the query world shares every unchanged
surface (and its textures) with the map world.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planarloc.synthetic.world import trajectory as traj
from planarloc.synthetic.world.config import EffectsConfig, WorldConfig
from planarloc.synthetic.world.effects import apply_image_effects, mount_poses, tilt_poses
from planarloc.synthetic.world.placement import FreeFloor, check_clearance, place_boxes, rearrange_boxes
from planarloc.synthetic.world.render import render
from planarloc.synthetic.world.scene import (
    Box,
    Plane,
    Room,
    World,
    box_planes,
    corridor_planes,
    poster_planes,
    room_planes,
)


@dataclass(frozen=True, eq=False)
class Session:
    """One recorded sequence: a world, a camera and the poses it was rendered from.

    Attributes:
        name: "map" or "query".
        world: the scene as it was during this session.
        K: (3, 3) intrinsics; width, height: image size.
        R: (N, 3, 3) and t: (N, 3) ``cam_from_world`` poses actually rendered (mount and tilt
            included); gravity in camera frame i is ``R[i][:, 1]`` (world y points down).
        timestamps: (N,) seconds.
        effects: image effects applied to every render.
        noise_entropy: seed of the per-frame noise generators.
    """

    name: str
    world: World
    K: np.ndarray
    width: int
    height: int
    R: np.ndarray
    t: np.ndarray
    timestamps: np.ndarray
    effects: EffectsConfig
    noise_entropy: int

    def __len__(self) -> int:
        return len(self.R)


def render_frame(session: Session, index: int) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``index`` of ``session``: (H, W, 3) uint8 RGB with effects applied, and (H, W) float32
    depth in metres (0 = nothing seen)."""
    if not 0 <= index < len(session):
        raise ValueError(f"frame index {index} out of range for a session of {len(session)} frames")
    image, depth = render(
        session.world, session.K, session.R[index], session.t[index], session.width, session.height
    )
    rng = np.random.default_rng([session.noise_entropy, index])
    return apply_image_effects(image, session.effects, rng), depth


def _paths(
    config: WorldConfig, room: Room
) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Map and query paths ((N, 2) xz, (N,) yaw) of ``config.trajectory`` in ``room``."""
    tc = config.trajectory
    m = tc.wall_margin
    if tc.shape == "loop":
        radii = (room.size_x / 2 - m, room.size_z / 2 - m)
        if min(radii) <= 0.1:
            raise ValueError(
                f"loop wall_margin {m} m leaves no loop in a {room.size_x} x {room.size_z} m room"
            )
        center = (room.size_x / 2, room.size_z / 2)
        map_path = traj.ellipse_loop(center, radii, tc.n_map)
        base = traj.ellipse_loop(center, radii, tc.n_query, phase=0.5)
    else:
        if room.size_z >= room.size_x:
            start, end = (room.size_x / 2, m), (room.size_x / 2, room.size_z - m)
        else:
            start, end = (m, room.size_z / 2), (room.size_x - m, room.size_z / 2)
        if max(room.size_x, room.size_z) - 2 * m <= 0.5:
            raise ValueError(
                f"line wall_margin {m} m leaves no path in a {room.size_x} x {room.size_z} m room"
            )
        map_path = traj.straight_line(start, end, tc.n_map)
        base = traj.straight_line(start, end, tc.n_query)
    query_path = traj.offset_path(
        *base, tc.lateral_offset, np.radians(tc.yaw_offset_deg), np.radians(tc.yaw_wobble_deg)
    )
    return map_path, query_path


def _world(
    static: list[Plane], room: Room, boxes: tuple[Box, ...], px_per_m: float, cache: dict[Box, list[Plane]]
) -> World:
    planes = list(static)
    for i, box in enumerate(boxes):
        if box not in cache:
            cache[box] = box_planes(box, px_per_m, f"box{i}")
        planes += cache[box]
    return World(tuple(planes), room, boxes)


def build_sessions(config: WorldConfig, seed: int = 0) -> tuple[Session, Session]:
    """The (map, query) sessions of ``config``.

    Raises:
        ValueError: if the configuration cannot be realised (trajectory too close to walls,
            boxes that do not fit, ...).
    """
    if not isinstance(config, WorldConfig):
        raise ValueError(f"config must be a WorldConfig, got {type(config).__name__}")  # noqa: TRY004
    if not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    sc, tc = config.scene, config.trajectory
    streams = np.random.SeedSequence(int(seed)).spawn(7)
    static_rng, layout_rng, change_rng = (np.random.default_rng(s) for s in streams[:3])
    room = Room(sc.size_x, sc.size_z, sc.height)

    map_path, query_path = _paths(config, room)
    check_clearance(map_path[0], room, (), tc.min_clearance, "map trajectory")
    check_clearance(query_path[0], room, (), tc.min_clearance, "query trajectory")
    closed = tc.shape == "loop"
    keep_out = np.vstack([traj.densify(map_path[0], closed), traj.densify(query_path[0], closed)])

    box_gap = max(sc.box_clearance, tc.min_clearance)
    floor = FreeFloor(room, keep_out, box_gap, sc.box_size_min, sc.box_size_max)
    boxes = place_boxes(layout_rng, floor, sc.n_boxes)
    qe = config.query_effects
    query_boxes = boxes
    if qe.moved_boxes or qe.added_boxes:
        query_boxes = rearrange_boxes(change_rng, floor, boxes, qe.moved_boxes, qe.added_boxes)
    check_clearance(map_path[0], room, boxes, tc.min_clearance, "map trajectory")
    check_clearance(query_path[0], room, query_boxes, tc.min_clearance, "query trajectory")

    # Textures last: the checks above are cheap and fail fast.
    if sc.kind == "corridor":
        static, occupied = corridor_planes(room, static_rng, sc.px_per_m)
    else:
        static, occupied = room_planes(room, static_rng, sc.px_per_m), {}
    static += poster_planes(room, static_rng, sc.n_posters, sc.px_per_m, occupied)
    cache: dict[Box, list[Plane]] = {}
    map_world = _world(static, room, boxes, sc.px_per_m, cache)
    query_world = map_world if query_boxes == boxes else _world(static, room, query_boxes, sc.px_per_m, cache)

    K = config.camera.intrinsics()
    sessions = []
    for name, (xz, yaw), world, effects, tilt_seq, noise_seq in (
        ("map", map_path, map_world, config.map_effects, streams[3], streams[5]),
        ("query", query_path, query_world, config.query_effects, streams[4], streams[6]),
    ):
        if name == "map":
            height: float | np.ndarray = tc.camera_height
            pitch, roll = tc.mount_pitch_deg, tc.mount_roll_deg
        else:
            height = tc.camera_height
            if tc.query_height_drop or tc.query_height_wobble:
                height = traj.height_profile(
                    tc.camera_height, tc.query_height_drop, tc.query_height_wobble, len(xz)
                )
            pitch, roll = tc.query_mount_deg()
        R, t = traj.planar_poses(xz, yaw, height)
        R, t = mount_poses(R, t, pitch, roll)
        if effects.tilt_deg > 0:
            R, t = tilt_poses(R, t, np.random.default_rng(tilt_seq), effects.tilt_deg)
        for arr in (R, t):
            arr.setflags(write=False)
        stamps = np.arange(len(R)) * tc.frame_period
        entropy = int(noise_seq.generate_state(1, dtype=np.uint64)[0])
        sessions.append(
            Session(name, world, K, config.camera.width, config.camera.height, R, t, stamps, effects, entropy)
        )
    return sessions[0], sessions[1]
