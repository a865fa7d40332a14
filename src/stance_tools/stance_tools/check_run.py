"""`stance check-run BAG [--scene NAME]`: checks on a contact plan's executed motion, read
from its bag without ROS (stance_tools.bag).

The bag must hold /joint_states and /pik/base_pose (pik_node, same header stamps),
/trajectory/active_stance and /trajectory/joint_trajectory (trajectory_node) and
/stabilizer/state (stabilizer_gate_node); the last execution in the bag (from the last
active stance 0 on) is checked. Times are header stamps (s); stance k is reached at its
active stance's stamp (the last one when trajectory_node announced it again: reached late
after waiting for the robot, late ticks, a pik_node pause or a slow set_stack call, or the
last stance executed), and the transition k -> k + 1 runs from stance k's stamp to stance
k + 1's: the trajectory's pace from the start, then its end sample until stance k + 1 is
reached (command_times). Positions are in the world frame (m), joints in rad.

Checks (one table each):
- contacts: every contact's spot (forward kinematics of the joint states and base pose)
  stays within CONTACT_TOLERANCE of its target from when its stance is reached until the
  transition that moves that spot starts, in the command's time the joint states track
  (as for equilibrium below);
- joint_limits: every joint state inside the URDF position limits (the whole bag);
- joint_velocity: finite differences of the joint states (from execution start on) over
  VELOCITY_WINDOW s (pik_node's stamps jitter by a period) under the URDF velocity limits
  times 1 + VELOCITY_TOLERANCE;
- trajectory_c1: the commanded JointTrajectory is C1 across its waypoints, within what
  its waypoint spacing can tell: no position step faster than the URDF velocity limit
  times 1 + VELOCITY_TOLERANCE (a position jump), no velocity step faster than
  C1_ACCELERATION_BOUND (a velocity jump);
- equilibrium: static equilibrium (equilibrium.contacts_equilibrium) of the CoM of the
  joint states on the supporting contacts, every EQUILIBRIUM_PERIOD s: during a transition
  the contacts common to both stances (they all support, as in the interpolation), after
  the last stance its supporting contacts. The support is the command's at the instant the
  joint state tracks: pik_node follows the commanded trajectory with a lag (its gains,
  periods missed under load), so a state sampled just after a contact's release still
  leans on it, and one sampled just after a landing has not landed yet (tracking_delays,
  at most MAX_TRACKING_DELAY);
- stabilizer: the enabled flips of /stabilizer/state are StabilizerGate.schedule's on the
  executed stances, each within STABILIZER_DELAY of its transition's start or end. A flip
  undone within STABILIZER_DELAY (a support released and a non-coplanar contact created
  at once: on for no time) counts as no switch, scheduled or published: whether the gate's
  timer ticks between the two is chance, and the stabilizer stays off either way.

Exit code 0 when every check passes, 1 when some fail (listed on stderr), 2 when the bag
cannot be read.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

JOINT_STATES = "/joint_states"
BASE_POSE = "/pik/base_pose"
ACTIVE_STANCE = "/trajectory/active_stance"
JOINT_TRAJECTORY = "/trajectory/joint_trajectory"
STABILIZER_STATE = "/stabilizer/state"
PLAN = "/contact_planner/plan"

CONTACT_TOLERANCE = 0.002        # m: held spot position against its contact target
POSITION_LIMIT_TOLERANCE = 1e-6  # rad (m): beyond a URDF position limit
VELOCITY_TOLERANCE = 0.1         # fraction above a URDF velocity limit
# s: finite differences over at least this time: pik_node limits each step to its nominal
# period, and after a late period its steps come closer together than that. Stamp intervals
# run from 0.8 to 4.3 ms (p1, p99) on a loaded machine: in the chair run, a joint moving at
# exactly its limit measured 1.13x it over 20 ms, 1.05x over 50 ms, 1.02x over 100 ms
VELOCITY_WINDOW = 0.05
# rad/s^2: velocity step / time step between waypoints; the sinusoidal timing (no
# acceleration limit) reaches ~200 on flat_steps with Talos
C1_ACCELERATION_BOUND = 500.0
EQUILIBRIUM_PERIOD = 0.1         # s between two equilibrium samples
MAX_TRACKING_DELAY = 0.3         # s: the largest lag of the joint states looked for
DELAY_STEP = 0.005               # s: resolution of the lag estimate
# rad: commanded states this close to the best match are as good: at rest or at the slow
# start of a transition the smallest such lag is taken (the support of the latest command)
DELAY_TOLERANCE = 1e-3
DELAY_CHUNK = 2000               # samples per lag evaluation (bounds its memory)
STABILIZER_DELAY = 0.15          # s: a flip against its scheduled time


@dataclass
class Check:
    """One check's table (columns, rows) and its failures (empty: passed)."""

    name: str
    columns: tuple
    rows: list = field(default_factory=list)
    failures: list = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return not self.failures


