"""`stance bench graph`: CPU use of each node of the default graph, idle and executing a plan.

Starts the default graph (data/graph.yaml) supervised as `stance graph` does, with the
parameters `stance demo` gives it (stabilizer gate on the scene, trajectory_node's
velocity_scale), waits until every node is up and lets it settle. Then, per node, reads the
CPU time (utime + stime, plus that of reaped children) of every live process of the node's
process group from /proc/<pid>/stat, so contact_planner_node's planner process counts, over
consecutive 1-s windows in two phases:
  - idle: no plan;
  - executing: a flat_steps plan from the PlanContacts action (as `stance demo` gets it),
    measured from trajectory_node's `executing` status on, so planning and interpolation are
    not counted; an execution that ends earlier ends the phase at its last whole window.
Reports per node and phase the median, p99 and mean % of one core, the graph's total per
window, the verdict against the target (total mean < 100 % of one core) and the load average
at start and end (the machine may be shared). The nodes inherit OPENBLAS_NUM_THREADS and
OMP_NUM_THREADS (1 unless set: stance_tools.bench); this process runs no BLAS code.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from pathlib import Path

from .cli import positive
from .processes import terminate_as_interrupt

SCENE = "flat_steps"
WINDOW = 1.0              # s per CPU sample
TARGET_PERCENT = 100.0    # % of one core: the graph's total mean must stay below
DEFAULT_LOG_DIR = Path("out") / "bench_graph" / "logs"
STOP_TIMEOUT = 10.0       # s the nodes get to exit after SIGINT, before SIGTERM
UP_TOPICS = ("/joint_states", "/stabilizer/state")  # published once pik_node and the gate run
BLAS_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")


class BenchError(RuntimeError):
    """The graph did not come up, plan or execute, or a node exited during a phase."""


def add_graph_arguments(parser) -> None:
    parser.add_argument("--seconds", type=positive(float), default=20.0,
                        help="s measured per phase (idle, executing)")
    parser.add_argument("--settle", type=positive(float), default=5.0,
                        help="s between the graph being up and the idle phase")
    parser.add_argument("--velocity-scale", type=positive(float), default=None,
                        help="trajectory_node's joint speeds as a fraction of the URDF limits "
                             "(default: stance demo's, so the execution outlasts --seconds)")
    parser.add_argument("--log-dir", type=Path, default=DEFAULT_LOG_DIR,
                        help=f"node logs (default: {DEFAULT_LOG_DIR})")
    parser.add_argument("--json", help="also write the figures to this JSON file")


def run_graph(args) -> int:
    from . import demo

    velocity_scale = demo.VELOCITY_SCALE if args.velocity_scale is None else args.velocity_scale
    load_start = os.getloadavg()
    try:
        with terminate_as_interrupt():
            phases, node_pids = _run_phases(args, velocity_scale)
    except BenchError as error:
        print(f"stance bench graph: {error} (node logs in {args.log_dir})")
        return 1
    except KeyboardInterrupt:  # the nodes have been stopped on the way out
        print("stance bench graph: interrupted")
        return 130
    figures = {
        "scene": SCENE, "velocity_scale": velocity_scale, "window_s": WINDOW,
        "target_percent": TARGET_PERCENT,
        "blas_threads": {name: os.environ.get(name) for name in BLAS_VARIABLES},
        "load_average": {"start": list(load_start), "end": list(os.getloadavg())},
        "node_pids": node_pids, "phases": phases,
    }
    _print(figures)
    if args.json:
        with open(args.json, "w") as output:
            json.dump(figures, output, indent=2)
    return 0


def _run_phases(args, velocity_scale: float) -> tuple[dict, dict]:
    """Start the graph, measure idle then executing, stop the graph; (figures per phase,
    {node: pid})."""
    from .demo import (DISCOVERY, INTERPOLATION_TIMEOUT, PIPELINE_TOPICS, PLANNING_TIMEOUT,
                       STARTUP_TIMEOUT, GraphClient, pipeline_nodes)
    from .graph import DEFAULT_GRAPH, GraphError, Reporter, SupervisedNode, load_graph, \
        supervise

    args.log_dir.mkdir(parents=True, exist_ok=True)
    report = Reporter()
    try:
        specs = {spec.name: spec for spec in load_graph(DEFAULT_GRAPH)}
        commands = pipeline_nodes(SCENE, {"velocity_scale": velocity_scale})
    except GraphError as error:
        raise BenchError(f"the default graph is not installed: {error}") from None
    for name, _ in commands:
        (args.log_dir / f"{name}.log").unlink(missing_ok=True)
    nodes = [SupervisedNode(specs[name], argv, args.log_dir, report) for name, argv in commands]
    client = GraphClient()
    stop = threading.Event()
    supervisor = None
    try:
        time.sleep(DISCOVERY)
        foreign = [topic for topic in PIPELINE_TOPICS if client.node.count_publishers(topic)]
        if foreign:
            raise BenchError(f"{', '.join(foreign)} already published: another graph runs in "
                             f"this DDS domain (ROS_DOMAIN_ID="
                             f"{os.environ.get('ROS_DOMAIN_ID', '0')})")
        supervisor = threading.Thread(target=supervise,
                                      args=(nodes, stop, STOP_TIMEOUT, report))
        supervisor.start()
        _wait_up(client, nodes, STARTUP_TIMEOUT)
        report(f"graph up; settling {args.settle:g} s")
        time.sleep(args.settle)
        pids = {node.spec.name: node.proc.pid for node in nodes}
        phases = {}
        report(f"idle phase: {args.seconds:g} s")
        phases["idle"] = _measure(nodes, pids, args.seconds, time.sleep)
        report(f"planning {SCENE} (not measured) ...")
        since = client.status_count()
        result = client.plan(SCENE, timeout=PLANNING_TIMEOUT)
        if result is None or not result.success:
            raise BenchError("planning failed: " + (f"{result.reason}: {result.message}"
                                                    if result else "no result"))
        status = client.wait_status(since, ("executing", "failed"), INTERPOLATION_TIMEOUT)
        if status is None or status.startswith("failed"):
            raise BenchError(f"trajectory_node: {status or 'no execution after the plan'}")
        report(f"executing phase: {args.seconds:g} s at most; trajectory_node: {status}")
        phases["executing"] = _measure(
            nodes, pids, args.seconds,
            lambda timeout: client.wait_status(since, ("done", "failed"), timeout))
        phases["executing"]["execution"] = status
        if (phases["executing"]["ended_by"] or "").startswith("failed"):
            raise BenchError(f"trajectory_node: {phases['executing']['ended_by']}")
        return phases, pids
    finally:
        stop.set()
        if supervisor is not None:
            supervisor.join()
        client.close()


def _wait_up(client, nodes, timeout: float) -> None:
    """Return once every node runs, the PlanContacts server answers, trajectory_node's status
    and UP_TOPICS are published; raise BenchError after timeout s or if a node exits."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        exited = [node.spec.name for node in nodes
                  if node.finished or node.restarts or node.restart_at is not None]
        if exited:
            raise BenchError(f"{', '.join(exited)} exited during start-up")
        if all(node.running for node in nodes) and client.status_count() and \
                all(client.node.count_publishers(topic) for topic in UP_TOPICS) and \
                client.action_server_answers(client.client):   # probed once the rest is up
            return
        time.sleep(0.1)
    raise BenchError(f"the graph was not up after {timeout:g} s")


