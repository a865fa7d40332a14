"""Best-first contact planner on the small flat_steps scene (and the shipped gap scene): a
verified plan, determinism, ordered son generation, and every failure reason (bad goal,
infeasible start, no path, budget, cancel) returned instead of raised or hung."""

import math
import time
from dataclasses import replace

import numpy as np
import pytest

from stance.planning import planner
from stance.planning.contacts import Contact
from stance.planning.planner import PlanRequest, plan_contacts
from stance.planning.scene import Goal, load_scene
from stance.planning.verify import verify_plan
from stance.robot import Robot
from stance_tools import cli


@pytest.fixture(scope="module")
def robot():
    return Robot.load("talos")


@pytest.fixture(scope="module")
def scene(robot):
    return load_scene("flat_steps", robot)


@pytest.fixture(scope="module")
def outcome(robot, scene):
    return plan_contacts(robot, PlanRequest(scene=scene, max_nodes=200, time_budget=120.0))


def test_flat_steps_plan_reaches_the_goal_and_passes_verification(robot, scene, outcome):
    assert outcome.success, outcome.message
    plan = outcome.plan
    assert len(plan.stances) >= 3
    first, last = plan.stances[0], plan.stances[-1]
    assert {c.spot for c in first.contacts} == {"left_sole", "right_sole"}
    assert last.q[0] > scene.goal.threshold   # base_link x past the goal line
    report = verify_plan(plan, scene, robot)
    assert report.ok, report.failures
    assert outcome.statistics["nodes_expanded"] <= 200


def test_same_request_gives_the_same_plan(robot, scene, outcome):
    """Same stances; values agree to rounding (the QP solver's SIMD paths depend on memory
    alignment, so the last bits may differ between runs)."""
    again = plan_contacts(robot, PlanRequest(scene=scene, max_nodes=200, time_budget=120.0))
    assert len(again.plan.stances) == len(outcome.plan.stances)
    for ours, theirs in zip(again.plan.stances, outcome.plan.stances):
        assert [(c.spot, c.surface, c.in_stability) for c in ours.contacts] == \
            [(c.spot, c.surface, c.in_stability) for c in theirs.contacts]
        np.testing.assert_allclose([(c.x, c.y, c.theta) for c in ours.contacts],
                                   [(c.x, c.y, c.theta) for c in theirs.contacts], atol=1e-9)
        np.testing.assert_allclose(ours.q, theirs.q, atol=1e-9)


def test_a_worker_pool_gives_the_same_plan(robot, scene, outcome):
    """Sons generated in parallel processes are taken in the sequential order."""
    pooled = plan_contacts(robot, PlanRequest(scene=scene, max_nodes=200, time_budget=120.0,
                                              workers=2))
    assert pooled.success
    assert [[(c.spot, c.surface, c.in_stability) for c in s.contacts]
            for s in pooled.plan.stances] == \
        [[(c.spot, c.surface, c.in_stability) for c in s.contacts]
         for s in outcome.plan.stances]
    for ours, theirs in zip(pooled.plan.stances, outcome.plan.stances):
        np.testing.assert_allclose(ours.q, theirs.q, atol=1e-7)


def test_a_worker_pool_gives_the_bitwise_same_plan_on_the_gap(robot):
    """On gap_wall, 2 workers gave other last bits from stance 2 on, and so another plan
    (coal's box support factor, kept from each process's first box query; every process
    now makes the same one: stance.planning.coal_order)."""
    scene = load_scene("gap_wall", robot)
    alone, pooled = (plan_contacts(robot, PlanRequest(scene=scene, max_nodes=200,
                                                      time_budget=120.0, workers=workers))
                     for workers in (1, 2))
    assert alone.success and pooled.success
    assert len(pooled.plan.stances) == len(alone.plan.stances)
    for ours, theirs in zip(pooled.plan.stances, alone.plan.stances):
        assert ours.contacts == theirs.contacts     # x, y, theta compared exactly
        np.testing.assert_array_equal(ours.q, theirs.q)


def test_every_expanded_stance_had_its_transition_interpolated(outcome):
    statistics = outcome.statistics
    assert statistics["transitions_checked"] >= statistics["nodes_expanded"] - 1
    assert statistics["transitions_rejected"] == 0


