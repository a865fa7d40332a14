"""Best-first contact-before-motion planner (Escande et al. 2008, sections 2.2-2.8).

The search runs over sets of supporting contacts. Each node is a stance with a witness
posture; its sons' supporting sets differ from its own by one contact (section 2.3):
- removing contact c: a posture with every contact of the set, c no longer in stability
  (checked at the instant c is broken); the son supports on the set without c, and its
  stance keeps c as a geometric contact (in_stability False): the witness still touches it;
- adding a contact of a free spot R on a surface E (not while a supporting contact holds a
  body within fewer than 6 DoFs of R: the transition could not be executed, see
  `_Search._placeable`): the posture generator places it, with
  the potential f_T as criterion, inside a convex search volume of E x ]-pi, pi] (2.5-2.6),
  the new contact not yet in stability; a volume around the found contact is then cut out
  and the rest split into convex parts for the next son of the same pair.
The leaf with the least f_T (2.7) is expanded first. With `ordered_sons` (2.8) a pair
(R, E) keeps a single leaf: its next son is generated only when that leaf is selected,
because the generator returns a pair's sons best first. Without it every son of every pair
is generated when a node is expanded (up to MAX_SONS_PER_PAIR). New leaves too close to an
existing stance (same pairs, every contact within CLOSENESS) are discarded.

Beyond the paper: before a leaf is expanded, the transition from its parent is interpolated
as trajectory_node will interpolate it (`transition_steps` samples); a leaf whose transition
fails is dropped, so every transition of a returned plan can be executed.

plan_contacts never raises for planning failures: it returns a PlanOutcome with a reason.
Everything is deterministic (posture generations are capped in iterations, not time), so
the same request gives the same plan; the wall-time budget only ends the search.
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin

from .contacts import Plan
from .scene import placement_problem
from .volumes import initial_volume

# Failure reasons, as reported by the planner, the action result and the CLI.
SUCCESS = "success"
INFEASIBLE_START = "infeasible_start"   # no posture realises the start stance
NO_PATH = "no_path"                     # the search tree is exhausted, or no stance
#                                         can meet the goal (_goal_out_of_reach)
BUDGET_EXHAUSTED = "budget_exhausted"   # max_nodes or time_budget reached
BAD_GOAL = "bad_goal"                   # goal condition malformed or names unknown frames
CANCELLED = "cancelled"                 # should_stop() returned True
# Pinocchio joint kinds that only turn their child frame: revolute about any axis, bounded
# or not, spherical
TURNING_JOINTS = frozenset(
    f"JointModel{kind}" for kind in ("RX", "RY", "RZ", "RUBX", "RUBY", "RUBZ",
                                     "RevoluteUnaligned", "RevoluteUnboundedUnaligned",
                                     "Spherical", "SphericalZYX"))
REACH_MARGIN = 0.01   # m: contacts are met within tolerances, a start's within 1 mm slack


@dataclass
class PlanRequest:
    """What to plan. None fields default to the scene's own start, key postures, goal."""

    scene: object                       # stance.planning.scene.Scene
    start: tuple | None = None          # Contacts of the start stance
    key_postures: np.ndarray | None = None   # (K, nq)
    goal: object | None = None          # stance.planning.scene.Goal
    max_nodes: int = 2400               # nodes expanded at most
    time_budget: float = 900.0          # s of wall time at most
    seed: int = 0
    ordered_sons: bool = True           # section 2.8: one leaf per (spot, surface) pair
    slope: float | None = None          # k of f_T (eq. 1), f units per m along T';
                                        # None: the scene's potential_slope
    workers: int = 1                    # processes generating a node's first sons together
    transition_steps: int = 20          # n of the trajectory interpolation that each stance's
                                        # incoming transition must pass before the stance is
                                        # expanded (0: unchecked); see _Search.executable

    def __post_init__(self):
        """ValueError naming a budget or setting that means nothing (a NaN budget used to
        disable its limit: an unreachable goal then searched on until the tree ran out)."""
        for name, least in (("max_nodes", 1), ("workers", 1), ("transition_steps", 0)):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and value >= least):
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        if not self.time_budget > 0.0:
            raise ValueError(f"time_budget must be > 0 s, got {self.time_budget!r}")
        if self.slope is not None and not (math.isfinite(self.slope) and self.slope > 0.0):
            raise ValueError(f"slope must be finite and > 0, got {self.slope!r}")


