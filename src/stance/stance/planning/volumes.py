"""Contact search volumes (Escande et al. 2008, sections 2.5-2.6).

A contact of a spot on a convex surface is v = (x, y, theta): a point of the surface
polygon E (m, surface frame) and a rotation about the surface normal (rad). The search
volume C = E x [theta_lower, theta_upper] is a convex prism (the paper's E x ]-pi, pi],
closed here). Once a contact is found, a box V around it is subtracted and C \\ V is cut
into convex prisms on which the search goes on.

Theta wrap-around is not merged: a box reaching past +-pi is not continued on the other side
of the interval, so a contact near theta = pi does not exclude its neighbours near -pi.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog

MIN_AREA = 1e-4           # m^2: polygons of at most this area are slivers, dropped
MIN_THETA_WIDTH = 0.02    # rad: theta intervals at most this wide are slivers, dropped
_CONVEXITY_TOLERANCE = 1e-12
_VERTEX_TOLERANCE = 1e-9  # m: vertices this close to their neighbours' line are dropped


@dataclass(frozen=True, eq=False)
class SearchVolume:
    """C = polygon x [theta_lower, theta_upper].

    polygon: (N, 2) convex vertices, counter-clockwise, in the surface frame (m); vertices
        within _VERTEX_TOLERANCE of the line through their neighbours (duplicates,
        collinear points: their edges' normals would be noise) are dropped.
    theta_lower, theta_upper: rad.
    halfspaces and chebyshev_center are meaningful for non-empty volumes only.
    """

    polygon: np.ndarray
    theta_lower: float
    theta_upper: float

    def __post_init__(self):
        polygon = np.asarray(self.polygon, dtype=float)
        if polygon.ndim != 2 or polygon.shape[1] != 2:
            raise ValueError(f"polygon must be (N, 2), got {polygon.shape}")
        polygon = _without_redundant_vertices(polygon)
        if len(polygon) >= 3:
            edges = np.roll(polygon, -1, axis=0) - polygon
            following = np.roll(edges, -1, axis=0)
            turns = edges[:, 0] * following[:, 1] - edges[:, 1] * following[:, 0]
            if np.any(turns < -_CONVEXITY_TOLERANCE):
                raise ValueError("polygon must be convex and counter-clockwise")
        object.__setattr__(self, "polygon", polygon)

    @property
    def area(self) -> float:
        """Polygon area (m^2)."""
        return _polygon_area(self.polygon)

    def halfspaces(self) -> tuple:
        """(A (m, 3), b (m,)) with C = {v = (x, y, theta) : A v <= b}; polygon rows have unit
        normals. Read-only arrays, computed once (the posture generator asks at every
        iteration)."""
        if "_halfspaces" not in self.__dict__:
            object.__setattr__(self, "_halfspaces", self._compute_halfspaces())
        return self._halfspaces

    def _compute_halfspaces(self) -> tuple:
        edges = np.roll(self.polygon, -1, axis=0) - self.polygon
        normals = np.column_stack([edges[:, 1], -edges[:, 0]])   # outward for CCW
        normals /= np.linalg.norm(normals, axis=1)[:, None]
        A = np.zeros((len(normals) + 2, 3))
        A[:-2, 0:2] = normals
        A[-2:, 2] = [1.0, -1.0]
        b = np.concatenate([np.einsum("ij,ij->i", normals, self.polygon),
                            [self.theta_upper, -self.theta_lower]])
        A.flags.writeable = b.flags.writeable = False
        return A, b

    def contains(self, v, tolerance: float = 1e-9) -> bool:
        """True when v = (x, y, theta) satisfies every half-space within tolerance (m, rad;
        negative: strictly inside by that margin)."""
        A, b = self.halfspaces()
        return bool(np.all(A @ np.asarray(v, dtype=float) <= b + tolerance))

    def is_empty(self) -> bool:
        """True for an empty volume or a sliver (area at most MIN_AREA or theta width at
        most MIN_THETA_WIDTH)."""
        return self.area <= MIN_AREA or self.theta_upper - self.theta_lower <= MIN_THETA_WIDTH

    def chebyshev_center(self) -> np.ndarray:
        """(3,) a point deep inside: the centre of the polygon's largest inscribed circle
        (linear programme) and the middle of the theta interval."""
        A, b = self.halfspaces()
        A, b = A[:-2, 0:2], b[:-2]
        # Maximise r subject to a_i . c + r <= b_i over (c_x, c_y, r); rows have unit norm.
        result = linprog(c=[0.0, 0.0, -1.0], A_ub=np.column_stack([A, np.ones(len(A))]),
                         b_ub=b, bounds=[(None, None), (None, None), (0.0, None)],
                         method="highs")
        if not result.success:
            raise ValueError(f"no Chebyshev centre: {result.message}")
        return np.array([result.x[0], result.x[1],
                         0.5 * (self.theta_lower + self.theta_upper)])

    def subtract(self, center, half_extents) -> list:
        """Convex parts of C minus the box V = center +- half_extents over (x, y, theta):
        the slabs x < cx - hx and x > cx + hx, then within the x band y < cy - hy and
        y > cy + hy, then within the x and y bands theta < ct - ht and theta > ct + ht.
        Empty parts and slivers are dropped; C itself is returned when V misses it."""
        (cx, cy, ct), (hx, hy, ht) = np.asarray(center, float), np.asarray(half_extents, float)
        x_band = clip_polygon(clip_polygon(self.polygon, (1.0, 0.0), cx + hx),
                              (-1.0, 0.0), -(cx - hx))
        xy_band = clip_polygon(clip_polygon(x_band, (0.0, 1.0), cy + hy), (0.0, -1.0),
                               -(cy - hy))
        theta_overlap = min(self.theta_upper, ct + ht) - max(self.theta_lower, ct - ht)
        if _polygon_area(xy_band) <= 0.0 or theta_overlap <= 0.0:
            return [self]
        lower, upper = self.theta_lower, self.theta_upper
        parts = [
            SearchVolume(clip_polygon(self.polygon, (1.0, 0.0), cx - hx), lower, upper),
            SearchVolume(clip_polygon(self.polygon, (-1.0, 0.0), -(cx + hx)), lower, upper),
            SearchVolume(clip_polygon(x_band, (0.0, 1.0), cy - hy), lower, upper),
            SearchVolume(clip_polygon(x_band, (0.0, -1.0), -(cy + hy)), lower, upper),
            SearchVolume(xy_band, lower, min(upper, ct - ht)),
            SearchVolume(xy_band, max(lower, ct + ht), upper),
        ]
        return [part for part in parts if not part.is_empty()]


def initial_volume(surface_polygon, theta_range=(-math.pi, math.pi)) -> SearchVolume:
    """The whole search volume of a convex surface polygon ((N, 2) CCW, m) over theta_range
    (rad)."""
    return SearchVolume(np.asarray(surface_polygon, dtype=float), float(theta_range[0]),
                        float(theta_range[1]))


def clip_polygon(polygon: np.ndarray, normal, offset: float) -> np.ndarray:
    """The convex polygon (N, 2) cut to the half-plane normal . p <= offset
    (Sutherland-Hodgman, one edge); vertex order is kept, empty result (0, 2)."""
    normal = np.asarray(normal, dtype=float)
    if len(polygon) == 0:
        return polygon
    excess = polygon @ normal - offset
    clipped = []
    for i in range(len(polygon)):
        j = (i + 1) % len(polygon)
        if excess[i] <= 0.0:
            clipped.append(polygon[i])
        if (excess[i] < 0.0 < excess[j]) or (excess[j] < 0.0 < excess[i]):
            t = excess[i] / (excess[i] - excess[j])
            clipped.append(polygon[i] + t * (polygon[j] - polygon[i]))
    return np.array(clipped).reshape(-1, 2)


def _without_redundant_vertices(polygon: np.ndarray) -> np.ndarray:
    """The polygon (N, 2) without the vertices within _VERTEX_TOLERANCE of the line through
    their two neighbours (or of their previous neighbour, when the neighbours coincide)."""
    points = list(polygon)
    removed = True
    while removed and len(points) >= 3:
        removed = False
        for i in range(len(points)):
            previous, current, following = points[i - 1], points[i], points[(i + 1) % len(points)]
            chord, offset = following - previous, current - previous
            chord_length = np.linalg.norm(chord)
            distance = (abs(chord[0] * offset[1] - chord[1] * offset[0]) / chord_length
                        if chord_length > _VERTEX_TOLERANCE else np.linalg.norm(offset))
            if distance < _VERTEX_TOLERANCE:
                del points[i]
                removed = True
                break
    return np.array(points, dtype=float).reshape(-1, 2)


def _polygon_area(polygon: np.ndarray) -> float:
    """Signed area (m^2, shoelace formula), positive for counter-clockwise vertices."""
    if len(polygon) < 3:
        return 0.0
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * float(x @ np.roll(y, -1) - y @ np.roll(x, -1))
