"""Tilt augmentation of map images (the "Tilt" of TiltR2D2), with SIFT in place of R2D2.

Under local planar motion the affine distortion between a query and a reference view reduces
to a scale change plus a *transition tilt*: a vertical stretch of the image (paper, Sec. III-B;
Jiao et al., "Leveraging local planar motion property for robust visual matching and
localization", RA-L 2022). Scale is handled by the detector; the tilt is simulated on the map
images: each image is compressed vertically by ``t`` for the tilts ``t = √2^j, j = 0…5``
(1, 1.41, 2, 2.83, 4, 5.66), features are extracted on every compressed copy, their
y-coordinates are mapped back to the original image, and all tilts are pooled.

Anti-aliasing follows ASIFT (Morel & Yu, "ASIFT: A new framework for fully affine invariant
image comparison", SIAM J. Imaging Sci. 2009): a Gaussian of σ = 0.8·√(t² − 1) along
the compressed axis only, before subsampling.

Pixel convention: OpenCV (centre of the top-left pixel at (0, 0)). ``cv2.resize`` with
``INTER_LINEAR`` samples destination pixel ``y'`` at source position ``(y' + 0.5)·s − 0.5`` with
``s = H / H'`` the exact height ratio, so a point at ``y'`` in the compressed image lies at
``y = (y' + 0.5)·s − 0.5`` in the original. Deviation from the published description of
TiltR2D2 ("multiply y back by t"): ``y'·t`` is off by ``0.5·(t − 1)`` pixels (2.3 px at
t = 5.66) and ignores the rounding of ``H / t``; we use the exact mapping.

This module is detector-agnostic: :func:`tilted_extraction` takes a ``detect`` callable, so
:mod:`planarloc.features.extract` composes it with SIFT.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence

import cv2
import numpy as np

from planarloc.geometry.validation import InputError, check_array

logger = logging.getLogger(__name__)

DEFAULT_TILTS: tuple[float, ...] = tuple(math.sqrt(2.0) ** j for j in range(6))
"""The paper's six tilts √2^j, j = 0…5."""

ASIFT_BLUR = 0.8
"""ASIFT anti-aliasing constant c in σ = c·√(t² − 1)."""

DetectFn = Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray, np.ndarray]]
"""``detect(gray (H, W) uint8, max_features) -> (keypoints (N, 2), descriptors (N, D), sizes (N,))``."""


def check_tilts(tilts: Sequence[float]) -> tuple[float, ...]:
    """Validate a tilt list: non-empty, finite, every ``t >= 1``; returns it as a tuple of floats."""
    arr = check_array("tilts", tilts, (None,))
    if arr.size == 0:
        raise InputError("tilts: expected at least one tilt, got an empty list; hint: use (1.0,) for no tilt")
    if np.any(arr < 1.0):
        raise InputError(f"tilts: every tilt must be >= 1 (a vertical compression), got {arr.tolist()}")
    return tuple(float(t) for t in arr)


def tilted_height(height: int, t: float) -> int:
    """Height in pixels of an image of ``height`` rows compressed by tilt ``t`` (at least 1)."""
    return max(1, int(round(height / t)))


def tilt_image(gray: np.ndarray, t: float, blur: float = ASIFT_BLUR) -> tuple[np.ndarray, float]:
    """Compress an image vertically by tilt ``t`` after anti-aliasing along y.

    Args:
        gray: (H, W) uint8 image.
        t: tilt >= 1; ``t = 1`` returns the image unchanged.
        blur: ASIFT constant ``c``; the Gaussian has σ = c·√(s² − 1) pixels along y only,
            with ``s`` the exact height ratio.

    Returns:
        ``(tilted, s)``: the (round(H / t), W) uint8 image and the exact ratio ``s = H / H'``
        to pass to :func:`original_from_tilted`.

    References:
        Morel & Yu, ASIFT (SIAM J. Imaging Sci. 2009), anti-aliasing before tilt subsampling.
    """
    if gray.ndim != 2:
        raise InputError(f"gray: expected shape (H, W), got {gray.shape}")
    if not t >= 1.0:
        raise InputError(f"t: tilt must be >= 1, got {t}")
    h, w = gray.shape
    h_t = tilted_height(h, t)
    if h_t == h:
        return gray, 1.0
    s = h / h_t
    sigma = blur * math.sqrt(s * s - 1.0)
    # Separable blur along y only: a 1x1 kernel in x (ksize width 1) and 2·ceil(4σ)+1 taps in y.
    ky = 2 * int(math.ceil(4.0 * sigma)) + 1
    blurred = cv2.GaussianBlur(gray, (1, ky), sigmaX=1e-6, sigmaY=sigma, borderType=cv2.BORDER_REFLECT_101)
    tilted = cv2.resize(blurred, (w, h_t), interpolation=cv2.INTER_LINEAR)
    return tilted, s


