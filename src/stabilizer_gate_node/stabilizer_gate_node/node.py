"""stabilizer_gate_node: when the foot stabilizer may run along a contact plan (Escande et
al. 2008, section 4), as a ROS 2 node.

Thin adapter over stance.execution.stabilizer.StabilizerGate: OFF at the start of the
transition that creates a contact making the support non-coplanar, ON at the end of the
transition after which only coplanar contacts support; the blend ramps over `ramp_time`.
Coplanarity uses the `scene`'s surfaces and spot patches, or without a scene the contact
frames of the messages (the first contact seen on a surface name defines its plane).

Contract of /trajectory/active_stance: stance k is published when the transition into it
starts (the first stance: when execution starts), header.stamp = when that transition ends
as planned (the robot reaches stance k's witness), and published again once the robot is
there if that is later than planned, or if no next stance follows (the end of an
execution). A stamp not after the receipt time means the transition is over on receipt:
an OFF switch then comes late, when the contact is already made (its ramp still takes
ramp_time, so nothing jumps). An ON switch at the end of a transition waits for the robot
to be known at its stance: stance k published again, or stance k + 1 (the next transition
starts); without either, the stabilizer stays off. A plan on /contact_planner/plan is
scheduled ahead (logged) and an active stance not following it is reported. Bad input (no
contact, no supporting contact, a spot in two contacts, NaN or non-unit pose, unknown
surface or spot with a scene, a contact off its surface's plane, a stamp before the epoch
or more than MAX_STAMP_AHEAD s ahead) is logged and rejected; the state is kept, learned
surfaces included (a rejected stance or plan teaches none).

Topics (QoS in parentheses):
  sub  /trajectory/active_stance  stance_msgs/ContactStance (reliable, keep last 10)
  sub  /contact_planner/plan      stance_msgs/StancePlan (reliable, transient local, depth 1)
  pub  /stabilizer/state          stance_msgs/StabilizerState at `rate` Hz from the first
                                  accepted stance on (reliable, keep last 1000, as
                                  pik_node's per-step streams)
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import sys

from contact_planner_node.conversions import contact_from_msg
from pik_node.conversions import se3_from_pose_msg, time_from_msg
from pik_node.node import LATCHED, RELIABLE, STREAM, float_parameter, run_node
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from stance.execution.stabilizer import (NOT_YET_REACHED, LearnedSurfaces, StabilizerGate,
                                         Transition, switch)
from stance.planning.scene import load_scene
from stance.tasks import TargetError
from stance_msgs.msg import ContactStance, StabilizerState, StancePlan
from std_msgs.msg import Header

MAX_STAMP_AHEAD = 3600.0   # s: an active stance's stamp is a transition's planned end
ACTIVE_STANCE_TOPIC = "/trajectory/active_stance"
PLAN_TOPIC = "/contact_planner/plan"
STATE_TOPIC = "/stabilizer/state"


class StabilizerGateNode(Node):
    def __init__(self, **kwargs):
        super().__init__("stabilizer_gate_node", **kwargs)
        self._declare_parameters()
        get = self.get_parameter
        scene_spec = get("scene").value
        self.learning = not scene_spec
        self.gate = StabilizerGate(
            LearnedSurfaces() if self.learning else load_scene(scene_spec),
            angle_tolerance=math.radians(get("angle_tolerance").value),
            distance_tolerance=get("distance_tolerance").value,
            ramp_time=get("ramp_time").value)
        self.transitions = []      # Transition of each accepted active stance, pruned
        self.plan_switches = None  # stance index -> planned SwitchEvent | None, last plan
        self.state_pub = self.create_publisher(StabilizerState, STATE_TOPIC, STREAM)
        self.create_subscription(ContactStance, ACTIVE_STANCE_TOPIC, self._on_active_stance,
                                 RELIABLE)
        self.create_subscription(StancePlan, PLAN_TOPIC, self._on_plan, LATCHED)
        self.create_timer(1.0 / get("rate").value, self._publish_state)
        self.get_logger().info(
            f"coplanarity from {scene_spec or 'the contact frames'} within "
            f"{get('angle_tolerance').value:g} deg and {self.gate.distance_tolerance:g} m, "
            f"ramp {self.gate.ramp_time:g} s, state at {get('rate').value:g} Hz")

    def _declare_parameters(self):
        self.declare_parameter("scene", "", ParameterDescriptor(
            description="shipped scene name or scene file path; empty: surfaces learned from "
                        "the stances' contact frames (origins and normals)", read_only=True))
        self.declare_parameter("angle_tolerance", 2.0, float_parameter(
            "largest angle between the surface normals of coplanar contacts (deg)", 0.0, 90.0))
        self.declare_parameter("distance_tolerance", 0.005, float_parameter(
            "largest distance of a contact point from the first contact's plane (m)", 0.0, 1.0))
        self.declare_parameter("ramp_time", 0.5, float_parameter(
            "time for the blend to go from off to on or back (s)", 0.01, 60.0))
        self.declare_parameter("rate", 50.0, float_parameter(
            "publication rate of the stabilizer state (Hz)", 1.0, 1000.0))

    @contextlib.contextmanager
    def _learning(self):
        """Surfaces and spots learned inside the block (no scene) are kept only when it ends
        without an error: a rejected stance or plan teaches nothing."""
        if not self.learning:
            yield
            return
        known = self.gate.scene
        self.gate.scene = known.copy()
        try:
            yield
        except BaseException:
            self.gate.scene = known
            raise

    def _contacts(self, stance: ContactStance, field: str) -> list:
        """Library contacts of a ContactStance; ValueError naming the field. Without a scene,
        unknown surfaces and spots are first learned from the contact frames (call inside
        _learning)."""
        if not stance.contacts:
            raise ValueError(f"{field}.contacts: empty")
        spots = [msg.spot for msg in stance.contacts]
        for index, spot in enumerate(spots):
            if spot in spots[:index]:
                raise ValueError(f"{field}.contacts[{index}].spot: {spot!r} is already in "
                                 f"contacts[{spots.index(spot)}]")
        if self.learning:
            frames = []
            for index, msg in enumerate(stance.contacts):
                try:
                    frames.append(se3_from_pose_msg(msg.pose))
                except TargetError as error:
                    raise ValueError(f"{field}.contacts[{index}].pose: {error}") from None
            for msg, frame in zip(stance.contacts, frames):
                self.gate.scene.learn(msg.spot, msg.surface, frame, msg.friction)
        return [contact_from_msg(msg, self.gate.scene, f"{field}.contacts[{index}]")
                for index, msg in enumerate(stance.contacts)]

    def _on_plan(self, msg: StancePlan):
        try:
            with self._learning():
                stances = [self._contacts(stance, f"stances[{k}]")
                           for k, stance in enumerate(msg.stances)]
                events = self.gate.schedule(stances)
        except ValueError as error:
            self.get_logger().warning(f"plan of scene {msg.scene!r} rejected: {error}")
            return
        self.plan_switches = {index: None for index in range(len(stances))}
        self.plan_switches.update({event.stance_index: event for event in events})
        steps = "; ".join(f"{'on' if e.enabled else 'off'} at the {e.at} of the transition "
                          f"into stance {e.stance_index}" for e in events)
        self.get_logger().info(f"plan of {len(stances)} stances on scene {msg.scene!r}: "
                               f"{steps or 'the stabilizer never switches'}")

    def _on_active_stance(self, msg: ContactStance):
        now = self.get_clock().now().nanoseconds * 1e-9
        try:
            with self._learning():
                stamp = time_from_msg(msg.header.stamp, "header.stamp").nanoseconds * 1e-9
                if stamp > now + MAX_STAMP_AHEAD:
                    raise ValueError(f"header.stamp: {stamp - now:.0f} s ahead, more than "
                                     f"{MAX_STAMP_AHEAD:g} s for a transition's end")
                support = self.gate.support(msg.index, self._contacts(msg, "active_stance"))
        except ValueError as error:
            self.get_logger().warning(f"active stance {msg.index} rejected, state kept: {error}")
            return
        if self.transitions:
            # the last stance announced again, or the next one: the robot is at the last
            # one (or at a new plan's first witness after a failed execution); an earlier
            # confirmation is kept, so that a copy never delays a switch under way
            last = self.transitions[-1]
            self.transitions[-1] = dataclasses.replace(last, reached=min(last.reached, now))
            if last.support.index == msg.index:
                self.get_logger().info(f"active stance {msg.index} reached, stamped "
                                       f"{stamp - last.end:+.2f} s from its planned end")
                return
            self._compare_with_plan(last.support, support)
        end = max(now, stamp)
        self.transitions.append(Transition(support, now, end, reached=NOT_YET_REACHED))
        self.get_logger().info(f"active stance {msg.index}: "
                               f"{'coplanar' if support.coplanar else 'non-coplanar'} support, "
                               f"transition over in {end - now:.2f} s as planned")

    def _compare_with_plan(self, previous, support):
        """Warn when the transition previous -> support switches otherwise than planned."""
        if self.plan_switches is None or previous.index + 1 != support.index or \
                support.index not in self.plan_switches:
            return
        planned, actual = self.plan_switches[support.index], switch(previous, support)
        if _when_and_how(planned) != _when_and_how(actual):
            self.get_logger().warning(
                f"active stance {support.index} does not follow the last plan: planned "
                f"{planned.reason if planned else 'no switch'}, now "
                f"{actual.reason if actual else 'no switch'}")

    def _publish_state(self):
        if not self.transitions:
            return
        now = self.get_clock().now()
        seconds = now.nanoseconds * 1e-9
        state = self.gate.state(seconds, self.transitions)
        self.transitions = self.gate.prune(self.transitions, seconds)
        self.state_pub.publish(StabilizerState(
            header=Header(stamp=now.to_msg()), enabled=state.enabled, blend=state.blend,
            coplanar=state.coplanar, stance_index=state.stance_index,
            balance_mode=state.balance_mode, reason=state.reason))


def _when_and_how(event) -> tuple | None:
    """(at, enabled) of a SwitchEvent, None for no switch: what must agree with the plan."""
    return None if event is None else (event.at, event.enabled)


def main(args=None):
    return run_node("stabilizer_gate_node", StabilizerGateNode,
                    (ParameterException, OSError, ValueError), args)


if __name__ == "__main__":
    sys.exit(main())
