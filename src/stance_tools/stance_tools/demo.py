"""`stance demo`: a recorded, plotted and checked run of Stance on Talos.

--scenario pik: the PIK demo: pik_node (feet fixed > CoM over the feet > right hand >
posture, progressive clamping, 500 Hz), the recorder, and a scripted right-hand path that
drives the arm into its damping zones and onto its limits, each in its own process; then
the plots of the bag in OUTPUT/bag and OUTPUT/plots.

--scenario SCENE (a shipped scene, e.g. flat_steps, or chair_table, alias chair): the
multi-contact pipeline: pik_node, contact_planner_node, trajectory_node and
stabilizer_gate_node (the default graph's nodes, stabilizer gate on the scene, the planner
with --planner-workers processes), the recorder on PIPELINE_TOPICS, a
PlanContacts goal for the scene, the execution until the trajectory status is `done`
(`failed`: exit 1), then `stance check-run` on the bag and a report folder OUTPUT/SCENE:
bag/, plots (contacts.png, stabilizer.png, joints.png, com.png, damping.png, errors.png),
the plan (plan.json) and its contact sheet (plan.png), report.md, logs/. Exit 0 when every
check passes.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import re
import sys
import threading
import time
from pathlib import Path

from .background_node import PROBE_WAIT, BackgroundNode
from .cli import positive
from .processes import ProcessGroup, terminate_as_interrupt

DEFAULT_OUTPUT = Path("out") / "demo"
PIK = "pik"
DEFAULT_SCENARIO = "flat_steps"
PIPELINE_TOPICS = ("/joint_states", "/pik/base_pose", "/pik/status", "/robot_description",
                   "/contact_planner/plan", "/trajectory/joint_trajectory",
                   "/trajectory/active_stance", "/trajectory/status", "/stabilizer/state")
# Subscribers each topic has once the graph and the recorder are up (the recorder, the
# nodes reading it, this command's own status subscription).
READY_SUBSCRIBERS = {"/joint_states": 1, "/pik/base_pose": 1, "/pik/status": 2,
                     "/robot_description": 1,
                     "/contact_planner/plan": 3, "/trajectory/joint_trajectory": 1,
                     "/trajectory/active_stance": 2, "/trajectory/status": 2,
                     "/stabilizer/state": 1}
# nodes a plan waits for on /trajectory/active_stance (trajectory_node's stance_listeners):
# the gate, as in the default graph, and the recorder, so that the bag holds stance 0
STANCE_LISTENERS = ["stabilizer_gate_node", "stance_recorder"]
STARTUP_TIMEOUT = 120.0    # s for the nodes and the recorder to come up
PLANNING_TIMEOUT = 960.0   # s for the plan: contact_planner_node's time_budget and a margin
INTERPOLATION_TIMEOUT = 300.0  # s from the plan to the trajectory status `executing`
EXECUTION_MARGIN = 60.0    # s allowed beyond the announced execution duration
SETTLE = 1.0               # s recorded after `done` (the robot at rest on the last stance)
DISCOVERY = 1.0            # s to discover a graph already running in the DDS domain
SHEET_PANELS = 12          # stances drawn at most on the contact sheet
# trajectory_node's joint speeds as a fraction of the URDF limits. Its own default, 0.5,
# makes flat_steps' steps 0.23 s and weight shifts 60 ms long (CoM at 1 m/s): on a loaded
# machine pik_node then misses periods and lands the feet up to 7 cm late.
VELOCITY_SCALE = 0.15
PLANNER_WORKERS = min(2, os.cpu_count() or 1)
SCENARIO_ALIASES = {"chair": "chair_table"}   # the name for the chair escape
# Scenes whose default time law is time-optimal: the chair plan's 59 transitions take about
# 3 minutes at VELOCITY_SCALE time-optimally, over 15 minutes with the sinusoidal profile
# under the acceleration bound.
TIME_OPTIMAL_SCENES = ("chair_table",)


def add_arguments(parser) -> None:
    parser.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT,
                        help="output directory (a scene's report goes to OUTPUT/SCENE)")
    parser.add_argument("--scenario", default=DEFAULT_SCENARIO,
                        help=f"'{PIK}' (the PIK demo) or a shipped scene for the contact "
                             "pipeline, e.g. flat_steps, chair_table "
                             f"(default: {DEFAULT_SCENARIO})")
    parser.add_argument("--timing", choices=["sinusoidal", "time_optimal"],
                        help="pipeline: trajectory_node's time law (default: time_optimal "
                             "on chair_table, else its parameter file's)")
    parser.add_argument("--velocity-scale", type=positive(float), default=VELOCITY_SCALE,
                        help="pipeline: trajectory_node's joint speeds as a fraction of the "
                             f"URDF limits (default: {VELOCITY_SCALE})")
    parser.add_argument("--planner-workers", type=positive(int), default=PLANNER_WORKERS,
                        help="pipeline: contact_planner_node's worker processes (default: "
                             f"{PLANNER_WORKERS}, the cores up to 2)")
    parser.add_argument("--path", default="reach_limits",
                        help="pik: right-hand path, built-in name or YAML file")
    parser.add_argument("--strategy", default="progressive",
                        choices=["none", "clamping", "progressive"],
                        help="pik: joint limit strategy")


def run(args) -> int:
    try:
        with terminate_as_interrupt():
            return run_pik(args) if args.scenario == PIK else run_pipeline(args)
    except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the child processes were stopped
        print("stance demo: interrupted", file=sys.stderr)
        return 130


def run_pik(args) -> int:
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
        failure = recorder_failure(group.stop(recorder))
        print(recorder.log_path.read_text().strip())
        group.stop(pik)
        if failure:
            return _fail(group, failure)
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


# --- the contact pipeline (--scenario SCENE) ------------------------------------------------

class GraphClient(BackgroundNode):
    """The PlanContacts client and the trajectory statuses received (texts)."""

    def __init__(self):
        from rclpy.action import ActionClient
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from stance_msgs.action import PlanContacts
        from std_msgs.msg import String

        super().__init__("stance_demo")
        self.client = ActionClient(self.node, PlanContacts, "/contact_planner/plan_contacts")
        self.goal_type = PlanContacts.Goal
        self.lock = threading.Lock()
        self.statuses = []
        self.node.create_subscription(
            String, "/trajectory/status", self._on_status,
            QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL))
        self.start_spinning()

    def _on_status(self, msg):
        with self.lock:
            self.statuses.append(msg.data)

    def status_count(self) -> int:
        with self.lock:
            return len(self.statuses)

    def ready(self) -> str | None:
        """None once the action server, trajectory_node's status and every recorded topic's
        subscribers are there; else what is still missing."""
        if not self.client.server_is_ready():
            return "the PlanContacts action server"
        if not self.status_count():
            return "trajectory_node's status"
        for topic, count in READY_SUBSCRIBERS.items():
            if not self.node.count_publishers(topic) or \
                    self.node.count_subscribers(topic) < count:
                return f"{topic}: publisher and {count} subscriber(s)"
        if not self.action_server_answers(self.client):   # probed once the rest is up
            return "the PlanContacts action server's answer"
        return None

    def plan(self, scene: str, timeout: float):
        """The PlanContacts result for the scene (None when the goal is rejected or times
        out; a goal still running after timeout s is canceled, so it frees the planner)."""
        handle = self.send_goal(self.client, self.goal_type(scene=scene), timeout=30.0)
        if handle is None or not handle.accepted:
            return None
        response = self.call(handle.get_result_async, timeout=timeout)
        if response is None:
            self.call(handle.cancel_goal_async, timeout=PROBE_WAIT)
            return None
        return response.result

    def wait_status(self, since: int, states, timeout: float) -> str | None:
        """The first status after the first `since` ones whose state is in `states`; None
        after timeout s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                for text in self.statuses[since:]:
                    if text.split(":", 1)[0] in states:
                        return text
            time.sleep(0.05)
        return None


