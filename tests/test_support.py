"""Inequality rows in the QP hierarchy: the support task (CoM inside a support polygon).

A level's inequality rows bind it and every level below; the level meets them as well as it
can, and no lower level ever takes a row further out than its level left it. Without an
active row the answer is the unconstrained one.
"""

import numpy as np
import pinocchio as pin
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from helpers.problems import hierarchy_problems, residual
from stance.hierarchy import stack_levels
from stance.pik import PIKSolver
from stance.qp_hierarchy import Inequalities, QPHierarchy
from stance.robot import Robot
from stance.stack import StackError, parse_stack_yaml
from stance.tasks import ComTask, TargetError, frame_rectangle_corners
from stance_tools.bench import bench_start

DAMPING = 1e-3
PRIORITY_TOLERANCE = 1e-8
BOUND_TOLERANCE = 1e-9
AGREEMENT = 1e-7   # two certified KKT points of one level (MULTIPLIER_SLACK / damping^2)
PROPERTY = settings(max_examples=100, deadline=None, derandomize=True, database=None)


@st.composite
def row_problems(draw):
    """(levels, nv, fixed_index, fixed_dq, bounds, Inequalities): random levels, bounds
    around 0 and 1-4 random rows per problem, each declared by a random level, with room
    of either sign (some rows start violated)."""
    levels, nv, fixed_index, fixed_dq, rng = draw(hierarchy_problems())
    width = 10.0 ** rng.uniform(-2, 0.5, size=(2, nv))
    count = int(rng.integers(1, 5))
    inequalities = Inequalities(rng.normal(size=(count, nv)), rng.normal(size=count),
                                rng.integers(0, len(levels), size=count),
                                [f"row{row}" for row in range(count)])
    return levels, nv, fixed_index, fixed_dq, (-width[0], width[1]), inequalities


def rows_of_levels(inequalities, level_count):
    """The rows declared by levels 0 .. level_count - 1."""
    keep = inequalities.level < level_count
    return Inequalities(inequalities.rows[keep], inequalities.room[keep],
                        inequalities.level[keep],
                        [label for label, kept in zip(inequalities.labels, keep) if kept])


def solve(solver, levels, nv, fixed_index, fixed_dq, bounds, inequalities):
    jacobian, target, offsets = stack_levels(levels, nv)
    return solver.solve_stacked(jacobian, target, offsets, fixed_index, fixed_dq,
                                bounds=bounds, inequalities=inequalities)


def excess(inequalities, dq):
    """How far each row is beyond its room (0 inside)."""
    return np.maximum(inequalities.rows @ dq - inequalities.room, 0.0)


@PROPERTY
@given(row_problems())
def test_a_lower_level_never_disturbs_a_higher_one_with_inequalities(problem):
    """Solving levels 0..i alone (with their rows) and solving the whole stack give level
    i the same residual, and no row of levels 0..i ends further out in the whole stack."""
    levels, nv, fixed_index, fixed_dq, bounds, inequalities = problem
    solver = QPHierarchy(damping=DAMPING)
    full = solve(solver, levels, nv, fixed_index, fixed_dq, bounds, inequalities)
    for index, level in enumerate(levels):
        prefix_rows = rows_of_levels(inequalities, index + 1)
        prefix = solve(solver, levels[:index + 1], nv, fixed_index, fixed_dq, bounds,
                       prefix_rows)
        assert abs(residual(level, full.dq) - residual(level, prefix.dq)) < PRIORITY_TOLERANCE
        assert np.all(excess(prefix_rows, full.dq)
                      <= excess(prefix_rows, prefix.dq) + PRIORITY_TOLERANCE)


