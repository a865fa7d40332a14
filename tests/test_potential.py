"""Potential field on a rough trajectory (stance.planning.potential, Escande et al. 2.7)."""

import numpy as np
import pinocchio as pin
import pytest

from stance.planning.potential import RoughTrajectory
from stance.robot import Robot


@pytest.fixture(scope="module")
def model():
    return Robot.load("talos").model


@pytest.fixture(scope="module")
def half_sitting():
    return Robot.load("talos").reference_configurations["half_sitting"]


def key_posture(reference, x, y, rotation_vector=(0.0, 0.0, 0.0), bend=0.0):
    """reference moved to base (x, y) m with the given base rotation, joints offset by bend."""
    q = reference.copy()
    q[0], q[1] = x, y
    q[3:7] = pin.Quaternion(pin.exp3(np.array(rotation_vector, dtype=float))).coeffs()
    q[7:] += bend
    return q


@pytest.fixture(scope="module")
def turning(model, half_sitting):
    """Three corners, base rotating about z and tilting, joints changing along the way."""
    keys = [key_posture(half_sitting, 0.0, 0.0),
            key_posture(half_sitting, 1.0, 0.0, (0.0, 0.0, 0.3), 0.1),
            key_posture(half_sitting, 1.2, 1.0, (0.1, 0.0, 0.9), -0.1),
            key_posture(half_sitting, 2.0, 1.4, (0.0, 0.1, 1.2), 0.05)]
    return RoughTrajectory(model, keys, corner_deviation=0.05)


