"""stance teleop: path validation and interpolation, the key map and the raw terminal loop
(pure, no ROS); then the command in its own process against a fake pik_node that only
publishes /pik/status and records the targets it receives."""

import io
import os
import termios
import threading
import time

import numpy as np
import pytest
import yaml
from conftest import wait_until
from geometry_msgs.msg import Point, PointStamped, Pose, PoseStamped, Quaternion
from helpers.probe import BackgroundNode
from rclpy.qos import QoSProfile, ReliabilityPolicy
from scipy.spatial.transform import Rotation
from stance_msgs.msg import SolverStatus, TaskStatus
from stance_tools.cli import main as teleop_main
from stance_tools.teleop import (QUIT_KEYS, ROTATION_KEYS, TRANSLATION_KEYS, KeyboardTeleop,
                                 PathError, ScriptedPath, Target, builtin_path_names,
                                 load_path, parse_path, run_keyboard)

RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
START = Target(np.array([0.11, -0.43, 0.78]), Rotation.from_euler("xyz", [0.3, -0.2, 2.5]))


# --- Paths --------------------------------------------------------------------------------------

@pytest.mark.parametrize("text, field", [
    ("{offset: [0, 0, 0], duration: 1}", "must be a non-empty list of waypoints"),
    ("[]", "must be a non-empty list of waypoints"),
    ("[7]", "waypoint 0: must be a mapping"),
    ("[{offset: [0, 0, 0]}]", "waypoint 0: missing field 'duration'"),
    ("[{duration: 1}]", "waypoint 0: missing field 'offset'"),
    ("[{offset: [0, 0], duration: 1}]", "waypoint 0.offset: must be a list of 3"),
    ("[{offset: [0, 0, .nan], duration: 1}]", "waypoint 0.offset: must be a list of 3"),
    ("[{offset: [0, 0, 0], duration: 1}, {offset: [0, 0, 0], rpy: [0, a, 0], duration: 1}]",
     "waypoint 1.rpy: must be a list of 3"),
    ("[{offset: [0, 0, 0], duration: 0}]", "waypoint 0.duration: must be a number > 0"),
    ("[{offset: [0, 0, 0], duration: '1'}]", "waypoint 0.duration: must be a number > 0"),
    ("[{offset: [0, 0, 0], duration: 1.0e+7}]", "waypoint 0.duration: must be a number > 0 "
                                                "(s), at most 1e+06"),
    ("[{offset: [0, 0, 0], duration: 1, speed: 2}]", "waypoint 0: unknown field 'speed'"),
])
def test_malformed_path_is_rejected_naming_the_field(text, field):
    with pytest.raises(PathError) as error:
        parse_path(yaml.safe_load(text), "bad.yaml")
    assert str(error.value).startswith("bad.yaml: ")
    assert field in str(error.value)


def test_path_files_and_builtin_names(tmp_path):
    broken = tmp_path / "broken.yaml"
    broken.write_text("- {offset: [0, 0, 0], duration: 1\n")
    with pytest.raises(PathError, match="broken.yaml: invalid YAML"):
        load_path(str(broken))
    with pytest.raises(PathError, match="cannot read"):
        load_path(str(tmp_path / "missing.yaml"))
    with pytest.raises(PathError, match="built-in: circle, reach_limits"):
        load_path("figure_eight")


def test_exponents_without_a_dot_are_numbers_within_bounds(tmp_path):
    """YAML 1.1 (PyYAML) read 1e308 and 5e-2 as strings; they are numbers, and a number
    beyond 1e6 is refused."""
    path = tmp_path / "exponents.yaml"
    path.write_text("- {offset: [5e-2, 0, 0], duration: 2e0}\n")
    waypoint, = load_path(str(path))
    assert waypoint.offset[0] == 0.05 and waypoint.duration == 2.0
    path.write_text("- {offset: [1e308, 0, 0], duration: 1}\n")
    with pytest.raises(PathError, match=r"offset: .* at most 1e\+06 in magnitude, got "
                                        r"\[1e\+308, 0, 0\]"):
        load_path(str(path))


