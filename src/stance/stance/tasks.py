"""IK tasks: one class per task kind. A task turns the robot's current kinematics into a
Jacobian J (rows x nv) and an error e (rows), both restricted to its selected axes.

Frames: errors and Jacobians are expressed in the world-aligned frame at the task frame's
origin (Pinocchio LOCAL_WORLD_ALIGNED): rows x, y, z in meters, rx, ry, rz in radians.
The solver asks for J dq = step(e): the error scaled by the gain, capped in norm per row
group (a task's `step_caps`; `capped_steps` applies them to a whole stack at once).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pinocchio as pin
from scipy.spatial import ConvexHull, QhullError

from .stack import AXES, TaskSpec, short_repr


# What Levenberg-Marquardt damping counts of a task's rows (Task.lm_counts; PIKSolver
# module docstring, step 2): nothing (a posture: it does not curve), the capped step
# target, or gain x error uncapped (the CoM: capped at ComTask.max_step, a target out of
# reach left a 2-row level lambda 0.2, and the whole body swung at its velocity bounds
# around its farthest reach, as with a support polygon out of reach)
LM_NONE, LM_STEP, LM_ERROR = 0, 1, 2


class TargetError(ValueError):
    """A task target is malformed (non-finite, wrong size, unknown joint, bad quaternion)."""


# m: the largest |x|, |y| or |z| of a position target (frame, CoM, support polygon). Far
# beyond any workspace, small enough that squares and products of positions stay finite (a
# target at x = 1e300 passed the NaN checks, its step overflowed to 0 and the level said
# 'met' with an infinite error).
MAX_COORDINATE = 1e6


def require_finite(values, what: str) -> np.ndarray:
    array = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(array)):
        raise TargetError(f"{what} contains NaN or infinite values")
    return array


def require_within_reach(position, what: str) -> np.ndarray:
    """position (m) if finite with no coordinate beyond MAX_COORDINATE, else TargetError."""
    position = require_finite(position, what)
    if np.any(np.abs(position) > MAX_COORDINATE):
        raise TargetError(f"{what} has a coordinate beyond {MAX_COORDINATE:g} m")
    return position


def pose_from_position_quaternion(position, quaternion_xyzw, tolerance: float = 1e-3) -> pin.SE3:
    """SE3 from a position (m) and a unit quaternion (x, y, z, w); rejects |q| - 1 > tolerance."""
    position = require_finite(position, "position")
    quaternion = require_finite(quaternion_xyzw, "orientation")
    norm = float(np.linalg.norm(quaternion))
    if abs(norm - 1.0) > tolerance:
        raise TargetError(f"orientation quaternion is not unit (norm {norm:.6g})")
    x, y, z, w = quaternion / norm
    return pin.SE3(pin.Quaternion(w, x, y, z).toRotationMatrix(), position)


@numba.njit(cache=True)
def capped_steps(error, gain, group, cap, scale, out):
    """out = scale * step, step = gain * error with each row group's part capped in norm
    at cap[group] (per row: gain, group, scale; task units). Returns nothing: numba boxes
    any returned array at a cost (~0.5 us)."""
    squares = np.zeros(len(cap))
    for row in range(len(error)):
        out[row] = gain[row] * error[row]
        squares[group[row]] += out[row] * out[row]
    for row in range(len(error)):
        norm = math.sqrt(squares[group[row]])
        if norm > cap[group[row]]:
            out[row] *= cap[group[row]] / norm
        out[row] *= scale[row]


def step_cap_groups(tasks) -> tuple:
    """(cap group per row, norm cap per group) of the tasks' rows stacked in order."""
    groups, caps = [], []
    for task in tasks:
        task_groups = np.zeros(task.dimension, dtype=np.int64)
        for positions, cap in task.step_caps():
            task_groups[positions] = len(caps)
            caps.append(cap)
        groups.extend(task_groups)
    return np.array(groups, dtype=np.int64), np.array(caps, dtype=float)


NEAR_ZERO_ANGLE = 1e-4   # rad: below it, theta / (2 sin theta) by its Taylor series
NEAR_PI_MARGIN = 1e-2    # rad: within it of pi, the axis from the symmetric part of R


@numba.njit(cache=True)
def _length(vector):
    """Euclidean norm of a 3-vector (numba's dot would call BLAS)."""
    return math.sqrt(vector[0] * vector[0] + vector[1] * vector[1] + vector[2] * vector[2])