@dataclass
class PlanProgress:
    nodes_expanded: int
    posture_generations: int
    best_potential: float
    elapsed: float                      # s


@dataclass
class PlanOutcome:
    reason: str                         # SUCCESS or one of the failure reasons above
    message: str                        # human-readable detail
    plan: Plan | None = None
    statistics: dict = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return self.reason == SUCCESS


CLOSENESS_POSITION = 0.03   # m: contacts closer than this are the same contact
CLOSENESS_ANGLE = 0.3       # rad
SUBTRACTED_HALF_EXTENTS = (0.08, 0.08, 0.6)  # m, m, rad: volume V cut around a found contact
MAX_SONS_PER_PAIR = 8       # unordered generation: sons per (spot, surface) pair and node


@dataclass
class _Node:
    """A stance in the search tree (leaf until expanded): the contacts its witness q
    touches, those with in_stability supporting it."""

    contacts: tuple
    q: np.ndarray
    potential: float
    parent: _Node | None
    pair_source: object = None      # the _PairSons that produced it (ordered mode)
    depth: int = 0

    @property
    def supporting(self) -> tuple:
        return tuple(c for c in self.contacts if c.in_stability)


class _PairSons:
    """Sons of one node for one (spot, surface) pair, best first: each call places the
    spot in the best remaining convex search volume and cuts a volume around it out."""

    def __init__(self, node, spot, surface, volumes):
        self.node, self.spot, self.surface = node, spot, surface
        self.volumes = list(volumes)

    def next_son(self, generate):
        """(contacts, q, potential) of the next son, or None when the pair is exhausted;
        `generate(node, free)` runs the posture generator."""
        from .posture import FreeContact
        while self.volumes:
            volume = self.volumes.pop(0)
            result = generate(self.node, FreeContact(self.spot, self.surface, volume))
            if result is None:
                continue
            placed = result.contacts[-1]
            center = np.array([placed.x, placed.y, placed.theta])
            self.volumes.extend(volume.subtract(center, np.array(SUBTRACTED_HALF_EXTENTS)))
            return result
        return None


