"""Free space in the floor plane: clearances to walls and boxes, and random box placement.

All geometry here is 2D in the world x-z (floor) plane, in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planarloc.synthetic.world.scene import Box, Room, room_walls

_MAX_TRIES = 2000


def polygon_distance(points_xz: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Signed distance from points to a convex polygon (negative inside).

    Args:
        points_xz: (N, 2) points.
        polygon: (M, 2) convex polygon vertices in order (either orientation).

    Returns:
        (N,) distances.
    """
    p = np.asarray(points_xz, dtype=np.float64).reshape(-1, 2)
    a = np.asarray(polygon, dtype=np.float64)
    b = np.roll(a, -1, axis=0)
    ab = b - a  # (M, 2)
    ap = p[:, None, :] - a[None]  # (N, M, 2)
    f = np.clip(np.einsum("nmk,mk->nm", ap, ab) / np.einsum("mk,mk->m", ab, ab), 0.0, 1.0)
    dist = np.linalg.norm(ap - f[..., None] * ab, axis=2).min(axis=1)
    cross = ab[None, :, 0] * ap[..., 1] - ab[None, :, 1] * ap[..., 0]  # (N, M)
    inside = np.all(cross >= 0, axis=1) | np.all(cross <= 0, axis=1)
    return np.where(inside, -dist, dist)


def clearance(points_xz: np.ndarray, room: Room, boxes: tuple[Box, ...] = ()) -> np.ndarray:
    """(N,) distance from each point to the nearest wall or box footprint.

    Negative if the point is outside the room or inside a box.
    """
    p = np.asarray(points_xz, dtype=np.float64).reshape(-1, 2)
    d = np.min(np.column_stack([p[:, 0], room.size_x - p[:, 0], p[:, 1], room.size_z - p[:, 1]]), axis=1)
    for box in boxes:
        d = np.minimum(d, polygon_distance(p, box.footprint()))
    return d


def check_clearance(
    points_xz: np.ndarray, room: Room, boxes: tuple[Box, ...], min_clearance: float, what: str
) -> None:
    """Raise ValueError naming ``what`` if any point is closer than ``min_clearance`` to a wall or a box."""
    d = clearance(points_xz, room, boxes)
    if d.size and d.min() < min_clearance:
        i = int(np.argmin(d))
        p = np.asarray(points_xz).reshape(-1, 2)[i]
        raise ValueError(
            f"{what}: point {i} at x={p[0]:.2f}, z={p[1]:.2f} is {d[i]:.2f} m from a wall or box, "
            f"less than the required {min_clearance:.2f} m; shrink the trajectory or enlarge the room"
        )


def _separated(poly_a: np.ndarray, poly_b: np.ndarray, gap: float) -> bool:
    """True if some edge normal of either convex polygon separates them by at least ``gap``."""
    for poly in (poly_a, poly_b):
        edges = np.roll(poly, -1, axis=0) - poly
        normals = np.column_stack([-edges[:, 1], edges[:, 0]]) / np.linalg.norm(edges, axis=1)[:, None]
        pa, pb = poly_a @ normals.T, poly_b @ normals.T  # (4, K)
        if np.any((pb.min(axis=0) - pa.max(axis=0) >= gap) | (pa.min(axis=0) - pb.max(axis=0) >= gap)):
            return True
    return False


def _random_box(
    rng: np.random.Generator,
    room: Room,
    size_min: tuple[float, float, float],
    size_max: tuple[float, float, float],
    against_wall: bool,
) -> Box:
    sx, sy, sz = (float(v) for v in rng.uniform(size_min, size_max))
    size = (sx, sy, sz)
    seed = int(rng.integers(2**31))
    if against_wall:
        walls = room_walls(room)
        lengths = np.array([w.length for w in walls])
        wall = walls[int(rng.choice(len(walls), p=lengths / lengths.sum()))]
        along = float(
            rng.uniform(size[0] / 2 + 0.05, max(size[0] / 2 + 0.05, wall.length - size[0] / 2 - 0.05))
        )
        center = wall.start + wall.direction * along + wall.normal * (size[2] / 2 + 0.05)
        yaw = float(np.arctan2(wall.normal[0], wall.normal[1]))  # front face looks into the room
        return Box((float(center[0]), float(center[1])), size, yaw, seed)
    center = rng.uniform([0.3, 0.3], [room.size_x - 0.3, room.size_z - 0.3])
    return Box((float(center[0]), float(center[1])), size, float(rng.uniform(-np.pi, np.pi)), seed)


