"""Swing and ball-and-socket joint limits (Raunhardt and Boulic, IV.B.2-3) and the mannequin.

Geometry of the limit domains against brute-force sampling; the swing/twist decomposition;
eq. 6-10 (only the component of the swing variation orthogonal to the limit is damped, by
the cubic h of the normalized depth); the second-stage clamp that lets a joint slide along
its limit (Fig. 6); limit files; and whole PIK runs on the mannequin where no swing leaves
its domain and no twist its interval.
"""

import math

import numpy as np
import pinocchio as pin
import pytest
from helpers.limit_runs import (mannequin_run, mannequin_start, set_swing_twist, swing_excess,
                                twist_excess)
from hypothesis import given, settings
from hypothesis import strategies as st

from stance.limits import cubic_step
from stance.models import MANNEQUIN_LIMIT_FILE, build_mannequin
from stance.swing import (BallLimit, EllipticCone, LimitFileError, SphericalPolygon,
                          SwingLimit, _altered, damp_swing, load_limit_file, parse_limits,
                          quaternion_rotation, rotation_from_swing_twist, rotation_quaternion,
                          swing_direction, swing_direction_jacobian, swing_from_direction,
                          swing_rotation, swing_twist)

THICKNESS = 0.2
SWING_TOLERANCE = math.radians(0.5)
TWIST_TOLERANCE = 1e-9
PROPERTY = settings(max_examples=12, deadline=None, derandomize=True, database=None)
SEEDS = st.integers(0, 2**32 - 1)


def direction(angle, azimuth):
    """Unit direction `angle` rad from z toward azimuth (rad from x)."""
    return np.array([math.sin(angle) * math.cos(azimuth),
                     math.sin(angle) * math.sin(azimuth), math.cos(angle)])


CONE = EllipticCone(1.0, 0.6)
# Convex pentagon in the upper hemisphere (its gnomonic image is a convex planar polygon).
PENTAGON = SphericalPolygon([direction(angle, azimuth) for angle, azimuth in
                             [(1.1, 0.0), (0.9, 1.3), (0.7, 2.6), (1.0, 3.8), (0.8, 5.0)]])
# Star-shaped around z, not convex: every other vertex pulled in (reflex vertices).
STAR = SphericalPolygon([direction(0.8 if k % 2 == 0 else 0.3, k * np.pi / 4)
                         for k in range(8)])
# The same shape, wide enough that a swing 0.3 rad inside its first edge's middle is
# nearest that edge (in STAR it is nearer the next ones): the damping tests' star.
WIDE_STAR = SphericalPolygon([direction(1.2 if k % 2 == 0 else 0.7, k * np.pi / 4)
                              for k in range(8)])
DOMAINS = {"cone": CONE, "polygon": PENTAGON, "star": WIDE_STAR}


def polygon_boundary(polygon, samples_per_edge=4000) -> np.ndarray:
    """Dense directions along the great-circle edges."""
    points = []
    for start, end in zip(polygon.vertices, np.roll(polygon.vertices, -1, axis=0)):
        angle = math.acos(np.clip(start @ end, -1.0, 1.0))
        for t in np.linspace(0.0, 1.0, samples_per_edge):
            points.append((math.sin((1 - t) * angle) * start + math.sin(t * angle) * end)
                          / math.sin(angle))
    return np.array(points)


def inside_gnomonic(polygon, unit) -> bool:
    """Brute-force containment for any simple polygon in the upper hemisphere: crossings of
    a ray from the gnomonic image of `unit` with the (straight) images of the edges."""
    if unit[2] <= 0:
        return False
    planar = polygon.vertices[:, :2] / polygon.vertices[:, 2:]
    x, y = unit[:2] / unit[2]
    inside = False
    for (x0, y0), (x1, y1) in zip(planar, np.roll(planar, -1, axis=0)):
        if (y0 > y) != (y1 > y) and x < x0 + (y - y0) * (x1 - x0) / (y1 - y0):
            inside = not inside
    return inside


def tangent_and_normal(domain, s):
    normal = domain.normal_at(s)
    return np.array([-normal[1], normal[0]]), normal


