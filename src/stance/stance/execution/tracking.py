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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from ..stack import TaskSpec

GAINS = {"contact": 0.5, "com": 0.5, "posture": 0.3}  # trajectory_node's defaults


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
    """(stack, {held spot: frame target}) of transition `transition` (stance i -> i + 1);
    planner: the TransitionPlanner that interpolated the plan."""
    first, second = plan.stances[transition], plan.stances[transition + 1]
    moving = planner.moving_paths(first, second)
    held = [contact for contact in first.contacts if contact.spot not in moving]
    specs = execution_stack(scene, held, sorted(moving), gains)
    return specs, {contact.spot: held_frame_target(scene, contact) for contact in held}


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
    position error after the step (m), velocity-limit factor (1: not slowed)."""

    times: np.ndarray
    transitions: np.ndarray
    held_error: np.ndarray
    velocity_scale: np.ndarray

    def worst(self) -> tuple:
        """(error m, time s, transition) of the largest held-contact error."""
        k = int(np.argmax(self.held_error))
        return float(self.held_error[k]), float(self.times[k]), int(self.transitions[k])


def track(solver, scene, planner, plan, path, trajectory, rate: float = 500.0,
          target_rate: float = 100.0, gains=None) -> Tracking:
    """Track the timed plan with `solver` (a PIKSolver; its dt should be 1 / rate) from the
    first witness. path: planner.interpolate(plan); trajectory: its timing."""
    gains = GAINS if gains is None else gains
    model = solver.robot.model
    data, scratch = pin.Data(model), pin.Data(model)
    boundaries = trajectory.times[path.stance_samples]
    last = len(plan.stances) - 2
    steps = int(np.ceil(trajectory.duration * rate))
    refresh = max(1, int(round(rate / target_rate)))
    times = np.arange(steps) / rate
    transitions = np.zeros(steps, dtype=np.int64)
    held_error, velocity_scale = np.zeros(steps), np.ones(steps)
    q = plan.stances[0].q.copy()
    transition = 0
    stack, held = transition_tasks(scene, planner, plan, 0, gains)
    solver.set_stack(stack, q)
    frames = {spot: model.getFrameId(scene.spots[spot].frame) for spot in scene.spots}
    for k, t in enumerate(times):
        while transition < last and t >= boundaries[transition + 1]:
            transition += 1
            stack, held = transition_tasks(scene, planner, plan, transition, gains)
            solver.set_stack(stack, q)
        if k % refresh == 0:
            for name, target in task_targets(model, scratch, stack, held,
                                             trajectory.sample(t)[0]).items():
                solver.task(name).target = target
        result = solver.step(q)
        q = result.q
        pin.framesForwardKinematics(model, data, q)
        transitions[k], velocity_scale[k] = transition, result.velocity_scale
        held_error[k] = max((np.linalg.norm(data.oMf[frames[spot]].translation
                                            - target.translation)
                             for spot, target in held.items()), default=0.0)
    return Tracking(times, transitions, held_error, velocity_scale)