@numba.njit(cache=True)
def frame_error(target, current, out):
    """out = [p_target - p; log3(R_target R^T)] (m, rad) of two 4x4 homogeneous poses
    [R p; 0 1], the rotation vector as pinocchio.log3 gives it (norm in [0, pi]); compiled,
    as a frame task's error is needed at every IK step (tests compare it with Pinocchio).
    Returns nothing, as capped_steps."""
    for i in range(3):
        out[i] = target[i, 3] - current[i, 3]
    r = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            r[i, j] = (target[i, 0] * current[j, 0] + target[i, 1] * current[j, 1]
                       + target[i, 2] * current[j, 2])
    vee = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    cosine = min(max(0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0), -1.0), 1.0)
    angle = math.atan2(0.5 * _length(vee), cosine)  # |vee| = 2 sin(angle)
    if angle < NEAR_ZERO_ANGLE:
        out[3:] = (0.5 + angle * angle / 12.0) * vee
    elif angle < math.pi - NEAR_PI_MARGIN:
        out[3:] = angle / (2.0 * math.sin(angle)) * vee
    else:  # R = cos I + sin [a]x + (1 - cos) a a^T: axis from the diagonal and symmetric part
        k = 0
        for i in range(1, 3):
            if r[i, i] > r[k, k]:
                k = i
        axis = np.zeros(3)
        axis[k] = math.sqrt(max(0.0, (r[k, k] - cosine) / (1.0 - cosine)))
        if vee[k] < 0.0:
            axis[k] = -axis[k]
        for i in range(3):
            if i != k:
                axis[i] = (r[i, k] + r[k, i]) / (2.0 * (1.0 - cosine) * axis[k])
        out[3:] = angle / _length(axis) * axis


@numba.njit(cache=True)
def frame_rows(world_jacobian, support, current, target, rows, jacobian, error):
    """Rows `rows` (indices into x, y, z, rx, ry, rz) of a frame task, written into
    jacobian (len(rows) x nv) and error (len(rows)): the frame's Jacobian in
    LOCAL_WORLD_ALIGNED, from the joint Jacobians `world_jacobian` (6 x nv, Pinocchio's
    data.J in the WORLD frame) on the `support` DoFs (those moving the frame; the other
    columns are zero), and frame_error(target, current) (4x4 poses). Same arithmetic as
    pinocchio.getFrameJacobian: linear = v - p x omega at the frame origin p."""
    full_error = np.empty(6)
    frame_error(target, current, full_error)
    for k in range(len(rows)):
        error[k] = full_error[rows[k]]
    jacobian[:] = 0.0
    px, py, pz = current[0, 3], current[1, 3], current[2, 3]
    for column in support:
        wx, wy, wz = world_jacobian[3, column], world_jacobian[4, column], \
            world_jacobian[5, column]
        for k in range(len(rows)):
            axis = rows[k]
            if axis == 0:
                jacobian[k, column] = world_jacobian[0, column] - (py * wz - pz * wy)
            elif axis == 1:
                jacobian[k, column] = world_jacobian[1, column] - (pz * wx - px * wz)
            elif axis == 2:
                jacobian[k, column] = world_jacobian[2, column] - (px * wy - py * wx)
            else:
                jacobian[k, column] = world_jacobian[axis, column]


@numba.njit(cache=True)
def _frame_batch_rows(world_jacobian, poses, supports, support_starts, axes, axis_starts,
                      first_rows, jacobian, error):
    """frame_rows for n frame tasks in one call: task i with poses[i] = [current, target]
    (2 x 4 x 4), support DoFs supports[support_starts[i]:support_starts[i + 1]] and axes
    axes[axis_starts[i]:axis_starts[i + 1]] writes the rows of jacobian and error that
    start at first_rows[i]."""
    for i in range(len(first_rows)):
        rows = slice(first_rows[i], first_rows[i] + axis_starts[i + 1] - axis_starts[i])
        frame_rows(world_jacobian, supports[support_starts[i]:support_starts[i + 1]],
                   poses[i, 0], poses[i, 1], axes[axis_starts[i]:axis_starts[i + 1]],
                   jacobian[rows], error[rows])


@numba.njit(cache=True)
def selected_rows(full_jacobian, target, current, rows, jacobian, error):
    """jacobian[k] = full_jacobian[rows[k]], error[k] = target[rows[k]] - current[rows[k]]
    (one compiled call instead of several numpy ones)."""
    for k in range(len(rows)):
        jacobian[k] = full_jacobian[rows[k]]
        error[k] = target[rows[k]] - current[rows[k]]