def _measure(nodes, pids: dict, seconds: float, wait) -> dict:
    """% of one core per node over whole WINDOW-s windows for `seconds` s. wait(timeout)
    sleeps up to timeout s and may return why to stop early (a status text): the window in
    progress is then dropped. Raises BenchError if a node exits or is restarted."""
    windows = {name: [] for name in pids}
    own = []  # this process (the graph client), for comparison
    ticks_per_s = os.sysconf("SC_CLK_TCK")
    ended_by = None
    began, before, own_before = time.monotonic(), _group_ticks(pids.values()), \
        time.process_time()
    for _ in range(max(1, round(seconds / WINDOW))):
        ended_by = wait(max(0.0, began + WINDOW - time.monotonic()))
        if ended_by is not None:
            break
        restarted = [node.spec.name for node in nodes
                     if not node.running or node.proc.pid != pids[node.spec.name]]
        if restarted:
            raise BenchError(f"{', '.join(restarted)} exited during the measurement")
        now, ticks, own_now = time.monotonic(), _group_ticks(pids.values()), \
            time.process_time()
        for name, pid in pids.items():
            windows[name].append(100.0 * (ticks[pid] - before[pid]) / ticks_per_s / (now - began))
        own.append(100.0 * (own_now - own_before) / (now - began))
        began, before, own_before = now, ticks, own_now
    totals = [sum(values) for values in zip(*windows.values())]
    return {"seconds_requested": seconds, "windows": len(totals), "ended_by": ended_by,
            "nodes": {name: _statistics(values) for name, values in windows.items()},
            "total": _statistics(totals),
            "within_target": bool(totals) and _statistics(totals)["mean"] < TARGET_PERCENT,
            "benchmark_process": _statistics(own)}


