"""An rclpy node in its own context, spun by a background thread until close(): the base
of the demo's graph client and of the tests' probes."""

from __future__ import annotations

import threading
import time
import uuid

import rclpy
from rclpy.action.client import ClientGoalHandle
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from unique_identifier_msgs.msg import UUID

PROBE_WAIT = 1.0  # s: how long the answer probe, or a cancel after a timeout, waits


class BackgroundNode:
    """An rclpy node in its own context, spun by a background thread until close()."""

    def __init__(self, name, domain_id=None):
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = Node(name, context=self.context)
        self.executor, self._thread = None, None    # until start_spinning()

    def start_spinning(self):
        """Call once the node's entities exist."""
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._running = True
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self):
        while self._running and self.context.ok():
            self.executor.spin_once(timeout_sec=0.05)

    def call(self, function, *args, timeout: float, **kwargs):
        """The result of the future that function(*args, **kwargs) returns, the call made in
        the spinning thread (an rclpy ActionClient can handle the answer to a request before
        its *_async method has registered the future, ros2/rclpy#1123); an exception it
        raises is raised here, the spinning thread going on. None after timeout s: the call
        is then not made, or its future cancelled (the client forgets the request)."""
        task = self.executor.create_task(_future_of, function, args, kwargs)
        deadline = time.monotonic() + timeout
        while not (task.done() and task.result().done()):
            if time.monotonic() > deadline:
                if task.done():
                    self.executor.create_task(task.result().cancel)
                else:
                    task.cancel()
                return None
            time.sleep(0.02)
        return task.result().result()

    def send_goal(self, client, goal, timeout: float, **kwargs):
        """The goal handle (accepted or not) for goal, sent by client (an ActionClient of
        this node; kwargs: send_goal_async's but goal_uuid), None after timeout s without
        the server's answer. The server may have accepted the goal and its answer been lost
        (Fast DDS drops a response to a reader the server has not matched yet;
        action_server_answers) or be late: the goal would run on unseen, holding a server
        that serves one goal at a time. So a timeout also sends a cancel request for the
        goal's id. It cancels a goal the server has taken (the goal and cancel requests
        travel apart, but a server taking both at once handles the goal first); a goal
        request the server has not taken yet, after timeout s, is not canceled (the
        answer, "unknown goal", is not awaited beyond PROBE_WAIT s). rclpy logs a late
        answer as "Ignoring unexpected goal response"."""
        goal_id = _random_goal_id()
        handle = self.call(client.send_goal_async, goal, goal_uuid=goal_id, timeout=timeout,
                           **kwargs)
        if handle is None:
            self.call(ClientGoalHandle(client, goal_id, None).cancel_goal_async,
                      timeout=PROBE_WAIT)
        return handle

    def action_server_answers(self, client, timeout: float = PROBE_WAIT) -> bool:
        """Whether the server of `client` (an ActionClient of this node) answers a request
        within timeout s. ActionClient.server_is_ready only says that the server's request
        readers match ours, while Fast DDS drops a response whose reader the server has not
        matched within 100 ms (ros2/rmw_fastrtps#390, a warning in the server's log): a
        goal sent right after discovery can stay unanswered. The probe, a result request
        for an unknown goal, leaves nothing behind on the server (the answer is
        STATUS_UNKNOWN). It goes through the result service, which rcl_action creates after
        the goal and cancel services: an answer means the server has matched our result
        reader, and so the goal and cancel ones, as long as the server matches our readers in
        the order they were announced (one reliable builtin writer announces them)."""
        if not client.server_is_ready():
            return False
        unknown_goal = ClientGoalHandle(client, _random_goal_id(), None)
        return self.call(unknown_goal.get_result_async, timeout=timeout) is not None

    def close(self):
        if self._thread is not None:
            self._running = False
            self._thread.join(timeout=2.0)
            self.executor.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)


def _future_of(function, args, kwargs) -> Future:
    """function(*args, **kwargs), a future; the future of the exception if it raises (which
    would otherwise end the executor's spin)."""
    try:
        return function(*args, **kwargs)
    except Exception as error:  # noqa: BLE001 - handed to the caller through the future
        failed = Future()
        failed.set_exception(error)
        return failed


def _random_goal_id() -> UUID:
    """A fresh random goal id (unique_identifier_msgs/UUID)."""
    return UUID(uuid=list(uuid.uuid4().bytes))