def point_inside_by(domain, depth):
    """A swing `depth` rad inside the limit (depth < 0: outside): below the boundary point
    at azimuth 0.7 rad of the cone, or the middle of the polygon's first edge."""
    if isinstance(domain, EllipticCone):
        boundary = domain.closest_boundary_point(2.0 * np.array([math.cos(0.7),
                                                                 math.sin(0.7)]))
        return boundary - depth * domain.normal_at(boundary)
    middle = domain.vertices[0] + domain.vertices[1]
    middle /= np.linalg.norm(middle)
    inward = domain.inward_normals[0]
    return swing_from_direction(math.cos(depth) * middle + math.sin(depth) * inward)


# Geometry of the domains.

@pytest.mark.parametrize("seed", range(5))
def test_cone_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, 200001)
    boundary = np.stack([CONE.a * np.cos(t), CONE.b * np.sin(t)], axis=1)
    for s in rng.uniform(-1.6, 1.6, (40, 2)):
        distances = np.linalg.norm(boundary - s, axis=1)
        closest = CONE.closest_boundary_point(s)
        assert np.linalg.norm(closest - s) == pytest.approx(distances.min(), abs=1e-5)
        assert (closest[0] / CONE.a) ** 2 + (closest[1] / CONE.b) ** 2 == pytest.approx(1.0)
        inside = (s[0] / CONE.a) ** 2 + (s[1] / CONE.b) ** 2 <= 1.0
        assert CONE.contains(s) == inside
        assert CONE.signed_distance(s) == pytest.approx(
            distances.min() if inside else -distances.min(), abs=1e-5)


@pytest.mark.parametrize("a, b", [(0.6, 2.1), (2.1, 0.6)], ids=["a<b", "a>b"])
@pytest.mark.parametrize("tiny", [0.0, -0.0, 1.8e-19, -3e-14])
def test_cone_closest_point_on_and_next_to_the_axes(a, b, tiny):
    """Swings on an axis up to rounding (a Talos hip at half_sitting: s_x = 1.8e-19) once
    divided by zero in the bisection."""
    cone = EllipticCone(a, b)
    t = np.linspace(0, 2 * np.pi, 200001)
    boundary = np.stack([a * np.cos(t), b * np.sin(t)], axis=1)
    for s in ([tiny, -0.411], [0.411, tiny], [tiny, 1.9], [2.0, tiny]):
        s = np.array(s)
        closest = cone.closest_boundary_point(s)
        assert (closest[0] / a) ** 2 + (closest[1] / b) ** 2 == pytest.approx(1.0)
        assert np.linalg.norm(closest - s) == pytest.approx(
            np.linalg.norm(boundary - s, axis=1).min(), abs=1e-5)


@pytest.mark.parametrize("polygon", [PENTAGON, STAR], ids=["convex", "star"])
@pytest.mark.parametrize("seed", range(5))
def test_polygon_matches_brute_force(seed, polygon):
    rng = np.random.default_rng(seed)
    boundary = polygon_boundary(polygon)
    for _ in range(50):
        s = swing_from_direction(direction(rng.uniform(0, 1.4), rng.uniform(0, 2 * np.pi)))
        unit = swing_direction(s)
        angles = np.arccos(np.clip(boundary @ unit, -1, 1))
        inside = inside_gnomonic(polygon, unit)
        assert polygon.contains(s) == inside
        assert polygon.signed_distance(s) == pytest.approx(
            angles.min() if inside else -angles.min(), abs=1e-3)
        closest = swing_direction(polygon.closest_boundary_point(s))
        assert math.acos(min(1.0, closest @ unit)) == pytest.approx(angles.min(), abs=1e-3)
        assert abs(polygon.signed_distance(polygon.closest_boundary_point(s))) < 1e-9


@pytest.mark.parametrize("name", DOMAINS)
def test_normal_is_the_direction_of_steepest_approach(name):
    """normal_at(s) = -grad signed_distance / |grad| wherever s is off the boundary."""
    domain, rng, eps = DOMAINS[name], np.random.default_rng(3), 1e-6
    for s in rng.uniform(-1.0, 1.0, (40, 2)):
        if abs(domain.signed_distance(s)) < 1e-3:
            continue
        gradient = np.array([(domain.signed_distance(s + eps * e)
                              - domain.signed_distance(s - eps * e)) / (2 * eps)
                             for e in np.eye(2)])
        assert domain.normal_at(s) == pytest.approx(-gradient / np.linalg.norm(gradient),
                                                    abs=1e-4)


