"""`stance check-run` on a bag recorded from a real flat_steps execution (pik_node,
trajectory_node at the demo's speed, stabilizer_gate_node and `stance record` as processes,
the plan computed in-process and published as contact_planner_node would): every check
passes, exit 0; so does a run whose pik_node lags (the soles trail their path) and whose
clock therefore waited for each sole to land. On a
rewritten copy of the bag with a joint pushed beyond its limit, and on altered arrays fed
to the check functions, the check concerned fails (exit 1 naming it)."""

import dataclasses
import time

import numpy as np
import pytest
from conftest import NODE_START_TIMEOUT, wait_until
from contact_planner_node.conversions import stance_plan_msg
from helpers.probe import BackgroundNode
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer
from pik_node.node import LATCHED
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from stance import Robot
from stance.execution.stabilizer import StabilizerGate
from stance.planning.planner import PlanRequest, plan_contacts
from stance.planning.scene import load_scene
from stance_msgs.msg import StancePlan
from stance_tools import check_run
from stance_tools.bag import mcap_files
from stance_tools.cli import main as stance
from stance_tools.demo import PIPELINE_TOPICS, READY_SUBSCRIBERS, VELOCITY_SCALE
from stance_tools.processes import ProcessGroup
from std_msgs.msg import String

STEPS = 10   # samples_per_transition: a shorter run than the node's default
# rad/s: the command's fastest joint moves faster than this (the lag estimate's 1 mrad
# tolerance is then 5 ms at most)
MOVING_SPEED = 0.2
STATUS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                    durability=DurabilityPolicy.TRANSIENT_LOCAL)


class PlanPublisher(BackgroundNode):
    """Publishes the plan (latched, as contact_planner_node); collects trajectory
    statuses."""

    def __init__(self):
        super().__init__("check_run_probe")
        self.statuses = []
        self.node.create_subscription(String, "/trajectory/status",
                                      lambda msg: self.statuses.append(msg.data), STATUS)
        self.plan_pub = self.node.create_publisher(StancePlan, "/contact_planner/plan", LATCHED)
        self.start_spinning()

    def ready(self):
        """Every recorded topic has its publisher and its subscribers (the demo's rule;
        this probe stands for contact_planner_node's plan publisher)."""
        return all(self.node.count_publishers(topic) and
                   self.node.count_subscribers(topic) >= count
                   for topic, count in READY_SUBSCRIBERS.items())


def record_flat_steps_run(directory, velocity_scale=VELOCITY_SCALE, trajectory_args=()):
    """Execute flat_steps through the nodes while recording (trajectory_node at
    velocity_scale, with trajectory_args: more `-p name:=value`); returns (the bag path,
    trajectory_node's statuses)."""
    robot = Robot.load("talos")
    scene = load_scene("flat_steps", robot)
    outcome = plan_contacts(robot, PlanRequest(scene=scene, ordered_sons=True))
    assert outcome.success, outcome.message
    bag = directory / "bag"
    group = ProcessGroup(directory / "logs")
    probe = None
    try:
        group.start("pik_node", name="pik_node")
        group.start("trajectory_node", "--ros-args", "-p", f"samples_per_transition:={STEPS}",
                    "-p", f"velocity_scale:={velocity_scale}", *trajectory_args,
                    name="trajectory_node")
        group.start("stabilizer_gate_node", "--ros-args", "-p", "scene:=flat_steps",
                    name="stabilizer_gate_node")
        recorder = group.start("stance", "record", "-o", str(bag), *PIPELINE_TOPICS,
                               name="record")
        probe = PlanPublisher()
        wait_until(probe.ready, NODE_START_TIMEOUT, period=0.1,
                   what="the nodes and the recorder")
        probe.plan_pub.publish(stance_plan_msg(outcome.plan, scene, robot,
                                               Time(nanoseconds=time.time_ns()).to_msg()))
        wait_until(lambda: any(s.startswith(("done:", "failed:")) for s in probe.statuses),
                   180, period=0.1, what="trajectory status done")
        assert not any(s.startswith("failed:") for s in probe.statuses), probe.statuses
        time.sleep(1.0)
        assert group.stop(recorder) == 0, recorder.log_path.read_text()
    finally:
        if probe is not None:
            probe.close()
        group.stop_all()
    return bag, probe.statuses


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    return record_flat_steps_run(tmp_path_factory.mktemp("check_run"))[0]


@pytest.fixture(scope="module")
def report(bag):
    return check_run.check_bag(bag)