def polyline_distance(point, vertices):
    """Distance (m) from a point to the polyline through vertices, in any dimension."""
    distances = []
    for a, b in zip(vertices[:-1], vertices[1:]):
        t = np.clip((point - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        distances.append(np.linalg.norm(point - (a + t * (b - a))))
    return min(distances)


def finite_differences(function, model, q, step=1e-6):
    """Central differences of function(q) through pin.integrate, one tangent direction at a
    time."""
    gradient = np.zeros(model.nv)
    for i in range(model.nv):
        dq = np.zeros(model.nv)
        dq[i] = step
        forward = function(pin.integrate(model, q, dq))
        backward = function(pin.integrate(model, q, -dq))
        gradient[i] = (forward - backward) / (2.0 * step)
    return gradient


def test_potential_strictly_decreases_along_the_trajectory(turning):
    abscissas = np.linspace(0.0, turning.length, 80)
    values = []
    for s in abscissas:
        value = turning.evaluate(turning.configuration_at(s))
        assert value.s == pytest.approx(s, abs=1e-9)
        assert np.linalg.norm(value.residual) < 1e-9
        values.append(value.value)
    assert np.all(np.diff(values) < 0.0)
    goal = turning.evaluate(turning.goal_configuration)
    assert goal.value == pytest.approx(min(values))
    assert goal.s == pytest.approx(turning.length)


@pytest.mark.parametrize("where", ["segment", "arc"])
def test_derivatives_match_central_differences(turning, where):
    rng = np.random.default_rng(7)
    s_corner = turning.s_of_key_postures[1]      # a smoothed corner projects to its arc
    s = s_corner if where == "arc" else 0.25 * s_corner
    model = turning.model
    for _ in range(3):
        q = pin.integrate(model, turning.configuration_at(s), 0.02 * rng.standard_normal(model.nv))
        value = turning.evaluate(q)
        assert np.linalg.norm(value.ds_dq[0:6]) > 0.5
        assert np.all(value.ds_dq[6:] == 0.0)
        np.testing.assert_allclose(
            value.ds_dq, finite_differences(lambda q: turning.project(q).s, model, q), atol=1e-6)
        np.testing.assert_allclose(
            value.gradient, finite_differences(lambda q: turning.evaluate(q).value, model, q),
            atol=1e-6)


def test_smoothed_curve_stays_within_corner_deviation(turning):
    vertices = np.array([turning.free_flyer_point(q) for q in turning.key_postures])
    deviations = [polyline_distance(turning.free_flyer_point(turning.configuration_at(s)),
                                    vertices)
                  for s in np.linspace(0.0, turning.length, 400)]
    assert max(deviations) <= turning.corner_deviation + 1e-9
    # The corners are really smoothed, by the largest radius allowed: their vertices are
    # corner_deviation away from the arcs.
    for corner in turning.key_postures[1:-1]:
        assert turning.project(corner).distance == pytest.approx(turning.corner_deviation)


def test_tangent_points_stay_within_half_segments(model, half_sitting):
    keys = [key_posture(half_sitting, 0.0, 0.0), key_posture(half_sitting, 0.1, 0.0),
            key_posture(half_sitting, 0.1, 0.1)]
    trajectory = RoughTrajectory(model, keys, corner_deviation=1.0)
    vertices = np.array([trajectory.free_flyer_point(q) for q in keys])
    # The arc starts at the first segment's middle and ends at the second one's middle:
    # a quarter circle of radius 0.05 m.
    assert trajectory.length == pytest.approx(0.05 + 0.05 + 0.05 * np.pi / 2.0)
    middle = trajectory.free_flyer_point(trajectory.configuration_at(trajectory.length / 2))
    corner_to_middle = 0.05 * (np.sqrt(2) - 1)
    assert polyline_distance(middle, vertices) == pytest.approx(corner_to_middle / np.sqrt(2))


def sweep_around_corner(trajectory, reference, corner, radius):
    """s' of points on a circle of `radius` m around the corner (x, y), sweeping 270 deg
    across the bisector, and the largest step between consecutive points (m)."""
    angles = np.linspace(-np.pi / 2.0, np.pi, 2001)
    abscissas = [trajectory.project(key_posture(reference, corner[0] + radius * np.cos(a),
                                                corner[1] + radius * np.sin(a))).s
                 for a in angles]
    return np.array(abscissas), radius * (angles[1] - angles[0])


@pytest.mark.parametrize("radius", [0.01, 0.1])
def test_projection_is_continuous_across_a_corner(model, half_sitting, radius):
    keys = [key_posture(half_sitting, 0.0, 0.0), key_posture(half_sitting, 1.0, 0.0),
            key_posture(half_sitting, 1.0, 1.0)]
    smoothed = RoughTrajectory(model, keys, corner_deviation=0.05)
    abscissas, step = sweep_around_corner(smoothed, half_sitting, (1.0, 0.0), radius)
    assert np.max(np.abs(np.diff(abscissas))) < 5.0 * step
    # Without smoothing, the closest point jumps from one segment to the other inside the
    # corner: the check above would catch it.
    sharp = RoughTrajectory(model, keys, corner_deviation=0.0)
    abscissas, step = sweep_around_corner(sharp, half_sitting, (1.0, 0.0), 0.01)
    assert np.max(np.abs(np.diff(abscissas))) > 0.01


def test_a_point_off_the_curve_has_a_larger_potential(turning):
    for s in [0.25 * turning.s_of_key_postures[1], turning.s_of_key_postures[1],
              turning.s_of_key_postures[2]]:
        on_curve = turning.configuration_at(s)
        off_curve = on_curve.copy()
        off_curve[7:] += 0.05        # joints do not move the projection in F
        off_curve[2] += 0.02         # the trajectory's base stays at constant height
        on_value, off_value = turning.evaluate(on_curve), turning.evaluate(off_curve)
        assert off_value.s == pytest.approx(on_value.s, abs=1e-9)
        assert off_value.value > on_value.value
        assert off_value.value - on_value.value == pytest.approx(
            off_value.residual @ off_value.residual)


def test_repeated_key_postures_are_one_vertex(model, half_sitting):
    keys = [key_posture(half_sitting, 0.0, 0.0), key_posture(half_sitting, 1.0, 0.0),
            key_posture(half_sitting, 1.0, 0.0), key_posture(half_sitting, 1.0, 1.0)]
    repeated = RoughTrajectory(model, keys)
    single = RoughTrajectory(model, [keys[0], keys[1], keys[3]])
    assert repeated.length == pytest.approx(single.length)
    s = repeated.s_of_key_postures
    assert s[1] == pytest.approx(s[2])
    np.testing.assert_allclose(s[[0, 1, 3]], single.s_of_key_postures)


def test_two_key_postures_make_one_segment(model, half_sitting):
    start = key_posture(half_sitting, 0.0, 0.0)
    goal = key_posture(half_sitting, 0.6, 0.8, (0.0, 0.0, 0.4), 0.2)
    trajectory = RoughTrajectory(model, [start, goal], rotation_scale=0.5)
    assert trajectory.length == pytest.approx(np.hypot(1.0, 0.5 * 0.4))
    halfway = trajectory.configuration_at(trajectory.length / 2.0)
    np.testing.assert_allclose(halfway[7:], half_sitting[7:] + 0.1)
    np.testing.assert_allclose(halfway[0:2], [0.3, 0.4])
    # Beyond the goal, the slope is flat: s' is clamped.
    beyond = key_posture(half_sitting, 1.2, 1.6, (0.0, 0.0, 0.4), 0.2)
    value = trajectory.evaluate(beyond)
    assert value.s == pytest.approx(trajectory.length)
    assert np.all(value.ds_dq == 0.0)


def test_collinear_corner_keeps_the_key_posture(model, half_sitting):
    keys = [key_posture(half_sitting, 0.0, 0.0), key_posture(half_sitting, 1.0, 0.0, bend=0.3),
            key_posture(half_sitting, 3.0, 0.0)]
    trajectory = RoughTrajectory(model, keys)
    assert trajectory.length == pytest.approx(3.0)
    np.testing.assert_allclose(trajectory.s_of_key_postures, [0.0, 1.0, 3.0])
    np.testing.assert_allclose(trajectory.configuration_at(1.0)[7:], keys[1][7:])
    value = trajectory.evaluate(key_posture(half_sitting, 1.0, 0.05))
    np.testing.assert_allclose(value.ds_dq[0:3], [1.0, 0.0, 0.0], atol=1e-12)


def test_coincident_bases_and_half_turns_are_rejected(model, half_sitting):
    base = key_posture(half_sitting, 0.0, 0.0)
    with pytest.raises(ValueError):
        RoughTrajectory(model, [base, key_posture(half_sitting, 0.0, 0.0, bend=0.2)])
    with pytest.raises(ValueError):
        RoughTrajectory(model, [base])
    turned_around = key_posture(half_sitting, 1.0, 0.0, (0.0, 0.0, 3.1))
    with pytest.raises(ValueError):
        RoughTrajectory(model, [base, turned_around])
