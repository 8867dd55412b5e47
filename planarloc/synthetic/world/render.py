"""Deterministic z-buffer renderer of textured planar rectangles (numpy + OpenCV).

Camera: pinhole ``K`` in the OpenCV pixel convention (the centre of the top-left pixel is
(0, 0)); axes x right, y down, z forward; pose ``cam_from_world``: x_cam = R x_world + t.

Per plane: clip the rectangle against the near plane, take the bounding box of its
projection, and for every pixel there evaluate the inverse homography image -> texture.
The homography is built so that its third coordinate is exactly the inverse depth 1/z of
the plane point seen through the pixel centre (1/z is affine in (u, v) for a plane), which
gives analytic per-pixel depth and the z-buffer test. A pixel belongs to the plane if its
ray hits the rectangle (texture coordinates in range) in front of the near plane and
closer than what is already drawn. Colours are sampled with ``cv2.remap`` (bilinear) from
a Gaussian mip pyramid at the per-pixel minification, cross-fading adjacent levels
("brilinear" filtering), which avoids aliasing of far or grazing surfaces.
"""

from __future__ import annotations

import cv2
import numpy as np

from planarloc.synthetic.world.scene import Plane, World

NEAR = 0.05
"""Near clipping distance in metres: nothing closer than this (along z) is drawn."""

_EDGE_TEXELS = 0.02  # tolerance of the inside-rectangle test, in texels
_LOD_STEP = 8  # pixels between samples of the mip level map (it varies smoothly)
_BLEND_WIDTH = 0.5  # width, in mip levels, of the cross-fade between adjacent levels


def _check_camera(
    K: object, R: object, t: object, width: int, height: int, near: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    K = np.asarray(K, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    if K.shape != (3, 3) or K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]):
        raise ValueError(f"K must be a (3, 3) pinhole matrix with positive focal lengths, got {K.tolist()}")
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("cam_from_world_R must be a (3, 3) rotation matrix")
    if t.shape != (3,) or not np.all(np.isfinite(t)):
        raise ValueError(f"cam_from_world_t must be 3 finite numbers, got {t!r}")
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    if not (np.isfinite(near) and near > 0):
        raise ValueError(f"near must be a positive distance, got {near!r}")
    return K, R, t


def clip_polygon_near(points_cam: np.ndarray, near: float = NEAR) -> np.ndarray:
    """Clip a convex polygon to the half-space z >= near (Sutherland-Hodgman).

    Args:
        points_cam: (N, 3) vertices in camera coordinates, in order.

    Returns:
        (M, 3) clipped vertices (M = 0 if the polygon is entirely behind).
    """
    out = []
    n = len(points_cam)
    for i in range(n):
        a, b = points_cam[i], points_cam[(i + 1) % n]
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            s = (near - a[2]) / (b[2] - a[2])
            out.append(a + s * (b - a))
    return np.array(out).reshape(-1, 3)