def test_star_shaped_polygon_normal_is_the_steepest_approach_next_to_each_edge():
    """Near the middle of each edge, reflex or not, normal_at is -grad signed_distance."""
    eps = 1e-6
    for edge, (start, end) in enumerate(zip(STAR.vertices, np.roll(STAR.vertices, -1, 0))):
        middle = (start + end) / np.linalg.norm(start + end)
        for depth in (0.03, -0.03):
            s = swing_from_direction(math.cos(depth) * middle
                                     + math.sin(depth) * STAR.inward_normals[edge])
            assert STAR.signed_distance(s) == pytest.approx(depth, abs=1e-9)
            gradient = np.array([(STAR.signed_distance(s + eps * e)
                                  - STAR.signed_distance(s - eps * e)) / (2 * eps)
                                 for e in np.eye(2)])
            assert STAR.normal_at(s) == pytest.approx(-gradient / np.linalg.norm(gradient),
                                                      abs=1e-4)


@pytest.mark.parametrize("polygon, vertices", [(PENTAGON, range(5)), (STAR, range(0, 8, 2))],
                         ids=["convex", "star tips"])
def test_normal_next_to_a_convex_vertex_is_between_its_two_edges(polygon, vertices):
    """A direction 1e-10 rad outside a convex vertex (its closest boundary point) has its
    outward normal in the cone of the outward normals of the two edges that meet there
    (mapped back to the sphere's tangent plane), whichever edge found the vertex."""
    count = len(polygon.vertices)
    for vertex in vertices:
        unit = polygon.vertices[vertex]
        edges = [-polygon.inward_normals[(vertex - 1) % count],
                 -polygon.inward_normals[vertex]]
        projected = np.column_stack([n - (n @ unit) * unit for n in edges])
        outside = unit + 1e-10 * projected.sum(axis=1) / np.linalg.norm(projected.sum(axis=1))
        s = swing_from_direction(outside / np.linalg.norm(outside))
        jacobian = swing_direction_jacobian(s)
        tangent = jacobian @ np.linalg.solve(jacobian.T @ jacobian, polygon.normal_at(s))
        weights, *_ = np.linalg.lstsq(projected, tangent, rcond=None)
        assert projected @ weights == pytest.approx(tangent, abs=1e-6)
        assert np.all(weights > 0.0), vertex


def test_polygon_winding_twice_around_the_rest_direction_is_rejected():
    pentagram = [direction(0.6, k * 4 * np.pi / 5) for k in range(5)]
    with pytest.raises(ValueError, match="once around z"):
        SphericalPolygon(pentagram)


def test_polygon_not_around_the_rest_direction_is_rejected():
    with pytest.raises(ValueError, match="rest direction"):
        SphericalPolygon([direction(0.5, 0.0), direction(1.0, 0.3), direction(1.0, -0.3)])


@pytest.mark.parametrize("polygon", [PENTAGON, STAR], ids=["convex", "star"])
def test_polygon_vertex_order_does_not_matter(polygon):
    reversed_polygon = SphericalPolygon(polygon.vertices[::-1])
    for s in np.random.default_rng(4).uniform(-1.2, 1.2, (30, 2)):
        assert reversed_polygon.signed_distance(s) == pytest.approx(
            polygon.signed_distance(s))


# Swing / twist decomposition.

def test_swing_twist_round_trip():
    rng = np.random.default_rng(5)
    for _ in range(500):
        rotation = pin.exp3(rng.normal(size=3))
        s, theta = swing_twist(rotation)
        if np.linalg.norm(s) > np.pi - 1e-3:
            continue  # the decomposition is singular at the antipode of z
        assert rotation_from_swing_twist(s, theta) == pytest.approx(rotation, abs=1e-9)
        assert swing_direction(s) == pytest.approx(rotation[:, 2], abs=1e-12)
        assert -np.pi <= theta <= np.pi


def test_pure_swing_and_pure_twist_are_recovered():
    s = np.array([0.4, -0.7])
    assert swing_twist(swing_rotation(s))[0] == pytest.approx(s)
    assert swing_twist(swing_rotation(s))[1] == pytest.approx(0.0, abs=1e-12)
    s_twist, theta = swing_twist(pin.exp3(np.array([0.0, 0.0, 0.9])))
    assert s_twist == pytest.approx(np.zeros(2), abs=1e-12)
    assert theta == pytest.approx(0.9)


# Eq. 6-10 and the second stage.

