"""Interpolation between stances (Escande et al. 2008, 3.3): the moving spot's path
(straight lines along the normals, C1 spline, constant orientation then slerp), and a
flat_steps plan interpolated sample by sample (common contacts held, joint limits, ends
on the witnesses, contact events), failures naming the transition and sample, and detours
around paths the chair scene blocks."""

import math
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from stance.execution.interpolation import (DETOUR_LINE_TOLERANCE, SAMPLE_CONTACT_TOLERANCE,
                                            InterpolationError, SpotPath, TransitionPlanner,
                                            spot_pose)
from stance.planning.collision import CollisionModel
from stance.planning.contacts import Contact, Plan, Stance, load_plan
from stance.planning.planner import PlanRequest, plan_contacts
from stance.planning.scene import load_scene
from stance.robot import Robot
from stance.stopping import Stopped

LIFT = 0.05
CHAIR_PLAN = Path(__file__).resolve().parent.parent / "docs" / "figures" / "chair_table_plan.json"
UP = np.array([0.0, 0.0, 1.0])
SLANTED = np.array([0.0, math.sin(0.4), math.cos(0.4)])


@pytest.fixture(scope="module")
def path():
    """From a pose on a floor to a pose on a slanted surface, rotated."""
    start = pin.SE3(pin.rpy.rpyToMatrix(math.pi, 0.0, 0.2), np.array([0.1, 0.2, 0.0]))
    end = pin.SE3(pin.rpy.rpyToMatrix(math.pi - 0.4, 0.3, 1.0), np.array([0.6, -0.1, 0.3]))
    return SpotPath(start, end, UP, SLANTED, LIFT)


def angle(a, b):
    return float(np.linalg.norm(pin.log3(a.T @ b)))


def test_path_starts_and_ends_at_the_contact_poses(path):
    assert np.allclose(path.pose(0.0).homogeneous, path.start.homogeneous, atol=1e-12)
    assert np.allclose(path.pose(1.0).homogeneous, path.end.homogeneous, atol=1e-12)


def test_straight_lines_along_the_normals_with_constant_orientation(path):
    leave = np.linspace(0.0, path.leave_length, 7) / path.length
    enter = 1.0 - np.linspace(0.0, path.enter_length, 7) / path.length
    for s in leave:
        pose = path.pose(s)
        assert np.allclose(pose.translation, path.start.translation + s * path.length * UP,
                           atol=1e-12)
        assert angle(pose.rotation, path.start.rotation) < 1e-12
    for s in enter:
        pose = path.pose(s)
        assert np.allclose(pose.translation,
                           path.end.translation + (1.0 - s) * path.length * SLANTED, atol=1e-12)
        assert angle(pose.rotation, path.end.rotation) < 1e-12
    middle = path.pose(0.5).translation
    assert np.linalg.norm(middle - path.start.translation) > 2 * LIFT


def test_position_is_c1_at_the_junctions(path):
    h = 1e-6
    for junction in (path.leave_length / path.length,
                     (path.leave_length + path.spline_length) / path.length):
        before = (path.pose(junction).translation - path.pose(junction - h).translation) / h
        after = (path.pose(junction + h).translation - path.pose(junction).translation) / h
        assert np.linalg.norm(after - before) < 1e-3 * np.linalg.norm(before)
        assert np.linalg.norm(before) == pytest.approx(path.length, rel=1e-3)


def test_orientation_is_slerped_along_the_spline(path):
    total = angle(path.start.rotation, path.end.rotation)
    assert total > 0.5
    for fraction in (0.25, 0.5, 0.75):
        s = (path.leave_length + fraction * path.spline_length) / path.length
        rotation = path.pose(s).rotation
        assert angle(path.start.rotation, rotation) == pytest.approx(fraction * total, abs=1e-9)
        assert angle(rotation, path.end.rotation) == pytest.approx((1 - fraction) * total,
                                                                   abs=1e-9)


def test_a_free_end_has_no_straight_line():
    start = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.4]))
    end = pin.SE3(np.diag([1.0, -1.0, -1.0]), np.array([0.3, 0.0, 0.0]))
    free = SpotPath(start, end, None, UP, LIFT)
    assert free.leave_length == 0.0 and free.phase(0.01) == "spline"
    assert np.allclose(free.pose(0.0).translation, start.translation)
    assert np.allclose(free.pose(1.0).translation, end.translation)


