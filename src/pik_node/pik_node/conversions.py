"""Conversions between stance_msgs / standard messages and the stance library.

Every function here either returns library values or raises StackError / TargetError with
a message meant for the sender; nothing here touches a node.
"""

from __future__ import annotations

import numpy as np
from geometry_msgs.msg import Point, Polygon, Pose
from rclpy.time import Time
from stance.stack import AXES, FRAME_KINDS, KINDS, StackError, TaskSpec, short_repr
from stance.tasks import (MAX_COORDINATE, TargetError, pose_from_position_quaternion,
                          require_finite)
from stance_msgs.msg import TaskSpec as TaskSpecMsg

import pinocchio as pin

WORLD_FRAMES = ("", "world")
# m: the largest |x|, |y| or |z| a target or the base may have: the library's bound on
# targets (tasks.MAX_COORDINATE), checked here too to name the message's field
MAX_POSITION = MAX_COORDINATE
KIND_CODES = {
    TaskSpecMsg.KIND_POSE: "pose",
    TaskSpecMsg.KIND_POSITION: "position",
    TaskSpecMsg.KIND_ORIENTATION: "orientation",
    TaskSpecMsg.KIND_COM: "com",
    TaskSpecMsg.KIND_POSTURE: "posture",
    TaskSpecMsg.KIND_SUPPORT: "support",
}
AXIS_BITS = {axis: 1 << index for index, axis in enumerate(AXES)}
assert set(KIND_CODES.values()) == set(KINDS)


def spec_from_msg(msg: TaskSpecMsg) -> TaskSpec:
    """Library TaskSpec from a stance_msgs/TaskSpec (validated later with the stack)."""
    if msg.kind not in KIND_CODES:
        raise StackError(f"task {short_repr(msg.name)}: unknown kind code {msg.kind} "
                         f"(expected {sorted(KIND_CODES)})")
    if msg.axis_mask & ~0b111111:
        raise StackError(f"task {short_repr(msg.name)}: axis_mask {msg.axis_mask} has unknown "
                         "bits")
    axes = tuple(axis for axis, bit in AXIS_BITS.items() if msg.axis_mask & bit)
    return TaskSpec(name=msg.name, kind=KIND_CODES[msg.kind], frame=msg.frame,
                    priority=msg.priority, weight=msg.weight, axes=axes, gain=msg.gain,
                    enabled=msg.enabled)


def msg_from_spec(spec: TaskSpec) -> TaskSpecMsg:
    codes = {kind: code for code, kind in KIND_CODES.items()}
    mask = sum(AXIS_BITS[axis] for axis in spec.axes)
    return TaskSpecMsg(name=spec.name, kind=codes[spec.kind], frame=spec.frame,
                       priority=spec.priority, weight=float(spec.weight), axis_mask=mask,
                       gain=float(spec.gain), enabled=spec.enabled)


def check_world_frame(frame_id: str) -> None:
    if frame_id not in WORLD_FRAMES:
        raise TargetError(f"unknown frame {short_repr(frame_id)}: targets are expressed in "
                          "'world'")


def se3_from_pose_msg(pose: Pose) -> pin.SE3:
    """pin.SE3 from geometry_msgs/Pose (m, unit quaternion); rejects NaN, non-unit q and
    positions beyond MAX_POSITION."""
    position = (pose.position.x, pose.position.y, pose.position.z)
    orientation = (pose.orientation.x, pose.orientation.y, pose.orientation.z,
                   pose.orientation.w)
    placement = pose_from_position_quaternion(position, orientation)
    check_position_bound(position)
    return placement


def point_from_msg(point: Point) -> np.ndarray:
    """(x, y, z) (m) from a geometry_msgs/Point; rejects NaN and positions beyond
    MAX_POSITION."""
    position = require_finite((point.x, point.y, point.z), "position")
    check_position_bound(position)
    return position


def polygon_from_msg(polygon: Polygon) -> np.ndarray:
    """(vertices, 2) world xy (m) from a geometry_msgs/Polygon (z ignored); rejects NaN
    and coordinates beyond MAX_POSITION (the task checks the rest: count, area)."""
    vertices = require_finite([(point.x, point.y) for point in polygon.points],
                              "polygon").reshape(-1, 2)
    for vertex in vertices:
        check_position_bound(vertex)
    return vertices


def check_position_bound(position) -> None:
    """Raise TargetError if a (finite) position has a coordinate beyond MAX_POSITION (m)."""
    for axis, value in zip("xyz", position):
        if not abs(value) <= MAX_POSITION:
            raise TargetError(f"position {axis} = {value:g} m is beyond the bound "
                              f"|{axis}| <= {MAX_POSITION:g} m")


