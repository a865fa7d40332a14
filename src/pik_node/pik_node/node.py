"""pik_node: prioritized IK with progressive clamping as a ROS 2 node.

Thin adapter over stance.PIKSolver. A control thread paced by deadlines (not an executor
timer, whose wake-up overhead would sit inside the loop) runs one IK step per period from
the current configuration and publishes it; the executor thread only serves inputs, and a
lock keeps the two consistent. Targets arrive per task on /pik/tasks/<name>/target; the
stack is replaced atomically through /pik/set_stack. Bad input is answered (service
response, /pik/status.last_rejection, log) and never changes the node's state.

Topics and services (QoS in parentheses; the per-step outputs keep 1000 samples, 2 s at
500 Hz, so that a stalled reliable reader is repaired: see STREAM):
  sub  /pik/tasks/<name>/target   PoseStamped | PointStamped (com) | JointState (posture)
                                  | PolygonStamped (support) (reliable, keep last 10)
  pub  /joint_states              sensor_msgs/JointState, actuated joints (reliable, 1000)
  pub  /pik/base_pose             geometry_msgs/PoseStamped, free-flyer in world
                                  (reliable, 1000)
  pub  /pik/status                stance_msgs/SolverStatus, one per step (reliable, 1000)
  pub  /robot_description         std_msgs/String, URDF (reliable, transient local)
  srv  /pik/set_stack             stance_msgs/SetStack (a stack with no enabled task is
                                  taken, its response ends with a warning)
  srv  /pik/set_task_enabled      stance_msgs/SetTaskEnabled (same warning)
  srv  /pik/set_configuration     stance_msgs/SetConfiguration: jump to a configuration
                                  (base pose, joints inside their limits); every task
                                  then holds its value there, and the solver steps on
                                  as a fresh one (no kept QP start)
Positions (targets, base pose) are bounded by conversions.MAX_POSITION (1e6 m); no state
that is not finite is committed (an IK step that gives one is discarded and reported).
The strategy parameter can be set at run time (`stance param set /pik_node strategy
clamping`, or ros2 param set).
"""

from __future__ import annotations

import gc
import re
import signal
import sys
import threading
import time

import numpy as np
import pinocchio as pin
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped, PolygonStamped, PoseStamped
from rcl_interfaces.msg import (FloatingPointRange, ParameterDescriptor,
                                SetParametersResult)
from rclpy.exceptions import InvalidParameterTypeException, ParameterException
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.signals import SignalHandlerOptions
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from stance import PIKSolver, Robot, RobotModelError, StackError, TargetError
from stance.limits import STRATEGIES
from stance.pik import HIERARCHIES, LM_DAMPING, demo_stack_file
from stance.stack import parse_stack_yaml, short_repr
from stance.swing import LimitFileError, limit_file_path, load_limit_file
from stance_msgs.msg import LevelStatus, SolverStatus, TaskStatus
from stance_msgs.srv import SetConfiguration, SetStack, SetTaskEnabled
from std_msgs.msg import Header, String

from .conversions import (check_stamp, check_task_frames, check_within_limits,
                          check_world_frame, configuration_from_msg, joint_targets_from_msg,
                          point_from_msg, polygon_from_msg, se3_from_pose_msg,
                          spec_from_msg)

RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# The per-step outputs: two seconds of history at 500 Hz. A reliable reader whose process
# is stalled (a recorder on a loaded machine) gets what it missed repaired from the
# writer's history: at depth 10, 0.6 s stalls lost about a hundred samples, at 500 one
# (under load). KEEP_LAST never blocks the publisher.
STREAM = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
MAX_REJECTION_LENGTH = 500   # characters of /pik/status.last_rejection
# A loop that missed more than BEHIND_FRACTION of its periods over a RATE_WINDOW s window
# says so in the log (sporadic misses on a loaded machine only count in the status)
RATE_WINDOW = 5.0
BEHIND_FRACTION = 0.1
TARGET_TYPES = {"pose": PoseStamped, "position": PoseStamped, "orientation": PoseStamped,
                "com": PointStamped, "posture": JointState, "support": PolygonStamped}


