"""Collision model: SRDF pairs, signed distances, gradients against finite differences
through pin.integrate, ignored contact pairs and the near-pair refresh policy (Talos)."""

import glob
import os
import subprocess
import sys

import numpy as np
import pinocchio as pin
import pytest
from threadpoolctl import threadpool_limits

from stance.planning.collision import CollisionModel, example_robot_data_files
from stance.planning.contacts import Contact
from stance.planning.scene import ContactSpot, Goal, Obstacle, Scene, Surface
from stance.robot import Robot

STEP = 1e-6    # rad or m: central finite-difference step


def box(name, centre, size):
    return Obstacle(name, "box", pin.SE3(np.eye(3), np.array(centre, float)),
                    np.array(size, float))


@pytest.fixture(scope="module")
def robot():
    return Robot.load("talos")


@pytest.fixture(scope="module")
def scene(robot):
    """A floor box whose top is z = 0, a block beside the right hand, a free-floating
    surface; spots on both soles."""
    q0 = robot.reference_configurations["half_sitting"]
    square = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    surfaces = {
        "ground": Surface("ground", pin.SE3.Identity(), square, 0.8, obstacle="floor"),
        "floating": Surface("floating", pin.SE3(np.eye(3), np.array([2.0, 0, 1.0])),
                            square, 0.8),
    }
    obstacles = {"floor": box("floor", [0, 0, -0.5], [4, 4, 1]),
                 "block": box("block", [0.3, -0.45, 0.85], [0.2, 0.2, 0.3])}
    patch = np.array([[-0.1, -0.05], [0.1, -0.05], [0.1, 0.05], [-0.1, 0.05]])
    spots = {"left_foot": ContactSpot("left_foot", "left_sole_link", pin.SE3.Identity(), patch),
             "right_foot": ContactSpot("right_foot", "right_sole_link", pin.SE3.Identity(),
                                       patch)}
    return Scene("test", "talos", surfaces, obstacles, spots, [], q0, np.array([q0, q0]),
                 Goal("base_link", "x", 1.0))


@pytest.fixture(scope="module")
def collision(robot, scene):
    return CollisionModel(robot, scene)


def lowered(robot, depth):
    q = robot.reference_configurations["half_sitting"].copy()
    q[2] -= depth
    return q


def all_distances(collision, q):
    """Distances (m) of all pairs by Pinocchio's own pass over every pair (with the
    model's GJK and EPA tolerances)."""
    model = collision.robot.model
    geometry_data = collision.geometry_model.createData()
    for request, used in zip(geometry_data.distanceRequests,
                             collision.geometry_data.distanceRequests):
        request.gjk_tolerance, request.epa_tolerance = used.gjk_tolerance, used.epa_tolerance
    pin.computeDistances(model, model.createData(), collision.geometry_model, geometry_data, q)
    return np.array([result.min_distance for result in geometry_data.distanceResults])


def test_srdf_disables_self_pairs(collision):
    joints = collision.geometry_joints[collision.geometry_joints > 0]  # one per robot geometry
    all_pairs = sum(int(np.sum(joints[i + 1:] != joints[i])) for i in range(len(joints)))
    assert collision.self_pairs == 887 < all_pairs
    assert len(collision.pairs) - collision.self_pairs == 2 * len(joints)  # 2 obstacles


def test_gradients_match_central_differences(robot, collision):
    """Rows of several random near-contact configurations against central differences of
    the same pair's distance through pin.integrate; pairs where the one-sided differences
    disagree (non-smooth distance: parallel faces, feature switches) are skipped."""
    model = robot.model
    rng = np.random.default_rng(7)
    checked = 0
    with threadpool_limits(1):
        for _ in range(3):
            step = np.r_[np.zeros(6), rng.normal(scale=0.15, size=model.nv - 6)]
            q = pin.integrate(model, lowered(robot, -0.02), step)
            distances, gradients, labels = collision.constraint_rows(q, near=0.05)
            assert gradients.shape == (len(labels), model.nv)
            plus, minus = np.zeros_like(gradients), np.zeros_like(gradients)
            for i in range(model.nv):
                tangent = np.zeros(model.nv)
                tangent[i] = STEP
                for sign, table in ((1, plus), (-1, minus)):
                    d, _, names = collision.constraint_rows(
                        pin.integrate(model, q, sign * tangent), near=0.5)
                    found = dict(zip(names, d))
                    table[:, i] = [found[label] for label in labels]
            central = (plus - minus) / (2 * STEP)
            kink = np.abs((plus - distances[:, None]) - (distances[:, None] - minus)).max(axis=1)
            smooth = kink < 1e-9
            error = np.abs(central - gradients).max(axis=1)
            scale = np.maximum(1.0, np.abs(central).max(axis=1))
            assert np.all(error[smooth] < 1e-5 * scale[smooth]), (
                [(labels[k], error[k]) for k in np.flatnonzero(smooth & (error > 1e-5))])
            checked += int(np.sum(smooth & (np.abs(central).max(axis=1) > 1e-2)))
    assert checked >= 10