def joint_targets_from_msg(names, positions) -> dict:
    """Joint name -> position (rad) from sensor_msgs/JointState fields (a posture target or
    set_configuration's joints: the messages name neither, the caller says which)."""
    if len(names) != len(positions):
        raise TargetError(f"joint names and positions differ in number ({len(names)} and "
                          f"{len(positions)})")
    if len(set(names)) != len(names):
        raise TargetError("a joint name is repeated")
    values = np.asarray(positions, dtype=float)
    for name, value in zip(names, values.tolist()):
        if not np.isfinite(value):
            raise TargetError(f"position of {name} is NaN or infinite ({value})")
    return dict(zip(names, values.tolist()))


def check_within_limits(robot, joints: dict, tolerance: float = 1e-9) -> None:
    """Raise TargetError naming the first of `joints` (name -> position, rad or m) that lies
    outside its URDF limits by more than tolerance; unlimited and unknown joints pass."""
    limited = dict(zip(robot.limited_joint_names, zip(robot.lower, robot.upper)))
    for name, value in joints.items():
        lower, upper = limited.get(name, (-np.inf, np.inf))
        if not lower - tolerance <= value <= upper + tolerance:
            raise TargetError(f"{name} = {value:.4f} outside its limits "
                              f"[{lower:.4f}, {upper:.4f}]")


def check_task_frames(robot, specs) -> None:
    """Raise StackError for a frame task on a frame that no joint moves (attached to the
    world: 'universe', Pinocchio's FIXED_JOINT frame 0, and whatever hangs on it; the
    task's Jacobian would be zero) or on a free flyer's joint frame ('root_joint', a JOINT
    frame rather than a body: the base is targeted through its body frame). Other problems
    of the specs are left to the stack's own validation."""
    model = robot.model
    for spec in specs:
        if spec.kind not in FRAME_KINDS or not isinstance(spec.frame, str) \
                or not model.existFrame(spec.frame):
            continue
        frame = model.frames[model.getFrameId(spec.frame)]
        where = f"task {short_repr(spec.name)}: frame {spec.frame!r}"
        if frame.parentJoint == 0:
            raise StackError(f"{where} is fixed in the world (no joint moves it): "
                             f"a {spec.kind} task on it could never act")
        if robot.floating_base and frame.parentJoint == 1 \
                and frame.type == pin.FrameType.JOINT:
            bodies = [body.name for body in model.frames if body.parentJoint == 1
                      and body.type == pin.FrameType.BODY]
            raise StackError(f"{where} is the free flyer's joint frame, not a body frame: "
                             f"target the base body{f' ({bodies[0]!r})' if bodies else ''}")


def configuration_from_msg(robot, q: np.ndarray, base_pose: Pose, names, positions,
                           tolerance: float = 1e-9) -> np.ndarray:
    """A new configuration (nq): q with the free-flyer at base_pose (world, within
    MAX_POSITION; ignored for a fixed-base robot) and the named actuated 1-DoF joints at
    positions (rad or m), which must lie inside their limits (within tolerance). Raises
    TargetError naming the field."""
    try:
        joints = joint_targets_from_msg(names, positions)
    except TargetError as error:
        raise TargetError(f"joints: {error}") from None
    new_q = np.array(q, dtype=float)
    if robot.floating_base:
        try:
            base = se3_from_pose_msg(base_pose)
        except TargetError as error:
            raise TargetError(f"base_pose: {error}") from None
        new_q[:7] = pin.SE3ToXYZQUAT(base)
    for name in joints:
        joint = robot.model.joints[robot.model.getJointId(name)] \
            if name in robot.actuated_joint_names else None
        if joint is None or joint.nq != 1:
            raise TargetError(f"joints: unknown actuated 1-DoF joint {short_repr(name)}")
        new_q[joint.idx_q] = joints[name]
    try:
        check_within_limits(robot, joints, tolerance)
    except TargetError as error:
        raise TargetError(f"joints: {error}") from None
    return new_q


def check_stamp(stamp, field: str) -> None:
    """TargetError naming the field for a builtin_interfaces/Time before the epoch, which
    rclpy refuses with a bare ValueError, or with nanoseconds past a second (a stamp not
    normalised)."""
    if stamp.sec < 0:
        raise TargetError(f"{field}: {stamp.sec} s, before the epoch")
    if stamp.nanosec >= 1_000_000_000:
        raise TargetError(f"{field}: nanosec {stamp.nanosec} is a second or more")


def time_from_msg(stamp, field: str) -> Time:
    """rclpy Time of a builtin_interfaces/Time checked by check_stamp."""
    check_stamp(stamp, field)
    return Time.from_msg(stamp)
