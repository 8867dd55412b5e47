"""`planarloc map build|info|check`: create, summarise and verify maps of posed images."""

from __future__ import annotations

import argparse
from pathlib import Path

from planarloc.cli.commands import add_command
from planarloc.cli.console import info, note, progress_bar
from planarloc.cli.exit_codes import BUILD_RESUMES
from planarloc.cli.map_building import build_calibrated_map, left_out_exit
from planarloc.cli.options import (
    add_dataset_args,
    add_feature_args,
    add_ray_arg,
    check_vocabulary_size,
    feature_config,
    parse_dataset_options,
)
from planarloc.distributed.ray_backend import ray_session
from planarloc.io.datasets import read_dataset
from planarloc.io.output import check_output_file, dataset_files, input_files
from planarloc.map.builder import check_map_settings
from planarloc.map.codec import DEFAULT_STORAGE, STORAGE_LAYOUTS
from planarloc.map.gravity import map_gravity
from planarloc.map.integrity import check_map
from planarloc.map.pose_accuracy import load_accuracy
from planarloc.map.std_calibration import MIN_SAMPLES, load_std_calibration, std_calibration_due
from planarloc.map.store import MapDatabase


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "map",
        "build or inspect a map (a SQLite file of posed images and their features)",
        """A map is just posed images with their features: no 3D model is built.""",
        [
            "planarloc map build data/kitti_seq2 --format kitti --every 2 --out kitti.db",
            "planarloc map info kitti.db",
            "planarloc map check kitti.db",
        ],
    )
    msub = p.add_subparsers(dest="map_command", required=True)
    _add_build_parser(msub)
    _add_inspect_parsers(msub)


def _add_build_parser(msub: argparse._SubParsersAction) -> None:
    """`map build` and its options."""
    b = add_command(
        msub,
        "build",
        "build (or resume / extend) a map from a dataset",
        """Extract RootSIFT features of every posed image and store them with the poses in MAP.db, then index
        the map for retrieval (VLAD); then print `map info` of it.

        Re-running the same command resumes an interrupted build; running it on another dataset with the same
        --out appends those images. An image that cannot be used (missing, truncated or damaged, undecodable,
        of another size than its camera) is left out and named, the build goes on, and the list of them ends
        the output (exit code 3, "partly done"). Images are identified by content: changed poses are updated,
        changed image files re-extracted, and another dataset's image with a name already in the map is stored
        as DATASET/NAME (each reported in one line). A second build of the same file waits for the first (it
        names its PID).

        Appending to a map that holds images first matches up to 10 of the new images (those nearest to the
        map's cameras) against the map: if none shares matches with it, or the matches contradict the matched
        images' poses (another sequence whose poses also start at its first camera, e.g. a second KITTI
        sequence), the build stops with one line saying what was found and leaves the map as it was;
        --allow-unrelated-frames appends them anyway (with a warning).

        The world's gravity is the format's (KITTI, OpenLORIS, generated worlds), the dataset option up=...,
        or estimated from the camera centres' plane; `map info` shows it.

        New maps are compact (50-100 KB per KITTI image, the recall of full maps); --storage full stores
        float32 keypoints and 8-bit descriptors (about 5 times the bytes). Maps of either layout, and
        maps from before layouts existed (full), open alike.""",
        [
            "planarloc map build data/kitti_seq2 --format kitti --every 2 --out kitti.db",
            "planarloc map build data/fountain_p11 --format kapture --dataset-option up=-z --out f.db",
        ],
        run_build,
        interrupted=BUILD_RESUMES,
    )
    _add_build_options(b)


def _add_build_options(b: argparse.ArgumentParser) -> None:
    """The options of `map build`: the dataset, the map file, the features and the storage."""
    add_dataset_args(b)
    b.add_argument(
        "--every", type=int, default=1, help="only frames with index %% N == 0 go into the map (default: 1)"
    )
    b.add_argument("--out", "-o", required=True, type=Path, help="map file to create or extend")
    b.add_argument(
        "--dataset-option",
        action="append",
        metavar="KEY=VALUE",
        help="importer option, e.g. tum_camera=fr1 or max_dt=0.05 (repeatable); up=AXIS gives the "
        "world's up direction (e.g. up=z, up=-y, up=0,0,1; up=estimate: from the camera centres' plane "
        "even if the format declares one)",
    )
    add_feature_args(b)
    b.add_argument(
        "--storage",
        choices=STORAGE_LAYOUTS,
        default=DEFAULT_STORAGE,
        help=f"layout of a new map: compact (about a fifth of the bytes of full: transform-coded "
        f"descriptors, fixed-point keypoints, 4-bit global descriptors; the recall of full on KITTI) or "
        f"full (float32 keypoints, 8-bit descriptors); default: {DEFAULT_STORAGE}; an existing map "
        f"keeps its own",
    )
    b.add_argument(
        "--allow-unrelated-frames",
        action="store_true",
        help="append images to a non-empty map even when they share no matches with it or their "
        "matches contradict the poses (their world frame looks unrelated to the map's); default: "
        "refuse, leaving the map as it was",
    )
    add_ray_arg(b)


