"""Indirect assignment (b) and (c) with MSAC, alpha-shape components, weighted sampling, auto."""

import logging

import numpy as np
import pytest
from conftest import box_store

from colmap_citymodel.assign.indirect import ExtractedPlane, alpha_components, assign_msac, assign_roi_msac, extract_planes, match_planes, point_quality_weights
from colmap_citymodel.assign.schedule import assign, initial_threshold, next_threshold
from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.options import AssignmentOptions, RefineOptions
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, building_polygons, make_street_scene, sample_surface_points


def face_with_normal(store, normal):
    return int(np.argmax(store.normals @ np.asarray(normal, float)))


def plane_patch(rng, n, centre, u, v, size, noise):
    """n points on the rectangle centre + s u + t v (|s|, |t| <= size / 2) with normal noise."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    normal = np.cross(u, v)
    s = rng.uniform(-size[0] / 2, size[0] / 2, n)
    t = rng.uniform(-size[1] / 2, size[1] / 2, n)
    return (np.asarray(centre, float) + s[:, None] * u + t[:, None] * v
            + rng.normal(0, noise, n)[:, None] * normal)


def unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def test_extraction_recovers_planes_with_outliers():
    rng = np.random.default_rng(11)
    tilt = np.radians(30)
    truth = [  # (normal, a point on the plane, in-plane axes)
        (unit([0, -1, 0]), [5, 0, 5], [1, 0, 0], [0, 0, 1]),
        (unit([0, -np.sin(tilt), np.cos(tilt)]), [5, 20, 12],
         [1, 0, 0], [0, np.cos(tilt), np.sin(tilt)]),
        (unit([1, 0, 0]), [30, 10, 5], [0, 1, 0], [0, 0, 1]),
    ]
    clouds = [plane_patch(rng, 400, p, u, v, (10, 8), 0.02) for _, p, u, v in truth]
    outliers = rng.uniform([-5, -5, -5], [35, 30, 20], (120, 3))
    points = np.vstack(clouds + [outliers])
    planes = extract_planes(points, AssignmentOptions())
    for k, (normal, on_plane, _, _) in enumerate(truth):
        offset = -normal @ np.asarray(on_plane, float)
        best = max(planes, key=lambda p: abs(p.normal @ normal))
        sign = np.sign(best.normal @ normal)
        angle = np.degrees(np.arccos(min(1.0, abs(best.normal @ normal))))
        assert angle < 1.0, f"plane {k}: normal off by {angle:.2f} deg"
        assert abs(sign * best.offset - offset) < 0.02, f"plane {k}: offset"
        members = set(best.members.tolist())
        assert len(members & set(range(400 * k, 400 * (k + 1)))) > 0.95 * 400
        assert len(members & set(range(1200, 1320))) < 5  # hardly any random outlier


def test_extraction_of_the_same_points_is_reused():
    rng = np.random.default_rng(3)
    points = np.vstack([plane_patch(rng, 300, [5, 0, 5], [1, 0, 0], [0, 0, 1], (10, 8), 0.02),
                        plane_patch(rng, 300, [20, 5, 5], [0, 1, 0], [0, 0, 1], (10, 8), 0.02)])
    options = AssignmentOptions()
    first = extract_planes(points, options)
    again = extract_planes(points + 1e-12, options)  # a similarity and back: ~1e-13 m
    assert len(first) == 2 and all(a is b for a, b in zip(first, again))
    moved = points.copy()
    moved[0, 2] += 1e-6
    recomputed = extract_planes(moved, options)
    assert not any(a is b for a, b in zip(first, recomputed))
    # an explicit generator is never served from the last extraction
    fresh = extract_planes(points, options, rng=np.random.default_rng(options.random_seed))
    assert not any(a is b for a, b in zip(first, fresh))
    for a, b in zip(first, fresh):
        np.testing.assert_array_equal(a.members, b.members)


def test_extraction_follows_moved_points_while_its_planes_hold(monkeypatch):
    """Between refine's iterations the tie points move by centimetres: the segmentation is kept
    and its planes follow the points (here a similarity of 2 deg and 3 m plus 5 cm of
    non-rigid noise); a plane whose points no longer lie on one plane is extracted anew."""
    import colmap_citymodel.assign.indirect as indirect

    rng = np.random.default_rng(5)
    points = np.vstack([plane_patch(rng, 300, [5, 0, 5], [1, 0, 0], [0, 0, 1], (10, 8), 0.02),
                        plane_patch(rng, 300, [20, 5, 5], [0, 1, 0], [0, 0, 1], (10, 8), 0.02)])
    options = AssignmentOptions()
    calls = []
    real = indirect._extract_planes
    monkeypatch.setattr(indirect, "_extract_planes", lambda *a: calls.append(1) or real(*a))
    ids = np.arange(len(points)) + 7
    first = extract_planes(points, options, point_ids=ids)
    angle = np.radians(2.0)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0],
                         [0, 0, 1]])
    shift = np.array([3.0, -1.0, 0.5])
    moved = 1.001 * points @ rotation.T + shift + rng.normal(0, 0.05, points.shape)
    followed = extract_planes(moved, options, point_ids=ids)
    assert len(calls) == 1 and len(followed) == len(first) == 2
    for a, b in zip(first, followed):
        np.testing.assert_array_equal(a.members, b.members)
        assert abs(abs(b.normal @ (rotation @ a.normal)) - 1) < 1e-3
        assert np.sqrt(np.mean((moved[b.members] @ b.normal + b.offset) ** 2)) < 0.08
        assert abs(b.normal @ b.centroid + b.offset) < 1e-9
        np.testing.assert_allclose(b.centroid, 1.001 * rotation @ a.centroid + shift,
                                   atol=0.05)
    # Half of the first facade pushed 1 m out of its plane: no longer one plane.
    folded = points.copy()
    folded[:150, 1] += 1.0
    extract_planes(folded, options, point_ids=ids)
    assert len(calls) == 2
    # Other tie points (or none named): never taken for the last ones moved.
    extract_planes(moved, options, point_ids=ids + 1)
    extract_planes(points, options)
    assert len(calls) == 4
    every_time = AssignmentOptions(msac_keep_segmentation=False)
    extract_planes(points, every_time, point_ids=ids)
    extract_planes(points + [0.0, 0.0, 0.001], every_time, point_ids=ids)
    assert len(calls) == 6


def test_matching_rejects_rotated_distant_and_outside_planes():
    store = box_store()
    wall = face_with_normal(store, [0, -1, 0])
    options = AssignmentOptions()
    r = np.radians(20)

    def plane(normal, centroid):
        normal, centroid = unit(normal), np.asarray(centroid, float)
        return ExtractedPlane(normal, float(-normal @ centroid), np.zeros(0, np.int64), centroid)

    planes = [
        plane([0, 1, 0], [5, -0.2, 5]),  # the wall (normal sign flipped: either sign matches)
        plane([np.sin(r), -np.cos(r), 0], [5, -0.2, 5]),  # rotated 20 deg
        plane([0, -1, 0], [5, -5.0, 5]),  # parallel, 5 m in front
        plane([0, -1, 0], [14, -0.2, 5]),  # beside the wall: centroid outside its polygon
        plane([0, -1, 0], [5, -2.5, 5]),  # 2.5 m in front
    ]
    np.testing.assert_array_equal(match_planes(planes, store, 3.0, options),
                                  [wall, -1, -1, -1, wall])
    # the threshold is the caller's: at 0.4 m the plane 2.5 m away no longer matches
    np.testing.assert_array_equal(match_planes(planes, store, 0.4, options),
                                  [wall, -1, -1, -1, -1])


def test_msac_assigns_wall_points_and_rejects_rotated_or_distant_point_sets():
    rng = np.random.default_rng(12)
    store = box_store()
    wall = face_with_normal(store, [0, -1, 0])
    good = plane_patch(rng, 150, [5, -0.05, 5], [1, 0, 0], [0, 0, 1], (8, 8), 0.03)
    r = np.radians(20)  # a facade rotated by 20 deg about the vertical, in front of the box
    rotated = plane_patch(rng, 150, [5, -6, 5], [np.cos(r), np.sin(r), 0], [0, 0, 1], (8, 8),
                          0.03)
    distant = plane_patch(rng, 150, [5, -5, 5], [1, 0, 0], [0, 0, 1], (8, 8), 0.03)
    for other in (rotated, distant):
        points = np.vstack([good, other + [0, -12, 0] if other is distant else other])
        result = assign_msac(points, np.arange(len(points)), store, 3.0, AssignmentOptions())
        np.testing.assert_array_equal(result.face_index[:150], wall)
        assert not np.any(result.assigned[150:])
        assert result.method == "msac"
    # only the distant set: its plane is 5 m from the wall, beyond a 3 m threshold
    result = assign_msac(distant, np.arange(150), store, 3.0, AssignmentOptions())
    assert result.num_assigned == 0
    assert result.rejected_faces == {"unmatched_extracted_planes": 1}


def test_msac_drops_points_projecting_outside_the_model_polygon():
    rng = np.random.default_rng(13)
    store = box_store()
    wall = face_with_normal(store, [0, -1, 0])
    # one facade of points 14 m wide, the model wall is 10 m: 2 m overhang on each side
    points = plane_patch(rng, 400, [5, -0.05, 5], [1, 0, 0], [0, 0, 1], (14, 8), 0.03)
    result = assign_msac(points, np.arange(400), store, 1.0, AssignmentOptions())
    inside = (points[:, 0] > 0.1) & (points[:, 0] < 9.9)
    outside = (points[:, 0] < -0.1) | (points[:, 0] > 10.1)
    assert np.all(result.face_index[inside] == wall)
    assert not np.any(result.assigned[outside])


def test_alpha_components_split_coplanar_facades_and_bridge_windows():
    rng = np.random.default_rng(14)
    a = rng.uniform([0, 0], [10, 8], (300, 2))
    b = rng.uniform([15, 0], [25, 8], (300, 2))  # 5 m gap
    labels = alpha_components(np.vstack([a, b]), 1.0)
    assert len(np.unique(labels[:300])) == 1 and len(np.unique(labels[300:])) == 1
    assert labels[0] != labels[300]
    # a 1.2 m wide window column in one facade is bridged (gap below two radii)
    c = rng.uniform([0, 0], [10, 8], (600, 2))
    c = c[(c[:, 0] < 4.4) | (c[:, 0] > 5.6)]
    assert len(np.unique(alpha_components(c, 1.0))) == 1
    # a sparse pair 1.9 m apart is one component, 3 m apart two (radius 1 m: link 2 m)
    assert len(np.unique(alpha_components(np.array([[0, 0], [1.9, 0.0]]), 1.0))) == 1
    assert len(np.unique(alpha_components(np.array([[0, 0], [3.0, 0.0]]), 1.0))) == 2


def cell_graph_components(uv, radius):
    """alpha_components' definition, directly: cells of side r/4, two occupied cells linked when
    their closest distance is at most 2r (all pairs compared), components numbered in the order
    of their first cell by row, then column."""
    from scipy.sparse.csgraph import connected_components

    cell = radius / 4.0
    ij = np.floor((uv - uv.min(0)) / cell).astype(np.int64)
    cells, inverse = np.unique(ij, axis=0, return_inverse=True)  # rows sorted by (i, j)
    d = np.abs(cells[:, None, :] - cells[None, :, :])
    gap = cell * np.hypot(np.maximum(d[..., 0] - 1, 0), np.maximum(d[..., 1] - 1, 0))
    _, labels = connected_components(gap <= 2.0 * radius, directed=False)
    return labels[inverse.ravel()]


@pytest.mark.parametrize("seed", range(6))
def test_alpha_components_equal_the_cell_graph_definition(seed):
    # clusters, strips and sparse points at several radii: the block-wise computation gives the
    # components (and their numbering) of the cell graph
    rng = np.random.default_rng(seed)
    for _ in range(40):
        n = int(rng.integers(1, 300))
        centres = rng.uniform(0, rng.choice([2.0, 10.0, 40.0]), (int(rng.integers(1, 6)), 2))
        uv = centres[rng.integers(0, len(centres), n)] \
            + rng.normal(0, rng.choice([0.1, 0.6, 1.5]), (n, 2)) * rng.uniform(0.2, 1.0, 2)
        if rng.random() < 0.3:
            uv = np.round(uv * 8) / 8  # on cell borders
        radius = float(rng.choice([1.0, 0.3, 0.7, 2.5]))
        np.testing.assert_array_equal(alpha_components(uv, radius),
                                      cell_graph_components(uv, radius))


def test_extraction_separates_coplanar_facades_five_metres_apart():
    rng = np.random.default_rng(15)
    left = plane_patch(rng, 300, [5, 0, 5], [1, 0, 0], [0, 0, 1], (10, 8), 0.02)
    right = plane_patch(rng, 200, [20, 0, 5], [1, 0, 0], [0, 0, 1], (10, 8), 0.02)
    planes = extract_planes(np.vstack([left, right]), AssignmentOptions())
    assert len(planes) == 2
    members = sorted((set(p.members.tolist()) for p in planes), key=len, reverse=True)
    assert members[0] == set(range(300)) and members[1] == set(range(300, 500))
    assert abs(planes[0].centroid[0] - 5) < 1.0 and abs(planes[1].centroid[0] - 20) < 1.0


def roi_scene(rng):
    """In front of the y = 0 wall: 60 points on the wall and 200 on a plane tilted 25 deg from
    it that meets it at z = 1 (all in the wall's ROI at 3 m)."""
    wall = plane_patch(rng, 60, [5, -0.05, 4], [1, 0, 0], [0, 0, 1], (4, 6), 0.02)
    t = np.radians(25)
    tilted = plane_patch(rng, 200, [5, -3 * np.tan(t), 4], [1, 0, 0], [0, -np.sin(t), np.cos(t)],
                         (4, 6 / np.cos(t)), 0.02)
    return np.vstack([wall, tilted])


def test_roi_msac_respects_the_normal_constraint():
    rng = np.random.default_rng(16)
    store = box_store()
    wall = face_with_normal(store, [0, -1, 0])
    points = roi_scene(rng)
    ids = np.arange(len(points))
    result = assign_roi_msac(points, ids, store, 3.0, AssignmentOptions())
    assert result.method == "roi_msac"
    assert np.all(result.face_index[:60] == wall)
    # only tilted points near the intersection are inliers (0.4 m from the fitted plane, which
    # the tilted inliers lean a little)
    tilted_assigned = result.assigned[60:]
    assert np.all(np.abs(points[60:][tilted_assigned, 1]) < 0.6)
    assert tilted_assigned.sum() < 60
    np.testing.assert_allclose(result.distance[:60], points[:60] @ store.normals[wall]
                               + store.offsets[wall])
    # without the constraint (90 deg) the larger tilted plane wins the ROI
    free = assign_roi_msac(points, ids, store, 3.0, AssignmentOptions(max_normal_angle=90.0))
    assert free.assigned[60:].sum() > 150
    assert free.assigned[:60].sum() < 30


def test_weighted_sampling_prefers_points_of_high_quality():
    rng = np.random.default_rng(17)
    store = box_store()
    wall = face_with_normal(store, [0, -1, 0])
    good = plane_patch(rng, 80, [5, -0.05, 5], [1, 0, 0], [0, 0, 1], (8, 8), 0.02)
    poor = plane_patch(rng, 160, [5, -2.5, 5], [1, 0, 0], [0, 0, 1], (8, 8), 0.02)
    points = np.vstack([good, poor])
    ids = np.arange(len(points))
    weights = np.r_[np.ones(80), np.full(160, 1e-6)]
    plain = assign(points, ids, store, 3.0, AssignmentOptions(method="roi_msac"),
                   weights=weights)  # weights given, but weighted_sampling is off
    assert plain.assigned[80:].all() and not plain.assigned[:80].any()
    options = AssignmentOptions(method="roi_msac", weighted_sampling=True)
    weighted = assign(points, ids, store, 3.0, options, weights=weights)
    assert np.all(weighted.face_index[:80] == wall) and not weighted.assigned[80:].any()
    # (b) as well: the poor plane is never sampled, the good one matches the wall (a few of its
    # sparse points fail the point normal test)
    options = AssignmentOptions(method="msac", weighted_sampling=True)
    weighted = assign(points, ids, store, 3.0, options, weights=weights)
    assert np.count_nonzero(weighted.face_index[:80] == wall) > 70
    assert not weighted.assigned[80:].any()
    options.weighted_sampling = False  # unweighted, the poor plane is extracted and matched too
    assert assign(points, ids, store, 3.0, options, weights=weights).assigned[80:].mean() > 0.9
    # direct assignment takes the keyword and ignores it
    direct = assign(points, ids, store, 3.0, AssignmentOptions(method="direct"), weights=weights)
    assert direct.num_assigned == 240


def clean_building(rng):
    rings, semantics = building_polygons(0.0, 14.0, 0.0, 11.0, 10.0, 14.0, 0.0)
    flat, flat_semantics = building_polygons(20.0, 32.0, 0.0, 10.0, 8.0, 8.0, 0.0)
    rings, semantics = rings + flat, semantics + flat_semantics
    store = store_from_polygons(rings, semantics=semantics, origin=np.zeros(3))
    seen = [i for i, s in enumerate(semantics) if s != "GroundSurface"]
    points, face = sample_surface_points([rings[i] for i in seen], 0.7, rng)
    face = np.array(seen)[face]
    points += store.normals[face] * rng.normal(0, 0.02, len(points))[:, None]
    return store, points, face


def test_three_methods_agree_on_a_clean_building():
    rng = np.random.default_rng(18)
    store, points, truth = clean_building(rng)
    ids = np.arange(len(points))
    results = {m: assign(points, ids, store, 1.0, AssignmentOptions(method=m))
               for m in ("direct", "msac", "roi_msac")}
    for method, result in results.items():
        assert result.method == method
        assert result.num_assigned > 0.85 * len(points), method
        assert result.num_faces == len(np.unique(truth)), method
        correct = result.face_index[result.assigned] == truth[result.assigned]
        assert correct.mean() > 0.98, method  # points within ~0.1 m of an edge are ambiguous
    both = results["msac"].assigned & results["roi_msac"].assigned & results["direct"].assigned
    agree = (results["msac"].face_index[both] == results["direct"].face_index[both]) \
        & (results["roi_msac"].face_index[both] == results["direct"].face_index[both])
    assert agree.mean() > 0.98


def test_auto_uses_an_indirect_method_while_the_threshold_is_large(caplog):
    rng = np.random.default_rng(19)
    store, points, _ = clean_building(rng)
    ids = np.arange(len(points))
    options = AssignmentOptions(method="auto")
    with caplog.at_level(logging.INFO, logger="colmap_citymodel.assign"):
        far = assign(points, ids, store, 2.5, options)
        near = assign(points, ids, store, 0.4, options)
    assert far.method == "roi_msac" and near.method == "direct"
    assert "auto: roi_msac" in caplog.text and "auto: direct" in caplog.text
    options.auto_indirect_method = "msac"
    assert assign(points, ids, store, 2.5, options).method == "msac"


@pytest.mark.parametrize("method", ["msac", "roi_msac"])
def test_degenerate_inputs_assign_nothing(method):
    store = box_store()
    options = AssignmentOptions(method=method)
    line = np.column_stack([np.linspace(1, 9, 40), np.full(40, -0.05), np.full(40, 5.0)])
    for points in (np.zeros((0, 3)), line[:2], line, np.tile([5, -0.05, 5.0], (40, 1))):
        result = assign(points, np.arange(len(points)), store, 2.0, options)
        assert result.num_assigned == 0 and len(result.face_index) == len(points)


def test_threshold_upper_limit_depends_on_the_method():
    rng = np.random.default_rng(20)
    store = box_store()
    points = plane_patch(rng, 60, [5, -1.5, 5], [1, 0, 0], [0, 0, 1], (8, 8), 0.3)
    ids = np.arange(60)
    for method, upper in (("direct", 2.0), ("roi_msac", 3.0), ("msac", 3.0), ("auto", 3.0)):
        options = AssignmentOptions(method=method)
        assert initial_threshold(options) == upper
        first = assign(points, ids, store, upper, options)
        assert first.num_assigned > 0, method
        # 3.5 x ~1.5 m is above both limits: the schedule stays at the method's upper limit
        assert next_threshold(first, points, store, options, sigma=0.2) == upper


def test_options_file_selects_the_method():
    options = RefineOptions().mergedict({"assignment": {"method": "roi_msac",
                                                        "weighted_sampling": True}})
    assert options.assignment.method == "roi_msac" and options.assignment.weighted_sampling
    assert RefineOptions().assignment.method == "auto"


def test_point_quality_weights_from_track_length_and_angle():
    scene = make_street_scene(StreetSceneOptions(num_stations=4, point_spacing=3.0))
    rec = scene.truth
    ids = np.array(sorted(rec.point3D_ids()), np.int64)
    weights = point_quality_weights(rec, ids)
    assert weights.shape == ids.shape and np.all(weights > 0)
    assert np.median(weights) == pytest.approx(1.0)
    expected = []
    for pid in ids:  # every pair of rays, one point at a time
        point = rec.point3D(int(pid))
        centres = np.array([rec.image(e.image_id).projection_center()
                            for e in point.track.elements])
        rays = point.xyz - centres
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        angle = np.arccos(np.clip((rays @ rays.T).min(), -1, 1))
        expected.append(np.sqrt(len(rays)) * np.sin(min(angle, np.pi / 2)))
    expected = np.array(expected)
    np.testing.assert_allclose(weights, expected / np.median(expected), rtol=1e-9)
