"""Independent verification of a contact plan: every stance's witness posture is checked
again from scratch, without the planner's shortcuts.

- Contacts: forward kinematics (pinocchio) puts each spot frame where Contact.spot_target
  says: position error (m), normal error (rad, between the spot's z axes) and theta error
  (rad, rotation about the normal).
- Collisions: the robot's original URDF collision meshes (not convex hulls) against each
  other (pairs the SRDF does not disable) and against the scene obstacles (coal shapes fixed
  to the universe), with pinocchio's computeCollisions. A body in contact (the geometries
  of the spot frame's parent joint) may touch the obstacle its surface lies on.
- Joint limits of the 1-DoF joints (tolerance 1e-6 rad).
- Static equilibrium on the supporting contacts (in_stability True), the spot patches
  placed at their targets and the CoM from the posture: a feasibility LP on the contact
  forces with friction pyramids written as half-spaces, moments about the CoM;
  a formulation independent of stance.planning.equilibrium (generators, moments about the
  origin, a margin), so a bug in one shows as a disagreement with the other.
- One change between consecutive stances (Escande et al. 2008, section 2.2): the
  supporting contacts (in_stability True) of a stance and the next differ by exactly one
  contact, added or removed. Contacts are matched by place: same spot, same surface, same
  (x, y, theta) within 1e-9. Geometric-only contacts (in_stability False: a contact being
  broken, still touched by the witness) come and go freely. A stance has at most one
  contact per spot.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field

import coal
import numpy as np
import pinocchio as pin
from scipy.optimize import linprog

from ..stopping import stop_if_asked
from .equilibrium import GRAVITY
from .scene import placement_problem

JOINT_LIMIT_TOLERANCE = 1e-6   # rad (or m)
SAME_PLACE_TOLERANCE = 1e-9    # m and rad: a contact carried over between stances
OBSTACLE_PREFIX = "obstacle:"  # names of the obstacle geometries in the geometry model


def wrench_feasible(points, frames, frictions, com, mass: float,
                    gravity: float = GRAVITY) -> bool:
    """Whether forces f_i at `points` (M, 3) (m, world) balance the weight m g at `com`.

    frames: (M, 3, 3) contact frame rotations (columns: tangent t1, tangent t2, outward
    normal n); each force stays in the pyramid |t1.f| + |t2.f| <= mu n.f (four half-spaces,
    which imply n.f >= 0). Unknowns: the forces themselves (N); equalities: sum f = m g z
    and sum (p_i - com) x f_i = 0.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        return False
    frames = np.asarray(frames, dtype=float).reshape(-1, 3, 3)
    frictions = np.broadcast_to(np.asarray(frictions, dtype=float), (len(points),))
    count = len(points)
    equalities = np.zeros((6, 3 * count))
    inequalities = np.zeros((4 * count, 3 * count))
    for i in range(count):
        lever = points[i] - np.asarray(com, dtype=float)
        equalities[:3, 3 * i:3 * i + 3] = np.eye(3)
        equalities[3:, 3 * i:3 * i + 3] = pin.skew(lever)
        t1, t2, normal = frames[i].T
        for row, (s1, s2) in enumerate(((1, 1), (1, -1), (-1, 1), (-1, -1))):
            inequalities[4 * i + row, 3 * i:3 * i + 3] = s1 * t1 + s2 * t2 - frictions[i] * normal
    weight = np.array([0.0, 0.0, mass * gravity, 0.0, 0.0, 0.0])
    result = linprog(np.zeros(3 * count), A_ub=inequalities, b_ub=np.zeros(4 * count),
                     A_eq=equalities, b_eq=weight, bounds=[(None, None)] * (3 * count),
                     method="highs")
    return result.status == 0


