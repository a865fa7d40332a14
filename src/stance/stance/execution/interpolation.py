"""Configuration paths between consecutive stances of a plan (Escande et al. 2008, 3.3).

For each transition (stance S1 with witness q1 -> stance S2 with witness q2):
- the common contacts (same spot at the same place in S1 and S2) are held and all take
  part in stability, as in the paper;
- a spot whose contact is geometrically created, broken or changed moves along
  `SpotPath`: a straight line of `lift` m along the old surface's normal when it leaves a
  contact, a straight line along the new surface's normal when it enters one, a C1 cubic
  spline between (through a via point at the approach height when one end lies below the
  other's approach plane: the body rises before it crosses a surface's edge); orientation
  constant on the lines, slerp along the spline. The plan
  can move two spots in one transition (a contact kept geometric after its removal is
  dropped while another spot is placed): each then has its own path;
- the transition is cut in n steps; the n - 1 interior samples are posture generations
  (warm-started from the previous sample) with the common contacts, every moving spot held
  at its path pose C_k, and the criterion: distance to pin.interpolate(q1, q2, k / n).
  The ends are the witnesses themselves, so consecutive transitions join exactly.
When only stability changes, the interior samples hold the common contacts alone.

Beyond the paper: a moving spot on the same kinematic branch as a held spot with fewer than
6 DoFs between them (a thigh leaving a seat while its foot stays on the floor, a sole
stepping while its thigh stays on the seat: knee and ankle) is held in position only, as
a 6-D path of fixed orientation is then generally unreachable.

Frames: world frame, m, rad; configurations are Pinocchio q (nq).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin
from scipy.interpolate import CubicHermiteSpline
from scipy.spatial.transform import Rotation, Slerp

from ..planning.posture import PostureGenerator, PostureSettings, ReferencePosture
from ..planning.scene import placement_problem
from ..stopping import stop_if_asked

LIFT = 0.05    # m: default length of the straight lines leaving and entering a contact
# m: clearance required at the samples (the planner's stances use 5 mm): the moving body's
# path is imposed, so it passes as close to the other bodies as the path takes it (a swing
# foot by the stance shin in flat_steps fails at 5 mm)
SAMPLE_COLLISION_MARGIN = 0.002
# m and rad: contact error accepted at the samples. The planner's 0.1 mm is not always
# reachable with a body held 2 mm from another (the linearised collision rows and the
# contact penalty settle 0.1-0.3 mm apart); pik_node tracks the samples anyway and
# `stance check-run` holds executed contacts to 2 mm.
SAMPLE_CONTACT_TOLERANCE = 5e-4
# m and rad: how far a moving spot may stay from its path when collisions, stability or
# joint limits block the exact path (the paper corrected such paths by hand). On the lines
# the body stays close to the normal it leaves or enters along; the spline between is only
# a guide through free space.
LINE_TOLERANCE = 0.002
SPLINE_TOLERANCE = 0.08
DETOUR_LINE_TOLERANCE = 0.01
FUNNEL_SLOPE = 3.0  # m of allowance per m along the path from where the spline ends
TOUCH_DISTANCE = 0.01  # m along the path: a moving body may touch its contact's surface
VIA_MIN_RISE = 0.01  # m: an end this far below the other's approach plane gets a via point
PATH_WEIGHT = 1e-2  # of a moving spot's path error relative to a held contact's error
SUBDIVISIONS = 3  # levels of halved steps through which a failing sample is approached


class InterpolationError(RuntimeError):
    """A sample's posture generation failed: which transition, which sample and why."""

    def __init__(self, transition: int, sample: int, steps: int, reason: str):
        super().__init__(f"transition {transition} -> {transition + 1}: sample {sample}/"
                         f"{steps} failed: {reason}")
        self.transition, self.sample, self.reason = transition, sample, reason


@dataclass(frozen=True, eq=False)
class SpotPose:
    """A spot held at a world pose: a geometric contact for PostureGenerator (it reads
    spot, surface, in_stability and spot_target). `surface` names the surface whose
    obstacle the spot's body may touch (its collisions are ignored), or is None;
    position_only: the orientation is free; tolerance: m and rad, how far the spot may stay
    from `pose` (per axis); weight: of its error relative to a contact's (PostureGenerator reads
    these three)."""

    spot: str
    surface: str | None
    pose: pin.SE3
    position_only: bool = False
    tolerance: float = 0.0
    weight: float = 1.0
    in_stability: bool = False

    def spot_target(self, surface) -> pin.SE3:
        return self.pose


