"""contact_planner_node over DDS in its own process: malformed goals end with a reason and
a message naming the field, a running plan is cancelled within 1 s and the node serves the
next goal, a second goal while busy is rejected, a plan succeeds on flat_steps and is
latched on /contact_planner/plan for late subscribers. Plus the message conversions alone."""

import math
import os
import signal
import threading
import time

import numpy as np
import pinocchio as pin
import pytest
import rclpy
from action_msgs.msg import GoalStatus
from conftest import other_domain_id, wait_until
from contact_planner_node.conversions import (GoalRejected, contact_from_msg, contact_msg,
                                              key_postures_from_msgs)
from contact_planner_node.worker import PlannerProcess, descendants
from geometry_msgs.msg import Pose
from helpers.probe import BackgroundNode
from pik_node.conversions import se3_from_pose_msg
from rclpy.action import ActionClient
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from stance import Robot
from stance.planning.contacts import Contact
from stance.planning.planner import PlanRequest, plan_contacts
from stance.planning.scene import load_scene
from stance_msgs.action import PlanContacts
from stance_msgs.msg import StancePlan

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


def _answered(answer, timeout, what):
    """answer, the test failed when it is None (none came within timeout s)."""
    if answer is None:
        pytest.fail(f"timed out after {timeout} s waiting for {what}")
    return answer


class PlannerClient(BackgroundNode):
    """Sends PlanContacts goals, collects feedback, cancels."""

    def __init__(self, name="planner_client", domain_id=None):
        super().__init__(name, domain_id)
        self.client = ActionClient(self.node, PlanContacts, "/contact_planner/plan_contacts")
        self.feedback = []  # (monotonic s, Feedback)
        self.start_spinning()

    def _call(self, function, *args, timeout=30.0, what="response", **kwargs):
        return _answered(self.call(function, *args, timeout=timeout, **kwargs), timeout, what)

    def send(self, goal, timeout=30.0):
        """The goal handle (accepted or not), sent once the server answers requests."""
        wait_until(lambda: self.action_server_answers(self.client), timeout,
                   what="the action server to answer")
        return _answered(self.send_goal(self.client, goal, timeout=timeout,
                                        feedback_callback=self._on_feedback),
                         timeout, "goal response")

    def _on_feedback(self, msg):
        self.feedback.append((time.monotonic(), msg.feedback))

    def result(self, handle, timeout):
        """(status, result) of an accepted goal."""
        response = self._call(handle.get_result_async, timeout=timeout, what="action result")
        return response.status, response.result

    def cancel(self, handle):
        return self._call(handle.cancel_goal_async, what="cancel response")

    def plan(self, goal, timeout=60.0):
        handle = self.send(goal)
        assert handle.accepted
        return self.result(handle, timeout)


@pytest.fixture(scope="module")
def planner(tmp_path_factory):
    """One contact_planner_node for the module (it must survive every bad goal)."""
    from stance_tools.processes import ProcessGroup
    group = ProcessGroup(tmp_path_factory.mktemp("planner"))
    node = group.start("contact_planner_node", name="contact_planner_node")
    client = PlannerClient()
    try:
        ready = client.client.wait_for_server(timeout_sec=60)
        assert ready and node.poll() is None, node.log_path.read_text()
        yield node, client
    finally:
        client.close()
        group.stop_all()
        print(node.log_path.read_text())


@pytest.fixture(scope="module")
def flat_steps():
    return load_scene("flat_steps")


def failed(planner, goal, reason, *words):
    """Send goal; assert it ends aborted with reason and a message holding words."""
    node, client = planner
    status, result = client.plan(goal)
    assert status == GoalStatus.STATUS_ABORTED
    assert not result.success and result.reason == reason, result
    for word in words:
        assert word in result.message, (word, result.message)
    assert not result.plan.stances
    assert node.poll() is None
    return result


def start_contacts(scene):
    """The scene's start stance as library Contacts."""
    return [Contact(c.spot, c.surface, c.x, c.y, c.theta) for c in scene.start]


def start_msgs(scene):
    return [contact_msg(c, scene.surfaces[c.surface]) for c in start_contacts(scene)]


FLAT_STEPS_FLOOR = "polygon: [[-1.0, -1.0], [2.0, -1.0], [2.0, 1.0], [-1.0, 1.0]]"


@pytest.mark.parametrize("edit, words", [
    (("surfaces:", "surfaces: [unclosed"), ["scene_yaml", "YAML"]),
    ((FLAT_STEPS_FLOOR, "polygon: [[-1.0, -1.0], [2.0, -1.0]]"),
     ["scene_yaml", "surfaces[0].polygon"]),
], ids=["invalid yaml", "two-vertex polygon"])
def test_malformed_scene_yaml_names_the_field(planner, flat_steps, edit, words):
    text = open(flat_steps.source).read()
    assert edit[0] in text
    goal = PlanContacts.Goal(scene_yaml=text.replace(edit[0], edit[1], 1))
    failed(planner, goal, "malformed_scene", *words)


