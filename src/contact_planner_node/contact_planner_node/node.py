"""contact_planner_node: contact-before-motion planning (Escande et al.) as a ROS 2 action.

Thin adapter over stance.planning.planner.plan_contacts. Goals arrive on the PlanContacts
action; the goal is converted and checked in an executor worker thread (MultiThreadedExecutor,
reentrant callback group) and planned in a child process (worker.PlannerProcess), so the
node keeps serving goal, cancel and result requests whatever the planner does. One plan at
a time: a goal arriving while a plan runs is rejected (and logged). A goal that cannot be
planned (malformed scene, NaN, unknown spot, surface or frame) is accepted and aborted
with success false, a reason code and a message naming the field. A cancel request stops
the planner at its next posture generation, or kills its process after CANCEL_GRACE s.

Action, topics (QoS in parentheses):
  action /contact_planner/plan_contacts   stance_msgs/action/PlanContacts
                                          (feedback at most FEEDBACK_RATE Hz)
  pub    /contact_planner/plan            stance_msgs/StancePlan, the last successful plan
                                          (reliable, transient local, depth 1)
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import asdict

from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.exceptions import ParameterException
from rclpy.executors import MultiThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from pik_node.node import run_node
from stance import Robot, RobotModelError
from stance.planning.planner import CANCELLED, PlanOutcome, PlanProgress
from stance_msgs.action import PlanContacts
from stance_msgs.msg import StancePlan

from .conversions import GoalRejected, request_from_goal, scene_from_goal, stance_plan_msg
from .worker import CANCEL_GRACE, PLANNER_ERROR, PlannerProcess, PlannerProcessError

ACTION_NAME = "/contact_planner/plan_contacts"
PLAN_TOPIC = "/contact_planner/plan"
FEEDBACK_RATE = 5.0  # Hz, at most
MAX_WORKERS = 16     # planner worker processes at most
STOP_WAIT = 10 * CANCEL_GRACE  # s shutdown waits for a running plan to return
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)


class ContactPlannerNode(Node):
    def __init__(self, **kwargs):
        super().__init__("contact_planner_node", **kwargs)
        self._declare_parameters()
        get = self.get_parameter
        self.robot_spec = get("robot").value
        self.robot = Robot.load(self.robot_spec)
        if not self.robot.floating_base:
            raise RobotModelError(f"robot {self.robot_spec!r} has no free-flyer base: the "
                                  "contact planner moves the base through contacts")
        self.default_scene = get("default_scene").value
        self.max_nodes = get("max_nodes").value
        self.time_budget = get("time_budget").value
        self.workers = get("workers").value
        try:  # the default scene must load, for this robot
            scene_from_goal(PlanContacts.Goal(), self.default_scene, self.robot_spec, self.robot)
        except GoalRejected as error:
            raise ValueError(f"default_scene {self.default_scene!r}: {error}") from None
        self.planner = PlannerProcess(self.robot_spec)
        self._busy = threading.Lock()          # held from goal acceptance to the result
        self._stopping = threading.Event()     # the node shuts down: running plans stop
        self._plan_state = threading.Condition()  # guards _planning against _stopping
        self._planning = False                 # a goal is using the planner process
        self.plan_pub = self.create_publisher(StancePlan, PLAN_TOPIC, LATCHED)
        self._action_server = ActionServer(
            self, PlanContacts, ACTION_NAME, execute_callback=self._execute,
            goal_callback=self._on_goal, cancel_callback=lambda _: CancelResponse.ACCEPT,
            callback_group=ReentrantCallbackGroup())
        self.get_logger().info(
            f"robot {self.robot_spec}, default scene {self.default_scene}, max_nodes "
            f"{self.max_nodes}, time_budget {self.time_budget:g} s, workers {self.workers}; "
            f"serving {ACTION_NAME}")

    def _declare_parameters(self):
        def describe(text, **extra):
            return ParameterDescriptor(description=text, read_only=True, **extra)

        self.declare_parameter("robot", "talos", describe(
            "example-robot-data name or URDF path (free-flyer base); scenes must name it"))
        self.declare_parameter("default_scene", "chair_table", describe(
            "shipped scene name or scene file path, for goals naming no scene"))
        self.declare_parameter("max_nodes", 2400, describe(
            "nodes expanded at most, for goals with max_nodes 0",
            integer_range=[IntegerRange(from_value=1, to_value=2**32 - 1, step=1)]))
        self.declare_parameter("time_budget", 900.0, describe(
            "planning wall time at most (s), for goals with time_budget 0",
            floating_point_range=[FloatingPointRange(from_value=0.1, to_value=1e6)]))
        self.declare_parameter("workers", 1, describe(
            "processes generating a node's first sons together (1: the planner process "
            "alone; more use more cores, same plan)",
            integer_range=[IntegerRange(from_value=1, to_value=MAX_WORKERS, step=1)]))

    def stop_planning(self):
        """Make a running plan stop (shutdown) and wait, at most STOP_WAIT s, until it has
        left the planner process: rclpy's Executor.shutdown(timeout_sec) does not wait for
        running callbacks, so destroy_node would otherwise close the planner process under
        the plan's thread. A goal accepted but not yet executing never starts planning."""
        with self._plan_state:
            self._stopping.set()
            if not self._plan_state.wait_for(lambda: not self._planning, timeout=STOP_WAIT):
                self.get_logger().warning(f"the running plan did not end within {STOP_WAIT} "
                                          "s of shutdown; closing its planner process anyway")

    def destroy_node(self):
        self.planner.close()
        return super().destroy_node()

    def _on_goal(self, goal):
        if self._busy.acquire(blocking=False):
            return GoalResponse.ACCEPT
        self.get_logger().warning("goal rejected: a plan is already running (one at a time)")
        return GoalResponse.REJECT

    def _execute(self, goal_handle) -> PlanContacts.Result:
        with self._plan_state:
            planning = self._planning = not self._stopping.is_set()
        try:
            if not planning:
                goal_handle.abort()
                return PlanContacts.Result(success=False, reason=CANCELLED,
                                           message="the node is shutting down")
            return self._plan(goal_handle)
        finally:
            with self._plan_state:
                self._planning = False
                self._plan_state.notify_all()
            self._busy.release()

    def _plan(self, goal_handle) -> PlanContacts.Result:
        started = time.monotonic()
        goal = goal_handle.request
        try:
            scene = scene_from_goal(goal, self.default_scene, self.robot_spec, self.robot)
            request = request_from_goal(goal, scene, self.robot, self.max_nodes,
                                        self.time_budget, self.workers)
        except GoalRejected as error:
            self.get_logger().warning(f"goal refused ({error.reason}): {error}")
            goal_handle.abort()
            return PlanContacts.Result(success=False, reason=error.reason, message=str(error),
                                       planning_time=time.monotonic() - started)
        relay = FeedbackRelay(goal_handle)
        self.get_logger().info(f"planning on scene {scene.name} (max_nodes "
                               f"{request.max_nodes}, time_budget {request.time_budget:g} s)")
        try:
            outcome = self.planner.plan(
                request, progress=relay.report,
                should_stop=lambda: goal_handle.is_cancel_requested or self._stopping.is_set())
        except PlannerProcessError as error:
            self.get_logger().error(str(error))
            outcome = PlanOutcome(PLANNER_ERROR, str(error))
        statistics = {**asdict(relay.last), **outcome.statistics}
        result = PlanContacts.Result(
            success=outcome.success, reason=outcome.reason, message=outcome.message,
            nodes_expanded=int(statistics["nodes_expanded"]),
            posture_generations=int(statistics["posture_generations"]),
            planning_time=time.monotonic() - started)
        if outcome.success:
            result.plan = stance_plan_msg(outcome.plan, scene, self.robot,
                                          self.get_clock().now().to_msg())
            result.stances = len(result.plan.stances)
            self.plan_pub.publish(result.plan)
            goal_handle.succeed()
        elif outcome.reason == CANCELLED and goal_handle.is_cancel_requested:
            goal_handle.canceled()
        else:
            goal_handle.abort()
        self.get_logger().info(f"{outcome.reason} after {result.planning_time:.1f} s, "
                               f"{result.nodes_expanded} nodes, {result.stances} stances: "
                               f"{outcome.message}")
        return result


