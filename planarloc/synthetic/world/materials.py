"""Seeded surface materials for walls, floors, ceilings, doors and furniture (uint8 RGB).

Each generator draws from the ``numpy.random.Generator`` it is given in a fixed order
(same seed, same bytes) and takes ``px_per_m`` (texels per metre) so that a brick or a
tile has its physical size whatever the surface resolution. All of them scatter small
shapes, words and notes over the surface so that no large area is uniform and SIFT finds
features everywhere.
"""

from __future__ import annotations

import cv2
import numpy as np

from planarloc.synthetic.world.textures import (
    check_size,
    colorize,
    draw_decals,
    draw_text,
    fractal_noise,
    modulate,
    note,
    poster,
    random_color,
    shaded_color,
    speckle,
    to_uint8,
)

_BRICK_COLORS = (
    (150, 70, 50),
    (170, 100, 70),
    (120, 60, 45),
    (190, 160, 120),
    (140, 140, 135),
    (200, 185, 150),
)


def plaster(rng: np.random.Generator, height: int, width: int, px_per_m: float) -> np.ndarray:
    """Painted plaster wall with stains, speckles and scattered marks; (H, W, 3) uint8."""
    check_size(height, width)
    paint = random_color(rng, 140, 240)
    dark = shaded_color(rng, paint, 0.55, 0.75)
    stains = fractal_noise(rng, height, width, 0.8 * px_per_m, 5, 0.6)
    blotches = fractal_noise(rng, height, width, 0.06 * px_per_m, 2, 0.5)
    image = colorize(np.clip(0.75 * stains + 0.6 * (blotches - 0.5), 0, 1), dark, paint)
    image = speckle(rng, image, 0.03, 55.0)
    out = to_uint8(image)
    area_m2 = width * height / (px_per_m * px_per_m)
    for _ in range(int(area_m2 * 1.5)):  # pinned notes and small pictures
        nw = int(rng.uniform(0.08, 0.3) * px_per_m)
        nh = int(rng.uniform(0.08, 0.3) * px_per_m)
        if 4 < nw < width and 4 < nh < height:
            x, y = int(rng.integers(0, width - nw)), int(rng.integers(0, height - nh))
            out[y : y + nh, x : x + nw] = note(rng, nh, nw)
    draw_decals(rng, out, int(area_m2 * 15), int(0.03 * px_per_m) + 3, int(0.18 * px_per_m) + 4)
    return out


