"""Command-line options shared by subcommands, with defaults taken from the library's configs
(one source of defaults for API and CLI)."""

from __future__ import annotations

import argparse

from planarloc.geometry.camera import Camera
from planarloc.io.datasets import FORMATS
from planarloc.pipeline.features import DEFAULT_FEATURE_CONFIG, FeatureConfig
from planarloc.pipeline.localizer import LocalizerConfig
from planarloc.pipeline.retrieval import DEFAULT_NUM_WORDS
from planarloc.robust.options import Method, RansacOptions, Structure

_RANSAC = RansacOptions()
_LOC = LocalizerConfig()


def add_dataset_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("dataset", help="dataset folder (see --format)")
    p.add_argument("--format", "-f", required=True, choices=sorted(FORMATS),
                   help="dataset layout: kitti (image_l/, poses.txt, calib.txt), tum (rgb.txt, groundtruth.txt, "
                        "camera.txt), openloris, kapture, colmap (text model), list (name qw qx qy qz tx ty tz)")


def add_feature_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--tilt", action="store_true",
                   help="tilt-augment map features (paper Sec. III-B: 6 vertical tilts, ~3x slower build, "
                        "more matches under viewpoint change)")
    p.add_argument("--max-features", type=int, default=DEFAULT_FEATURE_CONFIG.max_features,
                   help="SIFT keypoints per image (default: %(default)s)")
    p.add_argument("--vocabulary-size", type=int, default=DEFAULT_NUM_WORDS,
                   help="VLAD visual words for retrieval (default: %(default)s)")


def check_vocabulary_size(value: int) -> int:
    """--vocabulary-size as a positive int (checked before any work)."""
    if value < 1:
        raise ValueError(f"--vocabulary-size must be >= 1, got {value}")
    return int(value)


def feature_config(args: argparse.Namespace) -> FeatureConfig:
    return FeatureConfig(max_features=args.max_features, tilt=args.tilt)


def add_localizer_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("localization")
    g.add_argument("--method", "-m", default=Method(_LOC.method).value, choices=[m.value for m in Method],
                   help="absolute pose solver: 2p1p / 2p2p (paper, planar) or the 6DoF baselines "
                        "(default: %(default)s)")
    g.add_argument("--structure", "-s", default=_RANSAC.structure.value, choices=[s.value for s in Structure],
                   help="none = the paper's 2D-2D constraints only (position unobservable when the query is "
                        "collinear with the map images: reported as degenerate_scale); tracks = also "
                        "triangulate query keypoints seen in 2+ map images (default: %(default)s)")
    g.add_argument("--top-n", "-k", type=int, default=_LOC.top_n, help="retrieved map images (default: %(default)s)")
    g.add_argument("--pairs", help="hloc pairs file 'query db' to use instead of the built-in VLAD retrieval")
    g.add_argument("--use-depth", action="store_true", help="use map depth images as 2D-3D constraints")
    g.add_argument("--iterations", type=int, default=None,
                   help="fixed number of RANSAC iterations (the paper uses 100); default: adaptive "
                        f"between {_RANSAC.min_iterations} and {_RANSAC.max_iterations}")
    g.add_argument("--threshold", type=float, default=_RANSAC.threshold_px,
                   help="inlier threshold, Sampson error in pixels (default: %(default)s)")
    g.add_argument("--max-position-std", type=float, default=_RANSAC.max_position_std_m,
                   help="report degenerate_scale above this position std in metres (default: %(default)s)")
    g.add_argument("--seed", type=int, default=0, help="RANSAC seed (default: %(default)s)")


def localizer_config(args: argparse.Namespace) -> LocalizerConfig:
    it = {} if args.iterations is None else {"min_iterations": args.iterations, "max_iterations": args.iterations}
    ransac = RansacOptions(structure=args.structure, threshold_px=args.threshold,
                           max_position_std_m=args.max_position_std, seed=args.seed, **it)
    return LocalizerConfig(top_n=args.top_n, method=args.method, ransac=ransac, use_depth=args.use_depth)


def parse_camera(text: str) -> Camera:
    """'MODEL W H P1 P2 ...' (COLMAP syntax) -> Camera."""
    tok = text.replace(",", " ").split()
    if len(tok) < 4:
        raise ValueError(f"--camera: expected 'MODEL WIDTH HEIGHT PARAMS...', e.g. 'PINHOLE 640 480 500 500 320 240', "
                         f"got {text!r}")
    try:
        return Camera(tok[0], tok[1], tok[2], tuple(float(v) for v in tok[3:]))
    except ValueError as exc:
        raise ValueError(f"--camera {text!r}: {exc}") from None
