"""`ros2 launch orchard_mapping orchard_graph.launch.py [bags:=front,back] [rate:=1.0] [params:=FILE] [out:=DIR]`
on a full ROS 2 Jazzy install (colcon build; see the README). The same graph as `orchard-map launch`: the
trunk detector, the local ground fitter, the odometry node (asking the detector node and fitting its trunk
cylinders against the ground fitter's grounds), the side merger, the trait reporter and, with
`bags`, the bag player. Not runnable from the project's venv (no `launch` on PyPI): there, use
`orchard-map launch`."""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node


def _nodes(context):
    share = Path(get_package_share_directory("orchard_mapping"))
    params = LaunchConfiguration("params").perform(context) or str(share / "config" / "ros_params.yaml")
    bags = [b for b in LaunchConfiguration("bags").perform(context).split(",") if b]
    rate = LaunchConfiguration("rate").perform(context)
    odometry = [params, {"detector": "node", "ground_fitter": "node", "exit_after_sides": len(bags)}]
    out = LaunchConfiguration("out").perform(context)
    merged = [params, {"out_dir": out}]
    nodes = [
        # restarted, they receive the latched side maps and trees again (docs/ros.md, "When a node dies")
        Node(package="orchard_mapping", executable="side_merger", name="side_merger", parameters=merged,
             respawn=True, output="screen"),
        Node(package="orchard_mapping", executable="trait_reporter", name="trait_reporter", parameters=merged,
             respawn=True, output="screen"),
        LifecycleNode(package="orchard_mapping", executable="trunk_detector", name="trunk_detector", namespace="",
                      parameters=[params], respawn=True, output="screen"),
        Node(package="orchard_mapping", executable="local_ground_fitter", name="local_ground_fitter",
             parameters=[params], respawn=True, output="screen"),
        Node(package="orchard_mapping", executable="rgbd_odometry", name="rgbd_odometry", parameters=odometry,
             output="screen"),
    ]
    if bags:
        sides = [a for s in ("front", "back")[: len(bags)] for a in ("--side", s)] if len(bags) <= 2 else []
        nodes.append(Node(package="orchard_mapping", executable="bag_player", name="bag_player",
                          # side changes once the odometry node acknowledged the images before them
                          arguments=[*bags, "--rate", rate, "--side-acks", "--wait-reader", "rgbd_odometry", *sides],
                          output="screen"))
    return nodes


def generate_launch_description():
    return LaunchDescription([
        DeclareLaunchArgument("bags", default_value="", description="comma-separated bags to replay (front,back)"),
        DeclareLaunchArgument("rate", default_value="1.0", description="replay speed"),
        DeclareLaunchArgument("params", default_value="", description="parameters file (default: ros_params.yaml)"),
        DeclareLaunchArgument("out", default_value="", description="folder for the merge's and the trees' files"),
        OpaqueFunction(function=_nodes),
    ])