class _Search:
    def __init__(self, robot, request, generator, trajectory, progress, should_stop):
        self.robot, self.request = robot, request
        self.scene = request.scene
        self.generator, self.trajectory = generator, trajectory
        self.progress, self.should_stop = progress, should_stop
        self.leaves = []            # heap of (potential, counter, node)
        self.counter = 0
        self.stances = {}           # pairs key -> list of contact arrays (closeness)
        self.expanded = 0
        self.best_potential = math.inf
        self.start_time = time.perf_counter()
        self.stopped_reason = None
        self.posture_calls = []     # (kind, success, wall s, CPU s) of every posture generation
        self.pool = []              # one-process executors (request.workers > 1)
        self.prefetched = {}        # call key -> PostureResult computed by the pool
        self.transitions = None     # execution.interpolation.TransitionPlanner, or None
        self.transition_checks = []  # (executable, s) of every transition checked

    # --------------------------------------------------------------- posture calls
    def generate(self, node, free=None, removed=None):
        """Posture for node's supporting contacts (+ free being placed, or with `removed`
        out of stability) from node's witness with f_T as criterion; None on failure.
        Results computed ahead by `prefetch` are used when there is one."""
        if self._must_stop():
            return None
        key = _call_key(free, removed)
        if key in self.prefetched:
            result = self.prefetched.pop(key)
        else:
            result = self.generator.generate(_call_contacts(node, removed), node.q,
                                             self.criterion, free=free)
        kind = "add" if free is not None else "remove"
        self.posture_calls.append((kind, result.success, result.seconds, result.cpu_seconds))
        return result if result.success else None

    def _must_stop(self):
        if self.stopped_reason:
            return True
        if self.should_stop is not None and self.should_stop():
            self.stopped_reason = CANCELLED
        elif time.perf_counter() - self.start_time > self.request.time_budget:
            self.stopped_reason = BUDGET_EXHAUSTED
        return self.stopped_reason is not None

    # --------------------------------------------------------------- leaves
    def _too_close(self, contacts):
        """True when a stance with the same supporting pairs, every contact within the
        closeness thresholds, exists; otherwise remembers this one."""
        ordered = sorted((c for c in contacts if c.in_stability), key=lambda c: c.pair)
        key = tuple(c.pair for c in ordered)
        values = np.array([[c.x, c.y, c.theta] for c in ordered])
        for other in self.stances.get(key, []):
            offsets = np.abs(values - other)
            offsets[:, 2] = np.abs(np.remainder(offsets[:, 2] + math.pi, 2 * math.pi) - math.pi)
            if np.all(np.hypot(offsets[:, 0], offsets[:, 1]) < CLOSENESS_POSITION) and \
                    np.all(offsets[:, 2] < CLOSENESS_ANGLE):
                return True
        self.stances.setdefault(key, []).append(values)
        return False

    def add_leaf(self, contacts, q, parent, pair_source=None):
        if self._too_close(contacts):
            return None
        potential = float(self.trajectory.evaluate(q).value)
        node = _Node(contacts, q, potential, parent, pair_source,
                     0 if parent is None else parent.depth + 1)
        heapq.heappush(self.leaves, (potential, self.counter, node))
        self.counter += 1
        return node

    # --------------------------------------------------------------- expansion
    def expand(self, node):
        """Generate node's sons (module docstring)."""
        from .posture import FreeContact
        supporting = node.supporting
        removals = supporting if len(supporting) > 1 else ()
        pairs = [_PairSons(node, spot.name, surface.name, [initial_volume(surface.polygon)])
                 for spot in self.scene.spots.values() if self._placeable(spot.name, node)
                 for surface in self.scene.surfaces.values()
                 if not spot.surfaces or surface.name in spot.surfaces]
        self.prefetch(node, removals, [FreeContact(pair.spot, pair.surface, pair.volumes[0])
                                       for pair in pairs])
        for contact in removals:
            result = self.generate(node, removed=contact)
            if result is not None:
                self.add_leaf(result.contacts, result.q, node)
        for pair in pairs:
            self._pair_sons(pair, node)

    def _placeable(self, spot, node) -> bool:
        """Whether a son may place `spot`: it supports nothing yet, and no supporting
        contact holds a body within fewer than 6 DoFs of it. A sole re-placed under a thigh
        held on a seat can only reach the two places where its ankle's circle about the
        knee meets the floor, and the way between them runs through the floor: the robot
        must lift the thigh first."""
        return all(contact.spot != spot and self.generator.chain_dofs(spot, contact.spot) >= 6
                   for contact in node.supporting)

    def prefetch(self, node, removals, frees):
        """With worker processes: generate the node's removal sons and each pair's first son
        at once, in parallel; `generate` then takes these results in its usual order.
        Call i goes to worker i mod workers, so every worker sees the same calls in every
        run: the search amplifies rounding, and a schedule that depended on timing would
        give the same plan twice only as long as a posture depends on its call alone (each
        generation forgets its collision model's state, every process holds the same
        coal state: coal_order)."""
        if not self.pool or self._must_stop():
            return
        calls = [(None, removed) for removed in removals] + [(free, None) for free in frees]
        futures = [self.pool[index % len(self.pool)].submit(
                       _pooled_generate, (_call_contacts(node, removed), node.q, free))
                   for index, (free, removed) in enumerate(calls)]
        self.prefetched = {_call_key(free, removed): future.result()
                           for (free, removed), future in zip(calls, futures)}

    def _pair_sons(self, pair, node):
        """Ordered mode: the pair's next son only; otherwise up to MAX_SONS_PER_PAIR."""
        count = 1 if self.request.ordered_sons else MAX_SONS_PER_PAIR
        for _ in range(count):
            while True:
                result = pair.next_son(self.generate)
                if result is None:
                    return
                placed = result.contacts[-1].with_stability(True)
                son = self.add_leaf(node.supporting + (placed,), result.q, node,
                                    pair if self.request.ordered_sons else None)
                if son is not None:
                    break

    def run(self, start_contacts, start_q):
        while self.leaves:
            if self._must_stop():
                return None, self.stopped_reason
            if self.expanded >= self.request.max_nodes:
                return None, BUDGET_EXHAUSTED
            _, _, node = heapq.heappop(self.leaves)
            if not self.executable(node):
                if node.pair_source is not None:
                    self._pair_sons(node.pair_source, node.parent)
                continue
            self.expanded += 1
            self.best_potential = min(self.best_potential, node.potential)
            if self._goal_reached(node.q):
                return node, SUCCESS
            if node.pair_source is not None:
                self._pair_sons(node.pair_source, node.parent)
            self.expand(node)
            if self.progress is not None:
                self.progress(self.snapshot())
        return None, self.stopped_reason or NO_PATH

    def executable(self, node) -> bool:
        """Whether the transition from node's parent to node interpolates as the trajectory
        node will interpolate it (beyond the paper, which corrected such paths by hand): a
        stance whose incoming transition fails (a foot that cannot pass a table leg, a
        guide that the collision rows hold in a dead end) is dropped before expansion, as
        lazy planners drop an edge found in collision only when they need it."""
        if self.transitions is None or node.parent is None:
            return True
        from ..execution.interpolation import InterpolationError
        from .contacts import Stance
        began = time.perf_counter()
        try:
            self.transitions.transition(node.depth - 1, Stance(node.parent.contacts,
                                                               node.parent.q),
                                        Stance(node.contacts, node.q))
            executable = True
        except InterpolationError:
            executable = False
        self.transition_checks.append((executable, time.perf_counter() - began))
        return executable

    def _goal_reached(self, q):
        goal = self.request.goal
        pin.framesForwardKinematics(self.robot.model, self.robot.data, q)
        position = self.robot.data.oMf[self.robot.model.getFrameId(goal.frame)].translation
        return goal.reached(position)

    def snapshot(self):
        return PlanProgress(self.expanded, len(self.posture_calls), self.best_potential,
                            time.perf_counter() - self.start_time)


