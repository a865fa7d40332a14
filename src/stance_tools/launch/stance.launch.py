"""The Stance node graph for a full ROS 2 install: `ros2 launch stance_tools stance.launch.py`.

The nodes, parameter files and restart policy of `stance graph` (stance_tools/data/graph.yaml):
each node with its package's installed config/<executable>.yaml, respawned when it exits.
Optional nodes are left out when their package is not installed.
"""

import os

from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
from launch import LaunchDescription
from launch_ros.actions import Node

# (package, executable, optional), as in the default graph
NODES = [
    ("pik_node", "pik_node", False),
    ("contact_planner_node", "contact_planner_node", False),
    ("trajectory_node", "trajectory_node", True),
    ("stabilizer_gate_node", "stabilizer_gate_node", True),
]
MAX_RESTARTS = 3
RESPAWN_DELAY = 1.0  # s


def generate_launch_description():
    nodes = []
    for package, executable, optional in NODES:
        try:
            share = get_package_share_directory(package)
        except PackageNotFoundError:
            if optional:
                continue
            raise
        nodes.append(Node(package=package, executable=executable, output="screen",
                          parameters=[os.path.join(share, "config", f"{executable}.yaml")],
                          respawn=True, respawn_delay=RESPAWN_DELAY,
                          respawn_max_retries=MAX_RESTARTS))
    return LaunchDescription(nodes)
