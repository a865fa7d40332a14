"""Swing and ball-and-socket joint limits (Raunhardt and Boulic, IV.B.2 and IV.B.3).

A joint rotation R (joint frame relative to its placement in the parent) is split about the
joint's rest (bone) axis, the local z axis, as R = R_swing(s) R_twist(theta):
- s (rad, 2-D swing plane): exponential-map vector [s_x, s_y, 0] of the rotation taking z
  to the bone direction R z by the shortest arc; |s| is the swing angle (valid below pi);
- theta (rad): the axial rotation about local z left over, in (-pi, pi].

Limit domains live in the swing plane: an `EllipticCone` is an ellipse centred on s = 0 and
distances are Euclidean in the plane (uniform thickness q_hat in the exponential map,
Fig. 4); a `SphericalPolygon` is defined on the unit sphere of bone directions with
great-circle edges and distances are geodesic angles on that sphere (Fig. 7), mapped to and
from the plane by the exponential map. Both give a signed distance (inside positive), the
closest boundary point and the outward normal of the limit in the swing plane, which is all
the shared damping path `damp_swing` needs.

Damping (eq. 6-10): with d = (q_hat - dist) / q_hat, a variation of the swing inside the
activation zone that heads toward the limit (d_{k+1} > d_k > 0; eq. 8 as printed has the
inequality reversed, we follow the meaning of eq. 3) has only its component orthogonal to
the limit at the current closest point damped by h(d_k); the parallel component is kept.
Second stage: a state outside the domain is clamped onto the closest boundary point, so the
joint slides along the limit (Fig. 6). The twist follows the revolute rule (eq. 1-5).

The limit models fix all three velocity DoFs of a Pinocchio spherical joint (local angular
velocity, rad) to log3(R_k^T R'_{k+1}) whenever the swing or the twist is altered. The same
rule applies to a chain of 2-3 revolute joints treated as one joint (JointGroupLimit, e.g.
Talos' hips): its rotation is the product of the joints', and an altered rotation is turned
back into joint angles.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

import numba
import numpy as np
import pinocchio as pin
import yaml

from .hierarchy import _damped_least_squares
from .limits import (NEGLIGIBLE_VARIATION, LimitDecision, RevoluteLimits, apply_decision,
                     cubic_step)

OUTSIDE_TOLERANCE = 1e-9   # rad: a state this close outside a limit counts as on it
Z_AXIS = np.array([0.0, 0.0, 1.0])


class LimitFileError(ValueError):
    """A limit file is malformed; the message names the offending joint and field."""


# Swing / twist decomposition.

def swing_direction(s) -> np.ndarray:
    """Unit bone direction R_swing(s) z (joint frame) of swing vector s (rad)."""
    angle = math.hypot(s[0], s[1])
    scale = math.sin(angle) / angle if angle > 1e-12 else 1.0
    return np.array([scale * s[1], -scale * s[0], math.cos(angle)])


def swing_from_direction(direction) -> np.ndarray:
    """Swing vector s (rad) of the shortest-arc rotation taking z to `direction` (unit)."""
    sine = math.hypot(direction[0], direction[1])
    angle = math.atan2(sine, direction[2])
    if sine < 1e-12:
        return np.array([angle, 0.0])  # rest (0) or the singular antipode (pi)
    return angle / sine * np.array([-direction[1], direction[0]])


def swing_direction_jacobian(s) -> np.ndarray:
    """d(swing_direction)/ds (3x2)."""
    angle = math.hypot(s[0], s[1])
    if angle < 1e-6:  # sinc(a) ~ 1 - a^2/6: (sinc)'/a ~ -1/3, sin(a)/a ~ 1
        sinc, sinc_slope, sin_over = 1.0 - angle * angle / 6.0, -1.0 / 3.0, 1.0
    else:
        sinc = math.sin(angle) / angle
        sinc_slope = (angle * math.cos(angle) - math.sin(angle)) / angle ** 3
        sin_over = sinc
    sx, sy = s
    return np.array([[sinc_slope * sx * sy, sinc + sinc_slope * sy * sy],
                     [-sinc - sinc_slope * sx * sx, -sinc_slope * sx * sy],
                     [-sin_over * sx, -sin_over * sy]])


def swing_rotation(s) -> np.ndarray:
    return pin.exp3(np.array([s[0], s[1], 0.0]))


def twist_rotation(theta: float) -> np.ndarray:
    cosine, sine = math.cos(theta), math.sin(theta)
    return np.array([[cosine, -sine, 0.0], [sine, cosine, 0.0], [0.0, 0.0, 1.0]])


def swing_twist(rotation) -> tuple[np.ndarray, float]:
    """(s (rad, swing plane), theta (rad)) with rotation = R_swing(s) R_twist(theta about z)."""
    s = swing_from_direction(rotation[:, 2])
    twist = swing_rotation(s).T @ rotation
    return s, math.atan2(twist[1, 0], twist[0, 0])


def rotation_from_swing_twist(s, theta: float) -> np.ndarray:
    return swing_rotation(s) @ twist_rotation(theta)


# Limit domains in the swing plane.

class SwingDomain:
    """Valid set of swing vectors s (rad). Subclasses give the signed distance to the limit
    (inside positive, rad), its closest boundary point and outward normal."""

    def signed_distance(self, s) -> float:
        raise NotImplementedError

    def closest_boundary_point(self, s) -> np.ndarray:
        raise NotImplementedError

    def normal_at(self, s) -> np.ndarray:
        """Outward unit normal (swing plane) of the limit at the boundary point closest to s:
        the direction of steepest approach to the limit from s."""
        raise NotImplementedError

    def contains(self, s, tolerance: float = 0.0) -> bool:
        return self.signed_distance(s) >= -tolerance


NEGLIGIBLE_COMPONENT = 1e-12


@numba.njit(cache=True)
def _ellipse_closest_point(a, b, x, y):
    """Closest point of the ellipse (x/a)^2 + (y/b)^2 = 1 to (x, y) (Eberly's bisection)."""
    swap = a < b
    if swap:
        a, b, x, y = b, a, y, x
    y0, y1 = abs(x), abs(y)
    # components below NEGLIGIBLE_COMPONENT * axis count as on the axis: a smaller y1 makes
    # -b^2 + b y1 round to -b^2, and the bisection would divide by t + b^2 = 0
    if y1 > NEGLIGIBLE_COMPONENT * b:
        if y0 > NEGLIGIBLE_COMPONENT * a:
            low = -b * b + b * y1
            high = -b * b + math.sqrt(a * a * y0 * y0 + b * b * y1 * y1)
            for _ in range(200):
                t = 0.5 * (low + high)
                if t == low or t == high:
                    break
                r0, r1 = a * y0 / (t + a * a), b * y1 / (t + b * b)
                if r0 * r0 + r1 * r1 > 1.0:
                    low = t
                else:
                    high = t
            t = 0.5 * (low + high)
            x0, x1 = a * a * y0 / (t + a * a), b * b * y1 / (t + b * b)
        else:
            x0, x1 = 0.0, b
    else:
        limit = (a * a - b * b) / a
        if y0 < limit:
            x0 = a * a * y0 / (a * a - b * b)
            x1 = b * math.sqrt(max(0.0, 1.0 - (x0 / a) ** 2))
        else:
            x0, x1 = a, 0.0
    x0, x1 = math.copysign(x0, x), math.copysign(x1, y)
    if swap:
        x0, x1 = x1, x0
    return x0, x1


class EllipticCone(SwingDomain):
    """Ellipse (s_x / a)^2 + (s_y / b)^2 <= 1 in the swing plane: semi-axes a along s_x
    (rotation about local x) and b along s_y, rad, both in (0, pi)."""

    def __init__(self, a: float, b: float):
        if not (0.0 < a < math.pi and 0.0 < b < math.pi):
            raise ValueError(f"cone semi-axes must lie in (0, pi) rad, got a={a}, b={b}")
        self.a, self.b = float(a), float(b)

    def closest_boundary_point(self, s) -> np.ndarray:
        return np.array(_ellipse_closest_point(self.a, self.b, float(s[0]), float(s[1])))

    def signed_distance(self, s) -> float:
        distance = float(np.linalg.norm(self.closest_boundary_point(s) - s))
        inside = (s[0] / self.a) ** 2 + (s[1] / self.b) ** 2 <= 1.0
        return distance if inside else -distance

    def normal_at(self, s) -> np.ndarray:
        point = self.closest_boundary_point(s)
        normal = np.array([point[0] / self.a ** 2, point[1] / self.b ** 2])
        return normal / np.linalg.norm(normal)


@numba.njit(cache=True)
def _cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


@numba.njit(cache=True)
def _polygon_closest(direction, vertices, ends, arc_axes):
    """SphericalPolygon._closest: per edge, the direction projected on its great circle if
    it falls inside the arc, else the nearer end; the candidate with the largest cosine."""
    best = vertices[0].copy()
    best_cosine, best_edge, at_vertex = -2.0, 0, False
    for edge in range(len(vertices)):
        start, end, axis = vertices[edge], ends[edge], arc_axes[edge]
        projected = direction - (direction @ axis) * axis
        length = np.sqrt(projected @ projected)
        candidate = start
        vertex = True
        if length > 1e-12:
            projected = projected / length
            if _cross(start, projected) @ axis >= 0.0 and _cross(projected, end) @ axis >= 0.0:
                candidate, vertex = projected, False
        if vertex and direction @ end > direction @ start:
            candidate = end
        cosine = direction @ candidate
        if cosine > best_cosine:
            best, best_cosine, best_edge, at_vertex = candidate.copy(), cosine, edge, vertex
    return best, best_edge, at_vertex


class SphericalPolygon(SwingDomain):
    """Convex spherical polygon of bone directions (joint frame) containing the rest
    direction z strictly inside; edges are great-circle arcs between consecutive vertices.
    Distances are geodesic angles on the unit sphere (rad)."""

    def __init__(self, vertices):
        vertices = np.asarray(vertices, dtype=float)
        if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
            raise ValueError("a spherical polygon needs at least 3 vertices [x, y, z]")
        norms = np.linalg.norm(vertices, axis=1)
        if np.any(norms < 1e-9):
            raise ValueError("spherical polygon vertices must be non-zero directions")
        self.vertices = vertices / norms[:, None]
        following = np.roll(self.vertices, -1, axis=0)
        normals = np.cross(self.vertices, following)
        lengths = np.linalg.norm(normals, axis=1)
        if np.any(lengths < 1e-9):
            raise ValueError("consecutive spherical polygon vertices must be distinct and "
                             "not antipodal")
        normals /= lengths[:, None]
        self._arc_axes = normals.copy()  # start x end: orients each edge's arc
        if np.sum(normals @ self.vertices.mean(axis=0)) < 0.0:
            normals = -normals  # clockwise vertices: make the normals point inward
        if np.any(self.vertices @ normals.T < -1e-9):
            raise ValueError("spherical polygon must be convex with vertices in order")
        if np.any(normals @ Z_AXIS <= 1e-9):
            raise ValueError("the rest direction z must lie strictly inside the polygon")
        self.inward_normals = normals
        self._edge_ends = following

    def _closest(self, direction):
        """(closest boundary direction, index of its edge, at a vertex) for a unit direction."""
        best, edge, at_vertex = _polygon_closest(np.asarray(direction, dtype=float),
                                                 self.vertices, self._edge_ends,
                                                 self._arc_axes)
        return best, int(edge), bool(at_vertex)

    def contains(self, s, tolerance: float = 0.0) -> bool:
        return bool(np.all(self.inward_normals @ swing_direction(s) >= -math.sin(tolerance)))

    def closest_boundary_point(self, s) -> np.ndarray:
        return swing_from_direction(self._closest(swing_direction(s))[0])

    def signed_distance(self, s) -> float:
        direction = swing_direction(s)
        closest = self._closest(direction)[0]
        angle = math.atan2(np.linalg.norm(_cross(direction, closest)), direction @ closest)
        inside = np.all(self.inward_normals @ direction >= 0.0)
        return angle if inside else -angle

    def normal_at(self, s) -> np.ndarray:
        direction = swing_direction(s)
        closest, edge, at_vertex = self._closest(direction)
        toward = closest - (closest @ direction) * direction  # tangent at s toward the limit
        if np.linalg.norm(toward) > 1e-9:
            outward = toward if np.all(self.inward_normals @ direction >= 0.0) else -toward
        elif at_vertex:  # on a vertex: between its two edges
            outward = -(self.inward_normals[edge] + self.inward_normals[edge - 1])
        else:
            outward = -self.inward_normals[edge]
        normal = swing_direction_jacobian(s).T @ outward  # gradient of the distance in s
        return normal / np.linalg.norm(normal)


class SwingPoint:
    """A swing vector s (rad) with its signed distance to `domain`'s limit (rad) and, once
    asked for, the limit's outward normal there: what the damping of a move from s needs,
    computed once however many moves from s the clamping loop tries."""

    def __init__(self, domain: SwingDomain, s):
        self.domain, self.s = domain, s
        self.distance = domain.signed_distance(s)
        self._normal = None

    @property
    def normal(self) -> np.ndarray:
        if self._normal is None:
            self._normal = self.domain.normal_at(self.s)
        return self._normal


class JointRotation(NamedTuple):
    """A joint rotation at one configuration: R (3x3), its swing point and twist (rad)."""
    rotation: np.ndarray
    swing: SwingPoint
    twist: float


def damp_swing(thickness: float, current: SwingPoint, s_next, progressive: bool):
    """Altered next swing (rad) and h for a move current.s -> s_next (eq. 6-10 and the
    second-stage clamp), or (None, 0) when the move is left alone. thickness: q_hat (rad)."""
    domain, s = current.domain, current.s
    distance_next = domain.signed_distance(s_next)
    if distance_next < -OUTSIDE_TOLERANCE:  # eq. 7, then the second stage
        return domain.closest_boundary_point(s_next), 1.0
    if not progressive:
        return None, 0.0
    depth = (thickness - current.distance) / thickness                   # d_k, eq. 6
    depth_next = (thickness - distance_next) / thickness                 # d_{k+1}
    if not depth_next > depth > 0.0:
        return None, 0.0
    h = cubic_step(depth)                                                # eq. 8
    variation = np.asarray(s_next) - s
    normal = current.normal
    orthogonal = (variation @ normal) * normal
    damped = s + (1.0 - h) * orthogonal + (variation - orthogonal)       # eq. 10
    if domain.signed_distance(damped) < -OUTSIDE_TOLERANCE:              # second stage
        damped = domain.closest_boundary_point(damped)
    return damped, h


# Limit models: the swing / twist rule, on Pinocchio spherical joints and on groups of
# revolute joints.

class SwingTwistRule:
    """What a ball-and-socket limit does to a joint rotation (IV.B.3): swing domain plus
    twist interval [min, max] (rad, revolute rule eq. 1-5), or a free twist (None).

    activation: damping thickness q_hat (rad) of the swing zone and of the twist zones
    (the latter capped like revolute joints)."""

    def __init__(self, name: str, domain: SwingDomain, twist=None, activation: float = 0.2):
        self.domain = domain
        self.thickness = float(activation)
        self.twist = None if twist is None else RevoluteLimits(
            [f"{name}_twist"], [0], [0], [twist[0]], [twist[1]], activation)
        self._state_key, self._state = None, None   # current()'s cache

    def fix(self, q, dq, fixed, fixed_dq, h, progressive: bool) -> bool:
        """The subclass' decide() written in place into the clamping loop's arrays (fixed,
        fixed_dq, h: nv); True if it fixes any DoF."""
        return apply_decision(self.decide(q, dq, ~fixed, progressive), fixed, fixed_dq, h)

    def warm_up(self, q) -> None:
        """Compile the kernels a decision near the limits needs (PIKSolver.warm_up): the
        domain's distance, closest point and normal at the joint's swing at q."""
        s, _ = swing_twist(self.rotation(q))
        self.domain.signed_distance(s)
        self.domain.normal_at(s)
        self.domain.closest_boundary_point(s)

    def current(self, key: bytes, rotation_at) -> JointRotation:
        """The joint's rotation at the configuration whose bytes are `key` (rotation_at():
        that rotation), with its swing point and twist: computed once per configuration,
        since the clamping loop asks about several moves from the same one."""
        if self._state_key != key:
            rotation = rotation_at()
            s, theta = swing_twist(rotation)
            self._state_key = key
            self._state = JointRotation(rotation, SwingPoint(self.domain, s), theta)
        return self._state

    def may_reach(self, current: JointRotation, reach: float, zone: float) -> bool:
        """Whether the joint rotation `current`, turned by at most `reach` rad, may bring
        the swing within `zone` rad of its domain's boundary or the twist into its damping
        zone (zone > 0) or past a bound (zone = 0). False is certain: the bone direction
        turns by at most reach, the swing vector by at most reach g with g = a / sin a at
        the largest swing angle a reachable, the twist by at most reach (1 + g)."""
        s, theta, distance = current.swing.s, current.twist, current.swing.distance
        widest = float(np.hypot(s[0], s[1])) + reach
        if widest >= 0.9 * math.pi:
            return True
        stretch = widest / math.sin(widest) if widest > 1e-9 else 1.0
        if distance - reach * stretch <= zone:
            return True
        if self.twist is None:
            return False
        twist = self.twist
        low, high = (twist.lower_threshold[0], twist.upper_threshold[0]) if zone > 0.0 else \
            (twist.lower[0], twist.upper[0])
        return min(theta - low, high - theta) - reach * (1.0 + stretch) <= 0.0

    def altered(self, current: JointRotation, rotation_next, progressive: bool) -> tuple:
        """(altered next rotation or None when the move is left alone, swing h, twist h)
        for a move of the joint rotation from `current` to `rotation_next`."""
        s_next, theta_next = swing_twist(rotation_next)
        swing_target, swing_h = damp_swing(self.thickness, current.swing, s_next,
                                           progressive)
        twist_target, twist_h = self._twist_target(current.twist, theta_next, progressive)
        if swing_target is None and twist_target is None:
            return None, 0.0, 0.0
        target = rotation_from_swing_twist(
            s_next if swing_target is None else swing_target,
            theta_next if twist_target is None else twist_target)
        return target, swing_h, twist_h

    def _twist_target(self, theta, theta_next, progressive):
        """Altered next twist (rad) and h by the revolute rule, or (None, 0)."""
        if self.twist is None:
            return None, 0.0
        variation = (theta_next - theta + math.pi) % (2.0 * math.pi) - math.pi
        decision = self.twist.decide(np.array([theta]), np.array([variation]),
                                     np.ones(1, dtype=bool), progressive)
        if not len(decision.index):
            return None, 0.0
        return theta + decision.dq[0], float(decision.h[0])

    def projected(self, current: JointRotation, rotation_next):
        """rotation_next projected into the limits without moving further out than the
        joint rotation `current`, or None when it needs no projection."""
        s_next, theta_next = swing_twist(rotation_next)
        changed = False
        allowed = min(0.0, current.swing.distance)
        if self.domain.signed_distance(s_next) < allowed:
            s_next, changed = self.domain.closest_boundary_point(s_next), True
        if self.twist is not None:
            twist, following = np.array([current.twist]), np.array([theta_next])
            self.twist.keep_inside(twist, following)
            changed = changed or following[0] != theta_next
            theta_next = following[0]
        return rotation_from_swing_twist(s_next, theta_next) if changed else None


class BallLimit(SwingTwistRule):
    """Ball-and-socket limit (IV.B.3) of one Pinocchio spherical joint (q: quaternion x, y,
    z, w; dq: local angular velocity, rad); see SwingTwistRule. Fixes all three velocity
    DoFs to log3(R_k^T R'_{k+1}) whenever the swing or the twist is altered."""

    def __init__(self, joint: str, q_index: int, v_index: int, domain: SwingDomain,
                 twist=None, activation: float = 0.2):
        super().__init__(joint, domain, twist, activation)
        self.joint = joint
        self.q_slice = slice(q_index, q_index + 4)
        self.v_index = np.arange(v_index, v_index + 3)
        self.dof_names = [f"{joint}_swing_x", f"{joint}_swing_y", f"{joint}_twist"]

    @classmethod
    def for_joint(cls, robot, joint: str, *args, **kwargs):
        """The limit of the robot's spherical joint `joint`; other arguments as __init__."""
        joint_model = robot.model.joints[robot.joint_id(joint)]
        if joint_model.shortname() != "JointModelSpherical":
            raise ValueError(f"joint {joint!r} is not a spherical joint")
        return cls(joint, joint_model.idx_q, joint_model.idx_v, *args, **kwargs)

    def rotation(self, q) -> np.ndarray:
        """Joint rotation R (joint frame relative to its placement) at configuration q."""
        return pin.Quaternion(np.asarray(q[self.q_slice])).normalized().toRotationMatrix()

    def decide(self, q, dq, free, progressive: bool) -> LimitDecision:
        """q: configuration (nq), dq: candidate variation (nv), free: bool (nv)."""
        velocity = dq[self.v_index]
        if (not np.all(free[self.v_index])
                or np.linalg.norm(velocity) <= NEGLIGIBLE_VARIATION):
            return _nothing()
        current = self.current(q[self.q_slice].tobytes(), lambda: self.rotation(q))
        if not self.may_reach(current, float(np.linalg.norm(velocity)), self.thickness):
            return _nothing()
        target, swing_h, twist_h = self.altered(
            current, current.rotation @ pin.exp3(velocity), progressive)
        if target is None:
            return _nothing()
        fixed = pin.log3(current.rotation.T @ target)
        return LimitDecision(self.v_index.copy(), fixed,
                             np.array([swing_h, swing_h, twist_h]))

    def keep_inside(self, q, q_next) -> None:
        """Project q_next's joint rotation (in place) into the limits without moving it
        further out than q: removes the negligible overshoot the decisions ignored."""
        current = self.current(q[self.q_slice].tobytes(), lambda: self.rotation(q))
        following = self.rotation(q_next)
        turn = float(np.linalg.norm(pin.log3(current.rotation.T @ following)))
        if not self.may_reach(current, turn, 0.0):
            return
        rotation = self.projected(current, following)
        if rotation is not None:
            q_next[self.q_slice] = pin.Quaternion(rotation).coeffs()


class SwingLimit(BallLimit):
    """Swing joint (2 DoFs) on a Pinocchio spherical joint: the swing is limited by the
    domain, the twist is either locked at 0 rad (held by the twist rule) or free."""

    def __init__(self, joint: str, q_index: int, v_index: int, domain: SwingDomain,
                 twist_locked: bool = True, activation: float = 0.2):
        super().__init__(joint, q_index, v_index, domain,
                         (0.0, 0.0) if twist_locked else None, activation)


REVOLUTE_AXES = {"JointModelRX": 0, "JointModelRY": 1, "JointModelRZ": 2}
GROUP_SOLVE_ITERATIONS = 20
GROUP_STEP_HALVINGS = 30      # a Gauss-Newton step halved at most this often
GROUP_SOLVE_DAMPING = 1e-6    # lambda of its steps (hierarchy DLS): finite when axes align
GROUP_SOLVE_TOLERANCE = 1e-12  # rad: rotation error, or last step, of the angles found
KEEP_INSIDE_ROUNDS = 3         # alternate projections onto the cone and the joints' bounds


@numba.njit(cache=True)
def _group_rotation(placements, axis_index, angles):
    """(R, (3, n) axes in the group frame) of R = prod_k placement_k Rot(axis_k, angle_k)."""
    rotation = np.eye(3)
    axes = np.zeros((3, len(angles)))
    for k in range(len(angles)):
        rotation = _product3(rotation, placements[k])
        axis = axis_index[k]
        axes[:, k] = rotation[:, axis]
        cosine, sine = math.cos(angles[k]), math.sin(angles[k])
        first, second = (axis + 1) % 3, (axis + 2) % 3
        for row in range(3):   # rotation @ Rot(axis, angle): two columns turn
            a, b = rotation[row, first], rotation[row, second]
            rotation[row, first], rotation[row, second] = (cosine * a + sine * b,
                                                           cosine * b - sine * a)
    return rotation, axes


@numba.njit(cache=True)
def _product3(a, b):
    """a @ b for 3x3 matrices without a BLAS call (its overhead dwarfs 27 products)."""
    product = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            product[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]
    return product


@numba.njit(cache=True)
def _group_angles(placements, axis_index, target, start, movable):
    """JointGroupLimit.angles_for compiled (movable: indices of the joints it may move).
    Steps are the hierarchy's damped least squares (GROUP_SOLVE_DAMPING), finite where two
    axes align. A step that does not lower the rotation error is halved: with a joint held,
    the target may be out of reach, where full steps can overshoot (nearly aligned axes,
    like the shoulder's two yaws) and cycle."""
    angles = start.copy()
    rotation, axes = _group_rotation(placements, axis_index, angles)
    error = rotation_log(_product3(target, rotation.T))  # group frame
    size = np.sqrt(np.sum(error * error))
    for _ in range(GROUP_SOLVE_ITERATIONS):
        if size <= GROUP_SOLVE_TOLERANCE:
            break
        step = _damped_least_squares(np.ascontiguousarray(axes[:, movable]), error,
                                     GROUP_SOLVE_DAMPING ** 2)
        lowered = False
        for _ in range(GROUP_STEP_HALVINGS):
            trial = angles.copy()
            trial[movable] += step
            trial_rotation, trial_axes = _group_rotation(placements, axis_index, trial)
            trial_error = rotation_log(_product3(target, trial_rotation.T))
            trial_size = np.sqrt(np.sum(trial_error * trial_error))
            if trial_size < size:
                lowered = True
                break
            step *= 0.5
        if not lowered:
            break   # no step lowers the error: the closest rotation the joints reach
        angles, axes, error, size = trial, trial_axes, trial_error, trial_size
        if np.sqrt(np.sum(step * step)) <= GROUP_SOLVE_TOLERANCE:
            break
    return start + (np.remainder(angles - start + np.pi, 2.0 * np.pi) - np.pi)


@numba.njit(cache=True)
def rotation_log(rotation):
    """Rotation vector (rad) of a rotation matrix, as pinocchio.log3, in compiled code:
    theta / sin(theta) times the skew part's vector, or from the symmetric part
    (1 - cos theta) a a^T past a quarter turn, where the skew part fades."""
    cosine = min(max(0.5 * (rotation[0, 0] + rotation[1, 1] + rotation[2, 2] - 1.0), -1.0),
                 1.0)
    skew = 0.5 * np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                           rotation[1, 0] - rotation[0, 1]])          # sin(theta) a
    sine = np.sqrt(np.sum(skew * skew))
    angle = math.atan2(sine, cosine)
    if cosine >= 0.0:
        return skew * (angle / sine if sine > 1e-8 else 1.0 + angle * angle / 6.0)
    axis = np.empty(3)
    largest = 0
    for i in range(3):
        if rotation[i, i] > rotation[largest, largest]:
            largest = i
    axis[largest] = math.sqrt(max((rotation[largest, largest] - cosine) / (1.0 - cosine), 0.0))
    for i in range(3):
        if i != largest:
            axis[i] = (0.5 * (rotation[i, largest] + rotation[largest, i])
                       / ((1.0 - cosine) * axis[largest]))
    if np.sum(axis * skew) < 0.0:
        axis = -axis
    return angle * axis


