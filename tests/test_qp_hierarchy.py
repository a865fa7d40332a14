"""QPHierarchy: strict priorities under bounds on dq, on random levels and on Talos.

Without a binding bound it must be DampedHierarchy; with bounds it must keep every higher
level's residual, respect the bounds, name the binding ones, and never fail or depend on
its warm start.
"""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import lsq_linear

from helpers.problems import hierarchy_problems, residual
from stance.hierarchy import (DampedHierarchy, Level, excludes_zero, first_level_out_of_bounds,
                             solve_compiled, stack_levels)
from stance.pik import PIKSolver, default_stack_specs
from stance import qp_hierarchy
from stance.qp_hierarchy import (CERTIFIED, COLD_MAX_ITERATIONS, INNER_MAX_ITERATIONS,
                                 WARM_MAX_ITERATIONS, KeptActiveSets, QPHierarchy,
                                 _active_set_solve, _kept_slot, _multiplier_slack,
                                 _nonnegative_fit, _polish, robot_dof_names)
from stance.robot import Robot
from stance.stack import parse_stack_yaml
from stance_tools.bench import (GRIPPER_JOINTS, GROUP_SCENARIOS, HANDS_FORWARD,
                                TALOS_LEVEL_STACK, StanceContender, bench_start,
                                bench_targets, level_contenders, limit_excess)

DAMPING = 1e-3
AGREEMENT = 1e-7          # rad: QPHierarchy vs DampedHierarchy without binding bounds
PRIORITY_TOLERANCE = 1e-8
BOUND_TOLERANCE = 1e-9    # rad or m
LOOSE_BOUND = 1e6         # never reached by a damped step of the random problems
PROPERTY = settings(max_examples=100, deadline=None, derandomize=True, database=None)
ARMS_OUT = GROUP_SCENARIOS["arms out"]    # hand offsets (m) out of reach, to the sides


@st.composite
def bounded_problems(draw):
    """(levels, nv, fixed_index, fixed_dq, (lower, upper)): hierarchy_problems plus bounds of
    random width around 0 (some one-sided or absent)."""
    levels, nv, fixed_index, fixed_dq, rng = draw(hierarchy_problems())
    width = 10.0 ** rng.uniform(-3, 0, size=(2, nv))
    lower, upper = -width[0], width[1]
    lower[rng.random(nv) < 0.2] = -np.inf
    upper[rng.random(nv) < 0.2] = np.inf
    return levels, nv, fixed_index, fixed_dq, (lower, upper)


def polish_counters() -> np.ndarray:
    """_polish's counters argument: [hot starts, polish solves], as QPHierarchy keeps them."""
    return np.zeros(2, dtype=np.int64)


def free_mask(nv, fixed_index) -> np.ndarray:
    free = np.ones(nv, dtype=bool)
    free[fixed_index] = False
    return free


@PROPERTY
@given(bounded_problems())
def test_without_binding_bounds_it_is_the_damped_hierarchy(problem):
    levels, nv, fixed_index, fixed_dq, _ = problem
    loose = (np.full(nv, -LOOSE_BOUND), np.full(nv, LOOSE_BOUND))
    expected = DampedHierarchy(damping=DAMPING).solve(levels, nv, fixed_index, fixed_dq)
    solver = QPHierarchy(damping=DAMPING)
    solution = solver.solve(levels, nv, fixed_index, fixed_dq, bounds=loose)
    np.testing.assert_allclose(solution.dq, expected.dq, rtol=0, atol=AGREEMENT)
    np.testing.assert_allclose(solution.step_residuals, expected.step_residuals,
                               rtol=0, atol=AGREEMENT)
    assert solution.binding == [] and solver.qp_solves == 0


@PROPERTY
@given(bounded_problems())
def test_first_level_is_the_bounded_damped_least_squares(problem):
    """Level 0 alone: min |J dq - t|^2 + lambda^2 |dq|^2 within the bounds, checked
    against scipy's bounded-variable least squares on the free DoFs."""
    levels, nv, fixed_index, fixed_dq, (lower, upper) = problem
    free = free_mask(nv, fixed_index)
    if not free.any():
        return
    level = levels[0]
    start = np.zeros(nv)
    start[fixed_index] = fixed_dq
    stacked = np.vstack([level.jacobian[:, free], DAMPING * np.eye(free.sum())])
    wanted = np.concatenate([level.target - level.jacobian @ start, np.zeros(free.sum())])
    reference = lsq_linear(stacked, wanted, bounds=(lower[free], upper[free]),
                           method="bvls", tol=1e-14).x
    solution = QPHierarchy(damping=DAMPING).solve([level], nv, fixed_index, fixed_dq,
                                                  bounds=(lower, upper))
    np.testing.assert_allclose(solution.dq[free], reference, rtol=0, atol=1e-7)


def test_bounds_excluding_zero_skip_the_unconstrained_solve(monkeypatch):
    """A free DoF whose bounds exclude 0 (a direct caller's: PIKSolver's never do) makes
    the unconstrained solution inadmissible: the cascade answers at once, and its answer
    is the bounded damped least squares."""
    jacobian, target = np.array([[1.0, 1.0, 0.0], [0.0, 1.0, 1.0]]), np.array([1.0, -2.0])
    lower, upper = np.array([0.2, -1.0, -1.0]), np.array([1.0, 1.0, -0.5])
    solver = QPHierarchy(damping=DAMPING)

    def refused(*args, **kwargs):
        raise AssertionError("unconstrained solve run although 0 is out of bounds")

    monkeypatch.setattr(solver.unconstrained, "solve_stacked", refused)
    solution = solver.solve([Level(jacobian, target)], 3, bounds=(lower, upper))
    stacked = np.vstack([jacobian, DAMPING * np.eye(3)])
    reference = lsq_linear(stacked, np.concatenate([target, np.zeros(3)]),
                           bounds=(lower, upper), method="bvls", tol=1e-14).x
    np.testing.assert_allclose(solution.dq, reference, rtol=0, atol=1e-9)


