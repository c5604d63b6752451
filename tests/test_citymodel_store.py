"""Plane frame (Unger eq. 2-4), vertex merging, degenerate/non-planar handling and the spatial
queries of the plane store, on small synthetic scenes with known answers."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from colmap_citymodel.citymodel.raw_model import CRSInfo, RawCityModel, RawPolygon
from colmap_citymodel.citymodel.store import Tolerances
from colmap_citymodel.citymodel.build import build_store, merge_vertices, store_from_polygons

CUBE_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    float,
)
# counter-clockwise seen from outside
CUBE_F = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
CUBE_SEM = ["GroundSurface", "RoofSurface"] + ["WallSurface"] * 4
CUBE_OUT = np.array([[0, 0, -1], [0, 0, 1], [0, -1, 0], [1, 0, 0], [0, 1, 0], [-1, 0, 0]], float)


def cube(origin=(0, 0, 0), size=1.0):
    v = CUBE_V * size + np.asarray(origin, float)
    return [v[f] for f in CUBE_F]


def rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def test_plane_frame_of_tilted_polygon():
    # a 4 x 2 m rectangle (plus an extra vertex) in its own frame, rotated and shifted
    ring2d = np.array([[0, 0], [4, 0], [4, 2], [2, 2.5], [0, 2]], float)
    R_true = rot([1, 2, 0.5], 0.7)
    P = np.c_[ring2d, np.zeros(len(ring2d))] @ R_true.T + [500_000.25, 5_400_000.5, 312.0]
    store = store_from_polygons([P])
    assert store.num_faces == 1
    # origin: floor of the lower bbox corner, coordinates stored locally
    np.testing.assert_array_equal(store.origin, np.floor(P.min(0)))
    assert np.all(store.vertices >= 0) and np.all(store.vertices < 10)
    # P0 = centroid of the vertices (eq. 2-4), in the local frame
    np.testing.assert_allclose(store.to_crs(store.centroids[0]), P.mean(0), atol=1e-9)
    R = store.rotations[0]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    # normal = rotated z axis, outward = counter-clockwise ring seen from the normal side
    np.testing.assert_allclose(store.normals[0], R_true[:, 2], atol=1e-9)
    # eigenvector order: column 0 along the long (4 m) side
    assert abs(R[:, 0] @ R_true[:, 0]) == pytest.approx(1.0, abs=1e-9)
    # eigenvalues of the covariance sorted descending along columns
    X = store.vertices[store.face_vertex_ids(0)]
    M = np.cov(X.T)  # eq. 2-3 (1/(N-1))
    lam = np.diag(R.T @ M @ R)
    assert lam[0] >= lam[1] >= lam[2] and lam[2] == pytest.approx(0, abs=1e-12)
    area_true = 8 + 0.5 * 4 * 0.5
    assert store.areas[0] == pytest.approx(area_true)
    assert store.rms_out_of_plane[0] == pytest.approx(0, abs=1e-9)
    # signed distance through offsets
    x = store.centroids[0] + 0.3 * store.normals[0]
    assert x @ store.normals[0] + store.offsets[0] == pytest.approx(0.3)
    # reversing the ring flips the normal and keeps R right-handed
    rev = store_from_polygons([P[::-1]])
    np.testing.assert_allclose(rev.normals[0], -R_true[:, 2], atol=1e-9)
    assert np.linalg.det(rev.rotations[0]) == pytest.approx(1.0)


def test_cube_normals_outward_and_shared_vertices():
    store = store_from_polygons(cube(), semantics=CUBE_SEM, origin=np.zeros(3))
    assert store.num_faces == 6 and len(store.vertices) == 8
    np.testing.assert_allclose(store.normals, CUBE_OUT, atol=1e-12)
    np.testing.assert_allclose(store.areas, 1.0)
    # every cube corner belongs to exactly 3 faces
    indptr, indices = store.vertex_faces
    assert np.all(np.diff(indptr) == 3)
    for v in range(8):
        for f in indices[indptr[v] : indptr[v + 1]]:
            assert v in store.face_vertex_ids(f)
    np.testing.assert_allclose(store.bbox_local, [[0, 0, 0], [1, 1, 1]])


def test_two_cubes_share_face_vertices():
    store = store_from_polygons(cube() + cube((1, 0, 0)), origin=np.zeros(3))
    # 8 + 8 corners, the 4 on the common face x=1 shared
    assert len(store.vertices) == 12
    # the common face appears twice with opposite orientation (one per solid): same vertex ids
    a = store.faces[3]  # cube 1 face x=1
    b = store.faces[6 + 5]  # cube 2 face x=1 (its x=0 side)
    assert set(a.exterior) == set(b.exterior)
    np.testing.assert_allclose(store.normals[3], -store.normals[11], atol=1e-12)


def test_merge_jitter_1mm_merged_5mm_not():
    # the second cube's corners moved by 0.9 mm / 5 mm in random directions
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(8, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    for step, expected in ((0.0009, 12), (0.005, 16)):
        v2 = CUBE_V + [1, 0, 0] + step * directions
        store = store_from_polygons(cube() + [v2[f] for f in CUBE_F], origin=np.zeros(3))
        assert len(store.vertices) == expected
        if expected == 12:  # the cubes share the 4 corners of their common face
            shared = set(store.faces[3].exterior) & set(store.faces[11].exterior)
            assert len(shared) == 4


def test_merge_exact_millimetre_rounding_in_crs():
    # the tum2twin case: two roundings of the same corner, exactly one unit (1 mm) apart in z,
    # at real coordinate magnitudes (float noise makes the difference 1 mm +- 1e-13)
    a = np.array([[691234.567, 5334567.891, 520.123], [691234.567, 5334567.891, 520.124]])
    merged, index, _ = merge_vertices(a - np.floor(a.min(0)), 0.001)
    assert len(merged) == 1 and index.tolist() == [0, 0]
    b = np.array([[0.0, 0, 0], [0, 0, 0.0011]])
    assert len(merge_vertices(b, 0.001)[0]) == 2


def test_merge_chains_transitively():
    pts = np.array([[0, 0, 0], [0.0008, 0, 0], [0.0016, 0, 0], [5, 5, 5]], float)
    merged, index, extent = merge_vertices(pts, 0.001)
    assert index.tolist() == [0, 0, 0, 1]
    assert extent == pytest.approx(0.0016)
    np.testing.assert_allclose(merged[0], [0.0008, 0, 0])


def test_degenerate_faces_dropped_and_counted():
    polys = cube()
    polys += [
        np.array([[0, 0, 0], [0.0004, 0, 0], [0, 0.0004, 0], [0, 0, 0]], float),  # < 3 distinct
        np.array([[0, 0, 5], [1, 0, 5], [2, 0, 5], [3, 0, 5]], float),  # collinear
        np.array([[0, 0, 7], [1, 0, 7], [1, 0.00005, 7]], float),  # tiny area
    ]
    store = store_from_polygons(polys, origin=np.zeros(3))
    assert store.num_faces == 6
    assert store.num_dropped_degenerate == 3
    assert store.summary()["num_dropped_degenerate"] == 3
    # vertices only used by dropped faces are gone
    assert len(store.vertices) == 8


def test_nonplanar_flagged_and_kept():
    bent = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0.3], [0, 4, 0]], float)
    flat = np.array([[10, 0, 0], [14, 0, 0], [14, 4, 0.02], [10, 4, 0]], float)
    store = store_from_polygons([bent, flat], origin=np.zeros(3))
    assert store.num_faces == 2
    assert store.nonplanar.tolist() == [True, False]
    assert store.rms_out_of_plane[0] > 0.05 > store.rms_out_of_plane[1] > 0
    assert store.summary()["num_nonplanar"] == 1


def test_duplicate_polygon_becomes_one_face_with_thematic_class():
    ring = cube()[1]
    raw = RawCityModel(
        source="mem",
        format="CityGML",
        version="2.0",
        crs=CRSInfo("EPSG:25832", 25832, None, "", True),
        polygons=[
            RawPolygon(ring, semantic="Unknown", building_id="b", gml_id="", from_solid=True),
            RawPolygon(np.roll(ring, 1, axis=0), semantic="RoofSurface", building_id="b",
                       gml_id="p1"),
            RawPolygon(ring + [0, 0, 1], semantic="Unknown", building_id="b", gml_id="p2"),
            RawPolygon(ring + [0, 0, 1], semantic="RoofSurface", building_id="b", gml_id="p2"),
        ],
        building_ids=["b"],
        part_ids=[],
    )
    store = build_store(raw)
    assert store.num_faces == 2
    assert [f.semantic for f in store.faces] == ["RoofSurface", "RoofSurface"]
    assert store.faces[0].gml_id == "p1"
    assert store.num_buildings == 1


def test_reversed_roof_ring_is_oriented_up():
    roof = cube()[1][::-1]  # clockwise from above: ring says "down"
    store = store_from_polygons([roof], semantics=["RoofSurface"], origin=np.zeros(3))
    np.testing.assert_allclose(store.normals[0], [0, 0, 1], atol=1e-12)
    assert any("reversed" in w for w in store.warnings)
    # ring reversed with it, so recomputing planes keeps the orientation
    np.testing.assert_allclose(store.with_vertices(store.vertices).normals[0], [0, 0, 1])


# ---------------------------------------------------------------------------------------------
# queries vs brute force
# ---------------------------------------------------------------------------------------------


def random_scene(rng, n_faces=60, with_holes=True):
    """Random tilted quads/pentagons (some with square holes) in a 30 m box."""
    polys, holes = [], []
    for i in range(n_faces):
        R = rot(rng.normal(size=3), rng.uniform(0, np.pi))
        c = rng.uniform(0, 30, 3)
        w, h = rng.uniform(1, 6, 2)
        ring = np.array([[-w, -h], [w, -h], [w, h], [0, h * 1.3], [-w, h]])
        hs = []
        if with_holes and i % 3 == 0:
            s = min(w, h) * 0.5
            hole = np.array([[-s, -s], [-s, s], [s, s], [s, -s]])
            hs = [np.c_[hole, np.zeros(4)] @ R.T + c]
        polys.append(np.c_[ring, np.zeros(len(ring))] @ R.T + c)
        holes.append(hs)
    return store_from_polygons(polys, holes=holes, origin=np.zeros(3))


def brute_force(store, pts, max_distance, margin):
    """Independent oracle: shapely polygons in each face's 2D frame, every face tested."""
    F = store.num_faces
    d = pts @ store.normals.T + store.offsets  # (P, F)
    inside = np.zeros((len(pts), F), bool)
    for f in range(F):
        R, c = store.rotations[f], store.centroids[f]
        to2 = lambda ids: (store.vertices[ids] - c) @ R[:, :2]  # noqa: E731
        poly = shapely.Polygon(to2(store.faces[f].exterior), [to2(h) for h in store.faces[f].holes])
        uv = (pts - c) @ R[:, :2]
        inside[:, f] = shapely.distance(poly, shapely.points(uv)) <= margin + 1e-12
    ok = inside & (np.abs(d) <= max_distance)
    score = np.where(ok, np.abs(d), np.inf)
    best = np.argmin(score, axis=1)
    has = np.isfinite(score[np.arange(len(pts)), best])
    return np.where(has, best, -1), np.where(has, d[np.arange(len(pts)), best], np.nan), inside