def test_unknown_scene_name_is_a_malformed_scene(planner):
    failed(planner, PlanContacts.Goal(scene="no_such_scene"), "malformed_scene", "scene",
           "no_such_scene")


def test_a_scene_file_that_is_not_text_is_a_malformed_scene(planner, tmp_path):
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xf0\x00\xff robot: talos")
    failed(planner, PlanContacts.Goal(scene=str(binary)), "malformed_scene", "scene",
           "not a YAML text file")


def test_unknown_goal_frame_is_a_bad_goal(planner):
    goal = PlanContacts.Goal(scene="flat_steps", goal_frame="no_such_frame", goal_axis="x",
                             goal_threshold=1.0, goal_sense=1)
    failed(planner, goal, "bad_goal", "goal.frame", "no_such_frame")


def test_nan_in_a_start_contact_is_rejected_naming_the_field(planner, flat_steps):
    start = start_msgs(flat_steps)
    start[-1].pose.position.x = float("nan")
    goal = PlanContacts.Goal(scene="flat_steps", start=start)
    failed(planner, goal, "malformed_goal", f"start[{len(start) - 1}].pose", "NaN")


@pytest.mark.parametrize("case, words", [
    ("unknown spot", ["start[0].spot", "no_such_spot"]),
    ("unknown surface", ["start[0].surface", "no_such_surface"]),
    ("off the plane", ["start[0].pose", "off the plane"]),
    ("key posture lengths", ["key_base_poses", "key_joints"]),
    ("nan key joint", ["key_joints[1]", "NaN"]),
    ("negative budget", ["time_budget"]),
])
def test_malformed_goal_fields_are_named(planner, flat_steps, case, words):
    goal = PlanContacts.Goal(scene="flat_steps", start=start_msgs(flat_steps))
    two_poses = [_standing_pose(), _standing_pose()]
    if case == "unknown spot":
        goal.start[0].spot = "no_such_spot"
    elif case == "unknown surface":
        goal.start[0].surface = "no_such_surface"
    elif case == "off the plane":
        goal.start[0].pose.position.z += 0.01
    elif case == "key posture lengths":
        goal.key_base_poses, goal.key_joints = two_poses, [JointState()]
    elif case == "nan key joint":
        goal.key_base_poses = two_poses
        goal.key_joints = [JointState(), JointState(name=["arm_left_1_joint"],
                                                    position=[float("nan")])]
    else:
        goal.time_budget = -1.0
    failed(planner, goal, "malformed_goal", *words)


def test_cancel_takes_effect_within_a_second_and_the_node_serves_the_next_goal(planner):
    node, client = planner
    long_goal = PlanContacts.Goal(scene="chair_table", max_nodes=100000, time_budget=600.0)
    handle = client.send(long_goal)
    assert handle.accepted
    time.sleep(3.0)  # well into the search (or still finding the start posture)
    busy = client.send(PlanContacts.Goal(scene="flat_steps"))
    assert not busy.accepted, "a second goal was accepted while a plan runs"
    result = []
    waiter = threading.Thread(target=lambda: result.append(client.result(handle, 30)))
    waiter.start()
    time.sleep(0.5)
    assert not result, "the long plan ended by itself"
    cancelled_at = time.monotonic()
    client.cancel(handle)
    waiter.join()
    latency = time.monotonic() - cancelled_at
    status, result = result[0]
    assert status == GoalStatus.STATUS_CANCELED
    assert not result.success and result.reason == "cancelled"
    assert latency < 1.0, f"cancel took {latency:.2f} s"
    # The node is free again: the next goal is accepted and answered.
    status, result = client.plan(PlanContacts.Goal(scene="flat_steps", goal_frame="nowhere",
                                                   goal_axis="x", goal_sense=1))
    assert result.reason == "bad_goal"


