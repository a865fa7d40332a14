"""`stance graph`: run the node graph as supervised processes (no ros2 launch needed).

Each node of a graph file (default: data/graph.yaml, the nodes of launch/stance.launch.py)
runs as `lib/<package>/<executable> --ros-args --params-file FILE -p name:=value ...` in its
own process. A node that crashes (nonzero exit or killed by a signal) is restarted after a
backoff doubled at each restart, up to its max_restarts; a node that exits with 0 is not.
Ctrl-C or SIGTERM stops every node (SIGINT, then SIGTERM and SIGKILL after grace periods)
and exits 0. The runner's reports are prefixed [graph]; node output is prefixed [<name>], or
goes to <log-dir>/<name>.log (appended across restarts).
"""

from __future__ import annotations

import json
import math
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from stance.yaml_file import load_yaml_file

from .cli import positive
from .param import is_parameter_value
from .processes import signal_group, spawn, stop_processes

DEFAULT_GRAPH = Path(__file__).parent / "data" / "graph.yaml"
NODE_FIELDS = ("name", "executable", "package", "params_file", "parameters", "restart",
               "optional")
RESTART_DEFAULTS = {"max_restarts": 3, "backoff": 1.0}
MAX_BACKOFF = 60.0  # s
NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")    # a ROS node name (its log file's too)
PARAMETER_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*")
POLL_PERIOD = 0.1  # s


class GraphError(ValueError):
    """A graph file is malformed or names what is not installed; the message names the field."""


@dataclass(frozen=True)
class NodeSpec:
    """One node of a graph: what to run and how to restart it."""

    where: str  # e.g. "nodes[0] (pik_node)", the prefix of error messages
    name: str
    executable: str
    package: str | None  # None: the executable's name
    params_file: Path | None  # None: the package's installed config/<executable>.yaml
    parameters: dict
    max_restarts: int
    backoff: float
    optional: bool


def load_graph(path: Path) -> list[NodeSpec]:
    """Parse and check a graph file (nothing is looked up in the install yet)."""
    path = Path(path)
    try:
        data = load_yaml_file(path, GraphError)
    except OSError as error:
        raise GraphError(str(error)) from error
    if not isinstance(data, dict) or "nodes" not in data:
        raise GraphError("nodes: missing (the file must be a mapping with a 'nodes' list)")
    if set(data) != {"nodes"}:
        raise GraphError(f"{sorted(set(data) - {'nodes'})[0]}: unknown field (only 'nodes')")
    if not isinstance(data["nodes"], list) or not data["nodes"]:
        raise GraphError("nodes: expected a non-empty list")
    specs = [_parse_node(entry, f"nodes[{index}]", path.parent)
             for index, entry in enumerate(data["nodes"])]
    seen = set()
    for spec in specs:
        if spec.name in seen:
            raise GraphError(f"{spec.where}.name: duplicate name")
        seen.add(spec.name)
    return specs


def _parse_node(entry, where: str, base: Path) -> NodeSpec:
    if not isinstance(entry, dict):
        raise GraphError(f"{where}: expected a mapping")
    name = _string(entry, "name", where)
    if not NODE_NAME.fullmatch(name):
        raise GraphError(f"{where}.name: {name!r} is not a node name (letters, digits and "
                         "underscores, not starting with a digit)")
    where = f"{where} ({name})"
    unknown = sorted(set(entry) - set(NODE_FIELDS))
    if unknown:
        raise GraphError(f"{where}.{unknown[0]}: unknown field (fields: {', '.join(NODE_FIELDS)})")
    params_file = entry.get("params_file")
    if params_file is not None:
        params_file = base / Path(_string(entry, "params_file", where)).expanduser()
    parameters = entry.get("parameters", {})
    if not isinstance(parameters, dict):
        raise GraphError(f"{where}.parameters: expected a mapping of name: value")
    for key, value in parameters.items():
        if not isinstance(key, str) or not PARAMETER_NAME.fullmatch(key):
            raise GraphError(f"{where}.parameters.{key}: not a parameter name")
        if not is_parameter_value(value):
            raise GraphError(f"{where}.parameters.{key}: expected a boolean, number, string "
                             "or list of one of these")
    optional = entry.get("optional", False)
    if not isinstance(optional, bool):
        raise GraphError(f"{where}.optional: expected true or false")
    max_restarts, backoff = _restart_policy(entry.get("restart", {}), f"{where}.restart")
    return NodeSpec(where=where, name=name, executable=_string(entry, "executable", where),
                    package=_string(entry, "package", where) if "package" in entry else None,
                    params_file=params_file, parameters=parameters, max_restarts=max_restarts,
                    backoff=backoff, optional=optional)


