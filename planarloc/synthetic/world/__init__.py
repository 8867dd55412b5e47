"""A small deterministic renderer of indoor scenes seen by a wheeled robot (numpy + OpenCV).

Modules:
    textures    seeded texture building blocks (noise, shapes, text, posters)
    materials   seeded surface materials (plaster, bricks, tiles, ceiling, wood, doors, cardboard)
    scene       Plane / Box / Room / World and builders (room, corridor, boxes, posters)
    render      z-buffer renderer of textured rectangles -> RGB image and metric depth
    trajectory  planar camera paths (loop, line, offset query path) and poses
    placement   clearances in the floor plane and random box placement
    effects     lighting / blur / noise on images, camera mount and pitch-roll jitter on poses
    config      frozen dataclass configuration
    presets     named configs: office (default), corridor, lifelong, pitched, offplane
    sessions    map and query sessions of a config and seed
    export      ``generate``: write both sessions in the TUM RGB-D layout (+ true gravity)

Conventions: world y points down (gravity), floor at y = 0; camera x right, y down, z
forward; poses are ``cam_from_world`` (x_cam = R x_world + t) and an upright camera with
yaw θ has R = [[cos θ, 0, -sin θ], [0, 1, 0], [sin θ, 0, cos θ]].

The renderer is ``planarloc.synthetic.world.render.render`` (not re-exported here, so that
the name ``render`` keeps meaning the module).
"""

from planarloc.synthetic.world.config import (
    CameraConfig,
    EffectsConfig,
    SceneConfig,
    TrajectoryConfig,
    WorldConfig,
)
from planarloc.synthetic.world.export import generate, is_complete
from planarloc.synthetic.world.presets import DEFAULT_PRESET, get_preset, preset_names, shrunk
from planarloc.synthetic.world.scene import Box, Plane, Room, World
from planarloc.synthetic.world.sessions import Session, build_sessions, render_frame

__all__ = [
    "DEFAULT_PRESET",
    "Box",
    "CameraConfig",
    "EffectsConfig",
    "Plane",
    "Room",
    "SceneConfig",
    "Session",
    "TrajectoryConfig",
    "World",
    "WorldConfig",
    "build_sessions",
    "generate",
    "get_preset",
    "is_complete",
    "preset_names",
    "render_frame",
    "shrunk",
]
