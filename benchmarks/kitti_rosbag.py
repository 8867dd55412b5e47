"""KITTI through a ROS 2 bag: the same evaluation from the KITTI import and from a bag of it.

The KITTI excerpt is written as a ROS 2 bag (sqlite3; sensor_msgs/Image mono8,
sensor_msgs/CameraInfo, geometry_msgs/PoseStamped on ``/pose``, stamps 0.1 s x frame index),
then ``planarloc evaluate --map-every N`` runs on both with the same options. Prints both
success rates and the largest per-query difference of the translation errors; the bag path
must reproduce the KITTI import (PASS = identical success rates and statuses, errors within 1 mm).

    python benchmarks/kitti_rosbag.py [--data ../shared/data/kitti_seq2] [--map-every 2]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from planarloc.cli.main import main
from planarloc.io.datasets import read_dataset
from planarloc.io.rosbag import write_rosbag


def evaluate(data: Path, fmt: str, options: list[str], out: Path, map_every: int, structure: str) -> dict:
    argv = [
        str(data),
        "-f",
        fmt,
        *options,
        "--map-every",
        str(map_every),
        "--structure",
        structure,
        "--map",
        str(out.with_suffix(".db")),
        "--json",
        str(out),
    ]
    if main(["evaluate", *argv]) != 0:
        raise SystemExit(f"evaluate {fmt} failed")
    return json.loads(out.read_text())


def run() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--data", type=Path, default=Path(__file__).resolve().parents[1] / "../shared/data/kitti_seq2"
    )
    ap.add_argument("--map-every", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        bag = write_rosbag(
            tmp / "kitti_bag",
            read_dataset(args.data, "kitti"),
            storage="sqlite3",
            pose_message="PoseStamped",
            pose_topic="/pose",
        )
        ok = True
        for structure in ("tracks", "none"):
            a = evaluate(args.data, "kitti", [], tmp / f"kitti-{structure}.json", args.map_every, structure)
            b = evaluate(
                bag,
                "rosbag",
                ["--dataset-option", "pose_topic=/pose", "--dataset-option", f"image_dir={tmp / 'images'}"],
                tmp / f"bag-{structure}.json",
                args.map_every,
                structure,
            )
            diff = max(
                (
                    abs(x["translation_error_m"] - y["translation_error_m"])
                    for x, y in zip(a["per_query"], b["per_query"])
                    if x["success"] and y["success"]
                ),
                default=0.0,
            )
            same = (
                a["success"] == b["success"]
                and [x["status"] for x in a["per_query"]] == [y["status"] for y in b["per_query"]]
                and diff < 1e-3
            )
            ok &= same
            fmt = " / ".join
            print(
                f"structure {structure}: kitti {fmt(f'{v:.1f}' for v in a['success'].values())} %, "
                f"bag {fmt(f'{v:.1f}' for v in b['success'].values())} %, max per-query difference "
                f"{diff:.2e} m -> {'PASS' if same else 'FAIL'}"
            )
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(run())