@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("depth", [0.02, 0.1, 0.18])
def test_only_the_orthogonal_component_is_damped_by_the_cubic(name, depth):
    domain = DOMAINS[name]
    s = point_inside_by(domain, depth)
    assert domain.signed_distance(s) == pytest.approx(depth, abs=1e-6)
    tangent, normal = tangent_and_normal(domain, s)
    variation = 0.002 * normal + 0.004 * tangent
    target, h = damp_swing(domain, THICKNESS, s, s + variation, progressive=True)
    d = (THICKNESS - depth) / THICKNESS
    assert h == pytest.approx(cubic_step(d), abs=1e-6)
    moved = target - s
    assert moved @ normal == pytest.approx((1 - h) * 0.002, abs=1e-9)
    assert moved @ tangent == pytest.approx(0.004, abs=1e-9)


@pytest.mark.parametrize("name", DOMAINS)
def test_variation_away_from_the_limit_or_outside_the_zone_is_untouched(name):
    domain = DOMAINS[name]
    s = point_inside_by(domain, 0.1)
    tangent, normal = tangent_and_normal(domain, s)
    assert damp_swing(domain, THICKNESS, s, s - 0.01 * normal + 0.01 * tangent,
                      True)[0] is None
    deep = point_inside_by(domain, 0.3)
    assert damp_swing(domain, THICKNESS, deep, deep + 0.01 * normal, True)[0] is None


@pytest.mark.parametrize("name", DOMAINS)
def test_clamping_only_does_not_damp_inside(name):
    domain = DOMAINS[name]
    s = point_inside_by(domain, 0.1)
    assert damp_swing(domain, THICKNESS, s, s + 0.01 * domain.normal_at(s),
                      False)[0] is None


@pytest.mark.parametrize("name", DOMAINS)
@pytest.mark.parametrize("progressive", [True, False])
def test_state_on_the_limit_heading_outside_slides_along_it(name, progressive):
    """Fig. 6: the next state is the valid state nearest the candidate, on the limit and
    moved along it by the parallel part of the variation."""
    domain = DOMAINS[name]
    s = point_inside_by(domain, 0.0)
    tangent, normal = tangent_and_normal(domain, s)
    target, h = damp_swing(domain, THICKNESS, s, s + 0.05 * normal + 0.05 * tangent,
                           progressive)
    assert h == 1.0
    assert abs(domain.signed_distance(target)) < 1e-9
    assert (target - s) @ tangent > 0.03


@pytest.mark.parametrize("name", DOMAINS)
def test_start_outside_moves_back_onto_the_limit(name):
    domain = DOMAINS[name]
    s = point_inside_by(domain, -0.2)
    target, h = damp_swing(domain, THICKNESS, s, s + 0.01 * domain.normal_at(s), True)
    assert h == 1.0 and abs(domain.signed_distance(target)) < 1e-9


# Limit models on the mannequin.

@pytest.fixture(scope="module")
def mannequin():
    return build_mannequin()


@pytest.fixture(scope="module")
def limit_models(mannequin):
    return load_limit_file(MANNEQUIN_LIMIT_FILE, mannequin)


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(coefficients=st.lists(st.floats(-2.0, 2.0), min_size=4, max_size=4).filter(
    lambda c: np.linalg.norm(c) > 1e-3))
def test_compiled_quaternion_conversions_are_pinocchios(coefficients):
    """quaternion_rotation and rotation_quaternion (the ball joints' compiled decisions and
    projections) = Pinocchio's (Eigen's) conversions, an unnormalized quaternion included,
    to rounding; the round trip gives the unit quaternion back up to its sign."""
    coefficients = np.asarray(coefficients)
    quaternion = pin.Quaternion(coefficients).normalized()
    rotation = quaternion_rotation(coefficients)
    np.testing.assert_allclose(rotation, quaternion.toRotationMatrix(), rtol=0, atol=4e-15)
    np.testing.assert_allclose(rotation_quaternion(rotation),
                               pin.Quaternion(rotation).coeffs(), rtol=0, atol=1e-15)
    back = rotation_quaternion(rotation)
    assert min(np.abs(back - quaternion.coeffs()).max(),
               np.abs(back + quaternion.coeffs()).max()) < 1e-14


