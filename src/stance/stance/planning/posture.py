"""Posture generator (Escande et al. 2008, section 2.2): a configuration that realises a set
of contacts, free of collisions, inside the joint limits and statically stable, optimising a
criterion (distance to a reference posture, or the potential f_T of the rough trajectory).

Each iteration linearises everything at the current configuration q and solves one QP
(DAQP by default, ProxSuite with `qp_backend`) in x = [dq (nv), dv (3 if a contact is being
placed)]:

    minimise   w_c |J_c dq - B dv - e_c|^2        contacts (spot frames on their targets)
             + criterion(dq) + damping |dq|^2
    subject to joint limits and a trust region on dq, collision rows d + G dq >= margin,
               the search volume A (v + dv) <= b,
               CoM rows A_s (c + J_com dq)_xy <= b_s - margin

Static stability is a region of the CoM's horizontal position, fixed for one call since the
supporting contacts are: the support polygon for coplanar horizontal contacts, else the
static equilibrium region (forces in friction cones balancing gravity; Bretl and Lall),
computed by LPs once per support set. Contacts are heavy quadratic penalties rather than
equalities, so no QP is ever infeasible (linearised equalities with a trust region can be);
the final posture is accepted only when every requirement holds exactly: contact errors
below `contact_tolerance`, no collision (with half the margin), joint limits, and static
stability (support polygon, or the static equilibrium LP at the final CoM).

Stability follows the paper (section 2.3): only contacts with `in_stability` support the
robot; the others (a contact being broken, or a new one) are geometric constraints only.

Frames: world frame, m, rad. Contact rows are world-aligned at the spot frame's origin
(Pinocchio LOCAL_WORLD_ALIGNED); dq is Pinocchio's tangent (q' = integrate(q, dq)).
"""

from __future__ import annotations

import collections
import math
import time
from dataclasses import dataclass, field

import daqp
import numpy as np
import pinocchio as pin
from proxsuite import proxqp
from scipy.spatial import ConvexHull, QhullError

from ..robot import Robot
from ..stack import TaskSpec
from ..tasks import PoseTask
from .contacts import Contact

from .equilibrium import are_coplanar, contact_vertices, contacts_equilibrium, \
    friction_cone_generators, support_polygon

GRAVITY = 9.81  # m/s^2
# A guide (a contact of weight < 1) has settled when its error (m or rad) shrank by less than
# GUIDE_PROGRESS over the last GUIDE_WINDOW iterations.
GUIDE_PROGRESS = 1e-4
GUIDE_WINDOW = 3
# The iteration is cycling when a step returns q closer than CYCLE_RETURN times its length to
# the iterate of CYCLE_PERIODS iterations ago while the contact error stays above
# CYCLE_PROGRESS of its value then (PostureGenerator._cycling).
CYCLE_PERIODS = (2, 3)
CYCLE_RETURN = 0.05
CYCLE_PROGRESS = 0.99


@dataclass
class PostureSettings:
    """Tuning of the posture generator (units in each comment)."""

    max_iterations: int = 60
    contact_weight: float = 1e4          # per (m or rad)^2 of contact error
    damping: float = 1e-2                # per rad^2 (or m^2) of dq
    criterion_weight: float = 1.0        # scales the criterion's quadratic model
    trust_joint: float = 0.25            # rad: largest |dq| of a joint per iteration
    trust_base: float = 0.25             # m or rad: largest |dq| of the base per iteration
    collision_margin: float = 0.005      # m: clearance required between bodies
    collision_near: float = 0.05         # m: pairs closer than this enter the QP
    collision_push: float = 0.02         # m: largest clearance gain asked per iteration
    com_margin: float = 0.01             # m: CoM inside the support polygon by this much
    contact_tolerance: float = 1e-4      # m (and rad): contact error accepted as matched
    converged_step: float = 1e-2         # |dq| below which the iteration has converged
    stall_window: int = 10              # iterations: give up when the contact error does not
                                         # halve over this many (see _stalled)
    time_budget: float = 0.5             # s per call
    qp_backend: str = "daqp"             # "daqp" or "proxsuite" (see stance bench plan)


