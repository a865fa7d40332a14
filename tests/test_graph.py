"""`stance graph` runs real nodes over DDS: they come up, a crashed node is restarted until
its max_restarts, SIGINT stops everything; malformed graph files are refused naming the
field; the launch file names the default graph's nodes and parameter files."""

import json
import os
import re
import signal
import sys
import time
import types
from pathlib import Path

import pytest
from ament_index_python.packages import get_package_share_directory
from conftest import NODE_START_TIMEOUT, wait_until
from helpers.probe import PikProbe
from stance_tools.graph import DEFAULT_GRAPH, GraphError, command, load_graph
from stance_tools.processes import group_exists

LAUNCH_FILE = Path(__file__).parents[1] / "src" / "stance_tools" / "launch" / "stance.launch.py"
# pik_node only, light (mannequin at 50 Hz), restarted once quickly; an optional missing node
TEST_GRAPH = """
nodes:
  - name: pik
    executable: pik_node
    parameters: {robot: mannequin, initial_configuration: standing, rate: 50.0}
    restart: {max_restarts: 1, backoff: 0.2}
  - name: later
    executable: no_such_node
    optional: true
"""


def write_graph(tmp_path, text):
    path = tmp_path / "graph.yaml"
    path.write_text(text)
    return path


def started_pids(runner, name=r"\S+"):
    return [int(pid) for pid in re.findall(rf"\[graph\] {name}: started \(pid (\d+)",
                                           runner.log_path.read_text())]


def log_has(runner, text):
    return text in runner.log_path.read_text()


def joint_states_since(probe, since):
    with probe.lock:
        return sum(1 for stamp, _ in probe.joint_states if stamp > since)


def test_crashed_node_is_restarted_then_given_up(processes, tmp_path):
    graph = write_graph(tmp_path, TEST_GRAPH)
    runner = processes.start("stance", "graph", "--graph", str(graph), name="graph")
    probe = PikProbe()
    try:
        first = wait_until(lambda: started_pids(runner, "pik"), 10, what="pik started")[0]
        assert log_has(runner, "[graph] later: optional, skipped: nodes[1] (later).executable")
        wait_until(lambda: joint_states_since(probe, 0) > 0, NODE_START_TIMEOUT,
                   what="/joint_states")
        assert log_has(runner, "[pik] ")  # node output, prefixed

        os.kill(first, signal.SIGKILL)
        killed_at = time.monotonic()
        wait_until(lambda: log_has(runner, "pik: killed by SIGKILL; restart 1/1 in 0.2 s"), 5,
                   what="crash report")
        pids = wait_until(lambda: started_pids(runner, "pik")[1:], 5, what="restart")
        assert pids[0] != first and log_has(runner, "restart 1/1)")
        wait_until(lambda: joint_states_since(probe, killed_at) > 0, 30,
                   what="/joint_states from the restarted node")

        os.kill(pids[0], signal.SIGKILL)
        wait_until(lambda: runner.poll() is not None, 10, what="the runner to give up")
        log = runner.log_path.read_text()
        assert "pik: killed by SIGKILL; giving up (max_restarts 1 reached)" in log, log
        assert "no node left running" in log
        assert runner.returncode == 1
        assert len(started_pids(runner, "pik")) == 2
    finally:
        probe.close()


def test_sigint_stops_the_default_graph_and_every_child(processes, tmp_path):
    runner = processes.start("stance", "graph", "--log-dir", str(tmp_path / "logs"),
                             name="graph")
    probe = PikProbe()
    try:
        wait_until(lambda: {"pik_node", "contact_planner_node"} <= set(
            probe.node.get_node_names()), 60, what="both nodes in the ROS graph")
        wait_until(lambda: joint_states_since(probe, 0) > 0, NODE_START_TIMEOUT,
                   what="/joint_states")
        pids = started_pids(runner)  # optional nodes too, when installed
        assert len(started_pids(runner, "pik_node")) == 1 and runner.poll() is None
        assert len(started_pids(runner, "contact_planner_node")) == 1
        for optional in ("trajectory_node", "stabilizer_gate_node"):
            assert log_has(runner, f"[graph] {optional}: ")  # started or reported skipped

        os.kill(runner.pid, signal.SIGINT)
        wait_until(lambda: runner.poll() is not None, 30, what="the runner to stop")
        assert runner.returncode == 0, runner.log_path.read_text()
        for pid in pids:  # each node's process group: the node and its own children
            wait_until(lambda: not group_exists(types.SimpleNamespace(pid=pid)), 5,
                       what=f"process group {pid} to end")
        assert "robot talos" in (tmp_path / "logs" / "pik_node.log").read_text()
        assert log_has(runner, "pik_node: stopped, exited with code 0")
    finally:
        probe.close()