def robot_asset_paths(spec: str) -> tuple:
    """(package directories, SRDF path or None) of a robot spec: an example-robot-data name
    or a URDF path (its directory and the two above it serve as package directories)."""
    if spec.endswith(".urdf") or os.path.sep in spec:
        folder = os.path.dirname(os.path.abspath(spec))
        return [folder, os.path.dirname(folder), os.path.dirname(os.path.dirname(folder))], None
    import example_robot_data as erd

    loader = erd.ROBOTS[spec]
    root = erd.getModelPath(os.path.join(loader.path, loader.urdf_subpath, loader.urdf_filename))
    srdf = None
    if loader.srdf_filename:
        srdf = os.path.join(root, loader.path, loader.srdf_subpath, loader.srdf_filename)
    # URDFs refer to package://example-robot-data/robots/... or package://<robot>_data/...
    return [os.path.dirname(os.path.dirname(root)), root], srdf


def _obstacle_geometry(obstacle):
    if obstacle.shape == "box":
        return coal.Box(*np.asarray(obstacle.size, dtype=float))
    if obstacle.shape == "mesh":
        return coal.MeshLoader().load(obstacle.mesh, np.asarray(obstacle.scale, dtype=float))
    raise ValueError(f"obstacle {obstacle.name!r}: unknown shape {obstacle.shape!r}")


class MeshCollisions:
    """Robot self-collisions (SRDF pairs) and robot-obstacle collisions on the URDF's
    collision geometries; obstacles are fixed to the universe joint."""

    def __init__(self, robot, scene, robot_spec: str | None = None):
        self.model = robot.model
        package_dirs, srdf = robot_asset_paths(robot_spec or scene.robot)
        self.geometry = pin.buildGeomFromUrdfString(robot.model, robot.urdf, pin.COLLISION,
                                                    package_dirs=package_dirs)
        self.geometry.addAllCollisionPairs()
        if srdf:
            pin.removeCollisionPairs(robot.model, self.geometry, srdf)
        robot_geometries = range(self.geometry.ngeoms)
        self.obstacle_of_geometry = {}
        for obstacle in scene.obstacles.values():
            index = self.geometry.addGeometryObject(pin.GeometryObject(
                OBSTACLE_PREFIX + obstacle.name, 0, 0, obstacle.pose, _obstacle_geometry(obstacle)))
            self.obstacle_of_geometry[index] = obstacle.name
            for robot_index in robot_geometries:
                self.geometry.addCollisionPair(pin.CollisionPair(robot_index, index))
        self.data = self.model.createData()
        self.geometry_data = self.geometry.createData()

    def colliding_pairs(self, q, allowed=frozenset()) -> list:
        """Colliding pairs at q as (name, name, penetration depth m); `allowed` holds
        (parent joint id, obstacle name) touches that do not count."""
        pin.computeCollisions(self.model, self.data, self.geometry, self.geometry_data, q, False)
        found = []
        for pair, result in zip(self.geometry.collisionPairs, self.geometry_data.collisionResults):
            if not result.isCollision():
                continue
            first, second = (self.geometry.geometryObjects[i] for i in (pair.first, pair.second))
            obstacle = self.obstacle_of_geometry.get(pair.second)
            if obstacle is not None and (first.parentJoint, obstacle) in allowed:
                continue
            depth = result.getContact(0).penetration_depth if result.numContacts() else math.nan
            found.append((first.name, second.name, abs(float(depth))))
        return found


@dataclass
class ContactError:
    """How far the spot frame is from its contact target: position (m), normal and theta
    (rad)."""

    contact: object
    position: float
    normal: float
    theta: float


@dataclass
class StanceReport:
    """Checks of one stance; `failures` is empty when it passes."""

    index: int
    contact_errors: list = field(default_factory=list)
    collisions: list = field(default_factory=list)        # (name, name, depth m)
    limit_violations: dict = field(default_factory=dict)  # joint name -> excess (rad or m)
    equilibrium: bool = False
    com: np.ndarray | None = None                          # world (m)
    transition: str = ""                                   # change from the previous stance
    failures: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failures


@dataclass
class PlanReport:
    stances: list
    failures: list      # "stance k: ..." and plan-level messages

    @property
    def ok(self) -> bool:
        return not self.failures