def test_a_restart_that_fixes_more_joints_is_cascaded_from_the_first_level():
    """previous: an unconstrained solution with no DoF fixed; DoF 2 (seen by level 1 only)
    is then fixed at 0.3, so the unconstrained solve restarts at level 1 and keeps level
    0's old start (DoF 2 at 0), while level 0 crosses its bound on DoF 0. The cascade must
    not start from that stale state: the same answer as without `previous`."""
    jacobian, target = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]]), np.array([1.0, 1.0])
    offsets = np.array([0, 1, 2])
    bounds = (np.full(3, -1.0), np.array([0.5, 1.0, 1.0]))
    previous = DampedHierarchy(damping=DAMPING).solve_stacked(jacobian, target, offsets)
    restarted = QPHierarchy(damping=DAMPING).solve_stacked(
        jacobian, target, offsets, [2], [0.3], bounds=bounds, previous=previous)
    fresh = QPHierarchy(damping=DAMPING).solve_stacked(jacobian, target, offsets, [2], [0.3],
                                                       bounds=bounds)
    assert restarted.dq[2] == 0.3 and restarted.dq[0] == pytest.approx(0.5, abs=1e-12)
    np.testing.assert_allclose(restarted.dq, fresh.dq, rtol=0, atol=1e-12)
    np.testing.assert_allclose(restarted.step_residuals, fresh.step_residuals, rtol=0,
                               atol=1e-12)


def test_a_restart_from_a_solution_within_the_bounds_cascades_from_its_crossing_level(
        monkeypatch):
    """previous within the bounds; DoF 2 (seen by level 1 only) then fixed at 0.8 pushes
    level 1's DoF 1 through its bound: the cascade starts at level 1 from the restarted
    state (level 0 kept) and gives the answer of a solve without `previous`."""
    jacobian, target = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0]]), np.array([0.3, 0.2])
    offsets = np.array([0, 1, 2])
    bounds = (np.array([-1.0, -0.4, -1.0]), np.full(3, 1.0))
    solver = QPHierarchy(damping=DAMPING)
    previous = solver.solve_stacked(jacobian, target, offsets, bounds=bounds)
    assert previous.restart is not None         # within the bounds: the unconstrained one
    starts = []
    cascade = solver._cascade

    def recorded(*args):
        starts.append(args[-1])                 # the level the cascade starts at
        return cascade(*args)

    monkeypatch.setattr(solver, "_cascade", recorded)
    restarted = solver.solve_stacked(jacobian, target, offsets, [2], [0.8], bounds=bounds,
                                     previous=previous)
    assert starts == [1]
    fresh = QPHierarchy(damping=DAMPING).solve_stacked(jacobian, target, offsets, [2], [0.8],
                                                       bounds=bounds)
    assert restarted.dq[2] == 0.8 and restarted.dq[1] == pytest.approx(-0.4, abs=1e-12)
    assert restarted.binding == ["dof1 lower"]
    np.testing.assert_allclose(restarted.dq, fresh.dq, rtol=0, atol=1e-12)
    np.testing.assert_allclose(restarted.step_residuals, fresh.step_residuals, rtol=0,
                               atol=1e-12)


def test_exact_solve_says_when_it_ran_out_of_iterations(monkeypatch):
    """The exact active-set fallback: converged with the bounded least squares optimum;
    without iterations left, a feasible step flagged as not converged."""
    projected, residual_ = np.array([[1.0, 2.0], [0.0, 1.0]]), np.array([3.0, 3.0])
    rows, low, high = np.eye(2), np.full(2, -0.5), np.full(2, 0.5)
    step, active, _, converged = _active_set_solve(projected, residual_, DAMPING, rows, low,
                                                   high)
    reference = lsq_linear(np.vstack([projected, DAMPING * np.eye(2)]),
                           np.concatenate([residual_, np.zeros(2)]), bounds=(low, high),
                           method="bvls", tol=1e-14).x
    assert converged and active.all()
    np.testing.assert_allclose(step, reference, rtol=0, atol=1e-12)
    monkeypatch.setattr(qp_hierarchy, "ACTIVE_SET_ITERATIONS", 0)
    step, _, _, converged = _active_set_solve(projected, residual_, DAMPING, rows, low, high)
    assert not converged
    assert np.all(step >= low) and np.all(step <= high)


@PROPERTY
@given(bounded_problems())
def test_lower_levels_keep_higher_levels_optimum_under_bounds(problem):
    """Level i's residual at the full solution equals its residual solving levels 0..i."""
    levels, nv, fixed_index, fixed_dq, bounds = problem
    solver = QPHierarchy(damping=DAMPING)
    full = solver.solve(levels, nv, fixed_index, fixed_dq, bounds=bounds)
    for index, level in enumerate(levels):
        prefix = solver.solve(levels[:index + 1], nv, fixed_index, fixed_dq, bounds=bounds)
        assert abs(residual(level, full.dq) - residual(level, prefix.dq)) < PRIORITY_TOLERANCE
        assert abs(full.step_residuals[index] - prefix.step_residuals[index]) \
            < PRIORITY_TOLERANCE


@PROPERTY
@given(bounded_problems())
def test_the_compiled_solve_is_the_answer_exactly_where_no_level_crosses_a_bound(problem):
    """Where the cascade keeps every level's unconstrained step (no QP), the answer is
    DampedHierarchy's compiled solve, its restart state included; elsewhere the cascade
    runs. Either way it is the cascade's result."""
    levels, nv, fixed_index, fixed_dq, (lower, upper) = problem
    solver, reference = QPHierarchy(damping=DAMPING), QPHierarchy(damping=DAMPING)
    solution = solver.solve(levels, nv, fixed_index, fixed_dq, bounds=(lower, upper))
    free = free_mask(nv, fixed_index)
    cascade = reference._cascade(*stack_levels(levels, nv), fixed_index, fixed_dq, free,
                                 lower, upper, ~free)
    np.testing.assert_allclose(solution.dq, cascade.dq, rtol=0, atol=AGREEMENT)
    assert (solution.restart is not None) == (reference.qp_solves == 0)
    assert solver.qp_solves == reference.qp_solves


