"""Tracking a timed plan offline (stance.execution.tracking), as trajectory_node and pik_node
do together: the execution stack per transition, and the shipped chair plan tracked with
the default graph's parameters holding every contact within check-run's tolerance."""

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from stance.execution.interpolation import TransitionPlanner
from stance.execution.timing import time_optimal_trajectory
from stance.execution.tracking import GAINS, task_targets, track, transition_tasks
from stance.pik import PIKSolver
from stance.planning.collision import CollisionModel
from stance.planning.contacts import load_plan
from stance.planning.scene import load_scene
from stance.robot import Robot
from stance_tools.check_run import CONTACT_TOLERANCE
from stance_tools.demo import VELOCITY_SCALE
from stance_tools.graph import DEFAULT_GRAPH, load_graph

ROOT = Path(__file__).resolve().parent.parent
CHAIR_PLAN = ROOT / "docs" / "figures" / "chair_table_plan.json"
WITNESS_CONTACT_TOLERANCE = 1e-3  # m: verified witnesses match their contacts within 1 mm


def node_parameters(package: str) -> dict:
    """The node's parameters in its shipped file, with the default graph's overrides."""
    shipped = yaml.safe_load((ROOT / "src" / package / "config" / f"{package}.yaml")
                             .read_text())[package]["ros__parameters"]
    [spec] = [spec for spec in load_graph(DEFAULT_GRAPH) if spec.executable == package]
    return {**shipped, **spec.parameters}


@pytest.fixture(scope="module")
def chair():
    """(robot, scene, the shipped chair plan, planner at n = 20, its path)."""
    plan = load_plan(str(CHAIR_PLAN))
    robot = Robot.load(load_scene(plan.scene).robot)
    scene = load_scene(plan.scene, robot)
    planner = TransitionPlanner(robot, scene, CollisionModel(robot, scene), steps=20)
    return robot, scene, plan, planner, planner.interpolate(plan)


def test_held_contacts_lead_the_stack_and_their_targets_are_met_at_the_witness(chair):
    robot, scene, plan, planner, _ = chair
    model, data = robot.model, pin.Data(robot.model)
    for index in range(len(plan.stances) - 1):
        stack, held = transition_tasks(scene, planner, plan, index, GAINS)
        moving = planner.moving_paths(plan.stances[index], plan.stances[index + 1])
        assert {spec.name for spec in stack if spec.priority == 0} == set(held)
        assert set(held).isdisjoint(moving) and set(moving) <= {
            spec.name for spec in stack if spec.priority == 1}
        q = plan.stances[index].q
        targets = task_targets(model, data, stack, held, q)
        np.testing.assert_array_equal(targets["posture"], q)
        np.testing.assert_allclose(targets["com"], pin.centerOfMass(model, data, q), atol=1e-12)
        pin.framesForwardKinematics(model, data, q)
        for spot, target in held.items():
            frame = data.oMf[model.getFrameId(scene.spots[spot].frame)]
            assert np.linalg.norm(frame.translation - target.translation) \
                < WITNESS_CONTACT_TOLERANCE


def test_the_chair_plan_tracked_with_the_graphs_parameters_holds_every_contact(chair):
    """What `stance demo --scenario chair` executes (time-optimal at the demo's speed), with
    pik_node's and trajectory_node's parameters in the default graph: every held contact
    stays within check-run's tolerance, at every IK step of the 91 stances."""
    robot, scene, plan, planner, path = chair
    pik, trajectory_node = node_parameters("pik_node"), node_parameters("trajectory_node")
    rate = pik["rate"]
    trajectory = time_optimal_trajectory(robot, path.q, path.event_samples, VELOCITY_SCALE,
                                         trajectory_node["acceleration_limit"])
    solver = PIKSolver(robot, strategy=pik["strategy"], damping=pik["damping"],
                       activation=pik["activation"], dt=1.0 / rate,
                       locked_joints=pik.get("locked_joints", ()))
    gains = {name: trajectory_node[f"{name}_gain"] for name in ("contact", "com", "posture")}
    tracking = track(solver, scene, planner, plan, path, trajectory, rate=rate,
                     target_rate=trajectory_node["rate"], gains=gains)
    error, time, transition = tracking.worst()
    assert tracking.transitions[-1] == len(plan.stances) - 2
    assert error < CONTACT_TOLERANCE, f"{error * 1e3:.2f} mm at t = {time:.2f} s, " \
                                      f"transition {transition}"
