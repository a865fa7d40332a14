"""Contact search volumes (stance.planning.volumes, Escande et al. 2.5-2.6)."""

import math
from unittest import mock

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from stance.planning import volumes
from stance.planning.volumes import SearchVolume, initial_volume

SQUARE = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])


def sample(volume, count, rng):
    """(count, 3) uniform points of the volume's bounding box."""
    low = np.append(volume.polygon.min(axis=0), volume.theta_lower)
    high = np.append(volume.polygon.max(axis=0), volume.theta_upper)
    return rng.uniform(low, high, size=(count, 3))


def inside(volume, points, tolerance):
    """Which points satisfy A v <= b + tolerance."""
    A, b = volume.halfspaces()
    return np.all(points @ A.T <= b + tolerance, axis=1)


def check_partition(volume, center, half_extents, pieces, rng, count=3000, margin=1e-7):
    """Pieces lie in C, are convex, have disjoint interiors, avoid V and cover C \\ V,
    except within margin (m, rad) of their boundaries."""
    A, b = volume.halfspaces()
    for piece in pieces:
        assert piece.theta_lower >= volume.theta_lower - 1e-12
        assert piece.theta_upper <= volume.theta_upper + 1e-12
        assert np.all(piece.polygon @ A[:-2, 0:2].T <= b[:-2] + margin)
        # Convex, simple and CCW: its signed area is its convex hull's.
        assert piece.area == pytest.approx(ConvexHull(piece.polygon, qhull_options="QJ").volume,
                                           abs=1e-9)
    points = sample(volume, count, rng)
    points = points[inside(volume, points, -margin)]
    distance_out_of_box = np.max(np.abs(points - center) - half_extents, axis=1)
    strictly = np.sum([inside(piece, points, -margin) for piece in pieces], axis=0)
    loosely = np.sum([inside(piece, points, margin) for piece in pieces], axis=0)
    assert np.all(strictly <= 1)
    assert np.all(loosely[distance_out_of_box > margin] >= 1)
    assert np.all(loosely[distance_out_of_box < -margin] == 0)
    return points


def test_subtracting_a_box_inside_leaves_six_parts_partitioning_the_rest():
    volume = initial_volume(SQUARE)
    center, half_extents = np.array([0.1, -0.2, 0.5]), np.array([0.1, 0.1, 0.3])
    pieces = volume.subtract(center, half_extents)
    assert len(pieces) == 6
    points = check_partition(volume, center, half_extents, pieces, np.random.default_rng(1))
    assert len(points) > 2000
    box_volume = np.prod(2 * half_extents)
    total = sum(piece.area * (piece.theta_upper - piece.theta_lower) for piece in pieces)
    assert total == pytest.approx(volume.area * 2 * math.pi - box_volume)


def test_slivers_are_dropped():
    volume = initial_volume(SQUARE, (-1.0, 1.0))
    # Left slab 5e-5 m wide (area 5e-5 m^2), theta gap below the box 0.01 rad.
    center = np.array([-0.45, 0.0, -0.79])
    half_extents = np.array([0.04995, 0.1, 0.2])
    pieces = volume.subtract(center, half_extents)
    assert len(pieces) == 4
    assert not any(piece.is_empty() for piece in pieces)
    left_slab = 5e-5 * 1.0 * 2.0
    theta_gap = (2 * half_extents[0]) * (2 * half_extents[1]) * 0.01
    kept = sum(piece.area * (piece.theta_upper - piece.theta_lower) for piece in pieces)
    assert kept == pytest.approx(volume.area * 2.0 - np.prod(2 * half_extents) - left_slab
                                 - theta_gap)
    assert SearchVolume(SQUARE * 0.004, 0.0, 1.0).is_empty()          # 6.4e-5 m^2
    assert SearchVolume(SQUARE, 0.0, 0.015).is_empty()
    assert not SearchVolume(SQUARE * 0.02, 0.0, 0.1).is_empty()       # 4e-4 m^2


def test_a_box_covering_the_volume_leaves_nothing():
    volume = initial_volume(SQUARE)
    assert volume.subtract([0.0, 0.0, 0.0], [0.6, 0.6, 4.0]) == []


