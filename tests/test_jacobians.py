"""Finite-difference checks of every task kind's Jacobian on Talos.

Each task holds its current value as target (error 0). Since the error is target minus
current value, its derivative along a tangent direction v is -J v; we compare it with a
central difference of the error along pin.integrate(q, +-eps v).
"""

import numpy as np
import pinocchio as pin
import pytest

from stance.pik import PIKSolver
from stance.robot import Robot
from stance.stack import TaskSpec
from stance.tasks import FrameTaskBatch, make_task

EPSILON = 1e-6
RELATIVE_TOLERANCE = 1e-6
SEEDS = range(4)
DIRECTIONS_PER_CONFIGURATION = 3

TASK_SPECS = [
    TaskSpec("pose", "pose", frame="gripper_right_base_link"),
    TaskSpec("position", "position", frame="gripper_left_base_link"),
    TaskSpec("orientation", "orientation", frame="head_2_link"),
    TaskSpec("pose_x_z_ry", "pose", frame="left_sole_link", axes=("x", "z", "ry")),
    TaskSpec("position_y", "position", frame="arm_right_4_link", axes=("y",)),
    TaskSpec("orientation_rz_rx", "orientation", frame="torso_2_link", axes=("rz", "rx")),
    TaskSpec("com", "com"),
    TaskSpec("com_xy", "com", axes=("x", "y")),
    TaskSpec("posture", "posture"),
]


@pytest.fixture(scope="module")
def talos():
    return Robot.from_example_robot_data("talos")


def random_configuration(robot, rng) -> np.ndarray:
    """Random base pose and limited joints drawn uniformly inside their limits."""
    q = pin.neutral(robot.model)
    q[:3] = rng.uniform(-1.0, 1.0, 3)
    q[3:7] = pin.Quaternion(*rng.normal(size=4)).normalized().coeffs()
    q[robot.limited_q_index] = rng.uniform(robot.lower, robot.upper)
    return q


def task_error(solver, task, q) -> np.ndarray:
    solver.compute_kinematics(q)
    return task.jacobian_and_error(solver.robot, q)[1]


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("spec", TASK_SPECS, ids=lambda spec: spec.name)
def test_jacobian_matches_finite_differences(talos, spec, seed):
    """-J v equals the central difference of the error along v, at error 0."""
    rng = np.random.default_rng(seed)
    q = random_configuration(talos, rng)
    solver = PIKSolver(talos)
    solver.set_stack([spec], q)  # the task holds its value at q: error 0
    task = solver.task(spec.name)
    solver.compute_kinematics(q)
    jacobian, error = (np.array(part) for part in task.jacobian_and_error(talos, q))
    assert np.allclose(error, 0.0, atol=1e-12)
    for _ in range(DIRECTIONS_PER_CONFIGURATION):
        direction = rng.normal(size=talos.model.nv)
        plus = task_error(solver, task, pin.integrate(talos.model, q, EPSILON * direction))
        minus = task_error(solver, task, pin.integrate(talos.model, q, -EPSILON * direction))
        finite_difference = (plus - minus) / (2.0 * EPSILON)
        expected = -jacobian @ direction
        scale = np.abs(expected).max()
        np.testing.assert_allclose(finite_difference, expected, rtol=RELATIVE_TOLERANCE,
                                   atol=RELATIVE_TOLERANCE * scale)



@pytest.mark.parametrize("seed", SEEDS)
def test_frame_rows_are_pinocchios_frame_jacobian_bit_for_bit(talos, seed):
    """A frame task's rows, read in place from the joint Jacobians, equal
    pinocchio.getFrameJacobian (LOCAL_WORLD_ALIGNED) exactly, and a FrameTaskBatch writes
    each task's rows exactly as the task's own write() does."""
    rng = np.random.default_rng(seed)
    q = random_configuration(talos, rng)
    solver = PIKSolver(talos)
    solver.compute_kinematics(q)
    tasks = [make_task(spec, talos) for spec in TASK_SPECS if spec.frame]
    for task in tasks:
        task.target = pin.SE3.Random()
        jacobian, _ = task.jacobian_and_error(talos, q)
        expected = pin.getFrameJacobian(talos.model, talos.data, task.frame_id,
                                        pin.LOCAL_WORLD_ALIGNED)[task.rows]
        assert np.array_equal(jacobian, expected)
    starts = np.cumsum([0, *(task.dimension for task in tasks)])
    jacobian, error = np.zeros((starts[-1], talos.model.nv)), np.zeros(starts[-1])
    FrameTaskBatch(talos, tasks, starts[:-1]).write(talos, jacobian, error)
    for task, start, end in zip(tasks, starts[:-1], starts[1:]):
        task_jacobian, task_error = task.jacobian_and_error(talos, q)
        assert np.array_equal(jacobian[start:end], task_jacobian)
        assert np.array_equal(error[start:end], task_error)