class PikNode(Node):
    def __init__(self, **kwargs):
        super().__init__("pik_node", **kwargs)
        self._declare_parameters()
        get = self.get_parameter
        self.robot = Robot.load(get("robot").value)
        self.q = self.robot.initial_configuration(get("initial_configuration").value or None)
        rate = get("rate").value
        # start-up errors name the parameter they come from (both are file names)
        limit_file = get("limits_file").value or self.robot.limit_file
        try:
            limit_file = limit_file_path(limit_file) if limit_file else None
            limit_models = load_limit_file(limit_file, self.robot) if limit_file else ()
        except (OSError, LimitFileError) as error:
            raise LimitFileError(f"limits_file: {_file_error(error)}") from None
        self.solver = PIKSolver(
            self.robot, strategy=get("strategy").value, damping=get("damping").value,
            lm_damping=get("lm_damping").value, activation=get("activation").value,
            dt=1.0 / rate if get("velocity_limits").value else None,
            hierarchy=get("hierarchy").value, limit_models=limit_models,
            locked_joints=self.get_parameter_or(
                "locked_joints", Parameter("locked_joints", Parameter.Type.STRING_ARRAY,
                                           [])).value)
        stack_file = get("stack_file").value or demo_stack_file(get("robot").value)
        if stack_file is None:
            raise StackError(f"no demo stack ships for robot {get('robot').value!r}: "
                             "set the stack_file parameter")
        try:
            with open(stack_file, encoding="utf-8") as stream:
                specs = parse_stack_yaml(stream.read(), self.robot.model.existFrame)
            check_task_frames(self.robot, specs)
        except (OSError, StackError, UnicodeDecodeError) as error:
            raise StackError(f"stack_file: {_file_error(error)}") from None
        self.solver.set_stack(specs, self.q)
        self.solver.warm_up(self.q)   # before any service or cycle: no first-step stall
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.rejected_inputs = 0
        self.last_rejection = ""
        self.last_input_stamp = Time()
        self.target_subscriptions = {}
        self.joint_state_pub = self.create_publisher(JointState, "/joint_states", STREAM)
        self.base_pose_pub = self.create_publisher(PoseStamped, "/pik/base_pose", STREAM)
        self.status_pub = self.create_publisher(SolverStatus, "/pik/status", STREAM)
        description_pub = self.create_publisher(String, "/robot_description", LATCHED)
        description_pub.publish(String(data=self.robot.urdf))
        self._description_pub = description_pub
        self.create_service(SetStack, "/pik/set_stack", self._on_set_stack)
        self.create_service(SetTaskEnabled, "/pik/set_task_enabled", self._on_set_enabled)
        self.create_service(SetConfiguration, "/pik/set_configuration",
                            self._on_set_configuration)
        self._sync_target_subscriptions()
        self._joint_names = [name for name, jid in zip(self.robot.actuated_joint_names,
                                                       self.robot.actuated_joint_ids)
                             if self.robot.model.joints[jid].nq == 1]
        self._joint_q_index = np.array([self.robot.model.joints[self.robot.joint_id(name)].idx_q
                                        for name in self._joint_names], dtype=int)
        self._lock = threading.Lock()
        self._period = 1.0 / rate
        self._stop = threading.Event()
        self._loop_thread = threading.Thread(target=self._run_loop, name="pik_loop",
                                             daemon=True)
        self.cycles = 0
        self.overruns = 0
        self.last_solve_time = 0.0    # s, the last IK step's
        self.discarded_steps = 0   # IK steps in a row whose configuration was not finite
        self._status_template = None
        self._hierarchy_name = get("hierarchy").value
        self._idle_warning()
        self.get_logger().info(
            f"robot {get('robot').value} (nv {self.robot.model.nv}), {len(self.solver.tasks)} "
            f"tasks, strategy {self.solver.strategy_name}, {rate:g} Hz"
            + (f", locked: {', '.join(self.solver.locked_joints)}"
               if self.solver.locked_joints else ""))
        self.get_logger().info(
            f"limit file: {limit_file or 'none (URDF bounds only)'}; stack file: {stack_file}")

    def _declare_parameters(self):
        def describe(text, read_only=True, **extra):
            return ParameterDescriptor(description=text, read_only=read_only, **extra)

        self.declare_parameter("robot", "talos", describe(
            "example-robot-data name, URDF path (free-flyer base) or mannequin"))
        self.declare_parameter("limits_file", "", describe(
            "YAML of swing and ball-and-socket joint limits (joint groups too), or a shipped "
            "file's name (talos, mannequin); empty = the robot's own, if any"))
        self.declare_parameter("initial_configuration", "", describe(
            "named reference configuration (SRDF); empty = half_sitting, standing or neutral, "
            "the first the robot has"))
        self.declare_parameter("stack_file", "", describe(
            "task stack YAML; empty = the robot's demo stack (talos, mannequin)"))
        self.declare_parameter("rate", 500.0, describe(
            "IK steps per second (Hz)",
            floating_point_range=[FloatingPointRange(from_value=1.0, to_value=2000.0)]))
        self.declare_parameter("strategy", "progressive", describe(
            f"joint limit strategy: {', '.join(STRATEGIES)}", read_only=False))
        self.declare_parameter("hierarchy", "svd", describe(
            f"prioritized solver: {', '.join(HIERARCHIES)} (qp: bounds as inequalities)"))
        self.declare_parameter("damping", 1e-3, describe(
            "damped least squares lambda once the targets are reached (> 0 unless "
            "lm_damping is 0)",
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1.0)]))
        self.declare_parameter("lm_damping", LM_DAMPING, describe(
            "Levenberg-Marquardt scale: lambda^2 = damping^2 + lm_damping |step targets|^2 "
            "(all tasks but posture), so targets out of reach do not make joints chatter",
            floating_point_range=[FloatingPointRange(from_value=0.0, to_value=1e4)]))
        self.declare_parameter("activation", 0.2, describe(
            "progressive clamping zone thickness next to each limit (rad)",
            floating_point_range=[FloatingPointRange(from_value=1e-3, to_value=1.0)]))
        self.declare_parameter("velocity_limits", True, describe(
            "scale each step so no joint exceeds its URDF velocity limit"))
        # a string array without a default (an empty list would be typed as bytes)
        self.declare_parameter("locked_joints", Parameter.Type.STRING_ARRAY, describe(
            "joints the IK never moves (e.g. grippers, which their own controllers "
            "command); unset: none"))

    def _on_set_parameters(self, parameters):
        """Every parameter checked before any is applied: an atomic set with one bad value
        changes nothing."""
        strategies = [parameter.value for parameter in parameters
                      if parameter.name == "strategy"]
        for strategy in strategies:
            if strategy not in STRATEGIES:
                reason = f"strategy must be one of {', '.join(STRATEGIES)}"
                self._reject(f"parameter strategy = {short_repr(strategy)} refused: {reason}")
                return SetParametersResult(successful=False, reason=reason)
        if strategies:
            with self._lock:
                self.solver.set_strategy(strategies[-1])
        return SetParametersResult(successful=True)

    # --- inputs -------------------------------------------------------------------------

    def _sync_target_subscriptions(self):
        """One target subscription per task, of the type its kind takes."""
        wanted = {name: TARGET_TYPES[task.spec.kind] for name, task in self.solver.tasks.items()}
        for name, (msg_type, subscription) in list(self.target_subscriptions.items()):
            if wanted.get(name) is not msg_type:
                self.destroy_subscription(subscription)
                del self.target_subscriptions[name]
        for name, msg_type in wanted.items():
            if name not in self.target_subscriptions:
                subscription = self.create_subscription(
                    msg_type, target_topic(name),
                    lambda msg, task_name=name: self._on_target(task_name, msg), RELIABLE)
                self.target_subscriptions[name] = (msg_type, subscription)

    def _on_target(self, name, msg):
        with self._lock:
            self._apply_target(name, msg)

    def _apply_target(self, name, msg):
        try:
            check_stamp(msg.header.stamp, "header.stamp")     # reported in /pik/status
            task = self.solver.task(name)
            kind = task.spec.kind
            if kind == "posture":
                if not msg.name:
                    raise TargetError("the JointState names no joint")
                joints = joint_targets_from_msg(msg.name, msg.position)
                check_within_limits(self.robot, joints)  # as /pik/set_configuration does
                task.set_joint_targets(self.robot, joints)
            elif kind == "com":
                check_world_frame(msg.header.frame_id)
                task.set_target(point_from_msg(msg.point))
            elif kind == "support":
                check_world_frame(msg.header.frame_id)
                task.set_target(polygon_from_msg(msg.polygon))
            else:
                check_world_frame(msg.header.frame_id)
                task.set_target(se3_from_pose_msg(msg.pose))
        except (TargetError, StackError) as error:
            self._reject(f"target of task {name!r} rejected: {error}")
            return
        self.last_input_stamp = msg.header.stamp

    def _on_set_stack(self, request, response):
        try:
            specs = [spec_from_msg(msg) for msg in request.tasks]
            check_task_frames(self.robot, specs)
            with self._lock:
                self.solver.set_stack(specs, self.q)
                self._status_template = None
        except (StackError, RobotModelError) as error:
            response.success, response.message = False, f"stack rejected: {error}"
            self._reject(response.message)
            return response
        self._sync_target_subscriptions()
        response.success = True
        response.message = f"stack of {len(specs)} tasks in force" + self._idle_warning()
        self.get_logger().info(response.message)
        return response

    def _on_set_enabled(self, request, response):
        try:
            with self._lock:
                self.solver.set_enabled(request.name, request.enabled)
                self._status_template = None
        except StackError as error:
            response.success, response.message = False, str(error)
            self._reject(response.message)
            return response
        response.success = True
        response.message = (f"task {request.name!r} "
                            f"{'enabled' if request.enabled else 'disabled'}"
                            + self._idle_warning())
        return response

    def _idle_warning(self) -> str:
        """A stack whose tasks are all disabled is allowed (the IK steps with no level and
        the robot stays put): '' if a task is enabled, else a warning, also logged."""
        if any(task.enabled for task in self.solver.tasks.values()):
            return ""
        warning = ("; warning: no task is enabled, nothing drives the robot until one is "
                   "(/pik/set_task_enabled)")
        self.get_logger().warning(warning[2:])
        return warning

    def _on_set_configuration(self, request, response):
        """Jump to the requested configuration and hold every task's value there (its
        target becomes its current value), all under the lock: one IK step sees either
        the old state or the new one. The solver forgets its kept starts: the next step is
        a fresh solver's from there."""
        try:
            with self._lock:
                q = configuration_from_msg(self.robot, self.q, request.base_pose,
                                           request.joints.name, request.joints.position)
                self.solver.compute_kinematics(q, com=True)
                if not (np.isfinite(q).all() and np.isfinite(self.robot.data.com[0]).all()):
                    raise TargetError("the configuration or its centre of mass is not finite")
                for task in self.solver.tasks.values():
                    task.hold(self.robot, q)
                self.solver.forget_starts()
                self.q = q
        except TargetError as error:
            response.success, response.message = False, f"configuration rejected: {error}"
            self._reject(response.message)
            return response
        response.success = True
        response.message = (f"configuration set ({len(request.joints.name)} joints named), "
                            f"{len(self.solver.tasks)} tasks hold their values")
        self.get_logger().info(response.message)
        return response

    def _reject(self, reason: str):
        """Count, keep (for /pik/status, at most MAX_REJECTION_LENGTH characters) and log
        a rejected input."""
        if len(reason) > MAX_REJECTION_LENGTH:
            reason = f"{reason[:MAX_REJECTION_LENGTH]}... ({len(reason)} characters)"
        self.rejected_inputs += 1
        self.last_rejection = reason
        self.get_logger().warning(reason)

    def _discard_step(self):
        """An IK step gave a non-finite configuration: the node keeps (and publishes) the
        previous one, the solver forgets every kept start, the step counts as a
        rejection and the first of a streak is logged."""
        self.solver.forget_starts()
        self.discarded_steps += 1
        self.rejected_inputs += 1
        self.last_rejection = (f"IK step {self.cycles + 1} gave a non-finite configuration: "
                               f"discarded, the previous one kept ({self.discarded_steps} "
                               "in a row)")
        if self.discarded_steps == 1:
            self.get_logger().error(self.last_rejection)

    # --- IK loop ------------------------------------------------------------------------

    def start_loop(self):
        self._loop_thread.start()

    def stop_loop(self):
        self._stop.set()
        self._loop_thread.join(timeout=5.0)

    def _run_loop(self):
        """One step per period; a late step shifts the schedule instead of bursting."""
        next_tick = window_start = time.monotonic()
        window_overruns, window_cycles = self.overruns, self.cycles
        while not self._stop.is_set():
            next_tick += self._period
            self._tick()
            now = time.monotonic()
            delay = next_tick - now
            if delay > 0:
                time.sleep(delay)  # clock_nanosleep: tighter wake-ups than a condition wait
            else:
                missed = int(-delay // self._period)
                self.overruns += missed
                next_tick += missed * self._period
            if now - window_start >= RATE_WINDOW:
                self._warn_if_behind(now - window_start, self.cycles - window_cycles,
                                     self.overruns - window_overruns)
                window_start, window_overruns, window_cycles = now, self.overruns, self.cycles

    def _warn_if_behind(self, window: float, steps: int, missed: int) -> None:
        """Log a warning when more than BEHIND_FRACTION of the periods of the last `window`
        s were missed (steps taken, periods missed)."""
        if missed > BEHIND_FRACTION * (steps + missed):
            self.get_logger().warning(
                f"IK loop behind its {1.0 / self._period:g} Hz: {steps / window:.0f} steps "
                f"per second over the last {window:.1f} s, {missed} periods missed (the last "
                f"step took {1e3 * self.last_solve_time:.1f} ms; /pik/status.overruns)")

    def _tick(self):
        with self._lock:
            # stamped once the inputs are frozen: what a step publishes reflects no input
            # received after its stamp (a callback may hold the lock for a while)
            stamp = self.get_clock().now().to_msg()
            result = self.solver.step(self.q)
            self.last_solve_time = result.solve_time
            finite = np.isfinite(result.q).all()
            if finite:
                self.q = result.q
                if self.discarded_steps:
                    self.get_logger().info(f"IK steps finite again after {self.discarded_steps}"
                                           " discarded")
                    self.discarded_steps = 0
            else:
                self._discard_step()
            q = self.q
            self.cycles += 1
            status = self._fill_status(stamp, result if finite else None)
        joint_state = JointState(header=_header(stamp), name=self._joint_names,
                                 position=q[self._joint_q_index].tolist())
        self.joint_state_pub.publish(joint_state)
        if self.robot.floating_base:
            base = PoseStamped(header=_header(stamp, "world"))
            fill_pose_msg(base.pose, q[:7])
            self.base_pose_pub.publish(base)
        self.status_pub.publish(status)

    def _fill_status(self, stamp, result) -> SolverStatus:
        """Update the reused status message in place (building it anew each step costs more
        than the IK step); rebuilt when the stack or an enable flag changes. result None (a
        discarded step): the solver's figures of the last kept step stay."""
        if self._status_template is None:
            self._status_template = self._new_status()
        status = self._status_template
        status.header.stamp = stamp
        status.strategy = self.solver.strategy_name
        status.hierarchy = self._hierarchy_name
        status.cycles = self.cycles
        status.overruns = self.overruns
        status.last_input_stamp = self.last_input_stamp
        status.rejected_inputs = self.rejected_inputs
        status.last_rejection = self.last_rejection
        if result is None:
            return status
        status.binding_constraints = result.binding_constraints
        status.clamping_iterations = result.clamping_iterations
        status.solve_time = result.solve_time
        status.damping = result.damping.tolist()
        status.clamped = result.clamped.tolist()
        for level_msg, level in zip(status.levels, result.levels):
            level_msg.residual_norm = level.residual_norm
            level_msg.step_residual_norm = level.step_residual_norm
            level_msg.condition = level.condition
            level_msg.damping = level.damping
        for task_msg in status.tasks:
            task_msg.error_norm = result.task_errors[task_msg.name]
            target, current = self.solver.task_poses(task_msg.name)
            if target is not None:
                fill_pose_msg(task_msg.target, pin.SE3ToXYZQUAT(target))
                fill_pose_msg(task_msg.current, pin.SE3ToXYZQUAT(current))
        return status

    def _new_status(self) -> SolverStatus:
        layout = self.solver.levels()
        status = SolverStatus(header=_header(Time(), "world"),
                              joint_names=self.solver.limited_dof_names)
        status.levels = [LevelStatus(priority=priority, tasks=names)
                         for priority, names in layout]
        status.tasks = [TaskStatus(name=name, priority=task.priority, enabled=task.enabled)
                        for name, task in self.solver.tasks.items()]
        return status


def fill_pose_msg(pose, xyz_quaternion) -> None:
    """Write (x, y, z (m), qx, qy, qz, qw) into a geometry_msgs/Pose: q[:7] of a free
    flyer, or pin.SE3ToXYZQUAT(placement). Plain attribute writes: pik_node fills nine
    poses per cycle, and unpacking generators cost it 5x more."""
    x, y, z, qx, qy, qz, qw = np.asarray(xyz_quaternion, dtype=float).tolist()
    position, orientation = pose.position, pose.orientation
    position.x, position.y, position.z = x, y, z
    orientation.x, orientation.y, orientation.z, orientation.w = qx, qy, qz, qw


def _file_error(error: Exception) -> str:
    """An error about a file, as a sentence: an OSError as 'No such file or directory:
    <path>' (no errno), anything else as its message."""
    if isinstance(error, OSError) and error.strerror:
        return f"{error.strerror}: {error.filename}" if error.filename else error.strerror
    return str(error)


def target_topic(task_name: str) -> str:
    """The topic a task's targets arrive on."""
    return f"/pik/tasks/{task_name}/target"


def _header(stamp, frame_id=""):
    return Header(stamp=stamp, frame_id=frame_id)


def float_parameter(description: str, low: float, high: float) -> ParameterDescriptor:
    """A read-only double parameter's descriptor with its allowed range [low, high]."""
    return ParameterDescriptor(description=description, read_only=True, floating_point_range=[
        FloatingPointRange(from_value=low, to_value=high)])


def spin_until_signal(node: Node, executor) -> None:
    """Spin `node` on `executor` until SIGINT or SIGTERM, then return so the caller shuts
    down in order."""
    stop = threading.Event()
    for signal_number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signal_number, lambda *_: stop.set())
    executor.add_node(node)
    while not stop.is_set() and rclpy.ok():
        executor.spin_once(timeout_sec=0.1)


