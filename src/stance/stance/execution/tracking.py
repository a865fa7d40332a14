"""Tracking a timed contact plan with the PIK solver, as the node graph does, offline.

The execution's task stack per transition (stance i -> i + 1), shared with trajectory_node:
the contacts held through the transition as pose tasks on their spots' robot frames at
priority 0 (target: the exact contact), the moving spots as pose tasks and the CoM (x, y)
at priority 1, the posture at priority 2.

`track` replays what trajectory_node and pik_node do together, without DDS: the targets of
the moving spots, CoM and posture are the forward kinematics of the trajectory sampled at
`target_rate`, the solver steps at `rate` from the first witness, and the stack changes
when the trajectory reaches a stance. It measures how far every held contact's frame is
from its target (m), the quantity `stance check-run` bounds, and how often the velocity
limits had to slow the motion. Deterministic: the same inputs give the same tracking.

A transition starts only once the robot is at the stance before it: at the end of each
transition the trajectory's clock holds (`ArrivalGate`) until each contact it creates has
its frame within ARRIVAL_TOLERANCE of its exact target and the CoM (x, y) is within
ARRIVAL_COM_TOLERANCE of the stance witness's. Only then does the next stack hold the created
contacts at priority 0, and only then may the next transition release a contact. The time
law has the robot at rest there, so waiting costs nothing when the IK keeps up; when it
lags (a loaded machine, missed control periods, velocity limits), holding a contact at its
exact target from a frame still centimetres away would drag it along the surface, and
lifting a foot with the CoM still on its way over the other would leave the robot out of
balance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ..stack import TaskSpec

GAINS = {"contact": 0.5, "com": 0.5, "posture": 0.3}  # trajectory_node's defaults
# (m, rad): a created contact's frame this close to its exact target counts as arrived;
# half check-run's 2 mm contact tolerance, reached within a few IK steps of rest
ARRIVAL_TOLERANCE = (1e-3, 1e-2)
# m: the CoM (x, y) this close to the stance witness's counts as arrived. Over DDS it ends a
# transition 1-2 mm behind its streamed target (the targets' latency); a lag that matters
# for balance is centimetres (a foot is 10-20 cm)
ARRIVAL_COM_TOLERANCE = 5e-3
ARRIVAL_TIMEOUT = 5.0   # s a transition's end waits for the robot to arrive at most


def held_frame_target(scene, contact) -> pin.SE3:
    """World pose of the robot frame carrying contact's spot when the contact is exact:
    spot target * placement^-1."""
    spot = scene.spots[contact.spot]
    return contact.spot_target(scene.surfaces[contact.surface]) * spot.placement.inverse()


def execution_stack(scene, held, moving, gains) -> list:
    """TaskSpecs for one transition: held contacts as pose tasks on their spots' robot
    frames at priority 0, moving spots as pose tasks at priority 1 with the CoM (x, y),
    posture at priority 2. gains: {'contact', 'com', 'posture'}; task names: spot names."""
    specs = [TaskSpec(name=c.spot, kind="pose", frame=scene.spots[c.spot].frame, priority=0,
                      gain=gains["contact"]) for c in held]
    specs += [TaskSpec(name=spot, kind="pose", frame=scene.spots[spot].frame, priority=1,
                       gain=gains["contact"]) for spot in moving]
    specs += [TaskSpec(name="com", kind="com", priority=1, axes=("x", "y"), gain=gains["com"]),
              TaskSpec(name="posture", kind="posture", priority=2, gain=gains["posture"])]
    return specs


def transition_tasks(scene, planner, plan, transition: int, gains) -> tuple:
    """(stack, held, created) of transition `transition` (stance i -> i + 1): its task
    stack, {held spot: frame target (pin.SE3, world)} and the same for the contacts it
    creates (spots moving in it and in contact in stance i + 1). planner: the
    TransitionPlanner that interpolated the plan."""
    first, second = plan.stances[transition], plan.stances[transition + 1]
    moving = planner.moving_paths(first, second)
    held = [contact for contact in first.contacts if contact.spot not in moving]
    specs = execution_stack(scene, held, sorted(moving), gains)
    created = {spot: held_frame_target(scene, after)
               for spot, (_, _, after) in moving.items() if after is not None}
    return specs, {c.spot: held_frame_target(scene, c) for c in held}, created


def witness_com(model, data, stance) -> np.ndarray:
    """(x, y) world CoM (m) of stance's witness configuration; data: scratch Data of model."""
    return pin.centerOfMass(model, data, stance.q, False)[:2].copy()