def test_a_stance_whose_transition_fails_is_not_expanded(robot, scene, monkeypatch):
    """The first transition that moves the left sole is refused: that stance is dropped
    (never part of the plan) and the search finds another way."""
    from stance.execution import interpolation
    original, refused = interpolation.TransitionPlanner.transition, []

    def transition(self, index, first, second):
        if not refused and "left_sole" in self.moving_paths(first, second):
            refused.append(second)
            raise interpolation.InterpolationError(index, 1, self.steps, "refused (test)")
        return original(self, index, first, second)

    monkeypatch.setattr(interpolation.TransitionPlanner, "transition", transition)
    result = plan_contacts(robot, PlanRequest(scene=scene, max_nodes=200, time_budget=120.0))
    assert result.success, result.message
    assert result.statistics["transitions_rejected"] == 1
    assert all(stance.contacts != refused[0].contacts or
               not np.array_equal(stance.q, refused[0].q) for stance in result.plan.stances)


def test_worker_processes_give_the_same_search_every_run(robot):
    """On the chair, where the search amplifies rounding, two runs with two worker
    processes expand the same nodes with the same posture generations: call i of a node
    goes to worker i mod workers, and each worker, a fresh process, gets the same calls in
    the same order whatever their timing."""
    def search():
        request = PlanRequest(scene=load_scene("chair_table", robot), max_nodes=120,
                              time_budget=300.0, workers=2)
        statistics = plan_contacts(robot, request).statistics
        return (statistics["posture_generations"],
                statistics["posture_calls"]["all"]["successes"],
                statistics["posture_calls"]["add"]["successes"])

    assert search() == search()


def test_ordered_sons_need_fewer_posture_generations_per_node(robot, scene, outcome):
    """Section 2.8: one leaf per (spot, surface) pair instead of every son at once."""
    unordered = plan_contacts(robot, PlanRequest(scene=scene, max_nodes=200, time_budget=120.0,
                                                 ordered_sons=False))
    assert unordered.success

    def per_node(statistics):
        return statistics["posture_generations"] / statistics["nodes_expanded"]

    assert per_node(unordered.statistics) > 1.2 * per_node(outcome.statistics)


def test_unknown_goal_frame_is_a_bad_goal(robot, scene):
    result = plan_contacts(robot, PlanRequest(scene=scene, goal=Goal("no_such_frame", "x", 1.0)))
    assert result.reason == planner.BAD_GOAL and "no_such_frame" in result.message


def test_feet_too_far_apart_is_an_infeasible_start(robot, scene):
    start = (Contact("left_sole", "floor", 1.9, 0.1, 0.0), Contact("right_sole", "floor", 0.0,
                                                                   -0.1, 0.0))
    result = plan_contacts(robot, PlanRequest(scene=scene, start=start))
    assert result.reason == planner.INFEASIBLE_START and "not reached" in result.message


@pytest.mark.parametrize("start, message", [
    ((Contact("left_sole", "floor", 5.0, 0.1, 0.0), Contact("right_sole", "floor", 5.0, -0.1,
                                                            0.0)),
     "start[0]: point (5, 0.1) is outside the polygon of 'floor'"),
    ((Contact("no_such_spot", "floor", 0.0, 0.1, 0.0),), "start[0].spot: unknown spot"),
    ((Contact("left_sole", "floor", math.nan, 0.1, 0.0),), "start[0].x: not finite"),
])
def test_a_start_contact_off_the_scene_is_an_infeasible_start(robot, scene, start, message):
    """Checked as the scene file's start is: off the floor it used to plan a stance in mid
    air; an unknown spot or a NaN raised deep in the posture generator."""
    result = plan_contacts(robot, PlanRequest(scene=scene, start=start))
    assert result.reason == planner.INFEASIBLE_START
    assert result.message.startswith(message), result.message