def _restart_policy(restart, where: str) -> tuple[int, float]:
    if not isinstance(restart, dict) or set(restart) - set(RESTART_DEFAULTS):
        raise GraphError(f"{where}: expected a mapping with max_restarts and backoff")
    restart = {**RESTART_DEFAULTS, **restart}
    max_restarts, backoff = restart["max_restarts"], restart["backoff"]
    if not isinstance(max_restarts, int) or isinstance(max_restarts, bool) or max_restarts < 0:
        raise GraphError(f"{where}.max_restarts: expected an integer >= 0")
    if not isinstance(backoff, (int, float)) or isinstance(backoff, bool) or \
            not 0.0 <= backoff < math.inf:
        raise GraphError(f"{where}.backoff: expected finite seconds >= 0")
    return max_restarts, float(backoff)


def _string(entry: dict, key: str, where: str) -> str:
    if key not in entry:
        raise GraphError(f"{where}.{key}: missing")
    value = entry[key]
    if not isinstance(value, str) or not value:
        raise GraphError(f"{where}.{key}: expected a non-empty string")
    return value


def command(spec: NodeSpec) -> list[str]:
    """The node's command line, as `ros2 run` would find it; raises GraphError naming the
    field whose package, executable or parameter file is not installed."""
    from ament_index_python.packages import PackageNotFoundError, get_package_prefix

    package = spec.package or spec.executable
    try:
        prefix = Path(get_package_prefix(package))
    except PackageNotFoundError:
        field = "package" if spec.package else "executable"
        raise GraphError(f"{spec.where}.{field}: no installed package '{package}'") from None
    executable = prefix / "lib" / package / spec.executable
    if not os.access(executable, os.X_OK):
        raise GraphError(f"{spec.where}.executable: no executable {executable}")
    params_file = spec.params_file
    if params_file is None:
        default = prefix / "share" / package / "config" / f"{spec.executable}.yaml"
        params_file = default if default.is_file() else None
    elif not params_file.is_file():
        raise GraphError(f"{spec.where}.params_file: no file {params_file}")
    argv = [str(executable), "--ros-args"]
    if params_file is not None:
        argv += ["--params-file", str(params_file)]
    for key, value in spec.parameters.items():  # JSON values are YAML, as -p expects
        argv += ["-p", f"{key}:={json.dumps(value)}"]
    return argv


def describe_exit(code: int) -> str:
    return f"killed by {signal.Signals(-code).name}" if code < 0 else f"exited with code {code}"


class Reporter:
    """Lines on stdout, whole and in order, from the runner and the nodes' output threads."""

    def __init__(self):
        self._lock = threading.Lock()

    def line(self, prefix: str, text: str) -> None:
        with self._lock:
            print(f"[{prefix}] {text}", flush=True)

    def __call__(self, text: str) -> None:
        self.line("graph", text)


