"""Tracking a timed plan offline (stance.execution.tracking), as trajectory_node and pik_node
do together: the execution stack per transition, the shipped chair plan tracked with the
default graph's parameters holding every contact within check-run's tolerance, and the
arrival gate: a contact is created only once its frame is there, and one is released only
once the CoM is over the rest."""

import math

from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from stance.execution.interpolation import TransitionPlanner
from stance.execution.timing import sinusoidal_trajectory, time_optimal_trajectory
from stance.execution.tracking import (ARRIVAL_COM_TOLERANCE, ARRIVAL_TOLERANCE, GAINS,
                                       ArrivalGate, task_targets, track, transition_tasks)
from stance.pik import PIKSolver
from stance.planning.collision import CollisionModel
from stance.planning.contacts import load_plan
from stance.planning.equilibrium import contacts_equilibrium
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
        stack, held, _ = transition_tasks(scene, planner, plan, index, GAINS)
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
    assert tracking.holds == [], "the chair plan waited for a contact without any load"


def test_the_arrival_gate_waits_for_every_created_contact_within_both_tolerances():
    target = pin.SE3(pin.rpy.rpyToMatrix(0.1, -0.2, 0.3), np.array([0.4, -0.1, 0.0]))
    position, angle = ARRIVAL_TOLERANCE
    gate = ArrivalGate({"left_sole": target, "right_hand": target}, timeout=2.0)
    near = target * pin.SE3(pin.rpy.rpyToMatrix(0.0, 0.0, 0.5 * angle),
                            np.array([0.0, 0.5 * position, 0.0]))
    shifted = target * pin.SE3(np.eye(3), np.array([2.0 * position, 0.0, 0.0]))
    turned = target * pin.SE3(pin.rpy.rpyToMatrix(2.0 * angle, 0.0, 0.0), np.zeros(3))
    assert not gate.update({"left_sole": near}, now=10.0)        # right_hand: no pose yet
    assert set(gate.late) == {"right_hand"} and gate.late["right_hand"][0] == math.inf
    assert not gate.update({"left_sole": shifted, "right_hand": near}, now=10.5)
    assert gate.late["left_sole"] == pytest.approx((2.0 * position, 0.0), abs=1e-12)
    assert "left_sole 2.0 mm, 0.000 rad off" == gate.describe_late()
    assert not gate.update({"left_sole": near, "right_hand": turned}, now=11.0)
    assert gate.late["right_hand"][1] == pytest.approx(2.0 * angle)
    assert gate.waited(11.0) == 1.0 and not gate.timed_out(11.0) and gate.timed_out(12.5)
    assert gate.update({"left_sole": near, "right_hand": target}, now=11.5)
    assert gate.late == {} and gate.waited(11.5) == 1.5
    assert set(gate.late_when_due) == {"right_hand"}   # what was missing when due
    assert ArrivalGate({}).update({}, now=0.0) and ArrivalGate({}).waited(3.0) == 0.0


def test_the_arrival_gate_waits_for_the_com_in_x_and_y_only():
    position = ARRIVAL_COM_TOLERANCE
    gate = ArrivalGate({}, com=np.array([0.1, -0.2, 0.8]))
    assert not gate.update({}, now=0.0)                       # no CoM reported yet
    assert gate.late == {"com": (math.inf, 0.0)}
    assert not gate.update({}, now=0.1, com=np.array([0.1 + 2.0 * position, -0.2, 0.8]))
    assert gate.describe_late() == f"com {2e3 * position:.1f} mm off"
    assert gate.update({}, now=0.2, com=np.array([0.1, -0.2 + 0.5 * position, 0.3]))
    assert gate.waited(0.2) == pytest.approx(0.2)


def test_created_contacts_are_the_moving_spots_landing_at_the_next_stance(flat_steps_plan):
    robot, scene, plan = flat_steps_plan
    planner = TransitionPlanner(robot, scene, CollisionModel(robot, scene), steps=10)
    for index in range(len(plan.stances) - 1):
        first, second = plan.stances[index], plan.stances[index + 1]
        _, _, created = transition_tasks(scene, planner, plan, index, GAINS)
        before = {c.spot: (c.surface, c.x, c.y, c.theta) for c in first.contacts}
        expected = {c.spot for c in second.contacts
                    if before.get(c.spot) != (c.surface, c.x, c.y, c.theta)}
        assert set(created) == expected
        held_next = transition_tasks(scene, planner, plan, index + 1, GAINS)[1] \
            if index + 2 < len(plan.stances) else {}
        for spot, target in created.items():
            if spot in held_next:   # the next transition holds it at the same target
                assert np.allclose(held_next[spot].homogeneous, target.homogeneous)


