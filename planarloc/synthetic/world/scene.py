"""Scene description: textured planar rectangles, and builders for rooms, corridors, boxes, posters.

World frame (metres): y points DOWN (gravity); the floor is the plane y = 0, so a point at
height h above the floor has y = -h. A room spans x in [0, size_x], z in [0, size_z] and
y in [-height, 0].

A :class:`Plane` is a rectangle ``origin + a * edge_u + b * edge_v`` for a, b in [0, 1],
carrying a texture whose columns run along ``edge_u`` and rows along ``edge_v``: texel
(col s, row r), with texel centres at integer coordinates, sits at
``origin + edge_u * (s + 0.5) / W + edge_v * (r + 0.5) / H``. Planes are two-sided.
Vertical surfaces are built with ``edge_v`` pointing down and ``edge_u`` pointing to the
viewer's right, so text on walls, posters and boxes reads correctly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import NamedTuple

import cv2
import numpy as np

from planarloc.synthetic.world import materials, textures

_LIGHT_XZ = np.array([0.6, 0.8])  # horizontal direction of the baked diffuse light


@dataclass(frozen=True, eq=False)
class Plane:
    """A textured rectangle in world coordinates.

    Attributes:
        origin: (3,) corner at texel (0, 0)'s outer corner.
        edge_u: (3,) edge vector along texture columns (width direction).
        edge_v: (3,) edge vector along texture rows (height direction), orthogonal to ``edge_u``.
        texture: (H, W, 3) or (H, W) uint8; stored as (H, W, 3) RGB.
        name: free label, e.g. ``"wall0.1"`` or ``"box3.top"``.
    """

    origin: np.ndarray
    edge_u: np.ndarray
    edge_v: np.ndarray
    texture: np.ndarray
    name: str = ""

    def __post_init__(self) -> None:
        vecs = {}
        for key in ("origin", "edge_u", "edge_v"):
            v = np.array(getattr(self, key), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"Plane.{key}: expected 3 finite numbers, got {getattr(self, key)!r}")
            v.setflags(write=False)
            vecs[key] = v
        lu, lv = np.linalg.norm(vecs["edge_u"]), np.linalg.norm(vecs["edge_v"])
        if lu < 1e-9 or lv < 1e-9:
            raise ValueError(f"Plane {self.name!r}: edges must have non-zero length")
        if abs(vecs["edge_u"] @ vecs["edge_v"]) > 1e-6 * lu * lv:
            raise ValueError(f"Plane {self.name!r}: edge_u and edge_v must be orthogonal (a rectangle)")
        tex = np.asarray(self.texture)
        if tex.dtype != np.uint8 or tex.ndim not in (2, 3) or (tex.ndim == 3 and tex.shape[2] != 3):
            raise ValueError(
                f"Plane {self.name!r}: texture must be uint8 (H, W) or (H, W, 3), got {tex.dtype} {tex.shape}"
            )
        if min(tex.shape[:2]) < 2:
            raise ValueError(f"Plane {self.name!r}: texture must be at least 2x2 texels, got {tex.shape[:2]}")
        # Own a read-only copy: the mip pyramid is cached, so the texture must not change.
        tex = cv2.cvtColor(tex, cv2.COLOR_GRAY2RGB) if tex.ndim == 2 else np.array(tex, order="C", copy=True)
        tex.setflags(write=False)
        for key, v in vecs.items():
            object.__setattr__(self, key, v)
        object.__setattr__(self, "texture", tex)

    @classmethod
    def from_corners(cls, p0: object, p1: object, p2: object, texture: np.ndarray, name: str = "") -> Plane:
        """Rectangle with corner ``p0`` at texel (0, 0), ``p1`` along the texture width, ``p2`` along
        its height."""
        p0 = np.asarray(p0, dtype=np.float64)
        return cls(
            p0, np.asarray(p1, dtype=np.float64) - p0, np.asarray(p2, dtype=np.float64) - p0, texture, name
        )

    @property
    def corners(self) -> np.ndarray:
        """(4, 3) corners in order origin, +u, +u+v, +v."""
        o, u, v = self.origin, self.edge_u, self.edge_v
        return np.stack([o, o + u, o + u + v, o + v])

    @property
    def normal(self) -> np.ndarray:
        """(3,) unit normal ``edge_u x edge_v`` (planes are two-sided; this only fixes a sign)."""
        n = np.cross(self.edge_u, self.edge_v)
        return n / np.linalg.norm(n)

    @cached_property
    def mipmaps(self) -> tuple[np.ndarray, ...]:
        """Gaussian pyramid of the texture (``cv2.pyrDown``), level 0 first, down to ~8 texels.

        Texel ``i`` of level ``l`` is centred on texel ``i * 2**l`` of level 0.
        """
        levels = [self.texture]
        while min(levels[-1].shape[:2]) >= 16:
            levels.append(cv2.pyrDown(levels[-1]))
        for level in levels:
            level.setflags(write=False)
        return tuple(levels)


@dataclass(frozen=True)
class Room:
    """Axis-aligned room: x in [0, size_x], z in [0, size_z], floor y = 0, ceiling y = -height (metres)."""

    size_x: float
    size_z: float
    height: float

    def __post_init__(self) -> None:
        for key in ("size_x", "size_z", "height"):
            v = getattr(self, key)
            if not (np.isfinite(v) and v > 0.5):
                raise ValueError(f"Room.{key} must be a finite size above 0.5 m, got {v!r}")


@dataclass(frozen=True)
class Box:
    """A box standing on the floor (furniture).

    Attributes:
        center_xz: (x, z) of the footprint centre.
        size: (width, height, depth) in metres; width along the local right axis
            ``(cos yaw, -sin yaw)`` and depth along the local forward axis ``(sin yaw, cos yaw)``
            (x-z components).
        yaw: rotation of the footprint about world y, radians (same sense as camera yaw).
        texture_seed: seed of the face textures, so a moved box keeps its look.
    """

    center_xz: tuple[float, float]
    size: tuple[float, float, float]
    yaw: float
    texture_seed: int

    def __post_init__(self) -> None:
        if len(self.size) != 3 or min(self.size) <= 0.05:
            raise ValueError(f"Box.size must be (width, height, depth) above 5 cm each, got {self.size!r}")

    @property
    def axes_xz(self) -> tuple[np.ndarray, np.ndarray]:
        """(right, forward) unit (2,) vectors of the footprint in world x-z."""
        c, s = np.cos(self.yaw), np.sin(self.yaw)
        return np.array([c, -s]), np.array([s, c])

    def footprint(self) -> np.ndarray:
        """(4, 2) x-z corners of the footprint, counter-clockwise in (x, z)."""
        right, fwd = self.axes_xz
        c = np.asarray(self.center_xz, dtype=np.float64)
        hw, hd = self.size[0] / 2, self.size[2] / 2
        return np.stack(
            [
                c - right * hw - fwd * hd,
                c + right * hw - fwd * hd,
                c + right * hw + fwd * hd,
                c - right * hw + fwd * hd,
            ]
        )


@dataclass(frozen=True, eq=False)
class World:
    """Everything the renderer draws, plus the free-space description trajectories are checked against.

    Attributes:
        planes: the textured rectangles (room surfaces, posters, doors and box faces).
        room: the enclosing room.
        boxes: the boxes whose faces are among ``planes`` (obstacles for the robot).
    """

    planes: tuple[Plane, ...]
    room: Room
    boxes: tuple[Box, ...] = field(default=())

    def __post_init__(self) -> None:
        object.__setattr__(self, "planes", tuple(self.planes))
        object.__setattr__(self, "boxes", tuple(self.boxes))
        if not self.planes or not all(isinstance(p, Plane) for p in self.planes):
            raise ValueError("World.planes must be a non-empty sequence of Plane")
        if not isinstance(self.room, Room) or not all(isinstance(b, Box) for b in self.boxes):
            raise ValueError("World.room must be a Room and World.boxes a sequence of Box")


class Wall(NamedTuple):
    """A room wall seen from inside: ``start`` is its left end, ``direction`` points to the viewer's right."""

    start: np.ndarray  # (2,) x-z
    direction: np.ndarray  # (2,) unit x-z
    length: float
    normal: np.ndarray  # (2,) unit x-z, pointing into the room


