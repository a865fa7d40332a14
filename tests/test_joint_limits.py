"""Joint limits: the cubic damping h, the per-joint decisions, and whole runs on Talos.

Raunhardt and Boulic, eq. 1-5: inside a damping zone, only the variation heading toward the
limit is damped by h(d) = 3 d^2 - 2 d^3; a variation that would cross the limit is clamped
exactly on it. With clamping or progressive clamping no limited joint may ever end a step
outside its limits, whatever the targets.
"""

import re

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from helpers.problems import random_offset
from stance.limits import RevoluteLimits, cubic_step, make_strategy
from stance.pik import PIKSolver, default_stack_specs
from stance.robot import Robot, RobotModelError
from stance.stack import TaskSpec
from stance.swing import load_limit_file

LOWER, UPPER, ACTIVATION = -1.0, 1.0, 0.2
LIMIT_TOLERANCE = 1e-9
STEPS = 30
LIMITING_STRATEGIES = ("clamping", "progressive")
PROPERTY = settings(max_examples=40, deadline=None, derandomize=True, database=None)
HAND_FRAMES = {"right_hand": "gripper_right_base_link", "left_hand": "gripper_left_base_link"}


# The cubic damping function h(d), d = normalized distance into the damping zone.

def test_cubic_is_zero_at_threshold_and_one_at_limit():
    assert cubic_step(0.0) == 0.0
    assert cubic_step(1.0) == 1.0


def test_cubic_is_monotone():
    values = [cubic_step(d) for d in np.linspace(-0.5, 1.5, 2001)]
    assert np.all(np.diff(values) >= 0.0)


def test_cubic_is_continuously_differentiable():
    """h' = 6 d (1 - d) inside, and the slopes vanish where h meets 0 and 1 outside."""
    eps = 1e-6
    slope = lambda d: (cubic_step(d + eps) - cubic_step(d - eps)) / (2 * eps)  # noqa: E731
    for d in np.linspace(0.05, 0.95, 19):
        assert slope(d) == pytest.approx(6 * d * (1 - d), abs=1e-6)
    for edge in (0.0, 1.0):  # the central difference straddles the join
        assert abs(slope(edge)) < 1e-5


# Decisions of a strategy for one joint in [LOWER, UPPER], damping zones 0.2 rad thick.

def decide(strategy: str, q: float, dq: float):
    limits = RevoluteLimits(["joint"], [0], [0], [LOWER], [UPPER], activation=ACTIVATION)
    return make_strategy(strategy).decide(limits, np.array([q]), np.array([dq]),
                                          np.ones(1, dtype=bool))


@pytest.mark.parametrize("q, dq", [(0.9, 0.05), (-0.9, -0.05)], ids=["upper", "lower"])
def test_variation_toward_a_limit_in_its_zone_is_damped_by_the_cubic(q, dq):
    decision = decide("progressive", q, dq)
    h = cubic_step(0.5)  # q lies halfway into the zone
    assert list(decision.index) == [0]
    assert decision.h[0] == pytest.approx(h)
    assert decision.dq[0] == pytest.approx((1 - h) * dq)


@pytest.mark.parametrize("q, dq", [(0.9, -0.05), (-0.9, 0.05), (UPPER, -0.1), (LOWER, 0.1)],
                         ids=["upper_zone", "lower_zone", "on_upper", "on_lower"])
def test_variation_away_from_a_limit_is_untouched(q, dq):
    assert len(decide("progressive", q, dq).index) == 0


@pytest.mark.parametrize("q, dq", [(0.5, 0.2), (-0.5, -0.2)], ids=["up", "down"])
def test_variation_outside_the_damping_zones_is_untouched(q, dq):
    assert len(decide("progressive", q, dq).index) == 0


def test_clamping_strategy_does_not_damp_inside_the_zone():
    assert len(decide("clamping", 0.9, 0.05).index) == 0


@pytest.mark.parametrize("strategy", LIMITING_STRATEGIES)
@pytest.mark.parametrize("q, dq, limit", [(0.93, 0.2, UPPER), (-0.97, -0.5, LOWER)],
                         ids=["upper", "lower"])
def test_crossing_variation_is_clamped_exactly_on_the_limit(strategy, q, dq, limit):
    decision = decide(strategy, q, dq)
    assert decision.h[0] == 1.0
    assert q + decision.dq[0] == limit


# Whole runs on Talos: feet > CoM > both hands > posture.

@pytest.fixture(scope="module")
def talos():
    return Robot.from_example_robot_data("talos")


def hands_stack() -> list:
    """The demo stack with both hands at priority 2, driven hard (gain 0.5)."""
    base = [spec for spec in default_stack_specs() if spec.name not in HAND_FRAMES]
    hands = [TaskSpec(name, "pose", frame=frame, priority=2, gain=0.5)
             for name, frame in HAND_FRAMES.items()]
    return base + hands


