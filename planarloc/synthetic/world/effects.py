"""Session effects: lighting change, blur and noise on images; camera mount and pitch/roll jitter on poses.

Image functions take and return (H, W, 3) uint8 images and are deterministic given their
arguments (noise draws from the ``numpy.random.Generator`` passed in). Scene changes
(moved or added boxes) are in :func:`planarloc.synthetic.world.placement.rearrange_boxes`.
"""

from __future__ import annotations

import cv2
import numpy as np

from planarloc.synthetic.world.config import EffectsConfig


def apply_lighting(
    image: np.ndarray,
    gain: float,
    gamma: float,
    shading_gradient: float = 0.0,
    shading_angle_rad: float = 0.0,
) -> np.ndarray:
    """Global exposure/tone change and a smooth brightness ramp.

    ``out = 255 * gain * (in / 255) ** gamma * (1 + shading_gradient * ramp)`` where ``ramp``
    goes linearly from -1 to 1 across the image along the direction ``shading_angle_rad``
    (0: left to right, pi/2: top to bottom).
    """
    lut = np.clip(np.rint(255.0 * gain * (np.arange(256) / 255.0) ** gamma), 0, 255).astype(np.uint8)
    out = cv2.LUT(image, lut)
    if shading_gradient == 0:
        return out
    h, w = image.shape[:2]
    xs = (np.arange(w, dtype=np.float32) - (w - 1) / 2) / max(w / 2, 1)
    ys = (np.arange(h, dtype=np.float32) - (h - 1) / 2) / max(h / 2, 1)
    c, s = np.float32(np.cos(shading_angle_rad)), np.float32(np.sin(shading_angle_rad))
    ramp = c * xs[None, :] + s * ys[:, None]
    ramp /= max(float(np.abs(ramp).max()), 1e-6)
    shade = (np.float32(1.0) + np.float32(shading_gradient) * ramp).astype(np.float32)
    return cv2.multiply(out, cv2.merge([shade, shade, shade]), dtype=cv2.CV_8U)


def add_noise(image: np.ndarray, rng: np.random.Generator, sigma: float) -> np.ndarray:
    """Add i.i.d. Gaussian noise of standard deviation ``sigma`` grey levels; rounds and clips."""
    if sigma == 0:
        return image.copy()
    noise = rng.standard_normal(image.shape, dtype=np.float32)
    noise *= np.float32(sigma)
    return cv2.add(image, noise, dtype=cv2.CV_8U)  # rounds to nearest and saturates


def blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of standard deviation ``sigma`` pixels (no-op for 0)."""
    if sigma == 0:
        return image.copy()
    return cv2.GaussianBlur(image, (0, 0), sigmaX=float(sigma), borderType=cv2.BORDER_REFLECT)


def apply_image_effects(image: np.ndarray, effects: EffectsConfig, rng: np.random.Generator) -> np.ndarray:
    """Lighting, then blur, then sensor noise, as configured in ``effects``."""
    out = image
    if effects.gain != 1 or effects.gamma != 1 or effects.shading_gradient != 0:
        out = apply_lighting(
            out, effects.gain, effects.gamma, effects.shading_gradient, np.radians(effects.shading_angle_deg)
        )
    out = blur(out, effects.blur_sigma)
    return add_noise(out, rng, effects.noise_sigma)


def tilt_rotation(pitch: float, roll: float) -> np.ndarray:
    """(3, 3) camera-frame rotation ``R_x(pitch) @ R_z(roll)`` (radians): pitch about x, roll about z."""
    cp, sp, cr, sr = np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    rz = np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
    return rx @ rz


def mount_poses(
    R: np.ndarray, t: np.ndarray, pitch_deg: float, roll_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Apply a fixed camera mount to poses, keeping the centres.

    Args:
        R: (N, 3, 3) ``cam_from_world`` rotations; t: (N, 3) translations.
        pitch_deg: downward pitch of the optical axis (positive: looks below the horizon).
        roll_deg: roll about the optical axis (positive: the camera's x-axis goes up).

    Returns:
        (R', t') with ``R' = M R``, ``t' = M t`` and ``M = R_x(pitch) R_z(roll)``; the inputs
        themselves (not copies) when both angles are 0, so upright sessions stay bit-identical.
    """
    if pitch_deg == 0 and roll_deg == 0:
        return R, t
    mount = tilt_rotation(np.radians(pitch_deg), np.radians(roll_deg))
    return mount @ np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64) @ mount.T


def gravity_in_camera(R: np.ndarray) -> np.ndarray:
    """(N, 3) unit direction of gravity (down) in the camera frames of (N, 3, 3) ``cam_from_world``
    rotations: the world is y-down, so ``g_cam = R (0, 1, 0)`` (the second column of R)."""
    return np.asarray(R, dtype=np.float64)[..., :, 1].copy()


def tilt_poses(
    R: np.ndarray, t: np.ndarray, rng: np.random.Generator, max_tilt_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Add random pitch and roll (each uniform in +-``max_tilt_deg``) to camera poses, keeping the centres.

    Args:
        R: (N, 3, 3) ``cam_from_world`` rotations; t: (N, 3) translations.

    Returns:
        (R', t') with ``R' = R_x(pitch) R_z(roll) R`` and ``t' = R_x(pitch) R_z(roll) t``.
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    angles = np.radians(max_tilt_deg) * rng.uniform(-1.0, 1.0, size=(len(R), 2))
    tilt = np.stack([tilt_rotation(p, r) for p, r in angles]) if len(R) else np.zeros((0, 3, 3))
    return tilt @ R, np.einsum("nij,nj->ni", tilt, t)