@PROPERTY
@given(bounded_problems())
def test_the_unconstrained_solve_stops_at_the_first_level_out_of_bounds(problem):
    """solve_compiled given bounds (the compiled clamping loop's solve) stops after the
    dq of the first level that leaves them: first_level_out_of_bounds of the full solve,
    whose bits it has up to there; within the bounds it is the full solve."""
    levels, nv, fixed_index, fixed_dq, (lower, upper) = problem
    jacobian, target, offsets = stack_levels(levels, nv)
    fixed, values = ~free_mask(nv, fixed_index), np.zeros(nv)
    values[fixed_index] = fixed_dq
    runs = []
    for bounds in ((np.zeros(0), np.zeros(0)), (lower, upper)):
        state = (np.zeros((len(levels), nv, nv)), np.zeros(len(levels), dtype=np.int64),
                 np.zeros((len(levels) + 1, nv)), np.zeros((len(levels), nv)),
                 np.zeros(len(levels)))
        dq, stop = solve_compiled(jacobian, target, offsets, fixed, values,
                                  np.zeros(0, dtype=bool), np.zeros(0), *state, DAMPING,
                                  1e-9, *bounds)
        runs.append((dq, stop, state))
    (full_dq, full_stop, full), (dq, stop, stopped) = runs
    assert full_stop == len(levels)
    if excludes_zero(fixed, lower, upper):
        return                      # the clamping loop cascades at once: no such solve
    assert stop == first_level_out_of_bounds(full[2], fixed, lower, upper)
    assert stopped[2][:stop + 2].tobytes() == full[2][:stop + 2].tobytes()
    assert stopped[1][:stop + 1].tobytes() == full[1][:stop + 1].tobytes()
    if stop == len(levels):
        assert dq.tobytes() == full_dq.tobytes()
        assert stopped[4].tobytes() == full[4].tobytes()


@PROPERTY
@given(bounded_problems())
def test_a_restart_under_new_bounds_finds_the_first_level_out_among_the_kept_levels(problem):
    """The compiled clamping loop restarts its solve when a limit pass fixes one more joint
    and brings new (damping) bounds: solve_compiled, restarted from a solution with one
    fixed joint fewer (none fewer: a pass that only damps) solved without bounds, stops at
    first_level_out_of_bounds of the full restarted solve, the levels the restart keeps
    included (their dq was never checked against these bounds)."""
    levels, nv, fixed_index, fixed_dq, (lower, upper) = problem
    jacobian, target, offsets = stack_levels(levels, nv)
    fixed, values = ~free_mask(nv, fixed_index), np.zeros(nv)
    values[fixed_index] = fixed_dq
    if excludes_zero(fixed, lower, upper):
        return                      # the clamping loop cascades at once: no such solve
    old_fixed, old_values = fixed.copy(), values.copy()
    if len(fixed_index):
        old_fixed[fixed_index[-1]], old_values[fixed_index[-1]] = False, 0.0
    previous = (np.zeros((len(levels), nv, nv)), np.zeros(len(levels), dtype=np.int64),
                np.zeros((len(levels) + 1, nv)), np.zeros((len(levels), nv)),
                np.zeros(len(levels)))
    solve_compiled(jacobian, target, offsets, old_fixed, old_values, np.zeros(0, dtype=bool),
                   np.zeros(0), *previous, DAMPING, 1e-9, np.zeros(0), np.zeros(0))
    stops = []
    for bounds in ((np.zeros(0), np.zeros(0)), (lower, upper)):
        state = tuple(array.copy() for array in previous)
        stops.append((solve_compiled(jacobian, target, offsets, fixed, values, old_fixed,
                                     old_values, *state, DAMPING, 1e-9, *bounds)[1], state))
    (full_stop, full), (stop, _) = stops
    assert full_stop == len(levels)
    assert stop == first_level_out_of_bounds(full[2], fixed, lower, upper)


@PROPERTY
@given(bounded_problems())
def test_bounds_and_fixed_joints_are_respected(problem):
    levels, nv, fixed_index, fixed_dq, (lower, upper) = problem
    solution = QPHierarchy(damping=DAMPING).solve(levels, nv, fixed_index, fixed_dq,
                                                  bounds=(lower, upper))
    free = free_mask(nv, fixed_index)
    assert np.all(solution.dq[free] >= lower[free] - BOUND_TOLERANCE)
    assert np.all(solution.dq[free] <= upper[free] + BOUND_TOLERANCE)
    assert np.array_equal(solution.dq[fixed_index], fixed_dq)
    assert np.all(np.isfinite(solution.step_residuals))


@PROPERTY
@given(bounded_problems())
def test_same_input_same_output(problem):
    """Two fresh solvers agree bit for bit; one solver called again (warm-started QPs)
    agrees bit for bit too, as the polished QP solutions do not depend on the warm start."""
    levels, nv, fixed_index, fixed_dq, bounds = problem
    first, second = QPHierarchy(damping=DAMPING), QPHierarchy(damping=DAMPING)
    solutions = [first.solve(levels, nv, fixed_index, fixed_dq, bounds=bounds),
                 second.solve(levels, nv, fixed_index, fixed_dq, bounds=bounds),
                 first.solve(levels, nv, fixed_index, fixed_dq, bounds=bounds)]
    for solution in solutions[1:]:
        assert np.array_equal(solution.dq, solutions[0].dq)
        assert np.array_equal(solution.step_residuals, solutions[0].step_residuals)
        assert solution.binding == solutions[0].binding


def test_contradictory_levels_are_met_in_least_squares_within_bounds():
    """Level 0 wants dq_a = 1, level 1 wants dq_a = -1 and dq_b = 1; bounds +-0.1."""
    names = ["a", "b", "c"]
    levels = [Level(np.array([[1.0, 0.0, 0.0]]), np.array([1.0])),
              Level(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), np.array([-1.0, 1.0]))]
    bounds = (np.full(3, -0.1), np.full(3, 0.1))
    solution = QPHierarchy(damping=DAMPING, dof_names=names).solve(levels, 3, bounds=bounds)
    np.testing.assert_allclose(solution.dq, [0.1, 0.1, 0.0], atol=BOUND_TOLERANCE)
    np.testing.assert_allclose(solution.step_residuals, [0.9, np.hypot(1.1, 0.9)], atol=1e-9)
    assert solution.binding == ["a upper", "b upper"]


