"""Direct assignment (a): closest face, threshold schedule, minimum points and planarity."""

import numpy as np
import pytest
from conftest import box_store

from colmap_citymodel.assign.assignment import (Assignment, Observers, front_share, planarity,
                                                roof_points_seen_from_below)
from colmap_citymodel.assign.schedule import assign, next_threshold
from colmap_citymodel.block.reconstruction import observations, observer_centres
from colmap_citymodel.errors import InputError
from colmap_citymodel.options import AssignmentOptions


def wall_points(rng, n, offset_sigma=0.05):
    """Points in front of the y = 0 wall (normal -y) at small distances."""
    x = rng.uniform(1, 9, n)
    z = rng.uniform(1, 9, n)
    y = -np.abs(rng.normal(0, offset_sigma, n)) - 0.01
    return np.column_stack([x, y, z])


def test_points_go_to_the_closest_face_within_the_threshold():
    rng = np.random.default_rng(1)
    store = box_store()
    near = wall_points(rng, 40)
    far = near + [0, -3.0, 0]  # 3 m in front of the wall: beyond the 2 m threshold
    roof = np.column_stack([rng.uniform(1, 9, 30), rng.uniform(1, 9, 30),
                            10 + rng.normal(0, 0.05, 30)])
    points = np.vstack([near, far, roof])
    ids = np.arange(len(points)) + 100
    result = assign(points, ids, store, 2.0, AssignmentOptions())
    wall = int(np.argmin(np.linalg.norm(store.normals - [0, -1, 0], axis=1)))
    top = int(np.argmax(store.normals[:, 2]))
    assert np.all(result.face_index[:40] == wall)
    assert np.all(result.face_index[40:80] == -1)
    assert np.all(result.face_index[80:] == top)
    np.testing.assert_allclose(np.abs(result.distance[:40]), np.abs(near[:, 1]), atol=1e-9)
    assert np.all(np.isnan(result.distance[40:80]))
    assert result.num_faces == 2 and result.num_assigned == 70
    np.testing.assert_array_equal(result.points_of_face(top), ids[80:])


def test_faces_with_too_few_points_or_collinear_points_are_rejected():
    rng = np.random.default_rng(2)
    store = box_store()
    few = wall_points(rng, 10)  # below 15
    line = np.column_stack([np.linspace(1, 9, 30), np.full(30, 10.02),
                            np.full(30, 5.0)])  # on the y = 10 wall but a line
    result = assign(np.vstack([few, line]), np.arange(40), store, 2.0,
                    AssignmentOptions(method="direct"))
    assert result.num_assigned == 0
    assert result.rejected_faces == {"too_few_points": 1, "not_planar": 1}
    relaxed = AssignmentOptions(method="direct", min_points_per_plane=5)
    assert assign(few, np.arange(10), store, 2.0, relaxed).num_assigned == 10


@pytest.mark.parametrize("method", ["direct", "roi_msac"])
def test_a_face_of_the_previous_assignment_keeps_points_close_to_a_line(method):
    rng = np.random.default_rng(4)
    store = box_store()
    wall = int(np.argmin(np.linalg.norm(store.normals - [0, -1, 0], axis=1)))
    other = int(np.argmin(np.linalg.norm(store.normals - [0, 1, 0], axis=1)))
    few = wall_points(rng, 10)  # 10 points: below 15
    # On the y = 10 wall, a band 8 m long and 0.22 m wide: planarity about 8e-4, under the
    # limit of 1e-3 and above half of it
    band = np.column_stack([rng.uniform(1, 9, 40), np.full(40, 10.02),
                            5.0 + rng.uniform(-0.11, 0.11, 40)])
    assert 0.5e-3 < planarity(band) < 1e-3
    points, ids = np.vstack([few, band]), np.arange(50)
    options = AssignmentOptions(method=method)
    assert assign(points, ids, store, 2.0, options).num_assigned == 0
    # The band's face held points in the previous assignment: it keeps them. The minimum
    # count is not relaxed: a face losing its points (a wrong one, as the block moves onto
    # the model) must be able to leave.
    kept = assign(points, ids, store, 2.0, options, kept_faces=np.array([wall, other]))
    assert np.all(kept.face_index[:10] == -1) and np.all(kept.face_index[10:] == other)
    assert assign(points, ids, store, 2.0, options,
                  kept_faces=np.array([wall])).num_assigned == 0
    strict = AssignmentOptions(method=method, face_hysteresis=1.0)
    assert assign(points, ids, store, 2.0, strict,
                  kept_faces=np.array([wall, other])).num_assigned == 0