def test_plan_on_flat_steps_succeeds_and_is_latched(planner, flat_steps):
    node, client = planner
    client.feedback.clear()
    started = time.monotonic()
    status, result = client.plan(PlanContacts.Goal(scene="flat_steps"),
                                 timeout=300)
    duration = time.monotonic() - started
    assert status == GoalStatus.STATUS_SUCCEEDED, result.message
    assert result.success and result.reason == "success"
    assert result.stances == len(result.plan.stances) >= 2
    assert result.nodes_expanded >= 1 and result.posture_generations >= 1
    assert 0.0 < result.planning_time <= duration
    # Feedback: counts never decrease, at most ~5 per second.
    counts = [fb.nodes_expanded for _, fb in client.feedback]
    assert counts == sorted(counts)
    assert len(client.feedback) <= 5 * duration + 2
    # The plan is the library's own (the planner is deterministic to rounding), converted: contact
    # poses are the contact frames on their surfaces, witnesses are the stances' q.
    robot = Robot.load("talos")
    expected = plan_contacts(robot, PlanRequest(scene=flat_steps, ordered_sons=True)).plan
    plan = result.plan
    assert plan.scene == "flat_steps" and plan.header.frame_id == "world"
    assert len(plan.stances) == len(expected.stances)
    for index, (stance_msg, stance) in enumerate(zip(plan.stances, expected.stances)):
        assert stance_msg.index == index
        assert [(c.spot, c.surface, c.in_stability) for c in stance_msg.contacts] == \
            [(c.spot, c.surface, c.in_stability) for c in stance.contacts]
        for contact_msg_, contact in zip(stance_msg.contacts, stance.contacts):
            surface = flat_steps.surfaces[contact.surface]
            assert contact_msg_.friction == surface.friction
            assert np.allclose(se3_from_pose_msg(contact_msg_.pose).homogeneous,
                               contact.contact_frame(surface).homogeneous, atol=1e-9)
        # equal to rounding: the QP solver's last bits depend on memory alignment
        assert np.allclose(_pose_values(stance_msg.witness_base_pose), stance.q[:7], atol=1e-9)
        joints = robot.actuated_positions(stance.q)
        assert list(stance_msg.witness_joints.name) == list(joints)
        assert np.allclose(stance_msg.witness_joints.position, list(joints.values()), atol=1e-9)
    # A subscriber that arrives after the plan still gets it (transient local, depth 1).
    late = BackgroundNode("late_plan_subscriber")
    received = []
    late.node.create_subscription(StancePlan, "/contact_planner/plan", received.append,
                                  LATCHED)
    late.start_spinning()
    try:
        wait_until(lambda: received, 10, what="the latched plan")
        assert received[0] == plan
    finally:
        late.close()


def test_sigint_during_a_plan_stops_the_node_and_its_planner_process(processes):
    domain = other_domain_id()  # away from the module's node
    node = processes.start("contact_planner_node", name="contact_planner_node",
                           env={"ROS_DOMAIN_ID": str(domain)})
    client = PlannerClient("sigint_client", domain_id=domain)
    try:
        assert client.client.wait_for_server(timeout_sec=60), node.log_path.read_text()
        handle = client.send(PlanContacts.Goal(scene="chair_table", time_budget=600.0))
        assert handle.accepted
        time.sleep(3.0)
        stopped_at = time.monotonic()
        os.killpg(node.pid, signal.SIGINT)
        assert node.wait(timeout=10) == 0, node.log_path.read_text()
        assert time.monotonic() - stopped_at < 5.0
        # The plan ends (cancelled) before the node closes its planner process under it.
        log = node.log_path.read_text()
        assert "planner process died" not in log and "Traceback" not in log, log
        # The planner process and multiprocessing's resource tracker end with the node.
        wait_until(lambda: not _session_alive(node.pid), 5, what="the node's session to end")
    finally:
        client.close()


class RecordedGoalHandle:
    """The goal handle an executing PlanContacts goal sees, recording how it ends."""

    def __init__(self, goal):
        self.request = goal
        self.is_cancel_requested = False
        self.ended = None

    def abort(self):
        self.ended = "aborted"


def test_a_goal_accepted_but_not_executing_at_shutdown_ends_without_a_wait():
    from contact_planner_node.node import ContactPlannerNode
    from rclpy.action import GoalResponse
    from stance.planning.planner import CANCELLED
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=other_domain_id())
    node = ContactPlannerNode(context=context)
    try:
        goal = PlanContacts.Goal(scene="flat_steps")
        assert node._on_goal(goal) == GoalResponse.ACCEPT
        started = time.monotonic()
        node.stop_planning()  # the executor has not run the goal yet
        assert time.monotonic() - started < 1.0
        handle = RecordedGoalHandle(goal)
        result = node._execute(handle)
        assert handle.ended == "aborted" and result.reason == CANCELLED, result
        assert not node._busy.locked()  # the next goal can be accepted
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize("parameter, reason", [
    ("default_scene:=no_such_scene", "default_scene"),
    ("max_nodes:=0", "max_nodes"),
    ("workers:=0", "workers"),
    ("robot:=no_such_robot", "unknown example-robot-data robot"),
])
def test_bad_startup_parameter_is_refused_with_its_reason(processes, parameter, reason):
    node = processes.start("contact_planner_node", "--ros-args", "-p", parameter,
                           name="contact_planner_node")
    assert node.wait(timeout=60) == 1
    assert reason in node.log_path.read_text()


# --- conversions alone (no DDS) ---------------------------------------------------------