def pinocchio_decision(model, q, dq, progressive):
    """A ball joint's decision written with Pinocchio's SO(3) maps, as before the compiled
    ball_fix, and without its _may_reach shortcut: (variation fixed (rad, 3), h (3)), or
    None when the swing / twist rule leaves the move alone."""
    rotation = pin.Quaternion(q[model.q_slice]).normalized().toRotationMatrix()
    s, theta = swing_twist(rotation)
    altered, target, swing_h, twist_h = _altered(
        model.rule, s, theta, model.domain.signed_distance(s),
        rotation @ pin.exp3(dq[model.v_index]), progressive)
    if not altered:
        return None
    return pin.log3(rotation.T @ target), np.array([swing_h, swing_h, twist_h])


@pytest.mark.parametrize("progressive", [True, False])
@PROPERTY
@given(seed=SEEDS)
def test_compiled_ball_decisions_are_the_pinocchio_ones(mannequin, limit_models, progressive,
                                                       seed):
    """ball_fix (BallLimit.decide) takes the decision written with Pinocchio's exp3, log3
    and quaternions, on every joint of the mannequin from random states inside its limits
    and random moves (normal, 0.001-0.1 rad per DoF): the same joints fixed, the same
    variations to 1e-9 rad and h to 1e-12 (the compiled maps agree with Pinocchio's to
    rounding, not bits)."""
    rng = np.random.default_rng(seed)
    decided = 0
    for _ in range(5):
        q = mannequin_start(mannequin, limit_models, rng)
        dq = rng.normal(size=mannequin.model.nv) * rng.uniform(0.001, 0.1)
        free = np.ones(mannequin.model.nv, dtype=bool)
        for model in limit_models:
            expected = pinocchio_decision(model, q, dq, progressive)
            decision = model.decide(q, dq, free, progressive)
            assert (expected is None) == (len(decision.index) == 0), model.joint
            if expected is not None:
                decided += 1
                assert list(decision.index) == list(model.v_index)
                np.testing.assert_allclose(decision.dq, expected[0], rtol=0, atol=1e-9)
                np.testing.assert_allclose(decision.h, expected[1], rtol=0, atol=1e-12)
    assert decided > 0


def test_ball_decision_fixes_the_joint_on_the_damped_target(mannequin):
    model = BallLimit.for_joint(mannequin, "left_hip", CONE, twist=(-0.5, 0.5))
    q = mannequin.initial_configuration("standing")
    s = point_inside_by(CONE, 0.05)
    set_swing_twist(mannequin, q, "left_hip", s, 0.45)
    tangent, normal = tangent_and_normal(CONE, s)
    v = mannequin.model.joints[mannequin.joint_id("left_hip")].idx_v
    rotation = rotation_from_swing_twist(s, 0.45)
    candidate = rotation_from_swing_twist(s + 0.003 * normal + 0.002 * tangent, 0.47)
    dq = np.zeros(mannequin.model.nv)
    dq[v:v + 3] = pin.log3(rotation.T @ candidate)
    decision = model.decide(q, dq, np.ones(mannequin.model.nv, dtype=bool), True)
    assert list(decision.index) == [v, v + 1, v + 2]
    reached = swing_twist(rotation @ pin.exp3(decision.dq))
    swing_h, twist_h = decision.h[0], decision.h[2]
    assert swing_h == pytest.approx(cubic_step((THICKNESS - 0.05) / THICKNESS), abs=1e-6)
    assert twist_h == pytest.approx(cubic_step((0.45 - 0.3) / 0.2), abs=1e-6)  # zone 0.3-0.5
    assert (reached[0] - s) @ normal == pytest.approx((1 - swing_h) * 0.003, abs=1e-6)
    assert (reached[0] - s) @ tangent == pytest.approx(0.002, abs=1e-6)
    assert reached[1] - 0.45 == pytest.approx((1 - twist_h) * 0.02, abs=1e-9)


def test_swing_limit_locks_the_twist(mannequin):
    model = SwingLimit.for_joint(mannequin, "left_wrist", CONE, twist_locked=True)
    q = mannequin.initial_configuration("standing")
    v = mannequin.model.joints[mannequin.joint_id("left_wrist")].idx_v
    dq = np.zeros(mannequin.model.nv)
    dq[v:v + 3] = [0.01, 0.02, 0.1]
    decision = model.decide(q, dq, np.ones(mannequin.model.nv, dtype=bool), True)
    reached = swing_twist(np.eye(3) @ pin.exp3(decision.dq))
    assert reached[1] == pytest.approx(0.0, abs=1e-12)
    assert model.dof_names == ["left_wrist_swing_x", "left_wrist_swing_y", "left_wrist_twist"]


