"""Whole PIK runs against swing and ball-and-socket limits, shared by the swing, joint
group and soak tests: the mannequin (spherical joints) and Talos (joint groups), with
random targets moved by < 0.3 m (reachable) or 1-3 m (unreachable)."""

import numpy as np
import pinocchio as pin
from helpers.problems import random_offset
from stance.pik import PIKSolver
from stance.qp_hierarchy import QPHierarchy
from stance.stack import TaskSpec
from stance.swing import rotation_from_swing_twist, swing_twist


def swing_excess(model, q) -> float:
    """How far (rad) the model's swing lies outside its domain (0 inside)."""
    s, _ = swing_twist(model.rotation(q))
    return max(0.0, -model.domain.signed_distance(s))


def twist_excess(model, q) -> float:
    """How far (rad) the model's twist lies beyond its interval (0 inside or free)."""
    if model.twist is None:
        return 0.0
    theta = swing_twist(model.rotation(q))[1]
    return max(0.0, theta - model.twist.upper[0], model.twist.lower[0] - theta)


def bound_excess(model, q) -> float:
    """How far (rad) a joint group's joints lie beyond their own bounds (0 inside)."""
    angles = q[model.q_index]
    return float(max(0.0, np.max(angles - model.bounds.upper),
                     np.max(model.bounds.lower - angles)))


def set_swing_twist(robot, q, joint, s, theta) -> None:
    """Set spherical joint `joint` of q (in place) to swing s and twist theta (rad)."""
    start = robot.model.joints[robot.joint_id(joint)].idx_q
    q[start:start + 4] = pin.Quaternion(rotation_from_swing_twist(s, theta)).coeffs()


def mannequin_start(robot, limit_models, rng) -> np.ndarray:
    """Standing, with every swing/ball joint at a random state inside its limits."""
    q = robot.initial_configuration("standing")
    for model in limit_models:
        while True:
            s = rng.uniform(-1.5, 1.5, 2)
            if model.domain.contains(s):
                break
        theta = 0.0 if model.twist is None else rng.uniform(model.twist.lower[0],
                                                            model.twist.upper[0])
        set_swing_twist(robot, q, model.joint, s, theta)
    return q


def mannequin_run(robot, limit_models, start, seed, reachable, strategy="progressive",
                  steps=40, compiled_loop=True, hierarchy="svd"):
    """(q, StepResult) after each step: left sole > CoM > right hand and right toes toward
    random targets > posture. compiled_loop: False runs the general (Python) clamping
    loop (PIKSolver's). hierarchy: svd or qp (QPHierarchy with the robot's joint bounds)."""
    stack = [TaskSpec("left_sole", "pose", frame="left_sole", priority=0, gain=0.5),
             TaskSpec("com", "com", priority=1, axes=("x", "y"), gain=0.2),
             TaskSpec("right_hand", "position", frame="right_hand", priority=2, gain=0.5),
             TaskSpec("right_toe", "position", frame="right_toe", priority=2, gain=0.5),
             TaskSpec("posture", "posture", priority=3, gain=0.02)]
    return _run(robot, limit_models, stack, start, ("right_hand", "right_toe"), seed,
                reachable, strategy, steps, compiled_loop, hierarchy)


def talos_group_run(robot, groups, seed, reachable, strategy="progressive", steps=40,
                    start=None, hierarchy="svd"):
    """(q, StepResult) after each step from `start` (default half_sitting): right foot >
    CoM > left foot and both hands toward random targets > posture."""
    moving = ("left_sole_link", "gripper_left_base_link", "gripper_right_base_link")
    stack = [TaskSpec("right_foot", "pose", frame="right_sole_link", priority=0, gain=0.5),
             TaskSpec("com", "com", priority=1, axes=("x", "y"), gain=0.2),
             *[TaskSpec(frame, "position", frame=frame, priority=2, gain=0.5)
               for frame in moving],
             TaskSpec("posture", "posture", priority=3, gain=0.02)]
    start = robot.initial_configuration() if start is None else start
    return _run(robot, groups, stack, start, moving, seed, reachable, strategy, steps,
                hierarchy=hierarchy)


def _run(robot, limit_models, stack, start, moving, seed, reachable, strategy, steps,
         compiled_loop=True, hierarchy="svd"):
    rng = np.random.default_rng(seed)
    solver = PIKSolver(robot, strategy=strategy, limit_models=limit_models,
                       compiled_loop=compiled_loop,
                       hierarchy=QPHierarchy.for_robot(robot) if hierarchy == "qp" else None)
    assert solver._one_call_loop == compiled_loop, "the limit models run in the compiled loop"
    solver.set_stack(stack, start)
    for name in moving:
        task = solver.task(name)
        target = task.target
        target.translation += random_offset(rng, reachable)
        task.set_target(target)
    q = start
    for _ in range(steps):
        result = solver.step(q)
        q = result.q
        yield q, result