class SpotPath:
    """World pose of a spot frame along s in [0, 1], proportional to the distance along
    the straight lines and the spline's parameter (a chord-length scale, so the position's
    derivative is continuous across the junctions).

    start, end: spot poses (world); leave_normal / enter_normal: outward unit normal (world)
    of the surface being left / entered, or None when the spot is free at that end.
    """

    def __init__(self, start: pin.SE3, end: pin.SE3, leave_normal=None, enter_normal=None,
                 lift: float = LIFT):
        self.start, self.end = start, end
        first = start.translation + (lift * leave_normal if leave_normal is not None else 0.0)
        last = end.translation + (lift * enter_normal if enter_normal is not None else 0.0)
        self.leave_length = lift if leave_normal is not None else 0.0
        self.enter_length = lift if enter_normal is not None else 0.0
        points = _spline_points(first, last, leave_normal, enter_normal)
        chords = np.linalg.norm(np.diff(points, axis=0), axis=1)
        knots = np.concatenate([[0.0], np.cumsum(chords)])
        if knots[-1] < lift:  # a short hop: stretch the parameter, keep the unit tangents
            knots *= max(lift, 1e-6) / max(knots[-1], 1e-12)
        self.spline_length = float(knots[-1])
        # Hermite tangents: the unit normal where a line joins (C1), the chord direction at
        # a free end, central differences at a via point (no overshoot past the corners)
        tangents = np.empty_like(points)
        tangents[0] = leave_normal if leave_normal is not None else _unit(points[1] - points[0])
        tangents[-1] = -enter_normal if enter_normal is not None else \
            _unit(points[-1] - points[-2])
        tangents[1:-1] = (points[2:] - points[:-2]) / (knots[2:] - knots[:-2])[:, None]
        self.spline = CubicHermiteSpline(knots, points, tangents)
        self.leave_normal, self.enter_normal = leave_normal, enter_normal
        self.slerp = Slerp([0.0, 1.0], Rotation.from_matrix(
            np.stack([start.rotation, end.rotation])))
        self.length = self.leave_length + self.spline_length + self.enter_length

    def pose(self, s: float) -> pin.SE3:
        """Spot pose (world) at s in [0, 1]."""
        u = min(max(s, 0.0), 1.0) * self.length
        if u <= self.leave_length and self.leave_length > 0.0:
            return pin.SE3(self.start.rotation, self.start.translation + u * self.leave_normal)
        entering_from = self.leave_length + self.spline_length
        if u >= entering_from and self.enter_length > 0.0:
            return pin.SE3(self.end.rotation, self.end.translation
                           + (self.length - u) * self.enter_normal)
        along = min(max(u - self.leave_length, 0.0), self.spline_length)
        rotation = self.slerp([along / self.spline_length]).as_matrix()[0]
        return pin.SE3(rotation, self.spline(along))

    def phase(self, s: float) -> str:
        """'leave', 'spline' or 'enter': the part of the path at s."""
        u = s * self.length
        if u < self.leave_length:
            return "leave"
        return "enter" if u > self.leave_length + self.spline_length else "spline"


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / max(float(np.linalg.norm(vector)), 1e-12)


def _spline_points(first, last, leave_normal, enter_normal) -> np.ndarray:
    """Points the spline passes through (world, m): the ends of the straight lines and,
    where an end lies below the other end's approach plane (the plane through it normal to
    its surface), a via point over that end on the plane, so the body rises clear of the
    surface's edge before it crosses (a hand from the hip onto a table top, a sole up onto
    a step) and descends only once past it (a sole down from a step)."""
    points = [first]
    if enter_normal is not None and enter_normal @ (first - last) < -VIA_MIN_RISE:
        points.append(first - (enter_normal @ (first - last)) * enter_normal)
    if leave_normal is not None and leave_normal @ (last - first) < -VIA_MIN_RISE:
        points.append(last - (leave_normal @ (last - first)) * leave_normal)
    points.append(last)
    return np.vstack(points)


