"""Posture generator: contacts matched, joint limits, static stability (coplanar and not),
failures with a reason, the static equilibrium region against the LP, locked joints, and
guide targets (a tolerance and a weight of their own)."""

import dataclasses
import math

import numpy as np
import pinocchio as pin
import pytest

from stance.planning.contacts import Contact
from stance.planning.equilibrium import contacts_equilibrium
from stance.execution.interpolation import SpotPose
from stance.planning.posture import (PostureGenerator, PostureSettings, ReferencePosture,
                                     equilibrium_region)
from stance.planning.scene import ContactSpot, Goal, Obstacle, Scene, Surface
from stance.robot import Robot

FLIP = pin.SE3(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
SOLE = np.array([[-0.1, -0.05], [0.1, -0.05], [0.1, 0.05], [-0.1, 0.05]])
PALM = np.array([[-0.03, -0.03], [0.03, -0.03], [0.03, 0.03], [-0.03, 0.03]])


def square(half):
    return np.array([[-half, -half], [half, -half], [half, half], [-half, half]], float)


@pytest.fixture(scope="module")
def robot():
    return Robot.load("talos")


@pytest.fixture(scope="module")
def scene(robot):
    """Talos on a floor, a table top to its front right, a wall to its left."""
    q0 = robot.initial_configuration()
    spots = {
        "left_sole": ContactSpot("left_sole", "left_sole_link", FLIP, SOLE),
        "right_sole": ContactSpot("right_sole", "right_sole_link", FLIP, SOLE),
        "right_hand": ContactSpot("right_hand", "gripper_right_base_link", pin.SE3.Identity(),
                                  PALM),
        "left_hand": ContactSpot("left_hand", "gripper_left_base_link", pin.SE3.Identity(),
                                 PALM),
    }
    wall_rotation = pin.rpy.rpyToMatrix(math.pi / 2, 0.0, 0.0)   # normal along -y
    surfaces = {
        "floor": Surface("floor", pin.SE3.Identity(), square(2.0), 0.7, "floor_box"),
        "table": Surface("table", pin.SE3(np.eye(3), np.array([0.35, -0.3, 0.75])),
                         square(0.3), 0.7),
        "wall": Surface("wall", pin.SE3(wall_rotation, np.array([0.2, 0.75, 1.0])),
                        square(0.5), 0.7),
        "far_table": Surface("far_table", pin.SE3(np.eye(3), np.array([2.5, 0.0, 0.75])),
                             square(0.2), 0.7),
    }
    obstacles = {"floor_box": Obstacle("floor_box", "box",
                                       pin.SE3(np.eye(3), np.array([0.0, 0.0, -0.05])),
                                       np.array([4.0, 4.0, 0.1]))}
    return Scene("posture_test", "talos", surfaces, obstacles, spots, [], q0,
                 np.array([q0, q0]), Goal("base_link", "x", 0.3))


@pytest.fixture(scope="module")
def generator(robot, scene):
    return PostureGenerator(robot, scene)


def sole_contact(robot, scene, spot, dx=0.0, dy=0.0):
    q0 = robot.initial_configuration()
    pin.framesForwardKinematics(robot.model, robot.data, q0)
    frame = robot.data.oMf[robot.model.getFrameId(scene.spots[spot].frame)]
    contact = frame * scene.spots[spot].placement * FLIP
    theta = math.atan2(contact.rotation[1, 0], contact.rotation[0, 0])
    return Contact(spot, "floor", contact.translation[0] + dx, contact.translation[1] + dy,
                   theta)


def spot_pose(generator, q, spot):
    pin.framesForwardKinematics(generator.model, generator.data, q)
    return generator.data.oMf[generator.model.getFrameId(f"spot:{spot}")]


def assert_realised(generator, scene, result):
    assert result.success, result.reason
    for contact in result.contacts:
        target = contact.spot_target(scene.surfaces[contact.surface])
        achieved = spot_pose(generator, result.q, contact.spot)
        assert np.linalg.norm(achieved.translation - target.translation) < 1e-3
        angle = np.linalg.norm(pin.log3(achieved.rotation.T @ target.rotation))
        assert angle < math.radians(1.0)
    robot = generator.robot
    q_limited = result.q[robot.limited_q_index]
    assert np.all(q_limited >= robot.lower - 1e-9) and np.all(q_limited <= robot.upper + 1e-9)


@pytest.mark.parametrize("dx", [0.0, 0.15, 0.3])
def test_a_moved_foot_is_reached_with_the_com_over_the_feet(robot, scene, generator, dx):
    contacts = (sole_contact(robot, scene, "left_sole"),
                sole_contact(robot, scene, "right_sole", dx=dx))
    q0 = robot.initial_configuration()
    result = generator.generate(contacts, q0, ReferencePosture(robot.model, q0))
    assert_realised(generator, scene, result)
    com = pin.centerOfMass(generator.model, generator.data, result.q)
    equilibrium = contacts_equilibrium(contacts, scene, com, generator.mass)
    assert equilibrium.feasible and equilibrium.margin > 0


def test_a_hand_on_a_table_with_one_foot_supporting(robot, scene, generator):
    """Non-coplanar support: left sole and right hand carry the robot; the right sole only
    touches (a contact being broken)."""
    contacts = (sole_contact(robot, scene, "left_sole"),
                sole_contact(robot, scene, "right_sole").with_stability(False),
                Contact("right_hand", "table", 0.05, 0.0, 0.0))
    q0 = robot.initial_configuration()
    result = generator.generate(contacts, q0, ReferencePosture(robot.model, q0))
    assert_realised(generator, scene, result)
    com = pin.centerOfMass(generator.model, generator.data, result.q)
    support = [c for c in contacts if c.in_stability]
    assert contacts_equilibrium(support, scene, com, generator.mass).feasible


def test_an_unreachable_contact_fails_with_its_reason(robot, scene, generator):
    contacts = (sole_contact(robot, scene, "left_sole"),
                sole_contact(robot, scene, "right_sole"),
                Contact("right_hand", "far_table", 0.0, 0.0, 0.0))
    q0 = robot.initial_configuration()
    result = generator.generate(contacts, q0, ReferencePosture(robot.model, q0))
    assert not result.success
    assert "right_hand" in result.reason and "not reached" in result.reason


def test_no_supporting_contact_is_refused(robot, scene, generator):
    contact = sole_contact(robot, scene, "left_sole").with_stability(False)
    result = generator.generate((contact,), robot.initial_configuration(), None)
    assert not result.success and "supporting" in result.reason


def test_equilibrium_region_is_inside_what_the_lp_accepts(robot, scene, generator):
    """Every CoM inside the (inner) region is in static equilibrium by the LP; the region
    is not trivially small; far outside it the LP fails."""
    support = (sole_contact(robot, scene, "left_sole"),
               Contact("left_hand", "wall", 0.0, 0.2, 0.0))
    a, b = equilibrium_region(support, scene)
    rng = np.random.default_rng(3)
    inside = 0
    for point in rng.uniform(-1.0, 1.5, size=(400, 2)):
        if np.all(a @ point <= b - 1e-6):
            inside += 1
            com = np.array([point[0], point[1], 0.9])
            assert contacts_equilibrium(support, scene, com, generator.mass).margin > -1e-6
    assert inside > 0
    far = np.array([5.0, 5.0, 0.9])
    assert not contacts_equilibrium(support, scene, far, generator.mass).feasible


def test_locked_joints_never_move(robot, scene):
    locked = dataclasses.replace(scene, locked_joints=("gripper_right_joint", "arm_left_4_joint"))
    generator = PostureGenerator(robot, locked)
    contacts = (sole_contact(robot, scene, "left_sole"),
                sole_contact(robot, scene, "right_sole"),
                Contact("right_hand", "table", 0.05, 0.0, 0.0))
    q0 = robot.initial_configuration()
    free = PostureGenerator(robot, scene).generate(contacts, q0, ReferencePosture(robot.model, q0))
    result = generator.generate(contacts, q0, ReferencePosture(robot.model, q0))
    assert_realised(generator, scene, result)
    for name in locked.locked_joints:
        index = robot.model.joints[robot.model.getJointId(name)].idx_q
        assert result.q[index] == q0[index], name
    moved = robot.model.joints[robot.model.getJointId("arm_left_4_joint")].idx_q
    assert abs(free.q[moved] - q0[moved]) > 1e-3   # the lock is what keeps it


def test_a_posture_does_not_depend_on_the_generations_before_it(robot, scene):
    """With collision rows: the same call gives the bitwise same posture from a fresh
    generator and from one that generated other postures first (a planner's worker
    processes each see a different share of the calls). A budget of 30 s keeps the
    deadline (a first call may compile kernels) out of it."""
    from stance.planning.collision import CollisionModel

    def fresh():
        return PostureGenerator(robot, scene, CollisionModel(robot, scene))

    q0 = robot.initial_configuration()
    call = ((sole_contact(robot, scene, "left_sole"),
             sole_contact(robot, scene, "right_sole").with_stability(False),
             Contact("right_hand", "table", 0.05, 0.0, 0.0)), q0,
            ReferencePosture(robot.model, q0))
    expected = fresh().generate(*call, time_budget=30.0)
    used = fresh()
    for dx in (0.1, 0.2):
        used.generate((sole_contact(robot, scene, "left_sole"),
                       sole_contact(robot, scene, "right_sole", dx=dx)), q0,
                      ReferencePosture(robot.model, q0), time_budget=30.0)
    again = used.generate(*call, time_budget=30.0)
    assert expected.success and again.iterations == expected.iterations
    np.testing.assert_array_equal(again.q, expected.q)


def test_a_guide_target_yields_to_the_contacts_within_its_tolerance(robot, scene):
    """A hand target out of reach: as a contact it fails; as a guide of weight 1e-2 and a
    tolerance larger than its distance it is accepted where the arm stops, with the feet
    still on their contacts."""
    generator = PostureGenerator(robot, scene, settings=PostureSettings(time_budget=math.inf))
    feet = (sole_contact(robot, scene, "left_sole"), sole_contact(robot, scene, "right_sole"))
    q0 = robot.initial_configuration()
    far = pin.SE3(np.eye(3), np.array([0.9, -0.3, 1.0]))     # ~0.3 m beyond the right hand
    hard = generator.generate(feet + (SpotPose("right_hand", None, far),), q0,
                              ReferencePosture(robot.model, q0, 1e-2))
    assert not hard.success and "right_hand not reached" in hard.reason
    guide = SpotPose("right_hand", None, far, tolerance=0.6, weight=1e-2)
    result = generator.generate(feet + (guide,), q0, ReferencePosture(robot.model, q0, 1e-2))
    assert result.success, result.reason
    reached = spot_pose(generator, result.q, "right_hand").translation
    assert 0.05 < np.linalg.norm(reached - far.translation) < 0.6
    assert np.linalg.norm(reached - far.translation) < \
        np.linalg.norm(spot_pose(generator, q0, "right_hand").translation - far.translation)
    for contact in feet:
        achieved = spot_pose(generator, result.q, contact.spot)
        target = contact.spot_target(scene.surfaces[contact.surface])
        assert np.linalg.norm(achieved.translation - target.translation) < 1e-3


def test_rows_out_of_one_steps_reach_give_the_step_toward_them():
    """A row the trust region cannot satisfy in one step (x0 >= 2 with |x| <= 1) is made
    soft: the step goes as far toward it as the bounds allow instead of failing."""
    from stance.planning.posture import _solve_daqp

    step = _solve_daqp(np.eye(2), np.array([0.0, 0.3]), np.array([[1.0, 0.0]]),
                       np.array([2.0]), np.array([np.inf]), -np.ones(2), np.ones(2))
    assert step is not None
    np.testing.assert_allclose(step, [1.0, -0.3], atol=1e-9)


def test_a_limit_cycle_of_the_iteration_is_recognised(robot, generator):
    """Steps that bring q back to where it was two or three iterations ago without lowering
    the contact error end the descent; a zigzag that still drifts or still lowers the error
    does not."""
    import collections

    rng = np.random.default_rng(3)
    q0 = robot.initial_configuration()
    there, aside = rng.uniform(-0.1, 0.1, (2, robot.model.nv))
    q1 = pin.integrate(robot.model, q0, there)
    back = pin.integrate(robot.model, q1, -0.99 * there)       # 1 % short of q0
    onward = pin.integrate(robot.model, q1, there)              # q0 + 2 steps away
    step = float(np.linalg.norm(there))
    flat, falling = [2e-3, 3e-3, 2e-3], [2e-3, 3e-3, 1.5e-3]
    two = collections.deque([q0, q1], maxlen=3)
    assert generator._cycling(two, back, step, flat)
    assert not generator._cycling(two, onward, step, flat)
    assert not generator._cycling(two, back, step, falling)
    # q0 -> q1 -> q2 -> back near q0
    q2 = pin.integrate(robot.model, q1, aside)
    three = collections.deque([q0, q1, q2], maxlen=3)
    closing = pin.difference(robot.model, q2, q0)
    around = pin.integrate(robot.model, q2, 0.99 * closing)
    assert generator._cycling(three, around, float(np.linalg.norm(closing)), [2e-3] + flat)
    assert not generator._cycling(three, around, float(np.linalg.norm(closing)),
                                  [2e-3] + falling)


def contact_error(generator, scene, contacts, q):
    """Largest contact error component (m or rad), as the generator measures it."""
    largest = 0.0
    for contact in contacts:
        target = contact.spot_target(scene.surfaces[contact.surface])
        achieved = spot_pose(generator, q, contact.spot)
        rotation = pin.log3(target.rotation @ achieved.rotation.T)
        largest = max(largest, np.abs(target.translation - achieved.translation).max(),
                      np.abs(rotation).max())
    return largest


def test_contacts_within_tolerance_end_the_descent_once_the_step_is_small(robot, scene):
    """A criterion pulling against the contacts (quadratic penalties) leaves a contact error
    floor. Inside the tolerance but above half of it, the call ends once the step is small
    instead of running to max_iterations, and succeeds."""
    contacts = (sole_contact(robot, scene, "left_sole"),
                sole_contact(robot, scene, "right_sole", dx=0.1))
    q0 = robot.initial_configuration()
    reference = q0.copy()
    reference[7:] += 0.2                   # every joint 0.2 rad off: a pull on the soles
    criterion = ReferencePosture(robot.model, reference, 0.1)
    floor_run = PostureGenerator(robot, scene, settings=PostureSettings(contact_tolerance=1e-12))
    floor = contact_error(floor_run, scene, contacts,
                          floor_run.generate(contacts, q0, criterion).q)
    settings = PostureSettings(contact_tolerance=1.5 * floor)
    result = PostureGenerator(robot, scene, settings=settings).generate(contacts, q0, criterion)
    assert result.success, result.reason
    assert 0.5 * settings.contact_tolerance < contact_error(floor_run, scene, contacts, result.q)
    assert result.iterations < settings.max_iterations / 2