def _contact_name(contact) -> str:
    role = "" if contact.in_stability else " (geometric)"
    return f"{contact.spot}@{contact.surface}{role}"


def _same_place(a, b) -> bool:
    turn = math.remainder(a.theta - b.theta, 2.0 * math.pi)
    return (a.spot == b.spot and a.surface == b.surface and abs(a.x - b.x) <= SAME_PLACE_TOLERANCE
            and abs(a.y - b.y) <= SAME_PLACE_TOLERANCE and abs(turn) <= SAME_PLACE_TOLERANCE)


def stance_transition(previous, current) -> tuple:
    """(ok, description) of the change between two contact tuples: the supporting contacts
    (in_stability) must differ by exactly one contact, added or removed (Escande et al.,
    section 2.2); geometric-only contacts (being broken) come and go with them."""
    before = [c for c in previous if c.in_stability]
    unmatched = list(before)
    added = []
    for contact in (c for c in current if c.in_stability):
        match = next((old for old in unmatched if _same_place(old, contact)), None)
        if match is None:
            added.append(contact)
        else:
            unmatched.remove(match)
    changes = ([f"adds {_contact_name(c)}" for c in added]
               + [f"removes {_contact_name(c)}" for c in unmatched])
    if not changes:
        return False, "no change of the supporting contacts"
    return len(changes) == 1, ", ".join(changes)


