"""`stance teleop`: move one pik_node task's target from the keyboard or along a scripted path.

The target starts at the task's current target, read from the first /pik/status message that
lists the task. It then moves in the world frame: offsets in meters along the world axes,
rotations in radians about world axes through the frame's origin (R = R_offset R_start).
Targets go to /pik/tasks/<task>/target with the message type pik_node subscribes with:
PoseStamped (pose, position and orientation tasks) or PointStamped (com tasks, translation
only). Posture tasks (JointState targets) are not supported.

A scripted path is a YAML list of waypoints relative to the starting target, reached one
after the other:

    - {offset: [dx, dy, dz], rpy: [roll, pitch, yaw], duration: s}   # rpy optional

rpy are extrinsic rotations about world x, y, z (rad); positions are interpolated linearly and
orientations by slerp (each segment turns the short way). Built-in paths: reach_limits
(Talos right hand, task right_hand, driven into its joint limits, ~20 s) and circle.
"""

# Layout: pure logic first (paths, interpolation, key map: no node needed), then the ROS side
# (TargetLink), then the two modes and the command.

from __future__ import annotations

import argparse
import math
import os
import select
import signal
import sys
import termios
import time
from contextlib import contextmanager
from dataclasses import dataclass
from importlib import resources

import numpy as np
import rclpy
import yaml
from geometry_msgs.msg import PointStamped, PoseStamped
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from scipy.spatial.transform import Rotation, Slerp
from stance.stack import MAX_NAME_LENGTH, NAME_PATTERN
from stance.tasks import MAX_COORDINATE
from stance.yaml_file import load_yaml
from stance_msgs.msg import SolverStatus

from .cli import positive

WORLD_FRAME = "world"
STATUS_TOPIC = "/pik/status"
PATHS_PACKAGE_DIR = "paths"
STEP_SCALE = 2.0  # factor applied to both steps by '+' and '-'
KEYBOARD_RATE = 20.0  # Hz, default republish rate of the keyboard mode
SCRIPTED_RATE = 50.0  # Hz, default publish rate of the scripted mode
MAX_RATE = 2000.0  # Hz: pik_node's highest rate; faster targets would never be used
FLUSH_TIMEOUT = 5.0  # s, wait for pik_node to acknowledge the last targets before exiting
# (Fast DDS acknowledges on its next heartbeat, every 3 s by default)
AXIS_NAMES = "xyz"


class PathError(ValueError):
    """A scripted path is malformed; the message names the file, waypoint and field."""


class TeleopError(RuntimeError):
    """pik_node or the task is not there, or the task cannot be teleoperated."""


# --- Pure logic: targets, paths, keys ---------------------------------------------------------

@dataclass(frozen=True)
class Target:
    """A task target in the world frame: position (m) and orientation."""

    position: np.ndarray  # (3,) m
    rotation: Rotation

    def moved(self, offset, rotation_offset: Rotation) -> Target:
        """Translated by offset (m, world axes), rotated by rotation_offset about world axes."""
        return Target(self.position + np.asarray(offset, dtype=float),
                      rotation_offset * self.rotation)


@dataclass(frozen=True)
class Waypoint:
    """A pose relative to the starting target, reached `duration` s after the previous one."""

    offset: np.ndarray  # (3,) m, world axes
    rotation: Rotation  # about world axes
    duration: float     # s, > 0


WAYPOINT_FIELDS = ("offset", "rpy", "duration")


def _is_number(value) -> bool:
    """An int or float of magnitude at most MAX_COORDINATE (1e6: m, rad or s); YAML
    booleans are not numbers here."""
    return (isinstance(value, (int, float)) and not isinstance(value, bool)
            and abs(value) <= MAX_COORDINATE)


def _vector3(value, where: str, unit: str) -> np.ndarray:
    if not isinstance(value, (list, tuple)) or len(value) != 3 or not all(map(_is_number, value)):
        raise PathError(f"{where}: must be a list of 3 finite numbers ({unit}), each at most "
                        f"{MAX_COORDINATE:g} in magnitude, got {value!r}")
    return np.array(value, dtype=float)


