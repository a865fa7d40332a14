"""Valley-like potential field on a rough trajectory (Escande et al. 2008, section 2.7).

The rough trajectory T runs through K key postures. The free-flyer subspace F is 6-D with
the point p(q) = (t, rotation_scale * log3(R_ref^T R)) of a configuration q: t the base
translation in the world (m), R the base rotation, R_ref the base rotation of the first
key posture, so F is euclidean in m with rotation_scale m per rad. The rotation chart is
valid for base rotations less than pi rad away from R_ref: key postures must stay within
MAX_ROTATION of it.

T' = p(T) is the polyline through the key postures' F points with each corner replaced by
a circular arc (in the plane of the two segments, tangent to both) of the largest radius
such that the arc stays within corner_deviation m of the corner and its tangent points
stay within the first or last half of each adjacent segment. Closer to T' than the arcs'
radii, the closest point Q' of T' to P' = p(P) is then a continuous function of P, f_T is
C1, and C2 but where the curvature jumps (the normal hyperplanes at the arcs' ends).
Corners that reverse the direction (turn of pi) cannot be smoothed and are left sharp.

Along T the base follows T' exactly and the other joints follow pin.interpolate between
the key postures (linear for revolute joints): Q = p^{-1}(Q') takes its base from Q' and
its joints from the piece of T' that Q' lies on, interpolated by Q''s fraction of that
piece's length (on a segment, linearly between the configurations at its ends; on an arc,
between the configurations at its two tangent points by the arc's angle fraction).

f_T(P) = ||P - Q||^2 - k s' (paper eq. 1), with P - Q = pin.difference(model, Q, P) (base
twist in Q's base frame: m and rad; joints in rad) and s' the curvilinear abscissa of Q'
along T' (m). Default k = 1: walking 1 m further along T' is worth a squared posture
residual of 1 (e.g. ten joints 0.3 rad off the trajectory's posture, or the base 1 m away
from it), so the slope drives the search while the valley keeps postures near T.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import pinocchio as pin

DEFAULT_SLOPE = 1.0            # k of eq. 1 (units of f per m of s')
DEFAULT_ROTATION_SCALE = 0.5   # m of F per rad of base rotation (about a body half-width)
_SAME_POINT = 1e-9             # m: key postures closer than this in F are one vertex
_STRAIGHT = 1e-9               # rad: corners turning less than this get no arc
_REVERSAL = 1e-6               # rad: corners turning more than pi minus this get no arc
MAX_ROTATION = math.pi - 0.1   # rad: largest base rotation of a key posture from R_ref


@dataclass(frozen=True)
class Projection:
    """Closest point of T' to a configuration's F point.

    s: curvilinear abscissa of Q' along T' (m).
    Q: (nq) the configuration of T at Q'.
    closest: (6,) Q' in F.
    distance: |P' - Q'| in F (m).
    ds_dpoint: (6,) gradient of s with respect to P' in F (zero beyond T''s ends).
    dQ_ds: (nv) derivative of Q along T per m of s, in Q's tangent space (pin.integrate
        convention).
    """

    s: float
    Q: np.ndarray
    closest: np.ndarray
    distance: float
    ds_dpoint: np.ndarray
    dQ_ds: np.ndarray


@dataclass(frozen=True)
class PotentialValue:
    """f_T at a configuration q.

    value: ||residual||^2 - k s.
    residual: (nv) pin.difference(model, Q, q).
    s: curvilinear abscissa of Q' along T' (m).
    ds_dq: (nv) gradient of s with respect to a tangent step dq at q
        (q_next = pin.integrate(model, q, dq)); only the base's 6 DoFs are non-zero.
    gradient: (nv) gradient of value with respect to the same tangent step dq.
    """

    value: float
    residual: np.ndarray
    s: float
    ds_dq: np.ndarray
    gradient: np.ndarray


@dataclass(frozen=True)
class _Segment:
    """A straight piece of T' from `start` along unit `direction`; q_start, q_end (nq) are
    the configurations of T at its ends."""

    s_start: float
    length: float
    start: np.ndarray
    direction: np.ndarray
    q_start: np.ndarray
    q_end: np.ndarray

    def point_at(self, u: float) -> np.ndarray:
        return self.start + u * self.direction

    def tangent_at(self, u: float) -> np.ndarray:
        return self.direction


@dataclass(frozen=True)
class _Arc:
    """A circular piece of T': centre + radius (cos a e1 + sin a e2) for a in [0, angle];
    e1, e2 orthonormal, e2 the direction of travel at a = 0."""

    s_start: float
    length: float
    center: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    radius: float
    angle: float
    q_start: np.ndarray
    q_end: np.ndarray

    def point_at(self, u: float) -> np.ndarray:
        a = u / self.radius
        return self.center + self.radius * (math.cos(a) * self.e1 + math.sin(a) * self.e2)

    def tangent_at(self, u: float) -> np.ndarray:
        a = u / self.radius
        return -math.sin(a) * self.e1 + math.cos(a) * self.e2


class RoughTrajectory:
    """The rough trajectory T through key postures and the potential f_T on it.

    model: Pinocchio model whose first joint is a free flyer.
    key_postures: (K, nq), K >= 2. Consecutive key postures at the same F point are one
        vertex of T' (the last of them is kept, so the goal is the last key posture).
    k: slope of eq. 1 (f per m of s'). corner_deviation: m in F. rotation_scale: m per rad.
    """

    def __init__(self, model: pin.Model, key_postures, k: float = DEFAULT_SLOPE,
                 corner_deviation: float = 0.05,
                 rotation_scale: float = DEFAULT_ROTATION_SCALE):
        if model.joints[1].shortname() != "JointModelFreeFlyer":
            raise ValueError("the model's first joint must be a free flyer")
        key_postures = np.array(key_postures, dtype=float)
        if key_postures.ndim != 2 or key_postures.shape[1] != model.nq:
            raise ValueError(f"key_postures must be (K, {model.nq}), got {key_postures.shape}")
        if len(key_postures) < 2:
            raise ValueError("a rough trajectory needs at least two key postures")
        if k <= 0.0 or corner_deviation < 0.0 or rotation_scale <= 0.0:
            raise ValueError("k and rotation_scale must be positive, corner_deviation >= 0")
        self.model = model
        self.k = float(k)
        self.corner_deviation = float(corner_deviation)
        self.rotation_scale = float(rotation_scale)
        self.key_postures = key_postures
        self._reference_rotation = _base_rotation(key_postures[0])
        points = np.array([self.free_flyer_point(q) for q in key_postures])
        if np.any(np.linalg.norm(points[:, 3:6], axis=1) > MAX_ROTATION * rotation_scale):
            raise ValueError("a key posture's base turns more than MAX_ROTATION from the "
                             "first key posture's")
        kept = [i for i in range(len(points) - 1)
                if np.linalg.norm(points[i + 1] - points[i]) > _SAME_POINT] + [len(points) - 1]
        if len(kept) < 2:
            raise ValueError("the key postures' bases all coincide: T' has no length")
        self._pieces = self._build_pieces(points[kept], key_postures[kept])
        self._piece_arrays = _piece_arrays(self._pieces)
        last = self._pieces[-1]
        self.length = last.s_start + last.length
        self._s_of_key_postures = np.array([self.project(q).s for q in key_postures])

    @property
    def goal_configuration(self) -> np.ndarray:
        """(nq) the last key posture: f_T is lowest there."""
        return self.key_postures[-1].copy()

    @property
    def s_of_key_postures(self) -> np.ndarray:
        """(K,) s' of each key posture's projection (m); a smoothed corner projects to its
        arc's middle."""
        return self._s_of_key_postures.copy()

    def free_flyer_point(self, q: np.ndarray) -> np.ndarray:
        """(6,) p(q) in F: base translation (m), scaled rotation vector from R_ref (m)."""
        relative = self._reference_rotation.T @ _base_rotation(q)
        return np.concatenate([q[0:3], self.rotation_scale * pin.log3(relative)])

    def configuration_at(self, s: float) -> np.ndarray:
        """(nq) the configuration of T at curvilinear abscissa s (m, clamped to T')."""
        s = min(max(float(s), 0.0), self.length)
        piece = next((p for p in self._pieces if s <= p.s_start + p.length), self._pieces[-1])
        u = s - piece.s_start
        return self._configuration(piece, u, piece.point_at(u))

    def project(self, q: np.ndarray) -> Projection:
        """Closest point Q' of T' to p(q), its abscissa s' and Q = p^{-1}(Q')."""
        point = self.free_flyer_point(q)
        index, u, closest, du = _closest_on_pieces(point, *self._piece_arrays)
        piece = self._pieces[index]
        distance = _distance(point, closest)
        Q = self._configuration(piece, u, closest)
        # Joints: pin.interpolate moves at a constant tangent velocity along the piece. Base:
        # the F tangent mapped to the local twist (inverse of the chart's derivative).
        dQ_ds = pin.difference(self.model, piece.q_start, piece.q_end) / piece.length
        tangent = piece.tangent_at(u)
        dQ_ds[0:3] = _base_rotation(Q).T @ tangent[0:3]
        dQ_ds[3:6] = (pin.Jexp3(closest[3:6] / self.rotation_scale) @ tangent[3:6]
                      / self.rotation_scale)
        return Projection(s=piece.s_start + u, Q=Q, closest=closest, distance=distance,
                          ds_dpoint=du, dQ_ds=dQ_ds)

    def evaluate(self, q: np.ndarray) -> PotentialValue:
        """f_T(q) = ||pin.difference(model, Q, q)||^2 - k s', and its gradient and ds'/dq
        with respect to a tangent step at q."""
        projection = self.project(q)
        residual = pin.difference(self.model, projection.Q, q)
        rotation = _base_rotation(q)
        log_jacobian = pin.Jlog3(self._reference_rotation.T @ rotation)
        ds_dq = np.zeros(self.model.nv)
        # Local twist (v, w): translation moves by R v, rotation vector by Jlog3 w.
        ds_dq[0:3] = rotation.T @ projection.ds_dpoint[0:3]
        ds_dq[3:6] = self.rotation_scale * log_jacobian.T @ projection.ds_dpoint[3:6]
        # residual(q) = difference(Q(s(q)), q): through q directly and through Q along T.
        d_residual_dQ, d_residual_dq = pin.dDifference(self.model, projection.Q, q)
        along_trajectory = residual @ d_residual_dQ @ projection.dQ_ds
        gradient = (2.0 * (d_residual_dq.T @ residual + along_trajectory * ds_dq)
                    - self.k * ds_dq)
        return PotentialValue(value=float(residual @ residual) - self.k * projection.s,
                              residual=residual, s=projection.s, ds_dq=ds_dq,
                              gradient=gradient)

    def _configuration(self, piece, u: float, point: np.ndarray) -> np.ndarray:
        """p^{-1}: joints interpolated along the piece, base from the F point."""
        fraction = u / piece.length
        q = pin.interpolate(self.model, piece.q_start, piece.q_end, fraction)
        rotation = self._reference_rotation @ pin.exp3(point[3:6] / self.rotation_scale)
        q[0:3] = point[0:3]
        q[3:7] = pin.Quaternion(rotation).coeffs()
        return q

    def _build_pieces(self, vertices: np.ndarray, postures: np.ndarray) -> list:
        """Segments and corner arcs of T', in order, with their abscissas."""
        lengths = np.linalg.norm(np.diff(vertices, axis=0), axis=1)
        directions = np.diff(vertices, axis=0) / lengths[:, None]
        arcs = {}       # vertex index -> (radius, turn angle, tangent length)
        for i in range(1, len(vertices) - 1):
            cosine = float(np.clip(directions[i - 1] @ directions[i], -1.0, 1.0))
            turn = math.acos(cosine)
            if turn < _STRAIGHT or turn > math.pi - _REVERSAL:
                continue
            half_tan = math.tan(turn / 2.0)
            by_deviation = self.corner_deviation / (1.0 / math.cos(turn / 2.0) - 1.0)
            by_length = 0.5 * min(lengths[i - 1], lengths[i]) / half_tan
            radius = min(by_deviation, by_length)
            if radius > 0.0:
                arcs[i] = (radius, turn, radius * half_tan)

        def posture_on_segment(j, distance):
            return pin.interpolate(self.model, postures[j], postures[j + 1],
                                   distance / lengths[j])

        pieces, s = [], 0.0
        for j in range(len(lengths)):
            trim_start = arcs[j][2] if j in arcs else 0.0
            trim_end = arcs[j + 1][2] if j + 1 in arcs else 0.0
            length = lengths[j] - trim_start - trim_end
            if length > _SAME_POINT:
                pieces.append(_Segment(
                    s, length, vertices[j] + trim_start * directions[j], directions[j],
                    posture_on_segment(j, trim_start),
                    posture_on_segment(j, lengths[j] - trim_end)))
                s += length
            if j + 1 in arcs:
                radius, turn, tangent_length = arcs[j + 1]
                incoming, outgoing = directions[j], directions[j + 1]
                inward = (outgoing - incoming) / np.linalg.norm(outgoing - incoming)
                center = vertices[j + 1] + radius / math.cos(turn / 2.0) * inward
                start = vertices[j + 1] - tangent_length * incoming
                pieces.append(_Arc(
                    s, radius * turn, center, (start - center) / radius, incoming, radius, turn,
                    posture_on_segment(j, lengths[j] - tangent_length),
                    posture_on_segment(j + 1, tangent_length)))
                s += radius * turn
        return pieces


def _piece_arrays(pieces) -> tuple:
    """The pieces of T' as arrays for _closest_on_pieces: is_arc (P,), length (P,),
    origin (P, 6) (a segment's start, an arc's centre), axis (P, 6) (a segment's direction,
    an arc's e2), e1 (P, 6) (zero for segments), radius (P,), angle (P,)."""
    arcs = [isinstance(piece, _Arc) for piece in pieces]
    zero = np.zeros(6)
    return (np.array(arcs),
            np.array([piece.length for piece in pieces]),
            np.array([piece.center if arc else piece.start for piece, arc in zip(pieces, arcs)]),
            np.array([piece.e2 if arc else piece.direction for piece, arc in zip(pieces, arcs)]),
            np.array([piece.e1 if arc else zero for piece, arc in zip(pieces, arcs)]),
            np.array([piece.radius if arc else 0.0 for piece, arc in zip(pieces, arcs)]),
            np.array([piece.angle if arc else 0.0 for piece, arc in zip(pieces, arcs)]))


@numba.njit(cache=True)
def _closest_on_pieces(point, is_arc, length, origin, axis, e1, radius, angle):
    """(piece index, u, closest point (6), du/dpoint (6)) of the piece of T' closest to
    `point` (the first one on ties): u the arc length from the piece's start (m), du/dpoint
    zero beyond a piece's ends, one-sided at them. Arrays: _piece_arrays."""
    best_distance, best = np.inf, (0, 0.0, np.zeros(6), np.zeros(6))
    for k in range(len(length)):
        closest, du = np.empty(6), np.zeros(6)
        if not is_arc[k]:
            u = 0.0
            for i in range(6):
                u += (point[i] - origin[k, i]) * axis[k, i]
            inside = 0.0 <= u <= length[k]
            u = min(max(u, 0.0), length[k])
            for i in range(6):
                closest[i] = origin[k, i] + u * axis[k, i]
                if inside:
                    du[i] = axis[k, i]
        else:
            w1 = w2 = 0.0
            for i in range(6):
                w1 += (point[i] - origin[k, i]) * e1[k, i]
                w2 += (point[i] - origin[k, i]) * axis[k, i]
            in_plane = math.hypot(w1, w2)
            a = math.atan2(w2, w1)
            inside = in_plane != 0.0 and 0.0 <= a <= angle[k]
            if inside:
                u = a * radius[k]
            else:                           # the nearer end (the start on ties)
                gaps = np.zeros(2)
                for end in range(2):
                    phase = end * length[k] / radius[k]
                    for i in range(6):
                        gap = point[i] - origin[k, i] - radius[k] * (
                            math.cos(phase) * e1[k, i] + math.sin(phase) * axis[k, i])
                        gaps[end] += gap * gap
                u = length[k] if gaps[1] < gaps[0] else 0.0
            phase = u / radius[k]
            for i in range(6):
                closest[i] = origin[k, i] + radius[k] * (
                    math.cos(phase) * e1[k, i] + math.sin(phase) * axis[k, i])
                if inside:
                    du[i] = radius[k] / in_plane * (
                        -math.sin(phase) * e1[k, i] + math.cos(phase) * axis[k, i])
        distance = 0.0
        for i in range(6):
            distance += (point[i] - closest[i]) ** 2
        if distance < best_distance:
            best_distance, best = distance, (k, u, closest, du)
    return best


def _distance(a: np.ndarray, b: np.ndarray) -> float:
    """Euclidean distance between two points of F (m)."""
    difference = a - b
    return math.sqrt(difference @ difference)


def _base_rotation(q: np.ndarray) -> np.ndarray:
    """3x3 base rotation of q (quaternion x, y, z, w at q[3:7], normalised)."""
    return pin.Quaternion(q[3:7] / np.linalg.norm(q[3:7])).toRotationMatrix()