class ArrivalGate:
    """Whether the robot is at the stance a transition ends in, so that its end may pass:
    the contacts the transition creates are made and the CoM is over the witness's.

    targets: {spot: frame target (pin.SE3, world)} (transition_tasks' created); tolerance:
    (m, rad) for them; timeout: s the end waits at most; com: (x, y) world (m) the CoM must
    reach within com_tolerance m (witness_com), None to skip. `update` is called at every
    tick the trajectory sits at the transition's end, with the current poses."""

    def __init__(self, targets: dict, tolerance=ARRIVAL_TOLERANCE,
                 timeout: float = ARRIVAL_TIMEOUT, com=None,
                 com_tolerance: float = ARRIVAL_COM_TOLERANCE):
        self.targets, self.tolerance, self.timeout = targets, tolerance, timeout
        self.com = None if com is None else np.asarray(com, dtype=float)[:2]
        self.com_tolerance = com_tolerance
        self.waiting_since = None   # s (the caller's clock) of the first update not arrived
        self.late = {}              # {spot or 'com': (m, rad)} off target at the last update
        self.late_when_due = {}     # the same at the first update (the transition's end)

    def update(self, poses: dict, now: float, com=None) -> bool:
        """True when every created contact's frame (poses: {spot: pin.SE3}; a missing spot
        is not arrived) is within tolerance of its target and the CoM (com: world (x, y...)
        m; None: not arrived) within com_tolerance of self.com; False while not."""
        self.late = {}
        if self.com is not None:
            offset = math.inf if com is None else math.dist(np.asarray(com)[:2], self.com)
            if offset > self.com_tolerance:
                self.late["com"] = (offset, 0.0)
        for spot, target in self.targets.items():
            pose = poses.get(spot)
            if pose is None:
                self.late[spot] = (math.inf, math.inf)
                continue
            offset = (math.dist(pose.translation, target.translation),
                      float(np.linalg.norm(pin.log3(target.rotation.T @ pose.rotation))))
            if offset[0] > self.tolerance[0] or offset[1] > self.tolerance[1]:
                self.late[spot] = offset
        if self.late and self.waiting_since is None:
            self.waiting_since, self.late_when_due = now, dict(self.late)
        return not self.late

    def waited(self, now: float) -> float:
        """s spent waiting so far (0 when the contacts were there at once)."""
        return 0.0 if self.waiting_since is None else now - self.waiting_since

    def timed_out(self, now: float) -> bool:
        return self.waited(now) > self.timeout

    def describe_late(self, late: dict | None = None) -> str:
        """'com 4.1 mm off; spot 12.3 mm, 0.045 rad off; ...' for `late` (default: the
        last update's)."""
        late = self.late if late is None else late
        return "; ".join(f"com {1e3 * position:.1f} mm off" if name == "com" else
                         f"{name} {1e3 * position:.1f} mm, {angle:.3f} rad off"
                         for name, (position, angle) in sorted(late.items()))


def task_targets(model, data, stack, held, q) -> dict:
    """{task name: target} of `stack` at configuration q (nq), as trajectory_node streams
    them: held contacts their exact frame target (pin.SE3), other frames their pose at q
    (pin.SE3), the CoM its position at q (3, world), the posture q itself. data: scratch
    pinocchio Data of model."""
    pin.framesForwardKinematics(model, data, q)
    targets = {}
    for spec in stack:
        if spec.kind == "posture":
            targets[spec.name] = np.array(q, dtype=float)
        elif spec.kind == "com":
            targets[spec.name] = pin.centerOfMass(model, data, q, False).copy()
        else:
            targets[spec.name] = held[spec.name] if spec.name in held \
                else data.oMf[model.getFrameId(spec.frame)].copy()
    return targets