def _add_inspect_parsers(msub: argparse._SubParsersAction) -> None:
    """`map info` and `map check`: a map file each."""
    for name, summary, description, func in (
        (
            "info",
            "summarise a map (images, features, gravity, camera mount tilt) and check its integrity",
            "Prints (on stdout) the number of images, the feature settings, whether the build is complete, "
            "and the map's gravity: where it comes from (declared by the format, the up= option, or "
            "estimated from the camera centres' plane) and the map cameras' mount pitch/roll relative to it; "
            "after the checks of `planarloc map check` (exit code 1 if the map is damaged).",
            run_info,
        ),
        (
            "check",
            "verify every row of a map (SQLite integrity, blobs, checksums)",
            "Runs SQLite's integrity_check and then decodes every stored row: cameras, poses, keypoint and "
            "descriptor blobs (lengths, finite values, checksums), global descriptors and the retrieval "
            "vocabulary. Prints one line per problem naming the row (on stderr); exit code 0 if the map is "
            "sound (one line on stdout), 1 if not (rebuild it with `planarloc map build`).",
            run_check,
        ),
    ):
        m = add_command(msub, name, summary, description, [f"planarloc map {name} kitti.db"], func)
        m.add_argument("map", type=Path, help="map file")


def run_build(args: argparse.Namespace) -> int:
    # Every option is checked before the first image is read (and before the map file exists).
    if args.every < 1:
        raise ValueError(f"--every must be >= 1, got {args.every}")
    features = feature_config(args)
    num_words = check_vocabulary_size(args.vocabulary_size)
    dataset_options = parse_dataset_options(args.dataset_option, fmt=args.format)
    check_output_file(args.out, "--out", input_files([args.dataset, *dataset_files(args.dataset)]))
    images = read_dataset(args.dataset, args.format, **dataset_options)
    images = [im for im in images if im.index % args.every == 0]
    if not images:
        raise ValueError(f"--every {args.every}: no frame of {args.dataset} has an index divisible by it")
    check_output_file(args.out, "--out", input_files(im.path for im in images))
    check_map_settings(args.out, features, num_words)  # before the first image is read
    note(f"building map {args.out} from {len(images)} images of {args.dataset}")
    with ray_session(args.ray) as ray_backend, progress_bar() as update:
        left_out = build_calibrated_map(
            images,
            args.out,
            features,
            num_words,
            update,
            mapper=ray_backend.map if ray_backend else None,
            storage=args.storage,
            allow_unrelated_frames=args.allow_unrelated_frames,
        )
    return left_out_exit(run_info(argparse.Namespace(map=args.out)), left_out, len(images))


def run_info(args: argparse.Namespace) -> int:
    report = check_map(args.map)
    if not report.ok:
        raise ValueError(
            f"{args.map}: damaged map: {report.problems[0]}"
            + (
                f" (and {len(report.problems) - 1} more problem(s): `planarloc map check {args.map}` "
                "lists them)"
                if len(report.problems) > 1
                else ""
            )
            + "; rebuild the map"
        )
    with MapDatabase.open(args.map) as db:
        n = db.num_images()
        cfg = db.config
        info(
            f"{args.map}: {n} images, features {cfg.get('feature_name', '?')}, "
            f"{'complete' if db.is_complete else 'incomplete build'}, integrity ok"
        )
        if n:
            for line in map_gravity(db).summary_lines():
                info(line)
            accuracy = load_accuracy(db)
            info(
                accuracy.summary()
                if accuracy is not None
                else "map pose accuracy: not measured (a map built before planarloc measured it, or too few "
                "overlapping images); queries assume the configured map prior"
            )
            info(f"std calibration: {_calibration_line(db)}")
    return 0


def _calibration_line(db: MapDatabase) -> str:
    """What `map info` says of the map's std calibration."""
    calibration = load_std_calibration(db)
    if calibration is not None:
        return calibration.summary()
    if std_calibration_due(db):
        return (
            "not measured yet (a map built before planarloc measured it, or a build that did not finish "
            "it; `planarloc map build` on the same images measures it); the modelled std is reported as is"
        )
    return (
        f"none (fewer than {MIN_SAMPLES} held-out map images localized with a measured map prior and "
        "enough 2D-3D inliers); the modelled std is reported as is"
    )


def run_check(args: argparse.Namespace) -> int:
    report = check_map(args.map)
    for line in report.problems:
        note(f"{args.map}: {line}")
    if not report.ok:
        raise ValueError(
            f"{args.map}: damaged map, {len(report.problems)} problem(s) listed above; "
            "rebuild the map (planarloc map build ... --out NEW.db)"
        )
    info(
        f"{args.map}: ok ({report.num_images} images, "
        f"{'complete' if report.complete else 'incomplete build'})"
    )
    return 0