def test_unreadable_or_stalled_paths_are_path_errors(tmp_path):
    """A non-UTF-8 file raised UnicodeDecodeError; a duration lost in the time sum's rounding
    (1e-17 s after 1 s) raised in scipy's Slerp (times not strictly increasing)."""
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe")
    with pytest.raises(PathError, match="not a YAML text file"):
        load_path(str(binary))
    stalled = tmp_path / "stalled.yaml"
    stalled.write_text("- {offset: [0.1, 0, 0], duration: 1.0}\n"
                       "- {offset: [0.2, 0, 0], duration: 1.0e-17}\n")
    with pytest.raises(PathError, match="waypoint 1: duration 1e-17 s too short"):
        ScriptedPath(load_path(str(stalled)))


def test_a_task_name_pik_node_cannot_have_is_refused(capsys):
    """It raised rclpy's invalid topic name deep in the publisher's creation."""
    assert teleop_main(["teleop", "--task", "a/../b"]) == 2
    assert "--task 'a/../b' is not a task name" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["circle", "reach_limits"])
def test_builtin_paths_are_valid_and_return_to_the_start(name):
    assert name in builtin_path_names()
    path = ScriptedPath(load_path(name))
    offset, rotation = path.sample(path.duration)
    np.testing.assert_allclose(offset, 0.0, atol=1e-12)
    assert rotation.magnitude() < 1e-12
    if name == "reach_limits":
        assert 15.0 <= path.duration <= 25.0


def test_interpolation_hits_the_waypoints_at_their_times():
    waypoints = parse_path(yaml.safe_load("""
        - {offset: [0.1, 0.0, 0.0], duration: 1.0}
        - {offset: [0.1, 0.2, 0.0], rpy: [0.0, 0.0, 0.8], duration: 0.5}
        - {offset: [0.0, 0.0, -0.3], rpy: [0.4, -0.3, 0.0], duration: 2.0}
    """))
    path = ScriptedPath(waypoints)
    assert path.duration == pytest.approx(3.5)
    np.testing.assert_allclose(path.arrival_times, [1.0, 1.5, 3.5])
    offset, rotation = path.sample(0.0)
    np.testing.assert_allclose(offset, 0.0)
    assert rotation.magnitude() < 1e-12
    for index, (waypoint, time_s) in enumerate(zip(waypoints, path.arrival_times)):
        offset, rotation = path.sample(time_s)
        np.testing.assert_allclose(offset, waypoint.offset, atol=1e-12)
        assert (rotation * waypoint.rotation.inv()).magnitude() < 1e-9
        assert path.waypoints_reached(time_s) == index + 1
    np.testing.assert_allclose(path.sample(1.25)[0], [0.1, 0.1, 0.0])  # linear
    np.testing.assert_allclose(path.sample(99.0)[0], waypoints[-1].offset)  # clamped
    assert path.waypoints_reached(0.99) == 0


def test_slerp_keeps_unit_quaternions_on_the_great_arc():
    waypoints = parse_path([{"offset": [0, 0, 0], "rpy": [0.0, 0.0, 1.0], "duration": 1.0},
                            {"offset": [0, 0, 0], "rpy": [1.2, -0.7, 2.0], "duration": 2.0}])
    path = ScriptedPath(waypoints)
    np.testing.assert_allclose(path.sample(0.5)[1].as_rotvec(), [0.0, 0.0, 0.5], atol=1e-12)
    for time_s in np.linspace(0.0, path.duration, 57):
        rotation = path.sample(time_s)[1]
        assert np.linalg.norm(rotation.as_quat()) == pytest.approx(1.0, abs=1e-12)
        target = START.moved(*path.sample(time_s))
        assert np.linalg.norm(target.rotation.as_quat()) == pytest.approx(1.0, abs=1e-12)
    # Within the second segment the rotation advances at a constant rate between its ends.
    first, second = waypoints[0].rotation, waypoints[1].rotation
    total_angle = (second * first.inv()).magnitude()
    quarter = path.sample(1.5)[1]
    assert (quarter * first.inv()).magnitude() == pytest.approx(total_angle / 4, abs=1e-9)
    assert (second * quarter.inv()).magnitude() == pytest.approx(3 * total_angle / 4, abs=1e-9)


# --- Keys ---------------------------------------------------------------------------------------

def test_every_key_has_one_meaning():
    keys = [*TRANSLATION_KEYS, *ROTATION_KEYS, *QUIT_KEYS, "+", "-", "r"]
    assert len(keys) == len(set(keys))


