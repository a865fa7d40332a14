"""stabilizer_gate_node over DDS in its own process: active stances switch the state as the
paper's rule says (off at the start of the transition creating the hand contact, on at the
end of the one releasing it) with a continuous blend; bad stances are rejected and the state
kept; a plan is scheduled ahead; in the graph, a late release followed by a new contact
never switches on; bad parameters end the node with exit code 1."""

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from conftest import NODE_START_TIMEOUT, other_domain_id, wait_until
from contact_planner_node.conversions import contact_msg
from helpers.probe import RELIABLE, BackgroundNode
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from stance.planning.contacts import Contact
from stance.planning.scene import load_scene
from stance_msgs.msg import ContactStance, StabilizerState, StancePlan

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
CHAIR_PLAN = Path(__file__).resolve().parent.parent / "docs" / "figures" / \
    "chair_table_plan.json"
RAMP = 0.3   # s
RATE = 50.0  # Hz
FEET = (Contact("left_sole", "floor", 0.0, 0.1, 0.0),
        Contact("right_sole", "floor", 0.0, -0.1, 0.0))
HAND = Contact("right_hand", "table", -0.3, -0.2, 0.0)
HAND_ON_TABLE = [FEET, FEET + (HAND,), FEET + (HAND.with_stability(False),)]


class GateProbe(BackgroundNode):
    """Publishes active stances and plans, collects (receipt s, StabilizerState)."""

    def __init__(self, name="stabilizer_gate_probe", domain_id=None):
        super().__init__(name, domain_id)
        self.lock = threading.Lock()
        self.states = []
        self.node.create_subscription(StabilizerState, "/stabilizer/state", self._on_state,
                                      RELIABLE)
        self.stance_pub = self.node.create_publisher(ContactStance, "/trajectory/active_stance",
                                                     RELIABLE)
        self.plan_pub = self.node.create_publisher(StancePlan, "/contact_planner/plan", LATCHED)
        self.start_spinning()

    def _on_state(self, msg):
        with self.lock:
            self.states.append(msg)

    def states_since(self, count):
        with self.lock:
            return list(self.states[count:])

    def count(self):
        with self.lock:
            return len(self.states)

    def publish_stance(self, msg):
        wait_until(lambda: self.stance_pub.get_subscription_count() > 0, 10,
                   what="the gate's stance subscription")
        self.stance_pub.publish(msg)


@pytest.fixture(scope="module")
def scene():
    return load_scene("chair_table")


@pytest.fixture(scope="module")
def gate(tmp_path_factory):
    """One stabilizer_gate_node without a scene (surfaces learned from contact frames)."""
    from stance_tools.processes import ProcessGroup
    group = ProcessGroup(tmp_path_factory.mktemp("gate"))
    node = group.start("stabilizer_gate_node", "--ros-args", "-p", f"ramp_time:={RAMP}",
                       "-p", f"rate:={RATE}", name="stabilizer_gate_node")
    probe = GateProbe()
    try:
        wait_until(lambda: probe.stance_pub.get_subscription_count() > 0
                   or node.poll() is not None, 30, what="the gate's stance subscription")
        assert node.poll() is None, node.log_path.read_text()
        yield node, probe
    finally:
        probe.close()
        group.stop_all()
        print(node.log_path.read_text())


def stamp(seconds):
    return Time(sec=int(seconds), nanosec=int((seconds % 1.0) * 1e9))


def seconds(time_msg):
    return time_msg.sec + time_msg.nanosec * 1e-9


def stance_msg(scene, index, contacts, ends_at=0.0):
    msg = ContactStance(index=index, contacts=[contact_msg(c, scene.surfaces[c.surface])
                                               for c in contacts])
    msg.header.stamp = stamp(ends_at)
    return msg


def wait_state(probe, predicate, timeout, what):
    """The first state received from now on satisfying predicate."""
    count = probe.count()
    return wait_until(lambda: next((s for s in probe.states_since(count) if predicate(s)),
                                   None), timeout, what=what)


