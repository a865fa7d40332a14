"""The planner in a child process, so a running plan never stalls the node.

A posture generation can hold the GIL for seconds inside native code (collision and QP
calls), which would starve the node's executor threads (no cancel, no goal response). The
child process loads the robot once and plans one request at a time; the parent relays its
progress reports and, once should_stop() is true, sets a shared stop event (the planner
polls it between posture generations). If the child has not answered CANCEL_GRACE s later,
it is killed, with the worker processes it started for a request with workers > 1, and a
fresh one is started: a stop always takes effect within that time. No rclpy here (the child
stays light).
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
import signal
import time
from dataclasses import dataclass

from stance.planning.planner import CANCELLED, PlanOutcome, PlanProgress

CANCEL_GRACE = 0.5   # s a stopped planner may take to return its own outcome
POLL_PERIOD = 0.05   # s between two should_stop() polls in the parent


PLANNER_ERROR = "planner_error"  # result reason when the planner process fails


class PlannerProcessError(RuntimeError):
    """The planner process died or raised (a programming error, not a planning failure)."""


class PlannerProcess:
    """plan_contacts (stance.planning.planner) in a persistent child process."""

    def __init__(self, robot_spec: str):
        self._robot_spec = robot_spec
        self._context = multiprocessing.get_context("spawn")  # no fork of DDS threads
        self._start()
        # not a daemon: killed at exit before multiprocessing would wait for it
        atexit.register(self._kill)

    def _start(self):
        self._connection, child_end = self._context.Pipe()
        self._stop = self._context.Event()
        self._process = self._context.Process(
            target=_serve, args=(self._robot_spec, child_end, self._stop),
            name="contact_planner", daemon=False)  # a daemon may not start the pool
        self._process.start()
        child_end.close()
        self._ready = False

    def plan(self, request, progress=None, should_stop=None) -> PlanOutcome:
        """As plan_contacts(robot, request, progress, should_stop), in the child; raises
        PlannerProcessError if the child dies or raises."""
        if not self._wait_until_ready(should_stop):
            return PlanOutcome(CANCELLED, "cancelled before planning started")
        self._stop.clear()
        self._connection.send(request)
        last = PlanProgress(0, 0, float("inf"), 0.0)
        stop_deadline = None
        while True:
            if self._connection.poll(POLL_PERIOD):
                kind, value = self._receive()
                if kind == "outcome":
                    return value
                last = value
                if progress is not None:
                    progress(value)
            if stop_deadline is None and should_stop is not None and should_stop():
                self._stop.set()
                stop_deadline = time.monotonic() + CANCEL_GRACE
            elif stop_deadline is not None and time.monotonic() > stop_deadline:
                self._restart()
                return PlanOutcome(CANCELLED, f"cancelled (the planner did not stop within "
                                              f"{CANCEL_GRACE} s: its process was restarted)",
                                   statistics={"nodes_expanded": last.nodes_expanded,
                                               "posture_generations": last.posture_generations})

    def _wait_until_ready(self, should_stop) -> bool:
        """True once the child has loaded the robot; False if should_stop() is true first
        (the child keeps loading, for the next request)."""
        while not self._ready:
            if should_stop is not None and should_stop():
                return False
            if self._connection.poll(POLL_PERIOD):
                self._ready = self._receive()[0] == "ready"
        return True

    def _receive(self):
        """The child's next (kind, value); a dead or failing child raises."""
        try:
            kind, value = self._connection.recv()
        except EOFError:
            self._restart()
            raise PlannerProcessError("the planner process died") from None
        if kind == "error":
            raise PlannerProcessError(value)
        return kind, value

    def _restart(self):
        self._kill()
        self._start()

    def _kill(self):
        """Kill the child and the worker processes it may have started (workers > 1)."""
        started = descendants(self._process.pid)
        self._process.kill()
        for pid in started:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        self._process.join()
        self._connection.close()

    def close(self):
        self._kill()
        atexit.unregister(self._kill)


@dataclass(frozen=True)
class ProcessEntry:
    """One live process from /proc/<pid>/stat: parent pid, process group, and the CPU
    time it and its reaped children used (clock ticks: utime + stime + cutime + cstime)."""

    parent: int
    group: int
    cpu_ticks: int


def process_table() -> dict:
    """{pid: ProcessEntry} of the live processes (Linux /proc)."""
    table = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            with open(f"/proc/{entry.name}/stat") as stat:
                text = stat.read()
        except OSError:  # gone meanwhile
            continue
        fields = text[text.rindex(")") + 2:].split()  # from field 3 (state) on
        table[int(entry.name)] = ProcessEntry(int(fields[1]), int(fields[2]),
                                              sum(int(value) for value in fields[11:15]))
    return table


def descendants(pid: int) -> list:
    """Pids of the live descendants of process pid."""
    children = {}
    for child, entry in process_table().items():
        children.setdefault(entry.parent, []).append(child)
    found, frontier = [], [pid]
    while frontier:
        kids = children.get(frontier.pop(), [])
        found.extend(kids)
        frontier.extend(kids)
    return found


def _serve(robot_spec, connection, stop):
    """Child process: load the robot, then plan each request received until EOF."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when this ends
    from threadpoolctl import threadpool_limits
    threadpool_limits(1)  # numeric code on one BLAS thread (workers > 1 add processes)
    from stance import Robot
    from stance.planning.planner import plan_contacts

    robot = Robot.load(robot_spec)
    connection.send(("ready", None))
    while True:
        try:
            request = connection.recv()
        except EOFError:
            return
        try:
            outcome = plan_contacts(robot, request,
                                    progress=lambda report: connection.send(("progress",
                                                                             report)),
                                    should_stop=stop.is_set)
        except Exception as error:  # a planner bug: report it and serve the next request
            connection.send(("error", f"planner raised {type(error).__name__}: {error}"))
            continue
        connection.send(("outcome", outcome))