@pytest.mark.parametrize("key", sorted(TRANSLATION_KEYS))
def test_translation_key_moves_one_step_along_a_world_axis(key):
    teleop = KeyboardTeleop(START, step=0.02, angle_step=0.1)
    assert teleop.press(key)
    axis, sign = TRANSLATION_KEYS[key]
    target = teleop.target()
    np.testing.assert_allclose(target.position - START.position, sign * 0.02 * np.eye(3)[axis])
    assert (target.rotation * START.rotation.inv()).magnitude() < 1e-12


@pytest.mark.parametrize("key", sorted(ROTATION_KEYS))
def test_rotation_key_turns_one_step_about_a_world_axis(key):
    teleop = KeyboardTeleop(START, step=0.02, angle_step=0.1)
    assert teleop.press(key)
    axis, sign = ROTATION_KEYS[key]
    target = teleop.target()
    np.testing.assert_allclose(target.position, START.position)
    world_rotation = target.rotation * START.rotation.inv()
    np.testing.assert_allclose(world_rotation.as_rotvec(), sign * 0.1 * np.eye(3)[axis],
                               atol=1e-12)


def test_com_teleop_ignores_rotation_keys_and_steps_scale_and_reset():
    teleop = KeyboardTeleop(START, step=0.01, angle_step=0.05, translation_only=True)
    assert not teleop.press("i")
    assert (teleop.target().rotation * START.rotation.inv()).magnitude() < 1e-12
    assert "rot" not in teleop.status_line()
    assert not teleop.press("+")
    assert teleop.step == pytest.approx(0.02) and teleop.angle_step == pytest.approx(0.1)
    teleop.press("w")
    teleop.press("-")
    teleop.press("q")
    np.testing.assert_allclose(teleop.target().position - START.position, [0.02, 0.0, 0.01])
    assert teleop.status_line() == "xyz +0.020 +0.000 +0.010 m | step 0.01 m"
    assert teleop.press("r")
    np.testing.assert_allclose(teleop.target().position, START.position)


class RecordingLink:
    """Stands in for TargetLink: records the published targets."""

    def __init__(self):
        self.targets = []

    def publish(self, target):
        self.targets.append(target)


def test_keyboard_loop_on_a_terminal_publishes_keys_and_restores_it():
    controller, terminal = os.openpty()
    try:
        saved = termios.tcgetattr(terminal)
        link = RecordingLink()
        out = io.StringIO()
        loop = threading.Thread(target=run_keyboard, args=(
            link, KeyboardTeleop(START, 0.01, 0.05), 1000.0, terminal, out))
        loop.start()
        wait_until(lambda: link.targets, 2.0, what="the initial target")
        assert not termios.tcgetattr(terminal)[3] & (termios.ICANON | termios.ECHO)
        os.write(controller, b"ww\x1b[Ad")  # the arrow key's escape sequence is ignored
        wait_until(lambda: np.allclose(link.targets[-1].position - START.position,
                                       [0.02, -0.01, 0.0]), 2.0, what="three moves")
        os.write(controller, b"\x03")
        loop.join(2.0)
        assert not loop.is_alive()
        assert termios.tcgetattr(terminal) == saved
        assert "xyz +0.020 -0.010 +0.000 m | rot +0.000 +0.000 +0.000 rad" in out.getvalue()
        assert len(link.targets) > 10  # republished at the rate between keys
    finally:
        os.close(controller)
        os.close(terminal)


# --- Over DDS -----------------------------------------------------------------------------------

class FakePik(BackgroundNode):
    """Stands in for pik_node: publishes /pik/status at 20 Hz listing `tasks` (name ->
    (target Pose, target message type)) and records what arrives on their target topics."""

    def __init__(self, tasks):
        super().__init__("fake_pik_node")
        self.received = {name: [] for name in tasks}
        status = SolverStatus(tasks=[TaskStatus(name=name, target=pose, current=pose)
                                     for name, (pose, _) in tasks.items()])
        publisher = self.node.create_publisher(SolverStatus, "/pik/status", RELIABLE)
        self.node.create_timer(0.05, lambda: publisher.publish(status))
        for name, (_, message_type) in tasks.items():
            self.node.create_subscription(message_type, f"/pik/tasks/{name}/target",
                                          self.received[name].append, RELIABLE)
        self.start_spinning()

    def targets(self, name, settle=0.2):
        """The targets received so far on a task's topic, after settle s for stragglers."""
        time.sleep(settle)
        return list(self.received[name])


