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

import numba
import numpy as np

from .hierarchy import _damped_least_squares
from .limits import (NEGLIGIBLE_VARIATION, LimitDecision, RevoluteLimits, keep_inside_bounds,
                     cubic_step, decision_by_fixing, fix_joints)
from .yaml_file import load_yaml_file

OUTSIDE_TOLERANCE = 1e-9   # rad: a state this close outside a limit counts as on it
Z_AXIS = np.array([0.0, 0.0, 1.0])


class LimitFileError(ValueError):
    """A limit file is malformed; the message names the offending joint and field."""


# Swing / twist decomposition, compiled: a joint group's decision runs in one call.

EXP3_TAYLOR_BELOW = np.finfo(float).eps ** 0.25   # Pinocchio's Taylor precision<3>
EXP3_EPSILON_SQ = np.finfo(float).eps ** 2


@numba.njit(cache=True)
def rotation_exp(v):
    """Rotation matrix of the rotation vector v (rad): pinocchio.exp3's Rodrigues formula in
    its operation order (Pinocchio 4), so the same bits, in compiled code."""
    t2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2] + EXP3_EPSILON_SQ
    t = math.sqrt(t2)
    cosine, sine = math.cos(t), math.sin(t)
    if t > EXP3_TAYLOR_BELOW:
        outer, skew = (1.0 - cosine) / t2, sine / t
    else:
        outer, skew, cosine = 0.5 - t2 / 24.0, 1.0 - t2 / 6.0, 1.0 - t2 / 2.0
    rotation = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            rotation[i, j] = (outer * v[i]) * v[j]
    rotation[0, 1] -= skew * v[2]
    rotation[1, 0] += skew * v[2]
    rotation[0, 2] += skew * v[1]
    rotation[2, 0] -= skew * v[1]
    rotation[1, 2] -= skew * v[0]
    rotation[2, 1] += skew * v[0]
    for i in range(3):
        rotation[i, i] += cosine
    return rotation


@numba.njit(cache=True)
def _product3(a, b):
    """a @ b for 3x3 matrices without a BLAS call (its overhead dwarfs 27 products)."""
    product = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            product[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]
    return product


@numba.njit(cache=True)
def swing_direction(s):
    """Unit bone direction R_swing(s) z (joint frame) of swing vector s (rad)."""
    angle = math.hypot(s[0], s[1])
    scale = math.sin(angle) / angle if angle > 1e-12 else 1.0
    return np.array([scale * s[1], -scale * s[0], math.cos(angle)])


@numba.njit(cache=True)
def swing_from_direction(direction):
    """Swing vector s (rad) of the shortest-arc rotation taking z to `direction` (unit)."""
    sine = math.hypot(direction[0], direction[1])
    angle = math.atan2(sine, direction[2])
    if sine < 1e-12:
        return np.array([angle, 0.0])  # rest (0) or the singular antipode (pi)
    return angle / sine * np.array([-direction[1], direction[0]])


@numba.njit(cache=True)
def swing_direction_jacobian(s):
    """d(swing_direction)/ds (3x2)."""
    angle = math.hypot(s[0], s[1])
    if angle < 1e-6:  # sinc(a) ~ 1 - a^2/6: (sinc)'/a ~ -1/3, sin(a)/a ~ 1
        sinc, sinc_slope, sin_over = 1.0 - angle * angle / 6.0, -1.0 / 3.0, 1.0
    else:
        sinc = math.sin(angle) / angle
        sinc_slope = (angle * math.cos(angle) - math.sin(angle)) / angle ** 3
        sin_over = sinc
    sx, sy = s[0], s[1]
    return np.array([[sinc_slope * sx * sy, sinc + sinc_slope * sy * sy],
                     [-sinc - sinc_slope * sx * sx, -sinc_slope * sx * sy],
                     [-sin_over * sx, -sin_over * sy]])


@numba.njit(cache=True)
def swing_rotation(s):
    return rotation_exp(np.array([s[0], s[1], 0.0]))


@numba.njit(cache=True)
def twist_rotation(theta):
    cosine, sine = math.cos(theta), math.sin(theta)
    return np.array([[cosine, -sine, 0.0], [sine, cosine, 0.0], [0.0, 0.0, 1.0]])