def room_walls(room: Room) -> tuple[Wall, ...]:
    """The 4 walls (z = 0, x = size_x, z = size_z, x = 0), each oriented as seen from inside."""
    sx, sz = room.size_x, room.size_z
    specs = (
        ((sx, 0.0), (0.0, 1.0), sx),
        ((sx, sz), (-1.0, 0.0), sz),
        ((0.0, sz), (0.0, -1.0), sx),
        ((0.0, 0.0), (1.0, 0.0), sz),
    )
    walls = []
    for start, normal, length in specs:
        n = np.array(normal)
        walls.append(Wall(np.array(start), np.array([-n[1], n[0]]), float(length), n))
    return tuple(walls)


def _xz_to_3d(xz: np.ndarray, y: float) -> np.ndarray:
    return np.array([xz[0], y, xz[1]], dtype=np.float64)


def _light_factor(normal_xz: np.ndarray, low: float, high: float) -> float:
    return low + (high - low) * 0.5 * (1.0 + float(normal_xz @ _LIGHT_XZ))


def _texture_size(length_u: float, length_v: float, px_per_m: float) -> tuple[int, int]:
    return max(8, round(float(length_v * px_per_m))), max(8, round(float(length_u * px_per_m)))


def wall_plane(
    wall: Wall,
    start: float,
    end: float,
    bottom: float,
    top: float,
    texture: np.ndarray,
    offset: float = 0.0,
    name: str = "",
) -> Plane:
    """The part of ``wall`` from ``start`` to ``end`` m along it and ``bottom`` to ``top`` m above the floor.

    ``offset`` moves the rectangle into the room (posters, doors) to stay in front of the wall.
    """
    if not (0.0 <= start < end <= wall.length + 1e-9) or not (0.0 <= bottom < top):
        raise ValueError(
            f"wall_plane {name!r}: bad extent along [{start}, {end}] of {wall.length} m, "
            f"heights [{bottom}, {top}]"
        )
    corner = wall.start + wall.direction * start + wall.normal * offset
    origin = _xz_to_3d(corner, -top)
    edge_u = _xz_to_3d(wall.direction * (end - start), 0.0)
    edge_v = np.array([0.0, top - bottom, 0.0])
    return Plane(origin, edge_u, edge_v, texture, name)