def test_a_lagging_contact_is_created_only_once_it_has_arrived(flat_steps_plan):
    """Soles tracked with a weak contact gain (0.02: a stand-in for an IK that falls behind
    under load) at half the URDF speeds: without the gate a sole is held at its exact
    contact from centimetres away and dragged; with it every transition end that lags
    waits, and no held contact is ever off by more than the arrival tolerance."""
    robot, scene, plan = flat_steps_plan
    planner = TransitionPlanner(robot, scene, CollisionModel(robot, scene), steps=10)
    path = planner.interpolate(plan)
    trajectory = sinusoidal_trajectory(robot, path.q, path.event_samples, 0.5)
    gains = {**GAINS, "contact": 0.02}

    def tracked(tolerance, com_tolerance):
        return track(PIKSolver(robot, dt=1.0 / 500.0), scene, planner, plan, path,
                     trajectory, gains=gains, tolerance=tolerance, com_tolerance=com_tolerance)

    ungated = tracked((math.inf, math.inf), math.inf)
    gated = tracked(ARRIVAL_TOLERANCE, ARRIVAL_COM_TOLERANCE)
    assert ungated.holds == [] and ungated.worst()[0] > 10.0 * ARRIVAL_TOLERANCE[0]
    assert gated.holds and all(arrived for _, _, arrived in gated.holds)
    assert gated.worst()[0] <= ARRIVAL_TOLERANCE[0] + 1e-6
    assert gated.times[-1] == pytest.approx(trajectory.duration + sum(
        waited for _, waited, _ in gated.holds), abs=0.05)
    assert gated.transitions[-1] == len(plan.stances) - 2


def test_a_lagging_com_releases_no_contact_before_it_is_over_the_rest(flat_steps_plan):
    """The CoM tracked with a weak gain (0.05: a stand-in for an IK that falls behind under
    load): without the gate a sole lifts while the CoM is still on its way over the other,
    and the robot leaves static equilibrium on the contacts it holds; with it each
    transition starts from the stance's CoM and the robot stays in equilibrium throughout
    (every tenth IK step checked)."""
    robot, scene, plan = flat_steps_plan
    planner = TransitionPlanner(robot, scene, CollisionModel(robot, scene), steps=10)
    path = planner.interpolate(plan)
    trajectory = sinusoidal_trajectory(robot, path.q, path.event_samples, 0.5)
    mass = pin.computeTotalMass(robot.model)
    supports = [tuple(c.with_stability(True) for c in plan.stances[k].contacts
                      if c.spot in transition_tasks(scene, planner, plan, k, GAINS)[1])
                for k in range(len(plan.stances) - 1)]

    def margins(com_tolerance):
        tracking = track(PIKSolver(robot, dt=1.0 / 500.0), scene, planner, plan, path,
                         trajectory, gains={**GAINS, "com": 0.05}, com_tolerance=com_tolerance)
        return tracking, np.array([
            contacts_equilibrium(supports[tracking.transitions[i]], scene, tracking.com[i],
                                 mass).margin for i in range(0, len(tracking.times), 10)])

    ungated, ungated_margins = margins(math.inf)
    gated, gated_margins = margins(ARRIVAL_COM_TOLERANCE)
    assert ungated.holds == [] and ungated_margins.min() < 0.0
    assert gated.holds and all(arrived for _, _, arrived in gated.holds)
    assert gated_margins.min() > 0.0
    data = robot.model.createData()
    for k in range(1, len(plan.stances) - 1):   # each transition starts at the stance's CoM
        first = int(np.argmax(gated.transitions == k))
        witness = pin.centerOfMass(robot.model, data, plan.stances[k].q, False)
        assert np.linalg.norm(gated.com[first - 1, :2] - witness[:2]) <= ARRIVAL_COM_TOLERANCE
