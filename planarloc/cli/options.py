"""Command-line options shared by subcommands, with defaults taken from the library's configs
(one source of defaults for API and CLI)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from planarloc.features.extract import DEFAULT_FEATURE_CONFIG, FeatureConfig
from planarloc.features.retrieval import DEFAULT_NUM_WORDS
from planarloc.geometry.camera import Camera
from planarloc.io.datasets import FORMATS
from planarloc.localize.localizer import LocalizerConfig
from planarloc.robust.options import Method, RansacOptions, Structure

_RANSAC = RansacOptions()
_LOC = LocalizerConfig()


FORMAT_HELP = ("dataset layout: kitti (image_l/, poses.txt, calib.txt), tum (rgb.txt, groundtruth.txt, camera.txt), "
               "openloris, kapture, colmap (text model), list (name qw qx qy qz tx ty tz), rosbag (ROS 1 .bag or "
               "ROS 2 bag folder; options image_topic, camera_info_topic, pose_topic or tf_parent+tf_child, "
               "base_to_camera, max_dt, every)")


def add_dataset_args(p: argparse.ArgumentParser, many: bool = False) -> None:
    if many:
        p.add_argument("dataset", nargs="+", help="dataset folder(s) (see --format)")
    else:
        p.add_argument("dataset", help="dataset folder (see --format)")
    p.add_argument("--format", "-f", required=True, choices=sorted(FORMATS), help=FORMAT_HELP)


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
                   help="auto = planar 2p1p where the planar model holds, 6DoF 5-point where it does not "
                        "(tilted or off-plane queries); 2p1p / 2p2p = the paper's planar methods; 5p5p-nister, "
                        "5p5p-stewenius, 8p8p = its 6DoF baselines (default: %(default)s)")
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


def add_gravity_file_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--gravity-file", type=Path, metavar="FILE",
                   help="per-query gravity (e.g. from an IMU), lines 'name gx gy gz': direction of gravity "
                        "(down) in the query camera frame (x right, y down, z forward); queries not listed "
                        "are assumed mounted like the map cameras")


def parse_gravity(text: str) -> np.ndarray:
    """'gx gy gz' (spaces or commas) -> (3,) unit gravity direction; ValueError naming --gravity."""
    tok = text.replace(",", " ").split()
    try:
        g = np.array([float(v) for v in tok])
    except ValueError:
        g = np.zeros(0)
    if g.shape != (3,) or not np.all(np.isfinite(g)) or not np.linalg.norm(g) > 1e-9:
        raise ValueError(f"--gravity: expected three numbers 'gx gy gz' (gravity pointing down in the query "
                         f"camera frame, not zero), e.g. '0 1 0' for an upright camera, got {text!r}")
    return g / np.linalg.norm(g)


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