@dataclass(frozen=True)
class ContactEvent:
    """A contact change at sample `sample` of the interpolated path: 'created' or 'broken'
    (geometrically), 'support_added' or 'support_removed' (only its stability)."""

    sample: int
    kind: str
    contact: object


@dataclass
class InterpolatedPlan:
    """Configurations through a whole plan.

    q: (N, nq) samples; transition: (N,) index i of the transition (stance i -> i + 1) each
    sample lies in (a stance's own sample belongs to the transition it ends; stance 0's to
    transition 0); stance_samples: sample index of each stance's witness (i * n);
    events: ContactEvents in sample order; transitions: per transition, a dict with the
    moving spots, posture generations, iterations and seconds.
    """

    q: np.ndarray
    transition: np.ndarray
    stance_samples: np.ndarray
    events: list
    transitions: list = field(default_factory=list)

    @property
    def event_samples(self) -> np.ndarray:
        """Sorted sample indices where some contact changes (rest points for timing)."""
        return np.unique([event.sample for event in self.events])


def _place(contact) -> tuple:
    return (contact.spot, contact.surface, contact.x, contact.y, contact.theta)


def spot_pose(generator: PostureGenerator, q: np.ndarray, spot: str) -> pin.SE3:
    """World pose of spot frame `spot:<spot>` at q (generator's model)."""
    pin.framesForwardKinematics(generator.model, generator.data, q)
    return pin.SE3(generator.data.oMf[generator.model.getFrameId(f"spot:{spot}")])


