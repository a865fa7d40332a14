"""Conversions between the PlanContacts action / stance_msgs and the planning library.

Every function here returns library values or raises GoalRejected, whose message names the
offending field of the action goal (e.g. `start[1].pose`); nothing here touches a node.
Frames: world (z up), m, rad; a surface's frame has z along its outward normal.
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import yaml
from geometry_msgs.msg import Pose
from pik_node.conversions import joint_targets_from_msg, se3_from_pose_msg
from pik_node.node import fill_pose_msg
from sensor_msgs.msg import JointState
from stance.planning.contacts import Contact
from stance.planning.planner import PlanRequest
from stance.planning.scene import Goal, SceneError, load_scene, parse_scene
from stance.tasks import TargetError
from stance.yaml_file import load_yaml
from stance_msgs.msg import Contact as ContactMsg
from stance_msgs.msg import ContactStance, StancePlan
from std_msgs.msg import Header

# Result reasons of the action beyond the planner's own (stance.planning.planner).
MALFORMED_SCENE = "malformed_scene"   # the scene cannot be loaded or parsed
MALFORMED_GOAL = "malformed_goal"     # a goal field other than the goal condition is invalid
# A start contact's pose must lie on its surface: within PLANE_TOLERANCE (m) of the plane,
# its z axis within NORMAL_TOLERANCE (rad) of the surface normal.
PLANE_TOLERANCE = 1e-3
NORMAL_TOLERANCE = 1e-2


class GoalRejected(ValueError):
    """The action goal cannot be planned; `reason` is the result's reason code."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


def scene_from_goal(goal, default_scene: str, robot_spec: str, robot):
    """The goal's scene: scene_yaml if given, else the scene name or path, else
    default_scene. The scene must be for robot_spec (the node's robot parameter)."""
    field = "scene_yaml" if goal.scene_yaml else "scene"
    try:
        if goal.scene_yaml:
            try:
                document = load_yaml(goal.scene_yaml)
            except yaml.YAMLError as error:
                raise SceneError(f"not valid YAML: {error}") from None
            scene = parse_scene(document, "<goal>", robot)
        else:
            scene = load_scene(goal.scene or default_scene, robot)
    except (SceneError, OSError) as error:
        raise GoalRejected(MALFORMED_SCENE, f"{field}: {error}") from None
    if scene.robot != robot_spec:
        raise GoalRejected(MALFORMED_SCENE, f"{field}: scene {scene.name!r} is for robot "
                                            f"{scene.robot!r}, this node plans for {robot_spec!r}")
    return scene


def request_from_goal(goal, scene, robot, max_nodes: int, time_budget: float,
                      workers: int = 1) -> PlanRequest:
    """PlanRequest from a PlanContacts goal; zero max_nodes / time_budget take the node's
    defaults, empty start / key postures / goal_frame the scene's; workers: processes
    generating a node's first sons together (the node's parameter)."""
    if not math.isfinite(goal.time_budget) or goal.time_budget < 0.0:
        raise GoalRejected(MALFORMED_GOAL, f"time_budget: {goal.time_budget} s is not a "
                                           "finite non-negative duration")
    start = tuple(contact_from_msg(msg, scene, f"start[{index}]")
                  for index, msg in enumerate(goal.start))
    return PlanRequest(
        scene=scene, start=start or None,
        key_postures=key_postures_from_msgs(goal.key_base_poses, goal.key_joints, robot),
        goal=goal_condition_from_msg(goal),
        max_nodes=goal.max_nodes or max_nodes, time_budget=goal.time_budget or time_budget,
        seed=goal.seed, ordered_sons=not goal.all_sons, workers=workers)