@PROPERTY
@given(row_problems())
def test_rows_bounds_and_fixed_joints_hold_and_the_answer_is_reproducible(problem):
    levels, nv, fixed_index, fixed_dq, bounds, inequalities = problem
    first = solve(QPHierarchy(damping=DAMPING), levels, nv, fixed_index, fixed_dq, bounds,
                  inequalities)
    again = solve(QPHierarchy(damping=DAMPING), levels, nv, fixed_index, fixed_dq, bounds,
                  inequalities)
    np.testing.assert_array_equal(first.dq, again.dq)
    np.testing.assert_array_equal(first.dq[fixed_index], fixed_dq)
    free = np.ones(nv, dtype=bool)
    free[fixed_index] = False
    lower, upper = bounds
    assert np.all(first.dq[free] >= lower[free] - BOUND_TOLERANCE)
    assert np.all(first.dq[free] <= upper[free] + BOUND_TOLERANCE)
    assert np.all(np.isfinite(first.step_residuals))
    outside = inequalities.rows @ first.dq >= inequalities.room - 1e-9
    assert [label for label, out in zip(inequalities.labels, outside) if out] == \
        [name for name in first.binding if name.startswith("row")]


@PROPERTY
@given(row_problems())
def test_rows_that_never_bind_leave_the_unconstrained_answer(problem):
    levels, nv, fixed_index, fixed_dq, bounds, inequalities = problem
    solver = QPHierarchy(damping=DAMPING)
    loose = inequalities._replace(room=np.full(len(inequalities.room), 1e9))
    with_rows = solve(solver, levels, nv, fixed_index, fixed_dq, bounds, loose)
    without = solve(solver, levels, nv, fixed_index, fixed_dq, bounds, None)
    np.testing.assert_allclose(with_rows.dq, without.dq, rtol=0, atol=AGREEMENT)


def test_a_violated_row_of_a_level_without_equalities_is_met():
    """One level of only a row 2 units out: the level brings dq onto it (up to damping^2
    of the shortfall), and the level below moves along it."""
    rows = np.array([[1.0, 1.0, 0.0]])
    inequalities = Inequalities(rows, np.array([-2.0]), np.array([0]), ["wall"])
    jacobian = np.vstack([np.zeros((0, 3)), np.eye(3)])
    offsets = np.array([0, 0, 3])
    solution = QPHierarchy(damping=DAMPING).solve_stacked(
        jacobian, np.array([5.0, 0.0, 1.0]), offsets, inequalities=inequalities)
    assert rows @ solution.dq == pytest.approx([-2.0], abs=1e-5)
    assert solution.dq[2] == pytest.approx(1.0, abs=1e-5)
    assert solution.binding == ["wall"]


def test_a_row_violation_weighs_its_weight_squared_against_the_damping():
    """One level of only a row 2 units out, weighted by w: min w^2 (t + 2)^2 + lambda^2
    (|y|^2 + t^2) over t = rows y (the slack on the row), so t = -2 w^2 / (w^2 + 1.5
    lambda^2) (|rows|^2 = 2); the level below keeps it there. PIKSolver weights a support
    level's rows by its Levenberg-Marquardt factor."""
    rows = np.array([[1.0, 1.0, 0.0]])
    jacobian = np.vstack([np.zeros((0, 3)), np.eye(3)])
    for weight in (1.0, DAMPING, 0.1 * DAMPING):
        inequalities = Inequalities(rows, np.array([-2.0]), np.array([0]), ["wall"],
                                    np.array([weight]))
        solution = QPHierarchy(damping=DAMPING).solve_stacked(
            jacobian, np.array([5.0, 0.0, 1.0]), np.array([0, 0, 3]),
            inequalities=inequalities)
        expected = -2.0 * weight ** 2 / (weight ** 2 + 1.5 * DAMPING ** 2)
        assert rows @ solution.dq == pytest.approx([expected], rel=1e-6)


def test_contradictory_rows_and_tasks_return_a_solution_naming_the_rows():
    """Level 0 wants dq_0 = 1, its row dq_0 <= 0: met halfway (same weight); the level
    below must not push further; the row is named binding."""
    rows = np.array([[1.0, 0.0]])
    inequalities = Inequalities(rows, np.array([0.0]), np.array([0]), ["cap"])
    jacobian = np.array([[1.0, 0.0], [1.0, 1.0]])
    solution = QPHierarchy(damping=DAMPING).solve_stacked(
        jacobian, np.array([1.0, 3.0]), np.array([0, 1, 2]), inequalities=inequalities)
    assert solution.dq[0] == pytest.approx(0.5, abs=1e-5)
    assert solution.dq[0] + solution.dq[1] == pytest.approx(3.0, abs=1e-5)
    assert solution.step_residuals[0] == pytest.approx(0.5, abs=1e-5)
    assert solution.binding == ["cap"]