@pytest.mark.parametrize("jacobian", [
    np.zeros((3, 4)),
    np.array([[1.0, 2.0, 0.0, 0.0], [1.0, 2.0, 0.0, 0.0], [1.0, 2.0, 0.0, 0.0]]),
    np.array([[1e-14, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1e3]]),
], ids=["zero", "duplicate_rows", "badly_scaled"])
def test_singular_stack_returns_a_bounded_solution(jacobian):
    levels = [Level(jacobian, np.array([1.0, -1.0, 2.0])),
              Level(jacobian[::-1].copy(), np.array([5.0, 5.0, 5.0])),
              Level(np.eye(4), np.full(4, 3.0))]
    bounds = (np.full(4, -0.5), np.full(4, 0.2))
    solution = QPHierarchy(damping=DAMPING).solve(levels, 4, [1], [0.0], bounds=bounds)
    assert np.all(np.isfinite(solution.dq)) and np.all(np.isfinite(solution.step_residuals))
    assert np.all(solution.dq >= bounds[0] - BOUND_TOLERANCE)
    assert np.all(solution.dq <= bounds[1] + BOUND_TOLERANCE)


# Talos: the demo stack through PIKSolver, progressive clamping.

@pytest.fixture(scope="module")
def talos():
    return Robot.from_example_robot_data("talos")


def talos_solver(robot, q, hierarchy, hand_offset, dt=None, locked_joints=()):
    solver = PIKSolver(robot, strategy="progressive", damping=DAMPING, dt=dt,
                       hierarchy=hierarchy, locked_joints=locked_joints)
    solver.set_stack(default_stack_specs(), q)
    hand = solver.task("right_hand")
    target = hand.target
    target.translation += np.asarray(hand_offset, dtype=float)
    hand.set_target(target)
    return solver


def test_talos_steps_agree_with_the_damped_hierarchy_inside_the_limits(talos):
    """Outside every damping zone (the grippers, which start inside theirs, locked; until
    the torso reaches its zone): no bound binds and the steps are the damped hierarchy's."""
    q = bench_start(talos)
    offset = [0.1, -0.1, 0.1]
    damped = talos_solver(talos, q, None, offset, locked_joints=GRIPPER_JOINTS)
    bounded = talos_solver(talos, q, QPHierarchy.for_robot(talos, damping=DAMPING), offset,
                           locked_joints=GRIPPER_JOINTS)
    for step in range(30):
        expected, result = damped.step(q), bounded.step(q)
        if expected.damping.any():
            break
        assert result.binding_constraints == []
        np.testing.assert_allclose(result.dq, expected.dq, rtol=0, atol=AGREEMENT)
        q = expected.q
    assert step >= 8


def test_a_damped_joint_never_moves_toward_its_limit_beyond_its_damped_variation(talos):
    """Progressive clamping on the QP hierarchy bounds a joint in its damping zone by the
    damped variation rather than fixing it there: it never moves toward its limit by more
    than the damped hierarchy's damped variation (the same decision: the same first
    solution)."""
    q = bench_start(talos)
    offset = [0.1, -0.1, 0.1]
    damped = talos_solver(talos, q, None, offset)
    bounded = talos_solver(talos, q, QPHierarchy.for_robot(talos, damping=DAMPING), offset)
    for _ in range(30):
        expected, result = damped.step(q), bounded.step(q)
        zone = (expected.damping > 0.0) & (expected.damping < 1.0)
        assert zone.any()
        v = bounded._dof_v_index[zone]
        toward = np.sign(expected.dq[v])
        assert np.all(toward * result.dq[v] <= toward * expected.dq[v] + AGREEMENT)
        q = expected.q


def test_talos_velocity_bounds_bind_and_are_named(talos):
    """A hand target 0.5 m away at dt 2 ms: the hierarchy's step (before PIKSolver's
    uniform scaling) respects the velocity limits, keeps the feet, and names velocity
    bounds as binding."""
    dt = 0.002
    q = bench_start(talos)
    hierarchy = QPHierarchy.for_robot(talos, dt=dt, damping=DAMPING)
    solver = talos_solver(talos, q, hierarchy, [0.5, -0.3, 0.3], dt=dt)
    speed = talos.velocity_limit * dt
    names = robot_dof_names(talos)
    seen = set()
    for _ in range(20):
        result = solver.step(q)
        assert result.velocity_scale > 1.0 - 1e-6  # only ProxSuite's 1e-9 can be left over
        solved = result.dq[talos.limited_v_index] / result.velocity_scale
        assert np.all(np.abs(solved) <= speed + BOUND_TOLERANCE)
        assert result.levels[0].step_residual_norm < 1e-6
        for constraint in result.binding_constraints:
            dof, kind = constraint.rsplit(" ", 1)
            assert dof in names and kind in ("lower", "upper", "velocity", "damped")
        seen.update(result.binding_constraints)
        limits = result.q[talos.limited_q_index]
        assert np.all(limits >= np.minimum(talos.lower, q[talos.limited_q_index]) - 1e-12)
        assert np.all(limits <= np.maximum(talos.upper, q[talos.limited_q_index]) + 1e-12)
        q = result.q
    assert any(constraint.endswith(" velocity") for constraint in seen)


def test_talos_damping_bounds_are_named_damped(talos):
    """On the QP hierarchy a damped joint is bounded by its damped variation: where dq is
    on that bound the status names it '<joint> damped' (it was named as a joint limit),
    for joints in their damping zone (0 < h < 1) only; the grippers start in theirs."""
    dt = 0.002
    q = bench_start(talos)
    hierarchy = QPHierarchy.for_robot(talos, dt=dt, damping=DAMPING)
    solver = talos_solver(talos, q, hierarchy, [0.25, -0.2, 0.2], dt=dt)
    limited = list(solver.limited_dof_names)
    damped = []
    for _ in range(10):
        result = solver.step(q)
        for constraint in result.binding_constraints:
            dof, kind = constraint.rsplit(" ", 1)
            if kind == "damped":
                assert 0.0 < result.damping[limited.index(dof)] < 1.0
                damped.append(dof)
            else:
                assert kind == "velocity"   # no joint limit within reach of this step
        q = result.q
    assert "gripper_left_joint" in damped