def _call_contacts(node, removed):
    """The contacts of a posture call from `node`: its supporting ones, `removed` (if any)
    out of stability."""
    return tuple(c.with_stability(c != removed) for c in node.supporting)


def _call_key(free, removed):
    if free is not None:
        return ("add", free.spot, free.surface, id(free.volume))
    return ("remove", removed)


_WORKER = {}   # in a pool process: its posture generator and criterion


def _start_worker(robot_spec, scene, key_postures, slope, settings):
    """Pool worker set-up: its own generator and criterion, one BLAS thread (the pool is
    the parallelism)."""
    from threadpoolctl import threadpool_limits

    from ..robot import Robot
    from .collision import CollisionModel
    from .posture import PostureGenerator, PotentialCriterion
    from .potential import RoughTrajectory
    threadpool_limits(1)
    robot = Robot.load(robot_spec)
    _WORKER["generator"] = PostureGenerator(robot, scene, CollisionModel(robot, scene),
                                            settings)
    _WORKER["criterion"] = PotentialCriterion(RoughTrajectory(robot.model, key_postures,
                                                              k=slope))


def _pooled_generate(call):
    contacts, q, free = call
    return _WORKER["generator"].generate(contacts, q, _WORKER["criterion"], free=free)


def _check_goal(robot, goal):
    """A failure message for a malformed goal, or ''."""
    if goal is None:
        return "no goal condition"
    if not robot.model.existFrame(goal.frame):
        return f"goal.frame: unknown robot frame {goal.frame!r}"
    if goal.axis not in ("x", "y", "z"):
        return f"goal.axis: must be x, y or z, got {goal.axis!r}"
    if goal.sense not in (1, -1):
        return f"goal.sense: must be +1 or -1, got {goal.sense!r}"
    if not math.isfinite(goal.threshold):
        return "goal.threshold: not finite"
    return ""