@dataclass
class FreeContact:
    """A contact being placed: spot on surface with (x, y, theta) searched in `volume`
    (stance.planning.volumes.SearchVolume); geometric only (not in stability)."""

    spot: str
    surface: str
    volume: object


@dataclass
class PostureResult:
    success: bool
    q: np.ndarray
    contacts: tuple                    # the requested contacts, the placed one appended
    reason: str = ""                   # why it failed ("" on success)
    iterations: int = 0
    seconds: float = 0.0               # wall time of the call
    criterion: float = float("nan")    # criterion value at q
    details: dict = field(default_factory=dict)
    cpu_seconds: float = 0.0           # CPU time of the call (its thread)


class ReferencePosture:
    """Criterion: weight * |difference(q_ref, q)|^2 over all DoFs (base included)."""

    def __init__(self, model, q_reference: np.ndarray, weight: float = 1e-2):
        self.model, self.q_reference, self.weight = model, np.asarray(q_reference), weight

    def quadratic(self, q):
        """(Hessian diagonal (nv), gradient (nv), value) of the criterion at q for dq."""
        residual = pin.difference(self.model, self.q_reference, q)
        return (np.full(self.model.nv, 2.0 * self.weight), 2.0 * self.weight * residual,
                self.weight * float(residual @ residual))


class PotentialCriterion:
    """Criterion: weight * f_T(q) (paper eq. 1): its exact gradient, and the Hessian 2 I of
    the valley term |difference(Q, q)|^2 with Q held fixed (Gauss-Newton)."""

    def __init__(self, trajectory, weight: float = 1e-2):
        self.trajectory, self.weight = trajectory, weight

    def quadratic(self, q):
        value = self.trajectory.evaluate(q)
        return (np.full(len(value.residual), 2.0 * self.weight), self.weight * value.gradient,
                self.weight * value.value)


