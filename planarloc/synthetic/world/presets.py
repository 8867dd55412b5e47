"""Named world presets.

- ``office`` (default): an 8 x 6 m room with boxes and posters; the map loops around the
  room, the query loops 0.3 m further out, turned 20 +- 8 degrees, with mild noise and
  up to 1 degree of pitch/roll.
- ``corridor``: a 2.6 x 20 m corridor with doors and posters; map and query both walk
  straight along it (query 0.3 m to the side, same heading): the forward-motion,
  low-parallax case that is degenerate for 2D-2D methods.
- ``lifelong``: ``office`` whose query session has different lighting (gain, gamma, a
  shading ramp), blur, more noise, and 2 moved plus 2 added boxes.
- ``pitched``: ``office`` recorded by robots whose cameras are mounted pitched down: the map
  robot 11°, the query robot 14° with 1° of roll, plus the query floor's 1° jitter.
- ``offplane``: ``office`` whose queries come from a hand-held camera 0.2–0.7 m lower than
  the map robot's, tilted up to 4° in pitch and roll: the planar model does not hold.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from planarloc.synthetic.world.config import (
    CameraConfig,
    EffectsConfig,
    SceneConfig,
    WorldConfig,
)

DEFAULT_PRESET = "office"


def office() -> WorldConfig:
    """An 8 x 6 x 2.6 m office: 6 boxes, 12 posters, 40 map and 30 query frames of 640 x 480.

    The camera, scene and trajectories are the config classes' defaults; the query session adds
    mild noise and floor jitter.
    """
    return WorldConfig(name="office", query_effects=EffectsConfig(noise_sigma=2.0, tilt_deg=1.0))


def corridor() -> WorldConfig:
    """A 2.6 x 20 x 2.6 m corridor: doors, 10 posters, 3 boxes; 40 map and 30 query frames, straight."""
    base = office()  # the same robots and cameras, in a corridor, driving straight
    return dataclasses.replace(
        base,
        name="corridor",
        scene=SceneConfig(
            kind="corridor",
            size_x=2.6,
            size_z=20.0,
            n_boxes=3,
            box_size_min=(0.4, 0.4, 0.3),
            box_size_max=(1.0, 1.4, 0.5),
            n_posters=10,
        ),
        trajectory=dataclasses.replace(
            base.trajectory, shape="line", wall_margin=1.0, yaw_offset_deg=0.0, yaw_wobble_deg=0.0
        ),
    )


def lifelong() -> WorldConfig:
    """``office`` with a changed query session: darker, gamma, shading ramp, blur, noise,
    2 moved and 2 added boxes."""
    return dataclasses.replace(
        office(),
        name="lifelong",
        query_effects=EffectsConfig(
            gain=0.75,
            gamma=1.3,
            shading_gradient=0.35,
            shading_angle_deg=30.0,
            noise_sigma=3.0,
            blur_sigma=0.7,
            tilt_deg=1.5,
            moved_boxes=2,
            added_boxes=2,
        ),
    )


def pitched() -> WorldConfig:
    """``office`` with cameras mounted pitched down: map 11°, query 14° pitch and 1° roll."""
    base = office()
    return dataclasses.replace(
        base,
        name="pitched",
        trajectory=dataclasses.replace(
            base.trajectory, mount_pitch_deg=11.0, query_mount_pitch_deg=14.0, query_mount_roll_deg=1.0
        ),
    )


def offplane() -> WorldConfig:
    """``office`` with hand-held queries 0.2–0.7 m below the map cameras, tilted up to 4°."""
    base = office()
    return dataclasses.replace(
        base,
        name="offplane",
        trajectory=dataclasses.replace(base.trajectory, query_height_drop=0.45, query_height_wobble=0.25),
        query_effects=dataclasses.replace(base.query_effects, tilt_deg=4.0),
    )


def robot_variant(config: WorldConfig, floor_tilt_deg: float, mount_pitch_deg: float) -> WorldConfig:
    """``config`` with both robots' cameras mounted ``mount_pitch_deg`` down and the query floor
    jitter set to ``floor_tilt_deg``; named e.g. ``office-tilt3-pitch10``."""
    return dataclasses.replace(
        config,
        name=f"{config.name}-tilt{floor_tilt_deg:g}-pitch{mount_pitch_deg:g}",
        trajectory=dataclasses.replace(
            config.trajectory,
            mount_pitch_deg=float(mount_pitch_deg),
            query_mount_pitch_deg=None,
            query_mount_roll_deg=None,
        ),
        query_effects=dataclasses.replace(config.query_effects, tilt_deg=float(floor_tilt_deg)),
    )


PRESETS: dict[str, Callable[[], WorldConfig]] = {
    "office": office,
    "corridor": corridor,
    "lifelong": lifelong,
    "pitched": pitched,
    "offplane": offplane,
}


def preset_names() -> tuple[str, ...]:
    """Names accepted by :func:`get_preset`."""
    return tuple(PRESETS)


def preset_summaries() -> dict[str, str]:
    """``{name: one line}`` of every preset (its docstring's first paragraph), e.g. for a help page."""
    return {
        name: " ".join((fn.__doc__ or "").split("\n\n")[0].split()).replace("``", "")
        for name, fn in PRESETS.items()
    }


def get_preset(name: str) -> WorldConfig:
    """The config of preset ``name``.

    Raises:
        ValueError: for an unknown name (the message lists the known ones).
    """
    try:
        return PRESETS[name]()
    except KeyError:
        raise ValueError(f"unknown world preset {name!r}; choose one of {', '.join(PRESETS)}") from None


def shrunk(
    config: WorldConfig, scale: float = 0.25, n_map: int = 8, n_query: int = 6, px_per_m: float = 80.0
) -> WorldConfig:
    """A quick version of ``config`` for tests and demos: images (and focal lengths) scaled by
    ``scale``, ``n_map`` / ``n_query`` frames on the same paths, coarser textures, half the posters.

    Example: ``shrunk(get_preset("office"))`` renders 160 x 120 frames in a few milliseconds.
    """
    cam = config.camera
    cx, cy = cam.principal_point
    camera = CameraConfig(
        width=max(16, round(float(cam.width * scale))),
        height=max(16, round(float(cam.height * scale))),
        fx=cam.fx * scale,
        fy=cam.fy * scale,
        cx=None if cam.cx is None else cx * scale,
        cy=None if cam.cy is None else cy * scale,
    )
    return dataclasses.replace(
        config,
        camera=camera,
        scene=dataclasses.replace(config.scene, px_per_m=px_per_m, n_posters=config.scene.n_posters // 2),
        trajectory=dataclasses.replace(config.trajectory, n_map=n_map, n_query=n_query),
    )