@pytest.mark.parametrize("inequalities, message", [
    (Inequalities(np.full((1, 2), np.nan), np.zeros(1), np.zeros(1, dtype=np.int64), ["a"]),
     "NaN"),
    (Inequalities(np.ones((1, 3)), np.zeros(1), np.zeros(1, dtype=np.int64), ["a"]),
     "rows"),
    (Inequalities(np.ones((1, 2)), np.zeros(1), np.array([3]), ["a"]), "levels"),
    (Inequalities(np.ones((1, 2)), np.zeros(1), np.array([0]), ["a"], np.zeros(1)),
     "weight"),
    (Inequalities(np.ones((1, 2)), np.zeros(1), np.array([0]), ["a"], np.ones(2)),
     "weight"),
])
def test_malformed_inequalities_are_refused(inequalities, message):
    with pytest.raises(ValueError, match=message):
        QPHierarchy().solve_stacked(np.eye(2), np.ones(2), np.array([0, 2]),
                                    inequalities=inequalities)


# Talos: feet > CoM inside the feet's support polygon > right hand pulled away > posture.

SUPPORT_STACK = """
- {name: left_foot, kind: pose, frame: left_sole_link, priority: 0, gain: 0.5}
- {name: right_foot, kind: pose, frame: right_sole_link, priority: 0, gain: 0.5}
- {name: balance, kind: support, priority: 1, gain: 0.2}
- {name: right_hand, kind: pose, frame: gripper_right_base_link, priority: 2, gain: 0.1}
- {name: posture, kind: posture, priority: 3, gain: 0.02}
"""
SOLE_HALF_SIZE = (0.08, 0.04)      # m, inside Talos' sole patch (0.10, 0.05)
HAND_PULL = (0.6, -0.6, -0.3)      # m: far out to the front right, below
SECOND_ORDER = 5e-4                # m: the CoM's excess over one linearized step


@pytest.fixture(scope="module")
def talos():
    return Robot.from_example_robot_data("talos")


def feet_polygon(robot, q) -> np.ndarray:
    """Corners of both sole rectangles in the world's xy plane (m)."""
    pin.framesForwardKinematics(robot.model, robot.data, q)
    return frame_rectangle_corners(robot, ("left_sole_link", "right_sole_link"),
                                   SOLE_HALF_SIZE)


def pulled_solver(robot, q, support: bool, polygon=None):
    solver = PIKSolver(robot, hierarchy="qp", dt=0.002)
    specs = [spec for spec in parse_stack_yaml(SUPPORT_STACK)
             if support or spec.kind != "support"]
    solver.set_stack(specs, q)
    if support:
        solver.task("balance").set_target(feet_polygon(robot, q) if polygon is None
                                          else polygon)
    hand = solver.task("right_hand")
    target = hand.target
    target.translation += np.array(HAND_PULL)
    hand.set_target(target)
    return solver


def com_distance_outside(robot, q, polygon) -> float:
    hull_task = PIKSolver(robot, hierarchy="qp")
    hull_task.set_stack(parse_stack_yaml("[{name: s, kind: support}]"), q)
    hull_task.task("s").set_target(polygon)
    hull_task.compute_kinematics(q)
    return hull_task.task("s").distance_outside(robot)


def test_talos_com_stays_over_the_feet_while_a_hand_pulls_it_out(talos):
    q0 = bench_start(talos)
    polygon = feet_polygon(talos, q0)
    runs = {}
    for support in (False, True):
        solver, q, worst = pulled_solver(talos, q0, support), q0.copy(), 0.0
        for _ in range(400):
            result = solver.step(q)
            q = result.q
            worst = max(worst, com_distance_outside(talos, q, polygon))
        runs[support] = worst, result
    assert runs[False][0] > 0.1     # unconstrained, the hand drags the CoM off the feet
    worst, result = runs[True]
    assert worst < SECOND_ORDER
    assert result.task_errors["left_foot"] < 1e-4 and result.task_errors["right_foot"] < 1e-4
    assert any(name.startswith("balance edge") for name in result.binding_constraints)