@numba.njit(cache=True)
def swing_twist(rotation):
    """(s (rad, swing plane), theta (rad)) with rotation = R_swing(s) R_twist(theta about z)."""
    s = swing_from_direction(rotation[:, 2])
    swing = swing_rotation(s)   # theta from the first column of R_swing^T R
    cosine = swing[0, 0] * rotation[0, 0] + swing[1, 0] * rotation[1, 0] \
        + swing[2, 0] * rotation[2, 0]
    sine = swing[0, 1] * rotation[0, 0] + swing[1, 1] * rotation[1, 0] \
        + swing[2, 1] * rotation[2, 0]
    return s, math.atan2(sine, cosine)


@numba.njit(cache=True)
def rotation_from_swing_twist(s, theta):
    return _product3(swing_rotation(s), twist_rotation(theta))


# Limit domains in the swing plane.

CONE, POLYGON = 0, 1          # kinds of SwingDomain.geometry
NO_ROWS = np.zeros((0, 3))


class SwingDomain:
    """Valid set of swing vectors s (rad): the signed distance to the limit (inside
    positive, rad), its closest boundary point and outward normal. `geometry` is what the
    compiled kernels see: (kind, cone semi-axes (2), polygon vertices, edge ends, arc axes,
    inward normals (n x 3 each; none for a cone))."""

    geometry: tuple

    def signed_distance(self, s) -> float:
        return _domain_distance(self.geometry, np.asarray(s, dtype=float))

    def closest_boundary_point(self, s) -> np.ndarray:
        return _domain_closest(self.geometry, np.asarray(s, dtype=float))

    def normal_at(self, s) -> np.ndarray:
        """Outward unit normal (swing plane) of the limit at the boundary point closest to s:
        the direction of steepest approach to the limit from s."""
        return _domain_normal(self.geometry, np.asarray(s, dtype=float))

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
        self.geometry = (CONE, np.array([self.a, self.b]), NO_ROWS, NO_ROWS, NO_ROWS,
                         NO_ROWS)


@numba.njit(cache=True)
def _cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


@numba.njit(cache=True)
def _polygon_closest(direction, vertices, ends, arc_axes):
    """(closest boundary direction, index of its edge, index of its vertex or -1 inside an
    edge) of a spherical polygon to a unit direction: per edge, the direction projected on
    its great circle if it falls inside the arc, else the nearer end; the candidate with
    the largest cosine. The boundary is the union of the arcs, convex or not."""
    best = vertices[0].copy()
    best_cosine, best_edge, best_vertex = -2.0, 0, -1
    for edge in range(len(vertices)):
        start, end, axis = vertices[edge], ends[edge], arc_axes[edge]
        projected = direction - (direction @ axis) * axis
        length = np.sqrt(projected @ projected)
        candidate, vertex = start, edge
        if length > 1e-12:
            projected = projected / length
            if _cross(start, projected) @ axis >= 0.0 and _cross(projected, end) @ axis >= 0.0:
                candidate, vertex = projected, -1
        if vertex >= 0 and direction @ end > direction @ start:
            candidate, vertex = end, (edge + 1) % len(vertices)
        cosine = direction @ candidate
        if cosine > best_cosine:
            best, best_cosine, best_edge, best_vertex = candidate.copy(), cosine, edge, vertex
    return best, best_edge, best_vertex


@numba.njit(cache=True)
def _inside_polygon(vertices, arc_axes, inward_normals, direction):
    """Whether a unit direction lies inside a spherical polygon star-shaped around z: in
    the fan triangle (z, v_i, v_i+1) of the sector (azimuths about z from v_i to v_i+1)
    it falls in, i.e. on the inner side of that sector's edge. z is inside, -z outside."""
    if direction[0] == 0.0 and direction[1] == 0.0:
        return direction[2] > 0.0
    sense = 1.0 if arc_axes[0, 2] > 0.0 else -1.0     # vertices counterclockwise about z
    count = len(vertices)
    for edge in range(count):
        start, end = vertices[edge], vertices[(edge + 1) % count]
        if sense * (start[0] * direction[1] - start[1] * direction[0]) >= 0.0 and \
                sense * (end[0] * direction[1] - end[1] * direction[0]) < 0.0:
            normal = inward_normals[edge]
            return (normal[0] * direction[0] + normal[1] * direction[1]
                    + normal[2] * direction[2]) >= 0.0
    return False


