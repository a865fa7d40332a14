"""Test publisher for the recorder: a latched /robot_description, then a steady stream.

1. Publishes a small URDF on /robot_description (std_msgs/String, transient local) and prints
   ``latched``.
2. After --start-delay seconds creates the stream publishers (so a recorder started in between
   must discover topics that appear later), waits until each has a subscriber, then publishes
   at --rate Hz for --duration s, on each tick, a sensor_msgs/JointState on /joint_states and a
   stance_msgs/SolverStatus on /pik/status, both carrying the tick's sequence number.
3. Waits until the subscribers acknowledged everything and prints one JSON line with the
   published counts, e.g. ``{"/joint_states": 5000, "/pik/status": 5000}``.

Message contents are a pure function of the sequence number (``joint_state(seq)``,
``solver_status(seq)``), so a test can rebuild exactly what was sent.
"""

import argparse
import json
import math
import sys
import time

import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, Quaternion
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState
from stance_msgs.msg import LevelStatus, SolverStatus, TaskStatus
from std_msgs.msg import Header, String

JOINT_NAMES = ["hip_pitch", "knee", "ankle_pitch", "shoulder_roll", "elbow", "slider"]
URDF = """<?xml version="1.0"?>
<robot name="stream_test">
  <link name="base"/><link name="thigh"/><link name="shin"/><link name="foot"/>
  <link name="arm"/><link name="forearm"/><link name="rail"/><link name="base_tool"/>
  <joint name="hip_pitch" type="revolute"><parent link="base"/><child link="thigh"/>
    <limit lower="-2.0" upper="0.7" effort="100" velocity="5"/></joint>
  <joint name="knee" type="revolute"><parent link="thigh"/><child link="shin"/>
    <limit lower="0.0" upper="2.6" effort="100" velocity="5"/></joint>
  <joint name="ankle_pitch" type="revolute"><parent link="shin"/><child link="foot"/>
    <limit lower="-1.3" upper="0.77" effort="100" velocity="5"/></joint>
  <joint name="shoulder_roll" type="revolute"><parent link="base"/><child link="arm"/>
    <limit lower="-0.5" upper="1.5" effort="50" velocity="5"/></joint>
  <joint name="elbow" type="revolute"><parent link="arm"/><child link="forearm"/>
    <limit lower="-2.0" upper="0.0" effort="50" velocity="5"/></joint>
  <joint name="slider" type="prismatic"><parent link="base"/><child link="rail"/>
    <limit lower="-0.1" upper="0.1" effort="50" velocity="1"/></joint>
  <joint name="fixed_tool" type="fixed"><parent link="forearm"/><child link="base_tool"/></joint>
  <transmission name="t"><joint name="knee"/></transmission>
</robot>
"""
STAMP_ORIGIN_S = 1_000_000  # deterministic stamps: origin + seq * 2 ms


def stamp(seq):
    nanoseconds = seq * 2_000_000
    return Time(sec=STAMP_ORIGIN_S + nanoseconds // 10**9, nanosec=nanoseconds % 10**9)


def joint_state(seq):
    """Positions (rad, m) sweeping inside and slightly beyond the URDF limits."""
    t = seq * 0.002
    return JointState(
        header=Header(stamp=stamp(seq), frame_id=str(seq)), name=JOINT_NAMES,
        position=[-0.6 + 1.3 * math.sin(t), 1.2 + 1.3 * math.sin(0.7 * t),
                  -0.2 + 0.9 * math.sin(1.3 * t), 0.5 * math.cos(0.5 * t), -0.3,
                  0.08 * math.sin(2.0 * t)],
        velocity=[math.cos(t + i) for i in range(len(JOINT_NAMES))],
        effort=[float(seq % 10 + i) for i in range(len(JOINT_NAMES))])


def solver_status(seq):
    """A SolverStatus with every nested field filled; clamping_iterations carries seq."""
    t = seq * 0.002

    def pose(x):
        return Pose(position=Point(x=x, y=-x, z=0.5 * x), orientation=Quaternion(w=1.0))

    damping = [max(0.0, min(1.0, math.sin(t + i))) for i in range(len(JOINT_NAMES))]
    return SolverStatus(
        header=Header(stamp=stamp(seq), frame_id=str(seq)), strategy="progressive",
        clamping_iterations=seq, solve_time=1e-4 * (1 + seq % 7),
        levels=[LevelStatus(priority=0, tasks=["left_sole", "right_sole"],
                            residual_norm=1e-9 * (1 + seq % 3), step_residual_norm=1e-12),
                LevelStatus(priority=1, tasks=["com"], residual_norm=math.exp(-t),
                            step_residual_norm=0.1 * math.exp(-t))],
        tasks=[TaskStatus(name=name, priority=priority, enabled=True,
                          error_norm=scale * math.exp(-t), target=pose(scale), current=pose(t))
               for name, priority, scale in (("left_sole", 0, 1e-9), ("right_sole", 0, 2e-9),
                                             ("com", 1, 1.0))],
        joint_names=JOINT_NAMES, damping=damping, clamped=[h >= 1.0 for h in damping],
        last_input_stamp=stamp(seq), rejected_inputs=seq // 1000,
        last_rejection="" if seq < 1000 else f"bad target {seq // 1000}")


def wait_for_subscribers(publishers, timeout):
    deadline = time.monotonic() + timeout
    while any(p.get_subscription_count() == 0 for p in publishers):
        if time.monotonic() > deadline:
            sys.exit(f"no subscriber after {timeout} s")
        time.sleep(0.01)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=500.0, help="Hz")
    parser.add_argument("--duration", type=float, default=10.0, help="s")
    parser.add_argument("--start-delay", type=float, default=1.0, help="s")
    args = parser.parse_args()

    rclpy.init()
    node = rclpy.create_node("publish_stream")
    latched = node.create_publisher(
        String, "/robot_description",
        QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    latched.publish(String(data=URDF))
    print("latched", flush=True)
    time.sleep(args.start_delay)

    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)  # the ROS default
    streams = {"/joint_states": (node.create_publisher(JointState, "/joint_states", qos),
                                 joint_state),
               "/pik/status": (node.create_publisher(SolverStatus, "/pik/status", qos),
                               solver_status)}
    wait_for_subscribers([publisher for publisher, _ in streams.values()], timeout=30.0)
    counts = dict.fromkeys(streams, 0)
    period = 1.0 / args.rate
    start = time.monotonic()
    for seq in range(round(args.rate * args.duration)):
        time.sleep(max(0.0, start + seq * period - time.monotonic()))
        for topic, (publisher, build) in streams.items():
            publisher.publish(build(seq))
            counts[topic] += 1
    for publisher, _ in streams.values():
        publisher.wait_for_all_acked(Duration(seconds=10))
    print(json.dumps(counts), flush=True)
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
