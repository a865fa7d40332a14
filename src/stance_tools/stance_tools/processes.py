"""Child processes of a Stance run: each started in its own session (signals reach its whole
process group), and stopped with SIGINT, then SIGTERM and SIGKILL after grace periods."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from contextlib import contextmanager
from pathlib import Path

TERM_GRACE = 2.0  # s between SIGTERM and SIGKILL


def spawn(argv, output, env: dict | None = None) -> subprocess.Popen:
    """Start argv in a new session; stdout and stderr go to output (a file or PIPE)."""
    return subprocess.Popen(list(argv), stdout=output, stderr=subprocess.STDOUT,
                            env=dict(os.environ, PYTHONUNBUFFERED="1", **(env or {})),
                            start_new_session=True)


def signal_group(proc, signal_number) -> None:
    """Send signal_number to proc's process group (proc and its own children), if any is left."""
    try:
        os.killpg(proc.pid, signal_number)
    except ProcessLookupError:
        pass


@contextmanager
def terminate_as_interrupt():
    """Inside, SIGTERM raises KeyboardInterrupt as Ctrl-C does: a command killed by SIGTERM
    still runs its `finally` blocks and stops its child processes (each in its own session,
    the signal does not reach them); without it they would outlive the command."""
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def group_exists(proc) -> bool:
    """True while any process of proc's process group is left (zombies included)."""
    try:
        os.killpg(proc.pid, 0)
    except ProcessLookupError:
        return False
    return True


def stop_processes(procs, timeout: float = 10.0) -> list[int]:
    """Stop procs together: SIGINT, up to timeout s, SIGTERM, up to TERM_GRACE s, SIGKILL;
    what they started themselves gets TERM_GRACE s more, then SIGKILL. Returns exit codes."""
    stopped = [proc for proc in procs if proc.poll() is None]
    for signal_number, grace in ((signal.SIGINT, timeout), (signal.SIGTERM, TERM_GRACE),
                                 (signal.SIGKILL, None)):
        running = [proc for proc in stopped if proc.poll() is None]
        if not running:
            break
        for proc in running:
            signal_group(proc, signal_number)
        deadline = None if grace is None else time.monotonic() + grace
        for proc in running:
            try:
                proc.wait(None if deadline is None else max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
    deadline = time.monotonic() + TERM_GRACE
    while any(map(group_exists, stopped)) and time.monotonic() < deadline:
        time.sleep(0.05)
    for proc in stopped:
        signal_group(proc, signal.SIGKILL)
    return [proc.returncode for proc in procs]


class ProcessGroup:
    def __init__(self, log_dir: Path):
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self._children = []

    def start(self, *argv, name: str | None = None, env: dict | None = None):
        """Start argv; stdout and stderr go to <log_dir>/<name>.log."""
        name = name or Path(argv[0]).name
        log_path = self.log_dir / f"{name}.log"
        if log_path.exists():  # a second process of the same name keeps its own log
            log_path = self.log_dir / f"{name}-{len(self._children)}.log"
        log = open(log_path, "w")
        proc = spawn(argv, log, env)
        proc.name, proc.log_path = name, log_path
        self._children.append((proc, log))
        return proc

    @staticmethod
    def stop(proc, timeout: float = 10.0) -> int:
        """SIGINT, wait up to timeout seconds, then SIGTERM and SIGKILL; returns the exit code."""
        return stop_processes([proc], timeout)[0]

    def stop_all(self) -> None:
        for proc, log in reversed(self._children):
            self.stop(proc)
            log.close()
        self._children.clear()