def test_talos_com_outside_the_polygon_comes_back_at_the_task_gain(talos):
    q0 = bench_start(talos)
    shifted = feet_polygon(talos, q0) + np.array([0.12, 0.0])   # CoM ~3 cm behind it
    solver = PIKSolver(talos, hierarchy="qp")
    solver.set_stack([spec for spec in parse_stack_yaml(SUPPORT_STACK)
                      if spec.name != "right_hand"], q0)
    solver.task("balance").set_target(shifted)
    q, distances = q0.copy(), []
    for _ in range(60):
        result = solver.step(q)
        distances.append(result.task_errors["balance"])
        q = result.q
    assert distances[0] > 0.01
    assert all(later <= earlier + 1e-6 for earlier, later in zip(distances, distances[1:]))
    assert distances[1] == pytest.approx(0.8 * distances[0], rel=0.05)   # gain 0.2
    assert com_distance_outside(talos, q, shifted) < 1e-4


@pytest.mark.parametrize("behind", [0.05, 0.5, 3.0])
def test_an_edge_asks_back_gain_x_the_distance_at_most_max_step(talos, behind):
    """The CoM `behind` m behind a polygon's back edge: that edge asks it back by gain x
    the distance per step, at most SupportTask.max_step (a CoM task's cap), while LM
    damping counts the whole gain x distance; the edges it is inside ask nothing back."""
    q = bench_start(talos)
    solver = PIKSolver(talos, hierarchy="qp")
    solver.set_stack(parse_stack_yaml(SUPPORT_STACK), q)
    task = solver.task("balance")
    solver.compute_kinematics(q)
    com_x = talos.data.com[0][0]
    task.set_target(np.array([[1.0, -1.0], [2.0, -1.0], [2.0, 1.0], [1.0, 1.0]])
                    + [com_x + behind - 1.0, 0.0])
    rows, room, returns = (np.empty((4, talos.model.nv)), np.empty(4), np.empty(4))
    task.write_inequalities(talos, rows, room, returns)
    back = int(np.argmin(room))
    assert task.max_step == ComTask.max_step == 0.02
    assert returns[back] == pytest.approx(task.gain * behind, rel=1e-9)
    assert room[back] == pytest.approx(-min(task.gain * behind, task.max_step), rel=1e-9)
    others = np.arange(4) != back
    assert np.all(room[others] > 0.0) and np.all(returns[others] == 0.0)


def test_support_needs_the_qp_hierarchy(talos):
    solver = PIKSolver(talos, hierarchy="svd")
    with pytest.raises(StackError, match="only the qp hierarchy"):
        solver.set_stack(parse_stack_yaml(SUPPORT_STACK), bench_start(talos))


@pytest.mark.parametrize("ahead", [1.0, 1000.0])
def test_a_polygon_out_of_reach_leaves_the_levels_below_to_their_hot_starts(talos, ahead):
    """The support level cannot keep its rows (the polygon `ahead` m in front): the rows
    it misses become equalities of the levels below, which then solve from their hot
    starts. Kept as exactly tight inequalities, they left those levels degenerate, and
    ProxSuite solved 1.6-2 of them per step. Its Levenberg-Marquardt damping grows with
    its shortfall, as a task's with its step target (tests/test_lm_damping.py): the CoM
    heads for a polygon 1 m ahead, and holds where it is for one 1000 m ahead, as hands
    out of reach do. Either way the level reports the CoM's distance outside, not met."""
    q = bench_start(talos)
    solver = PIKSolver(talos, hierarchy="qp", dt=0.002)
    solver.set_stack(parse_stack_yaml(SUPPORT_STACK), q)
    solver.task("balance").set_target(feet_polygon(talos, q) + [ahead, 0.0])
    distances = []
    for step in range(300):
        if step == 100:
            solves = solver.hierarchy.qp_solves
        result = solver.step(q)
        q = result.q
        distances.append(result.task_errors["balance"])
    assert (solver.hierarchy.qp_solves - solves) / 200 < 0.5
    if ahead < 10.0:
        assert distances[-1] < distances[100] - 0.05   # the CoM heads for the polygon
    else:
        assert abs(distances[-1] - distances[100]) < 0.01
    assert result.levels[0].condition == "met"      # the feet hold
    balance = result.levels[1]
    assert balance.tasks == ["balance"] and balance.condition != "met"
    assert balance.residual_norm == pytest.approx(distances[-1], rel=1e-12)


