"""The installed workspace has the layout a full ROS 2 install expects: `ros2 run <pkg>
<exe>` looks the package up in the ament index and runs lib/<pkg>/<exe> of its prefix."""

import os

import pytest
from ament_index_python.packages import get_package_prefix, get_package_share_directory


@pytest.mark.parametrize("package, executable", [("pik_node", "pik_node"),
                                                 ("contact_planner_node", "contact_planner_node"),
                                                 ("stabilizer_gate_node", "stabilizer_gate_node"),
                                                 ("trajectory_node", "trajectory_node"),
                                                 ("stance_tools", "stance")])
def test_executables_are_where_ros2_run_looks(package, executable):
    path = os.path.join(get_package_prefix(package), "lib", package, executable)
    assert os.access(path, os.X_OK), path


def test_interface_definitions_are_installed_for_recorders():
    share = get_package_share_directory("stance_msgs")
    for name in ("SolverStatus", "TaskSpec", "ContactStance", "StancePlan", "StabilizerState"):
        assert os.path.isfile(os.path.join(share, "msg", f"{name}.msg")), name
    assert os.path.isfile(os.path.join(share, "action", "PlanContacts.action"))


@pytest.mark.parametrize("package", ["pik_node", "contact_planner_node",
                                     "stabilizer_gate_node", "trajectory_node"])
def test_parameter_file_is_installed(package):
    share = get_package_share_directory(package)
    assert os.path.isfile(os.path.join(share, "config", f"{package}.yaml"))


def test_library_does_not_import_rclpy():
    import subprocess
    import sys
    code = ("import sys, stance, stance.pik, stance.hierarchy, stance.limits, stance.tasks, "
            "stance.planning.planner, stance.planning.posture, stance.planning.verify; "
            "sys.exit('rclpy' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_readme_limit_file_example_is_valid():
    """The limit-file example users copy from the README parses on the mannequin."""
    import pathlib
    import re

    import yaml
    from stance import Robot
    from stance.swing import parse_limits
    readme = (pathlib.Path(__file__).parents[1] / "README.md").read_text()
    block = re.search(r"```yaml\n(activation: .*?)```", readme, re.S).group(1)
    models = parse_limits(yaml.safe_load(block), Robot.load("mannequin"))
    assert [model.dof_names[0] for model in models] == ["left_hip_swing_x",
                                                        "left_shoulder_swing_x"]