class BoundedHierarchy:
    """A hierarchy object of the user's own with bounds on dq (PIKSolver's `hierarchy`),
    here a QPHierarchy behind a plain interface: no with_damping_bounds."""

    uses_bounds = True

    def __init__(self, inner):
        self.inner = inner

    def solve_stacked(self, *args, **options):
        return self.inner.solve_stacked(*args, **options)


def test_a_hierarchy_object_without_damped_names_keeps_its_own(talos):
    """The step's binding names are decided at the first read: one that cannot say which
    bounds are damped variations keeps its names (the damped grippers' bound as their
    limit side), and reading them raises nothing."""
    dt = 0.002
    q = bench_start(talos)
    hierarchy = BoundedHierarchy(QPHierarchy.for_robot(talos, dt=dt, damping=DAMPING))
    solver = talos_solver(talos, q, hierarchy, [0.25, -0.2, 0.2], dt=dt)
    seen = set()
    for _ in range(10):
        result = solver.step(q)
        seen.update(result.binding_constraints)
        q = result.q
    assert {name.rsplit(" ", 1)[1] for name in seen} <= {"lower", "upper", "velocity"}
    assert any(name.startswith("gripper_left_joint ") for name in seen)


def test_talos_repeated_steps_are_reproducible(talos):
    """Fresh solvers and a warm solver give the same step from the same configuration, and
    name the same binding bounds, but for a bound the step lies on with a zero multiplier
    (a degenerate vertex), which one path's active set holds and another's need not."""
    dt = 0.002
    q = bench_start(talos)

    def solver():
        return talos_solver(talos, q, QPHierarchy.for_robot(talos, dt=dt, damping=DAMPING),
                            [0.5, -0.3, 0.3], dt=dt)

    warm = solver()
    for _ in range(5):
        warm.step(q)
    results = [solver().step(q), solver().step(q), warm.step(q)]
    names = robot_dof_names(talos)
    speed = dict(zip(talos.limited_v_index.tolist(), talos.velocity_limit * dt))
    for result in results[1:]:
        np.testing.assert_allclose(result.dq, results[0].dq, rtol=0, atol=1e-9)
        for constraint in set(result.binding_constraints) ^ set(results[0].binding_constraints):
            dof, kind = constraint.rsplit(" ", 1)
            v = names.index(dof)
            assert kind == "velocity" and abs(abs(result.dq[v]) - speed[v]) < 1e-12
    assert results[0].binding_constraints == results[1].binding_constraints
    assert np.array_equal(results[0].dq, results[1].dq)


def test_a_solver_that_forgot_its_starts_steps_as_a_fresh_one(talos):
    """After forget_starts (a step its caller discarded), the next step, whose bounds
    cross, starts from no active set and no ProxSuite QP kept before: it takes a fresh
    solver's hot starts, ProxSuite solves and cold starts, and its step bit for bit."""
    start = bench_start(talos)
    used, fresh = four_level_qp_contender(talos, start), four_level_qp_contender(talos, start)
    q = start
    for _ in range(20):
        q, _ = used.step(q)
    assert used.solver.hierarchy.hot_starts > 0     # the steps so far left starts to reuse
    used.solver.forget_starts()

    def counts(hierarchy):
        return np.array([hierarchy.hot_starts, hierarchy.qp_solves, hierarchy.cold_starts])

    before = [counts(used.solver.hierarchy), counts(fresh.solver.hierarchy)]
    expected, result = fresh.solver.step(q), used.solver.step(q)
    spent = counts(fresh.solver.hierarchy) - before[1]
    assert spent[:2].sum() > 0                       # a level's bounds crossed
    np.testing.assert_array_equal(counts(used.solver.hierarchy) - before[0], spent)
    assert np.array_equal(result.dq, expected.dq)
    assert result.binding_constraints == expected.binding_constraints


def four_level_qp_contender(robot, start):
    """The issue's stack (feet > CoM > both hands > posture) on the QP hierarchy, both
    hands reaching into the torso's and wrists' limits (stance bench levels)."""
    return next(contender for contender in level_contenders(
        robot, TALOS_LEVEL_STACK, start, HANDS_FORWARD, 0.002, (4,))
        if contender.name.startswith("qp"))


def test_proxsuite_work_per_level_is_bounded(talos):
    """The clamped posture level's bound sets are degenerate (many of zero width), where a
    warm start capped in outer iterations only once ran 4,500 inner ones (120 ms). Every
    level through ProxSuite (no hot start): a level's QP, warm start and cold fallback
    together, stays within the caps."""
    start = bench_start(talos)
    contender = four_level_qp_contender(talos, start)
    hierarchy = contender.solver.hierarchy
    hierarchy.hot_start = False
    solve, spent = hierarchy._qp_solve, []

    def counted(*args):
        before = hierarchy.qp_iterations
        qp = solve(*args)
        spent.append(hierarchy.qp_iterations - before)
        return qp

    hierarchy._qp_solve = counted
    q = start
    for _ in range(140):
        q, _ = contender.step(q)
    assert len(spent) > 100 and hierarchy.cold_starts > 0   # the bounds did bind
    assert max(spent) <= (WARM_MAX_ITERATIONS + COLD_MAX_ITERATIONS) * INNER_MAX_ITERATIONS
    assert limit_excess(talos, q) == 0.0


