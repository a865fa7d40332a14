"""Static equilibrium of a robot on its contacts (Escande et al. 2008, section 2.2: the
stability constraint of the posture generator).

Each supporting contact is its patch's vertices, each taking a force inside the friction
cone linearised by an inscribed pyramid. The robot is in static equilibrium when some such
forces balance gravity at the centre of mass (CoM): force and moment balance. Units: N, m;
everything in the world frame (z up, gravity along -z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull

GRAVITY = 9.81  # m/s^2


def contact_vertices(contact, scene) -> tuple:
    """The contact's spot patch vertices placed on its surface.

    Returns (points (M, 3) in the world (m), outward surface normal (3,), friction
    coefficient). The spot frame in contact is `contact.spot_target(surface)`; the patch
    lies in that frame's xy-plane.
    """
    surface = scene.surfaces[contact.surface]
    patch = np.asarray(scene.spots[contact.spot].patch, dtype=float)
    spot = contact.spot_target(surface)
    points = patch @ spot.rotation[:, :2].T + spot.translation
    return points, surface.pose.rotation[:, 2].copy(), float(surface.friction)


def _stacked_vertices(contacts, scene) -> tuple:
    """Vertices of all contacts: points (M, 3), normals (M, 3), frictions (M,), tangents
    (M, 3) along each contact frame's x axis."""
    points, normals, frictions, tangents = [], [], [], []
    for contact in contacts:
        vertices, normal, friction = contact_vertices(contact, scene)
        tangent = contact.contact_frame(scene.surfaces[contact.surface]).rotation[:, 0]
        points.append(vertices)
        normals.append(np.tile(normal, (len(vertices), 1)))
        frictions.append(np.full(len(vertices), friction))
        tangents.append(np.tile(tangent, (len(vertices), 1)))
    return (np.vstack(points), np.vstack(normals), np.concatenate(frictions),
            np.vstack(tangents))


def are_coplanar(contacts, scene, angle_tolerance: float = math.radians(2.0),
                 distance_tolerance: float = 0.005) -> bool:
    """True when all contacts lie on one plane: their surface normals point the same way
    within `angle_tolerance` (rad) and all patch vertices lie within `distance_tolerance`
    (m) of the first contact's plane. No contact or one contact: True."""
    if not contacts:
        return True
    points, normals, _, _ = _stacked_vertices(contacts, scene)
    reference = normals[0]
    if np.any(normals @ reference < math.cos(angle_tolerance)):
        return False
    return bool(np.all(np.abs((points - points[0]) @ reference) <= distance_tolerance))


def support_polygon(contacts, scene) -> tuple:
    """Support polygon of coplanar contacts on horizontal surfaces (normal +z).

    Returns (vertices (K, 2) of the convex hull in the world xy, counter-clockwise; A (K, 2),
    b (K,)) with A @ xy <= b inside. Raises ValueError for non-coplanar or non-horizontal
    contacts, or a hull with no area.
    """
    if not contacts or not are_coplanar(contacts, scene):
        raise ValueError("support_polygon needs coplanar contacts")
    points, normals, _, _ = _stacked_vertices(contacts, scene)
    if normals[0] @ np.array([0.0, 0.0, 1.0]) < math.cos(math.radians(2.0)):
        raise ValueError("support_polygon needs horizontal surfaces (normal +z)")
    hull = ConvexHull(points[:, :2])
    return hull.points[hull.vertices], hull.equations[:, :2], -hull.equations[:, 2]