@dataclass
class Execution:
    """An executed plan read from a bag (module docstring for times and frames).

    joint_names (J,): /joint_states order; times (N,) s; joints (N, J) rad; q (N, nq):
    Pinocchio configurations (base pose of the same stamp); stances: library Stance per
    active stance (witness q unset) and stamps (K,) s; trajectory: (times (M,) s from
    its start, positions (M, J'), velocities (M, J'), joint names) or None; stabilizer:
    (times (L,) s, enabled (L,) bool, blend (L,))."""

    joint_names: list
    times: np.ndarray
    joints: np.ndarray
    q: np.ndarray
    stances: list
    stamps: np.ndarray
    trajectory: tuple | None
    stabilizer: tuple

    @cached_property
    def tracked_times(self) -> np.ndarray:
        """(N,) s: the command's time each joint state tracks, times minus its lag
        (tracking_delays); computed once for the contacts and equilibrium checks."""
        return self.times - tracking_delays(self, np.arange(len(self.times)))


def stamp_seconds(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def contact_from_frame(msg, scene):
    """Library Contact of a stance_msgs/Contact (decoded): its pose, the contact frame in
    the world, read as (x, y, theta) in its surface's frame."""
    import pinocchio as pin
    from stance.planning.contacts import Contact

    p, o = msg.pose.position, msg.pose.orientation
    frame = pin.SE3(pin.Quaternion(o.w, o.x, o.y, o.z).normalized().matrix(),
                    np.array([p.x, p.y, p.z]))
    local = scene.surfaces[msg.surface].pose.actInv(frame)
    theta = math.atan2(local.rotation[1, 0], local.rotation[0, 0])
    return Contact(msg.spot, msg.surface, float(local.translation[0]),
                   float(local.translation[1]), theta, bool(msg.in_stability))


def scene_name(bag) -> str | None:
    """The scene of the last plan recorded in the bag, None without one."""
    from .bag import read_messages

    name = None
    for _, _, msg in read_messages(bag, [PLAN]):
        name = msg.scene
    return name


def read_execution(bag, robot, scene) -> Execution:
    """The last execution in the bag; raises LookupError naming a missing topic."""
    from stance.planning.contacts import Stance

    from .bag import read_messages

    states, bases, stances, indices, trajectory, stabilizer = [], {}, [], [], None, []
    for topic, _, msg in read_messages(bag, [JOINT_STATES, BASE_POSE, ACTIVE_STANCE,
                                             JOINT_TRAJECTORY, STABILIZER_STATE]):
        if topic == JOINT_STATES:
            states.append((msg.header.stamp.sec, msg.header.stamp.nanosec, list(msg.name),
                           np.array(msg.position)))
        elif topic == BASE_POSE:
            p, o = msg.pose.position, msg.pose.orientation
            bases[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = \
                [p.x, p.y, p.z, o.x, o.y, o.z, o.w]
        elif topic == ACTIVE_STANCE:
            if msg.index == 0:
                stances, indices = [], []
            if indices and indices[-1] == msg.index:   # announced again: reached later
                stances.pop()
                indices.pop()
            indices.append(msg.index)
            stances.append((stamp_seconds(msg.header),
                            tuple(contact_from_frame(c, scene) for c in msg.contacts)))
        elif topic == JOINT_TRAJECTORY:
            trajectory = msg
        else:
            stabilizer.append((stamp_seconds(msg.header), msg.enabled, msg.blend))
    for name, missing in ((JOINT_STATES, not states), (BASE_POSE, not bases),
                          (ACTIVE_STANCE, not stances), (STABILIZER_STATE, not stabilizer)):
        if missing:
            raise LookupError(f"no {name} message in {bag}")
    names = states[0][2]
    q_index = [robot.model.joints[robot.joint_id(n)].idx_q for n in names]
    states = [s for s in states if (s[0], s[1]) in bases]
    times = np.array([sec + nanosec * 1e-9 for sec, nanosec, _, _ in states])
    joints = np.array([position for _, _, _, position in states])
    q = np.tile(robot.initial_configuration(), (len(states), 1))
    q[:, :7] = [bases[(sec, nanosec)] for sec, nanosec, _, _ in states]
    q[:, q_index] = joints
    stabilizer = tuple(np.array(column) for column in zip(*stabilizer))
    return Execution(names, times, joints, q,
                     [Stance(contacts, None) for _, contacts in stances],
                     np.array([stamp for stamp, _ in stances]),
                     None if trajectory is None else _trajectory_arrays(trajectory),
                     stabilizer)


def _trajectory_arrays(msg) -> tuple:
    times = np.array([p.time_from_start.sec + p.time_from_start.nanosec * 1e-9
                      for p in msg.points])
    return (times, np.array([p.positions for p in msg.points]),
            np.array([p.velocities for p in msg.points]), list(msg.joint_names))


# --- the checks ----------------------------------------------------------------------------

def held_intervals(stances, stamps) -> list:
    """(contact, first stance, last stance, start s, end s) for every contact kept at the
    same place over consecutive stances: held from when the first is reached until the
    transition leaving the last starts (the last stance: to the end of the run, inf)."""
    intervals, open_ = [], {}
    for k, stance in enumerate(stances):
        places = {c.spot: c for c in stance.contacts}
        for spot, (contact, first) in list(open_.items()):
            if spot not in places or _place(places[spot]) != _place(contact):
                intervals.append((contact, first, k - 1, stamps[first], stamps[k - 1]))
                del open_[spot]
        for spot, contact in places.items():
            open_.setdefault(spot, (contact, k))
    last = len(stances) - 1
    intervals += [(c, first, last, stamps[first], math.inf) for c, first in open_.values()]
    return sorted(intervals, key=lambda interval: (interval[3], interval[0].spot))


def _place(contact) -> tuple:
    return contact.surface, contact.x, contact.y, contact.theta


def spot_positions(robot, scene, q) -> dict:
    """{spot: (N, 3) world positions of its spot frame} at the configurations q (N, nq)."""
    import pinocchio as pin

    model, data = robot.model, robot.model.createData()
    frames = {name: (model.getFrameId(spot.frame), spot.placement)
              for name, spot in scene.spots.items()}
    positions = {name: np.empty((len(q), 3)) for name in frames}
    for i, configuration in enumerate(q):
        pin.forwardKinematics(model, data, configuration)
        for name, (frame_id, placement) in frames.items():
            positions[name][i] = (pin.updateFramePlacement(model, data, frame_id)
                                  * placement).translation
    return positions


def check_contacts(run: Execution, scene, positions) -> Check:
    """Spot positions (spot_positions of run.q) against the targets of the contacts held
    at the instant each joint state tracks (tracking_delays), until the command releases
    them: a state stamped after the transition that moves the spot started is not judged,
    even when its joints as a whole track an earlier instant (the lag is the slowest
    task's, the posture's; the spot's own task follows its lift at once)."""
    check = Check("contacts", ("spot", "surface", "stances", "samples", "max error (mm)"))
    tracked = run.tracked_times
    for contact, first, last, start, end in held_intervals(run.stances, run.stamps):
        inside = (tracked >= start) & (run.times <= end)
        target = contact.spot_target(scene.surfaces[contact.surface]).translation
        errors = np.linalg.norm(positions[contact.spot][inside] - target, axis=1)
        worst = float(errors.max()) if inside.any() else math.nan
        check.rows.append((contact.spot, contact.surface, f"{first}-{last}",
                           int(inside.sum()), f"{1e3 * worst:.3f}"))
        if not inside.any():
            check.failures.append(f"{contact.spot} on {contact.surface}, stances {first}-"
                                  f"{last}: no joint state while it is held")
        elif worst > CONTACT_TOLERANCE:
            at = run.times[inside][np.argmax(errors)] - run.stamps[0]
            check.failures.append(f"{contact.spot} on {contact.surface}, stances {first}-"
                                  f"{last}: {1e3 * worst:.2f} mm off its target at "
                                  f"t = {at:.2f} s (tolerance {1e3 * CONTACT_TOLERANCE:g} mm)")
    return check


def check_joint_limits(robot, names, times, joints) -> Check:
    """Joint positions (N, J) at times (N,) s against the URDF limits (robot)."""
    check = Check("joint_limits", ("joint", "lower", "min", "max", "upper"))
    column = {name: j for j, name in enumerate(names)}
    for name, lower, upper in zip(robot.limited_joint_names, robot.lower, robot.upper):
        if name not in column:
            continue
        values = joints[:, column[name]]
        low, high = float(values.min()), float(values.max())
        check.rows.append((name, f"{lower:.4f}", f"{low:.4f}", f"{high:.4f}", f"{upper:.4f}"))
        if low < lower - POSITION_LIMIT_TOLERANCE or high > upper + POSITION_LIMIT_TOLERANCE:
            worst = np.argmax(np.maximum(lower - values, values - upper))
            check.failures.append(f"{name}: {values[worst]:.4f} outside [{lower:.4f}, "
                                  f"{upper:.4f}] at t = {times[worst] - times[0]:.2f} s")
    return check


def check_joint_velocity(robot, names, times, joints) -> Check:
    """Joint speeds of joints (N, J) at times (N,) s, differences over VELOCITY_WINDOW,
    against the URDF velocity limits (robot) times 1 + VELOCITY_TOLERANCE."""
    check = Check("joint_velocity", ("joint", "max |v| (rad/s)", "limit", "ratio"))
    column = {name: j for j, name in enumerate(names)}
    later = np.searchsorted(times, times + VELOCITY_WINDOW)
    first = np.flatnonzero(later < len(times))
    dt = times[later[first]] - times[first]
    for name, limit in zip(robot.limited_joint_names, robot.velocity_limit):
        if name not in column:
            continue
        values = joints[:, column[name]]
        speeds = np.abs(values[later[first]] - values[first]) / dt
        worst = float(speeds.max()) if speeds.size else 0.0
        check.rows.append((name, f"{worst:.3f}", f"{limit:.3f}", f"{worst / limit:.2f}"))
        if worst > limit * (1.0 + VELOCITY_TOLERANCE):
            at = times[first[np.argmax(speeds)]] - times[0]
            check.failures.append(f"{name}: {worst:.3f} rad/s over its limit {limit:.3f} "
                                  f"at t = {at:.2f} s")
    return check


def check_trajectory_c1(robot, times, positions, velocities, names) -> Check:
    """C1 continuity of waypoints (module docstring): times (M,) s, positions and
    velocities (M, J) of the joints `names`; limits from robot."""
    check = Check("trajectory_c1", ("joint", "max |dq|/dt (rad/s)", "limit",
                                    "max |dv|/dt (rad/s^2)"))
    dt = np.diff(times)
    if np.any(dt <= 0.0):
        check.failures.append("waypoint times not increasing")
        return check
    limits = dict(zip(robot.limited_joint_names, robot.velocity_limit))
    rates = np.abs(np.diff(positions, axis=0)) / dt[:, None]
    accelerations = np.abs(np.diff(velocities, axis=0)) / dt[:, None]
    for j, name in enumerate(names):
        rate, acceleration = float(rates[:, j].max()), float(accelerations[:, j].max())
        limit = limits.get(name, math.inf)
        check.rows.append((name, f"{rate:.3f}", f"{limit:.3f}", f"{acceleration:.1f}"))
        if rate > limit * (1.0 + VELOCITY_TOLERANCE):
            check.failures.append(f"{name}: position jump: {rate:.2f} rad/s over its limit "
                                  f"{limit:.2f} into waypoint {int(np.argmax(rates[:, j])) + 1}")
        if acceleration > C1_ACCELERATION_BOUND:
            check.failures.append(f"{name}: velocity jump: {acceleration:.0f} rad/s^2 into "
                                  f"waypoint {int(np.argmax(accelerations[:, j])) + 1}")
    return check


def support_at(stances, stamps, t: float) -> tuple:
    """(stance k, supporting contacts) at time t s: during k -> k + 1 the contacts common to
    both (all supporting), after the last stance its supporting ones; None before start."""
    if t < stamps[0]:
        return None
    k = int(np.searchsorted(stamps, t, side="right")) - 1
    if k >= len(stances) - 1:
        return k, stances[-1].supporting()
    after = {_place(c) + (c.spot,) for c in stances[k + 1].contacts}
    return k, tuple(c.with_stability(True) for c in stances[k].contacts
                    if _place(c) + (c.spot,) in after)


def centers_of_mass(robot, q) -> np.ndarray:
    """(N, 3) world CoM at the configurations q (N, nq)."""
    import pinocchio as pin

    data = robot.model.createData()
    return np.array([pin.centerOfMass(robot.model, data, c, False) for c in q])


def check_equilibrium(run: Execution, robot, scene, com) -> Check:
    """Static equilibrium of com (N, 3) on the supports of run (equilibrium_samples) at the
    instants the joint states track (tracking_delays); one row per stance k (its
    transition k -> k + 1) with its largest lag."""
    import pinocchio as pin
    from stance.planning.equilibrium import contacts_equilibrium

    check = Check("equilibrium", ("from stance", "support", "samples", "min margin (N)",
                                  "max lag (s)"))
    mass = pin.computeTotalMass(robot.model)
    rows = {}
    for i in equilibrium_samples(run.times, run.stamps):
        delay = run.times[i] - run.tracked_times[i]
        tracked = max(run.tracked_times[i], run.stamps[0])
        k, support = support_at(run.stances, run.stamps, tracked)
        result = contacts_equilibrium(support, scene, com[i], mass)
        spots = ", ".join(sorted(c.spot for c in support))
        count, worst, lag = rows.get(k, (spots, 0, math.inf, 0.0))[1:]
        rows[k] = (spots, count + 1, min(worst, result.margin), max(lag, delay))
        if not result.feasible:
            check.failures.append(f"t = {run.times[i] - run.stamps[0]:.2f} s (tracking "
                                  f"{tracked - run.stamps[0]:.2f} s), from stance {k} on "
                                  f"{spots}: no static equilibrium (margin "
                                  f"{result.margin:.1f} N)")
    for k, (spots, count, worst, lag) in sorted(rows.items()):
        check.rows.append((k, spots, count, f"{worst:.1f}", f"{lag:.3f}"))
    return check


def tracking_delays(run: Execution, indices) -> np.ndarray:
    """How late (s) the joint states at indices follow the commanded trajectory: per
    sample, the smallest multiple of DELAY_STEP in [0, MAX_TRACKING_DELAY] whose commanded
    joints (C1 Hermite interpolation of the waypoints) are within DELAY_TOLERANCE (max over
    joints, rad) of the closest ones. Zeros without a trajectory. Commands come from
    command_times. A pik_node pause mid-transition shifts trajectory_node's time base but
    not the stamps it already announced: samples up to the next stance announced are
    measured ahead of their command by the pause."""
    from scipy.interpolate import CubicHermiteSpline

    indices = np.asarray(indices, dtype=int)
    found = np.zeros(len(indices))
    if run.trajectory is None:
        return found
    times, positions, velocities, names = run.trajectory
    columns = [run.joint_names.index(name) for name in names]
    commanded = CubicHermiteSpline(times, positions, velocities, axis=0)
    delays = np.arange(0.0, MAX_TRACKING_DELAY + 0.5 * DELAY_STEP, DELAY_STEP)
    for begin in range(0, len(indices), DELAY_CHUNK):   # (S, D, J) arrays of bounded size
        chunk = indices[begin:begin + DELAY_CHUNK]
        when = command_times(run.stamps, times, run.times[chunk, None] - delays)  # (S, D)
        errors = np.abs(commanded(np.clip(when, times[0], times[-1]))
                        - run.joints[chunk][:, None, columns]).max(axis=2)   # (S, D)
        close = errors <= errors.min(axis=1, keepdims=True) + DELAY_TOLERANCE
        found[begin:begin + DELAY_CHUNK] = delays[np.argmax(close, axis=1)]
    return found


def command_times(stamps, waypoint_times, wall) -> np.ndarray:
    """Trajectory time (s from its start) commanded at wall times (s; any shape), given
    when each stance was reached (stamps (K,) s) and the JointTrajectory's waypoint times
    (M,): from stance j's stamp, transition j at the trajectory's pace, then its end
    sample until stance j + 1's stamp (trajectory_node waited there for the robot; after
    late ticks, the end came later than this pace says). Without a wait this is
    wall - start. Stance samples: every (M - 1) / (K - 1)-th waypoint."""
    per_transition = (len(waypoint_times) - 1) // max(len(stamps) - 1, 1)
    boundaries = waypoint_times[::per_transition][:len(stamps)]
    j = np.clip(np.searchsorted(stamps, wall, side="right") - 1, 0, len(stamps) - 1)
    ends = boundaries[np.minimum(j + 1, len(boundaries) - 1)]
    return np.minimum(boundaries[j] + (np.asarray(wall) - stamps[j]), ends)


def equilibrium_samples(times, stamps) -> np.ndarray:
    """Indices of the samples from stamps[0] (s) on: one per EQUILIBRIUM_PERIOD s and one
    in the middle of each transition (stamps: when each stance is reached)."""
    grid = np.concatenate([np.arange(stamps[0], times[-1], EQUILIBRIUM_PERIOD),
                           0.5 * (stamps[1:] + stamps[:-1])])
    return np.unique(np.clip(np.searchsorted(times, grid), 0, len(times) - 1))


def expected_switches(stances, stamps, gate) -> tuple:
    """(initial enabled, [(time s, enabled, reason)]) of gate.schedule on the stances."""
    from stance.execution.stabilizer import START

    initial = gate.support(0, stances[0].contacts).coplanar
    events = gate.schedule([s.contacts for s in stances])
    return initial, [(stamps[e.stance_index - 1] if e.at == START else stamps[e.stance_index],
                      e.enabled, e.reason) for e in events]


def check_stabilizer(initial, expected, times, enabled, origin: float) -> Check:
    """Flips of `enabled` (L,) at `times` (L,) s against expected (expected_switches);
    origin: the execution start (s), for the table."""
    check = Check("stabilizer", ("switch", "expected t (s)", "actual t (s)", "enabled"))
    flips = _without_blips([(times[i], bool(enabled[i]))
                            for i in np.flatnonzero(np.diff(enabled)) + 1])
    expected = _without_blips(expected)
    if bool(enabled[0]) != initial:
        check.failures.append(f"starts {'on' if enabled[0] else 'off'}, the first stance's "
                              f"support says {'on' if initial else 'off'}")
    for n in range(max(len(flips), len(expected))):
        want = expected[n] if n < len(expected) else None
        got = flips[n] if n < len(flips) else None
        check.rows.append((n, "-" if want is None else f"{want[0] - origin:.2f}",
                           "-" if got is None else f"{got[0] - origin:.2f}",
                           (want or got)[1]))
        if want is None:
            check.failures.append(f"unexpected switch to {got[1]} at t = "
                                  f"{got[0] - origin:.2f} s")
        elif got is None:
            check.failures.append(f"missing switch: {want[2]}")
        elif got[1] != want[1] or abs(got[0] - want[0]) > STABILIZER_DELAY:
            check.failures.append(f"switch {n} to {got[1]} at t = {got[0] - origin:.2f} s, "
                                  f"expected to {want[1]} at {want[0] - origin:.2f} s")
    return check


def _without_blips(switches: list) -> list:
    """switches ((time s, enabled, ...), in time order) without the pairs whose second
    undoes the first within STABILIZER_DELAY."""
    kept = []
    for switch in switches:
        if kept and kept[-1][1] != switch[1] and switch[0] - kept[-1][0] <= STABILIZER_DELAY:
            kept.pop()
        else:
            kept.append(switch)
    return kept


@dataclass
class Report:
    """The checks of a run and what the demo's plots reuse: robot, run, com (N, 3), spot
    positions {spot: (N, 3)}."""

    checks: list
    robot: object
    run: Execution
    com: np.ndarray
    positions: dict

    @property
    def passed(self) -> bool:
        return all(check.passed for check in self.checks)


def check_bag(bag, scene_spec: str | None = None) -> Report:
    """Every check on a bag; raises LookupError (missing topic or scene), OSError."""
    from stance.execution.stabilizer import StabilizerGate
    from stance.planning.scene import load_scene
    from stance.robot import Robot

    scene_spec = scene_spec or scene_name(bag)
    if not scene_spec:
        raise LookupError(f"no {PLAN} in {bag}: name the scene with --scene")
    scene = load_scene(scene_spec)
    robot = Robot.load(scene.robot)
    run = read_execution(bag, robot, scene)
    positions = spot_positions(robot, scene, run.q)
    com = centers_of_mass(robot, run.q)
    executing = run.times >= run.stamps[0]
    checks = [check_contacts(run, scene, positions),
              check_joint_limits(robot, run.joint_names, run.times, run.joints),
              check_joint_velocity(robot, run.joint_names, run.times[executing],
                                   run.joints[executing])]
    if run.trajectory is None:
        missing = Check("trajectory_c1", ("problem",))
        missing.failures.append(f"no {JOINT_TRAJECTORY} message")
        checks.append(missing)
    else:
        checks.append(check_trajectory_c1(robot, *run.trajectory))
    checks.append(check_equilibrium(run, robot, scene, com))
    initial, expected = expected_switches(run.stances, run.stamps, StabilizerGate(scene))
    checks.append(check_stabilizer(initial, expected, run.stabilizer[0], run.stabilizer[1],
                                   run.stamps[0]))
    return Report(checks, robot, run, com, positions)


def format_table(check: Check, max_rows: int = 40) -> str:
    """The check's table as aligned text; at most max_rows rows (the rest counted)."""
    rows = [tuple(str(v) for v in row) for row in check.rows[:max_rows]]
    widths = [max(len(str(c)), *(len(r[i]) for r in rows)) if rows else len(str(c))
              for i, c in enumerate(check.columns)]
    lines = [f"== {check.name}: {'PASS' if check.passed else 'FAIL'}",
             "  ".join(str(c).ljust(w) for c, w in zip(check.columns, widths))]
    lines += ["  ".join(v.ljust(w) for v, w in zip(row, widths)) for row in rows]
    if len(check.rows) > max_rows:
        lines.append(f"... {len(check.rows) - max_rows} more rows")
    return "\n".join(lines)


def add_arguments(parser) -> None:
    parser.add_argument("bag", help="bag directory or .mcap file")
    parser.add_argument("--scene", help="scene name or YAML path (default: the scene of the "
                                        f"plan on {PLAN} in the bag)")


def run(args) -> int:
    bag = Path(args.bag)
    if not bag.exists():
        print(f"stance check-run: {bag} does not exist", file=sys.stderr)
        return 2
    try:
        report = check_bag(bag, args.scene)
    except (LookupError, OSError, ValueError) as error:
        print(f"stance check-run: {error}", file=sys.stderr)
        return 2
    return print_report(report)


def print_report(report: Report) -> int:
    """Tables on stdout, failures on stderr; the exit code (0 all passed, 1 otherwise)."""
    for check in report.checks:
        print(format_table(check) + "\n")
    failed = [check for check in report.checks if not check.passed]
    for check in failed:
        for failure in check.failures:
            print(f"FAIL {check.name}: {failure}", file=sys.stderr)
    print(f"check-run: {len(report.checks) - len(failed)}/{len(report.checks)} checks passed"
          + (f"; failed: {', '.join(c.name for c in failed)}" if failed else ""))
    return 1 if failed else 0
