"""trajectory_node: contact plans interpolated, timed and executed through pik_node (Escande
et al. 2008, sections 3.3 and 4), as a ROS 2 node.

Thin adapter over stance.execution: each new plan is converted on arrival; a preparer
thread verifies it, interpolates it (TransitionPlanner, `samples_per_transition` postures
per transition) and times it (`timing`: sinusoidal, the paper's, under `velocity_scale`
times the URDF speed limits; or time_optimal, also under `acceleration_limit`), then an
executor thread executes it (the rclpy executor keeps serving):
- the whole timed trajectory goes out once as a JointTrajectory (actuated 1-DoF joints,
  positions and velocities at the interpolated samples) for users' controllers;
- pik_node jumps to the first witness (/pik/set_configuration), then gets per transition a
  stack (/pik/set_stack, called when it changes): the contacts held through the
  transition as pose tasks on their spots' robot frames at priority 0 (target: the exact
  contact, spot target * placement^-1), the moving spots as pose tasks and the CoM (x, y)
  at priority 1, the posture at priority 2; at `rate` Hz, the targets of the moving spots,
  CoM and posture are the forward kinematics of the trajectory sampled at the current
  time, streamed on /pik/tasks/<name>/target as a teleoperator would; pik_node subscribes
  there when it takes a stack with that task, so after each /pik/set_stack call streaming
  waits until this node's publisher has matched it (a target sent before is lost), at
  most `service_timeout` s (then `failed: execution stopped: not started ...` at the
  start, `... transition k not started ...` later);
- the active stance goes out when the transition into it starts (stance 0: at the start),
  stamped with when that transition ends (the stabilizer_gate_node contract); a plan
  starts only once the nodes named in `stance_listeners` (the default graph: the
  stabilizer gate) subscribe to it and this node's publisher has matched them, waiting at
  most `service_timeout` s (then `failed: execution stopped: not started ...`);
- a transition starts only once the robot is at the stance before it
  (stance.execution.tracking.ArrivalGate): at the end of each transition the clock holds
  (the end sample streamed again) until pik_node's status shows each contact it creates
  with its frame within `arrival_tolerance` m and `arrival_angle_tolerance` rad of its
  exact target, and the CoM (x, y) within `arrival_com_tolerance` m of the stance witness's;
  only then does the next stack hold the created contacts at priority 0 and may the next
  transition release one. Unloaded, the robot is there on time and nothing waits; when
  pik_node lags, holding a contact at its target from centimetres away would drag it along
  its surface, and lifting a foot before the CoM is over the other would unbalance the
  robot. A wait beyond `arrival_timeout` s ends the plan in `failed: execution stopped:
  ...` naming what is off and by how much (pik_node then holds the created contacts at
  their targets);
- a late tick (the node starved under load) advances the trajectory's time by
  MAX_TICK_ADVANCE periods at most: the motion slows down instead of the targets jumping
  ahead along the path;
- a stance reached more than LATE_STANCE s after its stamp (a wait, late ticks, a slow
  /pik/set_stack call or match of its target topics) goes out again, stamped when it was
  reached, with `executing: stance k reached after waiting ...` or `... reached X s late
  (<causes>)` (late_reason), and the JointTrajectory goes out again with its start
  shifted by as much. The last stance executed (the plan's, or the one a newer plan takes
  over at) goes out again when reached in any case (stamped as planned if on time): no
  next stance says that the robot is there, which an ON switch of stabilizer_gate_node
  waits for.

pik_node lost during execution (PikWatch on /pik/status: silent for `pik_status_timeout`
s, or its cycle counter went back, i.e. a new process): streaming pauses at the current
sample (`executing: pik_node silent for ... at transition i (t = ...): streaming paused`)
until pik_node publishes again, for at most `pik_restart_timeout` s. A restarted pik_node
(`stance graph` restarts a crashed node) gets the configuration of the paused sample
(/pik/set_configuration) and the current stack again (`executing: pik_node restarted at
transition i ...; resuming from the last commanded configuration`); the same process after
a stall keeps its own. Streaming then resumes from that sample, the time base shifted by
the pause (the JointTrajectory goes out again with its start shifted; the stance in
progress, late by the pause, goes out again when reached: `executing: stance k reached X
s late (streaming paused Y s for pik_node)`). If pik_node does not come back in time, or
refuses the re-sent configuration or stack, the plan ends in `failed: execution stopped:
pik_node ...` and the node waits for the next one.

Plans are converted on arrival, prepared (verified, interpolated and timed) on one thread
and executed on another. Every plan is verified (stance.planning.verify, what `stance
check-plan` runs: contacts, collisions, joint limits, static equilibrium, one contact
change per stance); one that fails is rejected with its first failures. A new plan while
one executes is prepared meanwhile (its verification and collision models hold the GIL up
to ~60 ms at a time: a tick or two come late, and the motion slows down by as much); once
it is ready, the transition in progress is finished (the robot is then at rest on a
witness: every stance boundary is a contact event), then the new plan starts from its own
first witness (a jump if it does not start there); if the plan under way ends first, the
new one starts when ready. Its statuses meanwhile keep the state of the plan under way
(`executing: a newer plan ... is being prepared ...`). A plan arriving while another is
prepared replaces it if it is ready in turn; a ready plan waits for one such preparation
at most (then the newest ready one is handed over), so plans sent faster than they are
prepared still execute. A plan that cannot be converted, verified, interpolated or
executed is reported and never supersedes a plan under way or ready, which goes on even
though a newer one was sent (the status says so, with the rejection); with
none, the status says `failed` (and the log), the node waits for the next one and pik_node
holds its last targets. A plan stamped before the node started (the latched last plan,
found at start-up) is not executed unless `execute_latched_plan` is true: a node restarted
by `stance graph` must not replay the last plan from its first witness; the status says so.
A plan equal to the last one received (header stamp included) is ignored.
At shutdown a preparation under way stops with no status, before its next stance to
verify, sample to interpolate or transition to time (each ~5-30 ms of work on Talos).

Topics and services (QoS in parentheses):
  sub  /contact_planner/plan         stance_msgs/StancePlan (reliable, transient local)
  pub  /trajectory/joint_trajectory  trajectory_msgs/JointTrajectory (reliable, transient
                                     local), header.stamp = execution start
  pub  /trajectory/active_stance     stance_msgs/ContactStance (reliable, keep last 10); a
                                     stance reached late, and the last one executed, go
                                     out again when reached
  pub  /trajectory/status            std_msgs/String "<state>: <message>", state idle |
                                     interpolating | executing | done | failed (reliable,
                                     transient local, the last STATUS_HISTORY)
  pub  /pik/tasks/<name>/target      PoseStamped | PointStamped (com) | JointState (posture)
                                     (reliable, keep last 10)
  sub  /pik/status                   stance_msgs/SolverStatus (best effort, keep last 1),
                                     pik_node's liveness and its tasks' frames (PikWatch,
                                     a private node <name>_pik_watch the executor thread
                                     polls)
  cli  /pik/set_configuration, /pik/set_stack: a call waits at most `service_timeout` s
                                     for the service and its answer together, the
                                     request sent again each RESEND_PERIOD s
"""

