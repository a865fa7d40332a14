"""10^5 random IK steps with swing and ball-and-socket limits (issue 3, reliability): the
mannequin's eleven spherical joints and Talos' four joint groups, clamping and progressive
clamping, random starts and reachable or unreachable targets. No swing ends a step more
than 0.5 degrees outside its cone or polygon, no twist beyond its interval by more than
1e-9 rad, no grouped joint beyond its own bounds by more than 1e-9 rad; a swing or joint
group started outside never moves further out, and a group is back within them by the end
of its episode; a star-shaped (non-convex) shoulder polygon is met and holds too; the same
episode gives the same bits twice, on either hierarchy. Progressive clamping runs the same soaks on
the QP hierarchy too."""

import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from helpers.limit_runs import (bound_excess, mannequin_run, mannequin_start,
                                set_swing_twist, swing_excess, talos_group_run,
                                twist_excess)

from stance.models import MANNEQUIN_LIMIT_FILE, build_mannequin
from stance.robot import Robot
from stance.swing import (load_limit_file, parse_limits, rotation_from_swing_twist,
                          swing_twist)

MANNEQUIN_STEPS = 30_000   # per strategy and hierarchy
TALOS_STEPS = 20_000       # per strategy and hierarchy: 10^5 steps in all on the SVD one
STAR_STEPS = 20_000        # per strategy and hierarchy, a star-shaped shoulder polygon
EPISODE_STEPS = 100
SWING_TOLERANCE = math.radians(0.5)
TOLERANCE = 1e-9


def excesses(models, q) -> np.ndarray:
    return np.array([[swing_excess(model, q), twist_excess(model, q)] for model in models])


def push_outside(robot, models, q, rng) -> None:
    """One to three swings 0.05-0.3 rad out of their domain (in place)."""
    for index in rng.choice(len(models), rng.integers(1, 4), replace=False):
        model = models[index]
        s, theta = swing_twist(model.rotation(q))
        boundary = model.domain.closest_boundary_point(s)
        s = boundary + rng.uniform(0.05, 0.3) * model.domain.normal_at(boundary)
        set_swing_twist(robot, q, model.joint, s, theta)


@pytest.mark.parametrize("strategy, hierarchy", [
    ("clamping", "svd"), ("progressive", "svd"), ("progressive", "qp")])
