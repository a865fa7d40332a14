"""Robot kinematic models for the IK core: Pinocchio models with a free-flyer base.

Joint limits apply to actuated one-degree-of-freedom joints only; the floating base is
never limited (the example-robot-data loader's +-1 bounds on the free flyer are ignored).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin


class RobotModelError(ValueError):
    """The robot model cannot be loaded or a name does not exist in it."""


def is_urdf_path(spec: str) -> bool:
    """Whether a robot spec (Robot.load's) is a URDF file's path rather than a name."""
    return spec.endswith(".urdf") or os.path.sep in spec


@dataclass
class Robot:
    """A Pinocchio model plus what the IK needs to know about its joints.

    Attributes:
        model: the Pinocchio model (configuration q of size nq, velocity of size nv).
        urdf: the URDF text the model was built from (published as robot_description).
        floating_base: True when the first joint is a free flyer (never limited).
        reference_configurations: named configurations, e.g. ``half_sitting`` from the SRDF.
        limit_file: YAML of swing and ball-and-socket joint limits shipped with the model
            (stance.swing.load_limit_file), or None.
        name: the robot's name where it has one (an example-robot-data name or
            `mannequin`, as Robot.load takes them), None for a URDF file or a model
            built otherwise.
    """

    model: pin.Model
    urdf: str
    floating_base: bool
    reference_configurations: dict = field(default_factory=dict)
    limit_file: str | None = None
    name: str | None = None

    def __post_init__(self):
        self.data = self.model.createData()
        first_actuated = 2 if self.floating_base else 1
        self.actuated_joint_ids = list(range(first_actuated, self.model.njoints))
        self.actuated_joint_names = [self.model.names[i] for i in self.actuated_joint_ids]
        self.base_nv = 6 if self.floating_base else 0
        limited = []
        for joint_id in self.actuated_joint_ids:
            joint = self.model.joints[joint_id]
            if joint.nq != 1 or joint.nv != 1:
                continue  # continuous joints (cos, sin) and multi-DoF joints: no 1-D limit
            lower = self.model.lowerPositionLimit[joint.idx_q]
            upper = self.model.upperPositionLimit[joint.idx_q]
            if np.isfinite(lower) and np.isfinite(upper) and lower < upper:
                limited.append(joint_id)
        self.limited_joint_ids = limited
        self.limited_joint_names = [self.model.names[i] for i in limited]
        self.limited_q_index = np.array([self.model.joints[i].idx_q for i in limited], dtype=int)
        self.limited_v_index = np.array([self.model.joints[i].idx_v for i in limited], dtype=int)
        self.lower = self.model.lowerPositionLimit[self.limited_q_index].copy()
        self.upper = self.model.upperPositionLimit[self.limited_q_index].copy()
        self.velocity_limit = self.model.velocityLimit[self.limited_v_index].copy()
        # per frame id: velocity DoFs of the joints that move it (its parent and ancestors)
        self.frame_supports = [
            np.array([self.model.joints[joint].idx_v + dof
                      for joint in self.model.supports[frame.parentJoint][1:]
                      for dof in range(self.model.joints[joint].nv)], dtype=np.int64)
            for frame in self.model.frames]

    @classmethod
    def from_example_robot_data(cls, name: str = "talos") -> Robot:
        """Load a robot shipped by example-robot-data (kinematics only, no meshes)."""
        import example_robot_data as erd

        loader = erd.ROBOTS.get(name)
        if loader is None:
            raise RobotModelError(f"unknown example-robot-data robot {name!r}")
        relative = os.path.join(loader.path, loader.urdf_subpath, loader.urdf_filename)
        root = erd.getModelPath(relative)
        urdf_path = os.path.normpath(os.path.join(root, relative))
        srdf_path = None
        if loader.srdf_filename:
            srdf_path = os.path.normpath(
                os.path.join(root, loader.path, loader.srdf_subpath, loader.srdf_filename))
        robot = cls.from_urdf(urdf_path, floating_base=bool(loader.free_flyer),
                              srdf_path=srdf_path)
        robot.name = name
        return robot

    @classmethod
    def from_urdf(cls, urdf_path: str, floating_base: bool = True,
                  srdf_path: str | None = None) -> Robot:
        """Build from a URDF file; an SRDF adds its reference configurations."""
        if not os.path.isfile(urdf_path):
            raise RobotModelError(f"URDF not found: {urdf_path}")
        with open(urdf_path) as urdf_file:
            urdf = urdf_file.read()
        return cls.from_urdf_string(urdf, floating_base, srdf_path)

    @classmethod
    def from_urdf_string(cls, urdf: str, floating_base: bool = True,
                         srdf_path: str | None = None) -> Robot:
        try:
            if floating_base:
                model = pin.buildModelFromXML(urdf, pin.JointModelFreeFlyer())
            else:
                model = pin.buildModelFromXML(urdf)
        except (RuntimeError, ValueError) as error:
            raise RobotModelError(f"cannot build a model from the URDF: {error}") from error
        references = {}
        if srdf_path and os.path.isfile(srdf_path):
            pin.loadReferenceConfigurations(model, srdf_path)
            for entry in model.referenceConfigurations:
                references[entry.key()] = np.array(entry.data())
        return cls(model=model, urdf=urdf, floating_base=floating_base,
                   reference_configurations=references)

    @classmethod
    def load(cls, spec: str) -> Robot:
        """`spec` is `mannequin` (spherical joints, built in code), an example-robot-data
        name (e.g. talos) or a path to a URDF file."""
        if spec == "mannequin":
            from .models.mannequin import MANNEQUIN_LIMIT_FILE, build_mannequin
            robot = build_mannequin()
            robot.limit_file, robot.name = str(MANNEQUIN_LIMIT_FILE), spec
            return robot
        if is_urdf_path(spec):
            return cls.from_urdf(spec)
        return cls.from_example_robot_data(spec)

    def initial_configuration(self, name: str | None = None) -> np.ndarray:
        """A named reference configuration; default the first of half_sitting and standing
        the model has, else neutral."""
        if name is None:
            name = next((known for known in ("half_sitting", "standing")
                         if known in self.reference_configurations), "neutral")
        if name == "neutral":
            return pin.neutral(self.model)
        if name not in self.reference_configurations:
            known = ", ".join(["neutral", *self.reference_configurations])
            raise RobotModelError(f"unknown reference configuration {name!r} (known: {known})")
        return self.reference_configurations[name].copy()

    def frame_id(self, frame: str) -> int:
        if not self.model.existFrame(frame):
            raise RobotModelError(f"unknown frame {frame!r}")
        return self.model.getFrameId(frame)

    def joint_id(self, joint: str) -> int:
        if not self.model.existJointName(joint):
            raise RobotModelError(f"unknown joint {joint!r}")
        return self.model.getJointId(joint)

    def velocity_indices(self, joints) -> np.ndarray:
        """Indices into a velocity (nv) of the named joints' DoFs, in order."""
        index = []
        for name in joints:
            joint = self.model.joints[self.joint_id(name)]
            index.extend(range(joint.idx_v, joint.idx_v + joint.nv))
        return np.array(index, dtype=np.int64)

    def actuated_positions(self, q: np.ndarray) -> dict:
        """Actuated 1-DoF joint positions by name (rad or m)."""
        return {name: float(q[self.model.joints[jid].idx_q])
                for name, jid in zip(self.actuated_joint_names, self.actuated_joint_ids)
                if self.model.joints[jid].nq == 1}