from __future__ import annotations

import copy
import math
import sys
import threading
import time
import traceback
from typing import NamedTuple

import pinocchio as pin
from contact_planner_node.conversions import actuated_q_index
from geometry_msgs.msg import PointStamped, PoseStamped
from pik_node.conversions import se3_from_pose_msg, time_from_msg
from pik_node.node import (LATCHED, RELIABLE, TARGET_TYPES, fill_pose_msg, float_parameter,
                           run_node, target_topic)
from rcl_interfaces.msg import IntegerRange, ParameterDescriptor
from rclpy.duration import Duration
from rclpy.exceptions import InvalidNodeNameException, ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.validate_node_name import validate_node_name
from sensor_msgs.msg import JointState
from stance import Robot, RobotModelError
from stance.execution.interpolation import (InterpolatedPlan, InterpolationError,
                                           TransitionPlanner)
from stance.execution.timing import (Trajectory, sinusoidal_trajectory,
                                     time_optimal_trajectory)
from stance.execution.tracking import (ARRIVAL_COM_TOLERANCE, ARRIVAL_TIMEOUT,
                                       ARRIVAL_TOLERANCE, GAINS, ArrivalGate, task_targets,
                                       transition_tasks, witness_com)
from stance.planning.collision import CollisionModel
from stance.planning.contacts import Plan
from stance.planning.scene import Scene
from stance.planning.verify import verify_plan
from stance.stopping import Stopped
from stance_msgs.msg import ContactStance, SolverStatus, StancePlan
from stance_msgs.srv import SetConfiguration, SetStack
from std_msgs.msg import Header, String
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from .conversions import PlanRejected, configuration_request, plan_from_msg, stack_request

PLAN_TOPIC = "/contact_planner/plan"
TRAJECTORY_TOPIC = "/trajectory/joint_trajectory"
ACTIVE_STANCE_TOPIC = "/trajectory/active_stance"
STATUS_TOPIC = "/trajectory/status"
PIK_STATUS_TOPIC = "/pik/status"
LATEST = QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT)
# Statuses are events: a reader whose copy of one was lost gets it again from this history
# (with depth 1 the next status replaced it before the repair, and a pause went unseen).
# A late joiner receives the last STATUS_HISTORY statuses; the newest is the current state.
STATUS_HISTORY = 20
STATUS_QOS = QoSProfile(depth=STATUS_HISTORY, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)
RESEND_PERIOD = 1.0  # s without an answer before a service request is sent again
SLOW_CALL = 0.1      # s: a pik_node call answered later than this is logged (the stream waited)
# periods of trajectory time one tick may advance: a late tick (the node starved under load)
# slows the motion down instead of jumping the targets ahead along the path (a sole would
# then go straight to where its swing should be, along the ground)
MAX_TICK_ADVANCE = 2.0
LATE_STANCE = 0.05   # s: a stance reached this much after its stamp is announced again
NOTED_DELAY = 0.01   # s: a cause of a stance's lateness this long is named in its status
TIMINGS = ("sinusoidal", "time_optimal")


class ExecutionError(RuntimeError):
    """pik_node refused or did not answer a service call during execution."""


class PikLost(ExecutionError):
    """pik_node went silent or restarted during execution (PikWatch)."""


class Prepared(NamedTuple):
    """A plan ready to execute: the message, its plan and scene, the transition planner
    that interpolated it, the path and its timed trajectory."""

    msg: StancePlan
    plan: Plan
    scene: Scene
    planner: TransitionPlanner
    path: InterpolatedPlan
    trajectory: Trajectory