@pytest.mark.parametrize("leave", [None, UP])
def test_a_path_onto_a_higher_surface_rises_before_it_crosses(leave):
    """A hand from the hip onto a table, a sole from the floor onto a step: once it has
    moved 2 cm toward the end, the spot stays above the end's approach height (the
    straight spline would cut the surface's edge)."""
    start = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.4]))
    end = pin.SE3(np.eye(3), np.array([0.4, 0.0, 0.75]))
    path = SpotPath(start, end, leave, UP, LIFT)
    approach = end.translation[2] + LIFT
    points = np.array([path.pose(s).translation for s in np.linspace(0.0, 1.0, 401)])
    crossing = (points[:, 0] > 0.02) & (points[:, 0] < end.translation[0] - 0.02)
    assert crossing.any() and np.all(points[crossing, 2] >= approach)
    down = SpotPath(end, start, UP, leave, LIFT)   # and back down: it descends once past
    points = np.array([down.pose(s).translation for s in np.linspace(0.0, 1.0, 401)])
    crossing = (points[:, 0] > 0.02) & (points[:, 0] < end.translation[0] - 0.02)
    assert np.all(points[crossing, 2] >= approach)


@pytest.fixture(scope="module")
def flat():
    """(robot, scene, plan, planner, interpolated plan) of flat_steps at n = 10."""
    robot = Robot.load("talos")
    scene = load_scene("flat_steps", robot)
    outcome = plan_contacts(robot, PlanRequest(scene=scene))
    assert outcome.success, outcome.message
    planner = TransitionPlanner(robot, scene, CollisionModel(robot, scene), steps=10)
    return robot, scene, outcome.plan, planner, planner.interpolate(outcome.plan)


def spot_error(planner, scene, q, contact):
    """Position (m) and orientation (rad) error of a contact at q."""
    actual = spot_pose(planner.generator, q, contact.spot)
    target = contact.spot_target(scene.surfaces[contact.surface])
    return (float(np.linalg.norm(actual.translation - target.translation)),
            angle(actual.rotation, target.rotation))


def test_samples_hold_the_common_contacts_inside_joint_limits(flat):
    robot, scene, plan, planner, path = flat
    stances, steps = plan.stances, planner.steps
    assert path.q.shape == ((len(stances) - 1) * steps + 1, robot.model.nq)
    moved = 0
    for k, q in enumerate(path.q):
        transition = path.transition[k]
        second = {(c.spot, c.surface, c.x, c.y, c.theta) for c in stances[transition + 1].contacts}
        common = [c for c in stances[transition].contacts
                  if (c.spot, c.surface, c.x, c.y, c.theta) in second]
        assert common
        for contact in common:
            position, orientation = spot_error(planner, scene, q, contact)
            assert position < 1e-3 and orientation < 1e-3, (k, contact.spot)
        joints = q[robot.limited_q_index]
        assert np.all(joints >= robot.lower - 1e-9) and np.all(joints <= robot.upper + 1e-9)
        moved += len(common) < len(stances[transition].contacts)
    assert moved > 0


def test_path_ends_on_the_witnesses_and_moves_the_stepping_sole(flat):
    robot, scene, plan, planner, path = flat
    assert np.array_equal(path.stance_samples, np.arange(len(plan.stances)) * planner.steps)
    for index, stance in enumerate(plan.stances):
        assert np.array_equal(path.q[path.stance_samples[index]], stance.q)
    stepping = [i for i, figures in enumerate(path.transitions) if figures["moving"]]
    assert stepping
    index = stepping[0]
    first, second = plan.stances[index], plan.stances[index + 1]
    (spot, (spot_path, _, _)), = planner.moving_paths(first, second).items()
    heights = []
    for k in range(1, planner.steps):
        q = path.q[path.stance_samples[index] + k]
        target = spot_path.pose(k / planner.steps)
        actual = spot_pose(planner.generator, q, spot)
        assert np.linalg.norm(actual.translation - target.translation) < 1e-3
        heights.append(actual.translation[2])
    assert max(heights) > LIFT - 1e-3


def test_contact_events_break_then_create(flat):
    _, _, plan, planner, path = flat
    kinds = {(event.sample, event.kind) for event in path.events}
    for index, figures in enumerate(path.transitions):
        start, end = index * planner.steps, (index + 1) * planner.steps
        if figures["moving"]:
            assert (start, "broken") in kinds and (end, "created") in kinds
        else:
            assert (end, "support_removed") in kinds
    assert np.array_equal(path.event_samples, path.stance_samples[1:]) or \
        np.array_equal(path.event_samples, path.stance_samples)


