"""Collision model of a robot in a scene (coal through Pinocchio) for the posture generator.

Geometry: the robot's URDF collision meshes replaced by their convex hulls (qhull; built once
per mesh file and scale in this process), scene obstacles as coal boxes or convex hulls of
their meshes, fixed to the universe joint at their world pose. Pairs: every robot geometry
with every obstacle and, with self_collision, every robot pair the robot's SRDF does not
disable (Talos: 887 self pairs). Geometry names are the URDF's (e.g. leg_left_6_link_0) and
the obstacles' names; a geometry's parentJoint is the robot joint that moves it.

Distances are signed (m; negative: penetration depth of the hulls, by EPA). Gradients are
with respect to a tangent step dq (size nv) with q_next = pin.integrate(model, q, dq) (the
free flyer's twist in the base's local frame, as Pinocchio does): for a pair with nearest
points p1 on body 1, p2 on body 2 and normal n from body 1 to body 2 (world frame),
d' = n.(v(p2) - v(p1)) with the point velocity v(p) = (J_lin - [p]x J_ang) dq of the body's
joint WORLD Jacobian, i.e. the row [n, p x n] J.

Near pairs (constraint_rows): every pair has a certified lower bound of its distance from
the last refresh (the exact hull distance for pairs whose bounding volumes - a sphere about
each robot geometry, the world AABB of each obstacle - were closer than near + margin, the
bounding volumes' signed distance otherwise), lowered by how far the two bodies may have
moved since (|dt| + rotation angle * reach of the geometries about their joint origin). Only
pairs whose bound is below `near` get an exact distance, so no near pair is missed whatever
the step. A refresh (full pass: bounds of all pairs, exact distances below near + margin)
happens on the first call, when `near` grew, or when some body may have moved by more than
margin / 2 since the last one: then the candidates never outnumber the last refresh's exact
pairs. min_distance and penetrations use the same bounds to skip far pairs.

Measured costs (Talos with 7 boxes around it: 1251 pairs, about 50 rows at near = 8 cm;
one BLAS thread; median / p99 over 1000 calls; random q: half_sitting plus N(0, 0.15 rad)
on every joint; machine shared with other jobs):
    full pass (refresh) at random q            0.78 ms / 1.29 ms
    constraint_rows, walk of 5 mrad per joint  0.39 ms / 0.68 ms   (1 refresh in 7 calls)
    constraint_rows at random q, no refresh    0.45 ms / 0.72 ms
    min_distance after constraint_rows at q    0.26 ms / 0.32 ms
    min_distance or penetrations, cold         0.43 ms / 0.73 ms
One exact hull distance costs 2 to 4 us; about 0.2 ms per call is Python and numpy.
"""

from __future__ import annotations

import os

import coal
import numpy as np
import pinocchio as pin
from scipy.spatial.distance import cdist

# Convex hulls by (mesh path, scale): building one costs about 1 ms per mesh.
_HULLS: dict = {}

# GJK / EPA tolerances (m): gradients then match central differences to 1e-5 also in
# deep penetration (EPA at 1e-9 left 2e-4); no measurable cost on hulls.
_GJK_TOLERANCE = 1e-9
_EPA_TOLERANCE = 1e-12


def example_robot_data_files(spec: str) -> tuple[list, str | None]:
    """Package directories (for package:// mesh URIs) and SRDF path of an example-robot-data
    robot, or ([], None) when `spec` is not one."""
    import example_robot_data as erd

    loader = erd.ROBOTS.get(spec)
    if loader is None:
        return [], None
    root = erd.getModelPath(os.path.join(loader.path, loader.urdf_subpath, loader.urdf_filename))
    srdf = None
    if loader.srdf_filename:
        srdf = os.path.normpath(
            os.path.join(root, loader.path, loader.srdf_subpath, loader.srdf_filename))
    return [os.path.normpath(os.path.join(root, "..", ".."))], srdf


def convex_hull(key: tuple, load_mesh) -> coal.ConvexBase:
    """The convex hull of the triangle mesh load_mesh() returns, cached under `key` (mesh
    path, scale): the mesh is only loaded the first time."""
    hull = _HULLS.get(key)
    if hull is None:
        mesh = load_mesh()
        mesh.buildConvexHull(True, "Qt")  # returns False when the mesh was not convex: fine
        hull = mesh.convex
        hull.computeLocalAABB()
        _HULLS[key] = hull
    return hull