def _perpendicular(normal: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to `normal`: the world axis least aligned with it,
    projected onto the normal's plane."""
    axis = np.eye(3)[np.argmin(np.abs(normal))]
    tangent = axis - (axis @ normal) * normal
    return tangent / np.linalg.norm(tangent)


def friction_cone_generators(normal, mu: float, edges: int = 4, tangent=None) -> np.ndarray:
    """(edges, 3) unit generators of the pyramid inscribed in the Coulomb cone of axis
    `normal` and coefficient `mu`; the first edge leans toward `tangent` (a direction
    projected onto the normal's plane; default: a world axis, see _perpendicular)."""
    normal = np.asarray(normal, dtype=float)
    normal = normal / np.linalg.norm(normal)
    if tangent is None:
        first = _perpendicular(normal)
    else:
        first = np.asarray(tangent, dtype=float) - (np.asarray(tangent) @ normal) * normal
        first = first / np.linalg.norm(first)
    second = np.cross(normal, first)
    angles = 2.0 * math.pi * np.arange(edges) / edges
    generators = normal + mu * (np.outer(np.cos(angles), first) + np.outer(np.sin(angles), second))
    return generators / np.linalg.norm(generators, axis=1, keepdims=True)


@dataclass
class EquilibriumResult:
    """feasible: some contact forces balance gravity. forces: (M, 3) one force per vertex
    (N, world frame), None when the balance equations have no solution at all. margin: the
    smallest cone-generator multiplier (N) of the most robust balancing forces, capped at
    m g: > 0 strictly inside the feasible set, < 0 outside (some generator would have to
    pull), -inf when the balance equations cannot be met."""

    feasible: bool
    forces: np.ndarray | None
    margin: float


def static_equilibrium(points, normals, frictions, com, mass: float, gravity: float = GRAVITY,
                       tangents=None, edges: int = 4) -> EquilibriumResult:
    """Static equilibrium LP (scipy highs) with forces at contact vertices.

    points, normals: (M, 3) vertex positions (m) and outward surface normals (world);
    frictions: (M,) Coulomb coefficients; com: (3,) CoM (m); mass: kg; tangents: (M, 3) or
    None, the first pyramid edge direction per vertex (friction_cone_generators).
    Variables: one multiplier per cone generator and the margin t; maximise t subject to
    multipliers >= t, t <= m g, force balance sum f = -m g_vec and moment balance about the
    world origin sum p x f = -c x m g_vec, g_vec = (0, 0, -gravity).
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    normals = np.asarray(normals, dtype=float).reshape(-1, 3)
    frictions = np.broadcast_to(np.asarray(frictions, dtype=float), (len(points),))
    weight = mass * gravity
    if len(points) == 0:
        return EquilibriumResult(False, None, -math.inf)
    cones = np.stack([friction_cone_generators(
        normals[i], frictions[i], edges, None if tangents is None else tangents[i])
        for i in range(len(points))])                                     # (M, E, 3)
    moments = np.cross(points[:, None, :], cones)                          # (M, E, 3)
    count = len(points) * edges
    # Unknowns: multipliers (in units of m g, for conditioning) then t.
    balance = np.zeros((6, count + 1))
    balance[:3, :count] = cones.reshape(-1, 3).T
    balance[3:, :count] = moments.reshape(-1, 3).T
    gravity_wrench = np.array([0.0, 0.0, 1.0, *np.cross(com, [0.0, 0.0, 1.0])])
    lower_margin = np.hstack([-np.eye(count), np.ones((count, 1))])         # t - lambda <= 0
    objective = np.zeros(count + 1)
    objective[-1] = -1.0
    bounds = [(None, None)] * count + [(None, 1.0)]
    result = linprog(objective, A_ub=lower_margin, b_ub=np.zeros(count), A_eq=balance,
                     b_eq=gravity_wrench, bounds=bounds, method="highs")
    if result.status != 0:
        return EquilibriumResult(False, None, -math.inf)
    multipliers = result.x[:count].reshape(len(points), edges) * weight
    margin = float(result.x[-1]) * weight
    forces = np.einsum("me,mek->mk", multipliers, cones)
    return EquilibriumResult(margin >= -1e-9 * weight, forces, margin)


def contacts_equilibrium(contacts, scene, com, mass: float,
                         gravity: float = GRAVITY) -> EquilibriumResult:
    """static_equilibrium on the contacts' patch vertices, each friction pyramid aligned
    with its contact frame's x axis. No contact: infeasible."""
    if not contacts:
        return EquilibriumResult(False, None, -math.inf)
    points, normals, frictions, tangents = _stacked_vertices(contacts, scene)
    return static_equilibrium(points, normals, frictions, com, mass, gravity, tangents)
