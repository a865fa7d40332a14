"""Child processes of a Stance run: started in their own session with a log file each, and
stopped in reverse order with SIGINT, then SIGKILL after a grace period."""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path


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
        proc = subprocess.Popen(list(argv), stdout=log, stderr=subprocess.STDOUT,
                                env=dict(os.environ, PYTHONUNBUFFERED="1", **(env or {})),
                                start_new_session=True)
        proc.name, proc.log_path = name, log_path
        self._children.append((proc, log))
        return proc

    @staticmethod
    def stop(proc, timeout: float = 10.0) -> int:
        """SIGINT, wait up to timeout seconds, then SIGKILL; returns the exit code."""
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        return proc.returncode

    def stop_all(self) -> None:
        for proc, log in reversed(self._children):
            self.stop(proc)
            log.close()
        self._children.clear()