def random_start(robot, rng) -> np.ndarray:
    """half_sitting where each limited joint stays, moves anywhere inside its limits, or
    moves within 1 mrad of (possibly exactly onto) one of its limits."""
    q = robot.initial_configuration()
    count = len(robot.limited_q_index)
    choice = rng.integers(0, 3, count)
    anywhere = rng.uniform(robot.lower, robot.upper)
    inward = rng.choice([0.0, 1e-3], count) * rng.random(count)  # 0: exactly on the limit
    near_limit = np.where(rng.random(count) < 0.5, robot.lower + inward, robot.upper - inward)
    q[robot.limited_q_index] = np.select([choice == 1, choice == 2], [anywhere, near_limit],
                                         q[robot.limited_q_index])
    return q


def set_hand_targets(solver, rng, reachable: bool) -> None:
    """Move both hand targets by < 0.3 m (reachable) or 1-3 m (unreachable), random turn."""
    for name in HAND_FRAMES:
        task = solver.task(name)
        target = task.target
        target.translation += random_offset(rng, reachable)
        target.rotation = target.rotation @ pin.exp3(rng.normal(size=3))
        task.set_target(target)


def limit_excess(robot, q) -> np.ndarray:
    """Per limited joint, how far q lies outside its limits (0 inside), rad or m."""
    values = q[robot.limited_q_index]
    return np.maximum(0.0, np.maximum(values - robot.upper, robot.lower - values))


def run(robot, strategy, start, seed, reachable, steps=STEPS):
    """Configurations after each of `steps` IK steps from `start` toward random targets."""
    rng = np.random.default_rng(seed)
    solver = PIKSolver(robot, strategy=strategy)
    solver.set_stack(hands_stack(), start)
    set_hand_targets(solver, rng, reachable)
    configurations, q = [], start
    for _ in range(steps):
        q = solver.step(q).q
        configurations.append(q)
    return configurations


SEEDS = st.integers(0, 2**32 - 1)


@pytest.mark.parametrize("strategy", LIMITING_STRATEGIES)
@PROPERTY
@given(seed=SEEDS, reachable=st.booleans())
def test_no_joint_ever_ends_a_step_outside_its_limits(talos, strategy, seed, reachable):
    start = random_start(talos, np.random.default_rng(seed))
    for q in run(talos, strategy, start, seed, reachable):
        assert limit_excess(talos, q).max() <= LIMIT_TOLERANCE


@pytest.mark.parametrize("strategy", LIMITING_STRATEGIES)
@PROPERTY
@given(seed=SEEDS, reachable=st.booleans(), outside=st.integers(1, 4))
def test_a_joint_started_outside_its_limits_moves_back_and_never_further_out(
        talos, strategy, seed, reachable, outside):
    rng = np.random.default_rng(seed)
    start = random_start(talos, rng)
    joints = rng.choice(len(talos.limited_q_index), outside, replace=False)
    overshoot = rng.uniform(0.01, 0.3, outside)
    above = rng.random(outside) < 0.5
    start[talos.limited_q_index[joints]] = np.where(
        above, talos.upper[joints] + overshoot, talos.lower[joints] - overshoot)
    excess = limit_excess(talos, start)
    for step, q in enumerate(run(talos, strategy, start, seed, reachable)):
        next_excess = limit_excess(talos, q)
        assert np.all(next_excess <= excess + LIMIT_TOLERANCE)
        if step == 0:   # back toward the limits at once, even where no task moves them
            assert np.all(next_excess[excess > 0.0] < excess[excess > 0.0])
        excess = next_excess


def unreachable_reach(robot, strategy):
    """Both hands sent 1-3 m away from half_sitting, 100 steps."""
    return run(robot, strategy, robot.initial_configuration(), seed=7, reachable=False,
               steps=100)


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_no_joint_moves_toward_a_limit_in_its_zone_undamped_under_velocity_limits(
        talos, hierarchy):
    """Velocity saturation (dt set) drops the lowest levels on the SVD hierarchy, which can
    turn a joint toward a limit the full solution moved it away from: the limit pass runs
    on the saturated step too. Whatever the hierarchy, a joint that moves toward a limit
    from inside its damping zone is one the loop fixed (damped or clamped)."""
    solver = PIKSolver(talos, strategy="progressive", dt=0.002, hierarchy=hierarchy)
    q = talos.initial_configuration()
    solver.set_stack(default_stack_specs(), q)
    hand = solver.task("right_hand")
    target = hand.target
    target.translation += np.array([0.5, 0.3, -0.3])   # out of reach: the arm saturates
    hand.set_target(target)
    q_index, v_index = solver.limits.indices
    lower, upper, lower_threshold, upper_threshold, _ = solver.limits.table
    saturated, toward_in_zone = 0, 0
    for step in range(600):
        result = solver.step(q)
        position, variation = q[q_index], result.dq[v_index]
        toward = (((variation > 1e-9) & (position > upper_threshold))
                  | ((variation < -1e-9) & (position < lower_threshold)))
        toward &= (position >= lower) & (position <= upper)
        free = ~result.clamped[:len(v_index)]
        assert not (toward & free).any(), \
            (step, [solver.limited_dof_names[j] for j in np.flatnonzero(toward & free)])
        saturated += result.velocity_scale < 1.0
        toward_in_zone += toward.sum()
        q = result.q
    assert toward_in_zone > 100 and (hierarchy == "qp" or saturated > 100), \
        (toward_in_zone, saturated)


