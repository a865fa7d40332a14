"""Conversions between stance_msgs and the execution library for trajectory_node.

Every function here returns library values or messages, or raises ValueError with a message
naming the offending field; nothing here touches a node. Frames: world, m, rad.
"""

from __future__ import annotations

import numpy as np
from contact_planner_node.conversions import contact_from_msg
from pik_node.conversions import configuration_from_msg, msg_from_spec
from pik_node.node import fill_pose_msg
from sensor_msgs.msg import JointState
from stance.planning.contacts import Plan, Stance
from stance.planning.scene import SceneError, load_scene
from stance.tasks import TargetError
from stance_msgs.srv import SetConfiguration, SetStack


class PlanRejected(ValueError):
    """A StancePlan message that cannot be executed; the message names the field."""


def plan_from_msg(msg, robot, robot_spec: str):
    """(library Plan, scene) of a stance_msgs/StancePlan for robot (robot_spec: the node's
    robot parameter). Witnesses must name every actuated 1-DoF joint, inside its limits."""
    if len(msg.stances) < 2:
        raise PlanRejected(f"stances: {len(msg.stances)} stance(s), a plan to execute needs "
                           "at least 2")
    try:
        scene = load_scene(msg.scene, robot)
    except (SceneError, OSError) as error:
        raise PlanRejected(f"scene: {error}") from None
    if scene.robot != robot_spec:
        raise PlanRejected(f"scene: {scene.name!r} is for robot {scene.robot!r}, this node "
                           f"executes plans of {robot_spec!r}")
    joints = set(robot.actuated_positions(robot.initial_configuration()))
    stances = []
    for k, stance in enumerate(msg.stances):
        field = f"stances[{k}]"
        if not stance.contacts:
            raise PlanRejected(f"{field}.contacts: empty")
        contacts = tuple(contact_from_msg(contact, scene, f"{field}.contacts[{j}]")
                         for j, contact in enumerate(stance.contacts))
        missing = joints - set(stance.witness_joints.name)
        if missing:
            raise PlanRejected(f"{field}.witness_joints: {len(missing)} actuated joints "
                               f"missing, e.g. {sorted(missing)[0]!r}")
        try:
            q = configuration_from_msg(robot, robot.initial_configuration(),
                                       stance.witness_base_pose, stance.witness_joints.name,
                                       stance.witness_joints.position)
        except TargetError as error:
            raise PlanRejected(f"{field}.witness: {error}") from None
        stances.append(Stance(contacts, q))
    return Plan(scene.name, robot_spec, stances), scene


def configuration_request(robot, q: np.ndarray) -> SetConfiguration.Request:
    """/pik/set_configuration request for configuration q (nq)."""
    request = SetConfiguration.Request()
    fill_pose_msg(request.base_pose, q[:7])
    joints = robot.actuated_positions(q)
    request.joints = JointState(name=list(joints), position=list(joints.values()))
    return request


def stack_request(specs) -> SetStack.Request:
    return SetStack.Request(tasks=[msg_from_spec(spec) for spec in specs])