class FeedbackRelay:
    """Planner progress reports -> action feedback, at most FEEDBACK_RATE per second; keeps
    the last report (the result's counts when the planner's statistics lack them)."""

    def __init__(self, goal_handle):
        self._goal_handle = goal_handle
        self._next_publish = 0.0
        self.last = PlanProgress(nodes_expanded=0, posture_generations=0,
                                 best_potential=float("inf"), elapsed=0.0)

    def report(self, progress: PlanProgress) -> None:
        self.last = progress
        now = time.monotonic()
        if now < self._next_publish:
            return
        self._next_publish = now + 1.0 / FEEDBACK_RATE
        self._goal_handle.publish_feedback(PlanContacts.Feedback(
            nodes_expanded=progress.nodes_expanded,
            posture_generations=progress.posture_generations,
            best_potential=float(progress.best_potential), elapsed=float(progress.elapsed)))


def main(args=None):
    # Threads: one runs the plan, the others serve goal, cancel and result requests.
    return run_node("contact_planner_node", ContactPlannerNode,
                    (RobotModelError, ParameterException, OSError, ValueError), args,
                    stop=ContactPlannerNode.stop_planning,
                    make_executor=lambda: MultiThreadedExecutor(num_threads=4))


if __name__ == "__main__":
    sys.exit(main())
