"""Static equilibrium (stance.planning.equilibrium), cross-checked against the verifier's
own formulation (stance.planning.verify.wrench_feasible)."""

import math

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation
from stance.planning.contacts import Contact
from stance.planning.equilibrium import (
    are_coplanar,
    contact_vertices,
    contacts_equilibrium,
    friction_cone_generators,
    static_equilibrium,
    support_polygon,
)
from stance.planning.scene import ContactSpot, Goal, Scene, Surface
from stance.planning.verify import wrench_feasible

MASS = 50.0
WEIGHT = MASS * 9.81
SOLE = np.array([[0.1, 0.05], [-0.1, 0.05], [-0.1, -0.05], [0.1, -0.05]])   # m
PALM = np.array([[0.04, 0.04], [-0.04, 0.04], [-0.04, -0.04], [0.04, -0.04]])
SQUARE = np.array([[-2.0, -2.0], [2.0, -2.0], [2.0, 2.0], [-2.0, 2.0]])


def surface(name, rotation, origin, friction=0.7):
    return Surface(name, pin.SE3(np.asarray(rotation, dtype=float), np.asarray(origin, float)),
                   SQUARE, friction)


def wall_rotation(normal_x):
    """A wall facing +x (normal_x = 1) or -x (-1), its frame's x axis pointing up."""
    normal = np.array([normal_x, 0.0, 0.0])
    up = np.array([0.0, 0.0, 1.0])
    return np.column_stack([up, np.cross(normal, up), normal])


def make_scene(surfaces):
    spots = {"foot": ContactSpot("foot", "f", pin.SE3.Identity(), SOLE),
             "foot2": ContactSpot("foot2", "f2", pin.SE3.Identity(), SOLE),
             "left_hand": ContactSpot("left_hand", "l", pin.SE3.Identity(), PALM),
             "right_hand": ContactSpot("right_hand", "r", pin.SE3.Identity(), PALM)}
    return Scene("test", "none", {s.name: s for s in surfaces}, {}, spots, [], np.zeros(0),
                 np.zeros((2, 0)), Goal("f", "x", 1.0))


FLOOR = surface("floor", np.eye(3), [0.0, 0.0, 0.0])


def test_contact_vertices_lie_on_the_surface_around_the_contact_point():
    scene = make_scene([surface("step", np.eye(3), [1.0, 0.0, 0.2])])
    points, normal, friction = contact_vertices(
        Contact("foot", "step", 0.3, -0.1, math.pi / 2), scene)
    np.testing.assert_allclose(points[:, 2], 0.2)
    np.testing.assert_allclose(points.mean(axis=0), [1.3, -0.1, 0.2], atol=1e-12)
    # theta = 90 deg turns the sole's long side (x, 0.2 m) along the world y axis.
    np.testing.assert_allclose(np.ptp(points[:, :2], axis=0), [0.1, 0.2], atol=1e-12)
    np.testing.assert_allclose(normal, [0.0, 0.0, 1.0])
    assert friction == 0.7


def test_one_flat_foot_holds_the_com_above_it_only():
    scene = make_scene([FLOOR])
    foot = (Contact("foot", "floor", 0.0, 0.0, 0.0),)
    inside = contacts_equilibrium(foot, scene, np.array([0.05, 0.02, 0.9]), MASS)
    assert inside.feasible and inside.margin > 0.0
    np.testing.assert_allclose(inside.forces.sum(axis=0), [0.0, 0.0, WEIGHT], atol=1e-6)
    points, _, _ = contact_vertices(foot[0], scene)
    moment = np.cross(points - [0.05, 0.02, 0.9], inside.forces).sum(axis=0)
    np.testing.assert_allclose(moment, 0.0, atol=1e-6)
    outside = contacts_equilibrium(foot, scene, np.array([0.15, 0.0, 0.9]), MASS)
    assert not outside.feasible and outside.margin < 0.0


def test_pinching_between_two_walls_needs_friction():
    walls = [surface("east", wall_rotation(-1.0), [0.3, 0.0, 1.0]),
             surface("west", wall_rotation(1.0), [-0.3, 0.0, 1.0])]
    slippery = [surface("east", wall_rotation(-1.0), [0.3, 0.0, 1.0], friction=0.0),
                surface("west", wall_rotation(1.0), [-0.3, 0.0, 1.0], friction=0.0)]
    hands = (Contact("left_hand", "west", 0.0, 0.0, 0.0),
             Contact("right_hand", "east", 0.0, 0.0, 0.0))
    com = np.array([0.0, 0.0, 1.0])
    assert not are_coplanar(hands, make_scene(walls))
    assert contacts_equilibrium(hands, make_scene(walls), com, MASS).feasible
    assert not contacts_equilibrium(hands, make_scene(slippery), com, MASS).feasible
    assert not contacts_equilibrium(hands[:1], make_scene(walls), com, MASS).feasible