def test_a_box_missing_the_volume_leaves_it_whole():
    volume = initial_volume(SQUARE, (-1.0, 1.0))
    assert volume.subtract([2.0, 0.0, 0.0], [0.2, 0.2, 0.2]) == [volume]
    assert volume.subtract([0.0, 0.0, 2.0], [0.2, 0.2, 0.5]) == [volume]


def test_chebyshev_center_of_a_triangle_is_its_incenter():
    triangle = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    volume = SearchVolume(triangle, -0.5, 1.5)
    inradius = (2.0 - math.sqrt(2.0)) / 2.0
    np.testing.assert_allclose(volume.chebyshev_center(), [inradius, inradius, 0.5],
                               atol=1e-9)
    assert volume.contains(volume.chebyshev_center(), tolerance=-0.29)


def test_halfspaces_describe_the_prism():
    volume = initial_volume(SQUARE, (-1.0, 2.0))
    A, b = volume.halfspaces()
    assert A.shape == (6, 3) and b.shape == (6,)
    assert volume.contains([0.5, 0.5, 2.0])
    assert volume.contains([0.0, 0.0, 0.0], tolerance=-0.49)
    assert not volume.contains([0.51, 0.0, 0.0])
    assert not volume.contains([0.0, 0.0, -1.01])


def test_clockwise_or_concave_polygons_are_rejected():
    with pytest.raises(ValueError):
        SearchVolume(SQUARE[::-1], -1.0, 1.0)
    with pytest.raises(ValueError):
        SearchVolume(np.array([[0.0, 0.0], [1.0, 0.0], [0.2, 0.2], [0.0, 1.0]]), -1.0, 1.0)


def test_repeated_search_covers_the_volume_and_terminates():
    """The paper's loop: take a point of a volume, subtract a box around it, repeat."""
    pending, contacts = [initial_volume(SQUARE * 0.3)], []
    half_extents = np.array([0.05, 0.05, 0.5])
    while pending:
        volume = pending.pop()
        contact = volume.chebyshev_center()
        assert volume.contains(contact)
        contacts.append(contact)
        pending.extend(volume.subtract(contact, half_extents))
        assert len(contacts) < 500
    contacts = np.array(contacts)
    # Every point of C is close to some contact.
    points = sample(initial_volume(SQUARE * 0.3), 500, np.random.default_rng(3))
    gaps = np.min(np.max(np.abs(points[:, None, :] - contacts[None]) / (2 * half_extents),
                         axis=2), axis=1)
    assert np.all(gaps <= 0.75)


convex_polygons = st.lists(
    st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0)), min_size=3, max_size=12,
).map(np.array).filter(lambda points: ConvexHull(points, qhull_options="QJ").volume > 0.01)


@settings(max_examples=40, deadline=None)
@given(points=convex_polygons,
       center=st.tuples(st.floats(-1.2, 1.2), st.floats(-1.2, 1.2), st.floats(-4.0, 4.0)),
       half_extents=st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.floats(0.0, 3.0)),
       seed=st.integers(0, 2**16))
@example(points=np.array([[0.6748031819636711, 0.0], [-0.96875, 1.0], [-3.85e-55, 0.5]]),
         center=(0.0, 0.0, 0.0), half_extents=(0.0, 1.0, 1.0), seed=0)  # near-duplicate vertex
def test_subtraction_partitions_random_volumes(points, center, half_extents, seed):
    hull = ConvexHull(points)
    volume = initial_volume(points[hull.vertices])      # 2-D hull vertices are CCW
    center, half_extents = np.array(center), np.array(half_extents)
    with mock.patch.object(volumes, "MIN_AREA", 0.0), \
            mock.patch.object(volumes, "MIN_THETA_WIDTH", 0.0):
        pieces = volume.subtract(center, half_extents)
    assert len(pieces) <= 6
    check_partition(volume, center, half_extents, pieces, np.random.default_rng(seed), 1000)
    for piece in pieces:
        assert piece.contains(piece.chebyshev_center())
