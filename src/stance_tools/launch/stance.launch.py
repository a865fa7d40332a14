"""The Stance node graph for a full ROS 2 install: `ros2 launch stance_tools stance.launch.py`.

The nodes of `stance graph`'s default graph (stance_tools/data/graph.yaml), read from it:
each with its parameter file (default: the package's installed config/<executable>.yaml)
and the graph's parameter overrides, respawned up to the graph's max_restarts after its
backoff. Optional nodes are left out when their package is not installed.
"""

import os

from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
from launch import LaunchDescription
from launch_ros.actions import Node
from stance_tools.graph import DEFAULT_GRAPH, load_graph


def generate_launch_description():
    nodes = []
    for spec in load_graph(DEFAULT_GRAPH):
        package = spec.package or spec.executable
        try:
            share = get_package_share_directory(package)
        except PackageNotFoundError:
            if spec.optional:
                continue
            raise
        params_file = spec.params_file or os.path.join(share, "config",
                                                       f"{spec.executable}.yaml")
        parameters = [str(params_file)] + ([dict(spec.parameters)] if spec.parameters else [])
        nodes.append(Node(package=package, executable=spec.executable, name=spec.name,
                          output="screen", parameters=parameters, respawn=True,
                          respawn_delay=spec.backoff, respawn_max_retries=spec.max_restarts))
    return LaunchDescription(nodes)