class PikWatch:
    """pik_node's liveness during an execution (between arm() and disarm()), from its
    /pik/status stream; used by the executor thread only.

    Why this signal: a SIGKILLed pik_node stays in the DDS graph until its lease expires
    (Fast DDS: 20 s), so neither graph queries nor wait_for_service notice it; its status,
    one message per control period, does: silence longer than `silence` s means it went
    away (or stalls), and `cycles` (control periods since the process started) going back
    means a new process took over, even one restarted within `silence`. Both are pik_node's
    own contract, whatever the DDS implementation.

    The subscription (keep last 1) sits on a private node that no executor spins: each
    check takes only the newest status, instead of the executor handling all of them (at
    pik_node's 500 Hz that costs a fifth to a third of a core)."""

    def __init__(self, owner: Node, silence: float):
        self.silence = silence
        # the owner's command-line remappings (__node:=...) are not this node's
        self._node = Node(f"{owner.get_name()}_pik_watch", namespace=owner.get_namespace(),
                          context=owner.context, use_global_arguments=False,
                          start_parameter_services=False)
        self._subscription = self._node.create_subscription(
            SolverStatus, PIK_STATUS_TOPIC, lambda _: None, LATEST)
        self._seen = -math.inf    # monotonic s when a status was last taken
        self._newest = None       # that status
        self._cycles = 0          # of that status
        self._starts = 0          # cycle counter resets seen (new pik_node processes)
        self._armed = None        # (monotonic s, _starts) at arm(); None: not judged

    def destroy(self):
        self._node.destroy_node()

    def _take(self):
        """Take the newest status, if one arrived since the last take."""
        handle = self._subscription.handle
        with handle:
            taken = handle.take_message(SolverStatus, False)
        if taken is not None:
            if taken[0].cycles < self._cycles:
                self._starts += 1
            self._newest, self._cycles, self._seen = taken[0], taken[0].cycles, time.monotonic()

    def arm(self):
        """Judge from now on (pik_node has just answered)."""
        self._take()
        self._armed = (time.monotonic(), self._starts)

    def disarm(self):
        self._armed = None

    def lost(self) -> str | None:
        """Why pik_node is lost since arm(); None while it is fine or not judged."""
        if self._armed is None:
            return None
        self._take()
        since, starts = self._armed
        if self._starts != starts:
            return "pik_node restarted"
        silent = time.monotonic() - max(self._seen, since)
        return f"pik_node silent for {silent:.2f} s" if silent > self.silence else None

    def frames(self, names) -> dict:
        """{task name: achieved pose (pin.SE3, world; a CoM task's: its position, identity
        rotation)} of the named frame or CoM tasks in the newest status taken (lost() takes
        it); names it lacks are left out."""
        if self._newest is None:
            return {}
        return {task.name: se3_from_pose_msg(task.current) for task in self._newest.tasks
                if task.name in names}

    def back(self, lost_at: float) -> bool | None:
        """Once armed and lost at monotonic `lost_at`: True when a new process publishes,
        False when the same one publishes again, None while neither has."""
        self._take()
        if self._starts != self._armed[1]:
            return True
        return False if self._seen > lost_at else None


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
        self.execute_latched_plan = get("execute_latched_plan").value
        self.stance_listeners = self.get_parameter_or(
            "stance_listeners", Parameter("stance_listeners", Parameter.Type.STRING_ARRAY,
                                          [])).value
        for name in self.stance_listeners:
            try:
                validate_node_name(name)
            except InvalidNodeNameException as error:
                reason = str(error).splitlines()[0].removeprefix("Invalid node name: ")
                raise ValueError(f"stance_listeners: {name!r} is not a node name: "
                                 f"{reason.rstrip(':')}") from None
        self.arrival_tolerance = (get("arrival_tolerance").value,
                                  get("arrival_angle_tolerance").value)
        self.arrival_com_tolerance = get("arrival_com_tolerance").value
        self.arrival_timeout = get("arrival_timeout").value
        self._started = self.get_clock().now()
        self.pik_restart_timeout = get("pik_restart_timeout").value
        self._pik = PikWatch(self, get("pik_status_timeout").value)
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
        self.status_pub = self.create_publisher(String, STATUS_TOPIC, STATUS_QOS)
        self.set_configuration_client = self.create_client(SetConfiguration,
                                                           "/pik/set_configuration")
        self.set_stack_client = self.create_client(SetStack, "/pik/set_stack")
        self._target_pubs = {}
        self._arrival = None                  # newest (StancePlan, Plan, Scene) to prepare
        self._preparing = False               # the preparer works on an arrival
        self._ready = None                    # a Prepared plan held while a newer is prepared
        self._pending = None                  # newest Prepared plan, not executed yet
        self._executing = False               # the executor has a plan under way
        self._last_plan = None                # last StancePlan received
        self._wakeup = threading.Condition()  # guards the five above
        # a status decided from those flags and the last one published goes out before any
        # other (taken before _wakeup, never while holding it)
        self._status_lock = threading.RLock()
        self._stop = threading.Event()
        self._workers = [threading.Thread(target=target, name=name, daemon=True)
                         for target, name in ((self._prepare_plans, "trajectory_preparer"),
                                              (self._run, "trajectory_executor"))]
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
        for name, default in GAINS.items():
            self.declare_parameter(f"{name}_gain", default, float_parameter(
                f"IK gain of the {name} task(s): fraction of the error corrected per step",
                1e-3, 1.0))
        self.declare_parameter("service_timeout", 10.0, float_parameter(
            "wait for pik_node's services and their answers (s)", 0.1, 600.0))
        self.declare_parameter("pik_status_timeout", 0.5, float_parameter(
            "during execution, pik_node is lost when /pik/status is silent this long (s; "
            "longer than pik_node's period and stalls)", 0.01, 60.0))
        self.declare_parameter("pik_restart_timeout", 30.0, float_parameter(
            "wait for a lost pik_node to publish again before the execution stops (s; 0: "
            "stop at once)", 0.0, 600.0))
        self.declare_parameter("arrival_tolerance", ARRIVAL_TOLERANCE[0], float_parameter(
            "a created contact's frame this close to its target counts as arrived (m)",
            1e-5, 0.1))
        self.declare_parameter("arrival_angle_tolerance", ARRIVAL_TOLERANCE[1], float_parameter(
            "same for its orientation (rad)", 1e-4, 1.0))
        self.declare_parameter("arrival_com_tolerance", ARRIVAL_COM_TOLERANCE, float_parameter(
            "the CoM (x, y) this close to the stance witness's counts as arrived (m)",
            1e-4, 0.1))
        self.declare_parameter("arrival_timeout", ARRIVAL_TIMEOUT, float_parameter(
            "wait at a transition's end for its created contacts and the CoM at most this "
            "long before the execution stops (s)", 0.0, 600.0))
        self.declare_parameter("execute_latched_plan", False, ParameterDescriptor(
            description="also execute a plan stamped before this node started (the latched "
                        "last plan)", read_only=True))
        # a string array without a default (an empty list would be typed as bytes)
        listeners = ParameterDescriptor(
            description=f"nodes a plan waits for (at most service_timeout s) until each "
                        f"subscribes to {ACTIVE_STANCE_TOPIC} and this node's publisher "
                        "has matched it (stabilizer_gate_node); unset: none", read_only=True)
        self.declare_parameter("stance_listeners", Parameter.Type.STRING_ARRAY, listeners)

    # --- inputs, preparer and executor -----------------------------------------------------

    def _on_plan(self, msg: StancePlan):
        """Keep the newest plan for the preparer; one equal to the last received (a latched
        plan delivered again) is ignored."""
        if msg == self._last_plan:
            self.get_logger().info("plan received again: ignored")
            return
        self._last_plan = msg
        # checked here, so that a plan to reject never supersedes one under way
        try:
            stamp = time_from_msg(msg.header.stamp, "header.stamp")
        except ValueError as error:
            self._reject_plan(error, preparing_goes_on=True)
            return
        if not self.execute_latched_plan and 0 < stamp.nanoseconds < self._started.nanoseconds:
            self._status("idle", f"plan on scene {msg.scene!r} stamped "
                                 f"{(self._started - stamp).nanoseconds * 1e-9:.1f} s before "
                                 "this node started: not executed (publish it again, or set "
                                 "execute_latched_plan)")
            return
        try:
            plan, scene = plan_from_msg(msg, self.robot, self.robot_spec)
        except ValueError as error:
            self._reject_plan(error, preparing_goes_on=True)
            return
        with self._wakeup:
            self._arrival = (msg, plan, scene)
            self._wakeup.notify_all()

    def _reject_plan(self, error, preparing_goes_on: bool):
        """A plan rejected, decided at once from what goes on instead: the plan executed, a
        plan prepared (ready, or handed over and not yet taken), or when
        `preparing_goes_on` (the rejected plan is not the preparer's own) one the preparer
        works on; `failed` when none does."""
        self._status_by_what_goes_on(
            preparing_goes_on, f"a newer plan was rejected ({error}); this one goes on",
            f"a newer plan was rejected ({error}); the plan received before it goes on",
            ("failed", f"plan rejected: {error}"))

    def _has_pending(self) -> bool:
        with self._wakeup:
            return self._pending is not None

    def start_worker(self):
        for worker in self._workers:
            worker.start()

    def stop_worker(self):
        self._stop.set()
        with self._wakeup:
            self._wakeup.notify_all()
        for worker in self._workers:
            worker.join(timeout=2.0)

    def destroy_node(self):
        self._pik.destroy()
        super().destroy_node()

    def _prepare_plans(self):
        """Preparer: the newest arrival verified, interpolated and timed, then handed to the
        executor, unless a newer one arrived meanwhile: that one is prepared first, and
        replaces it if it is ready in turn (a rejected one leaves it to go on). The ready
        plan waits for one preparation at most: if yet another plan arrived meanwhile, the
        newest ready one is handed over first, so plans arriving faster than they are
        prepared still execute (the newest ready one takes over at the end of a transition)
        instead of waiting for the stream to end."""
        held_through_a_preparation = False
        while not self._stop.is_set():
            with self._wakeup:
                while self._arrival is None and self._ready is None and \
                        not self._stop.is_set():
                    self._wakeup.wait()
                if self._ready is not None and (self._arrival is None or
                                                held_through_a_preparation):
                    self._pending, self._ready = self._ready, None
                    self._wakeup.notify_all()
                arrival, self._arrival = self._arrival, None
                if arrival is None:
                    continue
                held_through_a_preparation = self._ready is not None
                self._preparing = True
            try:
                prepared = self._prepare(*arrival)
            except Exception as error:  # noqa: BLE001 - the node must keep serving plans
                if self._stop.is_set():
                    return
                self.get_logger().error(traceback.format_exc())
                prepared = None
                self._reject_plan(f"internal error: {error!r}", preparing_goes_on=False)
            with self._wakeup:
                self._preparing = False
                if prepared is not None:
                    if self._ready is not None:
                        self.get_logger().info("a newer plan arrived during interpolation: "
                                               "it replaces this one")
                    self._ready = prepared

    def _prepare(self, msg: StancePlan, plan, scene):
        """The Prepared plan (plan, scene: msg's, converted), None when rejected (said in
        the status: _reject_plan)."""
        what = f"plan of {len(msg.stances)} stances on scene {msg.scene!r}, n = {self.steps}"
        self._status_by_what_goes_on(
            False, f"a newer {what} is being prepared: it takes over at the end of a "
                   "transition once ready",
            f"a newer {what} is being prepared: it replaces the one received before it once "
            "ready", ("interpolating", what))
        try:
            _require_verified(plan, scene, self.robot, should_stop=self._stop.is_set)
            planner = TransitionPlanner(self.robot, scene, CollisionModel(self.robot, scene),
                                        steps=self.steps)
            path = planner.interpolate(plan, should_stop=self._stop.is_set)
            trajectory = self._time(path)
        except (ValueError, InterpolationError) as error:
            self._reject_plan(error, preparing_goes_on=False)
            return None
        except Stopped:    # the node stops: nothing to say
            return None
        return Prepared(msg, plan, scene, planner, path, trajectory)

    def _run(self):
        """Executor: one prepared plan after the other; an unexpected error fails that
        plan only."""
        while not self._stop.is_set():
            with self._wakeup:
                while self._pending is None and not self._stop.is_set():
                    self._wakeup.wait()
                pending, self._pending = self._pending, None
                self._executing = pending is not None
            if pending is None:
                continue
            try:
                self._execute(*pending)
            except ExecutionError as error:
                self._status("failed", f"execution stopped: {error}")
            except Exception as error:  # noqa: BLE001 - the node must keep serving plans
                if self._stop.is_set():
                    return
                self.get_logger().error(traceback.format_exc())
                self._status("failed", f"internal error: {error!r}")
            finally:
                with self._wakeup:
                    self._executing = False

    def _time(self, path):
        """The path timed; the time-optimal timing (seconds on a long plan) stops with the
        node (stopping.Stopped), the sinusoidal one takes ~2 ms per transition."""
        if self.timing == "sinusoidal":
            return sinusoidal_trajectory(self.robot, path.q, path.event_samples,
                                         self.velocity_scale)
        return time_optimal_trajectory(self.robot, path.q, path.event_samples,
                                       self.velocity_scale, self.acceleration_limit,
                                       should_stop=self._stop.is_set)

    # --- execution ------------------------------------------------------------------------

    def _execute(self, msg, plan, scene, planner, path, trajectory):
        """Stream the timed plan to pik_node (module docstring); returns when it is done, or
        at the end of the current transition when a newer plan is pending."""
        # s: when each stance is reached (the last one: the end, where the clock stops)
        boundaries = trajectory.times_of(path.stance_samples)
        self._await_stance_listeners()
        self._call(self.set_configuration_client, configuration_request(self.robot,
                                                                        plan.stances[0].q))
        self._pik.arm()
        try:
            self._stream_plan(msg, plan, scene, planner, trajectory, boundaries)
        finally:
            self._pik.disarm()

    def _await_stance_listeners(self):
        """Return once every node of stance_listeners subscribes to the active stance and
        this node's publisher has matched them (_unmatched): stance 0 goes out at the
        start, and a subscriber matched later (discovery can take seconds under load)
        misses it, so a stabilizer gate would take a later stance for the start."""
        if self.stance_listeners:
            self._await_matched("plan", "not started", lambda: self._unmatched(
                ACTIVE_STANCE_TOPIC, self.active_stance_pub, self.stance_listeners))

    def _hand_stack(self, stack, what: str, not_started: str):
        """/pik/set_stack with `stack`, returning once pik_node takes its targets
        (_await_target_subscriptions)."""
        self._call(self.set_stack_client, stack_request(stack))
        self._await_target_subscriptions(stack, what, not_started)

    def _await_target_subscriptions(self, stack, what: str, not_started: str):
        """Return once pik_node subscribes to the target topic of every task of `stack`
        and this node's publisher there has matched a subscription (_unmatched, not
        every: one of a killed pik_node stays in the graph, never matched, until its lease
        expires): pik_node subscribes to a task's topic when it takes a stack with that
        task, and a target sent before the match is lost (the first ones of a plan were,
        under load: the robot fell 0.2 rad behind the motion at once). pik_node: the
        publishers of /pik/status."""
        def missing():
            pik = {info.node_name for info in self.get_publishers_info_by_topic(
                PIK_STATUS_TOPIC)}
            if not pik:
                return f"no publisher of {PIK_STATUS_TOPIC} (pik_node) in the graph"
            return next(filter(None, (self._unmatched(target_topic(spec.name),
                                                      self._target_publisher(spec), pik,
                                                      every=False)
                                      for spec in stack)), "")
        self._await_matched(what, not_started, missing)

    def _await_matched(self, what: str, not_started: str, missing):
        """Return once missing() (what `what` still waits for) answers ''; log what it
        waits for once; ExecutionError `not_started ...: <what it waits for>` after
        service_timeout s (or at shutdown), PikLost as soon as the watch loses pik_node."""
        deadline, logged = time.monotonic() + self.service_timeout, False
        while reason := missing():
            lost = self._pik.lost()
            if lost:
                raise PikLost(lost)
            if self._stop.is_set():
                raise ExecutionError(f"{not_started} (the node stops): {reason}")
            if time.monotonic() > deadline:
                raise ExecutionError(f"{not_started} after {self.service_timeout:g} s: "
                                     f"{reason}")
            if not logged:
                self.get_logger().info(f"{what} waits: {reason}")
                logged = True
            time.sleep(0.01)

    def _unmatched(self, topic, publisher, nodes, every: bool = True) -> str:
        """What `publisher` (on `topic`) still waits for before it sends: '' once every
        node named in `nodes` subscribes there and the publisher has matched every
        subscription this node's graph shows there (a transient local one never matches a
        volatile publisher), or one at least if not `every`."""
        subscriptions = self.get_subscriptions_info_by_topic(topic)
        absent = sorted(set(nodes) - {subscription.node_name for subscription in subscriptions})
        if absent:
            return f"no subscription of {', '.join(absent)} to {topic}"
        matchable = sum(subscription.qos_profile.durability
                        != DurabilityPolicy.TRANSIENT_LOCAL for subscription in subscriptions)
        matched = publisher.get_subscription_count()
        if matched < (matchable if every else min(matchable, 1)):
            return f"{matched} of the {matchable} subscriptions to {topic} matched"
        return ""

    def _stream_plan(self, msg, plan, scene, planner, trajectory, boundaries):
        stack, held, gate = self._transition(scene, planner, plan, 0)
        # pik_node holds the first stack, and takes its targets, before the clock starts: a
        # service round trip or a discovery inside the clock (0.1-0.3 s under load) left
        # the robot that far behind at once
        self._hand_stack(stack, "plan", "not started")
        sent = stack                              # the stack pik_node holds
        # built once, before the clock starts (sampling a long plan takes 0.1-0.2 s), then
        # sent again restamped
        timed = self._joint_trajectory(trajectory)
        start, began = self.get_clock().now(), time.monotonic()
        self._send_timed(timed, start)
        self._publish_active(msg, 0, start, 0.0)
        due = self._publish_active(msg, 1, start, boundaries[1])
        paused = 0.0   # s streaming paused in the current transition (pik_node lost)
        held_by_call = 0.0   # s streaming waited in the current transition for set_stack
        #                      and its target topics
        self._status("executing", f"{len(plan.stances)} stances in {trajectory.duration:.2f} "
                                  f"s ({self.timing})")
        transition, last, t, next_tick = 0, len(plan.stances) - 2, 0.0, began
        while not self._stop.is_set():
            try:
                if stack != sent:
                    called_at = time.monotonic()
                    self._hand_stack(stack, f"transition {transition}",
                                     f"transition {transition} not started")
                    held_by_call += time.monotonic() - called_at
                    sent = stack
                lost = self._pik.lost()
                if lost:
                    raise PikLost(lost)
                self._stream(trajectory.sample(t)[0], stack, held)
            except PikLost as lost:
                lost_at = time.monotonic()
                sent = self._recover(str(lost), transition, t, trajectory, stack, sent)
                began, next_tick = time.monotonic() - t, time.monotonic()
                paused += next_tick - lost_at
                start = self.get_clock().now() - Duration(seconds=t)
                self._send_timed(timed, start)
                # waiting starts over with the new process
                gate = self._gate(gate.targets, gate.com)
                continue
            waiting = False
            while t >= boundaries[transition + 1]:
                end = boundaries[transition + 1]
                if not self._arrived(gate, transition):
                    waiting = True
                    break
                now = self.get_clock().now()
                late = (now - due).nanoseconds * 1e-9    # after the stamp announced
                superseded = transition < last and self._has_pending()
                why_late = late_reason(gate, late, paused, held_by_call) \
                    if gate.waiting_since is not None or late > LATE_STANCE else None
                if why_late:
                    start = now - Duration(seconds=end)
                if why_late or transition == last or superseded:
                    # again: stamped when reached if late, and where no next stance
                    # follows at once, what tells the stabilizer gate the robot is there
                    self._publish_active(msg, transition + 1, start, end)
                if transition < last and not superseded:
                    # the next transition starts: announced right away, so that the
                    # stabilizer gate sees a switch on at this end with one off at its start
                    due = self._publish_active(msg, transition + 2, start,
                                               boundaries[transition + 2])
                if why_late:
                    self._send_timed(timed, start)
                    self._status("executing", f"stance {transition + 1} reached {why_late}")
                if transition == last:
                    self._status("done", f"reached stance {len(plan.stances) - 1} of scene "
                                         f"{plan.scene!r}")
                    return
                if superseded:
                    self._stream(trajectory.sample(end)[0], stack, held)
                    self._status("executing", f"superseded by a newer plan at stance "
                                              f"{transition + 1}")
                    return
                transition += 1
                stack, held, gate = self._transition(scene, planner, plan, transition)
                paused = held_by_call = 0.0
            next_tick += self.period
            time.sleep(max(next_tick - time.monotonic(), 0.0))
            now = time.monotonic()
            next_tick = max(next_tick, now - self.period)   # no burst of catch-up ticks
            if waiting:   # the clock holds at the transition's end
                began = now - boundaries[transition + 1]
            else:         # a late tick advances MAX_TICK_ADVANCE periods at most
                began = max(began, now - t - MAX_TICK_ADVANCE * self.period)
            t = min(now - began, trajectory.duration)

    def _arrived(self, gate, transition) -> bool:
        """Whether the robot is at stance transition + 1 (pik_node's newest status): the
        contacts transition `transition` creates made, the CoM over the witness's;
        ExecutionError once it has been awaited arrival_timeout s."""
        now = time.monotonic()
        was_waiting = gate.waiting_since is not None
        poses = self._pik.frames(set(gate.targets) | {"com"})
        com = poses.pop("com", None)
        if gate.update(poses, now, None if com is None else com.translation):
            return True
        if not was_waiting:
            self.get_logger().info(f"waiting at stance {transition + 1} for the robot to "
                                   f"arrive: {gate.describe_late()}")
        elif gate.timed_out(now):
            raise ExecutionError(f"stance {transition + 1} not reached: after "
                                 f"{gate.waited(now):.2f} s, {gate.describe_late()} (arrival "
                                 f"tolerances {1e3 * gate.tolerance[0]:g} mm, "
                                 f"{gate.tolerance[1]:g} rad, CoM "
                                 f"{1e3 * gate.com_tolerance:g} mm)")
        return False

    def _recover(self, reason, transition, t, trajectory, stack, sent):
        """Streaming paused at sample time t (s): wait up to pik_restart_timeout s for
        pik_node to publish again; a new process gets the configuration at t and `stack`.
        Returns the stack pik_node then holds; ExecutionError when it does not come back or
        refuses them."""
        where = f"at transition {transition} (t = {t:.2f} s of {trajectory.duration:.2f} s)"
        self._status("executing", f"{reason} {where}: streaming paused, waiting up to "
                                  f"{self.pik_restart_timeout:g} s for it")
        lost_at = time.monotonic()
        while (restarted := self._pik.back(lost_at)) is None:
            if self._stop.is_set() or time.monotonic() - lost_at > self.pik_restart_timeout:
                raise ExecutionError(f"pik_node did not come back within "
                                     f"{self.pik_restart_timeout:g} s; {reason} {where}")
            time.sleep(0.01)
        self._pik.arm()
        if not restarted:
            self._status("executing", f"pik_node publishes again (same process) {where}; "
                                      "resuming")
            return sent
        try:
            self._call(self.set_configuration_client,
                       configuration_request(self.robot, trajectory.sample(t)[0]))
            self._call(self.set_stack_client, stack_request(stack))
        except ExecutionError as error:
            raise ExecutionError(f"pik_node restarted {where} but did not take the last "
                                 f"commanded configuration and stack: {error}") from None
        self._status("executing", f"pik_node restarted {where}; resuming from the last "
                                  "commanded configuration")
        return stack

    def _transition(self, scene, planner, plan, transition):
        """(stack, held contacts' frame targets by spot, ArrivalGate of the contacts it
        creates) of transition `transition` (stance i -> i + 1)."""
        stack, held, created = transition_tasks(scene, planner, plan, transition, self.gains)
        com = witness_com(self.robot.model, self._fk_data, plan.stances[transition + 1])
        return stack, held, self._gate(created, com)

    def _gate(self, targets, com) -> ArrivalGate:
        return ArrivalGate(targets, self.arrival_tolerance, self.arrival_timeout, com,
                           self.arrival_com_tolerance)

    def _stream(self, q, stack, held):
        """Publish every task's target at configuration q (nq) (tracking.task_targets)."""
        targets = task_targets(self.robot.model, self._fk_data, stack, held, q)
        header = Header(stamp=self.get_clock().now().to_msg(), frame_id="world")
        for spec in stack:
            value = targets[spec.name]
            if spec.kind == "posture":
                target = JointState(header=header, name=self._joints,
                                    position=value[self._joint_q_index].tolist())
            elif spec.kind == "com":
                target = PointStamped(header=header)
                target.point.x, target.point.y, target.point.z = (float(v) for v in value)
            else:
                target = PoseStamped(header=header)
                fill_pose_msg(target.pose, pin.SE3ToXYZQUAT(value))
            self._target_publisher(spec).publish(target)

    def _target_publisher(self, spec):
        key = (spec.name, TARGET_TYPES[spec.kind])
        if key not in self._target_pubs:
            self._target_pubs[key] = self.create_publisher(
                key[1], target_topic(spec.name), RELIABLE)
        return self._target_pubs[key]

    def _publish_active(self, msg, index, start, ends_after):
        """Stance `index` of the plan message, stamped start + ends_after (s); returns the
        stamp (rclpy Time)."""
        stance = copy.deepcopy(msg.stances[index])
        stance.index = index
        stamp = start + Duration(seconds=float(ends_after))
        stance.header = Header(stamp=stamp.to_msg(), frame_id="world")
        self.active_stance_pub.publish(stance)
        return stamp

    def _send_timed(self, timed: JointTrajectory, start):
        """Publish the timed plan (_joint_trajectory) starting at `start` (rclpy Time)."""
        timed.header.stamp = start.to_msg()
        self.trajectory_pub.publish(timed)

    def _joint_trajectory(self, trajectory) -> JointTrajectory:
        """The timed plan at its samples' times: actuated 1-DoF joints (rad, rad/s); its
        header stamp (the start) is set when sent."""
        msg = JointTrajectory(header=Header(frame_id="world"), joint_names=self._joints)
        for t in trajectory.times:
            q, v = trajectory.sample(float(t))
            msg.points.append(JointTrajectoryPoint(
                positions=q[self._joint_q_index].tolist(),
                velocities=v[self._joint_v_index].tolist(),
                time_from_start=Duration(seconds=float(t)).to_msg()))
        return msg

    def _call(self, client, request):
        """Call a pik_node service from the executor thread (rclpy's executor handles the
        answer): wait at most service_timeout s for the service and its answer; PikLost as
        soon as the watch loses pik_node. Unanswered, the request is sent again every
        RESEND_PERIOD s: after a restart the dead server still counts as available until
        its lease expires, and a request sent before the new server matched is lost (both
        services are idempotent). An answer later than SLOW_CALL s is logged: the stream
        waited."""
        called = time.monotonic()
        deadline, future, sent = called + self.service_timeout, None, 0.0
        while future is None or not future.done():
            lost = self._pik.lost()
            if lost or time.monotonic() > deadline or self._stop.is_set():
                if future is not None:
                    client.remove_pending_request(future)
                if lost:
                    raise PikLost(lost)
                raise ExecutionError(f"no answer from {client.srv_name}" if future else
                                     f"{client.srv_name} not available after "
                                     f"{self.service_timeout:g} s")
            if future is not None and time.monotonic() - sent > RESEND_PERIOD:
                client.remove_pending_request(future)
                future = None
            if future is None and client.service_is_ready():
                future, sent = client.call_async(request), time.monotonic()
            time.sleep(0.002)
        response = future.result()
        waited = time.monotonic() - called
        if waited > SLOW_CALL:
            self.get_logger().warning(f"{client.srv_name} answered after {waited:.2f} s "
                                      "(streaming waited)")
        if not response.success:
            raise ExecutionError(f"{client.srv_name}: {response.message}")
        return response

    def _status(self, state: str, message: str):
        with self._status_lock:
            self._state = state
            text = f"{state}: {message}"
            self.status_pub.publish(String(data=text))
            if state == "failed":
                self.get_logger().error(text)
            else:
                self.get_logger().info(text)

    def _status_by_what_goes_on(self, preparing_counts: bool, executing: str, prepared: str,
                                alone: tuple):
        """Publish `executing` (state executing) while a plan executes, else `prepared`
        (state interpolating) while one is prepared (ready, handed over and not taken yet,
        or when `preparing_counts` one the preparer works on), else alone = (state,
        message): decided from the flags and the last status (an execution that said
        `done` or `failed` is over) and published under the status lock, before any other
        thread's status."""
        with self._status_lock:
            with self._wakeup:
                is_executing = self._executing and self._state not in ("done", "failed")
                is_prepared = self._ready is not None or self._pending is not None or \
                    (preparing_counts and self._preparing)
            if is_executing:
                self._status("executing", executing)
            elif is_prepared:
                self._status("interpolating", prepared)
            else:
                self._status(*alone)