@dataclass
class Tracking:
    """Per IK step: time (s from the start), transition index, largest held-contact frame
    position error after the step (m), velocity-limit factor (1: not slowed), CoM after the
    step (3, world, m). holds: per transition end that waited for the robot to arrive
    (ArrivalGate), (transition, s waited, arrived: False when it timed out)."""

    times: np.ndarray
    transitions: np.ndarray
    held_error: np.ndarray
    velocity_scale: np.ndarray
    com: np.ndarray
    holds: list

    def worst(self) -> tuple:
        """(error m, time s, transition) of the largest held-contact error."""
        k = int(np.argmax(self.held_error))
        return float(self.held_error[k]), float(self.times[k]), int(self.transitions[k])


def track(solver, scene, planner, plan, path, trajectory, rate: float = 500.0,
          target_rate: float = 100.0, gains=None, tolerance=ARRIVAL_TOLERANCE,
          timeout: float = ARRIVAL_TIMEOUT,
          com_tolerance: float = ARRIVAL_COM_TOLERANCE) -> Tracking:
    """Track the timed plan with `solver` (a PIKSolver; its dt should be 1 / rate) from the
    first witness. path: planner.interpolate(plan); trajectory: its timing. The clock
    holds at each transition's end until its created contacts are made and the CoM is over
    the stance's (ArrivalGate with tolerance (m, rad), timeout s and com_tolerance m: a
    timed-out wait is recorded, and tracking goes on)."""
    gains = GAINS if gains is None else gains
    model = solver.robot.model
    data, scratch = pin.Data(model), pin.Data(model)
    boundaries = trajectory.times_of(path.stance_samples)
    last = len(plan.stances) - 2
    refresh = max(1, int(round(rate / target_rate)))
    times, transitions, held_error, velocity_scale, com, holds = [], [], [], [], [], []
    q = plan.stances[0].q.copy()
    transition, clock, k = 0, 0.0, 0      # clock: s of trajectory time (frozen by holds)

    def enter(index):
        stack, held, created = transition_tasks(scene, planner, plan, index, gains)
        solver.set_stack(stack, q)
        there = witness_com(model, scratch, plan.stances[index + 1])
        return stack, held, ArrivalGate(created, tolerance, timeout, there, com_tolerance)

    stack, held, gate = enter(0)
    frames = {spot: model.getFrameId(scene.spots[spot].frame) for spot in scene.spots}
    pin.framesForwardKinematics(model, data, q)
    center = pin.centerOfMass(model, data, False).copy()
    while True:
        now = k / rate
        if clock >= boundaries[transition + 1]:
            arrived = gate.update({spot: data.oMf[frames[spot]] for spot in gate.targets}, now,
                                  center)
            if not (arrived or gate.timed_out(now)):
                clock = boundaries[transition + 1]
            else:
                if gate.waiting_since is not None:
                    holds.append((transition, gate.waited(now), arrived))
                if transition == last:
                    break
                transition += 1
                stack, held, gate = enter(transition)
        if k % refresh == 0:
            for name, target in task_targets(model, scratch, stack, held,
                                             trajectory.sample(clock)[0]).items():
                solver.task(name).target = target
        result = solver.step(q)
        q = result.q
        pin.framesForwardKinematics(model, data, q)
        center = pin.centerOfMass(model, data, False).copy()   # at the kinematics just done
        com.append(center)
        times.append(now)
        transitions.append(transition)
        velocity_scale.append(result.velocity_scale)
        held_error.append(max((np.linalg.norm(data.oMf[frames[spot]].translation
                                              - target.translation)
                               for spot, target in held.items()), default=0.0))
        k += 1
        clock = min(clock + 1.0 / rate, trajectory.duration)
    return Tracking(np.array(times), np.array(transitions, dtype=np.int64),
                    np.array(held_error), np.array(velocity_scale), np.array(com), holds)