def test_hot_start_takes_the_same_steps_with_few_proxsuite_solves(talos):
    """From the same configurations (open loop), the hot-started hierarchy takes ProxSuite's
    steps (the KKT point is unique) and names the same binding bounds, while ProxSuite
    solves under a tenth of the levels whose bounds cross (the active set changes little
    from one step to the next)."""
    start = bench_start(talos)
    hot, cold = four_level_qp_contender(talos, start), four_level_qp_contender(talos, start)
    cold.solver.hierarchy.hot_start = False
    q = start
    for _ in range(140):
        expected, result = cold.solver.step(q), hot.solver.step(q)
        np.testing.assert_allclose(result.dq, expected.dq, rtol=0, atol=1e-9)
        assert result.binding_constraints == expected.binding_constraints
        q = expected.q
    crossed = cold.solver.hierarchy.qp_solves
    assert crossed > 100 and hot.solver.hierarchy.hot_starts > 0.9 * crossed
    assert hot.solver.hierarchy.qp_solves < 0.1 * crossed


def test_compiled_clamping_loop_runs_the_cascades_and_hands_over_for_proxsuite(talos):
    """On the issue's stack the compiled clamping loop runs every step, the cascades of
    the steps where a level crosses a bound included, and hands a step over to the general
    loop only where a level's hot start fails (ProxSuite's business): the same bits as the
    general loop throughout, both ways taken."""
    start = bench_start(talos)
    compiled, general = (four_level_qp_contender(talos, start).solver for _ in range(2))
    assert compiled._one_call_loop
    general._one_call_loop = False
    hierarchy, handed_over = compiled.hierarchy, []
    general_loop = compiled._clamping
    compiled._clamping = lambda *args: handed_over.append(1) or general_loop(*args)
    q, cascaded = start, 0
    for _ in range(200):
        before = (len(handed_over), hierarchy.qp_solves, hierarchy.hot_starts)
        expected, result = general.step(q), compiled.step(q)
        assert result.dq.tobytes() == expected.dq.tobytes()
        assert result.clamping_iterations == expected.clamping_iterations
        assert result.binding_constraints == expected.binding_constraints
        assert (len(handed_over) > before[0]) == (hierarchy.qp_solves > before[1])
        cascaded += len(handed_over) == before[0] and hierarchy.hot_starts > before[2]
        q = expected.q
    assert cascaded > 50 and len(handed_over) >= 1


def test_compiled_cascades_follow_a_stack_change(talos):
    """The kept active sets belong to one stack shape: when the posture level comes and
    goes (set_stack mid-approach) the compiled loop's cascades still give the general
    loop's bits, on the new shape and on the old one again."""
    start = bench_start(talos)
    contenders = [four_level_qp_contender(talos, start) for _ in range(2)]
    compiled, general = (contender.solver for contender in contenders)
    general._one_call_loop = False
    specs = parse_stack_yaml(TALOS_LEVEL_STACK)
    targets = {name: compiled.task(name).target for name in compiled.tasks}
    q, cascaded = start, 0
    three_levels = [spec for spec in specs if spec.kind != "posture"]
    for stack in (three_levels, specs, three_levels):
        for solver in (compiled, general):
            solver.set_stack(stack, q)
            for spec in stack:
                solver.task(spec.name).target = targets[spec.name]
        for _ in range(40):
            before = compiled.hierarchy.hot_starts
            expected, result = general.step(q), compiled.step(q)
            assert result.dq.tobytes() == expected.dq.tobytes()
            assert result.binding_constraints == expected.binding_constraints
            assert [level.step_residual_norm for level in result.levels] == \
                [level.step_residual_norm for level in expected.levels]
            cascaded += compiled.hierarchy.hot_starts > before
            q = expected.q
    assert cascaded > 20


def test_cascade_state_follows_the_problem_shape():
    """The compiled loop's cascade state is rebuilt for each new stack shape (numba does
    not check bounds: a 3-level table read for 4 levels reads other memory), the hot-start
    counter kept."""
    hierarchy = QPHierarchy()
    for level_count, nv in ((3, 5), (4, 5), (4, 7), (3, 5)):
        kept_keys, sides, known, used, counters, enforced, residuals = \
            hierarchy.cascade_state(level_count, nv)
        assert sides.shape[1:] == (level_count, nv) and known.shape[1] == level_count
        assert kept_keys.shape[1] == nv and enforced.shape == (nv,)
        assert residuals.shape == (level_count,) and counters is hierarchy._counters


def test_kept_active_sets_are_least_recently_used_slots():
    """A key seen before gets its own slot back; a new one starts from a
    copy of the sets used last, in an empty slot or else the least recently used one."""
    kept = KeptActiveSets.empty(1, 2)
    kept = KeptActiveSets(kept.keys[:2], kept.sides[:2], kept.known[:2], kept.used[:2])
    patterns = [np.array(pattern) for pattern in ([True, True], [True, False], [False, True])]
    first = _kept_slot(patterns[0], *kept)
    kept.sides[first, 0] = [1, -1]
    kept.known[first, 0] = True
    second = _kept_slot(patterns[1], *kept)
    assert second != first and list(kept.sides[second, 0]) == [1, -1] and kept.known[second, 0]
    kept.sides[second, 0] = [-1, 0]
    assert _kept_slot(patterns[0], *kept) == first       # seen: its own sets, now last used
    assert list(kept.sides[first, 0]) == [1, -1]
    assert _kept_slot(patterns[2], *kept) == second       # full: the least recently used
    assert list(kept.sides[second, 0]) == [1, -1]         # a copy of the last used sets