class JointGroupLimit(SwingTwistRule):
    """A chain of 2-3 revolute joints limited as one swing or ball-and-socket joint (e.g.
    Talos' hip: yaw, roll, pitch). The group rotation R is the product of the joints'
    rotations and of the placement rotations between them: the last joint's frame relative
    to the first joint's placement, at zero angles the identity. Swing and twist are taken
    about that frame's z as for spherical joints (only orientations count: axes that do not
    meet, like Talos' shoulder, are treated as if they did).

    The group owns its joints' velocity DoFs in place of the robot's revolute model, so it
    also keeps their own bounds (revolute rule, eq. 1-5, after the swing / twist rule). When
    the swing or twist is altered, the altered rotation is turned back into the angles of
    the joints still free in the clamping loop by Gauss-Newton from q (exact for three
    independent axes; the closest rotation they reach otherwise) and those joints are
    fixed; otherwise only the joints their bounds alter are. h per joint: the larger of the
    group's and the joint's own."""

    def __init__(self, name: str, robot, joints, domain: SwingDomain, twist=None,
                 activation: float = 0.2):
        super().__init__(name, domain, twist, activation)
        model = robot.model
        ids = [robot.joint_id(joint) for joint in joints]
        if not 2 <= len(ids) <= 3 or len(set(ids)) != len(ids):
            raise ValueError("a joint group needs 2 or 3 distinct joints")
        for joint, parent, child in zip(joints[1:], ids, ids[1:]):
            if model.parents[child] != parent:
                raise ValueError(f"joint {joint!r} is not a child of the joint before it")
        axes = []
        for joint, joint_id in zip(joints, ids):
            kind = model.joints[joint_id].shortname()
            if kind not in REVOLUTE_AXES:
                raise ValueError(f"joint {joint!r} is not a revolute joint about x, y or z "
                                 f"({kind})")
            axes.append(REVOLUTE_AXES[kind])
        self.name = name
        self.axis_index = np.array(axes, dtype=np.int64)  # 0, 1, 2: x, y, z
        self.placements = np.array([np.eye(3)] + [model.jointPlacements[i].rotation
                                                  for i in ids[1:]])
        self.q_index = np.array([model.joints[i].idx_q for i in ids])
        self.v_index = np.array([model.joints[i].idx_v for i in ids])
        self.dof_names = list(joints)
        bounds = (model.lowerPositionLimit[self.q_index], model.upperPositionLimit[self.q_index])
        local = np.arange(len(ids))
        self.bounds = RevoluteLimits(joints, local, local, *bounds, activation)

    def warm_up(self, q) -> None:
        super().warm_up(q)
        self.angles_for(self.rotation(q), q[self.q_index])

    def rotation(self, q) -> np.ndarray:
        """Group rotation R at configuration q (nq)."""
        return self.rotation_and_axes(q[self.q_index])[0]

    def rotation_and_axes(self, angles) -> tuple:
        """(group rotation R, (3, n) joint axes in the group frame) at joint angles (rad)."""
        return _group_rotation(self.placements, self.axis_index,
                               np.asarray(angles, dtype=float))

    def angles_for(self, target, start, movable=None) -> np.ndarray:
        """Joint angles (rad) whose group rotation is `target` (or closest to it), by
        Gauss-Newton on log3(target R^T) from `start` moving only the `movable` joints
        (bool, default all), each within pi of its start (the branch of the rotation
        closest to the start)."""
        start = np.asarray(start, dtype=float)
        movable = np.ones(len(start), dtype=bool) if movable is None else movable
        return _group_angles(self.placements, self.axis_index, np.asarray(target, dtype=float),
                             start, np.flatnonzero(movable))

    def decide(self, q, dq, free, progressive: bool) -> LimitDecision:
        """q: configuration (nq), dq: candidate variation (nv), free: bool (nv). Joints
        fixed earlier in the clamping loop keep their variation; the others are fixed
        where the swing / twist rule or their own bounds alter them."""
        angles, variation = q[self.q_index], dq[self.v_index].copy()
        movable = free[self.v_index]
        moving = variation[movable]
        if not len(moving) or math.sqrt(moving @ moving) <= NEGLIGIBLE_VARIATION:
            return _nothing()
        h, altered = np.zeros(len(angles)), np.zeros(len(angles), dtype=bool)
        target = None
        current = self.current(angles.tobytes(), lambda: self.rotation_and_axes(angles)[0])
        if self.may_reach(current, float(np.abs(variation).sum()), self.thickness):
            target, swing_h, twist_h = self.altered(
                current, self.rotation_and_axes(angles + variation)[0], progressive)
        if target is not None:
            reached = self.angles_for(target, angles, movable)
            variation[movable] = reached[movable] - angles[movable]
            h[movable], altered[movable] = max(swing_h, twist_h), True
        own, own_dq, own_h = ~movable, np.zeros(len(angles)), np.zeros(len(angles))
        if self.bounds.fix(angles, variation, own, own_dq, own_h, progressive):
            own &= movable
            variation[own] = own_dq[own]
            h[own] = np.maximum(h[own], own_h[own])
            altered |= own
        fixed = altered.nonzero()[0]
        if not len(fixed):
            return _nothing()
        return LimitDecision(self.v_index[fixed], variation[fixed], h[fixed])

    def keep_inside(self, q, q_next) -> None:
        """Project q_next's group rotation, then its joints (in place), into the limits
        without moving either further out than q (alternately, a few rounds: the bounds
        have the last word)."""
        angles, following = q[self.q_index], q_next[self.q_index].copy()
        self.bounds.keep_inside(angles, following)
        start = self.current(angles.tobytes(), lambda: self.rotation_and_axes(angles)[0])
        if not self.may_reach(start, float(np.sum(np.abs(following - angles))), 0.0):
            q_next[self.q_index] = following
            return
        for _ in range(KEEP_INSIDE_ROUNDS):
            rotation = self.projected(start, self.rotation_and_axes(following)[0])
            if rotation is None:
                break
            following = self.angles_for(rotation, following)
            self.bounds.keep_inside(angles, following)
        q_next[self.q_index] = following