def _wall_texture(
    rng: np.random.Generator, style: str, height: int, width: int, px_per_m: float
) -> np.ndarray:
    if style == "bricks":
        return materials.bricks(rng, height, width, px_per_m)
    if style == "wood":
        return materials.wood(rng, height, width, px_per_m, vertical=True)
    return materials.plaster(rng, height, width, px_per_m)


def _surround(
    room: Room, rng: np.random.Generator, px_per_m: float, styles: tuple[str, ...], segment_m: float
) -> list[Plane]:
    """Floor, ceiling and the 4 walls cut into segments of at most ``segment_m``, textured with ``styles``."""
    sx, sz, h = room.size_x, room.size_z, room.height
    tex = materials.tiles(
        rng, *_texture_size(sx, sz, px_per_m), px_per_m, tile_m=float(rng.uniform(0.3, 0.6))
    )
    planes = [
        Plane(
            np.zeros(3),
            np.array([sx, 0.0, 0.0]),
            np.array([0.0, 0.0, sz]),
            textures.shaded(tex, 0.95),
            "floor",
        )
    ]
    tex = materials.ceiling_panels(rng, *_texture_size(sx, sz, px_per_m), px_per_m)
    planes.append(
        Plane(
            np.array([0.0, -h, 0.0]),
            np.array([sx, 0.0, 0.0]),
            np.array([0.0, 0.0, sz]),
            textures.shaded(tex, 0.85),
            "ceiling",
        )
    )
    for w_idx, wall in enumerate(room_walls(room)):
        n_seg = int(np.ceil(wall.length / segment_m - 1e-9))
        cuts = np.linspace(0.0, wall.length, n_seg + 1)
        factor = _light_factor(wall.normal, 0.75, 1.0)
        for k in range(n_seg):
            style = styles[int(rng.integers(len(styles)))]
            tex = _wall_texture(rng, style, *_texture_size(cuts[k + 1] - cuts[k], h, px_per_m), px_per_m)
            planes.append(
                wall_plane(
                    wall, cuts[k], cuts[k + 1], 0.0, h, textures.shaded(tex, factor), name=f"wall{w_idx}.{k}"
                )
            )
    return planes


def room_planes(room: Room, rng: np.random.Generator, px_per_m: float = 200.0) -> list[Plane]:
    """An office room: tiled floor, panelled ceiling, 4 walls of plaster, bricks or wood (segments <= 4 m)."""
    return _surround(room, rng, px_per_m, ("plaster", "plaster", "bricks", "wood"), 4.0)


def door_planes(
    room: Room, rng: np.random.Generator, px_per_m: float, spacing_m: float = 4.0
) -> tuple[list[Plane], dict[int, list[tuple[float, float]]]]:
    """Doors (0.9 x 2.05 m) every ~``spacing_m`` along the two long walls.

    Returns:
        the door planes, and per wall index the occupied (start, end) intervals along the wall.
    """
    walls = room_walls(room)
    long_idx = (1, 3) if room.size_z >= room.size_x else (0, 2)
    planes: list[Plane] = []
    occupied: dict[int, list[tuple[float, float]]] = {}
    for w_idx in long_idx:
        wall = walls[w_idx]
        pos = float(rng.uniform(0.5, spacing_m))
        while pos + 0.9 < wall.length - 0.5:
            tex = materials.door(rng, *_texture_size(0.9, 2.05, px_per_m), px_per_m)
            factor = _light_factor(wall.normal, 0.75, 1.0)
            planes.append(
                wall_plane(
                    wall,
                    pos,
                    pos + 0.9,
                    0.0,
                    2.05,
                    textures.shaded(tex, factor),
                    0.01,
                    f"door{w_idx}.{len(planes)}",
                )
            )
            occupied.setdefault(w_idx, []).append((pos, pos + 0.9))
            pos += 0.9 + float(rng.uniform(0.6, 1.0)) * spacing_m
    return planes, occupied