@pytest.mark.parametrize("text, message", [
    ("node: []", "nodes: missing"),
    ("nodes:\n  - {executable: pik_node}", "nodes[0].name: missing"),
    ("nodes:\n  - {name: a}", "nodes[0] (a).executable: missing"),
    ("nodes:\n  - {name: a, executable: pik_node, param_file: p.yaml}",
     "nodes[0] (a).param_file: unknown field"),
    ("nodes:\n  - {name: a, executable: pik_node, restart: {max_restarts: -1}}",
     "nodes[0] (a).restart.max_restarts: expected an integer >= 0"),
    ("nodes:\n  - {name: a, executable: pik_node, parameters: {rate: {hz: 1}}}",
     "nodes[0] (a).parameters.rate"),
    ("nodes:\n  - {name: a, executable: pik_node}\n  - {name: a, executable: pik_node}",
     "nodes[1] (a).name: duplicate name"),
    # a NaN backoff: "restart 1/3 in nan s", never restarted, never ended
    ("nodes:\n  - {name: a, executable: pik_node, restart: {backoff: .nan}}",
     "nodes[0] (a).restart.backoff: expected finite seconds >= 0"),
    # a name that is a path: its log went outside --log-dir
    ("nodes:\n  - {name: ../../escaped, executable: pik_node}",
     "nodes[0].name: '../../escaped' is not a node name"),
    # a date: a traceback (not JSON); a bad name: the node crash-looped on its -p argument
    ("nodes:\n  - {name: a, executable: pik_node, parameters: {when: 2024-01-01}}",
     "nodes[0] (a).parameters.when: expected a boolean, number, string or list"),
    ("nodes:\n  - {name: a, executable: pik_node, parameters: {'bad key:=': 1}}",
     "nodes[0] (a).parameters.bad key:=: not a parameter name"),
])
def test_malformed_graph_names_the_field(tmp_path, text, message):
    with pytest.raises(GraphError, match=re.escape(message)):
        load_graph(write_graph(tmp_path, text))


def test_unreadable_graph_files_are_named(tmp_path):
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe")
    with pytest.raises(GraphError, match=r"binary.yaml: not a YAML text file \(not UTF-8"):
        load_graph(binary)
    with pytest.raises(GraphError, match=r"broken.yaml: not valid YAML"):
        load_graph(write_graph(tmp_path, "nodes: [\n").rename(tmp_path / "broken.yaml"))
    with pytest.raises(GraphError, match=r"No such file"):
        load_graph(tmp_path / "missing.yaml")


def test_a_parameter_written_with_an_exponent_is_a_number(tmp_path):
    """YAML 1.1 read 2e-3 as a string; pik_node's double parameter would refuse it."""
    [spec] = load_graph(write_graph(
        tmp_path, "nodes:\n  - {name: a, executable: pik_node, parameters: {damping: 2e-3}}\n"))
    assert spec.parameters == {"damping": 0.002}


@pytest.mark.parametrize("node, message", [
    ("{name: a, executable: no_such_node}", "nodes[0] (a).executable: no installed package"),
    ("{name: a, package: no_such_package, executable: pik_node}",
     "nodes[0] (a).package: no installed package 'no_such_package'"),
    ("{name: a, package: pik_node, executable: no_such_node}",
     "nodes[0] (a).executable: no executable"),
    ("{name: a, executable: pik_node, params_file: missing.yaml}",
     "nodes[0] (a).params_file: no file"),
])
def test_what_is_not_installed_is_named(tmp_path, node, message):
    [spec] = load_graph(write_graph(tmp_path, f"nodes:\n  - {node}\n"))
    with pytest.raises(GraphError, match=re.escape(message)):
        command(spec)


def test_command_is_ros2_run_with_parameter_file_and_overrides(tmp_path):
    [spec, _] = load_graph(write_graph(tmp_path, TEST_GRAPH))
    share = get_package_share_directory("pik_node")
    argv = command(spec)
    assert argv[0].endswith("/lib/pik_node/pik_node")
    assert argv[1:] == ["--ros-args", "--params-file", f"{share}/config/pik_node.yaml",
                        "-p", 'robot:="mannequin"', "-p", 'initial_configuration:="standing"',
                        "-p", "rate:=50.0"]


def test_cli_refuses_a_bad_graph_with_the_field(processes, tmp_path):
    graph = write_graph(tmp_path, "nodes:\n  - {name: a, executable: no_such_node}\n")
    runner = processes.start("stance", "graph", "--graph", str(graph), name="graph")
    assert runner.wait(30) == 2
    assert "nodes[0] (a).executable: no installed package" in runner.log_path.read_text()
    only = processes.start("stance", "graph", "--only", "nobody", name="only")
    assert only.wait(30) == 2
    assert "--only: no node named nobody" in only.log_path.read_text()


def test_launch_file_runs_the_default_graph(monkeypatch):
    """The launch file, run against stand-ins for launch and launch_ros (not installable
    here), declares the default graph's installed nodes with their parameter files, the
    graph's parameter overrides and restart policies: what `stance graph` runs."""
    nodes = []
    launch = types.ModuleType("launch")
    launch.LaunchDescription = list
    launch_ros = types.ModuleType("launch_ros")
    launch_ros.actions = types.SimpleNamespace(Node=lambda **kwargs: nodes.append(kwargs))
    for name, module in [("launch", launch), ("launch_ros", launch_ros),
                         ("launch_ros.actions", launch_ros.actions)]:
        monkeypatch.setitem(sys.modules, name, module)
    namespace = {}
    exec(compile(LAUNCH_FILE.read_text(), str(LAUNCH_FILE), "exec"), namespace)
    namespace["generate_launch_description"]()

    graph = load_graph(DEFAULT_GRAPH)
    installed = []
    for spec in graph:
        try:
            installed.append(command(spec))
        except GraphError:
            assert spec.optional, spec.name
    assert [(node["package"], node["executable"]) for node in nodes] == [
        tuple(argv[0].split("/")[-2:]) for argv in installed]
    for node, argv in zip(nodes, installed):
        params_file, *overrides = node["parameters"]
        after_file = argv.index("--params-file") + 1
        assert params_file == argv[after_file]
        assert [f"{key}:={json.dumps(value)}" for override in overrides
                for key, value in override.items()] == argv[after_file + 2::2]
    assert any(len(node["parameters"]) > 1 for node in nodes)  # the graph overrides some
    assert all(node["respawn"] for node in nodes)
    by_name = {spec.name: spec for spec in graph}
    assert [(node["respawn_max_retries"], node["respawn_delay"]) for node in nodes] == [
        (by_name[node["name"]].max_restarts, by_name[node["name"]].backoff) for node in nodes]