@pytest.mark.parametrize("margin", [0.0, 0.1, 0.5])
def test_closest_faces_matches_brute_force(margin):
    rng = np.random.default_rng(7)
    store = random_scene(rng)
    assert sum(len(f.holes) for f in store.faces) == 20
    # points near faces (on and off the polygons, in holes) and random points
    f = rng.integers(0, store.num_faces, 3000)
    R = store.rotations[f]
    uv = rng.uniform(-7, 7, (3000, 2))
    near = store.centroids[f] + np.einsum("kij,kj->ki", R[:, :, :2], uv)
    near += R[:, :, 2] * rng.normal(0, 0.4, (3000, 1))
    pts = np.vstack([near, rng.uniform(-2, 32, (2000, 3))])
    want_face, want_d, inside = brute_force(store, pts, 1.0, margin)
    got_face, got_d = store.closest_faces(pts, max_distance=1.0, margin=margin, candidates=None)
    assert (want_face >= 0).sum() > 1000  # the test exercises hits, not only misses
    np.testing.assert_array_equal(got_face, want_face)
    np.testing.assert_allclose(got_d, want_d, atol=1e-12)
    # contains_projection agrees with the oracle face by face
    for face in range(0, store.num_faces, 7):
        np.testing.assert_array_equal(
            store.contains_projection(face, pts, margin=margin), inside[:, face]
        )