def parse_path(data, source: str = "path") -> list:
    """Waypoints from the loaded YAML document; PathError names the offending field."""
    if not isinstance(data, list) or not data:
        raise PathError(f"{source}: must be a non-empty list of waypoints, got {data!r}")
    waypoints = []
    for index, entry in enumerate(data):
        where = f"{source}: waypoint {index}"
        if not isinstance(entry, dict):
            raise PathError(f"{where}: must be a mapping with {', '.join(WAYPOINT_FIELDS)}, "
                            f"got {entry!r}")
        unknown = sorted(set(entry) - set(WAYPOINT_FIELDS), key=str)
        if unknown:
            raise PathError(f"{where}: unknown field {unknown[0]!r} "
                            f"(expected {', '.join(WAYPOINT_FIELDS)})")
        for required in ("offset", "duration"):
            if required not in entry:
                raise PathError(f"{where}: missing field {required!r}")
        duration = entry["duration"]
        if not _is_number(duration) or duration <= 0:
            raise PathError(f"{where}.duration: must be a number > 0 (s), at most "
                            f"{MAX_COORDINATE:g}, got {duration!r}")
        offset = _vector3(entry["offset"], f"{where}.offset", "m")
        rpy = _vector3(entry.get("rpy", [0.0, 0.0, 0.0]), f"{where}.rpy", "rad")
        waypoints.append(Waypoint(offset, Rotation.from_euler("xyz", rpy), float(duration)))
    return waypoints


def builtin_path_names() -> list:
    folder = resources.files(__package__) / PATHS_PACKAGE_DIR
    return sorted(item.name[:-len(".yaml")] for item in folder.iterdir()
                  if item.name.endswith(".yaml"))


def load_path(spec: str) -> list:
    """Waypoints of a built-in path name (e.g. reach_limits) or of a YAML file."""
    if os.path.sep in spec or spec.endswith((".yaml", ".yml")):
        source = spec
        try:
            with open(spec, encoding="utf-8") as path_file:
                text = path_file.read()
        except OSError as error:
            raise PathError(f"{spec}: cannot read: {error.strerror}") from None
        except UnicodeDecodeError as error:
            raise PathError(f"{spec}: not a YAML text file (not UTF-8: byte "
                            f"{error.start})") from None
    else:
        names = builtin_path_names()
        if spec not in names:
            raise PathError(f"unknown built-in path {spec!r} (built-in: {', '.join(names)}; "
                            f"or give a .yaml file)")
        source = f"{spec}.yaml"
        text = (resources.files(__package__) / PATHS_PACKAGE_DIR / source).read_text()
    try:
        data = load_yaml(text)
    except yaml.YAMLError as error:
        raise PathError(f"{source}: invalid YAML: {error}") from None
    return parse_path(data, source)


class ScriptedPath:
    """Offsets along waypoints over time: linear in position, slerp in orientation.

    Time 0 is the starting target (zero offset); waypoint i is reached at arrival_times[i] s.
    """

    def __init__(self, waypoints: list):
        self.waypoints = waypoints
        self.arrival_times = np.cumsum([waypoint.duration for waypoint in waypoints])
        self._times = np.concatenate([[0.0], self.arrival_times])
        stalled = np.flatnonzero(np.diff(self._times) <= 0.0)
        if len(stalled):     # a duration lost in the sum's rounding (1e-17 after 1 s)
            raise PathError(f"waypoint {stalled[0]}: duration "
                            f"{waypoints[stalled[0]].duration:g} s too short to advance the "
                            f"time after {self._times[stalled[0]]:g} s")
        self._offsets = np.vstack([np.zeros(3)] + [waypoint.offset for waypoint in waypoints])
        self._slerp = Slerp(self._times, Rotation.concatenate(
            [Rotation.identity()] + [waypoint.rotation for waypoint in waypoints]))

    @property
    def duration(self) -> float:
        """s from the start to the last waypoint."""
        return float(self._times[-1])

    def sample(self, t: float):
        """(offset m, rotation offset) at t s, clamped to [0, duration]."""
        t = min(max(t, 0.0), self.duration)
        offset = np.array([np.interp(t, self._times, self._offsets[:, axis]) for axis in range(3)])
        return offset, self._slerp(t)

    def waypoints_reached(self, t: float) -> int:
        """How many waypoints have been reached at t s (1 ns early counts: sample times are
        sums of floating-point periods)."""
        return int(np.searchsorted(self.arrival_times, t + 1e-9, side="right"))


# Key pairs (+, -) per world axis x, y, z: translation by the linear step, rotation by the
# angular step.
TRANSLATION_KEY_PAIRS = ("ws", "ad", "qe")
ROTATION_KEY_PAIRS = ("ik", "jl", "uo")
QUIT_KEYS = ("\x03", "\x1b")  # Ctrl-C, Esc


