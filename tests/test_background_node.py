"""BackgroundNode: call() hands back what the spinning thread's call gave, an exception
included, and forgets a request it gave up on; action_server_answers() says no while the
server is absent or does not answer, yes once it answers, and leaves no request behind;
send_goal() cancels a goal whose answer did not come in time."""

import time

import pytest
from conftest import wait_until
from rclpy.action import ActionClient, ActionServer, CancelResponse, GoalResponse
from rclpy.task import Future
from stance_msgs.action import PlanContacts
from stance_tools.background_node import BackgroundNode

ACTION = "/probe_test/plan_contacts"


class GoalCounter(BackgroundNode):
    """A PlanContacts server that counts the goals it is asked to accept and rejects them;
    silent (discovered, answering nothing) until start_spinning()."""

    def __init__(self):
        super().__init__("probe_test_server")
        self.goals = 0
        self.server = ActionServer(self.node, PlanContacts, ACTION,
                                   execute_callback=lambda handle: PlanContacts.Result(),
                                   goal_callback=self._on_goal)

    def _on_goal(self, goal):
        self.goals += 1
        return GoalResponse.REJECT


@pytest.fixture
def client():
    node = BackgroundNode("probe_test_client")
    node.action_client = ActionClient(node.node, PlanContacts, ACTION)
    node.start_spinning()
    yield node
    node.close()


def pending_requests(action_client) -> int:
    return len(action_client._pending_result_requests) + len(action_client._futures)


def test_call_raises_what_the_call_raised_and_the_thread_spins_on(client):
    with pytest.raises(TypeError):
        client.call(client.action_client.send_goal_async, "not a goal", timeout=5.0)
    assert client.call(lambda: _done(7), timeout=5.0) == 7


def test_call_gives_up_after_its_timeout(client):
    assert client.call(Future, timeout=0.2) is None


def _done(value) -> Future:
    future = Future()
    future.set_result(value)
    return future


def test_the_probe_says_no_until_the_server_answers_and_creates_no_goal(client):
    assert not client.action_server_answers(client.action_client, timeout=0.3)  # no server
    server = GoalCounter()
    try:
        wait_until(client.action_client.server_is_ready, 30, what="the server's discovery")
        # discovered but not spinning: the probe goes unanswered and is forgotten
        assert not client.action_server_answers(client.action_client, timeout=0.5)
        client.call(lambda: _done(None), timeout=1.0)  # lets the cancellation run
        assert pending_requests(client.action_client) == 0
        server.start_spinning()
        answered = [client.action_server_answers(client.action_client) for _ in range(30)]
        assert any(answered), "the server never answered the probe"
        assert server.goals == 0 and pending_requests(client.action_client) == 0
        handle = client.call(client.action_client.send_goal_async, PlanContacts.Goal(),
                             timeout=10.0)
        assert handle is not None and not handle.accepted and server.goals == 1
    finally:
        server.close()


class SlowGoalServer(BackgroundNode):
    """A PlanContacts server that answers a goal request only after `answers_after` s (its
    goal callback blocks the node), accepting it, and then runs the goal for `runs` s
    unless its cancel is asked; the run waits on a timer, so the node takes a cancel
    request meanwhile."""

    def __init__(self, answers_after=1.5, runs=3.0):
        super().__init__("probe_test_slow_server")
        self.answers_after, self.runs = answers_after, runs
        self.ended = []                     # per goal: "canceled" or "succeeded"
        self.server = ActionServer(self.node, PlanContacts, ACTION,
                                   execute_callback=self._execute,
                                   goal_callback=self._on_goal,
                                   cancel_callback=lambda handle: CancelResponse.ACCEPT)

    def _on_goal(self, goal):
        time.sleep(self.answers_after)
        return GoalResponse.ACCEPT

    async def _execute(self, handle):
        deadline, over = time.monotonic() + self.runs, Future()
        timer = self.node.create_timer(0.05, lambda: over.done() or (
            (handle.is_cancel_requested or time.monotonic() > deadline) and
            over.set_result(None)))
        await over
        self.node.destroy_timer(timer)
        if handle.is_cancel_requested:
            handle.canceled()
            self.ended.append("canceled")
        else:
            handle.succeed()
            self.ended.append("succeeded")
        return PlanContacts.Result()


def test_a_goal_answered_too_late_is_canceled(client):
    server = SlowGoalServer()
    server.start_spinning()
    try:
        wait_until(lambda: client.action_server_answers(client.action_client), 30,
                   what="the server to answer")
        # the client gives up after 0.5 s; the server accepts the goal at 1.5 s, then takes
        # the cancel request that waited meanwhile
        assert client.send_goal(client.action_client, PlanContacts.Goal(), timeout=0.5) is None
        wait_until(lambda: server.ended, 10, what="the goal to end")
        assert server.ended == ["canceled"]
    finally:
        server.close()
