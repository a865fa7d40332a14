"""Each level's condition in a step's report: met, conflict (higher levels, limits or
bounds take what it needs), singular (its own rows cannot give its step) or damped (its
Levenberg-Marquardt damping alone holds part of it back): a singular or contradictory stack
returns a solution and says so."""

import numpy as np
import pinocchio as pin
import pytest

from stance.pik import LM_DAMPING, PIKSolver
from stance.robot import Robot
from stance.stack import TaskSpec, parse_stack_yaml
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


RUNTIME_KERNELS_CHECK = """
import numba
import numpy as np
from stance import hierarchy, limits, pik, qp_hierarchy, swing, tasks
from stance.robot import Robot
from stance.stack import parse_stack_yaml
from stance_tools.bench import bench_start

def loaded():
    return {(module.__name__, name, str(signature))
            for module in (hierarchy, limits, pik, qp_hierarchy, swing, tasks)
            for name, kernel in vars(module).items()
            if isinstance(kernel, numba.core.registry.CPUDispatcher)
            for signature in kernel.signatures}

talos = Robot.from_example_robot_data("talos")
q = bench_start(talos)
solver = pik.PIKSolver(talos, hierarchy=HIERARCHY, dt=0.002, lm_damping=pik.LM_DAMPING)
solver.set_stack(parse_stack_yaml(STACK), q)
solver.warm_up(q)
before = loaded()
target = solver.task("hand").target
target.translation += np.array([0.05, 0.0, 0.05])
solver.task("hand").set_target(target)
for _ in range(3):
    result = solver.step(q)
    q = result.q
print([level.condition for level in result.levels])
print(sorted(loaded() - before))
"""


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_warm_up_loads_what_a_damped_level_report_calls(hierarchy):
    """A level short of its step has its condition decided from Python at the first status
    read (_level_condition): warm_up must have loaded those kernels from numba's cache, or
    pik_node's control loop paid 40-80 ms at the first plan step it fell behind in. In a
    fresh process (this one has loaded them already)."""
    import subprocess
    import sys

    script = (f"HIERARCHY = {hierarchy!r}\nSTACK = {FEET + HAND_AND_POSTURE!r}\n"
              + RUNTIME_KERNELS_CHECK)
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    conditions, loaded = done.stdout.strip().splitlines()
    assert conditions == "['met', 'damped', 'conflict']"
    assert loaded == "[]"


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


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_a_level_a_clamped_joint_holds_back_is_a_conflict_not_damped(hierarchy):
    """Panda's hand turned about the base's z axis, beyond the only joint left free
    (panda_joint1, started 1 mm inside its upper limit): the joint stops on its limit and
    the hand's level keeps its whole step. LM damping also holds part of the step back,
    but with lambda = damping the clamped joint would still leave it: conflict."""
    panda = Robot.from_example_robot_data("panda")
    q = panda.initial_configuration("default")
    joint = panda.model.joints[panda.model.getJointId("panda_joint1")]
    q[joint.idx_q] = panda.model.upperPositionLimit[joint.idx_q] - 1e-3
    others = [name for name in panda.actuated_joint_names if name != "panda_joint1"]
    solver = PIKSolver(panda, hierarchy=hierarchy, dt=0.002, locked_joints=others)
    solver.set_stack(parse_stack_yaml("""
- {name: hand, kind: position, frame: panda_hand, priority: 0, gain: 0.1}
"""), q)
    target = solver.task("hand").target
    target.translation = pin.utils.rpyToMatrix(0.0, 0.0, 0.2) @ target.translation
    solver.task("hand").set_target(target)
    for _ in range(3):
        result = solver.step(q)
        q = result.q
    assert q[joint.idx_q] <= panda.model.upperPositionLimit[joint.idx_q] + 1e-12
    hand = result.levels[0]
    assert hand.damping > 10 * solver.damping     # LM damping is on for this level
    assert hand.step_residual_norm > 0.9 * 0.1 * hand.residual_norm  # nearly all kept
    assert hand.condition == "conflict"


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_a_level_the_velocity_limits_slow_is_a_conflict_not_damped(talos, hierarchy):
    """The hand 0.3 m away at gain 1: its step is far beyond the joints' velocity limits
    over 2 ms, which take part of it whatever its LM damping leaves."""
    q = bench_start(talos)
    solver = PIKSolver(talos, hierarchy=hierarchy, dt=0.002)
    solver.set_stack(parse_stack_yaml(FEET + """
- {name: hand, kind: position, frame: gripper_right_base_link, priority: 1, gain: 1.0}
"""), q)
    target = solver.task("hand").target
    target.translation += [0.3, 0.0, 0.0]
    solver.task("hand").set_target(target)
    result = solver.step(q)
    levels = {level.priority: level for level in result.levels}
    if hierarchy == "svd":                   # the hand's level saturated
        assert result.velocity_scale < 1.0
    else:                                       # velocity bounds bind
        assert any(name.endswith(" velocity") for name in result.binding_constraints)
    assert levels[0].condition == "met"
    assert levels[1].condition == "conflict"


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
@pytest.mark.parametrize("weight, damping", [(1e6, 1e-5), (1e6, 1e-6), (1e6, 1e-8),
                                             (1e5, 1e-6)])
def test_heavy_duplicate_rows_give_a_finite_step_and_a_condition(talos, hierarchy, weight,
                                                                 damping):
    """Two tasks with the same rows at a weight that dwarfs lambda^2 (Gram entries ~weight
    against damping^2, 1e16 and more apart): the Cholesky's pivots rounded to 0 or below,
    and the step was NaN or raised ZeroDivisionError (while stepping, or reading the
    level's condition). Weights stop at 1e6 (stack.MAX_WEIGHT); smaller lambdas reach the
    ratios 1e10-1e300 weights did at lambda 1e-3."""
    q = bench_start(talos)
    stack = [TaskSpec(name, "orientation", frame="right_sole_link", weight=weight)
             for name in ("a", "b")]
    solver = PIKSolver(talos, hierarchy=hierarchy, damping=damping)
    solver.set_stack(stack, q)
    target = solver.task("a").target
    target.rotation = pin.exp3(np.array([0.0, 0.0, 0.01])) @ target.rotation
    solver.task("a").set_target(target)     # a 0.01 rad conflict between the two
    result = solver.step(q)
    assert np.isfinite(result.q).all()
    assert result.levels[0].condition in ("met", "conflict", "singular", "damped")
    assert np.isfinite(result.levels[0].step_residual_norm)
