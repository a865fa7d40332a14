"""A humanoid mannequin (about 1.75 m, 78 kg) built in code, after the paper's mannequin.

Free-flyer root at the pelvis; lumbar and thoracic spine, neck, shoulders and hips are ball
joints (Pinocchio spherical joints), wrists and ankles swing joints (spherical joints whose
twist the limit file locks), elbows one revolute joint, knees two revolute joints (flexion,
then axial twist). In the standing configuration the world frame has x forward, y to the
left, z up, and the soles lie on z = 0.

Joint frames: spine and neck frames are world-aligned at rest (local z up); arm and leg
frames are turned by pi about x (local x forward, local z down the limb, the rest (bone)
axis of their swing limits). Limits of the spherical joints are in MANNEQUIN_LIMIT_FILE;
revolute limits are in the model's position limits.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pinocchio as pin

from ..robot import Robot

MANNEQUIN_LIMIT_FILE = Path(__file__).resolve().parent.parent / "data" / "mannequin_limits.yaml"

UP = np.eye(3)
DOWN = pin.utils.rotate("x", np.pi)  # local z down the limb, x forward
SIDES = {"left": 1.0, "right": -1.0}

# Segment lengths (m) and masses (kg).
PELVIS_TO_LUMBAR, LUMBAR_TO_THORAX, THORAX_TO_NECK, HEAD_LENGTH = 0.10, 0.20, 0.28, 0.22
SHOULDER_OFFSET = np.array([0.0, 0.19, 0.22])   # from the thoracic joint, left side
HIP_OFFSET = np.array([0.0, 0.09, -0.07])       # from the pelvis, left side
UPPER_ARM, FOREARM, HAND = 0.30, 0.26, 0.19
THIGH, SHANK, ANKLE_HEIGHT, TOE_LENGTH, HEEL_LENGTH = 0.43, 0.42, 0.08, 0.15, 0.05
MASSES = {"pelvis": 10.5, "abdomen": 10.0, "chest": 15.0, "head": 5.5, "upper_arm": 2.1,
          "forearm": 1.3, "hand": 0.5, "thigh": 10.0, "shank": 3.5, "foot": 1.1}
STANDING_KNEE, STANDING_ELBOW = 0.05, 0.15       # rad
# Revolute position limits (rad).
ELBOW_LIMITS, KNEE_LIMITS, KNEE_TWIST_LIMITS = (0.0, 2.5), (0.0, 2.4), (-0.6, 0.6)
JOINT_SPEED = 6.0  # rad/s, revolute velocity limit


def _segment_inertia(mass, bone, radius) -> pin.Inertia:
    """Solid cylinder of `radius` (m) from the joint along `bone` (m, joint frame)."""
    length = np.linalg.norm(bone)
    axis = bone / length
    across = mass * (3 * radius ** 2 + length ** 2) / 12.0
    along = mass * radius ** 2 / 2.0
    rotational = across * (np.eye(3) - np.outer(axis, axis)) + along * np.outer(axis, axis)
    return pin.Inertia(mass, bone / 2.0, rotational)


class _Builder:
    """Adds joints, bodies and frames from world positions and orientations at rest."""

    def __init__(self):
        self.model = pin.Model()
        self.model.name = "mannequin"
        self.world = {0: (np.eye(3), np.zeros(3))}   # joint id -> (rotation, position)

    def local(self, parent, rotation, position) -> pin.SE3:
        parent_rotation, parent_position = self.world[parent]
        return pin.SE3(parent_rotation.T @ rotation,
                       parent_rotation.T @ (position - parent_position))

    def joint(self, parent, name, joint_model, position, rotation=UP, limits=None) -> int:
        bounds = () if limits is None else (  # effort (N m), velocity (rad/s), position
            np.full(1, 1e3), np.full(1, JOINT_SPEED), np.array([limits[0]]),
            np.array([limits[1]]))
        joint_id = self.model.addJoint(parent, joint_model,
                                       self.local(parent, rotation, position), name, *bounds)
        self.world[joint_id] = (rotation, np.asarray(position, dtype=float))
        return joint_id

    def body(self, joint_id, mass, bone_world, radius) -> None:
        """Segment of `mass` from the joint along `bone_world` (m, world at rest)."""
        rotation = self.world[joint_id][0]
        inertia = _segment_inertia(mass, rotation.T @ bone_world, radius)
        self.model.appendBodyToJoint(joint_id, inertia, pin.SE3.Identity())

    def frame(self, joint_id, name, position) -> None:
        """Operational frame, world-aligned at rest, at `position` (m, world at rest)."""
        self.model.addFrame(pin.Frame(name, joint_id, self.local(joint_id, UP, position),
                                      pin.FrameType.OP_FRAME))


def build_mannequin() -> Robot:
    """The mannequin with its "standing" reference configuration (soles on z = 0)."""
    build = _Builder()
    pelvis_position = np.array([0.0, 0.0, THIGH + SHANK + ANKLE_HEIGHT - HIP_OFFSET[2]])
    root = build.joint(0, "root_joint", pin.JointModelFreeFlyer(), pelvis_position)
    build.body(root, MASSES["pelvis"], np.array([0.0, 0.0, 0.1]), 0.15)

    lumbar_position = pelvis_position + [0.0, 0.0, PELVIS_TO_LUMBAR]
    lumbar = build.joint(root, "spine_lower", pin.JointModelSpherical(), lumbar_position)
    build.body(lumbar, MASSES["abdomen"], np.array([0.0, 0.0, LUMBAR_TO_THORAX]), 0.14)
    thorax_position = lumbar_position + [0.0, 0.0, LUMBAR_TO_THORAX]
    thorax = build.joint(lumbar, "spine_upper", pin.JointModelSpherical(), thorax_position)
    build.body(thorax, MASSES["chest"], np.array([0.0, 0.0, THORAX_TO_NECK]), 0.16)
    neck_position = thorax_position + [0.0, 0.0, THORAX_TO_NECK]
    neck = build.joint(thorax, "neck", pin.JointModelSpherical(), neck_position)
    build.body(neck, MASSES["head"], np.array([0.0, 0.0, HEAD_LENGTH]), 0.09)
    build.frame(neck, "head", neck_position + [0.0, 0.0, HEAD_LENGTH / 2])

    for side, sign in SIDES.items():
        mirror = np.array([1.0, sign, 1.0])
        shoulder_position = thorax_position + mirror * SHOULDER_OFFSET
        shoulder = build.joint(thorax, f"{side}_shoulder", pin.JointModelSpherical(),
                               shoulder_position, DOWN)
        build.body(shoulder, MASSES["upper_arm"], np.array([0.0, 0.0, -UPPER_ARM]), 0.05)
        elbow_position = shoulder_position - [0.0, 0.0, UPPER_ARM]
        elbow = build.joint(shoulder, f"{side}_elbow", pin.JointModelRY(), elbow_position,
                            DOWN, ELBOW_LIMITS)
        build.body(elbow, MASSES["forearm"], np.array([0.0, 0.0, -FOREARM]), 0.04)
        wrist_position = elbow_position - [0.0, 0.0, FOREARM]
        wrist = build.joint(elbow, f"{side}_wrist", pin.JointModelSpherical(), wrist_position,
                            DOWN)
        build.body(wrist, MASSES["hand"], np.array([0.0, 0.0, -HAND]), 0.04)
        build.frame(wrist, f"{side}_hand", wrist_position - [0.0, 0.0, HAND / 2])

        hip_position = pelvis_position + mirror * HIP_OFFSET
        hip = build.joint(root, f"{side}_hip", pin.JointModelSpherical(), hip_position, DOWN)
        build.body(hip, MASSES["thigh"], np.array([0.0, 0.0, -THIGH]), 0.08)
        knee_position = hip_position - [0.0, 0.0, THIGH]
        knee = build.joint(hip, f"{side}_knee", pin.JointModelRevoluteUnaligned(0.0, -1.0, 0.0),
                           knee_position, DOWN, KNEE_LIMITS)  # flexes backward
        knee_twist = build.joint(knee, f"{side}_knee_twist", pin.JointModelRZ(), knee_position,
                                 DOWN, KNEE_TWIST_LIMITS)
        build.body(knee_twist, MASSES["shank"], np.array([0.0, 0.0, -SHANK]), 0.05)
        ankle_position = knee_position - [0.0, 0.0, SHANK]
        ankle = build.joint(knee_twist, f"{side}_ankle", pin.JointModelSpherical(),
                            ankle_position, DOWN)
        build.body(ankle, MASSES["foot"], np.array([TOE_LENGTH, 0.0, -ANKLE_HEIGHT]), 0.04)
        sole = ankle_position - [0.0, 0.0, ANKLE_HEIGHT]
        build.frame(ankle, f"{side}_sole", sole)
        build.frame(ankle, f"{side}_toe", sole + [TOE_LENGTH, 0.0, 0.0])
        build.frame(ankle, f"{side}_heel", sole - [HEEL_LENGTH, 0.0, 0.0])

    model = build.model
    standing = pin.neutral(model)
    for side in SIDES:
        standing[model.joints[model.getJointId(f"{side}_knee")].idx_q] = STANDING_KNEE
        ankle = model.joints[model.getJointId(f"{side}_ankle")].idx_q
        flat_foot = pin.exp3(np.array([0.0, STANDING_KNEE, 0.0]))  # undoes the knee bend
        standing[ankle:ankle + 4] = pin.Quaternion(flat_foot).coeffs()
        standing[model.joints[model.getJointId(f"{side}_elbow")].idx_q] = STANDING_ELBOW
    data = model.createData()
    pin.framesForwardKinematics(model, data, standing)
    standing[2] -= data.oMf[model.getFrameId("left_sole")].translation[2]
    return Robot(model=model, urdf="", floating_base=True,
                 reference_configurations={"standing": standing})