@numba.njit(cache=True)
def _domain_closest(geometry, s):
    """SwingDomain.closest_boundary_point of the domain whose geometry is given."""
    kind, axes, vertices, ends, arc_axes, _ = geometry
    if kind == CONE:
        return np.array(_ellipse_closest_point(axes[0], axes[1], s[0], s[1]))
    return swing_from_direction(_polygon_closest(swing_direction(s), vertices, ends,
                                                 arc_axes)[0])


@numba.njit(cache=True)
def _domain_distance(geometry, s):
    """SwingDomain.signed_distance (rad, inside positive): Euclidean in the plane for a
    cone, geodesic on the sphere for a polygon."""
    kind, axes, vertices, ends, arc_axes, inward_normals = geometry
    if kind == CONE:
        closest = _domain_closest(geometry, s)
        distance = math.hypot(closest[0] - s[0], closest[1] - s[1])
        inside = (s[0] / axes[0]) ** 2 + (s[1] / axes[1]) ** 2 <= 1.0
    else:
        direction = swing_direction(s)
        closest = _polygon_closest(direction, vertices, ends, arc_axes)[0]
        across = _cross(direction, closest)
        distance = math.atan2(math.sqrt(across @ across), direction @ closest)
        inside = _inside_polygon(vertices, arc_axes, inward_normals, direction)
    return distance if inside else -distance


@numba.njit(cache=True)
def _domain_normal(geometry, s):
    """SwingDomain.normal_at: the outward unit normal (swing plane) at s's closest point."""
    kind, axes, vertices, ends, arc_axes, inward_normals = geometry
    if kind == CONE:
        closest = _domain_closest(geometry, s)
        normal = np.array([closest[0] / axes[0] ** 2, closest[1] / axes[1] ** 2])
    else:
        direction = swing_direction(s)
        closest, edge, vertex = _polygon_closest(direction, vertices, ends, arc_axes)
        toward = closest - (closest @ direction) * direction  # tangent at s to the limit
        if math.sqrt(toward @ toward) > 1e-9:
            inside = _inside_polygon(vertices, arc_axes, inward_normals, direction)
            outward = toward if inside else -toward
        elif vertex >= 0:  # on a vertex: between the two edges that meet there
            outward = -(inward_normals[vertex] + inward_normals[vertex - 1])
        else:
            outward = -inward_normals[edge]
        jacobian = swing_direction_jacobian(s)   # its transpose: the distance's gradient
        normal = np.zeros(2)
        for row in range(3):
            normal += jacobian[row] * outward[row]
    return normal / math.hypot(normal[0], normal[1])


class SphericalPolygon(SwingDomain):
    """Spherical polygon of bone directions (joint frame), convex or star-shaped around the
    rest direction z: vertices in order about z (either sense), winding once, every edge
    with z strictly on its inner side (so z sees the whole boundary); edges are
    great-circle arcs between consecutive vertices. Distances are geodesic angles on the
    unit sphere (rad)."""

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
        arc_axes = normals.copy()  # start x end: orients each edge's arc
        if normals[0] @ Z_AXIS < 0.0:
            normals = -normals  # clockwise vertices: make the normals point inward
        if np.any(normals @ Z_AXIS <= 1e-9):
            raise ValueError("the rest direction z must lie strictly on the inner side of "
                             "every edge: the polygon must be convex or star-shaped around "
                             "z, with its vertices in order")
        azimuths = np.arctan2(self.vertices[:, 1], self.vertices[:, 0])
        turns = np.sum(np.angle(np.exp(1j * (np.roll(azimuths, -1) - azimuths)))) / (2 * np.pi)
        if abs(abs(turns) - 1.0) > 1e-6:
            raise ValueError(f"the vertices must go once around z, not {abs(turns):.3g} "
                             "times")
        self.inward_normals = normals
        self.geometry = (POLYGON, np.zeros(2), self.vertices, following, arc_axes, normals)


