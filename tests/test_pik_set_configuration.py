"""pik_node's /pik/set_configuration over DDS: a good request moves the robot there at once
and every task holds its value there (nothing drifts afterwards); NaN, unknown joints,
joints outside their limits and non-unit quaternions are rejected with their reason and
leave the state unchanged."""

import math

import numpy as np
import pytest
from conftest import NODE_START_TIMEOUT, wait_until
from helpers.probe import PikProbe, configuration_request, task_status
from stance import Robot
from stance_msgs.srv import SetConfiguration
from stance_tools.processes import ProcessGroup

ARM = "arm_left_2_joint"
SHIFT = 0.2  # m: base moved along x


@pytest.fixture(scope="module")
def pik(tmp_path_factory):
    group = ProcessGroup(tmp_path_factory.mktemp("pik"))
    node = group.start("pik_node", name="pik_node")
    probe = PikProbe("set_configuration_probe")
    client = probe.node.create_client(SetConfiguration, "/pik/set_configuration")
    try:
        wait_until(lambda: probe.status_count() > 10 or node.poll() is not None,
                   NODE_START_TIMEOUT, what="pik_node status")
        assert node.poll() is None, node.log_path.read_text()
        yield node, probe, client
    finally:
        probe.close()
        group.stop_all()
        print(node.log_path.read_text())


@pytest.fixture(scope="module")
def robot():
    return Robot.load("talos")


def test_good_request_moves_the_robot_and_every_task_holds_there(pik, robot):
    node, probe, client = pik
    _, before = probe.fresh_output()
    q = robot.initial_configuration()
    q[0] += SHIFT
    lower, upper = (bound[robot.limited_joint_names.index(ARM)]
                    for bound in (robot.lower, robot.upper))
    arm_value = 0.5 * (lower + upper) + 0.1
    q[robot.model.joints[robot.joint_id(ARM)].idx_q] = arm_value
    response = probe.call(client, configuration_request(robot, q))
    assert response.success, response.message

    joint_state, status = probe.fresh_output()
    positions = dict(zip(joint_state.name, joint_state.position))
    assert positions[ARM] == pytest.approx(arm_value, abs=1e-6)
    expected = robot.actuated_positions(q)
    assert max(abs(positions[name] - value) for name, value in expected.items()) < 1e-6
    for name in ("left_foot", "right_foot", "right_hand"):
        old, new = task_status(before, name), task_status(status, name)
        assert new.target.position.x == pytest.approx(old.target.position.x + SHIFT, abs=1e-3)
        assert new.error_norm < 1e-6, name
    assert all(level.residual_norm < 1e-6 for level in status.levels)


@pytest.mark.parametrize("case, words", [
    ("nan joint", ["joints: position of arm_left_2_joint is NaN"]),  # not "posture target"
    ("unknown joint", ["unknown", "no_such_joint"]),
    ("outside limits", [ARM, "outside its limits"]),
    ("non-unit quaternion", ["base_pose", "quaternion"]),
    ("nan base", ["base_pose", "NaN"]),
    ("huge base", ["base_pose", "position x = 1e+308 m is beyond the bound |x| <= 1e+06 m"]),
])
def test_bad_request_is_rejected_with_its_reason_and_changes_nothing(pik, robot, case, words):
    node, probe, client = pik
    joint_state, status = probe.fresh_output()
    q = robot.initial_configuration()
    request = configuration_request(robot, q)
    index = list(request.joints.name).index(ARM)
    if case == "nan joint":
        request.joints.position[index] = float("nan")
    elif case == "unknown joint":
        request.joints.name[index] = "no_such_joint"
    elif case == "outside limits":
        request.joints.position[index] = robot.upper[robot.limited_joint_names.index(ARM)] + 0.1
    elif case == "non-unit quaternion":
        request.base_pose.orientation.w = 0.5
    elif case == "huge base":
        request.base_pose.position.x = 1e308  # finite: it was taken, then all output NaN
    else:
        request.base_pose.position.z = float("nan")
    response = probe.call(client, request)
    assert not response.success
    for word in words:
        assert word in response.message, (word, response.message)
    after_state, after_status = probe.fresh_output()
    assert np.allclose(after_state.position, joint_state.position, atol=1e-9)
    assert after_status.rejected_inputs == status.rejected_inputs + 1
    assert response.message in after_status.last_rejection
    assert node.poll() is None
    assert math.isfinite(max(after_state.position))