def original_from_tilted(points: np.ndarray, s: float) -> np.ndarray:
    """Map (N, 2) pixel coordinates of a tilted image back to the original image.

    ``x`` is unchanged; ``y = (y' + 0.5)·s − 0.5`` (``cv2.resize`` pixel-centre mapping, OpenCV
    convention), with ``s = H / H'`` returned by :func:`tilt_image`.

    Example:
        >>> original_from_tilted(np.array([[10.0, 0.0]]), 2.0)
        array([[10. ,  0.5]])
    """
    pts = check_array("points", points, (None, 2))
    out = pts.copy()
    out[:, 1] = (pts[:, 1] + 0.5) * s - 0.5
    return out


def tilted_from_original(points: np.ndarray, s: float) -> np.ndarray:
    """Inverse of :func:`original_from_tilted`: ``y' = (y + 0.5) / s − 0.5``; (N, 2) -> (N, 2)."""
    pts = check_array("points", points, (None, 2))
    out = pts.copy()
    out[:, 1] = (pts[:, 1] + 0.5) / s - 0.5
    return out


def tilt_budgets(max_features: int, tilts: Sequence[float]) -> list[int]:
    """Feature budget per tilt, proportional to the area of the tilted image.

    The untilted image (t = 1) keeps the full ``max_features``, so the t = 1 part of the pool is
    exactly the plain extraction; tilt ``t`` gets ``ceil(max_features / t)``, the same feature
    density. The pool is therefore bounded by ``max_features·Σ 1/t`` (≈ 2.99·max_features for
    the default tilts).
    """
    return [max(1, int(math.ceil(max_features / t))) for t in tilts]


def tilted_extraction(
    gray: np.ndarray,
    detect: DetectFn,
    max_features: int,
    tilts: Sequence[float] = DEFAULT_TILTS,
    blur: float = ASIFT_BLUR,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Extract and pool features over vertically tilted copies of ``gray``.

    Args:
        gray: (H, W) uint8 image.
        detect: detector, ``detect(image, budget) -> (keypoints (N, 2), descriptors (N, D),
            sizes (N,))`` in the pixel coordinates of ``image``.
        max_features: budget of the untilted image; see :func:`tilt_budgets`.
        tilts: tilts ``t >= 1``; default the paper's √2^j, j = 0…5.
        blur: ASIFT anti-aliasing constant (σ = blur·√(t² − 1)).

    Returns:
        ``(keypoints (N, 2) float32, descriptors (N, D) float32, sizes (N,) float32,
        tilt_index (N,) int32)``: keypoints in ORIGINAL image pixels, descriptors as returned by
        ``detect``, sizes in tilted-image pixels (= horizontal extent in the original), and the
        index into ``tilts`` each feature came from. Tilts are concatenated in the given order.

    References:
        Paper Sec. III-B; Jiao et al., RA-L 2022 (TiltR2D2), tilt augmentation of the map.
    """
    tilts = check_tilts(tilts)
    kps, descs, sizes, index = [], [], [], []
    for j, (t, budget) in enumerate(zip(tilts, tilt_budgets(max_features, tilts), strict=True)):
        tilted, s = tilt_image(gray, t, blur)
        kp, desc, size = detect(tilted, budget)
        kps.append(original_from_tilted(kp, s).astype(np.float32) if len(kp) else kp.reshape(0, 2))
        descs.append(desc)
        sizes.append(size)
        index.append(np.full(len(kp), j, dtype=np.int32))
        logger.debug(
            "tilt %.3f (s=%.4f, %dx%d): %d features", t, s, tilted.shape[1], tilted.shape[0], len(kp)
        )
    return (
        np.concatenate(kps).astype(np.float32, copy=False),
        np.concatenate(descs).astype(np.float32, copy=False),
        np.concatenate(sizes).astype(np.float32, copy=False),
        np.concatenate(index),
    )