def test_contains_projection_hole_and_margin():
    outer = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]], float)
    hole = np.array([[4, 4, 0], [4, 6, 0], [6, 6, 0], [6, 4, 0]], float)
    store = store_from_polygons([outer], holes=[[hole]], origin=np.zeros(3))
    assert store.areas[0] == pytest.approx(96.0)
    pts = np.array(
        [[1, 1, 3], [5, 5, -2], [4.05, 5, 0], [10.05, 5, 0], [10.3, 5, 0], [5, 5, 0], [-0.07, -0.07, 1]]
    )
    assert store.contains_projection(0, pts, 0.0).tolist() == [
        True, False, False, False, False, False, False
    ]
    assert store.contains_projection(0, pts, 0.1).tolist() == [
        True, False, True, True, False, False, True
    ]
    face, d = store.closest_faces(pts, max_distance=2.5, margin=0.1)
    assert face.tolist() == [-1, -1, 0, 0, -1, -1, 0]  # [1,1,3] is 3 m away
    np.testing.assert_allclose(d[[2, 3, 6]], [0, 0, 1])


def test_closest_faces_picks_nearest_plane():
    # two parallel floors 1 m apart; a point 0.3 m above the lower one
    lo = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]], float)
    store = store_from_polygons([lo, lo + [0, 0, 1]], origin=np.zeros(3))
    face, d = store.closest_faces(np.array([[2, 2, 0.3], [2, 2, 0.8], [9, 9, 0.5]]), 1.0)
    assert face.tolist() == [0, 1, -1]
    np.testing.assert_allclose(d[:2], [0.3, -0.2])