class Task:
    """Base class. Subclasses set `self.rows` (selected row indices) and implement
    `write(robot, q, jacobian, error)` on kinematics already computed in robot.data."""

    max_step = 0.05  # norm cap of one step's task correction, task units
    lm_counts = LM_STEP  # what LM damping counts of its rows (LM_NONE, LM_STEP, LM_ERROR)

    def __init__(self, spec: TaskSpec, robot):
        self.spec = spec
        self.name = spec.name
        self.priority = spec.priority
        self.weight = spec.weight
        self.gain = spec.gain
        self.enabled = spec.enabled

    @property
    def dimension(self) -> int:
        return len(self.rows)

    def step_caps(self) -> list:
        """(row positions, cap) per group of rows whose step norm is capped together."""
        return [(np.arange(self.dimension), self.max_step)]

    def hold(self, robot, q) -> None:
        """Set the target to the current value (kinematics of q already in robot.data)."""
        raise NotImplementedError

    def keep_target(self, old) -> None:
        """Take over the target of `old`, a task of the same kind and frame that this one
        replaces in a new stack."""
        self.target = old.target

    def write(self, robot, q, jacobian: np.ndarray, error: np.ndarray) -> None:
        """Write J (rows x nv) and e (rows) into the given arrays."""
        raise NotImplementedError

    def jacobian_and_error(self, robot, q):
        jacobian = np.empty((self.dimension, robot.model.nv))
        error = np.empty(self.dimension)
        self.write(robot, q, jacobian, error)
        return jacobian, error

    def current_pose(self, robot):
        """Achieved value as SE3 for status (CoM: translation only); None if not a pose."""
        return None

    def target_pose(self):
        return None


class FrameTask(Task):
    """Position and/or orientation of a robot frame; target pin.SE3 in the world frame."""

    max_linear_step = 0.02   # m per IK step
    max_angular_step = 0.05  # rad per IK step

    def __init__(self, spec: TaskSpec, robot):
        super().__init__(spec, robot)
        self.frame_id = robot.frame_id(spec.frame)
        self.rows = np.array([AXES.index(axis) for axis in spec.selected_axes()],
                             dtype=np.int64)
        self._needs_rotation = bool(np.any(self.rows >= 3))
        self._linear = np.flatnonzero(self.rows < 3)
        self._angular = np.flatnonzero(self.rows >= 3)
        self.target = pin.SE3.Identity()

    @property
    def target(self) -> pin.SE3:
        """A copy: the tracked target changes only through the setter (which caches it)."""
        return self._target.copy()

    @target.setter
    def target(self, pose: pin.SE3) -> None:
        self._target = pose.copy()
        self._target_homogeneous = pose.homogeneous

    def hold(self, robot, q) -> None:
        self.target = robot.data.oMf[self.frame_id]

    def set_target(self, pose: pin.SE3) -> None:
        require_finite(pose.homogeneous, f"target of task {self.name!r}")
        require_within_reach(pose.translation, f"target of task {self.name!r}")
        self.target = pose

    def full_error(self, robot, out=None) -> np.ndarray:
        """6-D error [p_target - p; log3(R_target R^T)], world-aligned (m, rad); rotation
        rows 0 when no axis is selected. Written into `out` (6) if given."""
        error = np.empty(6) if out is None else out
        frame_error(self._target_homogeneous, robot.data.oMf[self.frame_id].homogeneous, error)
        if not self._needs_rotation:
            error[3:] = 0.0
        return error

    def write(self, robot, q, jacobian, error) -> None:
        """Selected rows of [p_target - p; log3(R_target R^T)] (m, rad) and of the frame
        Jacobian, world-aligned at the frame origin (jacobian and error C-contiguous)."""
        data = robot.data
        frame_rows(data.J, robot.frame_supports[self.frame_id],
                   data.oMf[self.frame_id].homogeneous,
                   self._target_homogeneous, self.rows, jacobian, error)

    def step_caps(self) -> list:
        """Translation and rotation rows capped separately (m and rad per step)."""
        return [(group, cap) for group, cap in ((self._linear, self.max_linear_step),
                                                (self._angular, self.max_angular_step))
                if len(group)]

    def current_pose(self, robot):
        return robot.data.oMf[self.frame_id].copy()

    def target_pose(self):
        return self._target.copy()


class PoseTask(FrameTask):
    """Frame position and orientation (axes x, y, z, rx, ry, rz)."""


class PositionTask(FrameTask):
    """Frame origin position (axes x, y, z); the target's rotation is ignored."""


class OrientationTask(FrameTask):
    """Frame orientation (axes rx, ry, rz); the target's translation is ignored."""