@numba.njit(cache=True)
def _damp_swing(geometry, thickness, s, distance, s_next, progressive):
    """damp_swing for a swing s at signed distance `distance` (rad) from the limit of the
    domain whose geometry is given: (altered, next swing (rad), h)."""
    distance_next = _domain_distance(geometry, s_next)
    if distance_next < -OUTSIDE_TOLERANCE:  # eq. 7, then the second stage
        return True, _domain_closest(geometry, s_next), 1.0
    if not progressive:
        return False, s_next, 0.0
    depth = (thickness - distance) / thickness                           # d_k, eq. 6
    depth_next = (thickness - distance_next) / thickness                 # d_{k+1}
    if not depth_next > depth > 0.0:
        return False, s_next, 0.0
    h = cubic_step(depth)                                                # eq. 8
    variation = s_next - s
    normal = _domain_normal(geometry, s)
    orthogonal = (variation[0] * normal[0] + variation[1] * normal[1]) * normal
    damped = s + (1.0 - h) * orthogonal + (variation - orthogonal)       # eq. 10
    if _domain_distance(geometry, damped) < -OUTSIDE_TOLERANCE:          # second stage
        damped = _domain_closest(geometry, damped)
    return True, damped, h


def damp_swing(domain: SwingDomain, thickness: float, s, s_next, progressive: bool):
    """Altered next swing (rad) and h for a move s -> s_next in `domain` (eq. 6-10 and the
    second-stage clamp), or (None, 0) when the move is left alone. thickness: q_hat (rad)."""
    s, s_next = np.asarray(s, dtype=float), np.asarray(s_next, dtype=float)
    altered, target, h = _damp_swing(domain.geometry, float(thickness), s,
                                     domain.signed_distance(s), s_next, progressive)
    return (target, h) if altered else (None, 0.0)


# The swing / twist rule (IV.B.3), compiled. A rule is (domain geometry, swing thickness
# q_hat (rad), twist table): the twist's RevoluteLimits.table, no columns if it is free.

FREE_TWIST = np.zeros((5, 0))
TWIST_INDICES = np.zeros((2, 1), dtype=np.int64)   # the twist: coordinate 0 of its own


@numba.njit(cache=True)
def _may_reach(s, theta, distance, reach, zone, twist_table):
    """Whether a joint rotation at swing s (rad) with twist theta (rad), `distance` (rad)
    inside its swing limit, turned by at most `reach` rad, may bring the swing within
    `zone` rad of the limit or the twist into its damping zone (zone > 0) or past a bound
    (zone = 0). False is certain: the bone direction turns by at most reach, the swing
    vector by at most reach g with g = a / sin a at the largest swing angle a reachable,
    the twist by at most reach (1 + g)."""
    widest = math.hypot(s[0], s[1]) + reach
    if widest >= 0.9 * math.pi:
        return True
    stretch = widest / math.sin(widest) if widest > 1e-9 else 1.0
    if distance - reach * stretch <= zone:
        return True
    if twist_table.shape[1] == 0:
        return False
    low, high = (twist_table[2, 0], twist_table[3, 0]) if zone > 0.0 else \
        (twist_table[0, 0], twist_table[1, 0])
    return min(theta - low, high - theta) - reach * (1.0 + stretch) <= 0.0


@numba.njit(cache=True)
def _twist_target(theta, theta_next, twist_table, progressive):
    """(altered, next twist (rad), h) of a twist move theta -> theta_next by the revolute
    rule (limits.fix_joints)."""
    if twist_table.shape[1] == 0:
        return False, theta_next, 0.0
    variation = (theta_next - theta + math.pi) % (2.0 * math.pi) - math.pi
    fixed, fixed_dq, h = np.zeros(1, dtype=np.bool_), np.zeros(1), np.zeros(1)
    if fix_joints(np.array([theta]), np.array([variation]), TWIST_INDICES, twist_table,
                  progressive, fixed, fixed_dq, h) == 0:
        return False, theta_next, 0.0
    return True, theta + fixed_dq[0], h[0]