def test_with_plane_shifts_moves_each_plane_along_its_normal():
    # two parallel floors 1 m apart; the lower one moved 0.4 m up, the upper one 0.1 m down
    lo = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]], float)
    store = store_from_polygons([lo, lo + [0, 0, 1]], origin=np.zeros(3))
    shifted = store.with_plane_shifts(np.array([-0.4, 0.1]))
    points = np.array([[2, 2, 0.3], [2, 2, 0.8], [4.05, 2, 0.45]])
    face, d = shifted.closest_faces(points, 0.2)
    assert face.tolist() == [0, 1, 0]  # the outline (and its margin) stays the face's
    np.testing.assert_allclose(d, [-0.1, -0.1, 0.05])
    np.testing.assert_allclose(shifted.normals, store.normals)
    with pytest.raises(ValueError):
        store.with_plane_shifts(np.zeros(3))


def test_with_vertices_and_subset_bbox():
    store = store_from_polygons(cube() + cube((5, 0, 0)), semantics=CUBE_SEM * 2,
                                origin=np.zeros(3), building_ids=["a"] * 6 + ["b"] * 6)
    moved = store.with_vertices(store.vertices + [0, 0, 2])
    np.testing.assert_allclose(moved.centroids, store.centroids + [0, 0, 2])
    np.testing.assert_allclose(moved.normals, store.normals)
    # lift one roof corner: the roof plane tilts, the faces keep their vertex indices
    v = store.vertices.copy()
    top = store.faces[1].exterior[0]
    v[top, 2] += 0.5
    tilted = store.with_vertices(v)
    assert tilted.normals[1] @ [0, 0, 1] < 0.999 and tilted.rms_out_of_plane[1] > 0
    assert tilted.faces[1].exterior.tolist() == store.faces[1].exterior.tolist()

    sub = store.subset_bbox([4, -1, -1], [7, 2, 2])
    assert sub.num_faces == 6 and len(sub.vertices) == 8 and sub.num_buildings == 1
    np.testing.assert_allclose(sub.bbox_local, [[5, 0, 0], [6, 1, 1]])
    np.testing.assert_allclose(sub.normals, CUBE_OUT, atol=1e-12)
    face, _ = sub.closest_faces(np.array([[5.5, 0.5, 1.2]]), 0.5)
    assert sub.faces[face[0]].semantic == "RoofSurface"
    assert store.subset_bbox([4, -1], [7, 2]).num_faces == 6  # 2D box