def contact_from_msg(msg: ContactMsg, scene, field: str) -> Contact:
    """Library Contact from a stance_msgs/Contact whose pose is the contact frame in the
    world; (x, y, theta) are read in the surface frame. msg.friction is not used (the
    surface's own applies)."""
    if msg.spot not in scene.spots:
        raise GoalRejected(MALFORMED_GOAL, f"{field}.spot: unknown spot {msg.spot!r} "
                                           f"(scene spots: {', '.join(scene.spots)})")
    if msg.surface not in scene.surfaces:
        raise GoalRejected(MALFORMED_GOAL, f"{field}.surface: unknown surface {msg.surface!r} "
                                           f"(scene surfaces: {', '.join(scene.surfaces)})")
    local = scene.surfaces[msg.surface].pose.actInv(_se3(msg.pose, f"{field}.pose"))
    height = float(local.translation[2])
    if abs(height) > PLANE_TOLERANCE:
        raise GoalRejected(MALFORMED_GOAL, f"{field}.pose: {height * 1e3:.1f} mm off the plane "
                                           f"of surface {msg.surface!r}")
    tilt = math.acos(float(np.clip(local.rotation[2, 2], -1.0, 1.0)))
    if tilt > NORMAL_TOLERANCE:
        raise GoalRejected(MALFORMED_GOAL, f"{field}.pose: z axis {tilt:.3f} rad away from the "
                                           f"normal of surface {msg.surface!r}")
    theta = math.atan2(local.rotation[1, 0], local.rotation[0, 0])
    return Contact(msg.spot, msg.surface, float(local.translation[0]),
                   float(local.translation[1]), theta, msg.in_stability)


def contact_msg(contact: Contact, surface) -> ContactMsg:
    """stance_msgs/Contact: pose = the contact frame in the world (z = surface normal)."""
    msg = ContactMsg(spot=contact.spot, surface=contact.surface,
                     friction=float(surface.friction), in_stability=contact.in_stability)
    frame = contact.contact_frame(surface)
    fill_pose_msg(msg.pose, pin.SE3ToXYZQUAT(frame))
    return msg


def key_postures_from_msgs(base_poses, joints, robot) -> np.ndarray | None:
    """(K, nq) key postures from free-flyer poses and joint states (None if both empty);
    joints not named keep the robot's default reference configuration (half_sitting)."""
    if not base_poses and not joints:
        return None
    if len(base_poses) != len(joints):
        raise GoalRejected(MALFORMED_GOAL, f"key_base_poses has {len(base_poses)} entries but "
                                           f"key_joints {len(joints)}")
    if len(base_poses) < 2:
        raise GoalRejected(MALFORMED_GOAL, "key_base_poses: a rough trajectory needs at least "
                                           "2 key postures")
    q_index = actuated_q_index(robot)
    postures = np.tile(robot.initial_configuration(), (len(base_poses), 1))
    for k, (pose, joint_state) in enumerate(zip(base_poses, joints)):
        base = _se3(pose, f"key_base_poses[{k}]")
        postures[k, :3] = base.translation
        postures[k, 3:7] = pin.Quaternion(base.rotation).coeffs()
        try:
            positions = joint_targets_from_msg(joint_state.name, joint_state.position)
        except TargetError as error:
            raise GoalRejected(MALFORMED_GOAL, f"key_joints[{k}]: {error}") from None
        for name, value in positions.items():
            if name not in q_index:
                raise GoalRejected(MALFORMED_GOAL, f"key_joints[{k}].name: unknown actuated "
                                                   f"joint {name!r}")
            postures[k, q_index[name]] = value
    return postures


def goal_condition_from_msg(goal) -> Goal | None:
    """The goal condition (None: the scene's). The planner checks it and answers BAD_GOAL
    naming the field (goal.frame, goal.axis, goal.sense, goal.threshold)."""
    if not goal.goal_frame:
        return None
    return Goal(goal.goal_frame, goal.goal_axis, goal.goal_threshold, goal.goal_sense)


def stance_plan_msg(plan, scene, robot, stamp) -> StancePlan:
    """stance_msgs/StancePlan of a library Plan (all poses in the world frame)."""
    header = Header(stamp=stamp, frame_id="world")
    msg = StancePlan(header=header, scene=plan.scene)
    for index, stance in enumerate(plan.stances):
        joints = robot.actuated_positions(stance.q)
        stance_msg = ContactStance(
            header=header, index=index,
            contacts=[contact_msg(c, scene.surfaces[c.surface]) for c in stance.contacts],
            witness_joints=JointState(header=header, name=list(joints),
                                      position=list(joints.values())))
        fill_pose_msg(stance_msg.witness_base_pose, stance.q[:7])
        msg.stances.append(stance_msg)
    return msg


def actuated_q_index(robot) -> dict:
    """Actuated 1-DoF joint name -> its index in q."""
    return {name: robot.model.joints[jid].idx_q
            for name, jid in zip(robot.actuated_joint_names, robot.actuated_joint_ids)
            if robot.model.joints[jid].nq == 1}


def _se3(pose: Pose, field: str) -> pin.SE3:
    try:
        return se3_from_pose_msg(pose)
    except TargetError as error:
        raise GoalRejected(MALFORMED_GOAL, f"{field}: {error}") from None