def pipeline_nodes(scene: str, trajectory: dict, planner: dict | None = None) -> list:
    """(name, argv) of the default graph's nodes, the stabilizer gate on `scene`,
    trajectory_node and contact_planner_node with the parameters `trajectory` and `planner`
    (beyond their parameter files')."""
    from .graph import DEFAULT_GRAPH, command, load_graph

    overrides = {"stabilizer_gate_node": {"scene": scene}, "trajectory_node": trajectory,
                 "contact_planner_node": planner or {}}
    return [(spec.name, command(dataclasses.replace(
        spec, parameters={**spec.parameters, **overrides.get(spec.name, {})})))
        for spec in load_graph(DEFAULT_GRAPH)]


@dataclasses.dataclass
class PipelineRun:
    """What the report states: planning (the action result), execution duration (s, from
    the `executing` status), wall times (s) of the whole run and of its phases."""

    result: object = None
    execution_duration: float = math.nan
    wall: dict = dataclasses.field(default_factory=dict)


def run_pipeline(args) -> int:
    from stance.planning.scene import scene_names

    scene = SCENARIO_ALIASES.get(args.scenario, args.scenario)
    if scene not in scene_names():
        print(f"stance demo: unknown scenario {scene!r}: '{PIK}' or one of "
              f"{', '.join(scene_names())}", file=sys.stderr)
        return 2
    output = (args.output / scene).resolve()
    bag = output / "bag"
    if bag.exists():
        _remove_bag(bag)
    began = time.monotonic()
    record = PipelineRun()
    group = ProcessGroup(output / "logs")
    try:
        timing = args.timing or ("time_optimal" if scene in TIME_OPTIMAL_SCENES else None)
        trajectory = {name: value for name, value in (("timing", timing),
                      ("velocity_scale", args.velocity_scale)) if value is not None}
        trajectory["stance_listeners"] = STANCE_LISTENERS
        message = _execute(group, scene, trajectory, {"workers": args.planner_workers}, bag,
                           record)
    finally:
        group.stop_all()
    if message:
        record.wall["total"] = time.monotonic() - began
        (output / "report.md").write_text(_markdown(scene, record, failure=message))
        print(f"stance demo: {message} (logs in {output / 'logs'})", file=sys.stderr)
        return 1
    return _report(output, scene, bag, record, began)