def test_planarity_measure():
    rng = np.random.default_rng(3)
    plane = np.column_stack([rng.uniform(0, 5, 100), rng.uniform(0, 5, 100), np.zeros(100)])
    line = np.column_stack([np.linspace(0, 5, 100), 1e-4 * rng.normal(size=100), np.zeros(100)])
    assert planarity(plane) > 0.5
    assert planarity(line) < 1e-3


def test_threshold_schedule_follows_mean_distance_with_bounds():
    rng = np.random.default_rng(4)
    store = box_store()
    options = AssignmentOptions()
    points = wall_points(rng, 50, offset_sigma=0.3)
    first = assign(points, np.arange(50), store, 2.0, options)
    mean_distance = np.mean(np.abs(first.distance[first.assigned]))
    expected = np.clip(3.5 * mean_distance, 0.4, 2.0)
    assert next_threshold(first, points, store, options, sigma=0.2) == pytest.approx(expected)
    # Points very close to the plane: the lower bound 2 x sigma_dTP applies.
    close = wall_points(rng, 50, offset_sigma=0.001)
    a = assign(close, np.arange(50), store, 2.0, options)
    assert next_threshold(a, close, store, options, sigma=0.2) == pytest.approx(0.4)
    assert next_threshold(a, close, store, options, sigma=0.05) == pytest.approx(0.1)


def test_without_unassigns_only_the_masked_points():
    a = Assignment(np.arange(4), np.array([0, 0, 1, -1]), np.array([0.1, -0.2, 0.3, np.nan]), 2.0)
    b = a.without(np.array([False, True, False, False]))
    np.testing.assert_array_equal(b.face_index, [0, -1, 1, -1])
    np.testing.assert_array_equal(a.face_index, [0, 0, 1, -1])  # the original is unchanged


def test_unknown_method_is_a_clear_error():
    with pytest.raises(InputError, match="unknown assignment method 'bogus'"):
        assign(np.zeros((1, 3)), np.arange(1), box_store(), 2.0, AssignmentOptions(method="bogus"))


def _observed_from(points, cameras):
    """Observers: every point seen from every camera in `cameras` (M, 3)."""
    rows = np.repeat(np.arange(len(points)), len(cameras))
    return Observers(rows, np.tile(np.asarray(cameras, float), (len(points), 1)))


def test_a_roof_keeps_only_the_points_seen_from_above_it():
    rng = np.random.default_rng(4)
    store = box_store()
    top = int(np.argmax(store.normals[:, 2]))
    wall = int(np.argmin(np.linalg.norm(store.normals - [0, -1, 0], axis=1)))
    # 30 points 0.3 m above the roof's plane (a parapet the model does not have), 40 on the wall
    roof = np.column_stack([rng.uniform(1, 9, 30), rng.uniform(1, 9, 30),
                            10.3 + rng.normal(0, 0.05, 30)])
    points = np.vstack([roof, wall_points(rng, 40)])
    ids = np.arange(len(points))
    street = [(-5.0, -20.0, 2.0), (5.0, -20.0, 2.0), (15.0, -20.0, 2.0)]  # below the roof
    drone = [(0.0, -10.0, 30.0), (10.0, 5.0, 30.0), (5.0, 20.0, 30.0)]  # above it
    options = AssignmentOptions()

    from_street = assign(points, ids, store, 2.0, options,
                         observers=_observed_from(points, street))
    assert np.all(from_street.face_index[:30] == -1)  # the roof is not seen from the street
    assert np.all(from_street.face_index[30:] == wall)  # walls are never tested
    assert from_street.num_faces == 1

    from_drone = assign(points, ids, store, 2.0, options, observers=_observed_from(points, drone))
    assert np.all(from_drone.face_index[:30] == top)
    # the wall's points, seen from behind by two of these cameras, stay: walls are not tested
    assert np.all(from_drone.face_index[30:] == wall)

    off = AssignmentOptions(roofs_seen_from_above=False)
    kept = assign(points, ids, store, 2.0, off, observers=_observed_from(points, street))
    assert np.all(kept.face_index[:30] == top)
    without = assign(points, ids, store, 2.0, options)  # no observers: nothing to test
    np.testing.assert_array_equal(without.face_index, kept.face_index)