def _axis_signs(pairs) -> dict:
    """Key -> (world axis index, sign)."""
    return {key: (axis, sign) for axis, pair in enumerate(pairs)
            for key, sign in zip(pair, (+1, -1))}


TRANSLATION_KEYS = _axis_signs(TRANSLATION_KEY_PAIRS)
ROTATION_KEYS = _axis_signs(ROTATION_KEY_PAIRS)


def key_map_text(translation_only: bool) -> str:
    """The key map printed at start."""
    def describe(pairs):
        return "   ".join(f"{plus}/{minus} {AXIS_NAMES[axis]}+/-"
                          for axis, (plus, minus) in enumerate(pairs))
    lines = [f"translate along world axes: {describe(TRANSLATION_KEY_PAIRS)}"]
    if not translation_only:
        lines.append(f"rotate about world axes:    {describe(ROTATION_KEY_PAIRS)}")
    lines.append(f"+/- scale steps x{STEP_SCALE:g}   r reset to start   Esc/Ctrl-C quit")
    return "\n".join(lines)


class KeyboardTeleop:
    """Keyboard mode state: the offset from the starting target, changed one key at a time.

    step: translation per key (m); angle_step: rotation per key (rad).
    translation_only: rotation keys are ignored (com tasks).
    """

    def __init__(self, start: Target, step: float, angle_step: float,
                 translation_only: bool = False):
        self.start = start
        self.step = step
        self.angle_step = angle_step
        self.translation_only = translation_only
        self.reset()

    def reset(self) -> None:
        self.offset = np.zeros(3)
        self.rotation_offset = Rotation.identity()

    def press(self, key: str) -> bool:
        """Apply one key; True when the target changed."""
        if key in TRANSLATION_KEYS:
            axis, sign = TRANSLATION_KEYS[key]
            self.offset[axis] += sign * self.step
        elif key in ROTATION_KEYS and not self.translation_only:
            axis, sign = ROTATION_KEYS[key]
            self.rotation_offset = (Rotation.from_rotvec(sign * self.angle_step * np.eye(3)[axis])
                                    * self.rotation_offset)
        elif key == "r":
            self.reset()
        elif key in ("+", "-"):
            factor = STEP_SCALE if key == "+" else 1.0 / STEP_SCALE
            self.step *= factor
            self.angle_step *= factor
            return False
        else:
            return False
        return True

    def target(self) -> Target:
        return self.start.moved(self.offset, self.rotation_offset)

    def status_line(self) -> str:
        """Offset from the start along world x y z (m), rotation offset as a world rotation
        vector (rad), and the current steps."""
        def xyz(vector):
            return " ".join(f"{value:+.3f}" for value in vector)
        if self.translation_only:
            return f"xyz {xyz(self.offset)} m | step {self.step:.3g} m"
        return (f"xyz {xyz(self.offset)} m | rot {xyz(self.rotation_offset.as_rotvec())} rad"
                f" | step {self.step:.3g} m {self.angle_step:.3g} rad")


# --- ROS side -----------------------------------------------------------------------------------

TARGET_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
STATUS_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                        reliability=ReliabilityPolicy.RELIABLE)
TARGET_TYPES = {"geometry_msgs/msg/PoseStamped": PoseStamped,
                "geometry_msgs/msg/PointStamped": PointStamped}


def target_from_pose_msg(pose) -> Target:
    """Target from a geometry_msgs/Pose; a zero quaternion (com status) reads as identity."""
    quaternion = np.array([pose.orientation.x, pose.orientation.y, pose.orientation.z,
                           pose.orientation.w])
    rotation = (Rotation.from_quat(quaternion) if np.linalg.norm(quaternion) > 1e-9
                else Rotation.identity())
    return Target(np.array([pose.position.x, pose.position.y, pose.position.z]), rotation)