def _execute(group, scene: str, trajectory: dict, planner: dict, bag: Path,
             record: PipelineRun) -> str | None:
    """Start the graph and the recorder, plan, execute, stop the recorder; None when all
    went well, else what failed."""
    phase = time.monotonic()
    client = GraphClient()
    try:
        time.sleep(DISCOVERY)
        foreign = [t for t in PIPELINE_TOPICS if client.node.count_publishers(t)]
        if foreign:
            return (f"{', '.join(foreign)} already published: another graph runs in this "
                    f"DDS domain (ROS_DOMAIN_ID={os.environ.get('ROS_DOMAIN_ID', '0')})")
        procs = [group.start(*argv, name=name)
                 for name, argv in pipeline_nodes(scene, trajectory, planner)]
        recorder = group.start("stance", "record", "-o", str(bag), *PIPELINE_TOPICS,
                               name="record")
        procs.append(recorder)
        missing = "the nodes"
        deadline = time.monotonic() + STARTUP_TIMEOUT
        while time.monotonic() < deadline:
            crashed = [proc.name for proc in procs if proc.poll() is not None]
            if crashed:
                return f"{', '.join(crashed)} exited during start-up"
            missing = client.ready()
            if missing is None:
                break
            time.sleep(0.1)
        else:
            return f"start-up timed out after {STARTUP_TIMEOUT:g} s waiting for {missing}"
        record.wall["start-up"] = time.monotonic() - phase
        print(f"graph up in {record.wall['start-up']:.1f} s; planning {scene} ...")
        phase, since = time.monotonic(), client.status_count()
        record.result = client.plan(scene, timeout=PLANNING_TIMEOUT)
        record.wall["planning"] = time.monotonic() - phase
        if record.result is None:
            return "the PlanContacts goal was rejected or got no result"
        if not record.result.success:
            return f"planning failed: {record.result.reason}: {record.result.message}"
        print(f"plan: {record.result.stances} stances, {record.result.nodes_expanded} nodes, "
              f"{record.result.planning_time:.1f} s; interpolating ...")
        phase = time.monotonic()
        status = client.wait_status(since, ("executing", "failed"), INTERPOLATION_TIMEOUT)
        if status is None or status.startswith("failed"):
            return f"trajectory_node: {status or 'no execution after the plan'}"
        record.wall["interpolation"] = time.monotonic() - phase
        match = re.search(r"in ([0-9.]+) s", status)
        record.execution_duration = float(match.group(1)) if match else math.nan
        print(f"{status} ...")
        phase = time.monotonic()
        status = client.wait_status(since, ("done", "failed"),
                                    record.execution_duration + EXECUTION_MARGIN)
        if status is None or status.startswith("failed"):
            return f"trajectory_node: {status or 'execution not done in time'}"
        record.wall["execution"] = time.monotonic() - phase
        print(status)
        time.sleep(SETTLE)
    finally:
        client.close()
    failure = recorder_failure(group.stop(recorder))
    return failure and f"{failure}: {recorder.log_path.read_text()[-1500:]}"


