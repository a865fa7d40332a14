"""trajectory_node: contact plans interpolated, timed and executed through pik_node (Escande
et al. 2008, sections 3.3 and 4), as a ROS 2 node.

Thin adapter over stance.execution: a worker thread (the executor keeps serving) converts
each new plan, interpolates it (TransitionPlanner, `samples_per_transition` postures per
transition), times it (`timing`: sinusoidal, the paper's, under `velocity_scale` times the
URDF speed limits; or time_optimal, also under `acceleration_limit`), then executes it:
- the whole timed trajectory goes out once as a JointTrajectory (actuated 1-DoF joints,
  positions and velocities at the interpolated samples) for users' controllers;
- pik_node jumps to the first witness (/pik/set_configuration), then gets per transition a
  stack (/pik/set_stack, called when it changes): the contacts held through the
  transition as pose tasks on their spots' robot frames at priority 0 (target: the exact
  contact, spot target * placement^-1), the moving spots as pose tasks and the CoM (x, y)
  at priority 1, the posture at priority 2; at `rate` Hz, the targets of the moving spots,
  CoM and posture are the forward kinematics of the trajectory sampled at the current
  time, streamed on /pik/tasks/<name>/target as a teleoperator would;
- the active stance goes out when the transition into it starts (stance 0: at the start),
  stamped with when that transition ends (the stabilizer_gate_node contract).

A new plan while one executes: the current transition is finished (the robot is then at
rest on a witness: every stance boundary is a contact event), then the new plan starts
from its own first witness (a jump if it does not start there). A plan arriving while
another is interpolated replaces it. A plan that cannot be converted, interpolated or
executed is reported (status `failed`, log) and the node waits for the next one; pik_node
then holds its last targets. The latched plan found at start-up is executed too; a plan
equal to the last one received (header stamp included) is ignored.

Topics and services (QoS in parentheses):
  sub  /contact_planner/plan         stance_msgs/StancePlan (reliable, transient local)
  pub  /trajectory/joint_trajectory  trajectory_msgs/JointTrajectory (reliable, transient
                                     local), header.stamp = execution start
  pub  /trajectory/active_stance     stance_msgs/ContactStance (reliable, keep last 10)
  pub  /trajectory/status            std_msgs/String "<state>: <message>", state idle |
                                     interpolating | executing | done | failed (reliable,
                                     transient local)
  pub  /pik/tasks/<name>/target      PoseStamped | PointStamped (com) | JointState (posture)
  cli  /pik/set_configuration, /pik/set_stack
"""

from __future__ import annotations

import copy
import sys
import threading
import time
import traceback

import pinocchio as pin
from contact_planner_node.conversions import actuated_q_index
from geometry_msgs.msg import PointStamped, PoseStamped
from pik_node.node import (LATCHED, RELIABLE, TARGET_TYPES, fill_pose_msg, float_parameter,
                           run_node)
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor
from rclpy.duration import Duration
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from sensor_msgs.msg import JointState
from stance import Robot, RobotModelError
from stance.execution.interpolation import InterpolationError, TransitionPlanner
from stance.execution.timing import sinusoidal_trajectory, time_optimal_trajectory
from stance.planning.collision import CollisionModel
from stance_msgs.msg import ContactStance, StancePlan
from stance_msgs.srv import SetConfiguration, SetStack
from std_msgs.msg import Header, String
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from .conversions import (configuration_request, execution_stack, held_frame_target,
                          plan_from_msg, stack_request)

PLAN_TOPIC = "/contact_planner/plan"
TRAJECTORY_TOPIC = "/trajectory/joint_trajectory"
ACTIVE_STANCE_TOPIC = "/trajectory/active_stance"
STATUS_TOPIC = "/trajectory/status"
TIMINGS = ("sinusoidal", "time_optimal")


class ExecutionError(RuntimeError):
    """pik_node refused or did not answer a service call during execution."""


