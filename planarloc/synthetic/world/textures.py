"""Seeded procedural texture building blocks: noise, colours, shapes, text, posters, notes.

Every generator takes a ``numpy.random.Generator`` and draws from it in a fixed order, so
the same seed gives the same bytes. Sizes are in texels. Images are (H, W, 3) uint8 RGB
(float32 in [0, 255] for intermediate results, as documented). Surface materials built
from these (plaster, bricks, tiles, ...) are in :mod:`planarloc.synthetic.world.materials`.
"""

from __future__ import annotations

import string

import cv2
import numpy as np

_FONTS = (
    cv2.FONT_HERSHEY_SIMPLEX,
    cv2.FONT_HERSHEY_DUPLEX,
    cv2.FONT_HERSHEY_COMPLEX,
    cv2.FONT_HERSHEY_TRIPLEX,
    cv2.FONT_HERSHEY_PLAIN,
)
_ALPHABET = string.ascii_uppercase + string.digits


def check_size(height: int, width: int) -> None:
    """Raise ValueError unless a texture size is positive."""
    if height < 1 or width < 1:
        raise ValueError(f"texture size must be positive, got {height}x{width}")


def random_color(rng: np.random.Generator, low: int = 0, high: int = 256) -> tuple[int, int, int]:
    """One RGB colour with channels drawn uniformly in [low, high)."""
    return tuple(rng.integers(low, high, size=3).tolist())


def fractal_noise(
    rng: np.random.Generator,
    height: int,
    width: int,
    cell_px: float,
    octaves: int = 4,
    persistence: float = 0.5,
) -> np.ndarray:
    """Multi-octave value noise.

    Args:
        cell_px: size in texels of the coarsest octave's cells; each further octave halves it
            (down to 1 texel).

    Returns:
        (height, width) float32 in [0, 1].
    """
    check_size(height, width)
    total = np.zeros((height, width), np.float32)
    amplitude = 1.0
    for octave in range(octaves):
        cell = max(cell_px / 2**octave, 1.0)
        grid_h, grid_w = int(np.ceil(height / cell)) + 2, int(np.ceil(width / cell)) + 2
        grid = rng.random((grid_h, grid_w), dtype=np.float32)
        up: np.ndarray
        if cell == 1.0:
            up = grid[:height, :width]
        else:
            up = cv2.resize(grid, (int(grid_w * cell), int(grid_h * cell)), interpolation=cv2.INTER_CUBIC)
            up = up[:height, :width]
        total += np.float32(amplitude) * up
        amplitude *= persistence
    lo, hi = float(total.min()), float(total.max())
    return (total - lo) / np.float32(max(hi - lo, 1e-6))


def shaded_color(
    rng: np.random.Generator, color: tuple[int, int, int], low: float, high: float
) -> tuple[int, int, int]:
    """``color`` with each channel scaled by its own factor drawn in [low, high) (R first), truncated."""
    r, g, b = (int(c * rng.uniform(low, high)) for c in color)
    return r, g, b


def colorize(values: np.ndarray, color_a: tuple[int, int, int], color_b: tuple[int, int, int]) -> np.ndarray:
    """Blend two colours by (H, W) weights in [0, 1]; returns (H, W, 3) float32 in [0, 255]."""
    out = np.empty((*values.shape, 3), np.float32)
    for c in range(3):  # per channel: much faster than broadcasting over a last axis of 3
        np.multiply(values, np.float32(color_b[c] - color_a[c]), out=out[..., c])
        out[..., c] += np.float32(color_a[c])
    return out


