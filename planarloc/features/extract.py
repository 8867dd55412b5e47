"""Local features: OpenCV SIFT with RootSIFT descriptors (or a learned type), optionally tilt-augmented.

:class:`FeatureConfig` is the single source of defaults for the API and the CLI
(:data:`DEFAULT_FEATURE_CONFIG`); :func:`extract_features` is the in-memory core used for one
live frame as well as for building a map. ``FeatureConfig.kind`` names the feature type
(:mod:`planarloc.features.registry`): ``rootsift`` here, the learned ones through
:mod:`planarloc.features.learned` (imported only when used: it needs torch).

References:
    Lowe, "Distinctive image features from scale-invariant keypoints", IJCV 2004 (SIFT).
    Arandjelović & Zisserman, "Three things everyone should know to improve object retrieval",
    CVPR 2012, Sec. 2 (RootSIFT: L1-normalise, element-wise square root).
    Paper Sec. III-B and :mod:`planarloc.features.tilt` (tilt augmentation).
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

import cv2
import numpy as np

from planarloc.features import tilt as _tilt
from planarloc.features.images import to_gray
from planarloc.features.registry import DEFAULT_FEATURE_TYPE, feature_type
from planarloc.geometry.validation import InputError

logger = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Features:
    """Local features of one image.

    Attributes:
        keypoints: (N, 2) float32 pixel coordinates (OpenCV convention, x right, y down),
            in the ORIGINAL image (tilted extractions are mapped back).
        descriptors: (N, D) float32 descriptors, L2-normalised (RootSIFT: D = 128, XFeat: 64,
            ALIKED: 128).
        scales: (N,) float32 keypoint sizes in pixels (learned types: a constant, they have none).
    """

    keypoints: np.ndarray
    descriptors: np.ndarray
    scales: np.ndarray

    def __len__(self) -> int:
        return len(self.keypoints)

    def first(self, n: int) -> Features:
        """The first ``n`` features, as views of these arrays (read-only stays read-only); ``self``
        when it has ``n`` or fewer. For a type that extracts strongest first
        (:attr:`~planarloc.features.registry.FeatureType.coarse_keypoints`), the ``n`` strongest:
        what a budget of ``n`` extracts."""
        if n < 0:
            raise InputError(f"Features.first: expected n >= 0, got {n}")
        if len(self) <= n:
            return self
        return Features(self.keypoints[:n], self.descriptors[:n], self.scales[:n])


@dataclass(frozen=True)
class FeatureConfig:
    """Settings of :func:`extract_features`; the defaults are the library's and the CLI's.

    Attributes:
        kind: the feature type, one of :data:`planarloc.features.registry.FEATURE_TYPES`
            (``rootsift``, ``xfeat``, ``xfeat-lighterglue``, ``aliked-lightglue``; ``--features``).
            The SIFT settings below (``contrast_threshold`` … ``rootsift``) only apply to ``rootsift``;
            ``max_features``, the tilts and ``resize_max`` apply to every type.
        max_features: SIFT keeps at most this many keypoints (by contrast response) on the
            untilted image; tilt ``t`` gets ``ceil(max_features / t)`` (same density), so a
            tilted pool holds at most ≈ 2.99·max_features for the default tilts.
        contrast_threshold: OpenCV SIFT ``contrastThreshold`` (divided internally by
            ``n_octave_layers``; 0.04 is OpenCV's default, Lowe's 0.03 corresponds to 0.09).
            Lower values give more keypoints in low-texture scenes at extra cost.
        edge_threshold: OpenCV SIFT ``edgeThreshold`` (Lowe's r = 10).
        n_octave_layers: scales per octave (Lowe: 3).
        sigma: Gaussian σ of octave 0 (Lowe: 1.6).
        rootsift: RootSIFT descriptors (L1-normalise, sqrt); ``False`` keeps SIFT, L2-normalised.
        tilt: pool features over the vertical tilts ``tilts`` (for MAP images; paper Sec. III-B).
        tilts: tilts ``t >= 1``; default the paper's √2^j, j = 0…5.
        tilt_blur: ASIFT anti-aliasing constant c, σ_y = c·√(t² − 1).
        resize_max: images whose longer side exceeds this many pixels are downscaled to it
            (``cv2.INTER_AREA``) before detection, as hloc does (its SIFT default, 1600);
            keypoints and scales are mapped back to full-resolution pixels. ``None`` keeps
            the full resolution. Stored with a map so that queries are extracted the same way;
            a map built before this setting existed reads as ``None`` (it was not resized).
    """

    max_features: int = 4000
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    n_octave_layers: int = 3
    sigma: float = 1.6  # px
    rootsift: bool = True
    tilt: bool = False
    tilts: tuple[float, ...] = _tilt.DEFAULT_TILTS
    tilt_blur: float = _tilt.ASIFT_BLUR
    resize_max: int | None = 1600
    kind: str = DEFAULT_FEATURE_TYPE

    def __post_init__(self) -> None:
        feature_type(self.kind, "FeatureConfig.kind (--features)")
        if self.resize_max is not None:
            if isinstance(self.resize_max, bool) or int(self.resize_max) < 16:
                raise InputError(
                    f"FeatureConfig.resize_max: expected None or an integer >= 16, got {self.resize_max}"
                )
            object.__setattr__(self, "resize_max", int(self.resize_max))
        if int(self.max_features) < 1:
            raise InputError(f"FeatureConfig.max_features: expected >= 1, got {self.max_features}")
        if not self.contrast_threshold > 0:
            raise InputError(f"FeatureConfig.contrast_threshold: expected > 0, got {self.contrast_threshold}")
        if not self.edge_threshold > 0:
            raise InputError(f"FeatureConfig.edge_threshold: expected > 0, got {self.edge_threshold}")
        if int(self.n_octave_layers) < 1:
            raise InputError(f"FeatureConfig.n_octave_layers: expected >= 1, got {self.n_octave_layers}")
        if not self.sigma > 0:
            raise InputError(f"FeatureConfig.sigma: expected > 0, got {self.sigma}")
        if not self.tilt_blur >= 0:
            raise InputError(f"FeatureConfig.tilt_blur: expected >= 0, got {self.tilt_blur}")
        object.__setattr__(self, "max_features", int(self.max_features))
        object.__setattr__(self, "n_octave_layers", int(self.n_octave_layers))
        object.__setattr__(self, "tilts", _tilt.check_tilts(self.tilts))

    @property
    def name(self) -> str:
        """Short name encoding the settings that change descriptors, e.g. ``rootsift-n4000-tilt6``.

        Stored with a map so that query and map features are known to be compatible. Learned
        types start with their kind (``xfeat-n4000``) and carry no SIFT settings.
        """
        default = FeatureConfig.__dataclass_fields__
        learned = self.kind != DEFAULT_FEATURE_TYPE
        parts = [self.kind if learned else "rootsift" if self.rootsift else "sift", f"n{self.max_features}"]
        for field, tag in (
            ()
            if learned
            else (
                ("contrast_threshold", "ct"),
                ("edge_threshold", "et"),
                ("n_octave_layers", "ol"),
                ("sigma", "s"),
            )
        ):
            if getattr(self, field) != default[field].default:
                parts.append(f"{tag}{getattr(self, field):g}")
        if self.tilt:
            if self.tilts == _tilt.DEFAULT_TILTS:
                parts.append(f"tilt{len(self.tilts)}")
            else:
                parts.append("tilt" + "_".join(f"{t:.3g}" for t in self.tilts))
            if self.tilt_blur != _tilt.ASIFT_BLUR:
                parts.append(f"tb{self.tilt_blur:g}")
        if self.resize_max != default["resize_max"].default:
            parts.append("full" if self.resize_max is None else f"r{self.resize_max}")
        return "-".join(parts)


DEFAULT_FEATURE_CONFIG = FeatureConfig()
"""The defaults shared by the API and the CLI."""

# One SIFT object per (thread, detector parameters): creating it is cheap (≈ 2 µs measured) but
# OpenCV does not document Feature2D objects as thread-safe, so each thread gets its own.
_detectors = threading.local()


def _sift(config: FeatureConfig, max_features: int) -> cv2.SIFT:
    key = (
        max_features,
        config.n_octave_layers,
        config.contrast_threshold,
        config.edge_threshold,
        config.sigma,
    )
    cache = getattr(_detectors, "cache", None)
    if cache is None:
        cache = _detectors.cache = {}
    sift = cache.get(key)
    if sift is None:
        sift = cv2.SIFT_create(  # type: ignore[attr-defined]  # missing from opencv's stubs
            nfeatures=max_features,
            nOctaveLayers=config.n_octave_layers,
            contrastThreshold=config.contrast_threshold,
            edgeThreshold=config.edge_threshold,
            sigma=config.sigma,
            # OpenCV's default upsampling of octave -1 reports keypoints 0.25 px too far right and
            # down (measured: +0.254, +0.257 px on KITTI); the precise upscale removes that bias
            # (measured < 0.01 px) at no extra cost. It matters for tilts, where y is scaled by t.
            enable_precise_upscale=True,
        )
        cache[key] = sift
    return sift


def rootsift(descriptors: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """RootSIFT from SIFT descriptors: L1-normalise, element-wise sqrt, L2-normalise.

    Args:
        descriptors: (N, D) non-negative SIFT descriptors (any scale).
        eps: guards all-zero rows (they stay zero).

    Returns:
        (N, D) float32, each non-zero row of unit L2 norm; the dot product of two RootSIFT
        vectors is the Hellinger kernel of the SIFT histograms.

    References:
        Arandjelović & Zisserman, CVPR 2012, Sec. 2.
    """
    d = np.asarray(descriptors, dtype=np.float32)
    if d.ndim != 2:
        raise InputError(f"descriptors: expected shape (N, D), got {d.shape}")
    if d.size and d.min() < 0:
        raise InputError("descriptors: SIFT descriptors must be non-negative for RootSIFT")
    d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), eps))
    # Already unit-norm up to rounding (Σ sqrt(p)² = Σ p = 1); renormalise to float32 precision.
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), eps)


def _l2_normalize(d: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    d = np.asarray(d, dtype=np.float32)
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), eps)


def _detect_sift(gray: np.ndarray, config: FeatureConfig, max_features: int):
    """(H, W) uint8 -> keypoints (N, 2) float32, raw SIFT descriptors (N, 128) float32, sizes (N,)."""
    kps, desc = _sift(config, max_features).detectAndCompute(gray, None)
    if not kps:
        return np.zeros((0, 2), np.float32), np.zeros((0, 128), np.float32), np.zeros(0, np.float32)
    pts = np.array([kp.pt for kp in kps], dtype=np.float32)
    sizes = np.array([kp.size for kp in kps], dtype=np.float32)
    return pts, desc.astype(np.float32, copy=False), sizes


def _detector(config: FeatureConfig):
    """The :data:`planarloc.features.tilt.DetectFn` of ``config.kind`` (a learned one imports torch)."""
    if config.kind == DEFAULT_FEATURE_TYPE:
        return lambda img, n: _detect_sift(img, config, n)
    from planarloc.features import learned  # torch: only for the learned types

    return learned.DETECTORS[config.kind]


def extract_features(image: np.ndarray, config: FeatureConfig = DEFAULT_FEATURE_CONFIG) -> Features:
    """Detect keypoints and compute descriptors: SIFT with (Root)SIFT descriptors, or the
    learned type ``config.kind`` (:mod:`planarloc.features.learned`).

    Args:
        image: (H, W) or (H, W, 3) uint8 image; colour images are BGR (as from ``cv2.imread``).
        config: extraction settings; ``config.tilt`` pools features over vertically tilted copies
            (intended for map images, see :mod:`planarloc.features.tilt`).

    Returns:
        :class:`Features` with keypoints (N, 2) in original-image pixels (also when
        ``config.resize_max`` downscaled the image for detection; OpenCV convention;
        OpenCV's precise upscale is enabled, so keypoints carry no 0.25 px bias),
        descriptors (N, D) float32 with unit L2 norm (D = 128 for RootSIFT and ALIKED, 64 for
        XFeat), and scales (N,) = SIFT keypoint size in pixels (of the tilted image for tilted
        features, i.e. their horizontal extent; learned types: a constant 8 px).
        An image without texture gives N = 0.

    Raises:
        InputError: on a non-uint8, empty or wrongly shaped image.
        MissingExtraError: a learned ``config.kind`` whose packages are not installed (an
            ImportError naming ``pip install 'planarloc[learned]'`` or ``[aliked]``).

    Example:
        >>> img = (np.random.default_rng(0).random((120, 160)) * 255).astype(np.uint8)
        >>> f = extract_features(img, FeatureConfig(max_features=500))
        >>> f.descriptors.shape[1], bool(np.allclose(np.linalg.norm(f.descriptors, axis=1), 1))
        (128, True)
    """
    gray = to_gray(image)
    full_shape = gray.shape
    resized = config.resize_max is not None and max(gray.shape) > config.resize_max
    if resized:
        s = config.resize_max / max(gray.shape)
        size = (max(1, round(gray.shape[1] * s)), max(1, round(gray.shape[0] * s)))
        gray = cv2.resize(gray, size, interpolation=cv2.INTER_AREA)
    detect = _detector(config)
    if config.tilt:
        pts, desc, sizes, _ = _tilt.tilted_extraction(
            gray,
            detect,
            config.max_features,
            config.tilts,
            config.tilt_blur,
        )
    else:
        pts, desc, sizes = detect(gray, config.max_features)
    desc = rootsift(desc) if config.rootsift and config.kind == DEFAULT_FEATURE_TYPE else _l2_normalize(desc)
    if resized:
        # Pixel centres at integer coordinates (OpenCV): x_small + 0.5 = s (x_full + 0.5).
        sx, sy = gray.shape[1] / full_shape[1], gray.shape[0] / full_shape[0]
        pts = np.column_stack([(pts[:, 0] + 0.5) / sx - 0.5, (pts[:, 1] + 0.5) / sy - 0.5]).astype(np.float32)
        sizes = (sizes / (0.5 * (sx + sy))).astype(np.float32)
    logger.debug(
        "extracted %d features (%s) on a %dx%d image (of %dx%d)",
        len(pts),
        config.name,
        gray.shape[1],
        gray.shape[0],
        full_shape[1],
        full_shape[0],
    )
    return Features(keypoints=pts, descriptors=desc, scales=sizes)
