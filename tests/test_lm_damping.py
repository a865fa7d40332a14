"""Levenberg-Marquardt damping (PIKSolver's lm_damping): each level's damped least squares
lambda_k^2 = damping^2 + lm_damping |e_k|^2 over its step targets of the tasks that curve.
Talos' hands driven out of reach make the joints chatter step to step without it (the
hierarchy's Gauss-Newton step overshoots around the closest reachable posture); with it they
hold still, and reachable targets converge as fast as before. Strict priorities hold with it
(tests/test_priority.py)."""

import math

import numpy as np
import pinocchio as pin
import pytest
from stance_tools.bench import (GROUP_SCENARIOS, SUPPORT_SCENARIOS, TALOS_LEVEL_STACK,
                                bench_start, bench_targets, support_solver)

from stance.pik import LM_DAMPING, PIKSolver
from stance.robot import Robot
from stance.stack import TaskSpec, parse_stack_yaml

STEPS = 400
DT = 0.002


@pytest.fixture(scope="module")
def talos():
    return Robot.load("talos")


def talos_run(robot, scenario, lm_damping, dt=DT, hierarchy="svd", com_ahead=0.0,
              steps=STEPS, watched="right_hand"):
    """(dq per step, the `watched` task's error per step, StepResult of the last step) on
    feet > CoM > both hands > posture, the CoM's target com_ahead m in front of its start."""
    specs = parse_stack_yaml(TALOS_LEVEL_STACK)
    start = bench_start(robot)
    targets = bench_targets(robot, specs, start, GROUP_SCENARIOS[scenario])
    solver = PIKSolver(robot, dt=dt, hierarchy=hierarchy, lm_damping=lm_damping)
    solver.set_stack(specs, start)
    for spec in specs:
        solver.task(spec.name).target = targets[spec.name]
    solver.task("com").target = solver.task("com").target + [com_ahead, 0.0, 0.0]
    q, variations, errors = start, [], []
    for _ in range(steps):
        result = solver.step(q)
        q = result.q
        variations.append(result.dq)
        errors.append(result.task_errors[watched])
    return np.array(variations), np.array(errors), result