class TargetLink:
    """pik_node as seen by teleop: the task's starting target and its target publisher."""

    def __init__(self, node, task: str, timeout: float):
        """Wait up to timeout s for /pik/status to list the task and for a subscriber of the
        task's target topic (its type tells pose from com); TeleopError otherwise."""
        self.node = node
        self.topic = f"/pik/tasks/{task}/target"
        self.start, self.message_type = self._wait_for_task(task, timeout)
        self.publisher = node.create_publisher(self.message_type, self.topic, TARGET_QOS)
        deadline = time.monotonic() + timeout
        while self.publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.01)

    @property
    def translation_only(self) -> bool:
        return self.message_type is PointStamped

    def _wait_for_task(self, task: str, timeout: float):
        start = None
        names_seen = set()

        def on_status(status):
            nonlocal start
            for task_status in status.tasks:
                names_seen.add(task_status.name)
                if task_status.name == task and start is None:
                    start = target_from_pose_msg(task_status.target)

        subscription = self.node.create_subscription(SolverStatus, STATUS_TOPIC, on_status,
                                                     STATUS_QOS)
        deadline = time.monotonic() + timeout
        type_names = []
        try:
            while time.monotonic() < deadline and not (start is not None and type_names):
                rclpy.spin_once(self.node, timeout_sec=0.02)
                type_names = sorted({info.topic_type for info in
                                     self.node.get_subscriptions_info_by_topic(self.topic)})
        finally:
            self.node.destroy_subscription(subscription)
        if not names_seen:
            raise TeleopError(f"no {STATUS_TOPIC} message within {timeout:g} s: is pik_node "
                              f"running (ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')})?")
        if start is None:
            raise TeleopError(f"no task {task!r} in pik_node's stack within {timeout:g} s "
                              f"(tasks seen: {', '.join(sorted(names_seen))})")
        if not type_names:
            raise TeleopError(f"nobody subscribes to {self.topic} within {timeout:g} s, so its "
                              f"message type is unknown")
        if len(type_names) > 1 or type_names[0] not in TARGET_TYPES:
            raise TeleopError(f"{self.topic} takes {', '.join(type_names)}: teleop moves pose, "
                              f"position, orientation and com targets only")
        return start, TARGET_TYPES[type_names[0]]

    def publish(self, target: Target) -> None:
        """One target message, stamped now, in the world frame."""
        message = self.message_type()
        message.header.frame_id = WORLD_FRAME
        message.header.stamp = self.node.get_clock().now().to_msg()
        x, y, z = (float(value) for value in target.position)
        if self.message_type is PointStamped:
            message.point.x, message.point.y, message.point.z = x, y, z
        else:
            pose = message.pose
            pose.position.x, pose.position.y, pose.position.z = x, y, z
            (pose.orientation.x, pose.orientation.y, pose.orientation.z,
             pose.orientation.w) = (float(value) for value in target.rotation.as_quat())
        self.publisher.publish(message)

    def flush(self, timeout: float) -> bool:
        """Wait up to timeout s until every subscriber acknowledged the targets published, so
        the last one is not lost when teleop exits right after it; False on timeout."""
        return self.publisher.wait_for_all_acked(Duration(seconds=timeout))


# --- Modes ----------------------------------------------------------------------------------------

def run_path(link: TargetLink, path: ScriptedPath, loops: int, rate: float, out) -> None:
    """Publish the path's targets at rate Hz, loops times over, printing each waypoint reached."""
    if link.translation_only and any(waypoint.rotation.magnitude() > 0
                                     for waypoint in path.waypoints):
        print("note: com task, the path's rotations are ignored", file=out)
    total = loops * path.duration
    count = len(path.waypoints)
    print(f"path: {count} waypoints, {path.duration:.2f} s x {loops} loop(s) at {rate:g} Hz",
          file=out, flush=True)
    period = 1.0 / rate
    start_time = time.monotonic()
    tick = 0
    reported = (0, 0)
    while True:
        t = min(tick * period, total)
        delay = start_time + t - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        loop = max(0, math.ceil(t / path.duration) - 1)  # a loop's end belongs to it
        local_time = t - loop * path.duration
        offset, rotation = path.sample(local_time)
        link.publish(link.start.moved(offset, rotation))
        reached = path.waypoints_reached(local_time)
        if reached and (loop, reached) > reported:
            reported = (loop, reached)
            x, y, z = path.waypoints[reached - 1].offset
            print(f"loop {loop + 1}/{loops}  waypoint {reached}/{count}  at {t:6.2f} s  "
                  f"offset x {x:+.3f} y {y:+.3f} z {z:+.3f} m", file=out, flush=True)
        if t >= total:
            break
        tick += 1
    print(f"done: {tick + 1} targets published", file=out, flush=True)