def obstacle_geometry(obstacle) -> coal.CollisionGeometry:
    """A scene obstacle as a coal shape: a box, or the convex hull of its (scaled) mesh."""
    if obstacle.shape == "box":
        box = coal.Box(*np.asarray(obstacle.size, dtype=float))
        box.computeLocalAABB()
        return box
    if obstacle.shape == "mesh":
        scale = np.asarray(obstacle.scale, dtype=float)
        return convex_hull((obstacle.mesh, tuple(scale)),
                           lambda: coal.MeshLoader().load(obstacle.mesh, scale))
    raise ValueError(f"obstacle {obstacle.name!r}: unknown shape {obstacle.shape!r}")


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (k, 3) arrays (half the cost of np.cross at k ~ 50)."""
    return np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
                     a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                     a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)


class CollisionModel:
    """Signed distances and their gradients between the robot's bodies and the obstacles.

    robot: stance.robot.Robot; scene: stance.planning.scene.Scene (its `robot` spec names
    the example-robot-data robot whose meshes and SRDF are used unless package_dirs and
    srdf_path are given). margin (m): the refresh policy's slack (module docstring).
    """

    def __init__(self, robot, scene, self_collision: bool = True,
                 package_dirs: list | None = None, srdf_path: str | None = None,
                 margin: float = 0.05):
        self.robot, self.scene, self.margin = robot, scene, margin
        model = robot.model
        if not robot.urdf:
            raise ValueError("the robot has no URDF, hence no collision geometry")
        if package_dirs is None and srdf_path is None:
            package_dirs, srdf_path = example_robot_data_files(scene.robot)
        geometry_model = pin.buildGeomFromUrdfString(
            model, robot.urdf, pin.COLLISION, package_dirs=list(package_dirs or []))
        for geometry in geometry_model.geometryObjects:
            if isinstance(geometry.geometry, coal.BVHModelBase):
                geometry.geometry = convex_hull((geometry.meshPath, tuple(geometry.meshScale)),
                                                lambda mesh=geometry.geometry: mesh)
            else:
                geometry.geometry.computeLocalAABB()
        robot_geometries = geometry_model.ngeoms
        if self_collision:
            geometry_model.addAllCollisionPairs()
            if srdf_path:
                pin.removeCollisionPairs(model, geometry_model, srdf_path)
        self.self_pairs = len(geometry_model.collisionPairs)
        for obstacle in scene.obstacles.values():
            if geometry_model.existGeometryName(obstacle.name):
                raise ValueError(f"obstacle {obstacle.name!r} has a robot geometry's name")
            obstacle_id = geometry_model.addGeometryObject(pin.GeometryObject(
                obstacle.name, 0, obstacle.pose, obstacle_geometry(obstacle)))
            for robot_id in range(robot_geometries):
                geometry_model.addCollisionPair(pin.CollisionPair(robot_id, obstacle_id))
        self.geometry_model = geometry_model
        self.geometry_data = geometry_model.createData()
        self.data = model.createData()
        for request in self.geometry_data.distanceRequests:
            request.gjk_tolerance = _GJK_TOLERANCE
            request.epa_tolerance = _EPA_TOLERANCE

        objects = list(geometry_model.geometryObjects)
        self.geometry_names = [g.name for g in objects]
        self.geometry_joints = np.array([g.parentJoint for g in objects], dtype=int)
        self.pairs = np.array([(p.first, p.second) for p in geometry_model.collisionPairs],
                              dtype=int).reshape(-1, 2)
        self.pair_joints = self.geometry_joints[self.pairs]
        self.labels = [f"{self.geometry_names[a]}|{self.geometry_names[b]}" for a, b in self.pairs]
        self._pair_index = {(int(a), int(b)): k for k, (a, b) in enumerate(self.pairs)}
        self._bounds_setup(objects, robot_geometries)
        # support[j]: 1 on the velocity columns that move joint j, 0 elsewhere.
        support = np.zeros((model.njoints, model.nv))
        for joint_id in range(1, model.njoints):
            for ancestor in model.supports[joint_id][1:]:
                joint = model.joints[ancestor]
                support[joint_id, joint.idx_v:joint.idx_v + joint.nv] = 1.0
        self._support = support
        self._reference = None      # joint placements (njoints, 4, 4) at the last refresh
        self._lower = None          # certified distance lower bounds (pairs,) at that refresh
        self._near = 0.0            # `near` of that refresh (m)
        self._ignored_key, self._ignored_mask = None, np.zeros(len(self.pairs), dtype=bool)

    def _bounds_setup(self, objects, robot_geometries):
        """Bounding volumes for cheap distance lower bounds: a sphere about each robot
        geometry (centre in its joint's frame, radius), the world AABB of each obstacle."""
        robot_objects, obstacle_objects = objects[:robot_geometries], objects[robot_geometries:]
        self._robot_joints = self.geometry_joints[:robot_geometries]
        self._centres = np.array([g.placement.act(g.geometry.aabb_center) for g in robot_objects])
        radii = np.array([g.geometry.aabb_radius for g in robot_objects])
        boxes = [g.geometry.aabb_local for g in obstacle_objects]
        self._box_centres = np.array([g.placement.act(box.center())
                                      for g, box in zip(obstacle_objects, boxes)]).reshape(-1, 3)
        self._box_extents = np.array([np.abs(g.placement.rotation) @ (0.5 * (box.max_ - box.min_))
                                      for g, box in zip(obstacle_objects, boxes)]).reshape(-1, 3)
        first, second = self.pairs[:, 0], self.pairs[:, 1]
        self._self_pairs = np.flatnonzero(second < robot_geometries)
        self._obstacle_pairs = np.flatnonzero(second >= robot_geometries)
        self_first, self_second = first[self._self_pairs], second[self._self_pairs]
        self._self_flat = self_first * robot_geometries + self_second
        self._self_radii = radii[self_first] + radii[self_second]
        obstacles = len(obstacle_objects)
        self._obstacle_flat = (first * obstacles + second - robot_geometries)[self._obstacle_pairs]
        self._obstacle_radii = radii[first[self._obstacle_pairs]]
        reach = np.zeros(self.robot.model.njoints)    # farthest geometry point from a joint (m)
        np.maximum.at(reach, self._robot_joints, np.linalg.norm(self._centres, axis=1) + radii)
        self._reach = reach
        joints = self.pair_joints
        self._flat_pair_joints = joints[:, 0] * self.robot.model.njoints + joints[:, 1]

    def ignored_pairs_for_contacts(self, contacts) -> frozenset:
        """Pair indices between the bodies carrying the contacts' spots and the obstacles
        their surfaces lie on (surfaces without an obstacle ignore nothing)."""
        model, ignored = self.robot.model, set()
        for contact in contacts:
            obstacle = self.scene.surfaces[contact.surface].obstacle
            if obstacle is None:
                continue
            if obstacle not in self.geometry_names:
                raise ValueError(f"surface {contact.surface!r}: unknown obstacle {obstacle!r}")
            obstacle_id = self.geometry_names.index(obstacle)
            joint = model.frames[model.getFrameId(self.scene.spots[contact.spot].frame)].parentJoint
            for geometry_id in np.flatnonzero(self.geometry_joints == joint):
                pair = self._pair_index.get((int(geometry_id), obstacle_id))
                if pair is not None:
                    ignored.add(pair)
        return frozenset(ignored)

    def constraint_rows(self, q: np.ndarray, near: float = 0.10,
                        ignored: frozenset = frozenset()) -> tuple:
        """Rows for the QP of every non-ignored pair closer than `near` (m) at q.

        Returns distances (k,) in m (negative: penetration), gradients (k, nv) of those
        distances with respect to dq (q_next = pin.integrate(model, q, dq)), and k labels
        "geomA|geomB". Near-pair policy and costs: module docstring.
        """
        pin.computeJointJacobians(self.robot.model, self.data, q)
        placements = self._place_geometries()
        stale = self._reference is None or near > self._near
        if not stale:
            largest, shrink = self._pair_motion(placements)
            stale = largest > 0.5 * self.margin
        if stale:
            candidates, results, distances = self._refresh(placements, near)
        else:
            candidates = np.flatnonzero((self._lower - shrink < near) & ~self._ignored(ignored))
            results, distances = self._distances(candidates)
        close = np.flatnonzero((distances < near) & ~self._ignored(ignored)[candidates])
        pairs = candidates[close]
        normals, points = self._witnesses([results[k] for k in close])
        joints = self.pair_joints[pairs]
        moving = self._support[joints[:, 1]] - self._support[joints[:, 0]]
        gradients = (np.hstack([normals, _cross(points, normals)]) @ self.data.J) * moving
        return distances[close], gradients, [self.labels[k] for k in pairs]

    def min_distance(self, q: np.ndarray, ignored: frozenset = frozenset()) -> tuple:
        """(distance in m, label) of the closest non-ignored pair at q; (inf, "") if none."""
        lower = self._lower_bounds(q)
        lower[self._ignored(ignored)] = np.inf
        best, label = np.inf, ""
        for pair in np.argsort(lower):
            if lower[pair] >= best:
                break
            distance = float(self._distances([pair])[1][0])
            if distance < best:
                best, label = distance, self.labels[pair]
        return best, label

    def penetrations(self, q: np.ndarray, ignored: frozenset = frozenset(),
                     tolerance: float = 0.0) -> list:
        """[(label, distance in m)] of the non-ignored pairs deeper than `tolerance` (m) into
        each other at q (distance < -tolerance), deepest first."""
        lower = self._lower_bounds(q)
        candidates = np.flatnonzero((lower < -tolerance) & ~self._ignored(ignored))
        distances = self._distances(candidates)[1]
        order = np.argsort(distances)
        return [(self.labels[candidates[k]], float(distances[k]))
                for k in order if distances[k] < -tolerance]

    def _lower_bounds(self, q):
        """Distance lower bounds (pairs,) in m at q: the bounding volumes' distances, or
        the last refresh's bounds minus the bodies' motion since, whichever is larger."""
        pin.forwardKinematics(self.robot.model, self.data, q)
        placements = self._place_geometries()
        lower = self._volume_bounds(placements)
        if self._reference is not None:
            np.maximum(lower, self._lower - self._pair_motion(placements)[1], out=lower)
        return lower

    def _place_geometries(self):
        """Geometry placements from the joint placements in self.data; returns the joint
        placements (njoints, 4, 4) in the world."""
        pin.updateGeometryPlacements(self.robot.model, self.data, self.geometry_model,
                                     self.geometry_data)
        return np.array([placement.homogeneous for placement in self.data.oMi])

    def _volume_bounds(self, placements):
        """Distances (m) between the pairs' bounding volumes: lower bounds of theirs."""
        joint = placements[self._robot_joints]
        centres = np.einsum("gij,gj->gi", joint[:, :3, :3], self._centres) + joint[:, :3, 3]
        bounds = np.empty(len(self.pairs))
        bounds[self._self_pairs] = (cdist(centres, centres).take(self._self_flat)
                                    - self._self_radii)
        # Signed distance from each sphere centre to each box: outside part + inside part.
        gaps = np.abs(centres[:, None, :] - self._box_centres) - self._box_extents
        inside = np.minimum(gaps.max(axis=2), 0.0)
        np.maximum(gaps, 0.0, out=gaps)
        signed = np.sqrt(np.einsum("gok,gok->go", gaps, gaps)) + inside
        bounds[self._obstacle_pairs] = signed.take(self._obstacle_flat) - self._obstacle_radii
        return bounds

    def _pair_motion(self, placements):
        """Bound (m) on how much each pair's distance may have shrunk since the refresh: the
        largest displacement of the two bodies' geometry points (|dt| + angle * reach)."""
        reference = self._reference
        shift = placements[:, :3, 3] - reference[:, :3, 3]
        cosine = 0.5 * (np.einsum("jik,jik->j", placements[:, :3, :3], reference[:, :3, :3]) - 1)
        motion = (np.sqrt(np.einsum("jk,jk->j", shift, shift))
                  + np.arccos(np.clip(cosine, -1.0, 1.0)) * self._reach)
        return motion.max(), np.add.outer(motion, motion).take(self._flat_pair_joints)

    def _refresh(self, placements, near):
        """Full pass: bounding-volume bounds of all pairs, exact distances below near +
        margin; returns those pair indices, their results and distances (m)."""
        lower = self._volume_bounds(placements)
        close = np.flatnonzero(lower < near + self.margin)
        results, distances = self._distances(close)
        lower[close] = distances
        self._reference, self._lower, self._near = placements, lower, near
        return close, results, distances

    def _distances(self, pairs):
        """Hull distance results and distances (k,) in m of pair indices `pairs` (geometry
        placements already updated)."""
        results = [pin.computeDistance(self.geometry_model, self.geometry_data, int(k))
                   for k in pairs]
        return results, np.array([r.min_distance for r in results], dtype=float)

    @staticmethod
    def _witnesses(results):
        """Normals (k, 3) from body 1 to body 2 and nearest points on body 1 (k, 3), world
        frame; the nearest point on body 2 is p1 + distance * normal (coal's convention)."""
        if not results:
            return np.zeros((0, 3)), np.zeros((0, 3))
        normals = np.concatenate([r.normal for r in results]).reshape(-1, 3)
        points = np.concatenate([r.getNearestPoint1() for r in results]).reshape(-1, 3)
        return normals, points

    def _ignored(self, ignored):
        """Boolean mask (pairs,) of the ignored pair indices (the last mask is reused)."""
        if ignored != self._ignored_key:
            mask = np.zeros(len(self.pairs), dtype=bool)
            mask[list(ignored)] = True
            self._ignored_key, self._ignored_mask = ignored, mask
        return self._ignored_mask