def test_hand_contact_switches_off_before_and_on_after_its_release(gate, scene):
    node, probe = gate
    probe.publish_stance(stance_msg(scene, 0, HAND_ON_TABLE[0]))
    first = wait_state(probe, lambda s: s.stance_index == 0, 10, "stance 0 in the state")
    assert (first.enabled, first.blend, first.coplanar, first.balance_mode) == \
        (True, 1.0, True, "com_polygon")

    count = probe.count()
    hand_made_at = time.time() + 1.0              # the transition lasts 1 s
    probe.publish_stance(stance_msg(scene, 1, HAND_ON_TABLE[1], hand_made_at))
    wait_until(lambda: time.time() > hand_made_at + 0.2, 3, what="the hand contact")
    approach = [s for s in probe.states_since(count) if s.stance_index == 1]
    off = [s for s in approach if seconds(s.header.stamp) < hand_made_at]
    assert off and not any(s.enabled for s in off)
    assert {s.balance_mode for s in approach} == {"static_equilibrium"}
    assert not any(s.coplanar for s in approach)
    assert "right_hand on table" in off[0].reason
    assert 0.0 < off[0].blend < 1.0               # ramping, not jumping
    assert off[-1].blend == 0.0                   # off before the contact is made

    # released, then the next stance announced 0.3 s after the planned end: the robot is
    # known to be at the release stance only then, and the gate switches on only then
    count = probe.count()
    released_at = time.time() + 0.6
    probe.publish_stance(stance_msg(scene, 2, HAND_ON_TABLE[2], released_at))
    wait_until(lambda: time.time() > released_at + 0.3, 3, what="past the planned release")
    confirmed_at = time.time()
    probe.publish_stance(stance_msg(scene, 3, FEET, time.time() + 1.0))
    wait_state(probe, lambda s: s.stance_index == 3 and s.blend == 1.0, 5, "the on ramp")
    states = probe.states_since(count)
    release = [s for s in states if s.stance_index == 2]
    assert release and all(not s.enabled and s.blend == 0.0 and s.coplanar for s in release)
    assert seconds(release[-1].header.stamp) > released_at + 0.2
    on = [s for s in states if s.enabled]
    assert all(s.balance_mode == "com_polygon" for s in on)
    assert "released" in on[0].reason and 0.0 < on[0].blend < 1.0
    assert_switches_on_once(states, confirmed_at)

    # released late, announced again when reached: off until then
    probe.publish_stance(stance_msg(scene, 4, HAND_ON_TABLE[1], time.time() + 0.5))
    wait_state(probe, lambda s: s.stance_index == 4 and s.blend == 0.0, 5, "off again")
    count = probe.count()
    planned_at = time.time() + 0.3
    probe.publish_stance(stance_msg(scene, 5, HAND_ON_TABLE[2], planned_at))
    wait_until(lambda: time.time() > planned_at + 0.5, 3, what="past the planned release")
    reached_at = time.time()
    probe.publish_stance(stance_msg(scene, 5, HAND_ON_TABLE[2], reached_at))
    wait_state(probe, lambda s: s.stance_index == 5 and s.blend == 1.0, 5, "the on ramp")
    states = [s for s in probe.states_since(count) if s.stance_index == 5]
    assert seconds(states[0].header.stamp) < planned_at        # seen from before its end
    assert_switches_on_once(states, reached_at)

    blends = np.array([s.blend for s in probe.states_since(0)])
    assert blends.min() >= 0.0 and blends.max() <= 1.0
    # Cubic ramp over RAMP s sampled at RATE Hz (a late sample may span two periods).
    assert np.abs(np.diff(blends)).max() <= 1.5 / RAMP * 3.0 / RATE
    assert node.poll() is None


def assert_switches_on_once(states, at):
    """states switch on once, not before `at` (s: when what confirms the release was
    sent), and never back off; off with blend 0 before."""
    enabled = [s.enabled for s in states]
    first_on = enabled.index(True)
    assert all(not s.enabled and s.blend == 0.0 for s in states[:first_on])
    assert all(enabled[first_on:])
    assert at <= seconds(states[first_on].header.stamp) <= at + 1.0


@pytest.mark.parametrize("case", ["nan pose", "no contact", "no supporting contact",
                                  "off its surface's plane", "spot twice",
                                  "stamp before the epoch", "stamp a year ahead"])
