"""Shared test fixtures: an isolated DDS domain per test session and managed child processes.

Tests run inside `source env.sh` (make test). Every process a test starts is stopped at the
end of that test, whatever its outcome (SIGINT, then SIGKILL after a grace period).
"""

import os
import time

import pytest
from stance_tools.processes import ProcessGroup

# Numeric code is pinned to one BLAS thread, as in the nodes.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
# One DDS domain per test session (and per xdist worker), 1-25, never the default one (0):
# two runs at once cross-talk only when they draw the same one. Domains stay within 0-101,
# whose DDS ports lie below Linux's ephemeral port range (ROS 2 docs, "About Domain ID").
DOMAIN_SPACING = 25
_worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").lstrip("gw") or "0"
os.environ["ROS_DOMAIN_ID"] = str(1 + (os.getpid() * 7 + int(_worker)) % DOMAIN_SPACING)


def other_domain_id(index: int = 1) -> int:
    """Another domain of this session (index 1, 2 or 3) for a test whose nodes must not meet
    the module's, or those of a test before it still shutting down: the session's domain
    plus 25 times index, at most 100, never a session's own (1-25) nor the default (0)."""
    if index not in (1, 2, 3):
        raise ValueError(f"other_domain_id: index {index} is not 1, 2 or 3")
    return int(os.environ["ROS_DOMAIN_ID"]) + DOMAIN_SPACING * index


@pytest.fixture
def processes(tmp_path):
    """Children of one test (the product's own ProcessGroup); all stopped after the test."""
    group = ProcessGroup(tmp_path)
    yield group
    group.stop_all()


# s a test waits for a node it started to come up: a pik_node's first start after an install
# or an edit of src/stance compiles its solver (numba, 80-90 s on a 2-core machine with a
# cold cache; later starts load it in half a second). wait_until returns as soon as the node
# is up, so a warm start waits no longer; the cold one no longer depends on an earlier test
# having filled the cache.
NODE_START_TIMEOUT = 240


def wait_until(predicate, timeout, period=0.02, what="condition"):
    """Poll predicate() until it is truthy; fail the test with `what` after timeout seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period)
    pytest.fail(f"timed out after {timeout:.1f} s waiting for {what}")


@pytest.fixture(scope="module")
def flat_steps_plan():
    """(robot, scene, plan) of flat_steps (the library's own planner)."""
    from stance import Robot
    from stance.planning.planner import PlanRequest, plan_contacts
    from stance.planning.scene import load_scene

    robot = Robot.load("talos")
    scene = load_scene("flat_steps", robot)
    outcome = plan_contacts(robot, PlanRequest(scene=scene, ordered_sons=True))
    assert outcome.success, outcome.message
    return robot, scene, outcome.plan
