"""The localizer's configuration: :class:`LocalizerConfig` and :func:`localizer_config`, the one
source of defaults every front door (CLI, service, ROS node) builds its configuration from."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from planarloc.features.matching import DEFAULT_RATIO
from planarloc.features.retrieval import DEFAULT_TOP_N
from planarloc.geometry.validation import InputError, check_integer
from planarloc.robust.options import Method, RansacOptions, Structure, parse_method

MAP_PRIORS = ("measured", "configured")
"""Where :attr:`LocalizerConfig.map_prior` takes the map pose prior from."""


@dataclass(frozen=True)
class LocalizerConfig:
    """Settings of the localization pipeline; the CLI uses these defaults.

    Attributes:
        top_n: number of retrieved map images (paper: 5).
        method: hypothesis families (``"auto"`` default: planar where it holds, 6DoF
            otherwise; the paper's ``"2p1p"`` etc. by name, see :class:`Method`).
        ransac: estimator options (structure mode, thresholds, iterations).
        ratio: ratio-test threshold of the matcher.
        use_depth: use the map images' depth maps (if any) as 2D-3D constraints.
        min_matches: references with fewer matches are dropped before estimation.
        map_prior: ``"measured"`` (default): the map pose prior is the map's own measurement
            (:mod:`planarloc.map.pose_accuracy`, stored by ``map build``) where the map has one,
            else ``ransac.map_rotation_std_deg`` / ``map_position_std_m``; ``"configured"``:
            always those two options.
        coarse_keypoints: a query first localizes from its ``coarse_keypoints`` strongest
            keypoints against as many of each of its ``coarse_top_n`` first retrieved map images
            (the coarse pass), and from all of them against every retrieved image only when that
            pass fails (its status is not ``success``): a quarter of the similarities per image,
            fewer images, fewer matches to verify, and most poses are pinned. Every pass is judged
            in full, so a pose of the coarse pass is a promise as any other; it is less precise
            (its std says by how much). ``None`` (default): the feature type's
            (:attr:`~planarloc.features.registry.FeatureType.coarse_keypoints`: 2,048 for
            ``xfeat``; no coarse pass for the others) with local structure (``tracks``, the
            default), none on 2D-2D constraints alone (``ransac.structure`` ``none``: there the
            coarse pass broke promises, :attr:`~planarloc.localize.localizer.Localizer.coarse_keypoints`);
            ``0``: every pass uses all keypoints. For a type that does not rank its keypoints
            (``rootsift``), a number > 0 takes the first ones stored, not the strongest.
        coarse_top_n: how many of the retrieved map images (the first, most similar ones) the
            coarse pass matches (at least 2). 3 of the 5: with XFeat, as many successes on the
            shared and generated sets as all 5, in 0.6–0.85x the time (BENCHMARKS.md).
    """

    top_n: int = DEFAULT_TOP_N
    method: Method | str = Method.AUTO
    ransac: RansacOptions = field(default_factory=RansacOptions)
    ratio: float = DEFAULT_RATIO
    use_depth: bool = False
    min_matches: int = 3
    map_prior: str = "measured"
    coarse_keypoints: int | None = None
    coarse_top_n: int = 3

    def __post_init__(self) -> None:
        object.__setattr__(self, "method", parse_method(self.method))  # a name ("2p1p") becomes its Method
        if self.map_prior not in MAP_PRIORS:
            raise InputError(f"map_prior: expected one of {', '.join(MAP_PRIORS)}, got {self.map_prior!r}")
        check_integer("coarse_keypoints", self.coarse_keypoints, 0, allow_none=True)
        check_integer("coarse_top_n", self.coarse_top_n, 2)
        if self.coarse_keypoints is not None:
            object.__setattr__(self, "coarse_keypoints", int(self.coarse_keypoints))
        object.__setattr__(self, "coarse_top_n", int(self.coarse_top_n))
        if int(self.top_n) < 2:
            raise InputError(f"top_n: need at least 2 reference images to fix the scale, got {self.top_n}")


def localizer_config(
    *,
    method: Method | str | None = None,
    structure: Structure | str | None = None,
    seed: int | None = None,
    top_n: int | None = None,
    iterations: int | None = None,
    threshold_px: float | None = None,
    max_position_std_m: float | None = None,
    use_depth: bool | None = None,
    coarse_keypoints: int | None = None,
    coarse_top_n: int | None = None,
) -> LocalizerConfig:
    """A :class:`LocalizerConfig` from the settings a front door lets its user choose.

    Every argument left None keeps the default of :class:`LocalizerConfig` /
    :class:`~planarloc.robust.options.RansacOptions`, so the CLI, the service and a ROS node
    configure alike. ``iterations`` fixes the number of RANSAC iterations (the paper: 100).
    ``coarse_keypoints`` None keeps the feature type's coarse pass (:attr:`LocalizerConfig.coarse_keypoints`).

    Raises:
        InputError: a value the options refuse (unknown method or structure, out of range).
    """
    ransac: dict[str, object] = {}
    for key, value in (
        ("structure", structure),
        ("seed", seed),
        ("threshold_px", threshold_px),
        ("max_position_std_m", max_position_std_m),
    ):
        if value is not None:
            ransac[key] = value
    if iterations is not None:
        ransac.update(min_iterations=iterations, max_iterations=iterations)
    config: dict[str, object] = {"ransac": RansacOptions(**ransac)}  # type: ignore[arg-type]
    for key, value in (
        ("method", method),
        ("top_n", top_n),
        ("use_depth", use_depth),
        ("coarse_keypoints", coarse_keypoints),
        ("coarse_top_n", coarse_top_n),
    ):
        if value is not None:
            config[key] = value
    return LocalizerConfig(**config)  # type: ignore[arg-type]


#: the localizer settings every front door names alike (its options' or parameters' attributes)
SHARED_SETTINGS = ("method", "structure", "seed", "top_n")


def localizer_config_from(
    source: object, names: Iterable[str] = SHARED_SETTINGS, **more: Any
) -> LocalizerConfig:
    """:func:`localizer_config` of the attributes ``names`` of ``source`` (an argparse namespace, a
    node's parameters) and of ``more``."""
    return localizer_config(**{name: getattr(source, name) for name in names}, **more)