def pose_msg(target):
    x, y, z, w = target.rotation.as_quat()
    return Pose(position=Point(x=target.position[0], y=target.position[1], z=target.position[2]),
                orientation=Quaternion(x=x, y=y, z=z, w=w))


COM_START = np.array([0.0, 0.0, 0.88])


@pytest.fixture(scope="module")
def fake_pik():
    """left_foot, com (PointStamped targets) and right_hand (PoseStamped targets)."""
    fake = FakePik({
        "left_foot": (Pose(), PoseStamped),
        "com": (pose_msg(Target(COM_START, Rotation.identity())), PointStamped),
        "right_hand": (pose_msg(START), PoseStamped),
    })
    yield fake
    fake.close()


def run_teleop(processes, *args, timeout=15.0):
    proc = processes.start("stance", "teleop", *args, name="teleop")
    wait_until(lambda: proc.poll() is not None, timeout, what="stance teleop to exit")
    return proc.returncode, proc.log_path.read_text()


def test_scripted_path_drives_the_target_topic(processes, fake_pik, tmp_path):
    path_file = tmp_path / "square.yaml"
    path_file.write_text("""
        - {offset: [0.1, 0.0, 0.0], duration: 0.4}
        - {offset: [0.1, 0.1, 0.0], rpy: [0.0, 0.0, 0.5], duration: 0.4}
        - {offset: [0.0, 0.0, 0.0], duration: 0.4}
    """)
    code, log = run_teleop(processes, "--task", "right_hand", "--path", str(path_file),
                           "--rate", "50")
    assert code == 0, log
    assert "loop 1/1  waypoint 3/3" in log
    messages = fake_pik.targets("right_hand")
    assert len(messages) >= 55, log  # 1.2 s at 50 Hz: 61 targets
    assert {message.header.frame_id for message in messages} == {"world"}
    positions = np.array([[m.pose.position.x, m.pose.position.y, m.pose.position.z]
                          for m in messages])
    rotations = Rotation.from_quat([[m.pose.orientation.x, m.pose.orientation.y,
                                     m.pose.orientation.z, m.pose.orientation.w]
                                    for m in messages])
    offsets = positions - START.position
    turns = (rotations * START.rotation.inv()).as_rotvec()
    np.testing.assert_allclose(offsets[0], 0.0, atol=1e-9)
    assert np.max(offsets[:, 0]) == pytest.approx(0.1, abs=1e-6)
    corner = np.argmax(offsets[:, 1])
    np.testing.assert_allclose(offsets[corner], [0.1, 0.1, 0.0], atol=1e-6)
    np.testing.assert_allclose(turns[corner], [0.0, 0.0, 0.5], atol=1e-6)
    np.testing.assert_allclose(offsets[-1], 0.0, atol=1e-9)
    np.testing.assert_allclose(turns[-1], 0.0, atol=1e-9)
    assert np.all(np.abs(np.diff(offsets, axis=0)) <= 0.1 / 20 + 1e-9)  # no jumps


def test_com_task_gets_points_and_ignores_rotations(processes, fake_pik, tmp_path):
    path_file = tmp_path / "sway.yaml"
    path_file.write_text("""
        - {offset: [0.0, 0.05, 0.0], rpy: [0.0, 0.0, 1.0], duration: 0.3}
        - {offset: [0.0, 0.0, 0.0], duration: 0.3}
    """)
    code, log = run_teleop(processes, "--task", "com", "--path", str(path_file))
    assert code == 0, log
    assert "rotations are ignored" in log
    points = np.array([[m.point.x, m.point.y, m.point.z] for m in fake_pik.targets("com")])
    np.testing.assert_allclose(points[0], COM_START, atol=1e-9)
    assert np.max(points[:, 1]) == pytest.approx(0.05, abs=1e-6)
    np.testing.assert_allclose(points[-1], COM_START, atol=1e-9)


def test_missing_task_is_reported_with_the_tasks_seen(processes, fake_pik):
    code, log = run_teleop(processes, "--task", "left_hand", "--path", "circle",
                           "--timeout", "5")  # > DDS discovery
    assert code == 1, log
    assert "no task 'left_hand'" in log and "tasks seen: com, left_foot, right_hand" in log