def test_summary_keys_and_crs_roundtrip():
    store = store_from_polygons([p + [690000, 5330000, 500] for p in cube()], semantics=CUBE_SEM)
    s = store.summary()
    for k in ("format", "version", "crs", "num_buildings", "num_parts", "num_faces",
              "num_vertices", "faces_by_class", "bbox", "num_dropped_degenerate",
              "num_nonplanar", "warnings"):
        assert k in s
    assert s["faces_by_class"] == {"GroundSurface": 1, "RoofSurface": 1, "WallSurface": 4}
    np.testing.assert_allclose(s["bbox"], [[690000, 5330000, 500], [690001, 5330001, 501]])
    np.testing.assert_array_equal(store.origin, [690000, 5330000, 500])
    x = np.array([[690000.5, 5330000.25, 500.125]])
    np.testing.assert_array_equal(store.to_crs(store.to_local(x)), x)


def test_tolerances_are_configurable():
    bent = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0.3], [0, 4, 0]], float)
    raw = RawCityModel("m", "CityGML", "2.0", CRSInfo(None, None, None, "", True),
                       [RawPolygon(bent)], [""], [])
    assert build_store(raw).nonplanar[0]
    assert not build_store(raw, nonplanar_tolerance=0.2).nonplanar[0]
    assert build_store(raw, tolerances=Tolerances(min_area=100.0)).num_faces == 0


@pytest.mark.slow
def test_query_speed_1e5_points_1e4_faces():
    """The assignment's budget: 1e5 points against 1e4 faces well under a second."""
    import sys
    import time
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_store_queries import sample_points, synthetic_city

    rng = np.random.default_rng(0)
    store = synthetic_city(10_000, rng)
    pts = sample_points(store, 100_000, rng)
    store.closest_faces(pts[:10], 1.0, 0.1)  # builds the grid
    t = time.perf_counter()
    face, _ = store.closest_faces(pts, 1.0, 0.1)
    elapsed = time.perf_counter() - t
    assert np.count_nonzero(face >= 0) > 30_000
    assert elapsed < 1.0, f"{elapsed:.2f} s"


def test_provenance_maps_every_read_coordinate_to_its_merged_vertex():
    # the second cube's shared corners are 0.9 mm off: merged, yet both values are known
    rng = np.random.default_rng(2)
    jitter = 0.0009 * rng.normal(size=(8, 3)) / np.sqrt(3)
    v2 = CUBE_V + [1, 0, 0] + jitter
    polygons = cube() + [v2[f] for f in CUBE_F]
    store = store_from_polygons(polygons, origin=np.zeros(3))
    prov = store.provenance
    assert prov is not None and len(prov) == 16  # 8 + 8 distinct coordinates, 12 vertices
    for ring in polygons:
        found = prov.vertex_of(ring)
        assert (found >= 0).all()
        # the vertex a coordinate maps to is the merged vertex within the tolerance
        assert np.linalg.norm(store.vertices[found] - ring, axis=1).max() < 0.001
    # both values of a merged corner name one vertex; an unknown value names none
    shared = np.array([[1.0, 0, 0], v2[0]])
    assert prov.vertex_of(shared).tolist() == [prov.vertex_of(shared)[0]] * 2
    assert prov.vertex_of(np.array([[1.0, 0, 0.0005], [1.0, 0, 0], [1.0, 0, 0]])).tolist() \
        == [-1] + [prov.vertex_of(shared)[0]] * 2
    # -0.0 is the value 0.0
    assert prov.vertex_of(np.array([[-0.0, -0.0, -0.0]]))[0] >= 0
    # cropping renumbers the vertices and forgets the coordinates of dropped ones
    sub = store.subset_bbox([1.5, -1], [3, 2])
    kept = sub.provenance.vertex_of(v2[CUBE_F[1]])
    assert (kept >= 0).all()
    np.testing.assert_allclose(sub.vertices[kept], v2[CUBE_F[1]], atol=0.001)
    assert (sub.provenance.vertex_of(CUBE_V[[0, 3]]) == -1).all()
    # moving vertices keeps where they came from
    assert store.with_vertices(store.vertices + 1).provenance is prov


def test_provenance_is_optional():
    raw = RawCityModel("<cube>", "synthetic", "", CRSInfo(None, None, None, "", True),
                       [RawPolygon(exterior=r) for r in cube()], ["b"], [])
    assert build_store(raw, keep_provenance=False).provenance is None