def test_penetration_into_the_floor(robot, collision):
    """Lowering half_sitting by 5 cm sinks both feet 5 cm deeper into the floor box."""
    pair = "leg_left_6_link_0|floor"
    before = dict(collision.penetrations(lowered(robot, 0.0), tolerance=-1.0))  # all < 1 m
    report = dict(collision.penetrations(lowered(robot, 0.05)))
    assert report[pair] < -0.04
    assert report[pair] == pytest.approx(before[pair] - 0.05, abs=1e-6)
    assert "leg_right_6_link_0|floor" in report
    distance, label = collision.min_distance(lowered(robot, 0.05))
    assert distance == pytest.approx(min(report.values()), abs=1e-9)
    assert label in report
    distances, _, labels = collision.constraint_rows(lowered(robot, 0.05), near=0.02)
    assert dict(zip(labels, distances))[pair] == pytest.approx(report[pair], abs=1e-9)
    raised = collision.penetrations(lowered(robot, -0.10))
    assert all(not label.endswith("|floor") for label, _ in raised)


@pytest.mark.parametrize("depth", [0.0, 0.05, 0.3])
def test_reports_match_a_brute_force_pass(robot, collision, depth):
    """min_distance and penetrations agree with all pairs' distances, also when bounding
    sphere centres are deep inside an obstacle (depth m below half_sitting)."""
    rng = np.random.default_rng(11)
    model = robot.model
    for _ in range(3):
        q = pin.integrate(model, lowered(robot, depth),
                          np.r_[np.zeros(6), rng.normal(scale=0.2, size=model.nv - 6)])
        brute = all_distances(collision, q)
        distance, label = collision.min_distance(q)
        assert distance == pytest.approx(brute.min(), abs=1e-6)
        assert brute[collision.labels.index(label)] == pytest.approx(brute.min(), abs=1e-6)
        reported = dict(collision.penetrations(q, tolerance=0.001))
        assert set(reported) == {collision.labels[k] for k in np.flatnonzero(brute < -0.001)}


def test_contact_pairs_are_ignored(robot, collision):
    left = Contact("left_foot", "ground", 0.0, 0.1, 0.0)
    ignored = collision.ignored_pairs_for_contacts([left])
    labels = {collision.labels[k] for k in ignored}
    assert labels and all(label.startswith("leg_left_6_") and label.endswith("|floor")
                          for label in labels)
    assert collision.ignored_pairs_for_contacts(
        [Contact("left_foot", "floating", 0.0, 0.0, 0.0)]) == frozenset()
    q = lowered(robot, 0.05)
    _, _, rows = collision.constraint_rows(q, near=0.05, ignored=ignored)
    assert not labels & set(rows) and "leg_right_6_link_0|floor" in rows
    reported = {label for label, _ in collision.penetrations(q, ignored=ignored)}
    assert not labels & reported and "leg_right_6_link_0|floor" in reported
    both = ignored | collision.ignored_pairs_for_contacts(
        [Contact("right_foot", "ground", 0.0, -0.1, 0.0)])
    assert "floor" not in collision.min_distance(q, ignored=both)[1]


@pytest.mark.parametrize("margin", [0.0, 0.02, 0.3])
def test_near_pairs_match_a_brute_force_pass(robot, scene, margin):
    """Along a random walk of the joints and the base (small steps, then large ones), with
    a contact's pairs ignored at every other call, the rows are exactly the non-ignored
    pairs a distance pass over all pairs finds closer than `near`, whatever the margin
    (the look-ahead of the bounds kept between calls)."""
    collision = CollisionModel(robot, scene, margin=margin)
    model, near = robot.model, 0.06
    ignored = collision.ignored_pairs_for_contacts([Contact("left_foot", "ground", 0, 0, 0)])
    rng = np.random.default_rng(3)
    q = lowered(robot, 0.02)
    for call, scale in enumerate([0.01] * 30 + [0.1] * 3):
        q = pin.integrate(model, q, np.r_[rng.normal(scale=0.3 * scale, size=6),
                                          rng.normal(scale=scale, size=model.nv - 6)])
        skipped = ignored if call % 2 else frozenset()
        distances, _, labels = collision.constraint_rows(q, near=near, ignored=skipped)
        brute = all_distances(collision, q)
        expected = {collision.labels[k] for k in np.flatnonzero(brute < near)
                    if k not in skipped}
        assert set(labels) == expected
        assert np.allclose(distances, [brute[collision.labels.index(label)] for label in labels],
                           atol=1e-6)


