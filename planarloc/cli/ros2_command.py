"""`planarloc ros2`: the ROS 2 node (:mod:`planarloc.ros2.node`)."""

from __future__ import annotations

import argparse

from planarloc.cli.commands import add_command


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub, "ros2", "run the ROS 2 localization node (poses, map -> odom, diagnostics)",
        """Subscribes to camera images with their CameraInfo (and optionally nav_msgs/Odometry, /tf, /tf_static,
        /initialpose) and publishes geometry_msgs/PoseWithCovarianceStamped on /planarloc/pose in frame map (the
        map's world), the map -> odom transform on /tf when odometry is given (as nav2's AMCL), and
        diagnostic_msgs/DiagnosticArray on /diagnostics. Only frames that are localized (and, with
        publish_predicted, predicted) within max_position_std_m are published. Settings are ROS parameters (the
        README's "ROS 2" section lists them). Ctrl-C stops it (exit 0). Needs: pip install 'planarloc[ros2]'.""",
        ["planarloc ros2 --map kitti.db",
         "planarloc ros2 --map office.db --ros-args -p image_topic:=/camera/image_raw/compressed "
         "-p odom_topic:=/odom -p base_to_camera:='0.3 0 0.2 -0.5 0.5 -0.5 0.5'"],
        run)
    p.add_argument("--map", required=True, help="the map file (the ROS parameter 'map')")
    p.add_argument("--ros-args", dest="ros_args", nargs=argparse.REMAINDER, default=[],
                   help="ROS arguments, e.g. -p name:=value (every argument after it)")


def run(args: argparse.Namespace) -> int:
    from planarloc.extras import require

    require("rclpy", "ros2")
    from planarloc.ros2.node import run as run_node

    return run_node(args.map, args.ros_args)
