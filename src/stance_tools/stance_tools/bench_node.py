"""`stance bench node`: pik_node's loop as a user sees it over DDS.

Starts pik_node in its own process at the requested rate, then, from this process:
  - rate: counts /joint_states and calls a cycle on time when the interval between
    consecutive header stamps (each step's start) is within +-50% of the period; the node's
    own count of periods missed by late steps (/pik/status overruns) is reported beside it;
  - latency: publishes right-hand targets (distinct header stamps, 50 Hz) and, for each,
    finds the /pik/status that first reports it in last_input_stamp; the latency is from
    the target's stamp to the arrival here of the /joint_states with that status' stamp,
    i.e. the first joint state computed with the new target.
Both processes read the same system clock.
"""

from __future__ import annotations

import json
import os
import signal
import struct
import subprocess
import threading
import time

import numpy as np

from .cli import positive


STAMP = struct.Struct("<iI")  # header.stamp after the 4-byte CDR encapsulation header


def add_node_arguments(parser) -> None:
    parser.add_argument("--rate", type=positive(float), default=500.0, help="pik_node rate (Hz)")
    parser.add_argument("--duration", type=positive(float), default=10.0, help="measured seconds")
    parser.add_argument("--target-rate", type=positive(float), default=50.0,
                        help="targets published per second")
    parser.add_argument("--json", help="also write the figures to this JSON file")


def run_node(args) -> int:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from stance_msgs.msg import SolverStatus

    reliable = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    node_process = subprocess.Popen(
        ["pik_node", "--ros-args", "-p", f"rate:={args.rate}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT, start_new_session=True)
    rclpy.init()
    node = Node("bench_node")
    arrivals = {}        # joint_states stamp (ns) -> arrival time (ns)
    first_status = {}    # last_input_stamp (ns) -> first status stamp (ns) reporting it
    cycle_counts = []    # (cycles, overruns) from each status
    hand_target = []
    lock = threading.Lock()

    def on_joint_states(cdr: bytes):
        now = time.time_ns()  # the stamp is read from the CDR bytes: no deserialization
        sec, nanosec = STAMP.unpack_from(cdr, 4)
        with lock:
            arrivals[sec * 1_000_000_000 + nanosec] = now

    def on_status(msg):
        with lock:
            first_status.setdefault(_ns(msg.last_input_stamp), _ns(msg.header.stamp))
            cycle_counts.append((msg.cycles, msg.overruns))
            if not hand_target:
                hand_target.extend(t.target for t in msg.tasks if t.name == "right_hand")

    node.create_subscription(JointState, "/joint_states", on_joint_states, reliable, raw=True)
    node.create_subscription(SolverStatus, "/pik/status", on_status, reliable)
    publisher = node.create_publisher(PoseStamped, "/pik/tasks/right_hand/target", reliable)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    spinning = threading.Event()
    spinning.set()
    spinner = threading.Thread(target=lambda: _spin(executor, spinning), daemon=True)
    spinner.start()
    try:
        if not _wait(lambda: hand_target and publisher.get_subscription_count() > 0, 60):
            print("pik_node did not come up within 60 s")
            return 1
        time.sleep(1.0)  # let the loop settle after discovery
        with lock:
            arrivals.clear()
            start_counts = cycle_counts[-1]
        sent = _publish_targets(node, publisher, hand_target[0], args)
        time.sleep(0.2)
        with lock:
            stamps = np.array(sorted(arrivals))
            arrival_of = dict(arrivals)
            reported = dict(first_status)
            end_counts = cycle_counts[-1]
    finally:
        spinning.clear()
        spinner.join(timeout=2.0)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        os.killpg(node_process.pid, signal.SIGINT)
        node_process.wait(timeout=10)

    figures = _figures(stamps, arrival_of, reported, sent, args.rate)
    cycles, overruns = (end - start for end, start in zip(end_counts, start_counts))
    figures["node_cycles"], figures["node_overruns"] = int(cycles), int(overruns)
    figures["node_on_time_fraction"] = float(cycles / (cycles + overruns)) if cycles else 0.0
    _print(figures, args)
    if args.json:
        with open(args.json, "w") as stream:
            json.dump(figures, stream, indent=2)
    return 0


def _publish_targets(node, publisher, start_pose, args) -> list:
    """Publish a slowly moving right-hand target; return the stamps sent (ns)."""
    from geometry_msgs.msg import PoseStamped
    sent = []
    period = 1.0 / args.target_rate
    begin = time.monotonic()
    while time.monotonic() - begin < args.duration:
        phase = time.monotonic() - begin
        msg = PoseStamped()
        msg.header.frame_id = "world"
        msg.header.stamp = node.get_clock().now().to_msg()
        msg.pose = type(start_pose)()
        msg.pose.position.x = start_pose.position.x + 0.05 * np.sin(phase)
        msg.pose.position.y = start_pose.position.y
        msg.pose.position.z = start_pose.position.z + 0.05 * (1 - np.cos(phase))
        msg.pose.orientation = start_pose.orientation
        publisher.publish(msg)
        sent.append(_ns(msg.header.stamp))
        time.sleep(max(0.0, period - (time.monotonic() - begin - phase)))
    return sent


def _figures(stamps, arrival_of, reported, sent, rate) -> dict:
    period = 1e9 / rate
    intervals = np.diff(stamps) if len(stamps) > 1 else np.zeros(0)
    on_time = (intervals > 0.5 * period) & (intervals < 1.5 * period)
    latencies = [arrival_of[reported[stamp]] - stamp for stamp in sent
                 if stamp in reported and reported[stamp] in arrival_of]
    latencies = np.array(latencies) / 1e6
    span = (stamps[-1] - stamps[0]) / 1e9 if len(stamps) > 1 else float("nan")
    return {
        "rate_hz": rate,
        "cycles": int(len(stamps)),
        "achieved_rate_hz": float((len(stamps) - 1) / span) if len(stamps) > 1 else 0.0,
        "on_time_fraction": float(on_time.mean()) if len(on_time) else 0.0,
        "interval_p99_ms": float(np.percentile(intervals, 99) / 1e6) if len(intervals) else 0,
        "targets_sent": len(sent),
        "targets_matched": int(len(latencies)),
        "latency_median_ms": float(np.median(latencies)) if len(latencies) else float("nan"),
        "latency_p99_ms": float(np.percentile(latencies, 99)) if len(latencies) else
        float("nan"),
    }


def _print(figures, args) -> None:
    print(f"pik_node loop at {figures['rate_hz']:g} Hz over {args.duration:g} s "
          f"({figures['cycles']} cycles)")
    print(f"  achieved rate       {figures['achieved_rate_hz']:8.1f} Hz")
    print(f"  cycles on time      {100 * figures['on_time_fraction']:8.2f} %  "
          f"(interval within +-50% of the period; p99 interval "
          f"{figures['interval_p99_ms']:.2f} ms)")
    print(f"  node's own count    {100 * figures['node_on_time_fraction']:8.2f} %  on time "
          f"({figures['node_overruns']} periods missed by late steps in "
          f"{figures['node_cycles']} cycles)")
    print(f"  target -> joint_states latency  median {figures['latency_median_ms']:.2f} ms, "
          f"p99 {figures['latency_p99_ms']:.2f} ms  "
          f"({figures['targets_matched']}/{figures['targets_sent']} targets matched)")


def _spin(executor, spinning):
    while spinning.is_set():
        executor.spin_once(timeout_sec=0.05)


def _wait(predicate, timeout) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return False


def _ns(stamp) -> int:
    return stamp.sec * 1_000_000_000 + stamp.nanosec