def _fits(
    box: Box, room: Room, keep_out_xz: np.ndarray, clearance_m: float, others: list[Box], gap_m: float
) -> bool:
    fp = box.footprint()
    if (
        fp[:, 0].min() < 0.02
        or fp[:, 1].min() < 0.02
        or fp[:, 0].max() > room.size_x - 0.02
        or fp[:, 1].max() > room.size_z - 0.02
    ):
        return False
    radius = 0.5 * float(np.hypot(box.size[0], box.size[2]))
    for other in others:
        reach = radius + 0.5 * float(np.hypot(other.size[0], other.size[2])) + gap_m
        near = np.hypot(box.center_xz[0] - other.center_xz[0], box.center_xz[1] - other.center_xz[1]) < reach
        if near and not _separated(fp, other.footprint(), gap_m):
            return False
    return not (len(keep_out_xz) and polygon_distance(keep_out_xz, fp).min() < clearance_m)


@dataclass(frozen=True, eq=False)
class FreeFloor:
    """Where boxes may stand: ``room``, at least ``clearance_m`` from the (M, 2) ``keep_out_xz``
    points (the trajectories) and within box sizes (width, height, depth) ``size_min..size_max``."""

    room: Room
    keep_out_xz: np.ndarray
    clearance_m: float
    size_min: tuple[float, float, float]
    size_max: tuple[float, float, float]


def place_boxes(
    rng: np.random.Generator,
    floor: FreeFloor,
    count: int,
    existing: tuple[Box, ...] = (),
    against_wall_fraction: float = 0.6,
    gap_m: float = 0.1,
) -> tuple[Box, ...]:
    """Randomly place ``count`` boxes on the free floor, clear of its keep-out points and each other.

    A fraction of the boxes stands against a wall facing into the room, the rest anywhere at a
    random yaw. Sizes (width, height, depth) are uniform in [size_min, size_max].

    Returns:
        the new boxes only (not ``existing``).

    Raises:
        ValueError: if no free spot is found (too many or too large boxes for the room).
    """
    room, size_min, size_max, clearance_m = floor.room, floor.size_min, floor.size_max, floor.clearance_m
    keep_out_xz = np.asarray(floor.keep_out_xz, dtype=np.float64).reshape(-1, 2)
    placed: list[Box] = []
    tries = 0
    while len(placed) < count:
        tries += 1
        if tries > _MAX_TRIES:
            raise ValueError(
                f"cannot place {count} boxes of size {size_min}..{size_max} "
                f"in a {room.size_x}x{room.size_z} m room "
                f"{clearance_m} m clear of the trajectories; use fewer or smaller boxes"
            )
        box = _random_box(rng, room, size_min, size_max, bool(rng.random() < against_wall_fraction))
        if _fits(box, room, keep_out_xz, clearance_m, list(existing) + placed, gap_m):
            placed.append(box)
    return tuple(placed)


def rearrange_boxes(
    rng: np.random.Generator, floor: FreeFloor, boxes: tuple[Box, ...], n_move: int, n_add: int
) -> tuple[Box, ...]:
    """Move ``n_move`` of ``boxes`` to new random spots (same size and look) and add ``n_add`` new boxes.

    Returns:
        the rearranged boxes: unmoved ones first in their original order, then moved, then added.
    """
    if n_move > len(boxes) or n_move < 0 or n_add < 0:
        raise ValueError(f"cannot move {n_move} of {len(boxes)} boxes and add {n_add}")
    room, clearance_m = floor.room, floor.clearance_m
    keep_out_xz = np.asarray(floor.keep_out_xz, dtype=np.float64).reshape(-1, 2)
    moved_idx = {int(i) for i in rng.choice(len(boxes), size=n_move, replace=False)} if n_move else set()
    kept = [b for i, b in enumerate(boxes) if i not in moved_idx]
    moved: list[Box] = []
    for i in sorted(moved_idx):
        old = boxes[i]
        for _ in range(_MAX_TRIES):
            cand = _random_box(rng, room, old.size, old.size, bool(rng.random() < 0.5))
            cand = Box(cand.center_xz, old.size, cand.yaw, old.texture_seed)
            far_enough = np.hypot(*(np.subtract(cand.center_xz, old.center_xz))) > 0.5
            if far_enough and _fits(cand, room, keep_out_xz, clearance_m, kept + moved, 0.1):
                moved.append(cand)
                break
        else:
            raise ValueError(f"cannot find a new spot for box {i}; use fewer boxes or move fewer")
    added = place_boxes(rng, floor, n_add, tuple(kept + moved))
    return tuple(kept + moved) + added
