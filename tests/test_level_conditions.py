"""Each level's condition in a step's report: met, conflict (higher levels, limits or
bounds take what it needs) or singular (its own rows cannot give its step): a singular or
contradictory stack returns a solution and says so."""

import numpy as np
import pytest

from stance.pik import LM_DAMPING, PIKSolver
from stance.robot import Robot
from stance.stack import parse_stack_yaml
from stance_tools.bench import bench_start

FEET = """
- {name: left_foot, kind: pose, frame: left_sole_link, priority: 0, gain: 0.5}
- {name: right_foot, kind: pose, frame: right_sole_link, priority: 0, gain: 0.5}
"""


@pytest.fixture(scope="module")
def talos():
    return Robot.from_example_robot_data("talos")


def stepped(robot, stack, moves, hierarchy, steps=3, lm_damping=LM_DAMPING):
    """The report of the last of `steps` steps, pose targets moved by `moves` (m, world)."""
    q = bench_start(robot)
    solver = PIKSolver(robot, hierarchy=hierarchy, dt=0.002, lm_damping=lm_damping)
    solver.set_stack(parse_stack_yaml(FEET + stack), q)
    for name, offset in moves.items():
        target = solver.task(name).target
        target.translation += np.asarray(offset, dtype=float)
        solver.task(name).set_target(target)
    for _ in range(steps):
        result = solver.step(q)
        q = result.q
    assert np.all(np.isfinite(result.q))
    return {level.priority: level for level in result.levels}


HAND_AND_POSTURE = """
- {name: hand, kind: position, frame: gripper_right_base_link, priority: 1, gain: 0.1}
- {name: posture, kind: posture, priority: 2, gain: 0.02}
"""


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_reachable_levels_are_met(talos, hierarchy):
    """Without Levenberg-Marquardt damping a reachable step is met at once."""
    levels = stepped(talos, HAND_AND_POSTURE, {"hand": (0.05, 0.0, 0.05)}, hierarchy,
                     lm_damping=0.0)
    assert levels[0].condition == levels[1].condition == "met"
    assert levels[2].condition == "conflict"   # the hand's level takes part of the posture's


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_a_level_its_lm_damping_holds_back_is_damped(talos, hierarchy):
    """With it the same hand's level gets its damped step: damped, its lambda above the
    feet's (met: their targets are reached, lambda about `damping`)."""
    levels = stepped(talos, HAND_AND_POSTURE, {"hand": (0.05, 0.0, 0.05)}, hierarchy)
    assert levels[0].condition == "met" and levels[1].condition == "damped"
    assert levels[1].damping > 10 * levels[0].damping
    assert levels[0].damping == pytest.approx(1e-3, rel=1e-3)


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
@pytest.mark.parametrize("priority, condition", [(2, "conflict"), (1, "singular")])
def test_a_contradicting_level_is_a_conflict_contradicting_rows_are_singular(
        talos, hierarchy, priority, condition):
    """The same hand at level 1 and, 0.1 m higher, at level 2 (the higher level takes what
    the lower needs: conflict) or also at level 1 (no dq gives both: singular)."""
    levels = stepped(talos, f"""
- {{name: hand, kind: position, frame: gripper_right_base_link, priority: 1, gain: 0.1}}
- {{name: hand_again, kind: position, frame: gripper_right_base_link, priority: {priority},
   gain: 0.1}}
""", {"hand_again": (0.0, 0.0, 0.1)}, hierarchy)
    assert levels[0].condition == "met"
    assert levels[priority].condition == condition
    assert levels[priority].step_residual_norm > 1e-3
