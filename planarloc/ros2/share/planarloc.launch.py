"""ROS 2 launch file of ``planarloc ros2``: the node with a parameter file, and optionally rviz2.

    ros2 launch $(planarloc ros2 --share-dir)/planarloc.launch.py map:=$PWD/office.db
    ros2 launch .../planarloc.launch.py map:=$PWD/office.db params_file:=$PWD/my_params.yaml rviz:=true

Launch arguments: ``map`` (the map file, required), ``params_file`` (default: ``params.yaml`` next to
this file, every parameter with its default; copy and edit it), ``planarloc`` (the ``planarloc``
executable, e.g. a virtual environment's ``bin/planarloc``; default: the one on ``PATH``) and ``rviz``
(``true``: also start ``rviz2`` with ``planarloc.rviz``: the pose with its covariance, TF, the map
frame). ``planarloc ros2`` is a pip-installed program, not a ROS package, so it is started as a
process (``ExecuteProcess``), with ``--map`` taking precedence over the parameter file's ``map``.
"""

import os

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration

HERE = os.path.dirname(os.path.abspath(__file__))


def generate_launch_description():
    return LaunchDescription(
        [
            DeclareLaunchArgument("map", description="the map file (planarloc map build ... --out MAP.db)"),
            DeclareLaunchArgument(
                "params_file",
                default_value=os.path.join(HERE, "params.yaml"),
                description="the node's ROS parameters (every one with its default in params.yaml)",
            ),
            DeclareLaunchArgument(
                "planarloc",
                default_value="planarloc",
                description="the planarloc executable (e.g. /path/to/venv/bin/planarloc)",
            ),
            DeclareLaunchArgument(
                "rviz", default_value="false", description="also start rviz2 with planarloc.rviz"
            ),
            ExecuteProcess(
                name="planarloc",
                cmd=[
                    LaunchConfiguration("planarloc"),
                    "ros2",
                    "--map",
                    LaunchConfiguration("map"),
                    "--ros-args",
                    "--params-file",
                    LaunchConfiguration("params_file"),
                ],
                output="screen",
            ),
            ExecuteProcess(
                name="rviz2",
                cmd=["rviz2", "-d", os.path.join(HERE, "planarloc.rviz")],
                condition=IfCondition(LaunchConfiguration("rviz")),
                output="screen",
            ),
        ]
    )