def corridor_planes(
    room: Room, rng: np.random.Generator, px_per_m: float = 200.0
) -> tuple[list[Plane], dict[int, list[tuple[float, float]]]]:
    """A corridor: a long room with plaster/brick walls and doors along both long walls.

    Returns:
        the planes, and per wall index the intervals taken by doors (for poster placement).
    """
    planes = _surround(room, rng, px_per_m, ("plaster", "plaster", "bricks"), 4.0)
    doors, occupied = door_planes(room, rng, px_per_m)
    return planes + doors, occupied


def poster_planes(
    room: Room,
    rng: np.random.Generator,
    count: int,
    px_per_m: float = 200.0,
    occupied: dict[int, list[tuple[float, float]]] | None = None,
) -> list[Plane]:
    """``count`` posters (0.4-1.2 m wide) 1 cm in front of the walls, overlapping neither each other
    nor ``occupied``.

    Raises:
        ValueError: if the walls have no room left for that many posters.
    """
    walls = room_walls(room)
    taken = {k: list(v) for k, v in (occupied or {}).items()}
    lengths = np.array([w.length for w in walls])
    planes: list[Plane] = []
    attempts = 0
    while len(planes) < count:
        attempts += 1
        if attempts > 200 * (count + 1):
            raise ValueError(f"cannot fit {count} posters on the walls of {room}; lower the poster count")
        w_idx = int(rng.choice(len(walls), p=lengths / lengths.sum()))
        wall = walls[w_idx]
        width = float(rng.uniform(0.4, 1.2))
        height = float(np.clip(width * rng.uniform(0.6, 1.5), 0.3, 1.2))
        bottom = float(rng.uniform(0.5, max(0.5, room.height - 0.2 - height)))
        if wall.length < width + 0.4 or bottom + height > room.height - 0.1:
            continue
        start = float(rng.uniform(0.2, wall.length - 0.2 - width))
        if any(start < b + 0.1 and a - 0.1 < start + width for a, b in taken.get(w_idx, [])):
            continue
        taken.setdefault(w_idx, []).append((start, start + width))
        tex = textures.poster(rng, *_texture_size(width, height, max(px_per_m, 300.0)))
        factor = _light_factor(wall.normal, 0.8, 1.0)
        planes.append(
            wall_plane(
                wall,
                start,
                start + width,
                bottom,
                bottom + height,
                textures.shaded(tex, factor),
                0.01,
                f"poster{len(planes)}",
            )
        )
    return planes


def box_planes(box: Box, px_per_m: float = 200.0, name: str = "box") -> list[Plane]:
    """The 5 visible faces (4 sides and top) of ``box``, textured from ``box.texture_seed``."""
    rng = np.random.default_rng(box.texture_seed)
    width, height, depth = box.size
    right, fwd = box.axes_xz
    c = np.asarray(box.center_xz, dtype=np.float64)
    wooden = rng.random() < 0.35
    planes = []

    def face(
        corner_xz: np.ndarray,
        u: np.ndarray,
        v: np.ndarray,
        extent_m: tuple[float, float],
        normal_xz: np.ndarray | None,
        label: str,
    ) -> None:
        """One face from its top corner and edges, in wood or cardboard, shaded by its normal (a side)."""
        size = _texture_size(*extent_m, px_per_m)
        tex = materials.wood(rng, *size, px_per_m) if wooden else materials.cardboard(rng, *size, px_per_m)
        shaded = tex if normal_xz is None else textures.shaded(tex, _light_factor(normal_xz, 0.6, 0.9))
        planes.append(Plane(_xz_to_3d(corner_xz, -height), u, v, shaded, f"{name}.{label}"))

    # (outward normal, half extent along it, face width); viewer's right on a face is (-n_z, n_x).
    sides = (
        (fwd, depth / 2, width),
        (right, width / 2, depth),
        (-fwd, depth / 2, width),
        (-right, width / 2, depth),
    )
    for k, (n, half, face_w) in enumerate(sides):
        face_right = np.array([-n[1], n[0]])
        face(
            c + n * half - face_right * face_w / 2,
            _xz_to_3d(face_right * face_w, 0.0),
            np.array([0.0, height, 0.0]),
            (face_w, height),
            n,
            f"side{k}",
        )
    face(
        c - right * width / 2 - fwd * depth / 2,
        _xz_to_3d(right * width, 0.0),
        _xz_to_3d(fwd * depth, 0.0),
        (width, depth),
        None,
        "top",
    )
    return planes
