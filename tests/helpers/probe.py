"""Test-side rclpy nodes spun in a background thread (stance_tools.background_node): a probe
that talks to pik_node (collects its outputs, publishes targets, calls its services)."""

from __future__ import annotations

import threading
import time

from geometry_msgs.msg import PointStamped, PoseStamped
from pik_node.node import fill_pose_msg
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from sensor_msgs.msg import JointState
from stance_msgs.msg import SolverStatus
from stance_msgs.srv import SetConfiguration, SetStack, SetTaskEnabled
from stance_tools.background_node import BackgroundNode

RELIABLE = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
# pik_node's 500 Hz streams: 2 s of queue. At depth 10 a probe slowed by a loaded machine
# had the reader overwrite statuses it had not taken (a CI run lost the first ones after a
# new support polygon, the only ones with the CoM far outside it).
STREAMS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


class PikProbe(BackgroundNode):
    """Collects pik_node's outputs, publishes targets, calls its services."""

    def __init__(self, name="pik_probe", domain_id=None):
        super().__init__(name, domain_id)
        self.lock = threading.Lock()
        self.joint_states = []
        self.statuses = []
        self.node.create_subscription(JointState, "/joint_states", self._on_joint_state,
                                      STREAMS)
        self.node.create_subscription(SolverStatus, "/pik/status", self._on_status, STREAMS)
        self.set_stack_client = self.node.create_client(SetStack, "/pik/set_stack")
        self.set_enabled_client = self.node.create_client(SetTaskEnabled,
                                                          "/pik/set_task_enabled")
        self._publishers = {}
        self.start_spinning()

    def _on_joint_state(self, msg):
        with self.lock:
            self.joint_states.append((time.monotonic(), msg))

    def _on_status(self, msg):
        with self.lock:
            self.statuses.append(msg)

    def latest_status(self):
        with self.lock:
            return self.statuses[-1] if self.statuses else None

    def latest_joint_state(self):
        with self.lock:
            return self.joint_states[-1][1] if self.joint_states else None

    def status_count(self):
        with self.lock:
            return len(self.statuses)

    def fresh_output(self, timeout=10.0):
        """The latest (joint state, status) once both are of IK steps stamped after this
        call. pik_node stamps a step once its inputs are frozen, so both reflect every input
        acknowledged before the call (the two clocks are the system clock). Counting
        arrivals does not: a probe slowed by a loaded machine can still be taking steps
        from before the call."""
        called = self.node.get_clock().now()

        def stamped_after(msg):
            return msg is not None and Time.from_msg(msg.header.stamp) > called

        deadline = time.monotonic() + timeout
        while not (stamped_after(self.latest_joint_state())
                   and stamped_after(self.latest_status())):
            if time.monotonic() > deadline:
                raise TimeoutError(f"no pik_node step stamped after {called} in {timeout} s")
            time.sleep(0.02)
        return self.latest_joint_state(), self.latest_status()

    def publish_target(self, task, msg):
        topic = f"/pik/tasks/{task}/target"
        if topic not in self._publishers:
            self._publishers[topic] = self.node.create_publisher(type(msg), topic, RELIABLE)
        publisher = self._publishers[topic]
        deadline = time.monotonic() + 5.0
        while publisher.get_subscription_count() == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        publisher.publish(msg)

    def call(self, client, request, timeout=10.0):
        if not client.wait_for_service(timeout_sec=timeout):
            raise TimeoutError(f"service {client.srv_name} not available")
        future = client.call_async(request)
        deadline = time.monotonic() + timeout
        while not future.done() and time.monotonic() < deadline:
            time.sleep(0.01)
        if not future.done():
            raise TimeoutError(f"no response from {client.srv_name}")
        return future.result()

def task_status(status, name):
    for task in status.tasks:
        if task.name == name:
            return task
    raise KeyError(name)


def pose_target(pose, frame_id="world"):
    msg = PoseStamped()
    msg.header.frame_id = frame_id
    msg.pose = pose
    return msg


def point_target(x, y, z, frame_id="world"):
    msg = PointStamped()
    msg.header.frame_id = frame_id
    msg.point.x, msg.point.y, msg.point.z = x, y, z
    return msg


def configuration_request(robot, q, joints=None):
    """/pik/set_configuration request: base pose from q, the joints named in `joints`
    ({name: rad}) or else every actuated joint at its value in q."""
    request = SetConfiguration.Request()
    fill_pose_msg(request.base_pose, q[:7])
    positions = joints if joints is not None else robot.actuated_positions(q)
    request.joints.name = list(positions)
    request.joints.position = [float(v) for v in positions.values()]
    return request
