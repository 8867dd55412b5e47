"""`planarloc ros2`: the ROS 2 node (:mod:`planarloc.ros2.node`)."""

from __future__ import annotations

import argparse

from planarloc.cli.commands import add_command
from planarloc.geometry.validation import InputError
from planarloc.ros2.settings import SHARE_DIR, parameters_listing


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "ros2",
        "run the ROS 2 localization node (poses, map -> odom, diagnostics)",
        """Subscribes to camera images with their CameraInfo (without one: the map's camera, if the map has
        only one) and optionally nav_msgs/Odometry, /tf, /tf_static and /initialpose; publishes
        geometry_msgs/PoseWithCovarianceStamped on /planarloc/pose in frame map, the map -> odom transform on
        /tf when odometry is given (as nav2's AMCL, stamped transform_tolerance_s ahead), and
        diagnostic_msgs/DiagnosticArray on /diagnostics (one per frame; a bad frame is a failed diagnostic
        with its reason). The map frame is z-up (REP-103/105): the map's world rotated by the map's gravity
        (map_frame_convention:=world keeps the map's own world, e.g. y down for KITTI). Only frames that are
        localized (and, with publish_predicted, predicted) within max_position_std_m are published. Ctrl-C
        stops it (exit 0). Needs: pip install 'planarloc[ros2]'.

        A ROS 2 launch file, a parameter file with every default and an rviz configuration are in the folder
        `planarloc ros2 --share-dir` prints (planarloc.launch.py, params.yaml, planarloc.rviz).""",
        [
            "planarloc ros2 --map kitti.db",
            (
                "planarloc ros2 --map office.db --ros-args -p image_topic:=/camera/image_raw/compressed "
                "-p odom_topic:=/odom -p base_to_camera:='0.3 0 0.2 -0.5 0.5 -0.5 0.5' -p "
                "transform_tolerance_s:=0.5"
            ),
            "planarloc ros2 --map office.db --ros-args --params-file my_params.yaml",
            "ros2 launch $(planarloc ros2 --share-dir)/planarloc.launch.py map:=$PWD/office.db rviz:=true",
        ],
        run,
        listing=parameters_listing(),
    )
    p.add_argument("--map", help="the map file (the ROS parameter 'map'; required to run the node)")
    p.add_argument(
        "--share-dir",
        action="store_true",
        help="print the folder of the launch file, params.yaml and the rviz configuration, and exit",
    )
    p.add_argument(
        "--ros-args",
        dest="ros_args",
        nargs=argparse.REMAINDER,
        default=[],
        help="ROS arguments, e.g. -p name:=value or --params-file FILE (every argument after it)",
    )


def run(args: argparse.Namespace) -> int:
    if args.share_dir:
        print(SHARE_DIR)
        return 0
    if not args.map:
        raise InputError("--map: give the map file (planarloc ros2 --map MAP.db)")
    from planarloc.extras import require

    require("rclpy", "ros2")
    from planarloc.ros2.node import run as run_node

    return run_node(args.map, args.ros_args)