def test_bad_stance_is_rejected_and_the_state_kept(gate, scene, case):
    node, probe = gate
    probe.publish_stance(stance_msg(scene, 10, FEET))
    wait_state(probe, lambda s: s.stance_index == 10 and s.blend == 1.0, 10, "stance 10")
    bad = stance_msg(scene, 11, FEET + (HAND,))
    if case == "nan pose":
        bad.contacts[2].pose.position.x = math.nan
    elif case == "no contact":
        bad.contacts = []
    elif case == "no supporting contact":
        for contact in bad.contacts:
            contact.in_stability = False
    elif case == "spot twice":
        bad.contacts[1].spot = bad.contacts[0].spot
    elif case == "stamp before the epoch":   # rclpy's Time refuses it: the node died
        bad.header.stamp.sec = -1
    elif case == "stamp a year ahead":       # the transition would never end
        bad.header.stamp = stamp(time.time() + 3.15e7)
    else:  # the floor learned at z = 0 is not at z = 0.1 m
        bad.contacts[0].pose.position.z = 0.1
    probe.publish_stance(bad)
    wait_until(lambda: "active stance 11 rejected" in node.log_path.read_text(), 5,
               what="the rejection in the log")
    count = probe.count()
    wait_until(lambda: probe.count() > count + 5, 5, what="states after the rejection")
    kept = probe.states_since(count)
    assert all((s.stance_index, s.enabled, s.blend) == (10, True, 1.0) for s in kept)
    assert node.poll() is None
    node.log_path.write_text("")  # the next case looks for its own rejection


def test_a_rejected_stance_teaches_no_surface(gate, scene):
    """Without a scene, surfaces are learned from the contacts of the stances the node
    accepts only: a rejected stance once taught its surfaces, and every later stance on
    them was measured against the rejected one's plane."""
    node, probe = gate
    probe.publish_stance(stance_msg(scene, 20, FEET))
    wait_state(probe, lambda s: s.stance_index == 20, 10, "stance 20")
    bad = stance_msg(scene, 21, FEET + (HAND,))
    bad.contacts[2].surface = "shelf"          # a surface name never seen
    bad.contacts[2].pose.position.z += 0.3
    for contact in bad.contacts:               # rejected: no supporting contact
        contact.in_stability = False
    probe.publish_stance(bad)
    wait_until(lambda: "active stance 21 rejected" in node.log_path.read_text(), 5,
               what="the rejection in the log")
    good = stance_msg(scene, 22, FEET + (HAND,))
    good.contacts[2].surface = "shelf"
    probe.publish_stance(good)
    wait_state(probe, lambda s: s.stance_index == 22, 10, "stance 22 on the shelf")
    assert "active stance 22 rejected" not in node.log_path.read_text()
    node.log_path.write_text("")


def test_plan_is_scheduled_and_unknown_surfaces_are_rejected_with_a_scene(processes, scene):
    domain = other_domain_id()  # away from the module's node
    node = processes.start("stabilizer_gate_node", "--ros-args", "-p", "scene:=chair_table",
                           name="stabilizer_gate_node", env={"ROS_DOMAIN_ID": str(domain)})
    probe = GateProbe("scene_gate_probe", domain)
    try:
        plan = StancePlan(scene="chair_table",
                          stances=[stance_msg(scene, k, contacts)
                                   for k, contacts in enumerate(HAND_ON_TABLE)])
        probe.plan_pub.publish(plan)                  # latched: the node gets it on joining
        wait_until(lambda: "plan of 3 stances" in node.log_path.read_text()
                   or node.poll() is not None, 30, what="the plan's schedule in the log")
        log = node.log_path.read_text()
        assert ("off at the start of the transition into stance 1; on at the end of the "
                "transition into stance 2") in log, log
        unknown = stance_msg(scene, 0, FEET)
        unknown.contacts[1].surface = "no_such_surface"
        probe.publish_stance(unknown)
        wait_until(lambda: "unknown surface 'no_such_surface'" in node.log_path.read_text(),
                   5, what="the rejection in the log")
        time.sleep(3.0 / RATE)
        assert probe.count() == 0                     # no stance accepted: nothing published
        probe.publish_stance(stance_msg(scene, 0, FEET))
        wait_state(probe, lambda s: s.stance_index == 0 and s.enabled, 5, "stance 0")
        lift_right_foot = (FEET[0], FEET[1].with_stability(False))    # the plan places a hand
        probe.publish_stance(stance_msg(scene, 1, lift_right_foot))
        wait_until(lambda: "does not follow the last plan" in node.log_path.read_text(), 5,
                   what="the plan mismatch warning")
    finally:
        probe.close()