def test_mannequin_is_a_standing_adult(mannequin, limit_models):
    robot = mannequin
    q = robot.initial_configuration("standing")
    data = robot.model.createData()
    pin.framesForwardKinematics(robot.model, data, q)
    height = data.oMf[robot.frame_id("head")].translation[2]
    assert 1.6 < height < 1.8
    soles = [data.oMf[robot.frame_id(f"{side}_{part}")].translation
             for side in ("left", "right") for part in ("sole", "toe", "heel")]
    assert np.allclose([sole[2] for sole in soles], 0.0, atol=1e-9)
    com = pin.centerOfMass(robot.model, data, q)
    heels_x = data.oMf[robot.frame_id("left_heel")].translation[0]
    toes_x = data.oMf[robot.frame_id("left_toe")].translation[0]
    assert heels_x < com[0] < toes_x and abs(com[1]) < 1e-9 and 0.9 < com[2] < 1.1
    assert set(robot.limited_joint_names) == {f"{side}_{joint}" for side in ("left", "right")
                                              for joint in ("elbow", "knee", "knee_twist")}
    assert all(swing_excess(model, q) == 0.0 for model in limit_models)


# Limit files.

@pytest.mark.parametrize("entry, field", [
    ({"type": "ball", "twist": [-1, 1]}, "cone"),
    ({"type": "ball", "cone": {"a": 0.5}, "twist": [-1, 1]}, "cone"),
    ({"type": "ball", "cone": {"a": -0.5, "b": 0.5}, "twist": [-1, 1]}, "cone.a"),
    ({"type": "ball", "cone": {"a": 0.5, "b": 0.5}}, "twist"),
    ({"type": "ball", "cone": {"a": 0.5, "b": 0.5}, "twist": [1, -1]}, "twist"),
    ({"type": "swing", "cone": {"a": 0.5, "b": 0.5}, "twist": "loose"}, "twist"),
    ({"type": "hinge", "cone": {"a": 0.5, "b": 0.5}}, "type"),
    ({"type": "swing", "polygon": [[1, 0, 0], [0, 1, 0]]}, "polygon"),
    ({"type": "swing", "cone": {"a": 0.5, "b": 0.5}, "activation": 0}, "activation"),
    ({"type": "swing", "cone": {"a": 0.5, "b": 0.5}, "colour": "red"}, "colour"),
])
def test_limit_file_errors_name_the_field(mannequin, entry, field):
    with pytest.raises(LimitFileError, match=f"joints.left_hip.*{field}"):
        parse_limits({"joints": {"left_hip": entry}}, mannequin)


def test_a_limit_file_that_is_not_text_is_a_limit_file_error(mannequin, tmp_path):
    binary = tmp_path / "limits.yaml"
    binary.write_bytes(b"\xf0\x00\xff joints: {}")
    with pytest.raises(LimitFileError, match="not a YAML text file"):
        load_limit_file(binary, mannequin)


@pytest.mark.parametrize("joint, message", [("nose", "no joint"),
                                            ("left_elbow", "not a spherical joint")])
def test_limit_file_rejects_joints_that_cannot_hold_a_swing_limit(mannequin, joint, message):
    with pytest.raises(LimitFileError, match=message):
        parse_limits({"joints": {joint: {"type": "swing", "cone": {"a": 0.5, "b": 0.5}}}},
                     mannequin)


@pytest.mark.parametrize("strategy", ["clamping", "progressive"])
@PROPERTY
@given(seed=SEEDS, reachable=st.booleans())
def test_no_swing_or_twist_ever_leaves_its_limits(mannequin, limit_models, strategy, seed,
                                                   reachable):
    start = mannequin_start(mannequin, limit_models, np.random.default_rng(seed))
    for q, _ in mannequin_run(mannequin, limit_models, start, seed, reachable, strategy):
        for model in limit_models:
            assert swing_excess(model, q) <= SWING_TOLERANCE, model.joint
            assert twist_excess(model, q) <= TWIST_TOLERANCE, model.joint