@pytest.mark.parametrize("keyed_apart", [True, False])
def test_solves_keyed_apart_hot_start_from_their_own_active_sets(keyed_apart):
    """The clamping loop's solutions of one step fix the same DoFs but have other bounds
    (a damped joint is bounded by its damped variation, not fixed). Keyed apart by the
    joints they fix or damp (kept_key), each starts the next step from the active set it
    ended with, and its polish certifies that set at its first solve. Keyed by their
    fixed DoFs alone, each started from the other's set (Talos reaching out of reach,
    bench support's reach far: 6.5 solves per polish, now 1.2)."""
    nv = 6
    levels = [Level(np.eye(nv), np.array([0.5, -0.5, 0.5, 0.05, 0.0, 0.5]))]
    tight = (np.full(nv, -0.1), np.full(nv, 0.1))          # 0, 1, 2 and 5 active
    damped = (np.r_[np.full(3, -1.0), np.full(3, -0.1)],
              np.r_[np.full(3, 1.0), np.full(3, 0.1)])     # 5 active
    keys = (np.zeros(nv, dtype=bool), np.arange(nv) < 3 if keyed_apart else
            np.zeros(nv, dtype=bool))
    solver = QPHierarchy(damping=DAMPING)
    for bounds, key in zip((tight, damped), keys):         # a first step: sets to keep
        solver.solve_stacked(*stack_levels(levels, nv), bounds=bounds, kept_key=key)
    hot_starts, polish_solves = solver.hot_starts, solver.polish_solves
    for _ in range(3):
        for bounds, key in zip((tight, damped), keys):
            solution = solver.solve_stacked(*stack_levels(levels, nv), bounds=bounds,
                                            kept_key=key)
            np.testing.assert_allclose(solution.dq, np.clip(levels[0].target, *bounds),
                                       atol=1e-5)
    assert solver.hot_starts - hot_starts == 6
    if keyed_apart:
        assert solver.polish_solves - polish_solves == 6
    else:
        assert solver.polish_solves - polish_solves > 12


def test_polish_lets_a_joining_bound_replace_the_one_it_conflicts_with():
    """One variable wanting 1, two bounds on it (upper 0.5, then 0.3), hot-started with the
    first active: the second joins, is dependent on the first and must replace it."""
    step, active, upper_side, status = _polish(
        np.ones((1, 1)), np.ones(1), DAMPING, np.ones((2, 1)), np.full(2, -1.0),
        np.array([0.5, 0.3]), np.array([True, False]), np.array([True, False]), 1e-12,
        polish_counters())
    assert status == CERTIFIED
    assert list(active) == [False, True] and upper_side[1]
    np.testing.assert_allclose(step, [0.3], atol=1e-15)


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_polish_drops_the_bound_a_dependent_joining_one_makes_redundant(side):
    """y wants (0, 10) under A: y1 + y2 <= 2, B: -y1 + y2 <= 2 and w: 3 y2 <= 9; the
    optimum (0, 2) is on A and B only. Hot-started on {w, A}, B joins and depends on both:
    it must replace w (the only one the dual step can drive to 0), not A. Replacing the
    last pivoted row instead swaps A and B forever. side -1: the same on lower bounds
    (target, bounds and optimum negated)."""
    rows = np.array([[0.0, 3.0], [1.0, 1.0], [-1.0, 1.0]])     # w, A, B
    bounds = np.array([9.0, 2.0, 2.0])
    low, high = (np.full(3, -10.0), bounds) if side > 0 else (-bounds, np.full(3, 10.0))
    on_upper = np.array([True, True, False]) & (side > 0)
    step, active, upper_side, status = _polish(
        np.eye(2), np.array([0.0, 10.0 * side]), DAMPING, rows, low, high,
        np.array([True, True, False]), on_upper, 1e-12, polish_counters())
    assert status == CERTIFIED
    assert list(active) == [False, True, True]
    assert list(upper_side[1:]) == [side > 0] * 2
    np.testing.assert_allclose(step, [0.0, 2.0 * side], atol=1e-12)