def test_unreachable_sample_names_transition_and_sample(flat):
    _, _, plan, planner, _ = flat
    first = plan.stances[0]
    moved = tuple(c if c.spot != "right_sole" else
                  type(c)(c.spot, c.surface, c.x + 1.5, c.y, c.theta) for c in first.contacts)
    away = first.q.copy()
    away[0] += 1.5        # the witness 1.5 m ahead: its right sole out of reach
    with pytest.raises(InterpolationError) as failure:
        planner.transition(7, first, Stance(moved, away))
    assert failure.value.transition == 7 and 1 <= failure.value.sample < planner.steps
    assert "transition 7 -> 8" in str(failure.value) and failure.value.reason


def test_an_interpolation_stops_when_asked_before_a_sample(flat):
    """should_stop is asked before each sample: the first True abandons the plan."""
    _, _, plan, planner, _ = flat
    asked = []
    with pytest.raises(Stopped, match="transition 0 -> 1, sample 4/10"):
        planner.interpolate(plan, should_stop=lambda: asked.append(True) or len(asked) > 3)
    assert len(asked) == 4


def test_plans_without_a_transition_or_with_a_witness_not_finite_are_refused(flat):
    """One stance used to give one sample (timing then raised IndexError); a NaN witness
    was taken as the posture criterion's reference and a NaN path came back."""
    robot, scene, plan, planner, _ = flat
    with pytest.raises(ValueError, match="a plan of 1 stance.s. has no transition"):
        planner.interpolate(Plan(plan.scene, plan.robot, plan.stances[:1]))
    broken = plan.stances[1].q.copy()
    broken[9] = math.nan
    stances = [plan.stances[0], Stance(plan.stances[1].contacts, broken)]
    with pytest.raises(ValueError, match="stance 1: the witness is not 39 finite values"):
        planner.interpolate(Plan(plan.scene, plan.robot, stances))
    unknown = [plan.stances[0], Stance((Contact("nose", "floor", 0.0, 0.0, 0.0),),
                                       plan.stances[1].q)]          # scipy's error before
    with pytest.raises(ValueError, match="stance 1: contacts.0..spot: unknown spot 'nose'"):
        planner.interpolate(Plan(plan.scene, plan.robot, unknown))


@pytest.mark.parametrize("keywords, message", [
    ({"steps": 0}, "steps must be an integer >= 1"),
    ({"steps": 1.5}, "steps must be an integer >= 1"),
    ({"lift": math.nan}, "lift must be finite and >= 0"),
])
def test_transition_planner_settings_that_mean_nothing_are_refused(flat, keywords, message):
    """steps 0 used to skip every transition (all events at sample 0)."""
    robot, scene, *_ = flat
    with pytest.raises(ValueError, match=message):
        TransitionPlanner(robot, scene, **keywords)


def test_spots_sharing_a_short_chain_with_a_held_spot_are_held_in_position_only(flat):
    robot = flat[0]
    chair = load_scene("chair_table", robot)
    planner = TransitionPlanner(robot, chair, None)
    thigh = Contact("right_thigh", "seat", 0.1, -0.1, 0.0)
    hand = Contact("left_hand", "table", 0.0, 0.3, 0.0)
    # knee and ankle (3 DoFs) between the right thigh and the right sole
    assert planner._position_only({"right_sole": None}, (thigh,)) == {"right_sole"}
    assert planner._position_only({"right_thigh": None},
                                  (Contact("right_sole", "floor", 0.2, -0.1, 0.0),)) \
        == {"right_thigh"}
    assert planner._position_only({"left_sole": None, "left_hand": None}, (thigh, hand)) \
        == set()


@pytest.fixture(scope="module")
def chair(flat):
    """(robot, scene, the shipped chair plan, planner at n = 20)."""
    robot = flat[0]
    plan = load_plan(str(CHAIR_PLAN))
    scene = load_scene(plan.scene, robot)
    return robot, scene, plan, TransitionPlanner(robot, scene, CollisionModel(robot, scene))


@pytest.fixture(scope="module")
def chair_transitions(chair):
    """(samples, statistics) of every transition of the shipped chair plan, in order."""
    robot, scene, plan, planner = chair
    return [planner.transition(index, first, second)
            for index, (first, second) in enumerate(zip(plan.stances[:-1], plan.stances[1:]))]