class SupervisedNode:
    """One node's process: started, watched, restarted with backoff or given up on."""

    def __init__(self, spec: NodeSpec, argv: list[str], log_dir: Path | None,
                 report: Reporter):
        self.spec, self.argv, self.log_dir, self.report = spec, argv, log_dir, report
        self.proc = None
        self.restarts = 0
        self.restart_at = None  # monotonic time of a pending restart
        self.finished = False
        self.gave_up = False
        self._output_thread = None

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def start(self) -> None:
        try:
            if self.log_dir is None:
                self.proc = spawn(self.argv, subprocess.PIPE)
                self._output_thread = threading.Thread(target=self._forward_output,
                                                       args=(self.proc.stdout,), daemon=True)
                self._output_thread.start()
            else:
                with open(self.log_dir / f"{self.spec.name}.log", "a") as log:
                    self.proc = spawn(self.argv, log)
        except OSError as error:
            self.report(f"{self.spec.name}: cannot start: {error}; giving up")
            self.finished = self.gave_up = True
            return
        restart = f", restart {self.restarts}/{self.spec.max_restarts}" if self.restarts else ""
        self.report(f"{self.spec.name}: started (pid {self.proc.pid}{restart}): "
                    f"{shlex.join(self.argv)}")

    def _forward_output(self, stream) -> None:
        with stream:
            for line in stream:
                self.report.line(self.spec.name, line.decode(errors="replace").rstrip())

    def poll(self, now: float) -> None:
        """Report an exit and schedule the restart, or start a restart that is due."""
        if self.finished:
            return
        if self.restart_at is not None:
            if now >= self.restart_at:
                self.restart_at = None
                self.restarts += 1
                self.start()
            return
        code = self.proc.poll()
        if code is None:
            return
        signal_group(self.proc, signal.SIGKILL)  # whatever the node itself started
        if code == 0:
            self.report(f"{self.spec.name}: exited with code 0; not restarted")
            self.finished = True
        elif self.restarts >= self.spec.max_restarts:
            self.report(f"{self.spec.name}: {describe_exit(code)}; giving up "
                        f"(max_restarts {self.spec.max_restarts} reached)")
            self.finished = self.gave_up = True
        else:
            delay = min(self.spec.backoff * 2 ** self.restarts, MAX_BACKOFF)
            self.restart_at = now + delay
            self.report(f"{self.spec.name}: {describe_exit(code)}; restart "
                        f"{self.restarts + 1}/{self.spec.max_restarts} in {delay:.1f} s")

    def join_output(self, timeout: float = 1.0) -> None:
        if self._output_thread is not None:
            self._output_thread.join(timeout)


def supervise(nodes: list[SupervisedNode], stop: threading.Event, stop_timeout: float,
              report: Reporter) -> int:
    """Start the nodes and watch them until stop is set (0) or none is left (1 if one was
    given up on); every node still running is stopped on the way out."""
    try:
        for node in nodes:
            node.start()
        while not stop.wait(POLL_PERIOD):
            now = time.monotonic()
            for node in nodes:
                node.poll(now)
            if all(node.finished for node in nodes):
                report("no node left running")
                return 1 if any(node.gave_up for node in nodes) else 0
        return 0
    finally:
        running = [node for node in nodes if node.running]
        if running:
            report(f"stopping {', '.join(node.spec.name for node in running)}")
        codes = stop_processes([node.proc for node in running], stop_timeout)
        for node in nodes:
            node.join_output()
        for node, code in zip(running, codes):
            report(f"{node.spec.name}: stopped, {describe_exit(code)}")


def add_arguments(parser) -> None:
    parser.add_argument("--graph", type=Path, default=DEFAULT_GRAPH, metavar="FILE",
                        help="graph file (YAML); default: the installed default graph")
    parser.add_argument("--only", nargs="+", metavar="NODE",
                        help="start only these nodes of the graph (by name)")
    parser.add_argument("--log-dir", type=Path, metavar="DIR",
                        help="write each node's output to DIR/<name>.log instead of stdout")
    parser.add_argument("--stop-timeout", type=positive(float), default=10.0, metavar="SECONDS",
                        help="seconds nodes get to exit after SIGINT, before SIGTERM")


def run(args) -> int:
    report = Reporter()
    try:
        specs = _select(load_graph(args.graph), args.only)
        commands = []
        for spec in specs:
            try:
                commands.append((spec, command(spec)))
            except GraphError as error:
                if not spec.optional:
                    raise
                report(f"{spec.name}: optional, skipped: {error}")
        if not commands:
            raise GraphError("nodes: none of the selected nodes is installed")
    except GraphError as error:
        print(f"stance graph: bad graph {args.graph}: {error}", file=sys.stderr)
        return 2
    if args.log_dir is not None:
        try:
            args.log_dir.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            print(f"stance graph: --log-dir {args.log_dir}: {error.strerror}", file=sys.stderr)
            return 2
        report(f"node logs in {args.log_dir}")
    nodes = [SupervisedNode(spec, argv, args.log_dir, report) for spec, argv in commands]
    stop = threading.Event()
    previous = {number: signal.signal(number, lambda *_: stop.set())
                for number in (signal.SIGINT, signal.SIGTERM)}
    try:
        return supervise(nodes, stop, args.stop_timeout, report)
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _select(specs: list[NodeSpec], only: list[str] | None) -> list[NodeSpec]:
    if not only:
        return specs
    names = [spec.name for spec in specs]
    unknown = [name for name in only if name not in names]
    if unknown:
        raise GraphError(f"--only: no node named {unknown[0]} (nodes: {', '.join(names)})")
    return [spec for spec in specs if spec.name in only]