@numba.njit(cache=True)
def _altered(rule, s, theta, distance, rotation_next, progressive):
    """(altered, next rotation, swing h, twist h) for a move of a joint rotation at swing s
    and twist theta (rad), `distance` inside its swing limit, to rotation_next."""
    geometry, thickness, twist_table = rule
    s_next, theta_next = swing_twist(rotation_next)
    swing_altered, swing_target, swing_h = _damp_swing(geometry, thickness, s, distance,
                                                       s_next, progressive)
    twist_altered, twist_target, twist_h = _twist_target(theta, theta_next, twist_table,
                                                         progressive)
    target = rotation_from_swing_twist(swing_target, twist_target)
    return swing_altered or twist_altered, target, swing_h, twist_h


@numba.njit(cache=True)
def _projected(rule, s, theta, distance, rotation_next):
    """(changed, rotation_next projected into the limits without moving further out than
    the joint rotation at swing s and twist theta, `distance` inside its swing limit)."""
    geometry, _, twist_table = rule
    s_next, theta_next = swing_twist(rotation_next)
    changed = False
    if _domain_distance(geometry, s_next) < min(0.0, distance):
        s_next, changed = _domain_closest(geometry, s_next), True
    if twist_table.shape[1]:
        following = np.array([theta_next])
        keep_inside_bounds(np.array([theta]), following, TWIST_INDICES[0], twist_table[0],
                     twist_table[1])
        changed = changed or following[0] != theta_next
        theta_next = following[0]
    return changed, rotation_from_swing_twist(s_next, theta_next)


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
        self.rule = (domain.geometry, self.thickness,
                     FREE_TWIST if self.twist is None else self.twist.table)

    def decide(self, q, dq, free, progressive: bool) -> LimitDecision:
        """q: configuration (nq), dq: candidate variation (nv), free: bool (nv)."""
        return decision_by_fixing(self, q, dq, free, progressive)

    def warm_up(self, q) -> None:
        """Compile the kernels a decision near the limits needs (PIKSolver.warm_up): the
        rule's at the joint's rotation at q, and the subclass' fix and keep_inside."""
        rotation = self.rotation(q)
        s, theta = swing_twist(rotation)
        distance = self.domain.signed_distance(s)
        self.domain.normal_at(s)
        _may_reach(s, theta, distance, 0.0, self.thickness, self.rule[2])
        _altered(self.rule, s, theta, distance, rotation, True)
        _projected(self.rule, s, theta, distance, rotation)
        nv = int(self.v_index.max()) + 1
        self.fix(q, np.zeros(nv), np.zeros(nv, dtype=bool), np.zeros(nv), np.zeros(nv), True)
        self.keep_inside(q, q.copy())


@numba.njit(cache=True)
def quaternion_rotation(coefficients):
    """Rotation matrix of the quaternion (x, y, z, w) normalized (Eigen's
    toRotationMatrix), in compiled code; the identity for a zero quaternion, as Eigen's
    normalized() leaves it zero."""
    norm = math.sqrt(coefficients[0] ** 2 + coefficients[1] ** 2 + coefficients[2] ** 2
                     + coefficients[3] ** 2)
    if norm == 0.0:
        return np.eye(3)
    x, y, z, w = (coefficients[0] / norm, coefficients[1] / norm, coefficients[2] / norm,
                  coefficients[3] / norm)
    tx, ty, tz = 2.0 * x, 2.0 * y, 2.0 * z
    twx, twy, twz = tx * w, ty * w, tz * w
    txx, txy, txz = tx * x, ty * x, tz * x
    tyy, tyz, tzz = ty * y, tz * y, tz * z
    return np.array([[1.0 - (tyy + tzz), txy - twz, txz + twy],
                     [txy + twz, 1.0 - (txx + tzz), tyz - twx],
                     [txz - twy, tyz + twx, 1.0 - (txx + tyy)]])


@numba.njit(cache=True)
def rotation_quaternion(rotation):
    """Unit quaternion (x, y, z, w) of a rotation matrix (Eigen's conversion), in
    compiled code."""
    trace = rotation[0, 0] + rotation[1, 1] + rotation[2, 2]
    coefficients = np.empty(4)
    if trace > 0.0:
        t = math.sqrt(trace + 1.0)
        coefficients[3] = 0.5 * t
        t = 0.5 / t
        coefficients[0] = (rotation[2, 1] - rotation[1, 2]) * t
        coefficients[1] = (rotation[0, 2] - rotation[2, 0]) * t
        coefficients[2] = (rotation[1, 0] - rotation[0, 1]) * t
        return coefficients
    i = 0
    if rotation[1, 1] > rotation[0, 0]:
        i = 1
    if rotation[2, 2] > rotation[i, i]:
        i = 2
    j, k = (i + 1) % 3, (i + 2) % 3
    t = math.sqrt(rotation[i, i] - rotation[j, j] - rotation[k, k] + 1.0)
    coefficients[i] = 0.5 * t
    t = 0.5 / t
    coefficients[3] = (rotation[k, j] - rotation[j, k]) * t
    coefficients[j] = (rotation[j, i] + rotation[i, j]) * t
    coefficients[k] = (rotation[k, i] + rotation[i, k]) * t
    return coefficients