@st.composite
def level_qps(draw):
    """(P, r, rows, low, high, exact optimum, its active set and sides, flips) of a level's
    QP with y = 0 feasible (low <= 0 <= high; some bounds of zero width, as for a joint on
    its limit), up to 2.5x as many bound rows as variables, the target far outside, and up
    to `flips` of the optimum's active set flipped for a hot start (the optimum of the
    exact primal active-set method)."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    variables, wanted = int(rng.integers(2, 13)), int(rng.integers(1, 13))
    count = int(rng.integers(2, int(2.5 * variables) + 1))
    rows = rng.normal(size=(count, variables))
    low, high = -rng.uniform(0.0, 1.0, count), rng.uniform(0.0, 1.0, count)
    low[rng.random(count) < 0.15], high[rng.random(count) < 0.15] = 0.0, 0.0
    projected, residual_ = rng.normal(size=(wanted, variables)), 10.0 * rng.normal(size=wanted)
    exact, active, upper_side, converged = _active_set_solve(projected, residual_, DAMPING,
                                                             rows, low, high)
    assert converged
    flips = rng.choice(count, size=min(count, int(rng.integers(0, 4))), replace=False)
    start = active.copy()
    start[flips] = ~start[flips]
    sides = upper_side | (~active & (rng.random(count) < 0.5))
    return projected, residual_, rows, low, high, exact, start, sides


@PROPERTY
@given(problem=level_qps())
def test_polish_from_a_nearby_hot_start_certifies_the_exact_optimum(problem):
    """From the optimum's active set with up to 3 bounds flipped (a hot start: the set
    changes little from one step to the next), the polish certifies the exact optimum;
    polished again from the set it kept, it gives the same bits (the compiled clamping
    loop's hand-over to ProxSuite polishes the levels above the failing one twice)."""
    projected, residual_, rows, low, high, exact, start, sides = problem
    slack = 1e-12 * (1.0 + np.abs(projected.T @ residual_).max())
    step, active, upper_side, status = _polish(projected, residual_, DAMPING, rows, low,
                                               high, start, sides, slack, polish_counters())
    assert status == CERTIFIED
    np.testing.assert_allclose(step, exact, rtol=0, atol=1e-8)
    again = _polish(projected, residual_, DAMPING, rows, low, high, active, upper_side, slack,
                    polish_counters())
    assert again[3] == CERTIFIED and again[0].tobytes() == step.tobytes()


@PROPERTY
@given(seed=st.integers(0, 2**32 - 1))
def test_polish_certifies_a_large_step_on_its_active_set_at_once(seed):
    """A level whose residual is 200 (a support polygon 1000 m ahead) and whose rows
    barely move it (singular values near lambda): its step is 1e4-1e5, and rounding
    misses its independent active rows by 1e-11. Only rows past the rank of the active
    set are checked for a miss: hot-started on the optimum's set, the polish certifies
    it with one solve. Checking every active row dropped the ones rounding missed, and a
    polish took 46-48 solves (some levels of that run ran out of rounds)."""
    rng = np.random.default_rng(seed)
    variables, bounds = 12, 8
    projected = DAMPING * rng.uniform(0.5, 2.0) * np.linalg.qr(
        rng.normal(size=(variables, variables)))[0][:4]
    residual_ = 200.0 * rng.normal(size=4)
    rows = rng.normal(size=(bounds, variables))
    rows /= np.linalg.norm(rows, axis=1)[:, None]
    low, high = -rng.uniform(0.0, 0.02, bounds), rng.uniform(0.0, 0.02, bounds)
    exact, active, upper_side, converged = _active_set_solve(projected, residual_, DAMPING,
                                                             rows, low, high)
    assert converged and active.any() and np.abs(exact).max() > 1e3
    counters = polish_counters()
    step, _, _, status = _polish(projected, residual_, DAMPING, rows, low, high, active,
                                 upper_side, _multiplier_slack(projected, residual_),
                                 counters)
    assert status == CERTIFIED and counters[1] == 1
    np.testing.assert_allclose(step, exact, rtol=1e-9, atol=0)


@PROPERTY
@given(seed=st.integers(0, 2**32 - 1))
def test_polish_certifies_a_degenerate_zero_step_from_a_wrong_set(seed):
    """y = 0 is the optimum, held by more bounds of zero room than the level has variables
    (a posture level whose joints all sit on their limits): the descent g is a nonnegative
    combination of their outward normals, but not of every independent subset's. Hot-
    started on such a subset, whose multipliers have a wrong sign, the polish certifies
    y = 0 at its first solve by NNLS over all the tight bounds; the dual method dropped
    the subset's bounds one by one and added them back (31-37 solves)."""
    rng = np.random.default_rng(seed)
    variables = int(rng.integers(3, 10))
    tight = variables + int(rng.integers(2, variables + 1))
    rows = rng.normal(size=(tight + 3, variables))
    low, high = np.full(tight + 3, -1.0), np.zeros(tight + 3)
    high[tight:] = 1.0                                   # three bounds with room left
    multipliers = rng.uniform(0.0, 1.0, tight) * (rng.random(tight) < 0.7)
    projected = rng.normal(size=(variables + 2, variables))
    gradient = rows[:tight].T @ multipliers             # g = P^T r, in the tight cone
    residual_ = np.linalg.lstsq(projected.T, gradient, rcond=None)[0]
    start = np.zeros(tight + 3, dtype=bool)
    start[rng.choice(tight, size=variables, replace=False)] = True
    counters = polish_counters()
    step, _, _, status = _polish(projected, residual_, DAMPING, rows, low, high, start,
                                 start.copy(), _multiplier_slack(projected, residual_),
                                 counters)
    assert status == CERTIFIED and counters[1] == 1
    assert np.abs(step).max() <= 1e-12


def test_hot_starts_hold_with_the_hands_out_of_reach(talos):
    """Talos' hands pulled out to the sides, out of reach (the bench's arms out): the arms
    stretch against their bounds and the active sets of the hands and posture levels
    change as they go. The polish (Goldfarb and Idnani's dual method) still finds the
    KKT point from the last set, so ProxSuite solves under 1 % of the levels whose bounds
    cross; swapping the most violated bound and the worst multiplier in turn cycled there
    and left nine steps in ten to ProxSuite, each 3-13 ms."""
    start = bench_start(talos)
    specs = parse_stack_yaml(TALOS_LEVEL_STACK)
    contender = StanceContender(talos, "progressive", specs,
                                bench_targets(talos, specs, start, ARMS_OUT), start, 0.002,
                                qp=True)
    q = start
    for _ in range(400):
        q = contender.step(q)[0]
    hierarchy = contender.solver.hierarchy
    assert hierarchy.hot_starts > 400        # the bounds did bind, several levels a step
    polishes = hierarchy.hot_starts + hierarchy.qp_solves
    assert hierarchy.qp_solves < 0.01 * polishes
    # each clamping solution starts from the set it ended with a step before (kept per
    # fixed and damped joints): 1.08 solves per polish, 3.4 when the step's two solutions
    # shared one kept set
    assert hierarchy.polish_solves < 1.5 * polishes
    assert limit_excess(talos, q) == 0.0


def test_nonnegative_fit_survives_a_column_left_out_by_the_rank_cut():
    """The entering column dependent to within the rank tolerance: no 0 / 0."""
    x, residual = _nonnegative_fit(np.array([[2.0, 1.0], [0.0, 5e-13]]),
                                   np.array([1.0, 30.0]), 2e-12)
    assert np.all(np.isfinite(x)) and np.all(x >= 0.0)
    assert np.isfinite(residual) and residual <= np.hypot(1.0, 30.0)


@pytest.mark.parametrize("rotate", [qp_hierarchy._transposed_q_rows,
                                    getattr(qp_hierarchy._transposed_q_rows, "py_func",
                                            qp_hierarchy._transposed_q_rows)],
                         ids=["compiled", "python"])
@pytest.mark.parametrize("wanted", [1, 3])
def test_rotating_a_task_leaves_it_untouched(rotate, wanted):
    """(P Q)^T of a one-row P (contiguous either way, which NumPy's ascontiguousarray hands
    back uncopied) and of a Fortran-ordered P: Q^T P^T, P unchanged."""
    rng = np.random.default_rng(wanted)
    active_rows, projected = rng.normal(size=(2, 5)), rng.normal(size=(wanted, 5))
    factorization = qp_hierarchy._pivoted_qr(np.ascontiguousarray(active_rows.T), -1)
    q = np.eye(5)
    for reflector, scale in zip(factorization[0], factorization[1]):
        q = q @ (np.eye(5) - scale * np.outer(reflector, reflector))
    for task in (projected, np.asfortranarray(projected)):
        before = task.copy()
        np.testing.assert_allclose(rotate(factorization, task), q.T @ before.T, atol=1e-12)
        np.testing.assert_array_equal(task, before)
