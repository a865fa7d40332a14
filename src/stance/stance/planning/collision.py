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

Near pairs (constraint_rows): every pair keeps a certified lower bound of its distance from
the last call (its exact hull distance if it was computed then, else a bound), lowered by
how far the pair's two bodies may have moved relative to each other since (|dt| + rotation
angle * reach of the moving geometries about their joint origin, measured in the other
body's frame: a self pair's bound survives a motion of the whole robot) and raised to the
bounding volumes' signed distance (a sphere about each robot geometry, the world AABB of
each obstacle). Only the non-ignored pairs whose bound is below near + margin get an exact
distance, so no near pair is missed whatever the step, and a pair far from everything is
not recomputed at each call. min_distance and penetrations use the same bounds to skip far
pairs.

Measured cost (chair_table scene: Talos, 12 obstacles, 1511 pairs in 333 joint pairs;
the 6,572 constraint_rows calls of the first 30 nodes of its search replayed, near = 5 cm,
about 40 rows and 65 exact distances per call; one BLAS thread; mean CPU time per call,
both versions in one run, machine shared with other jobs): 0.68 ms, against 1.07 ms for
the earlier policy (a full pass whenever some body had moved by 25 mm, which during a
posture search was two calls in three). One exact hull distance costs 4 to 5 us; the
bounds of all pairs cost about 40 us (numba).
"""

from __future__ import annotations

import math
import os

import coal
import numba
import numpy as np
import pinocchio as pin

# Convex hulls by (mesh path, scale): building one costs about 1 ms per mesh.
_HULLS: dict = {}

# GJK / EPA tolerances (m): gradients then match central differences to 1e-5 also in
# deep penetration (EPA at 1e-9 left 2e-4); no measurable cost on hulls.
_GJK_TOLERANCE = 1e-9
_EPA_TOLERANCE = 1e-12
# A fresh request's GJK warm start (search direction, support vertex indices): what
# CollisionModel.forget puts back.
_COLD_GUESS = np.array([1.0, 0.0, 0.0])
_COLD_SUPPORT = np.zeros(2, dtype=np.int32)


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


class CollisionModel:
    """Signed distances and their gradients between the robot's bodies and the obstacles.

    robot: stance.robot.Robot; scene: stance.planning.scene.Scene (its `robot` spec names
    the example-robot-data robot whose meshes and SRDF are used unless package_dirs and
    srdf_path are given). margin (m): pairs whose distance bound is below near + margin get
    an exact distance (module docstring).
    """

    def __init__(self, robot, scene, self_collision: bool = True,
                 package_dirs: list | None = None, srdf_path: str | None = None,
                 margin: float = 0.02):
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
        self._reference = None      # relative placements of the joint pairs at the last call
        self._lower = None          # certified distance lower bounds (pairs,) at that call
        self._ignored_key, self._ignored_mask = None, np.zeros(len(self.pairs), dtype=bool)
        self._warm = np.zeros(len(self.pairs), dtype=bool)  # pairs with a GJK warm start

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
        # Per pair: the robot geometry, the other robot geometry or the obstacle (index
        # among the obstacles), whether it is an obstacle, the spheres' radii summed.
        self._pair_obstacle = second >= robot_geometries
        self._pair_other = np.where(self._pair_obstacle, second - robot_geometries, second)
        self._pair_radius = radii[first].copy()
        robot_pairs = ~self._pair_obstacle
        self._pair_radius[robot_pairs] += radii[second[robot_pairs]]
        reach = np.zeros(self.robot.model.njoints)    # farthest geometry point from a joint (m)
        np.maximum.at(reach, self._robot_joints, np.linalg.norm(self._centres, axis=1) + radii)
        # The pairs' distinct (moving joint, frame joint): the first geometry's joint moves
        # in the second's frame (the universe for obstacles).
        joint_pairs, pair_to_joint_pair = np.unique(self.pair_joints, axis=0, return_inverse=True)
        self._joint_pairs, self._pair_to_joint_pair = joint_pairs, pair_to_joint_pair.reshape(-1)
        self._moving_reach = reach[self._joint_pairs[:, 0]]

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
        lower, relative = self._lower_bounds()
        candidates = np.flatnonzero((lower < near + self.margin) & ~self._ignored(ignored))
        results, distances = self._distances(candidates)
        lower[candidates] = distances
        self._reference, self._lower = relative, lower
        close = np.flatnonzero(distances < near)
        pairs = candidates[close]
        normals, points = self._witnesses([results[k] for k in close])
        gradients = _distance_gradients(normals, points, self.pair_joints[pairs],
                                        self._support, self.data.J)
        return distances[close], gradients, [self.labels[k] for k in pairs]

    def min_distance(self, q: np.ndarray, ignored: frozenset = frozenset()) -> tuple:
        """(distance in m, label) of the closest non-ignored pair at q; (inf, "") if none."""
        pin.forwardKinematics(self.robot.model, self.data, q)
        lower = self._lower_bounds()[0]
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
        pin.forwardKinematics(self.robot.model, self.data, q)
        lower = self._lower_bounds()[0]
        candidates = np.flatnonzero((lower < -tolerance) & ~self._ignored(ignored))
        distances = self._distances(candidates)[1]
        order = np.argsort(distances)
        return [(self.labels[candidates[k]], float(distances[k]))
                for k in order if distances[k] < -tolerance]

    def forget(self) -> None:
        """Drop what earlier calls left behind: the distance bounds and every pair's GJK
        warm start (Pinocchio's requests keep the last call's guesses, so a distance
        depends on the pair's history to rounding). The calls that follow then give what a
        fresh model would: a posture search that starts with forget() does not depend on
        what this model computed before."""
        self._reference = self._lower = None
        requests = self.geometry_data.distanceRequests
        for pair in np.flatnonzero(self._warm):
            request = requests[int(pair)]
            request.cached_gjk_guess = _COLD_GUESS
            request.cached_support_func_guess = _COLD_SUPPORT
        self._warm[:] = False

    def _lower_bounds(self):
        """Distance lower bounds (pairs,) in m at the joint placements of self.data: the
        bounding volumes' distances, or the last call's bounds minus the pairs' relative
        motion since, whichever is larger; and the joint pairs' relative placements."""
        pin.updateGeometryPlacements(self.robot.model, self.data, self.geometry_model,
                                     self.geometry_data)
        # tolist: one conversion of the vector, not one Python access per joint (2/3 the cost)
        placements = np.array([placement.homogeneous for placement in self.data.oMi.tolist()])
        if self._reference is None:
            previous, reference = np.zeros(0), (np.zeros((0, 3, 3)), np.zeros((0, 3)))
        else:
            previous, reference = self._lower, self._reference
        lower, rotations, translations = _pair_bounds(
            placements, self._robot_joints, self._centres, self.pairs[:, 0], self._pair_other,
            self._pair_obstacle, self._pair_radius, self._box_centres, self._box_extents,
            self._joint_pairs, self._moving_reach, self._pair_to_joint_pair, previous,
            *reference)
        return lower, (rotations, translations)

    def _distances(self, pairs):
        """Hull distance results and distances (k,) in m of pair indices `pairs` (geometry
        placements already updated)."""
        self._warm[pairs] = True
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


@numba.njit(cache=True)
def _distance_gradients(normals, points, joints, support, jacobian):
    """Rows (k, nv) d' = [n, p x n] J dq of k pairs (module docstring): normals (k, 3) and
    nearest points p (k, 3) on body 1, world frame; joints (k, 2) the bodies' joints;
    jacobian (6, nv) the joints' stacked WORLD Jacobian columns; support[j] (njoints, nv) 1
    on the columns that move joint j. A column moving both bodies (or neither) gives 0."""
    rows = np.empty((len(normals), jacobian.shape[1]))
    for k in range(len(normals)):
        n0, n1, n2 = normals[k, 0], normals[k, 1], normals[k, 2]
        p0, p1, p2 = points[k, 0], points[k, 1], points[k, 2]
        c0, c1, c2 = p1 * n2 - p2 * n1, p2 * n0 - p0 * n2, p0 * n1 - p1 * n0
        first, second = joints[k, 0], joints[k, 1]
        for j in range(jacobian.shape[1]):
            sign = support[second, j] - support[first, j]
            rows[k, j] = 0.0 if sign == 0.0 else sign * (
                n0 * jacobian[0, j] + n1 * jacobian[1, j] + n2 * jacobian[2, j]
                + c0 * jacobian[3, j] + c1 * jacobian[4, j] + c2 * jacobian[5, j])
    return rows


@numba.njit(cache=True)
def _pair_bounds(placements, robot_joints, centres, pair_robot, pair_other, pair_obstacle,
                 pair_radius, box_centres, box_extents, joint_pairs, moving_reach,
                 pair_to_joint_pair, previous, reference_rotations, reference_translations):
    """Certified distance lower bounds (pairs,) in m, and the joint pairs' relative
    placements (rotations (k, 3, 3), translations (k, 3) of the moving joint in the frame
    joint). placements: joint placements (njoints, 4, 4), world. A bound is the bounding
    volumes' signed distance (sphere to sphere, sphere to the obstacle's box), or, when
    previous bounds are given (else an empty array), previous minus the pair's motion since
    the reference placements (|dt| + angle * reach), whichever is larger."""
    world = np.empty((len(centres), 3))
    for g in range(len(centres)):
        joint = placements[robot_joints[g]]
        for i in range(3):
            world[g, i] = joint[i, 3] + joint[i, 0] * centres[g, 0] + \
                joint[i, 1] * centres[g, 1] + joint[i, 2] * centres[g, 2]
    count = len(joint_pairs)
    rotations, translations = np.empty((count, 3, 3)), np.empty((count, 3))
    motion = np.zeros(count)
    for k in range(count):
        moving, frame = placements[joint_pairs[k, 0]], placements[joint_pairs[k, 1]]
        for i in range(3):
            translations[k, i] = frame[0, i] * (moving[0, 3] - frame[0, 3]) + \
                frame[1, i] * (moving[1, 3] - frame[1, 3]) + \
                frame[2, i] * (moving[2, 3] - frame[2, 3])
            for j in range(3):
                rotations[k, i, j] = frame[0, i] * moving[0, j] + frame[1, i] * moving[1, j] + \
                    frame[2, i] * moving[2, j]
        if len(previous):
            shift = trace = 0.0
            for i in range(3):
                shift += (translations[k, i] - reference_translations[k, i]) ** 2
                for j in range(3):
                    trace += rotations[k, i, j] * reference_rotations[k, i, j]
            cosine = min(max(0.5 * (trace - 1.0), -1.0), 1.0)
            motion[k] = math.sqrt(shift) + math.acos(cosine) * moving_reach[k]
    lower = np.empty(len(pair_robot))
    for p in range(len(pair_robot)):
        centre = world[pair_robot[p]]
        if pair_obstacle[p]:
            # signed distance from the sphere centre to the box: outside part + inside part
            outside = 0.0
            inside = -np.inf
            for i in range(3):
                gap = abs(centre[i] - box_centres[pair_other[p], i]) - \
                    box_extents[pair_other[p], i]
                inside = max(inside, gap)
                outside += max(gap, 0.0) ** 2
            distance = math.sqrt(outside) + min(inside, 0.0)
        else:
            other = world[pair_other[p]]
            distance = math.sqrt((centre[0] - other[0]) ** 2 + (centre[1] - other[1]) ** 2
                                 + (centre[2] - other[2]) ** 2)
        lower[p] = distance - pair_radius[p]
        if len(previous):
            lower[p] = max(lower[p], previous[p] - motion[pair_to_joint_pair[p]])
    return lower, rotations, translations