class TransitionPlanner:
    """Interpolates the transitions of plans on one scene (see module docstring).

    steps: n per transition; lift: m, the straight lines; criterion_weight: of the
    ReferencePosture criterion; settings: of the posture generator (default: no time
    budget, SAMPLE_COLLISION_MARGIN, SAMPLE_CONTACT_TOLERANCE).
    """

    def __init__(self, robot, scene, collision=None, settings: PostureSettings | None = None,
                 steps: int = 20, lift: float = LIFT, criterion_weight: float = 1e-2):
        if not (isinstance(steps, (int, np.integer)) and steps >= 1):
            raise ValueError(f"steps must be an integer >= 1, got {steps!r}")
        if not (math.isfinite(lift) and lift >= 0.0):
            raise ValueError(f"lift must be finite and >= 0 m, got {lift!r}")
        self.scene, self.steps, self.lift = scene, steps, lift
        self.criterion_weight = criterion_weight
        settings = settings or PostureSettings(time_budget=math.inf,
                                               collision_margin=SAMPLE_COLLISION_MARGIN,
                                               contact_tolerance=SAMPLE_CONTACT_TOLERANCE)
        self.generator = PostureGenerator(robot, scene, collision, settings)

    def moving_paths(self, first, second) -> dict:
        """{spot: (SpotPath, contact in first or None, contact in second or None)} for the
        spots whose geometric contact differs between the two stances (Stance objects):
        paths from the spot's pose at q1 to its pose at q2."""
        places_1 = {c.spot: c for c in first.contacts}
        places_2 = {c.spot: c for c in second.contacts}
        paths = {}
        for spot in sorted(set(places_1) | set(places_2)):
            before, after = places_1.get(spot), places_2.get(spot)
            if before is not None and after is not None and _place(before) == _place(after):
                continue
            paths[spot] = (SpotPath(spot_pose(self.generator, first.q, spot),
                                    spot_pose(self.generator, second.q, spot),
                                    self._normal(before), self._normal(after), self.lift),
                           before, after)
        return paths

    def _normal(self, contact):
        """Outward unit normal (world) of the contact's surface, None without contact."""
        if contact is None:
            return None
        return self.scene.surfaces[contact.surface].pose.rotation[:, 2].copy()

    def transition(self, index: int, first, second, should_stop=None):
        """(interior samples (n - 1, nq), statistics dict) from stance `first` to `second`;
        raises InterpolationError when a sample fails on the path and on its detour, even
        when approached through SUBDIVISIONS levels of halved steps, and
        stopping.Stopped when should_stop (a callable, asked before each sample) answers
        True.

        From the first sample the path blocks (collisions, stability or joint limits), the
        transition takes a detour: the spline is then a guide only (any distance from it)
        and position-only spots may leave their lines by SPLINE_TOLERANCE. A sample that
        fails from the previous one is approached through intermediate samples (warm starts
        only, not returned): a large step between samples takes the linearised collision
        and contact rows too far from where they hold."""
        model, steps = self.generator.model, self.steps
        second_places = {_place(c) for c in second.contacts}
        common = tuple(c.with_stability(True) for c in first.contacts
                       if _place(c) in second_places)
        paths = self.moving_paths(first, second)
        position_only = self._position_only(paths, common)
        began = time.perf_counter()
        sampler = _Sampler(self, first, second, common, paths, position_only)
        q, previous, samples = first.q, first.q, []
        for k in range(1, steps):
            stop_if_asked(should_stop, f"stopped at transition {index} -> {index + 1}, "
                                       f"sample {k}/{steps}")
            # warm start: the previous sample moved on by the last sample's step
            guess = pin.integrate(model, q, pin.difference(model, previous, q))
            result = sampler.reach((k - 1) / steps, q, k / steps, guess, SUBDIVISIONS)
            if not result.success:
                raise InterpolationError(index, k, steps, result.reason)
            previous, q = q, result.q
            samples.append(q)
        detour_from = None if sampler.detour_from is None else \
            round(sampler.detour_from * steps, 3)
        statistics = {"moving": sorted(paths), "position_only": sorted(position_only),
                      "detour_from": detour_from, "generations": sampler.generations,
                      "subdivided": sampler.subdivided, "iterations": sampler.iterations,
                      "seconds": time.perf_counter() - began}
        return np.reshape(samples, (steps - 1, model.nq)), statistics

    @staticmethod
    def _tolerance(path, s: float, position_only: bool, detour: bool) -> float:
        """m and rad: how far a moving spot may stay from its path at s (see transition).
        Off the lines the allowance is at most FUNNEL_SLOPE times the distance along the
        path to where the spline, or the path, ends: the samples close in on the next
        stance's witness even when no sample falls on the entering line."""
        u = s * path.length
        line = DETOUR_LINE_TOLERANCE if detour else LINE_TOLERANCE
        if path.phase(s) == "spline":
            to_end = path.leave_length + path.spline_length - u
            return max(line, min(math.inf if detour else SPLINE_TOLERANCE,
                                 FUNNEL_SLOPE * to_end))
        if detour and position_only:
            return max(line, min(SPLINE_TOLERANCE, FUNNEL_SLOPE * (path.length - u)))
        return line

    def _position_only(self, paths, common) -> set:
        """Moving spots within fewer than 6 DoFs of another held or moving spot (a 6-D
        pose relative to it is then generally unreachable)."""
        others = [c.spot for c in common] + list(paths)
        return {spot for spot in paths
                if any(self.generator.chain_dofs(spot, other) < 6
                       for other in others if other != spot)}

    @staticmethod
    def _touched_surface(path, before, after, s):
        """The surface the moving body may touch at s: the one it leaves or enters while
        within TOUCH_DISTANCE of that contact along its path; None elsewhere, where the
        body keeps its collision margin from everything (a sole held in position only
        would otherwise tip its toe into the floor it leaves)."""
        u = s * path.length
        if before is not None and u <= TOUCH_DISTANCE:
            return before.surface
        if after is not None and path.length - u <= TOUCH_DISTANCE:
            return after.surface
        return None

    def interpolate(self, plan, should_stop=None) -> InterpolatedPlan:
        """The whole plan as one sampled path (raises InterpolationError on a failure;
        ValueError for fewer than two stances, a witness that is not nq finite values or a
        contact off the scene: scene.placement_problem; stopping.Stopped once
        should_stop, a callable asked before each sample, answers True)."""
        stances = plan.stances
        if len(stances) < 2:
            raise ValueError(f"a plan of {len(stances)} stance(s) has no transition to "
                             "interpolate")
        nq = self.generator.robot.model.nq
        for index, stance in enumerate(stances):
            q = np.asarray(stance.q, dtype=float)
            if q.shape != (nq,) or not np.isfinite(q).all():
                raise ValueError(f"stance {index}: the witness is not {nq} finite values")
            for k, contact in enumerate(stance.contacts):
                problem = placement_problem(self.scene.surfaces, self.scene.spots, contact)
                if problem:
                    raise ValueError(f"stance {index}: contacts[{k}]{problem[0]}: "
                                     f"{problem[1]}")
        results = [self.transition(index, first, second, should_stop)
                   for index, (first, second) in enumerate(zip(stances[:-1], stances[1:]))]
        return assemble(stances, self.steps, results)