@numba.njit(cache=True)
def _ball_state(ball, q):
    """(R, s, theta, distance) of a ball joint at configuration q: its rotation, swing and
    twist (rad), and the swing's signed distance inside the limit (rad)."""
    indices, rule = ball
    rotation = quaternion_rotation(q[indices[0]:indices[0] + 4])
    s, theta = swing_twist(rotation)
    return rotation, s, theta, _domain_distance(rule[0], s)


@numba.njit(cache=True)
def ball_fix(ball, q, dq, progressive, fixed, fixed_dq, h):
    """BallLimit.fix in one compiled call. ball: BallLimit.kernel_arguments, ((first q
    index, first v index), swing / twist rule); q index -1 fixes nothing (NO_BALL)."""
    indices, rule = ball
    if indices[0] < 0:
        return False
    first = indices[1]
    moving = 0.0
    for k in range(3):
        if fixed[first + k]:
            return False
        moving += dq[first + k] * dq[first + k]
    reach = math.sqrt(moving)
    rotation, s, theta, distance = _ball_state(ball, q)
    if reach <= NEGLIGIBLE_VARIATION and not _may_reach(s, theta, distance, 0.0, 0.0, rule[2]):
        return False    # unmoved inside (a joint outside its limits goes back even unmoved)
    if not _may_reach(s, theta, distance, reach, rule[1], rule[2]):
        return False
    altered, target, swing_h, twist_h = _altered(
        rule, s, theta, distance, _product3(rotation, rotation_exp(dq[first:first + 3])),
        progressive)
    if not altered:
        return False
    variation = rotation_log(_product3(rotation.T.copy(), target))
    for k in range(3):
        fixed[first + k], fixed_dq[first + k] = True, variation[k]
    h[first], h[first + 1], h[first + 2] = swing_h, swing_h, twist_h
    return True


@numba.njit(cache=True)
def _ball_keep_inside(ball, q, q_next):
    """BallLimit.keep_inside in one compiled call (ball: ball_fix's; NO_BALL: nothing)."""
    indices, rule = ball
    if indices[0] < 0:
        return
    rotation, s, theta, distance = _ball_state(ball, q)
    following = quaternion_rotation(q_next[indices[0]:indices[0] + 4])
    turn = rotation_log(_product3(rotation.T.copy(), following))
    if not _may_reach(s, theta, distance, math.sqrt(np.sum(turn * turn)), 0.0, rule[2]):
        return
    changed, projected = _projected(rule, s, theta, distance, following)
    if changed:
        q_next[indices[0]:indices[0] + 4] = rotation_quaternion(projected)


