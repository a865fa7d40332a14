"""The kinematic chain experiment of Raunhardt and Boulic (Figs. 9-10), asserted on the runs.

Findings of the paper checked on the computed trajectories: GPM (Liegeois joint-limit
avoidance at the lowest priority) lets joints 2 and 3 leave their limits; clamping and
progressive clamping never do; progressive clamping has no over-swing (a lower peak joint
acceleration near the limits than clamping); the final errors of the three methods are
within 10 % of each other and not zero (the tasks conflict).
"""

import numpy as np
import pytest

from stance.experiments import chain
from stance.limits import STRATEGIES


@pytest.fixture(scope="module")
def runs():
    return chain.run_chain()


def test_gpm_is_a_registered_strategy():
    assert list(STRATEGIES) == ["none", "gpm", "clamping", "progressive"]
    assert not STRATEGIES["gpm"].enforces_limits


def test_gpm_violates_the_limits_of_joints_2_and_3(runs):
    assert {2, 3} <= set(chain.violating_joints(runs["gpm"]))


@pytest.mark.parametrize("strategy", ["clamping", "progressive"])
def test_clamping_methods_never_violate_a_limit(runs, strategy):
    assert chain.violating_joints(runs[strategy]) == []


def test_the_qp_hierarchy_leaves_the_limits_to_the_strategy():
    """With hierarchy qp the joint limits are bounds only for the strategies that enforce
    them: GPM and none leave them as on the SVD hierarchy, the clamping methods never."""
    runs = chain.run_chain(hierarchy="qp")
    assert {2, 3} <= set(chain.violating_joints(runs["gpm"]))
    robot = chain.build_chain()
    start = np.zeros(robot.model.nq)
    unlimited = chain.run_strategy(chain.chain_solver(robot, "none", start, "qp"), start,
                                   chain.STEPS, [])
    assert chain.violating_joints(unlimited) != []
    assert chain.violating_joints(runs["clamping"]) == []
    assert chain.violating_joints(runs["progressive"]) == []


def test_progressive_clamping_has_no_over_swing(runs):
    progressive = chain.peak_acceleration_near_limits(runs["progressive"])
    clamping = chain.peak_acceleration_near_limits(runs["clamping"])
    assert progressive < clamping


def test_final_errors_agree_within_ten_percent_and_are_not_zero(runs):
    finals = np.array([run.total_error[-1] for run in runs.values()])
    assert finals.min() > 0.05  # m: the targets conflict
    assert finals.max() <= 1.1 * finals.min()


def test_gpm_pulls_joints_toward_mid_range_in_the_task_nullspace():
    """Without tasks (all DoFs free) one GPM step is -gain * dH/dq, shrunk by the damped
    least squares factor 1 / (1 + lambda^2) of the identity level."""
    robot = chain.build_chain()
    solver = chain.chain_solver(robot, "gpm", np.zeros(robot.model.nq))
    for index in range(len(chain.TARGETS)):
        solver.set_enabled(chain.effector_name(index), False)
    q = np.linspace(-0.9, 0.9, robot.model.nq)
    count, span = robot.model.nq, 2 * chain.JOINT_LIMIT
    expected = -chain.GPM_GAIN * q / (count * span**2) / (1 + chain.DAMPING**2)
    assert solver.step(q).dq == pytest.approx(expected, rel=1e-9)


def test_reproduce_writes_figures_and_tables(tmp_path, runs, monkeypatch):
    monkeypatch.setattr(chain, "run_chain", lambda steps=chain.STEPS: runs)
    paths = chain.reproduce(tmp_path)
    assert {path.name for path in paths} == {
        "chain_joints.png", "chain_errors.png", "chain_damping.png", "chain.md", "chain.json"}
    assert all(path.stat().st_size > 0 for path in paths)