def _goal_out_of_reach(robot, scene, goal) -> str:
    """A failure message when no stance can meet the goal, or '': every stance has a
    contact, whose spot lies on one of the surfaces it may touch, and the goal frame lies
    at most its chain's length (_chain_length) from that spot (REACH_MARGIN more)."""
    axis, farthest = "xyz".index(goal.axis), -math.inf
    for spot in scene.spots.values():
        reach = _chain_length(robot.model, spot.frame, goal.frame) + \
            float(np.linalg.norm(spot.placement.translation))
        for name in spot.surfaces or tuple(scene.surfaces):
            surface = scene.surfaces[name]
            for x, y in surface.polygon:
                corner = surface.pose.act(np.array([x, y, 0.0]))
                farthest = max(farthest, goal.sense * corner[axis] + reach)
    if farthest + REACH_MARGIN > goal.sense * goal.threshold:
        return ""
    return (f"goal out of reach: {goal.frame} {goal.axis} {'>' if goal.sense > 0 else '<'} "
            f"{goal.threshold:g} m, and no stance takes it past {goal.sense * farthest:.2f} m "
            f"(the scene's surfaces, then the longest chain from a spot to {goal.frame})")


def _chain_length(model, first: str, second: str) -> float:
    """Upper bound (m) on the distance between two frames' origins in any configuration:
    the offsets along the kinematic tree between them, the joints turning only (inf if a
    joint between them translates: the free flyer, a prismatic joint)."""
    frames = [model.frames[model.getFrameId(name)] for name in (first, second)]
    chains = [list(model.supports[frame.parentJoint]) for frame in frames]  # root first
    common = 0
    while common < min(map(len, chains)) and chains[0][common] == chains[1][common]:
        common += 1
    length = sum(float(np.linalg.norm(frame.placement.translation)) for frame in frames)
    for chain in chains:
        for joint in chain[common:]:
            if model.joints[joint].shortname() not in TURNING_JOINTS:
                return math.inf
            length += float(np.linalg.norm(model.jointPlacements[joint].translation))
    return length


def plan_contacts(robot, request: PlanRequest, progress=None, should_stop=None,
                  collision=None, settings=None) -> PlanOutcome:
    """Plan stances from the request's start to its goal (module docstring).

    robot: stance.robot.Robot of the scene; progress(PlanProgress) is called after each
    expansion; should_stop() is polled between posture generations (cancel). collision:
    a CollisionModel to reuse (built from the scene otherwise; the generator forgets its
    state at each call); settings:
    PostureSettings.
    """
    from .collision import CollisionModel
    from .contacts import Contact
    from .posture import PostureGenerator, PostureSettings, PotentialCriterion
    from .potential import RoughTrajectory

    scene = request.scene
    goal = request.goal if request.goal is not None else scene.goal
    request.goal = goal
    message = _check_goal(robot, goal)
    if message:
        return PlanOutcome(BAD_GOAL, message)
    key_postures = scene.key_postures if request.key_postures is None else request.key_postures
    start = tuple(Contact(c.spot, c.surface, c.x, c.y, c.theta)
                  for c in (scene.start if request.start is None else request.start))
    for index, contact in enumerate(start):
        problem = placement_problem(scene.surfaces, scene.spots, contact)
        if problem:
            return PlanOutcome(INFEASIBLE_START, f"start[{index}]{problem[0]}: {problem[1]}")
    message = _goal_out_of_reach(robot, scene, goal)
    if message:
        return PlanOutcome(NO_PATH, message)
    if collision is None:
        collision = CollisionModel(robot, scene)
    settings = settings or PostureSettings(time_budget=math.inf)
    generator = PostureGenerator(robot, scene, collision, settings)
    slope = scene.potential_slope if request.slope is None else request.slope
    trajectory = RoughTrajectory(robot.model, np.asarray(key_postures), k=slope)
    search = _Search(robot, request, generator, trajectory, progress, should_stop)
    search.criterion = PotentialCriterion(trajectory)
    if request.transition_steps > 0:
        from ..execution.interpolation import TransitionPlanner
        search.transitions = TransitionPlanner(robot, scene, collision,
                                               steps=request.transition_steps)
    if request.workers > 1:
        import concurrent.futures
        import multiprocessing
        search.pool = [concurrent.futures.ProcessPoolExecutor(
            1, mp_context=multiprocessing.get_context("spawn"), initializer=_start_worker,
            initargs=(scene.robot, scene, np.asarray(key_postures), slope, settings))
            for _ in range(request.workers)]
    try:
        return _run_search(search, generator, robot, request, scene, start, key_postures)
    finally:
        for worker in search.pool:
            worker.shutdown(cancel_futures=True)


