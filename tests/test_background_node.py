"""BackgroundNode.action_server_answers: the probe that a goal sent next gets its answer.
It says no while there is no server, yes once one answers, and creates no goal."""

import time

from rclpy.action import ActionClient, ActionServer, GoalResponse
from stance_msgs.action import PlanContacts
from stance_tools.background_node import BackgroundNode

ACTION = "/probe_test/plan_contacts"


class GoalCounter(BackgroundNode):
    """A PlanContacts server that counts the goals it is asked to accept and rejects them."""

    def __init__(self):
        super().__init__("probe_test_server")
        self.goals = 0
        self.server = ActionServer(self.node, PlanContacts, ACTION,
                                   execute_callback=lambda handle: PlanContacts.Result(),
                                   goal_callback=self._on_goal)
        self.start_spinning()

    def _on_goal(self, goal):
        self.goals += 1
        return GoalResponse.REJECT


def test_the_probe_says_no_without_a_server_and_yes_without_creating_a_goal():
    client = BackgroundNode("probe_test_client")
    action_client = ActionClient(client.node, PlanContacts, ACTION)
    client.start_spinning()
    server = None
    try:
        started = time.monotonic()
        assert not client.action_server_answers(action_client, timeout=0.5)
        assert time.monotonic() - started < 5.0
        server = GoalCounter()
        deadline = time.monotonic() + 30.0
        while not client.action_server_answers(action_client):
            assert time.monotonic() < deadline, "the server never answered the probe"
        assert server.goals == 0
        handle = client.call(action_client.send_goal_async, PlanContacts.Goal(), timeout=10.0)
        assert handle is not None and not handle.accepted and server.goals == 1
    finally:
        client.close()
        if server is not None:
            server.close()