def _require_verified(plan, scene, robot, shown: int = 3, should_stop=None) -> None:
    """PlanRejected naming the first `shown` failures of the plan's verification, if any
    (stopping.Stopped once should_stop answers True: verify_plan's)."""
    failures = verify_plan(plan, scene, robot, should_stop=should_stop).failures
    if failures:
        more = f" (and {len(failures) - shown} more)" if len(failures) > shown else ""
        raise PlanRejected(f"fails verification: {'; '.join(failures[:shown])}{more}")


def late_reason(gate, late, paused, held_by_call) -> str:
    """Why the stance `gate` awaited was reached `late` s after its stamp, for the status:
    a wait for the robot, streaming `paused` s for a lost pik_node, or `held_by_call` s
    by the set_stack call that started the transition and the match of its target topics
    (_hand_stack), late ticks for the rest."""
    pause = f"streaming paused {paused:.2f} s for pik_node" if paused else ""
    if gate.waiting_since is not None:
        waited = (f"waiting {gate.waited(time.monotonic()):.2f} s for the robot to arrive "
                  f"({gate.describe_late(gate.late_when_due)} when due)")
        return f"after {pause + ' and ' if pause else ''}{waited}"
    causes = [pause] if pause else []
    if held_by_call > NOTED_DELAY:
        causes.append(f"streaming held {held_by_call:.2f} s by the /pik/set_stack call "
                      "and its target topics")
    rest = late - paused - held_by_call
    if not causes:
        causes.append("late ticks: trajectory_node starved, the motion slowed")
    elif rest > NOTED_DELAY:
        causes.append(f"late ticks {rest:.2f} s: trajectory_node starved, the motion slowed")
    return f"{late:.2f} s late ({'; '.join(causes)})"


def main(args=None):
    return run_node("trajectory_node", TrajectoryNode,
                    (ParameterException, RobotModelError, OSError, ValueError), args,
                    start=TrajectoryNode.start_worker, stop=TrajectoryNode.stop_worker)


if __name__ == "__main__":
    sys.exit(main())