class PlanVerifier:
    """Checks stances of plans in one scene for one robot (models built once)."""

    def __init__(self, scene, robot, robot_spec: str | None = None,
                 contact_tolerance: float = 0.001, angle_tolerance: float = math.radians(1.0)):
        self.scene = scene
        self.robot = robot
        self.contact_tolerance = contact_tolerance
        self.angle_tolerance = angle_tolerance
        self.collisions = MeshCollisions(robot, scene, robot_spec)
        self.data = robot.model.createData()
        self.mass = pin.computeTotalMass(robot.model)

    def _contact_error(self, contact) -> tuple:
        """(ContactError, patch vertices at the target in the world (M, 3), contact frame
        rotation)."""
        spot = self.scene.spots[contact.spot]
        surface = self.scene.surfaces[contact.surface]
        placed = self.data.oMf[self.robot.frame_id(spot.frame)] * spot.placement
        target = contact.spot_target(surface)
        x_in_target = target.rotation.T @ placed.rotation[:, 0]
        error = ContactError(
            contact, float(np.linalg.norm(placed.translation - target.translation)),
            float(np.arccos(np.clip(placed.rotation[:, 2] @ target.rotation[:, 2], -1.0, 1.0))),
            abs(math.atan2(x_in_target[1], x_in_target[0])))
        patch = np.asarray(spot.patch, dtype=float)
        vertices = patch @ target.rotation[:, :2].T + target.translation
        return error, vertices, contact.contact_frame(surface).rotation

    def _unknown_frames(self, stance) -> list:
        """A failure per contact whose spot (known to the scene) names a frame the robot
        lacks."""
        frames = {contact.spot: self.scene.spots[contact.spot].frame
                  for contact in stance.contacts}
        return [f"spot {spot!r}: unknown frame {frame!r}" for spot, frame in frames.items()
                if not self.robot.model.existFrame(frame)]

    def check_stance(self, index: int, stance, previous=None) -> StanceReport:
        report = StanceReport(index)
        model = self.robot.model
        failures = report.failures
        if previous is not None:
            changed_once, report.transition = stance_transition(previous.contacts, stance.contacts)
            if not changed_once:
                failures.append(f"not one contact change from the previous stance: "
                                f"{report.transition}")
        q = np.asarray(stance.q, dtype=float)
        if q.shape != (model.nq,):
            failures.append(f"configuration of shape {q.shape}, the robot needs ({model.nq},)")
            return report
        if not np.isfinite(q).all():
            failures.append("configuration not finite")
            return report
        misplaced = [(contact, placement_problem(self.scene.surfaces, self.scene.spots,
                                                 contact)) for contact in stance.contacts]
        failures += [f"{_contact_name(contact)}: {problem[1]}"
                     for contact, problem in misplaced if problem]
        if any(problem for _, problem in misplaced):
            return report
        unknown = self._unknown_frames(stance)
        if unknown:
            failures += unknown
            return report
        spots = [contact.spot for contact in stance.contacts]
        failures += [f"spot {name!r} in {spots.count(name)} contacts"
                     for name in sorted(set(spots)) if spots.count(name) > 1]
        if self.robot.floating_base and abs(np.linalg.norm(q[3:7]) - 1.0) > 1e-6:
            failures.append("base quaternion is not unit")
        pin.framesForwardKinematics(model, self.data, q)
        support_points, support_frames, support_frictions = [], [], []
        allowed = set()
        for contact in stance.contacts:
            error, vertices, frame = self._contact_error(contact)
            report.contact_errors.append(error)
            name = _contact_name(contact)
            if error.position > self.contact_tolerance:
                failures.append(f"{name}: spot {1000 * error.position:.1f} mm from its target")
            if max(error.normal, error.theta) > self.angle_tolerance:
                failures.append(f"{name}: spot turned {math.degrees(error.normal):.2f} deg off "
                                f"the normal, {math.degrees(error.theta):.2f} deg in theta")
            surface = self.scene.surfaces[contact.surface]
            spot_joint = model.frames[self.robot.frame_id(self.scene.spots[contact.spot].frame)]
            if surface.obstacle is not None:
                allowed.add((spot_joint.parentJoint, surface.obstacle))
            if contact.in_stability:
                support_points.append(vertices)
                support_frames += [frame] * len(vertices)
                support_frictions += [surface.friction] * len(vertices)
        report.collisions = self.collisions.colliding_pairs(q, frozenset(allowed))
        failures += [f"collision {a} - {b} ({1000 * depth:.1f} mm deep)"
                     for a, b, depth in report.collisions]
        excess = np.maximum(self.robot.lower - q[self.robot.limited_q_index],
                            q[self.robot.limited_q_index] - self.robot.upper)
        report.limit_violations = {
            self.robot.limited_joint_names[i]: float(excess[i])
            for i in np.flatnonzero(excess > JOINT_LIMIT_TOLERANCE)}
        failures += [f"joint {name} {value:.4f} beyond its limit"
                     for name, value in report.limit_violations.items()]
        report.com = pin.centerOfMass(model, self.data, q).copy()
        report.equilibrium = bool(support_points) and wrench_feasible(
            np.vstack(support_points), np.array(support_frames), np.array(support_frictions),
            report.com, self.mass)
        if not report.equilibrium:
            failures.append("no static equilibrium on the supporting contacts "
                            f"(CoM at {np.round(report.com, 3).tolist()})")
        return report

    def verify(self, plan, should_stop=None) -> PlanReport:
        """Every stance checked; stopping.Stopped once should_stop (a callable, asked before
        each stance: ~10 ms of work on Talos) answers True."""
        failures = []
        if not plan.stances:
            failures.append("the plan has no stance")
        if plan.robot != self.scene.robot:
            failures.append(f"plan robot {plan.robot!r} differs from the scene's "
                            f"{self.scene.robot!r}")
        reports = []
        for index, stance in enumerate(plan.stances):
            stop_if_asked(should_stop, f"verification stopped at stance {index}")
            reports.append(self.check_stance(
                index, stance, plan.stances[index - 1] if index else None))
            failures += [f"stance {index}: {failure}" for failure in reports[-1].failures]
        return PlanReport(reports, failures)


def verify_plan(plan, scene, robot, contact_tolerance: float = 0.001,
                angle_tolerance: float = math.radians(1.0), should_stop=None) -> PlanReport:
    """Check every stance of `plan` in `scene` (see the module docstring); tolerances in m
    and rad; should_stop: PlanVerifier.verify's."""
    verifier = PlanVerifier(scene, robot, scene.robot, contact_tolerance, angle_tolerance)
    return verifier.verify(plan, should_stop)