@pytest.mark.parametrize("keywords, message", [
    ({"max_nodes": 0}, "max_nodes must be an integer >= 1"),
    ({"max_nodes": math.nan}, "max_nodes must be an integer >= 1"),
    ({"time_budget": math.nan}, "time_budget must be > 0 s"),
    ({"time_budget": -1.0}, "time_budget must be > 0 s"),
    ({"slope": math.nan}, "slope must be finite and > 0"),
    ({"workers": 0}, "workers must be an integer >= 1"),
    ({"transition_steps": -1}, "transition_steps must be an integer >= 0"),
])
def test_a_request_whose_budgets_mean_nothing_is_refused(scene, keywords, message):
    """A NaN budget used to disable its limit (an unreachable goal searched on until the
    tree ran out); a NaN slope ended in a misleading no_path."""
    with pytest.raises(ValueError, match=message):
        PlanRequest(scene=scene, **keywords)


def test_stance_plan_reports_a_bad_budget(capsys):
    assert cli.main(["plan", "flat_steps", "--max-nodes", "0", "--quiet"]) == 2
    assert "stance plan: max_nodes must be an integer >= 1, got 0" in capsys.readouterr().err


@pytest.mark.parametrize("goal, message", [
    (Goal("base_link", "x", 5.0), "base_link x > 5 m, and no stance takes it past 3.10 m"),
    (Goal("base_link", "z", -3.0, -1), "base_link z < -3 m, and no stance takes it past "
                                       "-1.10 m"),
])
def test_a_goal_no_stance_can_reach_is_no_path_at_once(robot, scene, goal, message):
    """The floor ends at x = 2 m and a sole lies at most 1.10 m from base_link (its leg's
    offsets): the search used to run until its budget was spent (15 min by default)."""
    result = plan_contacts(robot, PlanRequest(scene=scene, goal=goal))
    assert result.reason == planner.NO_PATH
    assert result.message == f"goal out of reach: {message} (the scene's surfaces, then " \
                             "the longest chain from a spot to base_link)"
    assert result.statistics == {}      # no posture generated


def test_a_start_off_the_scene_is_named_before_a_goal_out_of_reach(robot, scene):
    start = (Contact("left_sole", "floor", 5.0, 0.1, 0.0),)
    result = plan_contacts(robot, PlanRequest(scene=scene, start=start,
                                              goal=Goal("base_link", "x", 5.0)))
    assert result.reason == planner.INFEASIBLE_START


def test_no_configuration_takes_two_frames_farther_apart_than_their_chain(robot):
    """_chain_length bounds the distance between two frames over random configurations."""
    import pinocchio as pin

    rng = np.random.default_rng(5)
    model, data = robot.model, robot.model.createData()
    pairs = [("left_sole_link", "base_link"), ("gripper_right_base_link", "left_sole_link"),
             ("head_2_link", "right_sole_link")]
    bounds = [planner._chain_length(model, *pair) for pair in pairs]
    farthest = np.zeros(len(pairs))
    for _ in range(2000):
        q = robot.initial_configuration()
        q[robot.limited_q_index] = rng.uniform(robot.lower, robot.upper)
        pin.framesForwardKinematics(model, data, q)
        for index, (first, second) in enumerate(pairs):
            distance = np.linalg.norm(data.oMf[model.getFrameId(first)].translation -
                                      data.oMf[model.getFrameId(second)].translation)
            farthest[index] = max(farthest[index], distance)
    assert np.all(farthest <= bounds)
    assert np.all(farthest > 0.9 * np.array(bounds))   # a tight bound, not a wild guess


def test_a_goal_off_the_floor_ends_with_the_budget(robot, scene):
    far = Goal("base_link", "x", 2.5)     # the floor ends at x = 2 m
    began = time.monotonic()
    result = plan_contacts(robot, PlanRequest(scene=scene, goal=far, max_nodes=25))
    assert result.reason in (planner.BUDGET_EXHAUSTED, planner.NO_PATH)
    assert result.statistics["nodes_expanded"] <= 25
    assert time.monotonic() - began < 60.0


def test_time_budget_ends_the_search(robot, scene):
    result = plan_contacts(robot, PlanRequest(scene=scene, goal=Goal("base_link", "x", 2.5),
                                              time_budget=0.5))
    assert result.reason == planner.BUDGET_EXHAUSTED
    assert result.statistics["planning_time"] < 5.0