def test_mannequin_swings_hold_over_random_steps(strategy, hierarchy):
    robot = build_mannequin()
    models = load_limit_file(MANNEQUIN_LIMIT_FILE, robot)
    for seed in range(MANNEQUIN_STEPS // EPISODE_STEPS):
        rng = np.random.default_rng(seed)
        start = mannequin_start(robot, models, rng)
        if rng.random() < 0.3:
            push_outside(robot, models, start, rng)
        excess = excesses(models, start)
        allowed = np.maximum(excess, [SWING_TOLERANCE, TOLERANCE])
        for q, _ in mannequin_run(robot, models, start, seed, rng.random() < 0.5, strategy,
                                  EPISODE_STEPS, hierarchy=hierarchy):
            following = excesses(models, q)
            assert np.all(following <= allowed + TOLERANCE), \
                f"seed {seed}: {models[int(np.argmax(following.max(axis=1)))].joint}"
            allowed = np.maximum(np.minimum(allowed, following),
                                 [SWING_TOLERANCE, TOLERANCE])


def star_shoulder_models(robot) -> list:
    """The mannequin's limits with the right shoulder's 8-gon made star-shaped (every
    other vertex halfway to the rest direction z: reflex vertices)."""
    document = yaml.safe_load(Path(MANNEQUIN_LIMIT_FILE).read_text())
    octagon = np.array(document["joints"]["right_shoulder"]["polygon"])
    octagon /= np.linalg.norm(octagon, axis=1)[:, None]
    for vertex in range(1, len(octagon), 2):
        angle = math.acos(octagon[vertex, 2])
        azimuth = math.atan2(octagon[vertex, 1], octagon[vertex, 0])
        octagon[vertex] = [math.sin(angle / 2) * math.cos(azimuth),
                           math.sin(angle / 2) * math.sin(azimuth), math.cos(angle / 2)]
    document["joints"]["right_shoulder"]["polygon"] = octagon.tolist()
    return parse_limits(document, robot)


@pytest.mark.parametrize("strategy, hierarchy", [
    ("clamping", "svd"), ("progressive", "svd"), ("progressive", "qp")])
def test_a_star_shaped_shoulder_holds_over_random_steps(strategy, hierarchy):
    """The right hand's random targets drive the right shoulder onto a non-convex limit:
    it is met (the swing on it on a tenth of the steps or more) and never left."""
    robot = build_mannequin()
    models = star_shoulder_models(robot)
    shoulder = next(model for model in models if model.joint == "right_shoulder")
    assert not np.all(shoulder.domain.vertices @ shoulder.domain.inward_normals.T >= 0.0)
    on_limit = 0
    for seed in range(STAR_STEPS // EPISODE_STEPS):
        rng = np.random.default_rng(seed)
        start = mannequin_start(robot, models, rng)
        for q, _ in mannequin_run(robot, models, start, seed, rng.random() < 0.5,
                                  strategy, EPISODE_STEPS, hierarchy=hierarchy):
            assert swing_excess(shoulder, q) <= SWING_TOLERANCE, seed
            assert twist_excess(shoulder, q) <= TOLERANCE, seed
            on_limit += abs(shoulder.domain.signed_distance(
                swing_twist(shoulder.rotation(q))[0])) < 1e-9
    assert on_limit >= STAR_STEPS // 10, on_limit


def push_groups_outside(groups, q, rng) -> list:
    """One or two joint groups turned 0.05-0.3 rad out of their swing domain (in place,
    their joints' angles by the group's own Gauss-Newton); returns the groups pushed out
    (a shoulder, whose axes do not meet, may not reach the rotation asked)."""
    pushed = []
    for index in rng.choice(len(groups), rng.integers(1, 3), replace=False):
        group = groups[index]
        s, theta = swing_twist(group.rotation(q))
        boundary = group.domain.closest_boundary_point(s)
        s = boundary + rng.uniform(0.05, 0.3) * group.domain.normal_at(boundary)
        q[group.q_index] = group.angles_for(rotation_from_swing_twist(s, theta),
                                            q[group.q_index])
        if swing_excess(group, q) > 0.0:
            pushed.append(group)
    return pushed


def group_excesses(groups, q) -> np.ndarray:
    return np.array([[swing_excess(group, q), twist_excess(group, q),
                      bound_excess(group, q)] for group in groups])


@pytest.mark.parametrize("strategy, hierarchy", [
    ("clamping", "svd"), ("progressive", "svd"), ("progressive", "qp")])
def test_talos_groups_hold_over_random_steps(strategy, hierarchy):
    """Within the tolerances from inside; a group started outside (one episode in four)
    never moves further out, and moves back within them."""
    robot = Robot.load("talos")
    groups = load_limit_file("talos", robot)
    outside = 0
    tolerances = [SWING_TOLERANCE, TOLERANCE, TOLERANCE]
    for seed in range(TALOS_STEPS // EPISODE_STEPS):
        rng = np.random.default_rng(seed)
        start = robot.initial_configuration()
        if seed % 4 == 1:
            outside += bool(push_groups_outside(groups, start, rng))
        allowed = np.maximum(group_excesses(groups, start), tolerances)
        for q, _ in talos_group_run(robot, groups, seed, seed % 3 != 0, strategy,
                                    EPISODE_STEPS, start, hierarchy):
            following = group_excesses(groups, q)
            assert np.all(following <= allowed + TOLERANCE), \
                (seed, groups[int(np.argmax((following - allowed).max(axis=1)))].name)
            allowed = np.maximum(np.minimum(allowed, following), tolerances)
        assert np.all(following <= np.array(tolerances) + TOLERANCE), seed
    assert outside >= TALOS_STEPS // EPISODE_STEPS // 8


@pytest.mark.parametrize("hierarchy", ["svd", "qp"])
def test_swing_and_group_steps_are_bitwise_deterministic(hierarchy):
    """The same episode twice from fresh solvers gives the same bits at every step: the
    mannequin's spherical joints and Talos' joint groups, started outside their limits."""
    mannequin, talos = build_mannequin(), Robot.load("talos")
    balls, groups = load_limit_file(MANNEQUIN_LIMIT_FILE, mannequin), \
        load_limit_file("talos", talos)
    for seed in (3, 17, 42):
        rng = np.random.default_rng(seed)
        mannequin_q = mannequin_start(mannequin, balls, rng)
        push_outside(mannequin, balls, mannequin_q, rng)
        talos_q = talos.initial_configuration()
        assert push_groups_outside(groups, talos_q, rng)
        for run in (lambda: mannequin_run(mannequin, balls, mannequin_q.copy(), seed,
                                          seed % 2 == 0, "progressive", 40,
                                          hierarchy=hierarchy),
                    lambda: talos_group_run(talos, groups, seed, seed % 2 == 0,
                                            "progressive", 40, talos_q.copy(), hierarchy)):
            first, second = (np.array([q for q, _ in run()]) for _ in range(2))
            assert first.tobytes() == second.tobytes(), seed