class FrameTaskBatch:
    """Frame tasks whose rows lie in one stacked Jacobian and error, written together by
    one compiled call (FrameTask.write's arithmetic) instead of one call per task.

    tasks: the frame tasks; first_rows: the stacked row of each task's first selected axis.
    """

    def __init__(self, robot, tasks, first_rows):
        self.tasks = list(tasks)
        self._frame_ids = [task.frame_id for task in self.tasks]
        supports = [robot.frame_supports[frame_id] for frame_id in self._frame_ids]
        self._supports = np.concatenate([np.zeros(0, dtype=np.int64), *supports])
        self._support_starts = np.cumsum([0, *map(len, supports)]).astype(np.int64)
        self._axes = np.concatenate([np.zeros(0, dtype=np.int64),
                                     *(task.rows for task in self.tasks)])
        self._axis_starts = np.cumsum([0, *(task.dimension for task in self.tasks)]
                                      ).astype(np.int64)
        self._first_rows = np.array(first_rows, dtype=np.int64)
        self._poses = np.zeros((len(self.tasks), 2, 4, 4))

    def write(self, robot, jacobian, error) -> None:
        """Write the tasks' rows (kinematics already in robot.data) into the stacked
        jacobian and error."""
        data = robot.data
        placements, poses = data.oMf, self._poses
        for index, (task, frame_id) in enumerate(zip(self.tasks, self._frame_ids)):
            poses[index, 0] = placements[frame_id].homogeneous
            poses[index, 1] = task._target_homogeneous
        _frame_batch_rows(data.J, poses, self._supports, self._support_starts, self._axes,
                          self._axis_starts, self._first_rows, jacobian, error)


class ComTask(Task):
    """Center of mass position in the world frame (m); target a 3-vector."""

    max_step = 0.02  # m per IK step
    lm_counts = LM_ERROR

    def __init__(self, spec: TaskSpec, robot):
        super().__init__(spec, robot)
        self.rows = np.array([AXES.index(axis) for axis in spec.selected_axes()],
                             dtype=np.int64)
        self.target = np.zeros(3)

    def hold(self, robot, q) -> None:
        self.target = robot.data.com[0].copy()

    def set_target(self, position) -> None:
        position = require_within_reach(position, f"target of task {self.name!r}")
        if position.shape != (3,):
            raise TargetError(f"CoM target must have 3 values, got {position.shape}")
        self.target = position.copy()

    def write(self, robot, q, jacobian, error) -> None:
        data = robot.data
        selected_rows(data.Jcom, self.target, data.com[0], self.rows, jacobian, error)

    def current_pose(self, robot):
        return pin.SE3(np.eye(3), robot.data.com[0].copy())

    def target_pose(self):
        return pin.SE3(np.eye(3), self.target.copy())


def frame_rectangle_corners(robot, frames, half_size) -> np.ndarray:
    """Corners in the world's xy plane (m) of the rectangle +-half_size (x, y in m) about
    each frame's origin in that frame's xy plane, at robot.data's frame placements (call
    pin.updateFramePlacements first): the soles of standing feet, say, whose hull is their
    support polygon. Shape (4 x frames, 2)."""
    half_x, half_y = half_size
    local = np.array([[x, y, 0.0] for x in (-half_x, half_x) for y in (-half_y, half_y)])
    corners = []
    for frame in frames:
        placement = robot.data.oMf[robot.model.getFrameId(frame)]
        corners.append((local @ placement.rotation.T + placement.translation)[:, :2])
    return np.vstack(corners)