def test_a_support_task_sent_again_keeps_its_polygon(talos):
    """A stack sent again keeps each task's target: for a support task, its polygon."""
    q = bench_start(talos)
    solver = PIKSolver(talos, hierarchy="qp")
    solver.set_stack(parse_stack_yaml(SUPPORT_STACK), q)
    solver.task("balance").set_target(feet_polygon(talos, q))
    before = solver.task("balance").vertices.copy()
    solver.set_stack(parse_stack_yaml(SUPPORT_STACK), q)
    np.testing.assert_array_equal(solver.task("balance").vertices, before)
    assert solver.task("balance").edge_count == len(before)


@pytest.mark.parametrize("vertices, message", [
    ([[0, 0], [1, 0], [np.nan, 1]], "NaN"),
    ([[0, 0], [1, 0]], ">= 3"),
    ([[0, 0], [1, 1], [2, 2]], "no area"),
    ([[0, 0], [1e7, 0], [0, 1]], "beyond"),
    ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "xy"),
])
def test_bad_polygons_are_refused_and_the_old_one_kept(talos, vertices, message):
    q = bench_start(talos)
    solver = PIKSolver(talos, hierarchy="qp")
    solver.set_stack(parse_stack_yaml(SUPPORT_STACK), q)
    task = solver.task("balance")
    task.set_target(feet_polygon(talos, q))
    before = task.vertices.copy()
    with pytest.raises(TargetError, match=message):
        task.set_target(vertices)
    np.testing.assert_array_equal(task.vertices, before)


SOAK_EPISODES, SOAK_STEPS = 20, 100   # 2,000 random steps on the QP hierarchy


def test_random_episodes_keep_the_com_inside_or_bring_it_back(talos):
    """Random hand targets (reachable or 1-1.5 m away) and polygons (the soles' hull,
    sometimes moved so that the CoM starts up to 4 cm outside): no step takes the CoM
    further out than one linearized step's second-order error, it ends inside, and no
    joint leaves its limits."""
    q0 = bench_start(talos)
    soles = feet_polygon(talos, q0)
    for seed in range(SOAK_EPISODES):
        rng = np.random.default_rng(seed)
        polygon = soles + (rng.uniform(-0.04, 0.04, 2) if rng.random() < 0.5 else 0.0)
        solver = PIKSolver(talos, hierarchy="qp", dt=0.002)
        solver.set_stack(parse_stack_yaml(SUPPORT_STACK), q0)
        solver.task("balance").set_target(polygon)
        hand = solver.task("right_hand")
        target = hand.target
        reach = 1.5 if rng.random() < 0.3 else 0.4
        target.translation += rng.uniform(-reach, reach, 3)
        hand.set_target(target)
        q, distances = q0.copy(), []
        for _ in range(SOAK_STEPS + 1):
            result = solver.step(q)    # its report: the CoM's distance outside at q
            distances.append(result.task_errors["balance"])
            assert np.all(q[talos.limited_q_index] <= talos.upper + 1e-9), seed
            assert np.all(q[talos.limited_q_index] >= talos.lower - 1e-9), seed
            q = result.q
        for before, after in zip(distances, distances[1:]):
            assert after <= before + SECOND_ORDER, seed
        assert distances[-1] <= SECOND_ORDER, seed