_TYPE_MISMATCH = re.compile(r"parameter '(?P<name>[^']+)' to '(?P<value>.*)' of type "
                            r"'(?P<given>\w+)', expecting type '(?:Type\.)?(?P<expected>\w+)'")


def startup_error_message(error: Exception) -> str:
    """The reason a node cannot start, for its user. A parameter given with the wrong type
    (`-p rate:=500` for a double: rcl types 500 as an integer) names the parameter, the
    type it takes and how to write it; rclpy's own text otherwise."""
    match = _TYPE_MISMATCH.search(str(error)) \
        if isinstance(error, InvalidParameterTypeException) else None
    if match is None:
        return str(error)
    name, value, given, expected = match.group("name", "value", "given", "expected")
    hints = {"DOUBLE": f"write {name}:={value}.0" if given == "INTEGER"
             else f"write a number with a decimal point, e.g. {name}:=1.0",
             "BOOL": f"write {name}:=true or {name}:=false",
             "STRING": f"quote it: {name}:=\"'{value}'\""}
    return (f"parameter '{name}' must be {_a_type(expected)}, not {_a_type(given)} ({value})"
            + (f": {hints[expected]}" if expected in hints else ""))


def _a_type(type_name: str) -> str:
    """'INTEGER' -> 'an integer', 'STRING_ARRAY' -> 'a string array'."""
    words = type_name.lower().replace("_", " ")
    return f"{'an' if words[0] in 'aeiou' else 'a'} {words}"