def test_strategy_none_can_violate_limits(talos):
    """Sanity check of the harness: without a limit strategy the same run leaves limits."""
    assert max(limit_excess(talos, q).max() for q in unreachable_reach(talos, "none")) > 1e-2


def test_same_input_gives_bitwise_identical_output(talos):
    first, second = (np.array(unreachable_reach(talos, "progressive")) for _ in range(2))
    assert first.tobytes() == second.tobytes()


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
@pytest.mark.parametrize("strategy", LIMITING_STRATEGIES)
@PROPERTY
@given(seed=SEEDS, reachable=st.booleans(), dt=st.sampled_from([None, 0.002]),
       locked=st.sampled_from([(), ("torso_2_joint", "arm_right_4_joint")]),
       groups=st.booleans())
def test_the_compiled_clamping_loop_gives_the_python_loops_bits(talos, hierarchy, strategy,
                                                                seed, reachable, dt, locked,
                                                                groups):
    """PIKSolver runs the clamping loop in one compiled call when it can (1-DoF limits,
    with or without Talos' joint groups; damped least squares, or the QP hierarchy until a
    solution's levels leave its bounds, the general loop going on from there): every step
    gives the same bits as the general loop."""
    start = random_start(talos, np.random.default_rng(seed))
    solvers = []
    for one_call in (True, False):
        solver = PIKSolver(talos, strategy=strategy, dt=dt, locked_joints=locked,
                           hierarchy=hierarchy,
                           limit_models=load_limit_file("talos", talos) if groups else ())
        assert solver._one_call_loop
        solver._one_call_loop = one_call
        solver.set_stack(hands_stack(), start)
        set_hand_targets(solver, np.random.default_rng(seed), reachable)
        solvers.append(solver)
    q = start
    for _ in range(STEPS):
        compiled, general = (solver.step(q) for solver in solvers)
        for field in ("q", "dq", "damping", "clamped"):
            assert getattr(compiled, field).tobytes() == getattr(general, field).tobytes()
        assert compiled.clamping_iterations == general.clamping_iterations
        assert compiled.velocity_scale == general.velocity_scale
        assert compiled.binding_constraints == general.binding_constraints
        assert [level.step_residual_norm for level in compiled.levels] == \
            [level.step_residual_norm for level in general.levels]
        q = compiled.q


WARM_UP_CHECK = """
from stance import pik
from stance.robot import Robot
talos = Robot.load("talos")
solver = pik.PIKSolver(talos, strategy="none")
solver.set_stack(pik.default_stack_specs(), talos.initial_configuration())
solver.warm_up(talos.initial_configuration())
print(bool(pik._clamping_loop.signatures))
"""


def test_warm_up_compiles_the_clamping_loop_whatever_the_strategy():
    """pik_node warms its solver up before its first cycle with its start-up strategy; the
    strategy can become `progressive` later, and the compiled loop must not be compiled
    (seconds) then, in the middle of the control loop. In a fresh process."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", WARM_UP_CHECK], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "True"


@pytest.mark.parametrize("strategy", LIMITING_STRATEGIES)
def test_locked_joints_never_move_and_are_not_reported_clamped(talos, strategy):
    """Locked joints keep their value whatever the tasks and limits do, one of them started
    on its limit, the other far inside; the hands still move."""
    locked = ("gripper_right_joint", "arm_right_4_joint")
    rng = np.random.default_rng(11)
    start = talos.initial_configuration()             # the grippers sit on their limit 0
    solver = PIKSolver(talos, strategy=strategy, locked_joints=locked)
    solver.set_stack(hands_stack(), start)
    set_hand_targets(solver, rng, reachable=False)
    q_index = [talos.model.joints[talos.joint_id(name)].idx_q for name in locked]
    dofs = [solver.limited_dof_names.index(name) for name in locked]
    q = start
    for _ in range(STEPS):
        result = solver.step(q)
        assert not result.clamped[dofs].any() and not result.damping[dofs].any()
        q = result.q
    np.testing.assert_array_equal(q[q_index], start[q_index])
    assert np.abs(q[talos.limited_q_index] - start[talos.limited_q_index]).max() > 0.05


@pytest.mark.parametrize("locked, reason", [
    (["no_such_joint"], "locked_joints[0]: unknown joint"),
    (["torso_2_joint", "torso_2_joint"], "locked_joints[1]: 'torso_2_joint' named twice"),
    (["root_joint"], "free-flyer base"),
])
def test_bad_locked_joints_are_refused(talos, locked, reason):
    with pytest.raises(RobotModelError, match=re.escape(reason)):
        PIKSolver(talos, locked_joints=locked)
