"""trajectory_node's preparer and executor threads, in process (another DDS domain), with
verification, interpolation and execution stubbed: which plans execute, how often, and
what the status says when a newer plan is rejected, in sequences the DDS tests cannot time
(a plan held ready while a newer one is prepared, plans arriving faster than they are
prepared, a rejection after the plan under way ended)."""

import contextlib
import threading
import time
from types import SimpleNamespace

import pytest
import rclpy
import trajectory_node.node as trajectory
from conftest import other_domain_id, wait_until
from geometry_msgs.msg import PoseStamped
from pik_node.node import RELIABLE
from stance.stack import TaskSpec
from stance.stopping import Stopped
from stance_msgs.msg import SolverStatus
from stance_tools.background_node import BackgroundNode
from trajectory_node.conversions import PlanRejected
from trajectory_node.node import ExecutionError, TrajectoryNode


class Script:
    """Stubs: plan "bad ..." fails its verification, each plan takes prepare_time[name] s
    to verify and `execute_time` s to execute, and each execution ends in `done`. Records
    the plans executed and the statuses published."""

    def __init__(self, node, prepare_time, execute_time):
        self.node, self.prepare_time, self.execute_time = node, prepare_time, execute_time
        self.executed, self.statuses, self.verified = [], [], []
        node.status_pub.publish = lambda msg: self.statuses.append(msg.data)
        node._execute = self.execute
        node._time = lambda path: None

    def verify(self, plan, scene, robot, should_stop=None):
        self.verified.append(plan)
        time.sleep(self.prepare_time[plan])
        if plan.startswith("bad"):
            raise PlanRejected("fails verification: stub")

    def execute(self, msg, plan, scene, planner, path, trajectory):
        self.node._status("executing", f"plan {plan}")
        time.sleep(self.execute_time)
        self.executed.append(plan)
        self.node._status("done", f"plan {plan}")

    def arrive(self, name):
        """What _on_plan does with a plan that converted."""
        msg = SimpleNamespace(stances=[], scene=name)
        with self.node._wakeup:
            self.node._arrival = (msg, name, None)
            self.node._wakeup.notify_all()

    def during_preparation(self, first, second):
        """`second` arrives while `first` is being verified; returns once both executions
        or rejections are over, nothing left to prepare or execute."""
        self.arrive(first)
        wait_until(lambda: first in self.verified, 5, what=f"{first} verified")
        self.arrive(second)
        wait_until(lambda: self.executed and self.idle(), 10, what="an execution")

    def idle(self) -> bool:
        node = self.node
        with node._wakeup:
            return not (node._arrival or node._preparing or node._ready or node._pending
                        or node._executing)


class StubPlanner:
    def __init__(self, *args, **kwargs):
        pass

    def interpolate(self, plan, should_stop=None):
        return SimpleNamespace(q=None, event_samples=None)


class Endless:
    """A step of the preparation that only ends when asked to stop; `asking` is set once
    it asks."""

    def __init__(self):
        self.asking = threading.Event()

    def __call__(self, should_stop):
        while not should_stop():
            self.asking.set()
            time.sleep(0.01)
        raise Stopped("stopped")


@pytest.fixture
def stubbed(monkeypatch):
    """stubbed(prepare_time, execute_time): a context giving a running node's Script."""
    monkeypatch.setattr(trajectory, "CollisionModel", lambda robot, scene: None)
    monkeypatch.setattr(trajectory, "TransitionPlanner", StubPlanner)

    @contextlib.contextmanager
    def start(prepare_time, execute_time=0.3):
        context = rclpy.Context()
        rclpy.init(context=context, domain_id=other_domain_id())
        try:
            node = TrajectoryNode(context=context)
            script = Script(node, prepare_time, execute_time)
            monkeypatch.setattr(trajectory, "_require_verified", script.verify)
            node.start_worker()
            try:
                yield script
            finally:
                node.stop_worker()
                node.destroy_node()
        finally:
            rclpy.try_shutdown(context=context)
    return start


def test_a_plan_ready_goes_on_when_the_newer_one_is_rejected(stubbed):
    """A is prepared while B arrives; B fails: A executes once, and no status says failed
    (A used to be dropped for B, then B failed: nothing ran)."""
    with stubbed({"A": 0.3, "bad B": 0.3}) as script:
        script.during_preparation("A", "bad B")
        assert script.executed == ["A"]
        rejection = next(s for s in script.statuses if "rejected" in s)
        assert rejection.startswith("interpolating: a newer plan was rejected (fails "
                                    "verification: stub)"), script.statuses
        assert rejection.endswith("the plan received before it goes on")
        assert not any(s.startswith("failed") for s in script.statuses), script.statuses


def test_a_newer_plan_ready_replaces_the_one_held(stubbed):
    """A is prepared while B arrives; B is ready too: only B executes."""
    with stubbed({"A": 0.3, "B": 0.3}) as script:
        script.during_preparation("A", "B")
        assert script.executed == ["B"]
        assert any(s.startswith("interpolating: a newer plan of 0 stances on scene 'B', n = "
                                "20 is being prepared") for s in script.statuses), \
            script.statuses