class _Sampler:
    """Posture generations along one transition (TransitionPlanner.transition): the held
    contacts, each moving spot on its path, the interpolated witnesses as criterion."""

    def __init__(self, planner, first, second, common, paths, position_only):
        self.planner, self.first, self.second = planner, first, second
        self.common, self.paths, self.position_only = common, paths, position_only
        self.detour_from = None         # s of the first sample off the exact path
        self.generations = self.iterations = self.subdivided = 0

    def reach(self, s_from: float, q_from: np.ndarray, s_to: float, guess: np.ndarray,
              depth: int):
        """PostureResult at s_to, from the posture q_from at s_from; on failure, through
        the midpoint first, `depth` times at most."""
        result = self.sample(s_to, guess)
        if result.success or depth == 0:
            return result
        middle = 0.5 * (s_from + s_to)
        halfway = self.reach(s_from, q_from, middle, q_from, depth - 1)
        if not halfway.success:
            return result
        self.subdivided += 1
        model = self.planner.generator.model
        onward = pin.integrate(model, halfway.q, pin.difference(model, q_from, halfway.q))
        return self.reach(middle, halfway.q, s_to, onward, depth - 1)

    def sample(self, s: float, guess: np.ndarray):
        """PostureResult at s: on the exact path, else (and from then on) on the detour."""
        planner = self.planner
        model = planner.generator.model
        criterion = ReferencePosture(model, pin.interpolate(model, self.first.q, self.second.q,
                                                            s), planner.criterion_weight)
        for detour in ((False, True) if self.detour_from is None else (True,)):
            held = tuple(SpotPose(spot, planner._touched_surface(path, before, after, s),
                                  path.pose(s), spot in self.position_only,
                                  planner._tolerance(path, s, spot in self.position_only,
                                                     detour), PATH_WEIGHT)
                         for spot, (path, before, after) in self.paths.items())
            result = planner.generator.generate(self.common + held, guess, criterion)
            self.generations += 1
            self.iterations += result.iterations
            if result.success:
                if detour and self.detour_from is None:
                    self.detour_from = s
                return result
        return result


def assemble(stances, steps: int, results) -> InterpolatedPlan:
    """InterpolatedPlan from the stances and, per transition, the (interior samples,
    statistics) of TransitionPlanner.transition."""
    blocks, labels, events = [stances[0].q[None, :]], [0], []
    for index, (first, second) in enumerate(zip(stances[:-1], stances[1:])):
        blocks.extend([results[index][0], second.q[None, :]])
        labels.extend([index] * steps)
        events.extend(_events(index * steps, (index + 1) * steps, first, second))
    return InterpolatedPlan(np.vstack(blocks), np.array(labels),
                            np.arange(len(stances)) * steps, events,
                            [statistics for _, statistics in results])


def _events(start_sample: int, end_sample: int, first, second) -> list:
    """Contact changes from stance `first` to `second`: geometric breaks at the start of
    the transition, creations and stability changes at its end."""
    places_2 = {_place(c): c for c in second.contacts}
    places_1 = {_place(c): c for c in first.contacts}
    events = [ContactEvent(start_sample, "broken", c) for key, c in places_1.items()
              if key not in places_2]
    for key, contact in places_2.items():
        before = places_1.get(key)
        if before is None:
            events.append(ContactEvent(end_sample, "created", contact))
        elif before.in_stability != contact.in_stability:
            kind = "support_added" if contact.in_stability else "support_removed"
            events.append(ContactEvent(end_sample, kind, contact))
    return events