def modulate(image: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """Multiply a float (H, W, 3) image by (H, W) or (H, 1) gains, in place; returns ``image``."""
    for c in range(3):
        image[..., c] *= gain
    return image


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Round (half to even) and clip a float image to uint8."""
    return cv2.add(np.asarray(image, np.float32), 0.0, dtype=cv2.CV_8U)  # one saturating pass


def speckle(rng: np.random.Generator, image: np.ndarray, density: float, strength: float) -> np.ndarray:
    """Add sparse light and dark dots (1-2 texels) to a float (H, W, 3) image; returns a new image."""
    h, w = image.shape[:2]
    out = image.copy()
    n = int(density * h * w)
    ys = rng.integers(0, h, n)
    xs = rng.integers(0, w, n)
    delta = rng.uniform(-strength, strength, n).astype(np.float32)
    out[ys, xs] += delta[:, None]
    big = rng.random(n) < 0.3
    out[np.minimum(ys[big] + 1, h - 1), xs[big]] += delta[big, None]
    out[ys[big], np.minimum(xs[big] + 1, w - 1)] += delta[big, None]
    return out


def random_text(rng: np.random.Generator, min_len: int = 3, max_len: int = 10) -> str:
    """A random word of uppercase letters and digits."""
    n = int(rng.integers(min_len, max_len + 1))
    return "".join(_ALPHABET[i] for i in rng.integers(0, len(_ALPHABET), n))


def draw_text(rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int]) -> None:
    """Draw one random word fitted in ``box = (x, y, w, h)`` of a uint8 image, in place."""
    x, y, w, h = box
    text = random_text(rng)
    font = _FONTS[int(rng.integers(len(_FONTS)))]
    thickness = int(rng.integers(1, 4))
    (tw, th), _ = cv2.getTextSize(text, font, 1.0, thickness)
    scale = min(w / max(tw, 1), h / max(th, 1)) * float(rng.uniform(0.6, 1.0))
    if scale * th < 6:
        return
    thickness = max(1, round(float(thickness * scale)))
    color = random_color(rng)
    cv2.putText(image, text, (x, y + int(th * scale)), font, scale, color, thickness, cv2.LINE_AA)


def draw_shape(rng: np.random.Generator, image: np.ndarray, box: tuple[int, int, int, int]) -> None:
    """Draw one random circle, rectangle, ellipse, polygon or line bundle in ``box``, in place."""
    x, y, w, h = box
    if w < 4 or h < 4:
        return
    color = random_color(rng)
    filled = rng.random() < 0.6
    thickness = -1 if filled else int(rng.integers(1, max(2, min(w, h) // 12 + 2)))
    kind = int(rng.integers(5))
    cx, cy = x + w // 2, y + h // 2
    if kind == 0:
        cv2.circle(image, (cx, cy), max(2, min(w, h) // 2), color, thickness, cv2.LINE_AA)
    elif kind == 1:
        cv2.rectangle(image, (x, y), (x + w - 1, y + h - 1), color, thickness, cv2.LINE_AA)
    elif kind == 2:
        angle = float(rng.uniform(0, 180))
        cv2.ellipse(
            image, (cx, cy), (max(1, w // 2), max(1, h // 4)), angle, 0, 360, color, thickness, cv2.LINE_AA
        )
    elif kind == 3:
        n = int(rng.integers(3, 9))
        angles = np.sort(rng.uniform(0, 2 * np.pi, n))
        radii = rng.uniform(0.3, 1.0, n)
        pts = np.stack([cx + radii * np.cos(angles) * w / 2, cy + radii * np.sin(angles) * h / 2], axis=1)
        polygon = np.rint(pts).astype(np.int32)
        if filled:
            cv2.fillPoly(image, [polygon], color, cv2.LINE_AA)
        else:
            cv2.polylines(image, [polygon], True, color, thickness, cv2.LINE_AA)
    else:
        for _ in range(int(rng.integers(2, 6))):
            p0 = (int(rng.integers(x, x + w)), int(rng.integers(y, y + h)))
            p1 = (int(rng.integers(x, x + w)), int(rng.integers(y, y + h)))
            cv2.line(image, p0, p1, random_color(rng), int(rng.integers(1, 4)), cv2.LINE_AA)


def draw_decals(rng: np.random.Generator, image: np.ndarray, count: int, min_px: int, max_px: int) -> None:
    """Scatter ``count`` small shapes and words of ``min_px``-``max_px`` texels over ``image``, in place."""
    h, w = image.shape[:2]
    for _ in range(count):
        bw = int(rng.integers(min_px, max_px + 1))
        bh = int(rng.integers(min_px, max_px + 1))
        bx = int(rng.integers(0, max(1, w - bw)))
        by = int(rng.integers(0, max(1, h - bh)))
        if rng.random() < 0.35:
            draw_text(rng, image, (bx, by, bw, max(6, bh // 2)))
        else:
            draw_shape(rng, image, (bx, by, bw, bh))


def gradient(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A linear gradient between two random colours at a random angle; (H, W, 3) float32."""
    angle = rng.uniform(0, 2 * np.pi)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    ramp = np.cos(angle) * xs / max(width, 1) + np.sin(angle) * ys / max(height, 1)
    ramp = (ramp - ramp.min()) / max(float(ramp.max() - ramp.min()), 1e-6)
    return colorize(ramp.astype(np.float32), random_color(rng), random_color(rng))


def poster(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A poster: gradient background, random shapes, words and a border; (H, W, 3) uint8."""
    check_size(height, width)
    base = gradient(rng, height, width)
    modulate(base, 0.75 + 0.5 * fractal_noise(rng, height, width, max(height, width) / 6, 3))
    image = to_uint8(base)
    scale = min(height, width)
    for _ in range(int(rng.integers(10, 20))):
        bw = int(rng.integers(scale // 10 + 2, scale // 2 + 3))
        bh = int(rng.integers(scale // 10 + 2, scale // 2 + 3))
        draw_shape(
            rng,
            image,
            (int(rng.integers(0, max(1, width - bw))), int(rng.integers(0, max(1, height - bh))), bw, bh),
        )
    for _ in range(int(rng.integers(3, 8))):
        bw = int(rng.integers(width // 3 + 1, width + 1))
        bh = int(rng.integers(scale // 14 + 4, scale // 5 + 6))
        draw_text(
            rng,
            image,
            (int(rng.integers(0, max(1, width - bw))), int(rng.integers(0, max(1, height - bh))), bw, bh),
        )
    draw_decals(rng, image, int(rng.integers(10, 25)), max(4, scale // 30), max(6, scale // 10))
    border = max(2, scale // 40)
    cv2.rectangle(image, (0, 0), (width - 1, height - 1), random_color(rng, 0, 80), border)
    return print_grain(rng, image)


def print_grain(rng: np.random.Generator, image: np.ndarray, strength: float = 0.12) -> np.ndarray:
    """Paper and print texture: blotchy brightness of relative ``strength``, fine grain; new uint8 image."""
    h, w = image.shape[:2]
    blotch = fractal_noise(rng, h, w, max(4.0, min(h, w) / 12), 3)
    out = modulate(image.astype(np.float32), (1.0 - strength / 2) + strength * blotch)
    out += rng.normal(0.0, 3.0, (h, w, 1)).astype(np.float32)
    return to_uint8(out)


def note(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A small paper note or picture: plain paper with a few words and shapes; (H, W, 3) uint8."""
    check_size(height, width)
    out = np.empty((height, width, 3), np.uint8)
    out[:] = random_color(rng, 150, 256)
    lines = int(rng.integers(1, 4))
    for k in range(lines):
        draw_text(rng, out, (1, k * height // lines, width - 2, max(6, height // lines - 2)))
    for _ in range(int(rng.integers(1, 4))):
        bw, bh = int(rng.integers(3, max(4, width // 2))), int(rng.integers(3, max(4, height // 2)))
        draw_shape(
            rng,
            out,
            (int(rng.integers(0, max(1, width - bw))), int(rng.integers(0, max(1, height - bh))), bw, bh),
        )
    cv2.rectangle(out, (0, 0), (width - 1, height - 1), random_color(rng, 0, 120), 1)
    return out


def shaded(texture: np.ndarray, factor: float) -> np.ndarray:
    """Texture multiplied by a brightness factor (baked diffuse lighting); same shape, uint8."""
    return to_uint8(texture.astype(np.float32) * np.float32(factor))