class SupportTask(Task):
    """Center of mass inside a support polygon: an inequality, no equality row.

    The polygon is the convex hull of vertices in the world's xy plane (m), with any safety
    margin already taken off; until one is set the task constrains nothing. Each edge e
    (outward unit normal n_e, n_e . p <= b_e inside) gives one row of the level's
    inequalities n_e^T J_com,xy dq <= room_e, room_e = b_e - n_e . c_xy where that is >= 0;
    a CoM outside the edge must come back by gain x its distance (room_e < 0), the way a
    task corrects gain x its error per step, at most max_step per step as a CoM task's
    step; LM damping counts the uncapped return, as a CoM task's error: a polygon out of
    reach holds the CoM as a CoM target out of reach does. The QP hierarchy keeps these
    rows from the task's level down (qp_hierarchy.Inequalities); its error is the largest
    distance outside an edge line (m, 0 inside).
    """

    max_step = ComTask.max_step  # m per IK step: the largest return asked of the CoM

    def __init__(self, spec: TaskSpec, robot):
        super().__init__(spec, robot)
        self.rows = np.zeros(0, dtype=np.int64)
        self.vertices = np.zeros((0, 2))      # hull vertices, counterclockwise
        self._normals = np.zeros((0, 2))      # outward unit normal per edge
        self._offsets = np.zeros(0)           # n_e . p <= offset_e inside

    @property
    def edge_count(self) -> int:
        return len(self._offsets)

    def hold(self, robot, q) -> None:
        """A support task has no value to hold: its polygon stays as it is (none at first)."""

    def keep_target(self, old) -> None:
        """Take over the polygon of `old` (a support task this one replaces)."""
        self.vertices, self._normals, self._offsets = old.vertices, old._normals, old._offsets

    def set_target(self, vertices) -> None:
        """Set the polygon from >= 3 xy vertices (m, world frame) spanning a nonzero area."""
        points = require_within_reach(vertices, f"polygon of task {self.name!r}")
        if points.ndim != 2 or points.shape[1] != 2 or len(points) < 3:
            raise TargetError(f"polygon of task {self.name!r} needs >= 3 xy vertices, "
                              f"got shape {points.shape}")
        try:
            hull = ConvexHull(points)
        except QhullError as error:
            raise TargetError(f"polygon of task {self.name!r} has no area (collinear or "
                              "repeated vertices)") from error
        self.vertices = points[hull.vertices].copy()
        self._normals = hull.equations[:, :2].copy()
        self._offsets = -hull.equations[:, 2].copy()

    def write(self, robot, q, jacobian, error) -> None:
        """No equality rows."""

    def write_inequalities(self, robot, rows: np.ndarray, room: np.ndarray,
                           returns: np.ndarray) -> None:
        """Fill edge_count rows (nv each), their room (m) and the return LM damping counts
        per edge (m: gain x distance outside, uncapped; 0 inside) at robot.data's CoM."""
        rows[:] = self._normals @ robot.data.Jcom[:2]
        inside = self._inside(robot)
        returns[:] = self.gain * np.maximum(-inside, 0.0)
        room[:] = np.where(inside >= 0.0, inside, -np.minimum(returns, self.max_step))

    def distance_outside(self, robot) -> float:
        """Largest distance of the CoM's ground projection outside an edge line (m)."""
        if not self.edge_count:
            return 0.0
        return float(max(0.0, -np.min(self._inside(robot))))

    def _inside(self, robot) -> np.ndarray:
        """Per edge, how far robot.data's CoM lies inside its line (m, < 0 outside)."""
        return self._offsets - self._normals @ robot.data.com[0][:2]

    def current_pose(self, robot):
        return pin.SE3(np.eye(3), robot.data.com[0].copy())


class PostureTask(Task):
    """Actuated joint positions (rad); the target is a full configuration vector."""

    max_step = 0.05  # rad per IK step (norm over all joints)
    lm_counts = LM_NONE

    def __init__(self, spec: TaskSpec, robot):
        super().__init__(spec, robot)
        self.rows = np.arange(robot.base_nv, robot.model.nv)
        self.target = pin.neutral(robot.model)
        self._jacobian = np.zeros((len(self.rows), robot.model.nv))
        self._jacobian[:, robot.base_nv:] = np.eye(len(self.rows))

    def hold(self, robot, q) -> None:
        self.target = np.array(q, dtype=float)

    def set_joint_targets(self, robot, positions: dict) -> None:
        """Set targets of the named 1-DoF joints (rad); other joints keep theirs."""
        target = self.target.copy()
        for joint, value in positions.items():
            if not robot.model.existJointName(joint):
                raise TargetError(f"posture target names unknown joint {short_repr(joint)}")
            joint_id = robot.model.getJointId(joint)
            if joint_id == 0:       # Pinocchio's world joint: its idx_q is -1
                raise TargetError(f"posture target names {joint!r}, the world, not a joint "
                                  "of the robot")
            joint_model = robot.model.joints[joint_id]
            if joint_model.nq != 1:
                raise TargetError(f"joint {joint!r} is not a one-coordinate joint")
            target[joint_model.idx_q] = float(require_finite(value, f"position of {joint!r}"))
        self.target = target

    def write(self, robot, q, jacobian, error) -> None:
        jacobian[:] = self._jacobian
        error[:] = pin.difference(robot.model, q, self.target)[robot.base_nv:]


TASK_CLASSES = {
    "pose": PoseTask,
    "position": PositionTask,
    "orientation": OrientationTask,
    "com": ComTask,
    "posture": PostureTask,
    "support": SupportTask,
}


def make_task(spec: TaskSpec, robot) -> Task:
    return TASK_CLASSES[spec.kind](spec, robot)