@pytest.mark.parametrize("strategy", ["clamping", "progressive"])
@PROPERTY
@given(seed=SEEDS, reachable=st.booleans())
def test_the_compiled_clamping_loop_gives_the_python_loops_bits(mannequin, limit_models,
                                                                strategy, seed, reachable):
    """The mannequin's spherical joints decide inside the compiled clamping loop
    (swing.ball_fix): every step gives the general loop's bits, with the same decisions."""
    start = mannequin_start(mannequin, limit_models, np.random.default_rng(seed))
    compiled, general = (mannequin_run(mannequin, limit_models, start, seed, reachable,
                                       strategy, compiled_loop=compiled)
                         for compiled in (True, False))
    for (q, result), (general_q, expected) in zip(compiled, general):
        assert q.tobytes() == general_q.tobytes()
        assert result.damping.tobytes() == expected.damping.tobytes()
        assert result.clamped.tobytes() == expected.clamped.tobytes()
        assert result.clamping_iterations == expected.clamping_iterations


def excesses(limit_models, q) -> np.ndarray:
    """Swing and twist excess (rad) of every model."""
    return np.array([[swing_excess(model, q), twist_excess(model, q)]
                     for model in limit_models])


@PROPERTY
@given(seed=SEEDS, reachable=st.booleans(), outside=st.integers(1, 3))
def test_a_joint_started_outside_moves_back_and_never_further_out(
        mannequin, limit_models, seed, reachable, outside):
    """Swings pushed 0.05-0.3 rad out of their domain, ball twists 0.05-0.3 rad past a
    bound: no step takes them further out, and they end back inside."""
    rng = np.random.default_rng(seed)
    start = mannequin_start(mannequin, limit_models, rng)
    for index in rng.choice(len(limit_models), outside, replace=False):
        model = limit_models[index]
        s, theta = swing_twist(model.rotation(start))
        boundary = model.domain.closest_boundary_point(s)
        s = boundary + rng.uniform(0.05, 0.3) * model.domain.normal_at(boundary)
        if model.twist is not None and model.twist.upper[0] > model.twist.lower[0]:
            theta = model.twist.upper[0] + rng.uniform(0.05, 0.3)
        set_swing_twist(mannequin, start, model.joint, s, theta)
    excess = excesses(limit_models, start)
    assert excess.max() > 0.0
    for q, _ in mannequin_run(mannequin, limit_models, start, seed, reachable):
        next_excess = excesses(limit_models, q)
        assert np.all(next_excess <= excess + 1e-9)
        excess = next_excess
    assert excess[:, 0].max() <= SWING_TOLERANCE
    assert excess[:, 1].max() <= TWIST_TOLERANCE


@pytest.mark.parametrize("progressive", [True, False])
def test_an_unmoved_ball_joint_outside_goes_back_and_one_inside_stays(mannequin,
                                                                      limit_models,
                                                                      progressive):
    """No task moves the joint (dq = 0): outside its swing limit and twist bound, its
    variation is fixed to one back onto them; inside, nothing is fixed."""
    model = next(model for model in limit_models if isinstance(model, BallLimit)
                 and model.twist is not None and model.twist.upper[0] > model.twist.lower[0])
    q, nv = mannequin.initial_configuration("standing"), mannequin.model.nv
    fixed, fixed_dq, h = np.zeros(nv, dtype=bool), np.zeros(nv), np.zeros(nv)
    assert not model.fix(q, np.zeros(nv), fixed, fixed_dq, h, progressive)
    s, _ = swing_twist(model.rotation(q))
    boundary = model.domain.closest_boundary_point(s)
    set_swing_twist(mannequin, q, model.joint, boundary + 0.2 * model.domain.normal_at(boundary),
                    model.twist.upper[0] + 0.2)
    assert swing_excess(model, q) > 0.1 and twist_excess(model, q) > 0.1
    assert model.fix(q, np.zeros(nv), fixed, fixed_dq, h, progressive)
    back = pin.integrate(mannequin.model, q, np.where(fixed, fixed_dq, 0.0))
    assert swing_excess(model, back) <= SWING_TOLERANCE
    assert twist_excess(model, back) <= TWIST_TOLERANCE


def test_strategy_none_lets_swings_leave_their_limits(mannequin, limit_models):
    """Sanity check of the harness: without a limit strategy the same runs leave limits."""
    start = mannequin.initial_configuration("standing")
    worst = max(swing_excess(model, q) for q, _ in mannequin_run(
        mannequin, limit_models, start, seed=2, reachable=False, strategy="none", steps=100)
                for model in limit_models)
    assert worst > 5 * SWING_TOLERANCE