class PostureGenerator:
    """Finds postures for sets of contacts in one scene (see module docstring).

    robot: stance.robot.Robot; scene: stance.planning.scene.Scene; collision: a
    stance.planning.collision.CollisionModel for the same robot and scene, or None to
    ignore collisions.
    """

    def __init__(self, robot: Robot, scene, collision=None,
                 settings: PostureSettings | None = None):
        self.scene, self.collision = scene, collision
        self.settings = settings or PostureSettings()
        model = pin.Model(robot.model)
        for spot in scene.spots.values():
            parent = model.frames[robot.frame_id(spot.frame)]
            model.addFrame(pin.Frame(f"spot:{spot.name}", parent.parentJoint,
                                     parent.placement * spot.placement, pin.OP_FRAME))
        self.robot = Robot(model=model, urdf=robot.urdf, floating_base=robot.floating_base,
                           reference_configurations=robot.reference_configurations)
        self.model, self.data = self.robot.model, self.robot.data
        self.mass = float(pin.computeTotalMass(self.model))
        self.weight = self.mass * GRAVITY
        self._spot_tasks = {name: PoseTask(TaskSpec(name=f"spot_{i}", kind="pose",
                                                    frame=f"spot:{name}"), self.robot)
                            for i, name in enumerate(scene.spots)}
        limited = self.robot.limited_v_index
        self._limited_v, self._limited_q = limited, self.robot.limited_q_index
        self._base_nv = self.robot.base_nv
        self._locked_v = self.robot.velocity_indices(scene.locked_joints)
        self._regions = {}
        self.calls = 0

    # ----------------------------------------------------------------- public API
    def chain_dofs(self, spot_a: str, spot_b: str) -> float:
        """Unlocked DoFs of the joints between two spots when one lies on the other's
        kinematic branch (a sole and the thigh above it: knee and ankle, 3), inf when they
        are on different branches. Fewer than 6: neither spot can take an arbitrary pose
        while the other is held."""
        joint_a, joint_b = (self.model.frames[self.model.getFrameId(f"spot:{spot}")].parentJoint
                            for spot in (spot_a, spot_b))
        upper, lower = sorted((joint_a, joint_b), key=lambda j: len(self.model.supports[j]))
        branch = list(self.model.supports[lower])
        if upper not in branch:
            return math.inf
        locked = set(self.scene.locked_joints)
        return sum(self.model.joints[j].nv for j in branch[branch.index(upper) + 1:]
                   if self.model.names[j] not in locked)

    def generate(self, contacts, q_init: np.ndarray, criterion, free: FreeContact | None = None,
                 time_budget: float | None = None) -> PostureResult:
        """Search a posture for `contacts` (plus `free` being placed) from q_init.

        A contact may carry a `tolerance` (m and rad): the error accepted for it when larger
        than settings.contact_tolerance, and a `weight` below 1: then it is a guide (the
        interpolation's paths), scaled by the weight and acting only in the nullspace of the
        other contacts. A contact whose surface is None touches nothing (no collision
        ignored); one with `position_only` true is held in position only (orientation free)."""
        start, cpu_start = time.perf_counter(), time.thread_time()
        budget = self.settings.time_budget if time_budget is None else time_budget
        self.calls += 1
        if self.collision is not None:
            self.collision.forget()   # a posture that depends on its inputs only
        contacts = tuple(contacts)
        support = [c for c in contacts if c.in_stability]
        if not support:
            return PostureResult(False, q_init, contacts, "no supporting contact")
        if not np.isfinite(q_init).all():
            return PostureResult(False, q_init, contacts, "start configuration not finite")
        q = self._clip_to_limits(np.array(q_init, dtype=float))
        for contact in contacts:
            self._spot_tasks[contact.spot].target = contact.spot_target(
                self.scene.surfaces.get(contact.surface))
        stability = self._stability_model(support)
        ignored = self._ignored_pairs(contacts, free)
        v = self._initial_free_parameters(q, free) if free else None
        deadline = start + budget
        q, v, iterations = self._descend(q, contacts, free, v, stability, criterion, ignored,
                                         deadline)
        final = contacts if free is None else contacts + (self._free_contact(free, v),)
        reason, details = self._acceptance(q, final, support, ignored)
        guides = tuple(c for c in contacts if getattr(c, "weight", 1.0) < 1.0)
        if reason and guides:
            # the guides' pull held a contact off (through an active bound): settle the
            # contacts alone from here, by the smallest motion (no criterion), then check
            # the guides where they stayed
            held = tuple(c for c in contacts if c not in guides)
            q, v, more = self._descend(q, held, free, v, stability, None, ignored, deadline)
            iterations += more
            final = contacts if free is None else contacts + (self._free_contact(free, v),)
            reason, details = self._acceptance(q, final, support, ignored)
        value = criterion.quadratic(q)[2] if criterion is not None else float("nan")
        return PostureResult(reason == "", q, final, reason, iterations,
                             time.perf_counter() - start, value, details,
                             time.thread_time() - cpu_start)

    def _descend(self, q, contacts, free, v, stability, criterion, ignored, deadline):
        """Iterate from q until converged, stalled, cycling, max_iterations or the deadline
        (perf_counter s); returns (q, v, iterations). Converged: the contacts within their
        tolerance and the step below converged_step (the contacts are quadratic penalties
        balanced against the criterion, so the error can settle on a floor inside the
        tolerance), or the contacts within half their tolerance and the guides no longer
        approaching their targets (by GUIDE_PROGRESS over GUIDE_WINDOW iterations)."""
        iterations = 0
        errors, guide_errors = [], []
        iterates = collections.deque(maxlen=CYCLE_PERIODS[-1])  # the last iterates
        tolerance = self.settings.contact_tolerance
        for iterations in range(1, self.settings.max_iterations + 1):
            if time.perf_counter() > deadline:
                break
            dq, dv, contact_error, guide_error = self._iterate(q, contacts, free, v, stability,
                                                               criterion, ignored)
            errors.append(contact_error)
            guide_errors.append(guide_error)
            iterates.append(q)
            q = self._clip_to_limits(pin.integrate(self.model, q, dq))
            if free is not None:
                v = v + dv
            step = math.sqrt(dq @ dq + (dv @ dv if dv is not None else 0.0))
            guides_settled = len(guide_errors) > GUIDE_WINDOW and \
                guide_errors[-1 - GUIDE_WINDOW] - guide_errors[-1] < GUIDE_PROGRESS
            if contact_error < tolerance and step < self.settings.converged_step or \
                    contact_error < 0.5 * tolerance and guides_settled:
                break
            if self._stalled(errors) or self._cycling(iterates, q, step, errors):
                break
        return q, v, iterations

    def _stalled(self, errors) -> bool:
        """The contact error (m or rad) has not halved over the last stall_window iterations
        while still far from the tolerance: the contacts are out of reach."""
        window = self.settings.stall_window
        if len(errors) <= window or errors[-1] < 100 * self.settings.contact_tolerance:
            return False
        return errors[-1] > 0.5 * errors[-1 - window]

    def _cycling(self, iterates, q, step, errors) -> bool:
        """The last step brought q back near the iterate of two or three iterations ago
        (closer than CYCLE_RETURN times the step's length, tangent norm) and the contact
        error did not fall below CYCLE_PROGRESS of its value then: the linearised steps
        cycle through two or three configurations (e.g. sets of active collision rows),
        and more iterations would repeat them. iterates: the last CYCLE_PERIODS[-1]
        iterates, oldest first."""
        for period in CYCLE_PERIODS:
            if len(iterates) < period or len(errors) <= period or \
                    errors[-1] < CYCLE_PROGRESS * errors[-1 - period]:
                continue
            back = pin.difference(self.model, iterates[-period], q)
            if math.sqrt(back @ back) < CYCLE_RETURN * step:
                return True
        return False

    # ----------------------------------------------------------------- model pieces
    def _kinematics(self, q):
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        pin.jacobianCenterOfMass(self.model, self.data, q, False)

    def _clip_to_limits(self, q):
        q[self._limited_q] = np.clip(q[self._limited_q], self.robot.lower, self.robot.upper)
        return q

    def _stability_model(self, support):
        """(A, b): the CoM's world xy is statically stable where A c_xy <= b. Coplanar
        horizontal support: its support polygon; otherwise the static equilibrium region
        (cached per support set)."""
        key = tuple(sorted(support, key=lambda c: c.pair))
        if key not in self._regions:
            surfaces = self.scene.surfaces
            horizontal = all(surfaces[c.surface].pose.rotation[2, 2]
                             > math.cos(math.radians(2)) for c in support)
            if horizontal and are_coplanar(support, self.scene):
                _, a, b = support_polygon(support, self.scene)
                self._regions[key] = (a, b)
            else:
                self._regions[key] = equilibrium_region(support, self.scene)
        return self._regions[key]

    def _ignored_pairs(self, contacts, free):
        if self.collision is None:
            return frozenset()
        touching = [contact for contact in contacts if contact.surface is not None]
        if free is not None:
            touching.append(Contact(free.spot, free.surface, 0.0, 0.0, 0.0, False))
        return self.collision.ignored_pairs_for_contacts(touching)

    def _initial_free_parameters(self, q, free):
        """(x, y, theta) of the spot's current pose seen from the surface, moved into the
        search volume (its Chebyshev centre) when outside."""
        self._kinematics(q)
        surface = self.scene.surfaces[free.surface]
        spot = self.data.oMf[self.model.getFrameId(f"spot:{free.spot}")]
        local = surface.pose.actInv(spot)
        x_axis = local.rotation[:, 0]
        v = np.array([local.translation[0], local.translation[1],
                      math.atan2(x_axis[1], x_axis[0])])
        return v if free.volume.contains(v) else np.asarray(free.volume.chebyshev_center())

    def _free_contact(self, free, v):
        return Contact(free.spot, free.surface, float(v[0]), float(v[1]),
                       float(math.remainder(v[2], 2 * math.pi)), False)

    # ----------------------------------------------------------------- one iteration
    def _iterate(self, q, contacts, free, v, stability, criterion, ignored):
        settings, nv = self.settings, self.model.nv
        self._kinematics(q)
        n_free = 3 if free is not None else 0
        n = nv + n_free
        hessian = np.zeros((n, n))
        gradient = np.zeros(n)

        rows, targets, guide_rows, guide_targets = [], [], [], []
        largest_excess = guide_error = 0.0
        for contact in contacts:
            jacobian, error = self._spot_tasks[contact.spot].jacobian_and_error(self.robot, q)
            if getattr(contact, "position_only", False):
                jacobian, error = jacobian[:3], error[:3]
            largest_excess = max(largest_excess, float(np.abs(error).max())
                                 - self._extra_tolerance(contact))
            row = np.zeros((len(error), n))
            row[:, :nv] = jacobian
            weight = getattr(contact, "weight", 1.0)
            if weight < 1.0:
                guide_error = max(guide_error, float(np.abs(error).max()))
                guide_rows.append(math.sqrt(weight) * row)
                guide_targets.append(math.sqrt(weight) * error)
            else:
                rows.append(row)
                targets.append(error)
        if free is not None:
            jacobian, error, b_free = self._free_rows(free, v)
            largest_excess = max(largest_excess, float(np.abs(error).max()))
            rows.append(np.hstack([jacobian, -b_free]))
            targets.append(error)
        contact_rows = np.vstack(rows) if rows else np.zeros((0, n))
        contact_error = np.concatenate(targets) if targets else np.zeros(0)
        if guide_rows:
            # guides act in the contacts' nullspace: to first order they never pull a
            # contact off (a strict priority, as between the IK's levels)
            nullspace = np.eye(n) - np.linalg.pinv(contact_rows, rcond=1e-6) @ contact_rows
            contact_rows = np.vstack([contact_rows, np.vstack(guide_rows) @ nullspace])
            contact_error = np.concatenate([contact_error, *guide_targets])
            # damping by the guides' squared error (Sugihara's Levenberg-Marquardt rule), so
            # a guide out of reach settles instead of bouncing at the trust region
            hessian += settings.contact_weight * sum(t @ t for t in guide_targets) * np.eye(n)
        hessian += settings.contact_weight * contact_rows.T @ contact_rows
        gradient -= settings.contact_weight * contact_rows.T @ contact_error

        if criterion is not None:
            curvature, linear, _ = criterion.quadratic(q)
            hessian.flat[:nv * (n + 1):n + 1] += settings.criterion_weight * curvature  # dq's
            gradient[:nv] += settings.criterion_weight * linear
        hessian.flat[::n + 1] += settings.damping       # the whole diagonal

        # inequality rows: CoM in the stability region, collision pairs, search volume
        a_com, b_com = stability
        if self.collision is not None:
            distances, gradients, _ = self.collision.constraint_rows(
                q, near=settings.collision_near, ignored=ignored)
        else:
            distances, gradients = np.zeros(0), np.zeros((0, nv))
        a_volume, b_volume = free.volume.halfspaces() if free is not None else (None, ())
        com_end, collision_end = len(b_com), len(b_com) + len(distances)
        inequalities = np.zeros((collision_end + len(b_volume), n))
        lower = np.full(len(inequalities), -1e20)
        upper = np.full(len(inequalities), 1e20)
        inequalities[:com_end, :nv] = a_com @ self.data.Jcom[:2]
        upper[:com_end] = b_com - settings.com_margin - a_com @ self.data.com[0][:2]
        inequalities[com_end:collision_end, :nv] = gradients
        lower[com_end:collision_end] = np.minimum(settings.collision_margin - distances,
                                                  settings.collision_push)
        if free is not None:
            inequalities[collision_end:, nv:] = a_volume
            upper[collision_end:] = b_volume - a_volume @ v

        box_lower, box_upper = self._box(q, n, n_free)
        x = self._solve(hessian, gradient, inequalities, lower, upper, box_lower, box_upper)
        dv = x[nv:nv + 3] if n_free else None
        return x[:nv], dv, largest_excess, guide_error

    def _extra_tolerance(self, contact) -> float:
        """m and rad: the error a contact's own `tolerance` accepts beyond contact_tolerance."""
        return max(0.0, getattr(contact, "tolerance", 0.0) - self.settings.contact_tolerance)

    def _free_rows(self, free, v):
        """Jacobian and error of the spot being placed at (x, y, theta) = v, and B: how the
        spot target moves with dv (world-aligned rows)."""
        surface = self.scene.surfaces[free.surface]
        task = self._spot_tasks[free.spot]
        task.target = self._free_contact(free, v).spot_target(surface)
        jacobian, error = task.jacobian_and_error(self.robot, None)
        b_free = np.zeros((6, 3))
        b_free[:3, 0] = surface.pose.rotation[:, 0]
        b_free[:3, 1] = surface.pose.rotation[:, 1]
        b_free[3:, 2] = surface.pose.rotation[:, 2]
        return jacobian, error, b_free

    def _box(self, q, n, n_free):
        """Bounds on x: trust region, joint limits, locked joints, free contact step."""
        settings, nv = self.settings, self.model.nv
        lower = np.full(n, -np.inf)
        upper = np.full(n, np.inf)
        lower[:self._base_nv], upper[:self._base_nv] = -settings.trust_base, settings.trust_base
        lower[self._base_nv:nv], upper[self._base_nv:nv] = -settings.trust_joint, \
            settings.trust_joint
        position = q[self._limited_q]
        lower[self._limited_v] = np.maximum(lower[self._limited_v], self.robot.lower - position)
        upper[self._limited_v] = np.minimum(upper[self._limited_v], self.robot.upper - position)
        lower[self._locked_v] = upper[self._locked_v] = 0.0
        if n_free:
            lower[nv:nv + 3], upper[nv:nv + 3] = -settings.trust_base, settings.trust_base
        return lower, upper

    def _solve(self, hessian, gradient, c_matrix, lower, upper, box_lower, box_upper):
        """x of the iteration's QP with the configured backend; a zero step if it fails."""
        solve = _solve_daqp if self.settings.qp_backend == "daqp" else _solve_proxsuite
        x = solve(hessian, gradient, c_matrix, lower, upper, box_lower, box_upper)
        if x is None or not np.all(np.isfinite(x)):
            return np.zeros(hessian.shape[0])
        return np.clip(x, box_lower, box_upper)

    # ----------------------------------------------------------------- acceptance
    def _acceptance(self, q, contacts, support, ignored):
        """("", details) when every requirement holds at q, else (reason, details)."""
        settings = self.settings
        pin.framesForwardKinematics(self.model, self.data, q)
        com = pin.centerOfMass(self.model, self.data, q)
        details = {}
        worst, missed = 0.0, None
        for contact in contacts:
            task = self._spot_tasks[contact.spot]
            task.target = contact.spot_target(self.scene.surfaces.get(contact.surface))
            rows = 3 if getattr(contact, "position_only", False) else 6
            error = float(np.max(np.abs(task.full_error(self.robot)[:rows])))
            worst = max(worst, error)
            allowed = settings.contact_tolerance + self._extra_tolerance(contact)
            if error > allowed and (missed is None or error > missed[1]):
                missed = (contact.spot, error)
        details["contact_error"] = worst
        if missed is not None:
            spot, error = missed
            return f"contact {spot} not reached (error {error * 1000:.1f} mm or mrad)", details
        if self.collision is not None:
            distance, label = self.collision.min_distance(q, ignored=ignored)
            details["min_distance"] = distance
            if distance < settings.collision_margin * 0.5:
                return f"collision {label} (distance {distance * 1000:.1f} mm)", details
        stable, margin = self._statically_stable(support, com)
        details["stability_margin"] = margin
        if not stable:
            return "not statically stable", details
        return "", details

    def _statically_stable(self, support, com):
        """Exact check at the CoM (m): the support polygon for coplanar horizontal
        support, else the static equilibrium LP, skipped when the CoM lies in the cached
        equilibrium region (an inner approximation, so stable for sure). Returns (stable,
        margin in m or N)."""
        surfaces = self.scene.surfaces
        if all(surfaces[c.surface].pose.rotation[2, 2] > math.cos(math.radians(2))
               for c in support) and are_coplanar(support, self.scene):
            _, a, b = support_polygon(support, self.scene)
            margin = float(np.min(b - a @ com[:2]))
            return margin >= 0.5 * self.settings.com_margin, margin
        a, b = self._stability_model(support)
        margin = float(np.min(b - a @ com[:2]))
        if margin >= 0.0:  # inside the inner approximation of the equilibrium region
            return True, margin
        result = contacts_equilibrium(support, self.scene, com, self.mass, GRAVITY)
        return bool(result.feasible), float(result.margin)