def _group_ticks(pgids) -> dict:
    """{pgid: clock ticks of CPU time used so far by the live processes of that process
    group} (reaped children count with their parent)."""
    from contact_planner_node.worker import process_table

    ticks = dict.fromkeys(pgids, 0)
    for entry in process_table().values():
        if entry.group in ticks:
            ticks[entry.group] += entry.cpu_ticks
    return ticks


def _statistics(percents: list) -> dict:
    """Median, p99 and mean (% of one core) of per-window figures; NaN without windows."""
    import numpy as np

    if not percents:
        return {"median": math.nan, "p99": math.nan, "mean": math.nan}
    return {"median": float(np.median(percents)), "p99": float(np.percentile(percents, 99)),
            "mean": float(np.mean(percents))}


def _print(figures: dict) -> None:
    blas = ", ".join(f"{name}={value}" for name, value in figures["blas_threads"].items())
    print(f"stance bench graph: default graph, default parameters but trajectory_node "
          f"velocity_scale {figures['velocity_scale']} and the stabilizer gate on {SCENE} "
          f"(as stance demo); CPU time of each node's process group (children included) "
          f"from /proc, per {figures['window_s']:g}-s window, in % of one core; {blas}")
    for phase, entry in figures["phases"].items():
        measured = entry["windows"] * figures["window_s"]
        line = f"{phase}: {measured:g} s measured of {entry['seconds_requested']:g} s"
        if entry["ended_by"]:
            line += f" (execution ended: {entry['ended_by']})"
        if "execution" in entry:
            line += f"; from trajectory_node's '{entry['execution']}'"
        print(line)
    print(f"{'node':<24}{'phase':<11}{'median %':>9}{'p99 %':>8}{'mean %':>8}")
    rows = [(name, phase, entry["nodes"][name]) for name in figures["node_pids"]
            for phase, entry in figures["phases"].items()]
    rows += [("total", phase, entry["total"]) for phase, entry in figures["phases"].items()]
    rows += [("(this benchmark)", phase, entry["benchmark_process"])
             for phase, entry in figures["phases"].items()]
    for name, phase, values in rows:
        print(f"{name:<24}{phase:<11}{values['median']:>9.1f}{values['p99']:>8.1f}"
              f"{values['mean']:>8.1f}")
    verdicts = ", ".join(f"{phase} {entry['total']['mean']:.1f} % "
                         f"{'PASS' if entry['within_target'] else 'FAIL'}"
                         for phase, entry in figures["phases"].items())
    print(f"target: graph total mean < {figures['target_percent']:g} % of one core: {verdicts}")
    load = figures["load_average"]
    print(f"load average (1, 5, 15 min) at start: "
          f"{' '.join(f'{value:.2f}' for value in load['start'])}, at end: "
          f"{' '.join(f'{value:.2f}' for value in load['end'])} ({os.cpu_count()} cores)")