def recorder_failure(exit_code: int) -> str | None:
    """What the recorder's exit code says went wrong (None: a complete recording). A
    negative code is the signal that ended it: it had not exited within the stop's SIGINT
    timeout, so its bag is not closed (its log names the last stage of its stop)."""
    if exit_code == 0:
        return None
    if exit_code < 0:
        return (f"the recorder did not exit after SIGINT and was killed (signal "
                f"{-exit_code}); its bag is not closed")
    return "the recorder reported lost or unwritten messages"


def _report(output: Path, scene: str, bag: Path, record: PipelineRun, began: float) -> int:
    """check-run, plots, contact sheet and report.md; the check-run exit code."""
    from . import check_run, plot

    phase = time.monotonic()
    report = check_run.check_bag(bag, scene)
    code = check_run.print_report(report)
    record.wall["check-run"] = time.monotonic() - phase
    phase = time.monotonic()
    figures = plot.plot_pipeline(bag, report, scene, output)
    figures.append(_contact_sheet(record.result.plan, scene, output))
    record.wall["plots"] = time.monotonic() - phase
    record.wall["total"] = time.monotonic() - began
    (output / "report.md").write_text(_markdown(scene, record, report, figures))
    print(f"report: {output / 'report.md'}")
    return code


def _contact_sheet(plan_msg, scene: str, output: Path) -> Path:
    """plan.json and its contact sheet plan.png (stance plot-plan)."""
    from stance.planning.contacts import save_plan
    from stance.planning.scene import load_scene
    from stance.robot import Robot
    from trajectory_node.conversions import plan_from_msg

    from . import plan_tools

    robot_spec = load_scene(scene).robot
    plan, _ = plan_from_msg(plan_msg, Robot.load(robot_spec), robot_spec)
    save_plan(plan, str(output / "plan.json"))
    parser = argparse.ArgumentParser(prog=f"stance {plan_tools.PLOT_COMMAND}")
    plan_tools.add_arguments(parser)
    every = max(1, math.ceil(len(plan.stances) / SHEET_PANELS))
    sheet = output / "plan.png"
    plan_tools.run_plot(parser.parse_args([str(output / "plan.json"), "-o", str(sheet),
                                           "--every", str(every)]))
    return sheet


def _markdown(scene, record: PipelineRun, report=None, figures=(), failure=None) -> str:
    """report.md: the run's numbers, then check-run's verdicts and the files, or why the run
    failed (failure)."""
    result = record.result
    lines = [f"# Stance demo: {scene}", "", "| quantity | value |", "|---|---|"]
    if result is not None:
        lines += [f"| planning time (planner) | {result.planning_time:.2f} s |",
                  f"| nodes expanded | {result.nodes_expanded} |",
                  f"| posture generations | {result.posture_generations} |",
                  f"| stances | {result.stances} |"]
    if math.isfinite(record.execution_duration):
        lines += [f"| execution duration (trajectory) | {record.execution_duration:.2f} s |"]
    lines += [f"| wall time: {phase} | {seconds:.1f} s |" for phase, seconds in record.wall.items()]
    if failure is not None:
        return "\n".join(lines + ["", f"## Run FAILED: {failure}", "", "See `logs/`.", ""])
    lines += ["", f"## check-run: {'all passed' if report.passed else 'FAILED'}", "",
              "| check | verdict | rows | failures |", "|---|---|---|---|"]
    lines += [f"| {c.name} | {'pass' if c.passed else 'FAIL'} | {len(c.rows)} | "
              f"{len(c.failures)} |" for c in report.checks]
    failures = [f"- {c.name}: {f}" for c in report.checks for f in c.failures]
    if failures:
        lines += ["", "Failures:", ""] + failures
    lines += ["", "## Files", "", "- `bag/`: MCAP bag (`stance check-run bag`)"]
    lines += [f"- `{path.name}`" for path in figures]
    lines += ["- `plan.json`: the plan (`stance check-plan plan.json`)", "- `logs/`", ""]
    return "\n".join(lines)