def test_contact_round_trip_through_the_message(flat_steps):
    surface_name, surface = next(iter(flat_steps.surfaces.items()))
    spot = next(iter(flat_steps.spots))
    contact = Contact(spot, surface_name, 0.05, -0.02, 2.5, in_stability=False)
    msg = contact_msg(contact, surface)
    assert msg.friction == surface.friction
    normal = pin.Quaternion(msg.pose.orientation.w, msg.pose.orientation.x,
                            msg.pose.orientation.y, msg.pose.orientation.z).matrix()[:, 2]
    assert np.allclose(normal, surface.pose.rotation[:, 2], atol=1e-12)
    back = contact_from_msg(msg, flat_steps, "start[0]")
    assert (back.spot, back.surface, back.in_stability) == (spot, surface_name, False)
    assert np.allclose([back.x, back.y, back.theta], [0.05, -0.02, 2.5], atol=1e-12)


def test_tilted_contact_is_rejected(flat_steps):
    surface_name, surface = next(iter(flat_steps.surfaces.items()))
    msg = contact_msg(Contact(next(iter(flat_steps.spots)), surface_name, 0.0, 0.0, 0.0),
                      surface)
    tilted = pin.Quaternion(msg.pose.orientation.w, msg.pose.orientation.x,
                            msg.pose.orientation.y, msg.pose.orientation.z) \
        * pin.Quaternion(pin.rpy.rpyToMatrix(0.05, 0.0, 0.0))
    (msg.pose.orientation.x, msg.pose.orientation.y, msg.pose.orientation.z,
     msg.pose.orientation.w) = tilted.coeffs()
    with pytest.raises(GoalRejected, match=r"start\[2\].pose: z axis 0.050 rad"):
        contact_from_msg(msg, flat_steps, "start[2]")


def test_planner_process_stops_on_request_and_serves_the_next_one(flat_steps):
    """The graceful path: the planner sees the stop between posture generations and
    returns its own outcome (the chair_table cancel above takes the kill path)."""
    planner = PlannerProcess("talos")
    try:
        reports = []
        outcome = planner.plan(PlanRequest(scene=flat_steps, ordered_sons=True),
                               progress=reports.append, should_stop=lambda: len(reports) >= 2)
        assert outcome.reason == "cancelled" and "restarted" not in outcome.message
        assert outcome.statistics["nodes_expanded"] >= 2
        assert planner.plan(PlanRequest(scene=flat_steps, ordered_sons=True)).success
    finally:
        planner.close()


def test_a_stopped_planner_leaves_no_worker_process_behind(flat_steps):
    """workers = 2: the child runs a pool of worker processes; once stopped (gracefully or
    killed after CANCEL_GRACE), every process the child had started has ended."""
    planner = PlannerProcess("talos")
    started = []

    def should_stop():
        if time.monotonic() - began < 4.0:   # the pool is up by then
            return False
        if not started:
            started.extend(descendants(planner._process.pid))
        return True

    try:
        began = time.monotonic()
        outcome = planner.plan(PlanRequest(scene=load_scene("chair_table"), workers=2,
                                           time_budget=600.0), should_stop=should_stop)
        assert outcome.reason == "cancelled"
        assert len(started) >= 2, started    # the pool's workers
        wait_until(lambda: not any(os.path.exists(f"/proc/{pid}") for pid in started), 5,
                   what="the planner's worker processes to end")
        assert planner.plan(PlanRequest(scene=flat_steps, ordered_sons=True)).success
    finally:
        planner.close()


def test_key_postures_keep_half_sitting_for_joints_not_named():
    robot = Robot.load("talos")
    joint_states = [JointState(), JointState(name=["arm_left_1_joint"], position=[0.3])]
    postures = key_postures_from_msgs([_standing_pose(), _standing_pose(x=0.5)],
                                      joint_states, robot)
    reference = robot.initial_configuration("half_sitting")
    assert postures.shape == (2, robot.model.nq)
    assert np.array_equal(postures[0, 7:], reference[7:])
    changed = np.flatnonzero(postures[1, 7:] != reference[7:])
    assert changed.size == 1
    assert robot.actuated_positions(postures[1])["arm_left_1_joint"] == 0.3
    assert postures[1, 0] == 0.5 and math.isclose(np.linalg.norm(postures[1, 3:7]), 1.0)
    assert key_postures_from_msgs([], [], robot) is None


def _session_alive(session_id):
    try:
        os.killpg(session_id, 0)
    except ProcessLookupError:
        return False
    return True


def _pose_values(pose):
    """[x, y, z, qx, qy, qz, qw] of a geometry_msgs/Pose."""
    return [pose.position.x, pose.position.y, pose.position.z, pose.orientation.x,
            pose.orientation.y, pose.orientation.z, pose.orientation.w]


def _standing_pose(x=0.0):
    pose = Pose()
    pose.position.x, pose.position.z, pose.orientation.w = x, 1.02, 1.0
    return pose
