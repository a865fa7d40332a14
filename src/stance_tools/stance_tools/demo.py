"""`stance demo`: the PIK demo on Talos, recorded and plotted.

pik_node (feet fixed > CoM over the feet > right hand > posture, progressive clamping,
500 Hz), the recorder, and a scripted right-hand path that drives the arm into its damping
zones and onto its limits, each in its own process; then the plots of the bag.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .processes import ProcessGroup

DEFAULT_OUTPUT = Path("out") / "demo"


def add_arguments(parser) -> None:
    parser.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT,
                        help="directory for the bag, the plots and the logs")
    parser.add_argument("--path", default="reach_limits",
                        help="right-hand path: built-in name or YAML file")
    parser.add_argument("--strategy", default="progressive",
                        choices=["none", "clamping", "progressive"])


def run(args) -> int:
    from ament_index_python.packages import get_package_share_directory

    output = args.output.resolve()
    bag = output / "bag"
    if bag.exists():
        _remove_bag(bag)
    params = Path(get_package_share_directory("pik_node")) / "config" / "pik_node.yaml"
    group = ProcessGroup(output / "logs")
    try:
        pik = group.start("pik_node", "--ros-args", "--params-file", str(params),
                          "-p", f"strategy:={args.strategy}", name="pik_node")
        recorder = group.start("stance", "record", "-o", str(bag), "--all", name="record")
        print(f"started pik_node and the recorder (logs in {output / 'logs'})")
        if not _wait_for_recorder(pik, recorder):
            return _fail(group, "pik_node or the recorder did not come up; see the logs")
        teleop = group.start("stance", "teleop", "--task", "right_hand", "--path", args.path,
                             name="teleop")
        print(f"right hand follows the '{args.path}' path ...")
        if teleop.wait() != 0:
            return _fail(group, f"teleop failed: {teleop.log_path.read_text()[-2000:]}")
        time.sleep(0.5)
        recorder_code = group.stop(recorder)
        print(recorder.log_path.read_text().strip())
        group.stop(pik)
        if recorder_code != 0:
            return _fail(group, "the recorder reported lost or unwritten messages")
    finally:
        group.stop_all()
    print(f"\nbag: {bag}\nplots:")
    return _plot(bag, output / "plots")


def _plot(bag: Path, output: Path) -> int:
    from . import plot

    parser = argparse.ArgumentParser(prog="stance plot")
    plot.add_arguments(parser)
    return plot.run(parser.parse_args([str(bag), "-o", str(output)]))


def _wait_for_recorder(pik, recorder, timeout: float = 60.0) -> bool:
    """True once pik_node publishes and the recorder subscribes to its status."""
    import rclpy
    from rclpy.node import Node

    rclpy.init()
    node = Node("stance_demo")
    try:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if pik.poll() is not None or recorder.poll() is not None:
                return False
            if node.count_publishers("/pik/status") and \
                    node.count_subscribers("/pik/status") and \
                    node.count_subscribers("/joint_states"):
                return True
            time.sleep(0.1)
        return False
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def _remove_bag(bag: Path) -> None:
    for child in bag.iterdir():
        child.unlink()
    bag.rmdir()


def _fail(group, message: str) -> int:
    group.stop_all()
    print(f"stance demo: {message}", file=sys.stderr)
    return 1