def _run_search(search, generator, robot, request, scene, start, key_postures):
    """The search proper, from the start posture (plan_contacts)."""
    from .contacts import Stance
    from .posture import ReferencePosture

    start_q = scene.start_configuration if request.start is None else key_postures[0]
    first = generator.generate(start, start_q, ReferencePosture(robot.model, start_q))
    search.posture_calls.append(("start", first.success, first.seconds, first.cpu_seconds))
    if not first.success:
        return PlanOutcome(INFEASIBLE_START, f"no posture realises the start stance: "
                                             f"{first.reason}", statistics=_statistics(search))
    search.add_leaf(start, first.q, None)
    node, reason = search.run(start, first.q)
    statistics = _statistics(search)
    if node is None:
        messages = {NO_PATH: "the search tree is exhausted",
                    BUDGET_EXHAUSTED: f"budget exhausted after {search.expanded} nodes and "
                                      f"{statistics['planning_time']:.0f} s",
                    CANCELLED: "cancelled"}
        return PlanOutcome(reason, messages[reason], statistics=statistics)
    chain = []
    while node is not None:
        chain.append(Stance(node.contacts, node.q, node.potential))
        node = node.parent
    chain.reverse()
    statistics["stances"] = len(chain)
    plan = Plan(scene.name, scene.robot, chain, statistics)
    return PlanOutcome(SUCCESS, f"{len(chain)} stances, {search.expanded} nodes expanded",
                       plan, statistics)


def _statistics(search) -> dict:
    """Search figures; posture_calls per kind (start, add, remove, and all of them):
    calls, successes, the median and p99 wall seconds of a call and its median CPU
    seconds (wall time counts the waits of processes sharing the cores)."""
    by_kind = {}
    for kind in ("start", "add", "remove", "all"):
        calls = [(ok, wall, cpu) for k, ok, wall, cpu in search.posture_calls
                 if kind in (k, "all")]
        if calls:
            wall = np.array([w for _, w, _ in calls])
            by_kind[kind] = {"calls": len(calls), "successes": sum(ok for ok, _, _ in calls),
                             "median_s": float(np.median(wall)),
                             "p99_s": float(np.percentile(wall, 99)),
                             "median_cpu_s": float(np.median([c for _, _, c in calls]))}
    checks = search.transition_checks
    return {"nodes_expanded": search.expanded,
            "posture_generations": len(search.posture_calls),
            "transitions_checked": len(checks),
            "transitions_rejected": sum(not ok for ok, _ in checks),
            "transition_check_time": float(sum(seconds for _, seconds in checks)),
            "planning_time": time.perf_counter() - search.start_time,
            "ordered_sons": search.request.ordered_sons,
            "posture_calls": by_kind}
