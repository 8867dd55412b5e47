"""Textures, scene builders, image effects and configs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from planarloc.synthetic.world import (
    Box,
    EffectsConfig,
    Plane,
    Room,
    SceneConfig,
    WorldConfig,
    get_preset,
    materials,
    preset_names,
    scene,
    textures,
)
from planarloc.synthetic.world.effects import apply_image_effects, apply_lighting

PPM = 100.0

GENERATORS = {
    "plaster": lambda rng: materials.plaster(rng, 180, 260, PPM),
    "bricks": lambda rng: materials.bricks(rng, 180, 260, PPM),
    "tiles": lambda rng: materials.tiles(rng, 180, 260, PPM),
    "ceiling": lambda rng: materials.ceiling_panels(rng, 180, 260, PPM),
    "wood": lambda rng: materials.wood(rng, 180, 260, PPM),
    "cardboard": lambda rng: materials.cardboard(rng, 180, 260, PPM),
    "door": lambda rng: materials.door(rng, 205, 90, PPM),
    "poster": lambda rng: textures.poster(rng, 180, 260),
}


@pytest.mark.parametrize("name", sorted(GENERATORS))
def test_textures_seeded_and_textured(name):
    make = GENERATORS[name]
    a = make(np.random.default_rng(7))
    assert a.dtype == np.uint8 and a.ndim == 3 and a.shape[2] == 3
    assert a.tobytes() == make(np.random.default_rng(7)).tobytes()
    assert a.tobytes() != make(np.random.default_rng(8)).tobytes()
    # No large uniform areas: few 16x16 blocks are flat.
    gray = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY).astype(np.float32)
    h, w = (s // 16 * 16 for s in gray.shape)
    blocks = gray[:h, :w].reshape(h // 16, 16, w // 16, 16).std(axis=(1, 3))
    limit = 0.2 if name in ("ceiling", "door") else 0.05  # lamps and name plates are plain
    assert np.mean(blocks < 2.0) <= limit, f"{name}: {np.mean(blocks < 2.0):.0%} flat blocks"


def test_plane_validation_and_geometry():
    tex = np.zeros((4, 6), np.uint8)
    p = Plane.from_corners([0, 0, 0], [2, 0, 0], [0, 1, 0], tex, "p")
    assert p.texture.shape == (4, 6, 3)
    np.testing.assert_allclose(p.corners, [[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]])
    np.testing.assert_allclose(p.normal, [0, 0, 1])
    with pytest.raises(ValueError, match="orthogonal"):
        Plane(np.zeros(3), np.array([1.0, 0, 0]), np.array([1.0, 1, 0]), tex)
    with pytest.raises(ValueError, match="uint8"):
        Plane(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), tex.astype(np.float32))
    big = Plane(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), np.zeros((64, 100, 3), np.uint8))
    assert [m.shape[:2] for m in big.mipmaps] == [(64, 100), (32, 50), (16, 25), (8, 13)]


def test_room_and_box_builders_face_the_viewer():
    room = Room(6.0, 4.0, 2.5)
    planes = scene.room_planes(room, np.random.default_rng(0), 40.0)
    names = [p.name for p in planes]
    assert (
        names[:2] == ["floor", "ceiling"] and sum(n.startswith("wall") for n in names) == 6
    )  # 6 m walls in 2 segments
    centre = np.array([3.0, -1.2, 2.0])
    for p in planes[2:]:
        # Texture rows run down and columns to the right of a viewer inside the room looking at the wall
        # (camera x = y x z with y down and z towards the wall).
        mid = p.origin + p.edge_u / 2 + p.edge_v / 2
        to_viewer = (centre - mid) * [1, 0, 1]
        assert p.edge_v[1] > 0 and p.edge_v[0] == p.edge_v[2] == 0
        assert np.dot(p.edge_u, np.cross(to_viewer, [0, 1, 0])) > 0
    box = Box((3.0, 2.0), (1.0, 0.8, 0.5), 0.4, 5)
    faces = scene.box_planes(box, 40.0)
    assert len(faces) == 5
    for face in faces[:4]:
        outward = np.cross(face.edge_v, face.edge_u)  # (down x right) points to the viewer for upright faces
        mid = face.origin + face.edge_u / 2 + face.edge_v / 2
        assert np.dot(outward, mid - [3.0, mid[1], 2.0]) > 0
    top = faces[4]
    assert (
        np.allclose(top.origin[1], -0.8) and np.allclose(top.edge_u[1], 0) and np.allclose(top.edge_v[1], 0)
    )
    fp = box.footprint()
    np.testing.assert_allclose(fp.mean(axis=0), [3.0, 2.0])
    np.testing.assert_allclose(sorted(np.linalg.norm(np.roll(fp, -1, 0) - fp, axis=1)), [0.5, 0.5, 1.0, 1.0])


def test_posters_and_doors_stay_on_walls():
    room = Room(2.6, 12.0, 2.6)
    planes, occupied = scene.corridor_planes(room, np.random.default_rng(1), 40.0)
    doors = [p for p in planes if p.name.startswith("door")]
    assert doors and set(occupied) == {1, 3}
    posters = scene.poster_planes(room, np.random.default_rng(2), 8, 40.0, occupied)
    for p in doors + posters:
        c = p.corners
        assert np.all(c[:, 1] <= 0) and np.all(c[:, 1] >= -room.height)
        assert np.all(
            (c[:, 0] >= -1e-9)
            & (c[:, 0] <= room.size_x + 1e-9)
            & (c[:, 2] >= -1e-9)
            & (c[:, 2] <= room.size_z + 1e-9)
        )
    with pytest.raises(ValueError, match="posters"):
        scene.poster_planes(Room(2.0, 2.0, 2.0), np.random.default_rng(0), 50, 40.0)


def test_image_effects():
    rng = np.random.default_rng(0)
    image = textures.poster(rng, 120, 160)
    darker = apply_lighting(image, 0.6, 1.2, 0.3, 0.0)
    assert darker.mean() < image.mean() * 0.7
    assert darker[:, :40].mean() < darker[:, -40:].mean()  # ramp goes left (dark) to right (bright)
    fx = EffectsConfig(noise_sigma=3.0, blur_sigma=0.8)
    a = apply_image_effects(image, fx, np.random.default_rng(1))
    assert a.tobytes() == apply_image_effects(image, fx, np.random.default_rng(1)).tobytes()
    assert a.tobytes() != apply_image_effects(image, fx, np.random.default_rng(2)).tobytes()
    assert apply_image_effects(image, EffectsConfig(), rng).tobytes() == image.tobytes()


def test_configs_validate_and_round_trip():
    for name in preset_names():
        config = get_preset(name)
        assert config.name == name
        assert WorldConfig.from_dict(config.to_dict()) == config
        assert config.camera.width == 640 and config.camera.height == 480 and config.camera.fx == 500.0
    with pytest.raises(ValueError, match="kind"):
        SceneConfig(kind="cave")
    with pytest.raises(ValueError, match="lower than the ceiling"):
        SceneConfig(height=2.0, box_size_max=(1.0, 2.5, 1.0))
    with pytest.raises(ValueError, match="gain"):
        EffectsConfig(gain=0)
    with pytest.raises(ValueError, match="map_effects"):
        WorldConfig(map_effects=EffectsConfig(added_boxes=1))