def bricks(rng: np.random.Generator, height: int, width: int, px_per_m: float) -> np.ndarray:
    """Running-bond brick wall with per-brick colour, mortar and grain; (H, W, 3) uint8."""
    check_size(height, width)
    brick_w = max(6, round(float(0.24 * px_per_m)))
    brick_h = max(3, round(float(0.08 * px_per_m)))
    mortar = max(1, round(float(0.012 * px_per_m)))
    mortar_color = np.asarray(random_color(rng, 150, 210), np.float32)
    base = np.asarray(_BRICK_COLORS[int(rng.integers(len(_BRICK_COLORS)))], np.float32)
    base = np.clip(base + rng.uniform(-25, 25, 3), 30, 230).astype(np.float32)
    image = np.empty((height, width, 3), np.float32)
    image[:] = mortar_color
    rows = height // brick_h + 1
    cols = width // brick_w + 2
    tints = rng.uniform(0.6, 1.35, size=(rows, cols, 1)) * rng.uniform(0.9, 1.1, size=(rows, cols, 3))
    tints = tints.astype(np.float32)
    for row in range(rows):
        y0 = row * brick_h
        shift = (brick_w // 2) * (row % 2)
        for col in range(cols):
            x0 = col * brick_w - shift
            xa, xb = max(x0 + mortar, 0), min(x0 + brick_w, width)
            ya, yb = y0 + mortar, min(y0 + brick_h, height)
            if xa < xb and ya < yb:
                image[ya:yb, xa:xb] = np.clip(base * tints[row, col], 0, 255)
    grain = fractal_noise(rng, height, width, 0.1 * px_per_m, 4)
    modulate(image, 0.7 + 0.6 * grain)
    image = speckle(rng, image, 0.03, 50.0)
    out = to_uint8(image)
    n = int(width * height / (px_per_m * px_per_m) * 2)
    draw_decals(rng, out, n, int(0.03 * px_per_m) + 3, int(0.12 * px_per_m) + 4)
    return out


def tiles(
    rng: np.random.Generator, height: int, width: int, px_per_m: float, tile_m: float = 0.4
) -> np.ndarray:
    """Floor tiles with marbled per-tile colour and grout lines; (H, W, 3) uint8."""
    check_size(height, width)
    tile = max(4, round(float(tile_m * px_per_m)))
    grout = max(1, round(float(0.01 * px_per_m)))
    color_a, color_b = random_color(rng, 40, 200), random_color(rng, 40, 200)
    marble = fractal_noise(rng, height, width, 0.3 * px_per_m, 5, 0.65)
    image = colorize(marble, color_a, color_b)
    rows, cols = height // tile + 1, width // tile + 1
    tints = rng.uniform(0.7, 1.25, size=(rows, cols)).astype(np.float32)
    tint_img = np.repeat(np.repeat(tints, tile, axis=0), tile, axis=1)[:height, :width]
    modulate(image, tint_img)
    grout_color = np.asarray(random_color(rng, 20, 120), np.float32)
    for y in range(0, height, tile):
        image[y : y + grout] = grout_color
    for x in range(0, width, tile):
        image[:, x : x + grout] = grout_color
    image = speckle(rng, image, 0.03, 60.0)
    out = to_uint8(image)
    n = int(width * height / (px_per_m * px_per_m) * 1.5)
    draw_decals(rng, out, n, int(0.02 * px_per_m) + 3, int(0.1 * px_per_m) + 4)
    return out


def ceiling_panels(rng: np.random.Generator, height: int, width: int, px_per_m: float) -> np.ndarray:
    """Suspended-ceiling panels with perforation noise, a metal grid and lamps; (H, W, 3) uint8."""
    check_size(height, width)
    panel = max(4, round(float(0.6 * px_per_m)))
    light = np.float32(rng.uniform(190, 230))
    noise = fractal_noise(rng, height, width, 0.2 * px_per_m, 4)
    image = cv2.merge([light * (0.8 + 0.25 * noise)] * 3)
    image = speckle(rng, image, 0.08, 70.0)
    rows, cols = height // panel + 1, width // panel + 1
    lamps = rng.random((rows, cols)) < 0.18
    grid_color = np.asarray(random_color(rng, 60, 140), np.float32)
    for r in range(rows):
        for c in range(cols):
            if lamps[r, c]:
                y0, x0 = r * panel, c * panel
                image[y0 : y0 + panel, x0 : x0 + panel] = 250.0
                for k in range(1, 4):
                    yk = y0 + k * panel // 4
                    image[yk : yk + max(1, panel // 40), x0 : x0 + panel] = 170.0
    w_line = max(1, panel // 30)
    for y in range(0, height, panel):
        image[y : y + w_line] = grid_color
    for x in range(0, width, panel):
        image[:, x : x + w_line] = grid_color
    out = to_uint8(image)
    n = int(width * height / (px_per_m * px_per_m) * 1.0)
    draw_decals(rng, out, n, int(0.03 * px_per_m) + 3, int(0.1 * px_per_m) + 4)
    return out


def wood(
    rng: np.random.Generator, height: int, width: int, px_per_m: float, vertical: bool = False
) -> np.ndarray:
    """Wooden planks (along x, or y if ``vertical``): grain, joints, knots, nails, marks; (H, W, 3) uint8."""
    check_size(height, width)
    h, w = (width, height) if vertical else (height, width)
    plank = max(4, round(float(rng.uniform(0.1, 0.2) * px_per_m)))
    warp = fractal_noise(rng, h, w, 0.3 * px_per_m, 3)
    ys = np.arange(h, dtype=np.float32)[:, None]
    period = max(3.0, float(rng.uniform(0.02, 0.04)) * px_per_m)
    rings = 0.5 + 0.5 * np.sin(ys * np.float32(2 * np.pi / period) + 14.0 * warp)
    blotch = fractal_noise(rng, h, w, 0.08 * px_per_m, 3)
    light, dark = random_color(rng, 130, 230), random_color(rng, 30, 110)
    image = colorize((0.45 * rings + 0.55 * blotch).astype(np.float32), dark, light)
    tints = rng.uniform(0.6, 1.3, h // plank + 1).astype(np.float32)
    modulate(image, np.repeat(tints, plank)[:h, None])
    image = speckle(rng, image, 0.02, 40.0)
    out = to_uint8(image)
    seam = random_color(rng, 10, 60)
    nail = max(1, int(0.006 * px_per_m))
    for y0 in range(0, h, plank):
        cv2.line(out, (0, y0), (w - 1, y0), seam, max(1, plank // 25))
        x = int(rng.integers(0, max(1, int(1.5 * px_per_m))))
        while x < w:  # butt joints with a pair of nails on each side
            cv2.line(out, (x, y0), (x, y0 + plank - 1), seam, max(1, plank // 25))
            for dx in (-3 * nail, 3 * nail):
                for fy in (0.3, 0.7):
                    cv2.circle(out, (x + dx, y0 + int(fy * plank)), nail, (40, 40, 45), -1, cv2.LINE_AA)
            x += int(rng.uniform(0.6, 2.0) * px_per_m)
    area_m2 = w * h / (px_per_m * px_per_m)
    for _ in range(int(area_m2 * 8) + 1):
        center = (int(rng.integers(0, w)), int(rng.integers(0, h)))
        axes = (
            int(rng.integers(3, int(0.05 * px_per_m + 5))),
            int(rng.integers(2, int(0.02 * px_per_m + 3))),
        )
        cv2.ellipse(out, center, axes, 0, 0, 360, random_color(rng, 20, 90), -1, cv2.LINE_AA)
        cv2.ellipse(
            out, center, (axes[0] + 2, axes[1] + 2), 0, 0, 360, random_color(rng, 60, 140), 1, cv2.LINE_AA
        )
    draw_decals(rng, out, int(area_m2 * 12.0) + 2, int(0.03 * px_per_m) + 3, int(0.12 * px_per_m) + 4)
    return np.ascontiguousarray(out.transpose(1, 0, 2)) if vertical else out


def cardboard(rng: np.random.Generator, height: int, width: int, px_per_m: float) -> np.ndarray:
    """A cardboard or painted furniture face with tape, printed labels and marks; (H, W, 3) uint8."""
    check_size(height, width)
    base = random_color(rng, 90, 220)
    shade = shaded_color(rng, base, 0.6, 0.85)
    image = colorize(fractal_noise(rng, height, width, 0.2 * px_per_m, 5, 0.6), shade, base)
    image = speckle(rng, image, 0.03, 40.0)
    out = to_uint8(image)
    if rng.random() < 0.5:
        tape = max(2, int(0.05 * px_per_m))
        y = int(rng.integers(0, max(1, height - tape)))
        cv2.rectangle(out, (0, y), (width - 1, y + tape), random_color(rng, 150, 255), -1)
    for _ in range(int(rng.integers(1, 4))):
        lw = int(rng.integers(max(8, width // 5), max(9, width // 2)))
        lh = int(rng.integers(max(8, height // 6), max(9, height // 2)))
        if lw < width and lh < height:
            x, y = int(rng.integers(0, width - lw)), int(rng.integers(0, height - lh))
            out[y : y + lh, x : x + lw] = poster(rng, lh, lw)
    n = int(width * height / (px_per_m * px_per_m) * 8) + 4
    draw_decals(rng, out, n, int(0.03 * px_per_m) + 3, int(0.12 * px_per_m) + 4)
    return out


def door(rng: np.random.Generator, height: int, width: int, px_per_m: float) -> np.ndarray:
    """A wooden door with frame, panels, handle and a name plate; (H, W, 3) uint8."""
    out = wood(rng, height, width, px_per_m, vertical=True)
    frame = max(2, int(0.06 * px_per_m))
    cv2.rectangle(out, (0, 0), (width - 1, height - 1), random_color(rng, 30, 200), frame)
    inset = max(3, int(0.15 * px_per_m))
    for y0, y1 in ((0.1, 0.45), (0.55, 0.92)):
        cv2.rectangle(
            out,
            (inset, int(y0 * height)),
            (width - inset, int(y1 * height)),
            random_color(rng, 20, 90),
            max(1, frame // 3),
        )
    hx, hy = int(0.82 * width), int(0.5 * height)
    cv2.circle(out, (hx, hy), max(2, int(0.03 * px_per_m)), (200, 200, 205), -1, cv2.LINE_AA)
    cv2.rectangle(out, (hx - int(0.1 * px_per_m), hy - 2), (hx, hy + 2), (180, 180, 190), -1)
    pw, ph = int(0.5 * width), int(0.06 * height)
    if pw > 8 and ph > 8:
        px, py = (width - pw) // 2, int(0.3 * height)
        plate = np.full((ph, pw, 3), random_color(rng, 180, 255), np.uint8)
        draw_text(rng, plate, (2, 2, pw - 4, ph - 4))
        out[py : py + ph, px : px + pw] = plate
    return out