class BallLimit(SwingTwistRule):
    """Ball-and-socket limit (IV.B.3) of one Pinocchio spherical joint (q: quaternion x, y,
    z, w; dq: local angular velocity, rad); see SwingTwistRule. Fixes all three velocity
    DoFs to log3(R_k^T R'_{k+1}) whenever the swing or the twist is altered. Decisions and
    projections run compiled (ball_fix, _ball_keep_inside)."""

    def __init__(self, joint: str, q_index: int, v_index: int, domain: SwingDomain,
                 twist=None, activation: float = 0.2):
        super().__init__(joint, domain, twist, activation)
        self.joint = joint
        self.q_slice = slice(q_index, q_index + 4)
        self.v_index = np.arange(v_index, v_index + 3)
        self.dof_names = [f"{joint}_swing_x", f"{joint}_swing_y", f"{joint}_twist"]
        self.kernel_arguments = (np.array([q_index, v_index], dtype=np.int64), self.rule)

    @classmethod
    def for_joint(cls, robot, joint: str, *args, **kwargs):
        """The limit of the robot's spherical joint `joint`; other arguments as __init__."""
        joint_model = robot.model.joints[robot.joint_id(joint)]
        if joint_model.shortname() != "JointModelSpherical":
            raise ValueError(f"joint {joint!r} is not a spherical joint")
        return cls(joint, joint_model.idx_q, joint_model.idx_v, *args, **kwargs)

    def rotation(self, q) -> np.ndarray:
        """Joint rotation R (joint frame relative to its placement) at configuration q."""
        return quaternion_rotation(np.asarray(q[self.q_slice], dtype=float))

    def fix(self, q, dq, fixed, fixed_dq, h, progressive: bool) -> bool:
        """Fix in place (fixed, fixed_dq, h: nv) the joint's three DoFs, when none is
        fixed yet and the swing / twist rule alters the rotation dq (nv) moves it to;
        True if it does. q: configuration (nq)."""
        return bool(ball_fix(self.kernel_arguments, q, dq, progressive, fixed, fixed_dq, h))

    def keep_inside(self, q, q_next) -> None:
        """Project q_next's joint rotation (in place) into the limits without moving it
        further out than q: removes the negligible overshoot the decisions ignored."""
        _ball_keep_inside(self.kernel_arguments, q, q_next)


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


@numba.njit(cache=True)
def group_fix(group, q, dq, progressive, fixed, fixed_dq, h):
    """JointGroupLimit.fix in one compiled call. group: JointGroupLimit.kernel_arguments,
    (kinematics, rule, bounds, report): the (placements, axis indices, q indices, v
    indices) of its joints, its swing / twist rule, the joints' own RevoluteLimits
    (indices, table) over the group's coordinates, and the group's report (swing h,
    twist h, 1.0 once altered: raised in place, JointGroupLimit.report)."""
    kinematics, rule, bounds, report = group
    placements, axis_index, q_index, v_index = kinematics
    geometry, thickness, twist_table = rule
    count = len(q_index)
    if count == 0:      # NO_GROUP
        return False
    angles, variation = np.empty(count), np.empty(count)
    movable = np.empty(count, dtype=np.bool_)
    moving = 0.0        # every joint's, fixed ones too: theirs may turn the group out
    for j in range(count):
        angles[j], variation[j], movable[j] = q[q_index[j]], dq[v_index[j]], not fixed[v_index[j]]
        moving += variation[j] * variation[j]
    rotation = _group_rotation(placements, axis_index, angles)[0]
    s, theta = swing_twist(rotation)
    distance = _domain_distance(geometry, s)
    if math.sqrt(moving) <= NEGLIGIBLE_VARIATION and \
            not _may_reach(s, theta, distance, 0.0, 0.0, twist_table) and \
            np.all((bounds[1][0] <= angles) & (angles <= bounds[1][1])):
        return False    # unmoved inside (a group outside its limits goes back even unmoved)
    group_h, altered = np.zeros(count), np.zeros(count, dtype=np.bool_)
    if _may_reach(s, theta, distance, np.sum(np.abs(variation)), thickness, twist_table):
        changed, target, swing_h, twist_h = _altered(
            rule, s, theta, distance,
            _group_rotation(placements, axis_index, angles + variation)[0], progressive)
        if changed and np.any(movable):   # the joints still free turned to the altered
            #                                   rotation, and fixed
            report[0], report[1] = max(report[0], swing_h), max(report[1], twist_h)
            report[2] = 1.0
            reached = _group_angles(placements, axis_index, target, angles,
                                    np.flatnonzero(movable))
            for j in range(count):
                if movable[j]:
                    variation[j] = reached[j] - angles[j]
                    group_h[j], altered[j] = max(swing_h, twist_h), True
    own, own_dq, own_h = ~movable, np.zeros(count), np.zeros(count)   # their own bounds
    if fix_joints(angles, variation, bounds[0], bounds[1], progressive, own, own_dq,
                  own_h) > 0:
        for j in range(count):
            if own[j] and movable[j]:
                variation[j] = own_dq[j]
                group_h[j], altered[j] = max(group_h[j], own_h[j]), True
    for j in range(count):
        if altered[j]:
            v = v_index[j]
            fixed[v], fixed_dq[v], h[v] = True, variation[j], group_h[j]
    return np.any(altered)