DAQP_OPTIMAL, DAQP_SOFT_OPTIMAL = 1, 2   # daqp.solve exit flags


def _solve_daqp(hessian, gradient, c_matrix, lower, upper, box_lower, box_upper):
    """DAQP (dual active set): bounds first, then the general rows. When the rows cannot
    all hold (a collision row against the trust region, a CoM farther outside the new
    support region than one step can move it), they are made soft and the QP solved again:
    its answer (flag 2, optimal with soft rows violated) is the step toward them."""
    rows = len(lower)
    upper_all = np.concatenate([box_upper, np.minimum(upper, 1e30)])
    lower_all = np.concatenate([box_lower, np.maximum(lower, -1e30)])
    sense = np.zeros(len(upper_all), dtype=np.int32)
    x, _, flag, _ = daqp.solve(hessian, gradient, c_matrix, upper_all, lower_all, sense)
    if flag != 1 and rows:
        sense[len(box_upper):] = 8
        x, _, flag, _ = daqp.solve(hessian, gradient, c_matrix, upper_all, lower_all, sense)
    return np.asarray(x) if flag in (DAQP_OPTIMAL, DAQP_SOFT_OPTIMAL) else None


def _solve_proxsuite(hessian, gradient, c_matrix, lower, upper, box_lower, box_upper):
    """ProxSuite dense QP (the IK's engine); slower on these ill-conditioned problems."""
    qp = proxqp.dense.QP(hessian.shape[0], 0, c_matrix.shape[0], True)
    qp.settings.eps_abs = 1e-7
    qp.settings.eps_rel = 0.0
    qp.settings.max_iter = 2000
    qp.settings.verbose = False
    qp.init(hessian, gradient, None, None, c_matrix, lower, upper, box_lower, box_upper)
    qp.solve()
    return np.array(qp.results.x)