def test_forget_makes_the_rows_independent_of_earlier_calls(robot, scene):
    """After forget(), constraint rows at q are bitwise those of a fresh model at q,
    whatever the model computed before; without it, the GJK warm starts and bounds left by
    the walk change them to rounding (so a posture would depend on its generator's
    history)."""
    model, near = robot.model, 0.08
    rng = np.random.default_rng(5)
    walk = [lowered(robot, 0.02)]
    for _ in range(20):
        walk.append(pin.integrate(model, walk[-1], rng.normal(scale=0.02, size=model.nv)))
    fresh = CollisionModel(robot, scene).constraint_rows(walk[-1], near=near)
    walked = CollisionModel(robot, scene)
    for q in walk[:-1]:
        walked.constraint_rows(q, near=near)
    remembered = walked.constraint_rows(walk[-1], near=near)
    assert remembered[2] == fresh[2]
    assert not (np.array_equal(remembered[0], fresh[0])
                and np.array_equal(remembered[1], fresh[1]))
    for q in walk[:-1]:
        walked.constraint_rows(q, near=near)
    walked.forget()
    forgotten = walked.constraint_rows(walk[-1], near=near)
    assert forgotten[2] == fresh[2]
    np.testing.assert_array_equal(forgotten[0], fresh[0])
    np.testing.assert_array_equal(forgotten[1], fresh[1])


def test_mesh_obstacle_is_a_convex_hull(robot, scene):
    packages, _ = example_robot_data_files("talos")
    meshes = sorted(glob.glob(os.path.join(packages[0], "**", "*.STL"), recursive=True))
    assert meshes
    obstacle = Obstacle("rock", "mesh", pin.SE3(np.eye(3), np.array([0.6, 0.0, 0.3])),
                        mesh=meshes[0], scale=np.full(3, 2.0))
    with_mesh = Scene(scene.name, "talos", scene.surfaces, {"rock": obstacle}, scene.spots,
                      [], scene.start_configuration, scene.key_postures, scene.goal)
    collision = CollisionModel(robot, with_mesh, self_collision=False)
    assert collision.self_pairs == 0 and len(collision.pairs) == 52
    distance, label = collision.min_distance(robot.reference_configurations["half_sitting"])
    assert np.isfinite(distance) and label.endswith("|rock")


# A process's box distances, after its first box query: a convex hull against a box, 300
# poses; the SHA-256 of the distances, normals and nearest points.
BOX_DISTANCES = """
import hashlib
import coal, numpy as np, pinocchio as pin
{first}
rng = np.random.default_rng(0)
points = rng.normal(size=(200, 3))
vertices = coal.StdVec_Vec3s()
for point in points / np.linalg.norm(points, axis=1)[:, None] * [0.1, 0.05, 0.2]:
    vertices.append(point)
hull, box = coal.Convex.convexHull(vertices, False, "Qt"), coal.Box(2, 2, 0.1)
digest = hashlib.sha256()
for _ in range(300):
    request, result = coal.DistanceRequest(), coal.DistanceResult()
    placement = coal.Transform3s(pin.rpy.rpyToMatrix(*rng.uniform(-np.pi, np.pi, 3)),
                                 rng.uniform(-0.1, 0.1, 3) + [0.0, 0.0, 0.3])
    coal.distance(hull, placement, box, coal.Transform3s(), request, result)
    digest.update(np.array([result.min_distance, *result.normal,
                            *result.getNearestPoint1()]).tobytes())
print(digest.hexdigest())
"""
AXIS_ALIGNED_BOX_QUERY = """
coal.distance(coal.Box(1, 1, 1), coal.Transform3s(), coal.Box(1, 1, 1),
              coal.Transform3s(np.eye(3), np.array([0.3, 0.2, 0.1])),
              coal.DistanceRequest(), coal.DistanceResult())
"""


def box_distances(first: str) -> str:
    """BOX_DISTANCES' digest, computed in a fresh Python process after `first`."""
    return subprocess.run([sys.executable, "-c", BOX_DISTANCES.format(first=first)],
                          capture_output=True, text=True, check=True).stdout


def test_box_distances_do_not_depend_on_the_process_first_box_query():
    """coal's box support function keeps a factor from the process's first box query
    (coal issue #894): a hull's distances to a box came out with other last bits when they
    were the process's first box queries than after a query between axis-aligned boxes.
    Importing stance.planning makes the first box query, so both processes compute the same
    bits."""
    plain = box_distances("import stance.planning")
    assert box_distances("import stance.planning\n" + AXIS_ALIGNED_BOX_QUERY) == plain