def test_real_run_passes_every_check(bag, report, capsys):
    assert [c.name for c in report.checks] == ["contacts", "joint_limits", "joint_velocity",
                                               "trajectory_c1", "equilibrium", "stabilizer"]
    assert report.passed, [(c.name, c.failures) for c in report.checks]
    # the checks looked at the motion: every stance, both soles, many samples
    assert len(report.run.stances) > 5
    contacts = report.checks[0]
    assert {row[0] for row in contacts.rows} == {"left_sole", "right_sole"}
    assert sum(row[3] for row in contacts.rows) > 1000
    assert len(report.checks[4].rows) == len(report.run.stances)
    assert stance(["check-run", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "== contacts: PASS" in out and "6/6 checks passed" in out


def rewrite_bag(source, target, edit):
    """Copy a bag's MCAP file with edit(topic, message) applied to each decoded message."""
    (path,) = mcap_files(source)
    target.mkdir()
    with open(path, "rb") as stream, open(target / "doctored.mcap", "wb") as out:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        writer = Ros2Writer(out)
        schemas = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages(
                log_time_order=True):
            if schema.name not in schemas:
                schemas[schema.name] = writer.register_msgdef(schema.name,
                                                              schema.data.decode())
            edit(channel.topic, decoded)
            writer.write_message(channel.topic, schemas[schema.name], decoded,
                                 log_time=message.log_time,
                                 publish_time=message.publish_time)
        writer.finish()
    return target / "doctored.mcap"


def test_joint_pushed_beyond_its_limit_fails_joint_limits(bag, tmp_path, capsys):
    robot = Robot.load("talos")
    name, upper = robot.limited_joint_names[3], robot.upper[3]
    count = [0]

    def push(topic, msg):
        if topic == "/joint_states":
            count[0] += 1
            if count[0] == 200:
                index = list(msg.name).index(name)
                msg.position[index] = upper + 0.05

    doctored = rewrite_bag(bag, tmp_path / "doctored", push)
    assert stance(["check-run", str(doctored), "--scene", "flat_steps"]) == 1
    captured = capsys.readouterr()
    assert "== joint_limits: FAIL" in captured.out
    assert f"FAIL joint_limits: {name}" in captured.err
    # the jump may also break contacts and speed limits at that sample, depending on the
    # joint and on what the robot does at that moment
    verdict = captured.out.strip().splitlines()[-1]
    assert verdict.startswith("check-run:") and "joint_limits" in verdict.split("failed:")[1]


def test_altered_arrays_fail_the_check_concerned(report):
    run = report.run
    robot = Robot.load("talos")
    scene = load_scene("flat_steps", robot)
    # the left sole 5 mm off wherever it is
    slipped = dict(report.positions, left_sole=report.positions["left_sole"] + [0.005, 0, 0])
    assert check_run.check_contacts(run, scene, report.positions).passed
    failures = check_run.check_contacts(run, scene, slipped).failures
    assert failures and all(f.startswith("left_sole") for f in failures)
    # a joint too fast
    names, times, joints = run.joint_names, run.times, run.joints.copy()
    column = names.index(robot.limited_joint_names[0])
    # a step of twice what the limit allows over the measuring window
    joints[len(times) // 2:, column] += 2.0 * robot.velocity_limit[0] * \
        check_run.VELOCITY_WINDOW
    failed = check_run.check_joint_velocity(robot, names, times, joints)
    assert failed.failures and failed.failures[0].startswith(robot.limited_joint_names[0])
    # a velocity jump and a position jump in the commanded trajectory
    t, q, v, trajectory_names = run.trajectory
    assert check_run.check_trajectory_c1(robot, t, q, v, trajectory_names).passed
    waypoint = len(t) // 2
    step = t[waypoint] - t[waypoint - 1]
    jumped = v.copy()
    jumped[waypoint, 0] += 2.0 * check_run.C1_ACCELERATION_BOUND * step
    assert any("velocity jump" in f for f in
               check_run.check_trajectory_c1(robot, t, q, jumped, trajectory_names).failures)
    moved = q.copy()
    moved[waypoint:, 1] += 2.0 * robot.velocity_limit.max() * step
    assert any("position jump" in f for f in
               check_run.check_trajectory_c1(robot, t, moved, v, trajectory_names).failures)
    # the CoM 0.5 m ahead of the feet: no equilibrium
    far = report.com + [0.5, 0.0, 0.0]
    assert check_run.check_equilibrium(run, robot, scene, report.com).passed
    assert not check_run.check_equilibrium(run, robot, scene, far).passed
    # the stabilizer switching off on coplanar support
    initial, expected = check_run.expected_switches(run.stances, run.stamps,
                                                    StabilizerGate(scene))
    times, enabled, _ = run.stabilizer
    assert initial and expected == []
    assert check_run.check_stabilizer(initial, expected, times, enabled, run.stamps[0]).passed
    flipped = enabled.copy()
    flipped[len(flipped) // 2:] = False
    failures = check_run.check_stabilizer(initial, expected, times, flipped,
                                          run.stamps[0]).failures
    assert failures and "unexpected switch" in failures[0]
    # a scheduled switch that never comes
    late = [(run.stamps[2], False, "stance 2: made up")]
    assert "missing switch" in check_run.check_stabilizer(initial, late, times, enabled,
                                                          run.stamps[0]).failures[0]
    # off and on again at once (a release, then a creation): no switch, published or not
    blip = [(run.stamps[2], False, "stance 2: released"),
            (run.stamps[2] + 0.02, True, "stance 3: created")]
    assert check_run.check_stabilizer(initial, blip, times, enabled, run.stamps[0]).passed
    middle = int(np.searchsorted(times, run.stamps[2]))
    blipped = enabled.copy()
    blipped[middle:middle + 2] = False
    assert times[middle + 2] - times[middle] < check_run.STABILIZER_DELAY
    assert check_run.check_stabilizer(initial, blip, times, blipped, run.stamps[0]).passed
    assert not check_run.check_stabilizer(initial, [], times, flipped, run.stamps[0]).passed


def ideal_run(run, robot, scene):
    """run with joint states and base poses exactly on its command at their stamps (the
    plan interpolated and timed again as trajectory_node did: its JointTrajectory checked
    against the recorded one), so that its own lag is zero whatever the load was."""
    from stance.execution.interpolation import TransitionPlanner
    from stance.execution.timing import sinusoidal_trajectory
    from stance.planning.collision import CollisionModel

    plan = plan_contacts(robot, PlanRequest(scene=scene, ordered_sons=True)).plan
    planner = TransitionPlanner(robot, scene, CollisionModel(robot, scene), steps=STEPS)
    path = planner.interpolate(plan)
    trajectory = sinusoidal_trajectory(robot, path.q, path.event_samples, VELOCITY_SCALE)
    waypoint_times, positions, _, names = run.trajectory
    np.testing.assert_allclose(waypoint_times, trajectory.times, atol=1e-6)
    q = np.array([trajectory.sample(t)[0] for t in
                  check_run.command_times(run.stamps, waypoint_times, run.times)])
    joints = np.array([[configuration[robot.model.joints[robot.joint_id(name)].idx_q]
                        for name in run.joint_names] for configuration in q])
    np.testing.assert_allclose(joints[:, [run.joint_names.index(n) for n in names]][0],
                               positions[0], atol=1e-9)
    return dataclasses.replace(run, joints=joints, q=q)


def test_lagging_joint_states_are_checked_on_the_support_they_track(report):
    """Joint states `lag` behind their command (a loaded pik_node), from the recorded run's
    command tracked exactly (ideal_run: the recorded states' own lag varies with the
    load): tracking_delays measures the lag where the command moves, and the equilibrium
    and contacts checks take the contacts the command had at the instant each state
    tracks. Checked at the stamps, the same states fail equilibrium: a contact released
    on time is still leaned on. 0.15 s: the worst margin at the stamps was -41 to -65 N."""
    robot = Robot.load("talos")
    scene = load_scene("flat_steps", robot)
    ideal = ideal_run(report.run, robot, scene)
    lag = 0.15
    source = np.clip(np.searchsorted(ideal.times, ideal.times - lag), 0, len(ideal.times) - 1)
    delayed = dataclasses.replace(ideal, joints=ideal.joints[source], q=ideal.q[source])
    chosen = check_run.equilibrium_samples(ideal.times, ideal.stamps)
    chosen = chosen[ideal.times[chosen] > ideal.stamps[0] + lag]
    # a lag shows only where the command moves (not at rest, nor while it waits at a stance)
    times, _, velocities, _ = ideal.trajectory
    speed = np.abs(velocities).max(axis=1)
    moving = np.interp(check_run.command_times(ideal.stamps, times, ideal.times[chosen] - lag),
                       times, speed) > MOVING_SPEED
    assert moving.sum() > 20
    assert np.all(check_run.tracking_delays(ideal, chosen[moving]) <= check_run.DELAY_STEP)
    measured = check_run.tracking_delays(delayed, chosen[moving])
    # (shifted by whole samples: a stamp at or after each one lag earlier)
    assert np.median(measured) == pytest.approx(lag, abs=2 * check_run.DELAY_STEP)
    com = check_run.centers_of_mass(robot, delayed.q)
    check = check_run.check_equilibrium(delayed, robot, scene, com)
    assert check.passed, check.failures
    assert max(float(row[4]) for row in check.rows) >= lag
    untracked = dataclasses.replace(delayed, trajectory=None)
    assert not check_run.check_equilibrium(untracked, robot, scene, com).passed
    positions = check_run.spot_positions(robot, scene, delayed.q)
    assert check_run.check_contacts(delayed, scene, positions).passed


def test_a_run_that_waited_for_its_contacts_passes_every_check(tmp_path):
    """pik_node made to lag (contact gain 0.02) at the node's own speed: trajectory_node
    waits at each landing and announces those stances again; check-run reads each stance
    once, stamped when it was reached, follows the waits in the command's time, and every
    check passes (a sole held from its planned, earlier stamp would be centimetres off)."""
    bag, statuses = record_flat_steps_run(tmp_path, 0.5, ("-p", "contact_gain:=0.02"))
    waits = [status for status in statuses if "reached after waiting" in status]
    assert len(waits) >= 3, statuses
    report = check_run.check_bag(bag)
    assert report.passed, [(c.name, c.failures) for c in report.checks]
    plan_length = int(next(s for s in statuses if s.startswith("executing: ")).split()[1])
    assert len(report.run.stances) == plan_length
    assert np.all(np.diff(report.run.stamps) > 0.0)