def test_a_late_release_then_a_new_contact_never_switches_on_in_the_graph(processes):
    """Four stances of the chair plan: the right hand leaves the support (stance 1: the
    rule switches on at the end of that transition) and the next transition makes a
    non-coplanar contact (stance 2: off at its start), so the stabilizer is on for no time.
    pik_node made to lag (contact and CoM gains 0.02) reaches every stance late: stance 1 is
    announced again when reached, stance 2 at once, and the gate never ramps on in between
    (it used to: on from stance 1's planned end, or while trajectory_node rebuilt its
    JointTrajectory, until stance 2 came; blend 0.39 in a loaded chair demo). pik_node,
    trajectory_node and the gate on the scene, in another DDS domain."""
    from stance import Robot
    from stance.execution.stabilizer import END, START, StabilizerGate
    from stance.planning.contacts import Plan, load_plan
    from test_trajectory_node import STEPS, TrajectoryProbe, plan_msg, reannounced

    robot, full = Robot.load("talos"), load_plan(CHAIR_PLAN)
    chair = load_scene("chair_table", robot)
    short = Plan(full.scene, full.robot, full.stances[61:65])
    events = StabilizerGate(chair).schedule([stance.contacts for stance in short.stances])
    assert [(e.stance_index, e.at, e.enabled) for e in events] == \
        [(1, END, True), (2, START, False)]
    domain = other_domain_id()
    env = {"ROS_DOMAIN_ID": str(domain)}
    processes.start("pik_node", name="pik_node", env=env)
    # the graph's rule: a plan starts once the gate listens (a gate discovered late took
    # the re-announced stance 1 for its start: on at once)
    processes.start("trajectory_node", "--ros-args", "-p", "contact_gain:=0.02", "-p",
                    "com_gain:=0.02", "-p", f"samples_per_transition:={STEPS}", "-p",
                    "stance_listeners:=[stabilizer_gate_node]", name="trajectory_node",
                    env=env)
    gate = processes.start("stabilizer_gate_node", "--ros-args", "-p", "scene:=chair_table",
                           "-p", f"rate:={RATE}", name="stabilizer_gate_node", env=env)
    probe = TrajectoryProbe("chair_probe", domain)
    states = GateProbe("chair_gate_probe", domain)
    try:
        wait_until(lambda: probe.joint_state is not None and probe.statuses, NODE_START_TIMEOUT,
                   what="pik_node's joint states and trajectory_node's status")
        counts = probe.counts()
        probe.publish_plan(plan_msg(robot, chair, short))
        statuses = probe.wait_status(counts, "done", 180)
        time.sleep(3.0 / RATE)
        published = states.states_since(0)
    finally:
        probe.close()
        states.close()
    assert 1 in reannounced(statuses), statuses     # the release stance was reached late
    assert "active stance 0: " in gate.log_path.read_text()     # the gate saw the start
    executed = [s for s in published if s.stance_index >= 1]
    assert executed and executed[-1].stance_index == 3
    assert max(s.blend for s in published) < 0.01
    # on for one state at most (the gate's timer between the two announcements)
    assert not any(a.enabled and b.enabled for a, b in zip(published, published[1:]))


@pytest.mark.parametrize("parameter, reason", [
    ("ramp_time:=0.0", "ramp_time"),
    ("rate:=nan", "rate"),
    ("angle_tolerance:=-1.0", "angle_tolerance"),
    ("scene:=no_such_scene", "unknown scene"),
])
def test_bad_startup_parameter_is_refused_with_its_reason(processes, parameter, reason):
    node = processes.start("stabilizer_gate_node", "--ros-args", "-p", parameter,
                           name="stabilizer_gate_node")
    assert node.wait(timeout=30) == 1
    assert reason in node.log_path.read_text()