@numba.njit(cache=True)
def _group_keep_inside(group, q, q_next):
    """JointGroupLimit.keep_inside in one compiled call (group: group_fix's)."""
    kinematics, rule, bounds, _ = group
    placements, axis_index, q_index, _ = kinematics
    twist_table = rule[2]
    local, lower, upper = bounds[0][0], bounds[1][0], bounds[1][1]
    count = len(q_index)
    angles, following = np.empty(count), np.empty(count)
    for j in range(count):
        angles[j], following[j] = q[q_index[j]], q_next[q_index[j]]
    keep_inside_bounds(angles, following, local, lower, upper)
    returned = following.copy()     # joints outside their bounds keep their way back
    s, theta = swing_twist(_group_rotation(placements, axis_index, angles)[0])
    distance = _domain_distance(rule[0], s)
    if _may_reach(s, theta, distance, np.sum(np.abs(following - angles)), 0.0, twist_table):
        for _ in range(KEEP_INSIDE_ROUNDS):
            changed, rotation = _projected(
                rule, s, theta, distance,
                _group_rotation(placements, axis_index, following)[0])
            if not changed:
                break
            following = _group_angles(placements, axis_index, rotation, following, local)
            keep_inside_bounds(returned, following, local, lower, upper)
    for j in range(count):
        q_next[q_index[j]] = following[j]


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
    group's and the joint's own. Decisions and projections run compiled (group_fix,
    _group_keep_inside)."""

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
        self.q_index = np.array([model.joints[i].idx_q for i in ids], dtype=np.int64)
        self.v_index = np.array([model.joints[i].idx_v for i in ids], dtype=np.int64)
        self.dof_names = list(joints)
        # the swing / twist rule's own h, reported beside the joints' (whose h is the
        # larger of the group's and their own): swing h, twist h, 1.0 once it altered the
        # joints, the largest since the last reset (PIKSolver resets it every step)
        self.report = np.zeros(3)
        self.report_names = [f"{name}_swing", f"{name}_twist"]
        bounds = (model.lowerPositionLimit[self.q_index], model.upperPositionLimit[self.q_index])
        local = np.arange(len(ids))
        self.bounds = RevoluteLimits(joints, local, local, *bounds, activation)
        self.kernel_arguments = ((self.placements, self.axis_index, self.q_index,
                                  self.v_index), self.rule,
                                 (self.bounds.indices, self.bounds.table), self.report)

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

    def fix(self, q, dq, fixed, fixed_dq, h, progressive: bool) -> bool:
        """Fix in place (fixed, fixed_dq, h: nv) the group's joints not fixed yet that the
        swing / twist rule or their own bounds alter; True if any. q: configuration (nq),
        dq: candidate variation (nv). Joints fixed earlier keep their variation."""
        return bool(group_fix(self.kernel_arguments, q, dq, progressive, fixed, fixed_dq, h))

    def keep_inside(self, q, q_next) -> None:
        """Project q_next's group rotation, then its joints (in place), into the limits
        without moving either further out than q (alternately, a few rounds: the bounds
        have the last word), except that a joint beyond its own bound keeps the way back
        q_next gives it even where the swing then grows: a group turned past a half turn
        (a hip pitch far past its bound) can only come back through the bone pointing
        straight up."""
        _group_keep_inside(self.kernel_arguments, q, q_next)


# group_fix's arguments for a group of no joints, which fixes nothing: the compiled
# clamping loop's stand-in for a robot without groups (numba cannot loop over no groups)
NO_GROUP = ((np.zeros((0, 3, 3)), np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64),
             np.zeros(0, dtype=np.int64)), (EllipticCone(1.0, 1.0).geometry, 1.0, FREE_TWIST),
            (np.zeros((2, 0), dtype=np.int64), np.zeros((5, 0))), np.zeros(3))
# ball_fix's arguments for no joint: the compiled loop's stand-in for a robot without balls
NO_BALL = (np.array([-1, -1], dtype=np.int64), NO_GROUP[1])


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
    document = load_yaml_file(path, LimitFileError)
    return parse_limits(document, robot)