def equilibrium_region(support, scene, directions: int = 16) -> tuple:
    """(A, b) with A c_xy <= b: an inner approximation of the CoM positions (world xy, m)
    where some contact forces of `support` balance gravity (the static equilibrium
    region, a vertical prism: Bretl and Lall). Its vertices are the extreme CoM positions
    along `directions` horizontal directions, each an LP over the cone multipliers
    (weight units) and the CoM. An empty region gives rows that nothing satisfies."""
    points, generators = [], []
    for contact in support:
        vertices, normal, friction = contact_vertices(contact, scene)
        tangent = contact.contact_frame(scene.surfaces[contact.surface]).rotation[:, 0]
        cone = friction_cone_generators(normal, friction, tangent=tangent)
        points.extend([vertex] * len(cone) for vertex in vertices)
        generators.extend(cone for _ in vertices)
    lever = np.vstack([np.array(group) for group in points])
    edges = np.vstack(generators)
    count = len(edges)
    # unknowns: multipliers (count, >= 0), c_x, c_y; force and moment balance per weight
    balance = np.zeros((6, count + 2))
    balance[:3, :count] = edges.T
    balance[3:, :count] = np.cross(lever, edges).T
    balance[3, count + 1] = -1.0     # moment x: sum (p x f)_x - c_y = 0
    balance[4, count] = 1.0          # moment y: sum (p x f)_y + c_x = 0
    target = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    centre = lever[:, :2].mean(axis=0)
    n = count + 2
    lower = np.concatenate([np.zeros(count), centre - 5.0, target])
    upper = np.concatenate([np.full(count, 1e30), centre + 5.0, target])
    sense = np.zeros(n + 6, dtype=np.int32)
    sense[n:] = 5                     # the balance rows are equalities
    # each LP as a QP with a vanishing proximal term (DAQP, ~15x faster than HiGHS through
    # scipy): any feasible answer is in the region, so the hull stays an inner approximation
    regularization = 1e-6 * np.eye(n)
    extremes = []
    for angle in np.linspace(0.0, 2 * math.pi, directions, endpoint=False):
        objective = np.zeros(n)
        objective[count:] = -np.array([math.cos(angle), math.sin(angle)])
        x, _, flag, _ = daqp.solve(regularization, objective, balance, upper, lower, sense)
        if flag != 1:
            return np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([-1.0, -1.0])
        extremes.append(np.asarray(x)[count:])
    extremes = np.array(extremes)
    try:
        hull = ConvexHull(extremes)
    except QhullError:
        return np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([-1.0, -1.0])
    return hull.equations[:, :2], -hull.equations[:, 2]