def test_plans_sent_faster_than_prepared_still_execute(stubbed):
    """A to E each arrive while the one before is verified. A ready plan waits for one
    newer preparation at most: B (which replaced A) executes while plans still arrive, then
    D (which replaced C), then E (the newest used to wait for the stream to end: only E
    executed, after all five preparations)."""
    with stubbed({name: 0.3 for name in "ABCDE"}, execute_time=0.3) as script:
        script.arrive("A")
        for previous, name in zip("ABCD", "BCDE"):
            wait_until(lambda previous=previous: previous in script.verified, 5,
                       what=f"{previous} verified")
            script.arrive(name)
        assert "executing: plan B" in script.statuses, script.statuses
        wait_until(lambda: "E" in script.executed and script.idle(), 10, what="E executed")
        assert script.executed == ["B", "D", "E"]


def test_a_rejection_after_the_plan_under_way_ended_says_failed(stubbed):
    """A executes while B (to reject) is verified, and A ends first: B's rejection is the
    last status and says failed, not that A goes on."""
    with stubbed({"A": 0.05, "bad B": 1.0}, execute_time=0.3) as script:
        script.arrive("A")
        wait_until(lambda: any(s.startswith("executing: plan A") for s in script.statuses),
                   5, what="A executing")
        script.arrive("bad B")
        wait_until(lambda: script.statuses[-1].startswith("failed") and script.idle(), 10,
                   what="B rejected")
        assert script.executed == ["A"]
        assert script.statuses[-1] == "failed: plan rejected: fails verification: stub"


def test_a_rejection_during_an_execution_says_it_goes_on(stubbed):
    with stubbed({"A": 0.05, "bad B": 0.05}, execute_time=1.0) as script:
        script.arrive("A")
        wait_until(lambda: any(s.startswith("executing: plan A") for s in script.statuses),
                   5, what="A executing")
        script.arrive("bad B")
        wait_until(lambda: script.executed and script.idle(), 10, what="A executed")
        assert script.executed == ["A"]
        assert "executing: a newer plan was rejected (fails verification: stub); this one " \
               "goes on" in script.statuses, script.statuses
        assert script.statuses[-1] == "done: plan A"


def test_plans_in_a_row_each_execute_once(stubbed):
    with stubbed({name: 0.05 for name in "ABC"}, execute_time=0.1) as script:
        for name in "ABC":
            script.arrive(name)
            wait_until(lambda name=name: name in script.executed, 10, what=f"{name} executed")
        wait_until(script.idle, 5, what="idle")
        assert script.executed == ["A", "B", "C"]


@pytest.mark.parametrize("step", ["verification", "interpolation", "timing"])
def test_stopping_the_node_ends_a_preparation_under_way(stubbed, monkeypatch, step):
    """Each step of a preparation asks to stop between stances, samples or transitions:
    stop_worker ends it at once, with no status, the preparer idle (an interpolation used
    to go on in a daemon thread after the node stopped; a verification or a time-optimal
    timing held the stop for seconds on the chair plan)."""
    endless = Endless()
    with stubbed({"A": 0.0}) as script:
        if step == "verification":
            monkeypatch.setattr(trajectory, "_require_verified",
                                lambda plan, scene, robot, should_stop: endless(should_stop))
        elif step == "interpolation":
            monkeypatch.setattr(StubPlanner, "interpolate",
                                lambda self, plan, should_stop: endless(should_stop))
        else:   # the node's own _time, on to the library's time-optimal timing
            del script.node._time
            script.node.timing = "time_optimal"
            monkeypatch.setattr(trajectory, "time_optimal_trajectory",
                                lambda *args, should_stop: endless(should_stop))
        script.arrive("A")
        wait_until(endless.asking.is_set, 5, what=f"the {step} under way")
        statuses = len(script.statuses)
        began = time.monotonic()
        script.node.stop_worker()
        assert time.monotonic() - began < 1.0
        assert not any(worker.is_alive() for worker in script.node._workers)
        assert len(script.statuses) == statuses and script.executed == []
        assert script.idle()


def test_streaming_waits_for_pik_node_to_subscribe_to_each_target(stubbed):
    """After a stack, streaming waits until this node's publisher on each task's target
    topic has matched pik_node (the /pik/status publisher): a target published then
    reaches it (one sent before the match is lost). pik_node not subscribing in time fails
    the plan, naming the topic."""
    # a topic of its own: a pik_node of an earlier test may have left left_sole's behind
    spec = TaskSpec(name="matched_sole", kind="pose", frame="left_sole_link")
    received = []
    with stubbed({}) as script:
        node = script.node
        pik = BackgroundNode("pik_node", other_domain_id())
        try:
            pik.node.create_publisher(SolverStatus, "/pik/status", 1)
            pik.start_spinning()
            wait_until(lambda: node.get_publishers_info_by_topic("/pik/status"), 30,
                       what="pik_node's status publisher in the graph")
            node.service_timeout = 0.5
            with pytest.raises(ExecutionError, match=r"^not started after 0.5 s: no "
                               "subscription of pik_node to /pik/tasks/matched_sole/target$"):
                node._await_target_subscriptions([spec], "plan", "not started")
            pik.node.create_subscription(PoseStamped, "/pik/tasks/matched_sole/target",
                                         received.append, RELIABLE)
            node.service_timeout = 30.0
            node._await_target_subscriptions([spec], "plan", "not started")
            node._target_publisher(spec).publish(PoseStamped())
            wait_until(lambda: received, 5, what="the target at pik_node")
        finally:
            pik.close()