def test_coplanarity():
    scene = make_scene([FLOOR, surface("step", np.eye(3), [1.0, 0.0, 0.1]),
                        surface("almost", np.eye(3), [1.0, 0.0, 0.003]),
                        surface("wall", wall_rotation(-1.0), [0.3, 0.0, 1.0]),
                        surface("tilted", Rotation.from_euler("x", 5, degrees=True).as_matrix(),
                                [1.0, 0.0, 0.0])])
    floor = Contact("foot", "floor", 0.0, 0.1, 0.0)
    assert are_coplanar([], scene) and are_coplanar([floor], scene)
    assert are_coplanar([floor, Contact("foot2", "floor", 0.5, -0.1, 1.0)], scene)
    assert are_coplanar([floor, Contact("foot2", "almost", 0.0, 0.0, 0.0)], scene)
    assert not are_coplanar([floor, Contact("foot2", "step", 0.0, 0.0, 0.0)], scene)
    assert not are_coplanar([floor, Contact("foot2", "wall", 0.0, 0.0, 0.0)], scene)
    assert not are_coplanar([floor, Contact("foot2", "tilted", 0.0, 0.0, 0.0)], scene)


def test_support_polygon_of_two_feet():
    scene = make_scene([FLOOR, surface("wall", wall_rotation(-1.0), [0.3, 0.0, 1.0])])
    feet = [Contact("foot", "floor", 0.0, 0.1, 0.0), Contact("foot2", "floor", 0.0, -0.1, 0.0)]
    vertices, a, b = support_polygon(feet, scene)
    np.testing.assert_allclose(np.sort(np.abs(vertices), axis=0), [[0.1, 0.15]] * len(vertices))
    following = np.roll(vertices, -1, axis=0)
    signed_area = 0.5 * np.sum(vertices[:, 0] * following[:, 1] - following[:, 0] * vertices[:, 1])
    assert signed_area == pytest.approx(0.2 * 0.3)   # positive: counter-clockwise
    assert np.all(a @ [0.0, 0.0] < b) and np.any(a @ [0.0, 0.2] > b)
    assert np.all(a @ vertices.T <= b[:, None] + 1e-12)
    with pytest.raises(ValueError):
        support_polygon([feet[0], Contact("left_hand", "wall", 0.0, 0.0, 0.0)], scene)


def test_friction_cone_generators_lie_on_the_cone():
    normal = np.array([0.0, 0.6, 0.8])
    tangent = np.array([1.0, 0.0, 0.0])
    generators = friction_cone_generators(normal, 0.5, edges=6, tangent=tangent)
    assert generators.shape == (6, 3)
    np.testing.assert_allclose(np.linalg.norm(generators, axis=1), 1.0)
    np.testing.assert_allclose(np.arccos(generators @ normal), math.atan(0.5))
    assert np.argmax(generators @ tangent) == 0
    default = friction_cone_generators(normal, 0.5)
    np.testing.assert_allclose(np.arccos(default @ normal), math.atan(0.5))


def random_case(rng):
    """Random contacts (1 to 3 square patches), frictions and CoM: mostly upward normals."""
    points, frames, frictions = [], [], []
    for _ in range(rng.integers(1, 4)):
        tilt = Rotation.from_rotvec(rng.normal(scale=0.4, size=3)).as_matrix()
        frame = tilt @ Rotation.from_euler("z", rng.uniform(0.0, 2 * math.pi)).as_matrix()
        half = rng.uniform(0.02, 0.1)
        corners = np.array([[half, half], [-half, half], [-half, -half], [half, -half]])
        centre = rng.uniform([-0.2, -0.2, 0.0], [0.2, 0.2, 0.6])
        points.append(corners @ frame[:, :2].T + centre)
        frames += [frame] * 4
        frictions += [rng.uniform(0.2, 1.0)] * 4
    com = rng.uniform([-0.15, -0.15, 0.5], [0.15, 0.15, 1.2])
    return np.vstack(points), np.array(frames), np.array(frictions), com, rng.uniform(1.0, 100.0)


def test_equilibrium_agrees_with_the_verifier_formulation():
    rng = np.random.default_rng(7)
    outcomes = []
    while len(outcomes) < 240:
        points, frames, frictions, com, mass = random_case(rng)
        result = static_equilibrium(points, frames[:, :, 2], frictions, com, mass,
                                    tangents=frames[:, :, 0])
        if abs(result.margin) < 1e-6 * mass:
            continue   # on the boundary: either answer is right
        assert result.feasible == wrench_feasible(points, frames, frictions, com, mass), (
            points, frames, frictions, com, mass, result.margin)
        if result.feasible:
            np.testing.assert_allclose(result.forces.sum(axis=0), [0, 0, mass * 9.81],
                                       atol=1e-6 * mass)
        outcomes.append(result.feasible)
    assert 40 <= sum(outcomes) <= len(outcomes) - 40   # both kinds well represented