def chatter(steps) -> float:
    """Largest change of a joint's variation from one step to the next over the second
    half of the run (rad): about 0 where the joints hold still or move smoothly. Without
    LM damping the run is chaotic: rounding decides when the jumps happen and whether
    they stop (a change in the last bits of the hierarchy's kernels left the plain run
    still, far from its targets, for its last 100 steps)."""
    return float(np.abs(np.diff(steps[len(steps) // 2:, 6:], axis=0)).max())


def hand_and_posture_solver(robot, lm_damping) -> PIKSolver:
    """A right hand position 5 cm from its target (gain 0.1) over a posture task."""
    q = robot.initial_configuration()
    solver = PIKSolver(robot, damping=1e-3, lm_damping=lm_damping)
    solver.set_stack([TaskSpec("hand", "position", "gripper_right_base_link", priority=0,
                               gain=0.1),
                      TaskSpec("posture", "posture", priority=1, gain=0.5)], q)
    target = solver.task("hand").target
    target.translation += [0.03, -0.04, 0.0]
    solver.task("hand").set_target(target)
    return solver


def test_each_level_lambda_grows_with_its_own_curved_step_targets(talos):
    q = talos.initial_configuration()
    moved = q.copy()
    moved[talos.limited_q_index] += 0.02               # a posture error, which does not count
    hand, posture = hand_and_posture_solver(talos, 50.0).step(moved).levels
    step = 0.1 * hand.residual_norm                    # m, the hand's step target
    assert hand.damping == pytest.approx(math.sqrt(1e-6 + 50.0 * step ** 2), rel=1e-12)
    assert posture.damping == 1e-3                     # posture: damping alone
    assert [level.damping for level in
            hand_and_posture_solver(talos, 0.0).step(moved).levels] == [1e-3, 1e-3]


def test_the_step_residual_is_reported_in_task_units(talos):
    """The level's rows are solved scaled by damping / lambda: its step residual is
    reported unscaled, |J dq - step| at the step taken."""
    solver = hand_and_posture_solver(talos, 50.0)
    q = talos.initial_configuration()
    frame = talos.model.getFrameId("gripper_right_base_link")
    result = solver.step(q)                            # leaves the kinematics of q
    wanted = 0.1 * (solver.task("hand").target.translation - talos.data.oMf[frame].translation)
    jacobian = pin.getFrameJacobian(talos.model, talos.data, frame,
                                    pin.LOCAL_WORLD_ALIGNED)[:3]
    assert result.levels[0].damping > 0.01
    assert result.levels[0].step_residual_norm == pytest.approx(
        np.linalg.norm(jacobian @ result.dq - wanted), rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("value", [-1.0, math.nan, math.inf])
def test_lm_damping_must_be_finite_and_non_negative(talos, value):
    with pytest.raises(ValueError, match="lm_damping"):
        PIKSolver(talos, lm_damping=value)
    with pytest.raises(ValueError, match="damping > 0"):
        PIKSolver(talos, damping=0.0, lm_damping=1.0)


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_hands_out_of_reach_without_velocity_limits_stay_put(talos, hierarchy):
    """No velocity limit to hide the overshoot: without LM damping the hands swing away
    from their targets (0.5 m or more) with joints jumping radians per step; with it they
    stay at the closest reachable posture, 0.18 m short."""
    plain_steps, plain_errors, _ = talos_run(talos, "arms out", 0.0, dt=None,
                                             hierarchy=hierarchy)
    steps, errors, _ = talos_run(talos, "arms out", LM_DAMPING, dt=None, hierarchy=hierarchy)
    assert plain_errors[-100:].max() > 0.5 and chatter(plain_steps) > 1.0
    assert errors[-100:].max() < 0.18
    assert chatter(steps) < 0.05 * chatter(plain_steps)


def test_qp_hands_out_of_reach_hold_still(talos):
    """On the QP hierarchy at 500 Hz the knees went back and forth at their velocity
    bounds (0.028 rad per step) with both hands out of reach; now they hold still."""
    plain_steps, _, plain = talos_run(talos, "arms out", 0.0, hierarchy="qp")
    steps, _, damped = talos_run(talos, "arms out", LM_DAMPING, hierarchy="qp")
    assert chatter(plain_steps) > 1e-2
    assert chatter(steps) < 2e-3
    assert damped.task_errors["right_hand"] <= plain.task_errors["right_hand"] + 1e-3


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_reachable_targets_converge_as_fast(talos, hierarchy):
    """Hands forward (reached): at most 10 % more steps to within 1 cm, and the same final
    accuracy, since lambda is back to `damping` there."""
    _, plain_errors, plain = talos_run(talos, "hands forward", 0.0, hierarchy=hierarchy)
    _, errors, damped = talos_run(talos, "hands forward", LM_DAMPING, hierarchy=hierarchy)
    reach = [int(np.argmax(run < 0.01)) for run in (plain_errors, errors)]
    assert min(reach) > 0 and reach[1] <= 1.1 * reach[0]
    assert damped.task_errors["right_hand"] < 1e-6
    assert all(level.damping == pytest.approx(1e-3, rel=1e-3) for level in damped.levels)


def test_a_support_polygon_out_of_reach_does_not_make_the_joints_chatter(talos):
    """The support polygon 3 m ahead of the feet (`stance bench support`'s "polygon
    ahead"): the CoM heads for it until the body is stretched on its bounds. A support
    level has no equality row, so its lambda stayed `damping`: the base, hips, torso and
    elbows then went back and forth at their velocity bounds every step (0.023 rad per
    step) for good. Its shortfall now counts in lambda as a task's step target does. And
    the return its rows ask per step is capped as a CoM task's step (SupportTask.max_step),
    with LM damping counting it uncapped, as a CoM task's error: the CoM holds, as for a
    CoM target out of reach, and the hands below reach their targets. Uncapped, the body
    leaned 0.84 m toward the polygon in 800 steps, each hand 1.0 m off its target."""
    specs = parse_stack_yaml(TALOS_LEVEL_STACK)
    start = bench_start(talos)
    targets = bench_targets(talos, specs, start, SUPPORT_SCENARIOS["polygon ahead"][0])
    solver = support_solver(talos, start, targets, DT, "support",
                            SUPPORT_SCENARIOS["polygon ahead"][1])
    balance = solver.task("balance")
    solver.compute_kinematics(start)
    outside_at_start = balance.distance_outside(talos)
    q, steps = start, []
    for _ in range(2 * STEPS):
        result = solver.step(q)
        q = result.q
        steps.append(result.dq)
    solver.compute_kinematics(q)
    balance_level = next(level for level in result.levels if "balance" in level.tasks)
    assert chatter(np.array(steps)) < 2e-3
    assert balance_level.damping > 1.0          # lambda of a shortfall of metres
    assert outside_at_start - 0.15 < balance.distance_outside(talos) < outside_at_start
    assert max(result.task_errors["left_foot"], result.task_errors["right_foot"]) < 1e-3
    assert max(result.task_errors["left_hand"], result.task_errors["right_hand"]) < 1e-3


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_a_com_target_out_of_reach_does_not_make_the_joints_chatter(talos, hierarchy):
    """The CoM's target 3 m ahead of the feet. Its step is capped at ComTask.max_step
    (0.02 m), and LM damping of the capped step left the 2-row level a lambda of 0.2: the
    base, hips and torso swung at their velocity bounds around the body's farthest reach
    for good (0.016 rad per step). Counted uncapped (gain x error, as a support polygon's
    shortfall is), it holds still. The price: a reachable CoM target more than max_step /
    gain (0.1 m) away is approached with more damping: 0.2 m ahead, to within 5 mm, the QP
    hierarchy took 19 steps without LM damping, 21 with the capped count, 23 now (the SVD
    one 24 in all three: its velocity limits bind first)."""
    variations, _, _ = talos_run(talos, "hands forward", LM_DAMPING, hierarchy=hierarchy,
                                 com_ahead=3.0, steps=2 * STEPS)
    assert chatter(variations) < 2e-3
    reach = [int(np.argmax(talos_run(talos, "hands forward", lm_damping, hierarchy=hierarchy,
                                     com_ahead=0.2, watched="com")[1] < 0.005))
             for lm_damping in (0.0, LM_DAMPING)]
    assert min(reach) > 0 and reach[1] <= 1.3 * reach[0], reach