def run_node(label: str, make_node, startup_errors: tuple, args=None, start=None, stop=None,
             make_executor=SingleThreadedExecutor) -> int:
    """The entry point of every Stance node: build the node (exit 1 with the reason on
    `startup_errors` and on parameter errors: a wrong type, a value out of range), freeze
    what exists then out of the cyclic garbage collector's reach, call start(node), spin on
    make_executor() until SIGINT or SIGTERM, call stop(node) (so work in executor
    callbacks ends: stop must wait for it, as rclpy's Executor.shutdown does not), shut
    down the executor and rclpy; exit 0."""
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    try:
        node = make_node()
    except (ParameterException, *startup_errors) as error:
        print(f"{label}: cannot start: {startup_error_message(error)}", file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    # What the node holds from start-up lives as long as it does: a full collection then
    # scans only what it allocates later (pik_node: 81 ms per full collection of its ~140k
    # start-up objects, 40 missed periods at 500 Hz; ~0 frozen)
    gc.collect()
    gc.freeze()
    if start is not None:
        start(node)
    executor = make_executor()
    try:
        spin_until_signal(node, executor)
    finally:
        if stop is not None:
            stop(node)
        executor.shutdown(timeout_sec=10.0)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def main(args=None):
    # Two Python threads share the GIL: with the default 5 ms switch interval either one can
    # hold the other for longer than a control period.
    sys.setswitchinterval(0.0005)
    return run_node("pik_node", PikNode,
                    (RobotModelError, StackError, LimitFileError, OSError, ValueError), args,
                    start=PikNode.start_loop, stop=PikNode.stop_loop)


if __name__ == "__main__":
    sys.exit(main())
