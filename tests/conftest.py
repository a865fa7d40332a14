"""Shared test fixtures: an isolated DDS domain per test session and managed child processes.

Tests run inside `source env.sh` (make test). Every process a test starts is stopped at the
end of that test, whatever its outcome.
"""

import os
import signal
import subprocess
import sys
import time

import pytest

# Numeric code is pinned to one BLAS thread, as in the nodes.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
# One DDS domain per test session (and per xdist worker), so parallel runs never cross-talk.
_worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").lstrip("gw") or "0"
os.environ["ROS_DOMAIN_ID"] = str(1 + (os.getpid() * 7 + int(_worker)) % 100)


class ProcessGroup:
    """Children started by one test; stop() sends SIGINT, then SIGKILL after a grace period."""

    def __init__(self, tmp_path):
        self._tmp_path = tmp_path
        self._children = []

    def start(self, *argv, name=None, env=None):
        """Start argv (a console script or `python -m ...`); output goes to a log file."""
        name = name or os.path.basename(argv[0])
        log_path = self._tmp_path / f"{name}-{len(self._children)}.log"
        log = open(log_path, "w")
        child_env = dict(os.environ, PYTHONUNBUFFERED="1", **(env or {}))
        proc = subprocess.Popen(list(argv), stdout=log, stderr=subprocess.STDOUT, env=child_env,
                                start_new_session=True)
        proc.log_path = log_path
        self._children.append((proc, log))
        return proc

    def python(self, *args, name=None, env=None):
        return self.start(sys.executable, *args, name=name, env=env)

    def stop(self, proc, timeout=10.0):
        """SIGINT, wait, SIGKILL; returns the exit code."""
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        return proc.returncode

    def stop_all(self):
        for proc, log in reversed(self._children):
            self.stop(proc)
            log.close()


@pytest.fixture
def processes(tmp_path):
    group = ProcessGroup(tmp_path)
    yield group
    group.stop_all()


def wait_until(predicate, timeout, period=0.02, what="condition"):
    """Poll predicate() until it is truthy; fail the test with `what` after timeout seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period)
    pytest.fail(f"timed out after {timeout:.1f} s waiting for {what}")