def test_cancel_is_seen_between_posture_generations(robot, scene):
    calls = []

    def should_stop():
        calls.append(time.monotonic())
        return len(calls) > 5

    result = plan_contacts(robot, PlanRequest(scene=scene), should_stop=should_stop)
    assert result.reason == planner.CANCELLED
    assert len(calls) == 6   # stopped at the first poll that said so


def test_progress_reports_grow(robot, scene):
    reports = []
    plan_contacts(robot, PlanRequest(scene=replace(scene), max_nodes=6), progress=reports.append)
    expanded = [r.nodes_expanded for r in reports]
    assert expanded == sorted(expanded) and expanded[-1] >= 5
    assert all(r.elapsed >= 0 for r in reports)


def test_plan_check_and_plot_from_the_command_line(tmp_path):
    """The CLI path users take: stance plan -> check-plan (independent) -> plot-plan."""
    import subprocess

    plan_file, sheet = tmp_path / "plan.json", tmp_path / "sheet.png"
    planned = subprocess.run(["stance", "plan", "flat_steps", "-o", str(plan_file), "--quiet"],
                             capture_output=True, text=True, timeout=300)
    assert planned.returncode == 0, planned.stderr
    assert "success" in planned.stdout
    checked = subprocess.run(["stance", "check-plan", str(plan_file)], capture_output=True,
                             text=True, timeout=300)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert "plan OK" in checked.stdout
    plotted = subprocess.run(["stance", "plot-plan", str(plan_file), "-o", str(sheet)],
                             capture_output=True, text=True, timeout=300)
    assert plotted.returncode == 0, plotted.stderr
    assert sheet.stat().st_size > 10_000


@pytest.fixture(scope="module")
def chair_search(robot):
    """A search on the chair scene (no collision model: only the spots' kinematics)."""
    from stance.planning.posture import PostureGenerator
    chair = load_scene("chair_table", robot)
    request = PlanRequest(scene=chair)
    return planner._Search(robot, request, PostureGenerator(robot, chair), None, None, None)


def test_chain_dofs_count_the_joints_between_spots_on_one_branch(chair_search):
    chain_dofs = chair_search.generator.chain_dofs
    assert chain_dofs("left_sole", "left_thigh") == chain_dofs("left_thigh", "left_sole") == 3
    assert chain_dofs("left_hand", "left_forearm") == 2
    assert chain_dofs("left_sole", "right_sole") == float("inf")
    assert chain_dofs("left_hand", "left_sole") == float("inf")


def seated(scene, *geometric):
    """The chair scene's start contacts, the named spots kept geometric only."""
    return tuple(Contact(c.spot, c.surface, c.x, c.y, c.theta, c.spot not in geometric)
                 for c in scene.start)


def test_a_sole_is_not_placed_while_its_thigh_holds(chair_search):
    """Re-placing a sole under a thigh held on the seat has no executable transition (the
    sole reaches two places only, the way between them runs through the floor)."""
    search, chair = chair_search, chair_search.scene
    start = chair.start_configuration
    lifted_sole = planner._Node(seated(chair, "left_sole"), start, 0.0, None)
    assert not search._placeable("left_sole", lifted_sole)
    assert search._placeable("left_hand", lifted_sole)
    lifted_thigh = planner._Node(seated(chair, "left_sole", "left_thigh"), start, 0.0, None)
    assert search._placeable("left_sole", lifted_thigh)
    assert not search._placeable("right_sole", lifted_thigh)
    assert not search._placeable("right_thigh", lifted_thigh)


def test_gap_wall_is_crossed_with_a_hand_on_the_wall(robot):
    """The shipped gap scene: both soles end on the far slab, the left hand holds the wall
    on the way, and the plan passes the independent verification."""
    gap = load_scene("gap_wall", robot)
    result = plan_contacts(robot, PlanRequest(scene=gap, max_nodes=400, time_budget=300.0))
    assert result.success, result.message
    stances = result.plan.stances
    assert any(contact.spot == "left_hand" for stance in stances for contact in stance.contacts)
    assert any({(c.spot, c.surface) for c in stance.contacts}
               >= {("left_sole", "far_slab"), ("right_sole", "far_slab")} for stance in stances)
    report = verify_plan(result.plan, gap, robot)
    assert report.ok, report.failures