def test_the_majority_of_a_points_images_decides_which_side_it_is_seen_from():
    store = box_store()
    top = int(np.argmax(store.normals[:, 2]))
    points = np.array([[5.0, 5.0, 10.0], [4.0, 4.0, 10.0], [6.0, 6.0, 10.0]])
    face_index = np.array([top, top, -1])
    above, below = (5.0, -10.0, 40.0), (5.0, -30.0, 1.5)
    # point 0: two of three images above; point 1: one of three; point 2: unassigned
    rows = np.array([0, 0, 0, 1, 1, 1, 2])
    centres = np.array([above, above, below, above, below, below, above], float)
    observers = Observers(rows, centres)
    share = front_share(points, face_index, store.normals, observers)
    np.testing.assert_allclose(share[:2], [2 / 3, 1 / 3])
    assert np.isnan(share[2])
    below_roof = roof_points_seen_from_below(points, face_index, store, observers)
    np.testing.assert_array_equal(below_roof, [False, True, False])
    # an image that is not registered (nan centre) does not count
    centres[[1, 2]] = np.nan
    share = front_share(points, face_index, store.normals, Observers(rows, centres))
    np.testing.assert_allclose(share[:2], [1.0, 1 / 3])


def test_observations_list_every_image_of_every_tie_point(street_scene):
    rec = street_scene.truth
    ids = np.array(sorted(rec.point3D_ids()))[::7]
    rows, image_ids = observations(rec, ids)
    assert len(rows) == sum(rec.point3D(int(i)).track.length() for i in ids)
    k = len(rows) // 2
    elements = rec.point3D(int(ids[rows[k]])).track.elements
    assert image_ids[k] in [e.image_id for e in elements]
    centres = observer_centres(rec, image_ids)
    np.testing.assert_allclose(centres[k], rec.image(int(image_ids[k])).projection_center())
    assert np.all(np.isnan(observer_centres(rec, np.array([10**6]))))


def facade_with_setback(depth: float):
    """A 10 x 10 m facade (y = 0, normal -y) over its lower half and, `depth` m behind it, a
    set-back storey's facade over its upper half; roofs not needed."""
    from colmap_citymodel.citymodel.build import store_from_polygons

    lower = np.array([(0, 0, 0), (10, 0, 0), (10, 0, 5), (0, 0, 5)], float)
    upper = np.array([(0, depth, 5), (10, depth, 5), (10, depth, 10), (0, depth, 10)], float)
    return store_from_polygons([lower, upper], origin=np.zeros(3),
                               semantics=["WallSurface", "WallSurface"])


def test_a_point_between_two_surfaces_goes_to_neither():
    # The faces overlap where the storey's projection meets the facade's (margin): near z = 5
    # a point 0.15 m behind the facade is 0.15 m from one and 0.15 m from the other.
    store = facade_with_setback(0.3)
    options = AssignmentOptions(min_points_per_plane=1, planarity_threshold=-1.0,
                                point_normal_angle=180.0)
    points = np.array([[5.0, -0.02, 5.05],  # on the facade, 0.28 m nearer than the storey
                       [5.0, 0.15, 5.05],  # half way: ambiguous
                       [5.0, 0.28, 5.05]])  # on the storey's facade
    a = assign(points, np.arange(3), store, 1.0, options)
    lower, upper = (int(np.argmin(np.abs(store.centroids[:, 2] - z))) for z in (2.5, 7.5))
    assert a.face_index.tolist() == [lower, -1, upper]
    off = assign(points, np.arange(3), store, 1.0,
                 AssignmentOptions(min_points_per_plane=1, planarity_threshold=-1.0,
                                   point_normal_angle=180.0, ambiguity_margin=0.0))
    assert off.face_index.tolist() == [lower, lower, upper]


def test_points_on_a_surface_turned_from_the_face_are_not_its_points():
    # A balcony slab 0.3 m in front of the y = 0 wall: its points lie within the threshold of
    # the wall's plane, but their neighbourhood is horizontal.
    rng = np.random.default_rng(5)
    store = box_store()
    wall = int(np.argmin(np.linalg.norm(store.normals - [0, -1, 0], axis=1)))
    facade = wall_points(rng, 200, offset_sigma=0.02)
    slab = np.column_stack([rng.uniform(2, 8, 200), rng.uniform(-0.45, -0.15, 200),
                            5.0 + rng.normal(0, 0.005, 200)])
    points = np.vstack([facade, slab])
    a = assign(points, np.arange(len(points)), store, 1.0,
               AssignmentOptions(method="direct", point_normal_angle=30.0))
    assert np.mean(a.face_index[:200] == wall) > 0.9
    assert np.mean(a.face_index[200:] == wall) < 0.1
    plain = assign(points, np.arange(len(points)), store, 1.0, AssignmentOptions(method="direct"))
    assert np.mean(plain.face_index[200:] == wall) > 0.9  # the default: no normal test