@contextmanager
def raw_terminal(fd: int):
    """Keys arrive one by one, unechoed, Ctrl-C as a byte; the settings are always restored."""
    saved = termios.tcgetattr(fd)
    mode = termios.tcgetattr(fd)
    mode[3] &= ~(termios.ICANON | termios.ECHO | termios.ISIG)
    mode[6][termios.VMIN] = 1
    mode[6][termios.VTIME] = 0
    termios.tcsetattr(fd, termios.TCSAFLUSH, mode)
    try:
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSAFLUSH, saved)


def read_key(fd: int) -> str:
    """One key press; escape sequences (arrows, function keys, Alt+key) read as ''."""
    key = os.read(fd, 1)
    if key != b"\x1b" or not select.select([fd], [], [], 0.02)[0]:
        return key.decode(errors="replace")
    if os.read(fd, 1) in (b"[", b"O"):  # CSI / SS3: parameter bytes, then a final 0x40-0x7e
        while not 0x40 <= os.read(fd, 1)[0] <= 0x7E:
            pass
    return ""


def run_keyboard(link: TargetLink, teleop: KeyboardTeleop, rate: float, fd: int, out) -> None:
    """Publish on every key that moves the target and republish every 1/rate s until quit."""
    print(key_map_text(teleop.translation_only), file=out)
    period = 1.0 / rate
    with raw_terminal(fd):
        try:
            print(f"\r{teleop.status_line()}\x1b[K", end="", file=out, flush=True)
            while True:
                link.publish(teleop.target())
                next_publish = time.monotonic() + period
                while select.select([fd], [], [], max(0.0, next_publish - time.monotonic()))[0]:
                    key = read_key(fd)
                    if key in QUIT_KEYS:
                        return
                    moved = teleop.press(key)
                    print(f"\r{teleop.status_line()}\x1b[K", end="", file=out, flush=True)
                    if moved:
                        break
        finally:
            print(file=out)  # keep the status line


# --- Command ------------------------------------------------------------------------------------

def add_arguments(parser) -> None:
    parser.description = __doc__
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--task", required=True, help="task name in pik_node's stack")
    parser.add_argument("--path", metavar="NAME_OR_FILE",
                        help="scripted mode: a built-in path (reach_limits, circle, ...) or a "
                             "YAML file; default: keyboard mode")
    parser.add_argument("--loops", type=positive(int), default=1,
                        help="scripted mode: path repetitions")
    parser.add_argument("--rate", type=positive(float, most=MAX_RATE),
                        help=f"publish rate, Hz (default {SCRIPTED_RATE:g} scripted, "
                             f"{KEYBOARD_RATE:g} keyboard republish)")
    parser.add_argument("--step", type=positive(float), default=0.01,
                        help="keyboard translation step, m")
    parser.add_argument("--angle-step", type=positive(float), default=0.05,
                        help="keyboard rotation step, rad")
    parser.add_argument("--timeout", type=positive(float), default=10.0,
                        help="s to wait for pik_node's status and the task")


def run(args) -> int:
    if not NAME_PATTERN.fullmatch(args.task) or len(args.task) > MAX_NAME_LENGTH:
        print(f"stance teleop: --task {args.task!r} is not a task name (pik_node's names "
              f"match {NAME_PATTERN.pattern}, at most {MAX_NAME_LENGTH} characters)",
              file=sys.stderr)
        return 2
    try:
        path = ScriptedPath(load_path(args.path)) if args.path else None
    except PathError as error:
        print(f"stance teleop: {error}", file=sys.stderr)
        return 2
    if path is None and not sys.stdin.isatty():
        print("stance teleop: keyboard mode needs a terminal on stdin (or use --path)",
              file=sys.stderr)
        return 2
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("stance_teleop")
    try:
        link = TargetLink(node, args.task, args.timeout)
        if path is not None:
            run_path(link, path, args.loops, args.rate or SCRIPTED_RATE, sys.stdout)
        else:
            teleop = KeyboardTeleop(link.start, args.step, args.angle_step,
                                    link.translation_only)
            run_keyboard(link, teleop, args.rate or KEYBOARD_RATE, sys.stdin.fileno(),
                         sys.stdout)
        if not link.flush(FLUSH_TIMEOUT):
            print(f"stance teleop: the last targets were not acknowledged within "
                  f"{FLUSH_TIMEOUT:g} s; pik_node may not have received them", file=sys.stderr)
            return 1
        return 0
    except TeleopError as error:
        print(f"stance teleop: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