def image_from_texture(plane: Plane, K: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(3, 3) homography mapping level-0 texel coordinates (s, r, 1) to ``z * (u, v, 1)``.

    Its third output coordinate is the depth z of the point, so the inverse homography maps a
    pixel (u, v, 1) to ``(s, r, 1) / z``.
    """
    tex_h, tex_w = plane.texture.shape[:2]
    du, dv = plane.edge_u / tex_w, plane.edge_v / tex_h
    A = np.column_stack([du, dv, plane.origin + 0.5 * (du + dv)])  # texel -> world point
    M = R @ A
    M[:, 2] += t
    return K @ M


def _lod_map(G: np.ndarray, x0: int, y0: int, w: int, h: int, max_level: int) -> np.ndarray:
    """(h, w) float32 mip level log2(texels per pixel), sampled coarsely and interpolated."""
    xs = x0 + np.arange(0, w + _LOD_STEP, _LOD_STEP, dtype=np.float64)
    ys = y0 + np.arange(0, h + _LOD_STEP, _LOD_STEP, dtype=np.float64)
    u, v = np.meshgrid(xs, ys)
    q0 = G[0, 0] * u + G[0, 1] * v + G[0, 2]
    q1 = G[1, 0] * u + G[1, 1] * v + G[1, 2]
    q2 = G[2, 0] * u + G[2, 1] * v + G[2, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        s, r = q0 / q2, q1 / q2
        dsu, dsv = (G[0, 0] - s * G[2, 0]) / q2, (G[0, 1] - s * G[2, 1]) / q2
        dru, drv = (G[1, 0] - r * G[2, 0]) / q2, (G[1, 1] - r * G[2, 1]) / q2
        rho = np.maximum(np.hypot(dsu, dru), np.hypot(dsv, drv))
        lod = np.log2(rho)
    lod[~np.isfinite(lod) | (q2 <= 0)] = max_level
    lod = np.clip(lod, 0.0, max_level).astype(np.float32)
    if lod.shape == (1, 1):
        return np.full((h, w), lod[0, 0], np.float32)
    return cv2.resize(lod, (w, h), interpolation=cv2.INTER_LINEAR)


def _level_span(lo: np.ndarray, hi: np.ndarray, level: int) -> tuple[int, int]:
    """Index range [a, b) where [lo, hi] meets the support of the weight of ``level``; (0, 0) if none."""
    reach = 0.5 + _BLEND_WIDTH / 2
    idx = np.flatnonzero((lo < level + reach) & (hi > level - reach))
    return (int(idx[0]), int(idx[-1]) + 1) if idx.size else (0, 0)


def _sample(plane: Plane, s: np.ndarray, r: np.ndarray, lod: np.ndarray | None) -> np.ndarray:
    """(h, w, 3) uint8 colours of texel coordinates (s, r) (level 0), filtered over mip levels.

    Level ``l`` gets weight ``clip(0.5 + (0.5 - |lod - l|) / _BLEND_WIDTH, 0, 1)``: the
    nearest level, cross-faded with the next one over a band of ``_BLEND_WIDTH`` levels
    ("brilinear" filtering: trilinear would be ``_BLEND_WIDTH = 1``). Each level is sampled
    only over the rows and columns where it has weight, and merged with ``cv2.blendLinear``.
    """
    levels = plane.mipmaps
    if lod is None:
        return cv2.remap(levels[0], s, r, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    row_lo, row_hi = lod.min(axis=1), lod.max(axis=1)
    col_lo, col_hi = lod.min(axis=0), lod.max(axis=0)
    out = np.zeros((*s.shape, 3), np.uint8)
    weight_sum = np.zeros(s.shape, np.float32)
    first = True
    for level in range(int(np.floor(row_lo.min())), int(np.ceil(row_hi.max())) + 1):
        ya, yb = _level_span(row_lo, row_hi, level)
        xa, xb = _level_span(col_lo, col_hi, level)
        if ya >= yb or xa >= xb:
            continue
        dist = np.abs(lod[ya:yb, xa:xb] - np.float32(level))
        weight = np.clip(
            np.float32(0.5 + 0.5 / _BLEND_WIDTH) - dist * np.float32(1.0 / _BLEND_WIDTH), 0.0, 1.0
        )
        scale = np.float32(0.5**level)
        sampled = cv2.remap(
            levels[level],
            s[ya:yb, xa:xb] * scale,
            r[ya:yb, xa:xb] * scale,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        if first:  # nothing drawn yet: weight_sum is 0 here, so blending would return `sampled`
            out[ya:yb, xa:xb] = sampled
            first = False
        else:
            out[ya:yb, xa:xb] = cv2.blendLinear(out[ya:yb, xa:xb], sampled, weight_sum[ya:yb, xa:xb], weight)
        weight_sum[ya:yb, xa:xb] += weight
    return out


def _draw_plane(
    plane: Plane,
    poly: np.ndarray,
    K: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    near: float,
    image: np.ndarray,
    inv_depth: np.ndarray,
) -> None:
    """Z-buffer ``plane`` (near-clipped camera-frame polygon ``poly``) into ``image``, ``inv_depth``."""
    height, width = inv_depth.shape
    proj = poly @ K.T
    uv = proj[:, :2] / proj[:, 2:3]
    x0, x1 = max(int(np.floor(uv[:, 0].min())), 0), min(int(np.ceil(uv[:, 0].max())) + 1, width)
    y0, y1 = max(int(np.floor(uv[:, 1].min())), 0), min(int(np.ceil(uv[:, 1].max())) + 1, height)
    if x0 >= x1 or y0 >= y1:
        return
    H = image_from_texture(plane, K, R, t)
    if abs(np.linalg.det(H)) < 1e-12 * np.abs(H).max() ** 3:
        return  # camera in the plane: the plane is seen edge-on
    G64 = np.linalg.inv(H)
    G = G64.astype(np.float32)
    u = np.arange(x0, x1, dtype=np.float32)[None, :]
    v = np.arange(y0, y1, dtype=np.float32)[:, None]
    inv = (G[2, 0] * u + G[2, 2]) + G[2, 1] * v
    visible = (inv > inv_depth[y0:y1, x0:x1]) & (inv <= np.float32(1.0 / near))
    rows = np.flatnonzero(visible.any(axis=1))
    if rows.size == 0:
        return
    cols = np.flatnonzero(visible.any(axis=0))
    ya, yb, xa, xb = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    inv, visible, u, v = inv[ya:yb, xa:xb], visible[ya:yb, xa:xb], u[:, xa:xb], v[ya:yb]
    x0, y0, x1, y1 = x0 + xa, y0 + ya, x0 + xb, y0 + yb
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        depth = np.float32(1.0) / inv
        s = ((G[0, 0] * u + G[0, 2]) + G[0, 1] * v) * depth
        r = ((G[1, 0] * u + G[1, 2]) + G[1, 1] * v) * depth
    tex_h, tex_w = plane.texture.shape[:2]
    # Closed rectangle test widened by _EDGE_TEXELS so that float32 rounding leaves no
    # cracks along the edges shared by adjacent planes.
    visible &= np.abs(s - np.float32((tex_w - 1) / 2)) <= np.float32(tex_w / 2 + _EDGE_TEXELS)
    visible &= np.abs(r - np.float32((tex_h - 1) / 2)) <= np.float32(tex_h / 2 + _EDGE_TEXELS)
    if not visible.any():
        return
    max_level = len(plane.mipmaps) - 1
    lod = _lod_map(G64, x0, y0, x1 - x0, y1 - y0, max_level) if max_level > 0 else None
    if lod is not None and float(lod.max()) <= 0.0:
        lod = None
    colors = _sample(plane, s, r, lod)
    mask = visible.view(np.uint8)
    # cv2.copyTo is ~15x faster than np.copyto(where=...); assigning its result keeps this
    # correct whether or not OpenCV wrote into the view in place.
    inv_depth[y0:y1, x0:x1] = cv2.copyTo(inv, mask, inv_depth[y0:y1, x0:x1])
    image[y0:y1, x0:x1] = cv2.copyTo(colors, mask, image[y0:y1, x0:x1])


def render(
    world: World,
    K: object,
    cam_from_world_R: object,
    cam_from_world_t: object,
    width: int,
    height: int,
    near: float = NEAR,
) -> tuple[np.ndarray, np.ndarray]:
    """Render the world seen by a pinhole camera.

    Args:
        world: the scene.
        K: (3, 3) intrinsics, OpenCV pixel convention.
        cam_from_world_R: (3, 3) rotation, x_cam = R x_world + t.
        cam_from_world_t: (3,) translation.
        width, height: image size in pixels.
        near: near clipping distance in metres.

    Returns:
        image: (height, width, 3) uint8 RGB; black where no surface is seen.
        depth: (height, width) float32 z-depth in metres of the surface seen through each
            pixel centre; 0 where no surface is seen.
    """
    K, R, t = _check_camera(K, cam_from_world_R, cam_from_world_t, width, height, near)
    image = np.zeros((int(height), int(width), 3), np.uint8)
    inv_depth = np.zeros((int(height), int(width)), np.float32)
    # Front to back (by nearest clipped vertex), so that hidden planes fail the depth test early.
    todo: list[tuple[float, int, Plane, np.ndarray]] = []
    for plane in world.planes:
        poly = clip_polygon_near(plane.corners @ R.T + t, float(near))
        if len(poly) >= 3:
            todo.append((float(np.linalg.norm(poly, axis=1).min()), len(todo), plane, poly))
    todo.sort(key=lambda item: item[:2])
    for _, _, plane, poly in todo:
        _draw_plane(plane, poly, K, R, t, float(near), image, inv_depth)
    depth = np.zeros_like(inv_depth)
    np.divide(np.float32(1.0), inv_depth, out=depth, where=inv_depth > 0)
    return image, depth