class TrajectoryNode(Node):
    def __init__(self, **kwargs):
        super().__init__("trajectory_node", **kwargs)
        self._declare_parameters()
        get = self.get_parameter
        self.timing = get("timing").value
        if self.timing not in TIMINGS:
            raise ValueError(f"timing must be one of {', '.join(TIMINGS)}, "
                             f"not {self.timing!r}")
        self.robot_spec = get("robot").value
        self.robot = Robot.load(self.robot_spec)
        if not self.robot.floating_base:
            raise ValueError(f"robot {self.robot_spec!r} has no free-flyer base: contact "
                             "plans need one")
        self.steps = get("samples_per_transition").value
        self.velocity_scale = get("velocity_scale").value
        self.acceleration_limit = get("acceleration_limit").value
        self.period = 1.0 / get("rate").value
        self.service_timeout = get("service_timeout").value
        self.gains = {name: get(f"{name}_gain").value for name in ("contact", "com", "posture")}
        self._fk_data = self.robot.model.createData()
        q_index = actuated_q_index(self.robot)    # actuated 1-DoF joints, pik_node's order
        self._joints = list(q_index)
        self._joint_q_index = list(q_index.values())
        self._joint_v_index = [self.robot.model.joints[self.robot.joint_id(name)].idx_v
                               for name in self._joints]

        self.trajectory_pub = self.create_publisher(JointTrajectory, TRAJECTORY_TOPIC, LATCHED)
        self.active_stance_pub = self.create_publisher(ContactStance, ACTIVE_STANCE_TOPIC,
                                                       RELIABLE)
        self.status_pub = self.create_publisher(String, STATUS_TOPIC, LATCHED)
        self.set_configuration_client = self.create_client(SetConfiguration,
                                                           "/pik/set_configuration")
        self.set_stack_client = self.create_client(SetStack, "/pik/set_stack")
        self._target_pubs = {}
        self._pending = None                  # newest StancePlan not yet taken
        self._last_plan = None                # last StancePlan received
        self._wakeup = threading.Condition()
        self._stop = threading.Event()
        self._worker = threading.Thread(target=self._run, name="trajectory_worker",
                                        daemon=True)
        self.create_subscription(StancePlan, PLAN_TOPIC, self._on_plan, LATCHED)
        self._status("idle", "waiting for a plan")

    def _declare_parameters(self):
        self.declare_parameter("robot", "talos", ParameterDescriptor(
            description="example-robot-data name or URDF path (pik_node's robot)",
            read_only=True))
        self.declare_parameter("samples_per_transition", 20, ParameterDescriptor(
            description="n: postures generated per transition", read_only=True,
            integer_range=[IntegerRange(from_value=2, to_value=1000, step=1)]))
        self.declare_parameter("timing", "sinusoidal", ParameterDescriptor(
            description=f"time law: {' | '.join(TIMINGS)}", read_only=True))
        self.declare_parameter("velocity_scale", 0.5, float_parameter(
            "joint speeds at most this fraction of their URDF limits", 0.01, 1.0))
        self.declare_parameter("acceleration_limit", 4.0, float_parameter(
            "joint acceleration limit of the time_optimal timing (rad/s^2)", 0.01, 1000.0))
        self.declare_parameter("rate", 100.0, float_parameter(
            "task targets streamed to pik_node per second (Hz)", 1.0, 1000.0))
        for name, default in (("contact", 0.5), ("com", 0.5), ("posture", 0.3)):
            self.declare_parameter(f"{name}_gain", default, float_parameter(
                f"IK gain of the {name} task(s): fraction of the error corrected per step",
                1e-3, 1.0))
        self.declare_parameter("service_timeout", 10.0, float_parameter(
            "wait for pik_node's services and their answers (s)", 0.1, 600.0))

    # --- inputs and worker ----------------------------------------------------------------

    def _on_plan(self, msg: StancePlan):
        """Keep the newest plan for the worker; one equal to the last received (a latched
        plan delivered again) is ignored."""
        if msg == self._last_plan:
            self.get_logger().info("plan received again: ignored")
            return
        self._last_plan = msg
        with self._wakeup:
            self._pending = msg
            self._wakeup.notify()

    def _has_pending(self) -> bool:
        with self._wakeup:
            return self._pending is not None

    def start_worker(self):
        self._worker.start()

    def stop_worker(self):
        self._stop.set()
        with self._wakeup:
            self._wakeup.notify()
        self._worker.join(timeout=2.0)

    def _run(self):
        """Worker: one plan after the other; an unexpected error fails that plan only."""
        while not self._stop.is_set():
            with self._wakeup:
                while self._pending is None and not self._stop.is_set():
                    self._wakeup.wait()
                msg, self._pending = self._pending, None
            if msg is None:
                continue
            try:
                self._process(msg)
            except Exception as error:  # noqa: BLE001 - the node must keep serving plans
                if self._stop.is_set():
                    return
                self.get_logger().error(traceback.format_exc())
                self._status("failed", f"internal error: {error!r}")

    def _process(self, msg: StancePlan):
        """Convert, interpolate, time and execute one plan; failures end in `failed`."""
        self._status("interpolating", f"plan of {len(msg.stances)} stances on scene "
                                      f"{msg.scene!r}, n = {self.steps}")
        try:
            plan, scene = plan_from_msg(msg, self.robot, self.robot_spec)
            planner = TransitionPlanner(self.robot, scene, CollisionModel(self.robot, scene),
                                        steps=self.steps)
            path = planner.interpolate(plan)
        except (ValueError, InterpolationError) as error:
            self._status("failed", f"plan rejected: {error}")
            return
        trajectory = self._time(path)
        if self._has_pending():
            self.get_logger().info("a newer plan arrived during interpolation: it replaces "
                                   "this one")
            return
        try:
            self._execute(msg, plan, scene, planner, path, trajectory)
        except ExecutionError as error:
            self._status("failed", f"execution stopped: {error}")

    def _time(self, path):
        if self.timing == "sinusoidal":
            return sinusoidal_trajectory(self.robot, path.q, path.event_samples,
                                         self.velocity_scale)
        return time_optimal_trajectory(self.robot, path.q, path.event_samples,
                                       self.velocity_scale, self.acceleration_limit)

    # --- execution ------------------------------------------------------------------------

    def _execute(self, msg, plan, scene, planner, path, trajectory):
        """Stream the timed plan to pik_node (module docstring); returns when it is done, or
        at the end of the current transition when a newer plan is pending."""
        boundaries = trajectory.times[path.stance_samples]   # s: when each stance is reached
        self._call(self.set_configuration_client, configuration_request(self.robot,
                                                                        plan.stances[0].q))
        stack, held = self._enter(scene, planner, plan, 0, None)
        start, began = self.get_clock().now(), time.monotonic()
        self.trajectory_pub.publish(self._joint_trajectory(trajectory, start))
        self._publish_active(msg, 0, start, 0.0)
        self._publish_active(msg, 1, start, boundaries[1])
        self._status("executing", f"{len(plan.stances)} stances in {trajectory.duration:.2f} "
                                  f"s ({self.timing})")
        transition, last, next_tick = 0, len(plan.stances) - 2, began
        while not self._stop.is_set():
            t = min(time.monotonic() - began, trajectory.duration)
            while transition < last and t >= boundaries[transition + 1]:
                if self._has_pending():
                    self._stream(trajectory.sample(boundaries[transition + 1])[0], stack, held)
                    self._status("executing", f"superseded by a newer plan at stance "
                                              f"{transition + 1}")
                    return
                transition += 1
                stack, held = self._enter(scene, planner, plan, transition, stack)
                self._publish_active(msg, transition + 1, start, boundaries[transition + 1])
            self._stream(trajectory.sample(t)[0], stack, held)
            if t >= trajectory.duration:
                self._status("done", f"reached stance {len(plan.stances) - 1} of scene "
                                     f"{plan.scene!r}")
                return
            next_tick += self.period
            time.sleep(max(next_tick - time.monotonic(), 0.0))

    def _enter(self, scene, planner, plan, transition, stack):
        """(stack, held contacts' frame targets by spot) of transition `transition` (stance
        i -> i + 1); pik_node's stack is set when it differs from `stack`."""
        first, second = plan.stances[transition], plan.stances[transition + 1]
        moving = planner.moving_paths(first, second)
        held = [contact for contact in first.contacts if contact.spot not in moving]
        specs = execution_stack(scene, held, sorted(moving), self.gains)
        if specs != stack:
            self._call(self.set_stack_client, stack_request(specs))
        return specs, {contact.spot: held_frame_target(scene, contact) for contact in held}

    def _stream(self, q, stack, held):
        """Publish every task's target at configuration q (nq): held contacts their exact
        frame target, other frames, the CoM and the joints their values at q (world)."""
        model, data = self.robot.model, self._fk_data
        pin.framesForwardKinematics(model, data, q)
        com = pin.centerOfMass(model, data, q, False)
        header = Header(stamp=self.get_clock().now().to_msg(), frame_id="world")
        for spec in stack:
            if spec.kind == "posture":
                target = JointState(header=header, name=self._joints,
                                    position=q[self._joint_q_index].tolist())
            elif spec.kind == "com":
                target = PointStamped(header=header)
                target.point.x, target.point.y, target.point.z = (float(v) for v in com)
            else:
                pose = held[spec.name] if spec.name in held else \
                    data.oMf[model.getFrameId(spec.frame)]
                target = PoseStamped(header=header)
                fill_pose_msg(target.pose, pose.translation,
                              pin.Quaternion(pose.rotation).coeffs())
            self._target_publisher(spec).publish(target)

    def _target_publisher(self, spec):
        key = (spec.name, TARGET_TYPES[spec.kind])
        if key not in self._target_pubs:
            self._target_pubs[key] = self.create_publisher(
                key[1], f"/pik/tasks/{spec.name}/target", RELIABLE)
        return self._target_pubs[key]

    def _publish_active(self, msg, index, start, ends_after):
        """Stance `index` of the plan message, stamped start + ends_after (s)."""
        stance = copy.deepcopy(msg.stances[index])
        stance.index = index
        stance.header = Header(stamp=(start + Duration(seconds=float(ends_after))).to_msg(),
                               frame_id="world")
        self.active_stance_pub.publish(stance)

    def _joint_trajectory(self, trajectory, start) -> JointTrajectory:
        """The timed plan at its samples' times: actuated 1-DoF joints (rad, rad/s)."""
        msg = JointTrajectory(header=Header(stamp=start.to_msg(), frame_id="world"),
                              joint_names=self._joints)
        for t in trajectory.times:
            q, v = trajectory.sample(float(t))
            msg.points.append(JointTrajectoryPoint(
                positions=q[self._joint_q_index].tolist(),
                velocities=v[self._joint_v_index].tolist(),
                time_from_start=Duration(seconds=float(t)).to_msg()))
        return msg

    def _call(self, client, request):
        """Call a pik_node service from the worker (the executor handles the answer)."""
        if not client.wait_for_service(timeout_sec=self.service_timeout):
            raise ExecutionError(f"{client.srv_name} not available after "
                                 f"{self.service_timeout:g} s")
        future = client.call_async(request)
        deadline = time.monotonic() + self.service_timeout
        while not future.done():
            if time.monotonic() > deadline or self._stop.is_set():
                client.remove_pending_request(future)
                raise ExecutionError(f"no answer from {client.srv_name}")
            time.sleep(0.002)
        response = future.result()
        if not response.success:
            raise ExecutionError(f"{client.srv_name}: {response.message}")
        return response

    def _status(self, state: str, message: str):
        text = f"{state}: {message}"
        self.status_pub.publish(String(data=text))
        if state == "failed":
            self.get_logger().error(text)
        else:
            self.get_logger().info(text)


def main(args=None):
    return run_node("trajectory_node", TrajectoryNode,
                    (ParameterException, RobotModelError, OSError, ValueError), args,
                    start=TrajectoryNode.start_worker, stop=TrajectoryNode.stop_worker)


if __name__ == "__main__":
    sys.exit(main())