def _nothing() -> LimitDecision:
    return LimitDecision(np.zeros(0, dtype=int), np.zeros(0), np.zeros(0))


# Limit files.

JOINT_TYPES = {"swing": SwingLimit, "ball": BallLimit}


def _number(value, where: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(
            value) or (positive and value <= 0):
        raise LimitFileError(f"{where} must be a finite{' positive' if positive else ''} "
                             f"number, got {value!r}")
    return float(value)


def _domain(entry: dict, where: str) -> SwingDomain:
    if ("cone" in entry) == ("polygon" in entry):
        raise LimitFileError(f"{where}: give exactly one of 'cone' or 'polygon'")
    try:
        if "cone" in entry:
            cone = entry["cone"]
            if not isinstance(cone, dict) or set(cone) != {"a", "b"}:
                raise LimitFileError(f"{where}.cone must be a mapping {{a, b}} (rad)")
            return EllipticCone(_number(cone["a"], f"{where}.cone.a", True),
                                _number(cone["b"], f"{where}.cone.b", True))
        polygon = entry["polygon"]
        if not isinstance(polygon, list) or not all(
                isinstance(vertex, list) and len(vertex) == 3 for vertex in polygon):
            raise LimitFileError(f"{where}.polygon must be a list of [x, y, z] directions")
        return SphericalPolygon([[_number(value, f"{where}.polygon[{i}]") for value in vertex]
                                 for i, vertex in enumerate(polygon)])
    except ValueError as error:
        if isinstance(error, LimitFileError):
            raise
        field = "cone" if "cone" in entry else "polygon"
        raise LimitFileError(f"{where}.{field}: {error}") from error


def _twist(entry: dict, kind: str, where: str, group: bool = False):
    """BallLimit: (min, max) rad; SwingLimit: locked (True) or free (False); a group:
    (min, max) or None (free), a locked swing group (0, 0)."""
    value = entry.get("twist", "locked" if kind == "swing" and not group else
                      "free" if kind == "swing" else None)
    if kind == "swing":
        if value not in ("locked", "free"):
            raise LimitFileError(f"{where}.twist of a swing joint must be 'locked' or 'free'")
        if group:
            return (0.0, 0.0) if value == "locked" else None
        return value == "locked"
    if not isinstance(value, list) or len(value) != 2:
        raise LimitFileError(f"{where}.twist must be [min, max] (rad)")
    low, high = (_number(v, f"{where}.twist") for v in value)
    if not low < high:
        raise LimitFileError(f"{where}.twist needs min < max, got [{low}, {high}]")
    return low, high


def _group_joints(entry: dict, kind: str, where: str, robot) -> list:
    joints = entry["joints"]
    if not isinstance(joints, list) or not all(isinstance(j, str) for j in joints):
        raise LimitFileError(f"{where}.joints must be a list of joint names")
    needed = (3,) if kind == "ball" else (2, 3)
    if len(joints) not in needed:
        raise LimitFileError(f"{where}.joints: a {kind} group needs "
                             f"{' or '.join(map(str, needed))} joints, got {len(joints)}")
    for joint in joints:
        if not robot.model.existJointName(joint):
            raise LimitFileError(f"{where}.joints: the robot has no joint {joint!r}")
    return joints


def parse_limits(document, robot) -> list:
    """Limit models from a parsed limit file (see load_limit_file)."""
    if not isinstance(document, dict) or not isinstance(document.get("joints"), dict):
        raise LimitFileError("a limit file needs a 'joints' mapping")
    default = _number(document.get("activation", 0.2), "activation", True)
    models, owners = [], {}
    for name, entry in document["joints"].items():
        where = f"joints.{name}"
        if not isinstance(entry, dict):
            raise LimitFileError(f"{where} must be a mapping")
        unknown = set(entry) - {"type", "cone", "polygon", "twist", "activation", "joints"}
        if unknown:
            raise LimitFileError(f"{where}: unknown field(s) {', '.join(sorted(unknown))}")
        kind = entry.get("type")
        if kind not in JOINT_TYPES:
            raise LimitFileError(f"{where}.type must be one of {', '.join(JOINT_TYPES)}")
        group = "joints" in entry
        joints = _group_joints(entry, kind, where, robot) if group else [name]
        if not group and not robot.model.existJointName(name):
            raise LimitFileError(f"{where}: the robot has no joint {name!r}")
        for joint in joints:
            if joint in owners:
                raise LimitFileError(f"{where}: joint {joint!r} is already limited by "
                                     f"joints.{owners[joint]}")
            owners[joint] = name
        activation = _number(entry.get("activation", default), f"{where}.activation", True)
        domain, twist = _domain(entry, where), _twist(entry, kind, where, group)
        try:
            models.append(JointGroupLimit(name, robot, joints, domain, twist, activation)
                          if group else
                          JOINT_TYPES[kind].for_joint(robot, name, domain, twist, activation))
        except ValueError as error:
            raise LimitFileError(f"{where}: {error}") from error
    return models


SHIPPED_LIMIT_FILES = Path(__file__).resolve().parent / "data"


def limit_file_path(spec) -> Path:
    """A limit file: the path `spec`, or the shipped data/<spec>_limits.yaml (e.g. talos,
    mannequin) when spec is a bare name."""
    path = Path(spec)
    if path.exists() or path.suffix or len(path.parts) > 1:
        return path
    shipped = SHIPPED_LIMIT_FILES / f"{spec}_limits.yaml"
    if shipped.is_file():
        return shipped
    names = sorted(p.name[:-len("_limits.yaml")]
                   for p in SHIPPED_LIMIT_FILES.glob("*_limits.yaml"))
    raise LimitFileError(f"{spec}: no such limit file, nor a shipped one "
                         f"({', '.join(names)})")


def load_limit_file(path, robot) -> list:
    """Limit models of a YAML limit file (a path, or a shipped file's name: see
    limit_file_path):

        activation: 0.2                     # default q_hat (rad)
        joints:
          <spherical joint>:
            type: ball | swing
            cone: {a: .., b: ..}            # or polygon: [[x, y, z], ...] (joint frame)
            twist: [min, max]               # ball (rad); swing: locked (default) | free
            activation: 0.15                # optional, rad
          <group name>:                     # 2-3 revolute joints limited as one
            type: ball | swing              # ball: 3 joints; swing: 2 or 3
            joints: [<joint>, <joint>, ...] # a chain, parent first (JointGroupLimit)
            cone: ... | polygon: ...        # in the last joint's frame at zero angles
            twist: [min, max]               # ball; swing: free (default) | locked
    """
    path = limit_file_path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise LimitFileError(f"{path}: not valid YAML: {error}") from error
    return parse_limits(document, robot)