def test_every_transition_of_the_chair_plan_interpolates_some_off_the_exact_path(
        chair_transitions):
    """The planner never re-places a sole under a held thigh, paths rise over surface
    edges: every transition interpolates (no InterpolationError), some by a detour."""
    statistics = [entry for _, entry in chair_transitions]
    assert any(entry["detour_from"] is not None for entry in statistics)


def test_a_failing_sample_is_reached_through_halved_steps():
    """_Sampler.reach on a stand-in generator that succeeds only from a guess within 0.3
    of the sample's s (s coded on one joint): the jump 0 -> 1 fails, halving twice reaches
    0.25, then 0.5 from the extrapolated guess, then 1; without depth it fails."""
    from types import SimpleNamespace

    from stance.execution import interpolation

    model = pin.buildSampleModelManipulator()
    q0 = pin.neutral(model)

    def at(s):
        q = q0.copy()
        q[0] = s
        return q

    class Sampler(interpolation._Sampler):
        def sample(self, s, guess):
            self.asked.append(s)
            return SimpleNamespace(success=abs(guess[0] - s) <= 0.3 + 1e-12, q=at(s))

    def reach(depth):
        sampler = Sampler(SimpleNamespace(generator=SimpleNamespace(model=model)),
                          None, None, (), {}, set())
        sampler.asked = []
        return sampler, sampler.reach(0.0, at(0.0), 1.0, at(0.0), depth)

    sampler, result = reach(3)
    assert result.success and result.q[0] == 1.0
    assert sampler.asked == [1.0, 0.5, 0.25, 0.5, 1.0] and sampler.subdivided == 2
    sampler, result = reach(0)
    assert not result.success and sampler.asked == [1.0] and sampler.subdivided == 0


def test_samples_off_the_exact_path_keep_contacts_limits_and_clearance(chair,
                                                                       chair_transitions):
    robot, scene, plan, planner = chair
    rerouted = [index for index, (_, entry) in enumerate(chair_transitions)
                if entry["detour_from"] is not None or entry["subdivided"]]
    assert len(rerouted) >= 2
    for index in rerouted:
        assert_rerouted_samples_hold(robot, scene, plan, planner, index,
                                     chair_transitions[index][0])


def assert_rerouted_samples_hold(robot, scene, plan, planner, index, samples):
    first, second = plan.stances[index], plan.stances[index + 1]
    second_places = {(c.spot, c.surface, c.x, c.y, c.theta) for c in second.contacts}
    common = [c for c in first.contacts if (c.spot, c.surface, c.x, c.y, c.theta) in second_places]
    paths = planner.moving_paths(first, second)
    gripper = [robot.model.joints[robot.model.getJointId(name)].idx_q
               for name in scene.locked_joints]
    for k, q in enumerate(samples, start=1):
        for contact in common:
            position, orientation = spot_error(planner, scene, q, contact)
            assert position < 2 * SAMPLE_CONTACT_TOLERANCE and \
                orientation < 2 * SAMPLE_CONTACT_TOLERANCE, (index, k, contact.spot)
        joints = q[robot.limited_q_index]
        assert np.all(joints >= robot.lower - 1e-9) and np.all(joints <= robot.upper + 1e-9)
        np.testing.assert_array_equal(q[gripper], first.q[gripper])
        touching = list(common) + [
            Contact(spot, surface, 0.0, 0.0, 0.0) for spot, (path, before, after) in paths.items()
            for surface in [planner._touched_surface(path, before, after, k / planner.steps)]
            if surface is not None]
        ignored = planner.generator.collision.ignored_pairs_for_contacts(touching)
        assert planner.generator.collision.penetrations(q, ignored) == [], (index, k)
        position_only = planner._position_only(paths, common)
        for spot, (path, _, _) in paths.items():   # on its lines the spot stays near them
            s = k / planner.steps
            if path.phase(s) != "spline":
                target, actual = path.pose(s), spot_pose(planner.generator, q, spot)
                allowed = planner._tolerance(path, s, True, True) if spot in position_only \
                    else DETOUR_LINE_TOLERANCE
                # per axis, as the generator measures a contact's error
                assert np.max(np.abs(actual.translation - target.translation)) <= \
                    allowed + 1e-6, (index, k, spot)
