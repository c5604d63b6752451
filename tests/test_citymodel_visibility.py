"""Surfaces inside the city's volume (citymodel.visibility): walls shared by two solids and the
part of a tall wall that a lower neighbour covers take no tie points; the rest of the city does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from colmap_citymodel.align.coarse import SurfaceDistance
from colmap_citymodel.assign.direct import assign_direct
from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.citymodel.read import read_city_model
from colmap_citymodel.citymodel.visibility import visibility, visible_triangles
from colmap_citymodel.options import AssignmentOptions

BERLIN = Path(__file__).parent / "data" / "citygml" / "berlin" / "3910_5819.gml"


def box(x0, y0, x1, y1, height):
    """Ground, roof and four walls of a box, rings counter-clockwise seen from outside."""
    g = [(x0, y0, 0), (x0, y1, 0), (x1, y1, 0), (x1, y0, 0)]
    r = [(x0, y0, height), (x1, y0, height), (x1, y1, height), (x0, y1, height)]
    walls = [
        [(x0, y0, 0), (x1, y0, 0), (x1, y0, height), (x0, y0, height)],  # -y
        [(x1, y0, 0), (x1, y1, 0), (x1, y1, height), (x1, y0, height)],  # +x
        [(x1, y1, 0), (x0, y1, 0), (x0, y1, height), (x1, y1, height)],  # +y
        [(x0, y1, 0), (x0, y0, 0), (x0, y0, height), (x0, y1, height)],  # -x
    ]
    rings = [g, r, *walls]
    return ([np.array(ring, float) for ring in rings],
            ["GroundSurface", "RoofSurface"] + ["WallSurface"] * 4)


@pytest.fixture(scope="module")
def tower_and_annex():
    """A 20 m tower (x 0..10) and an 8 m annex (x 10..20) built against its +x wall: the
    annex's -x wall lies inside the city as a whole, the tower's +x wall up to 8 m."""
    tower, sem_t = box(0, 0, 10, 10, 20.0)
    annex, sem_a = box(10, 0, 20, 10, 8.0)
    store = store_from_polygons(tower + annex, semantics=sem_t + sem_a, origin=np.zeros(3),
                                building_ids=["tower"] * 6 + ["annex"] * 6)
    return store


def face_at(store, x=None, y=None, zmax=None):
    """The wall whose centroid has this x (or y) and whose top is `zmax`."""
    for f in range(store.num_faces):
        if store.faces[f].semantic != "WallSurface":
            continue
        c = store.centroids[f]
        top = store.vertices[store.face_vertex_ids(f), 2].max()
        if ((x is None or abs(c[0] - x) < 1e-6) and (y is None or abs(c[1] - y) < 1e-6)
                and (zmax is None or abs(top - zmax) < 1e-6)):
            return f
    raise AssertionError("no such wall")


def test_shared_wall_hidden_and_covered_part_of_tall_wall(tower_and_annex):
    store = tower_and_annex
    vis = visibility(store)
    annex_inner = face_at(store, x=10.0, zmax=8.0)
    tower_inner = face_at(store, x=10.0, zmax=20.0)
    tower_outer = face_at(store, x=0.0)
    annex_outer = face_at(store, x=20.0)
    assert vis.hidden[annex_inner]
    assert vis.partial[tower_inner]
    assert vis.hidden_share[tower_inner] == pytest.approx(8.0 / 20.0, abs=0.06)
    assert vis.hidden_share[tower_outer] == 0 and vis.hidden_share[annex_outer] == 0
    # The front walls along y = 0 are visible over their whole height.
    for f in range(store.num_faces):
        if store.faces[f].semantic == "WallSurface" and abs(store.centroids[f][1]) < 1e-6:
            assert vis.hidden_share[f] == 0


def test_assignment_takes_only_visible_surfaces(tower_and_annex):
    store = tower_and_annex
    tower_inner = face_at(store, x=10.0, zmax=20.0)
    points = np.array([
        [10.1, 5.0, 15.0],  # on the tower's +x wall above the annex: visible
        [10.1, 5.0, 4.0],   # between tower and annex, below the annex's roof: hidden
        [-0.2, 5.0, 10.0],  # on the tower's outer -x wall
        [15.0, -0.1, 4.0],  # on the annex's front wall
    ])
    options = AssignmentOptions(min_points_per_plane=1, planarity_threshold=-1.0,
                                point_normal_angle=180.0)
    a = assign_direct(points, np.arange(4), store, 1.0, options)
    assert a.face_index[0] == tower_inner
    assert a.face_index[1] == -1
    assert a.face_index[2] == face_at(store, x=0.0)
    assert a.face_index[3] == face_at(store, y=0.0, zmax=8.0)


def test_surface_distance_ignores_hidden_parts(tower_and_annex):
    store = tower_and_annex
    surface = SurfaceDistance(store)
    d = surface(np.array([[10.0, 5.0, 4.0], [10.0, 5.0, 15.0], [-0.3, 5.0, 10.0]]), 10.0)
    # The hidden point's nearest visible surface is the annex's roof (4 m above it) or its
    # outer walls (5 m aside).
    assert d[0] == pytest.approx(4.0, abs=0.05)
    assert d[1] == pytest.approx(0.0, abs=1e-6)
    assert d[2] == pytest.approx(0.3, abs=1e-6)
    vertices, triangles, owner = visible_triangles(store)
    tower_inner = face_at(store, x=10.0, zmax=20.0)
    part = triangles[owner == tower_inner]
    e1 = vertices[part[:, 1]] - vertices[part[:, 0]]
    e2 = vertices[part[:, 2]] - vertices[part[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum()
    assert area == pytest.approx(10.0 * 12.0, rel=0.06)  # above the annex only
    assert vertices[part].reshape(-1, 3)[:, 2].min() >= 8.0 - 0.51


def test_real_tile_tower_with_its_lower_part():
    """Berlin 3910_5819: a tower (roof 83.5 m above the tile's origin) stands beside the
    77.5 m main part of the same building; the two parts' coincident walls are inner walls."""
    store = read_city_model(BERLIN)
    vis = visibility(store)
    by_id = {store.faces[f].gml_id: f for f in range(store.num_faces)}
    for inner in ("GEOM_634164", "GEOM_634166"):  # the main part's walls against the tower
        assert vis.hidden[by_id[inner]], inner
    for tower in ("GEOM_634183", "GEOM_634185"):  # the tower's walls: visible above 77.5 m
        assert vis.partial[by_id[tower]], tower
        assert 0.8 < vis.hidden_share[by_id[tower]] < 0.97
    assert vis.hidden_share[by_id["GEOM_634177"]] == 0  # the main part's outer +x facade
    summary = vis.summary()
    assert summary["hidden_faces"] > 50 and summary["partly_hidden_faces"] > 20


def test_facade_points_pushed_onto_an_inner_wall_are_found_on_the_facade():
    """A block whose facade points ended 7.5 m deep in the building, on the wall between the
    main part and the tower (Berlin 3910_5819), is moved back onto the facade by the coarse
    search: the inner wall is no surface a tie point can lie on."""
    from colmap_citymodel.align.coarse import search_translation

    store = read_city_model(BERLIN)
    by_id = {store.faces[f].gml_id: f for f in range(store.num_faces)}
    facade, inner = by_id["GEOM_634177"], by_id["GEOM_634164"]  # x = 447 and x = 439.5
    rng = np.random.default_rng(3)
    R, c = store.rotations[facade], store.centroids[facade]
    # Points on the facade where the inner wall stands behind it (its y and z range).
    ys = rng.uniform(12.0, 34.0, 3000)
    zs = rng.uniform(8.0, 70.0, 3000)
    xs = c[0] + (ys - c[1]) * (-store.normals[facade][1] / store.normals[facade][0])
    points = np.column_stack([xs, ys, zs]) + rng.normal(0, 0.03, (3000, 3))
    assert np.abs(points @ store.normals[facade] + store.offsets[facade]).max() < 0.2
    shift = store.centroids[inner] - c
    shift = (shift @ store.normals[facade]) * store.normals[facade]  # onto the inner wall
    assert 7.0 < np.linalg.norm(shift) < 8.0
    moved = points + shift
    assert np.median(np.abs(moved @ store.normals[inner] + store.offsets[inner])) < 0.3
    from colmap_citymodel.errormodel.model import placement_score
    from colmap_citymodel.options import AdjustmentOptions

    score = placement_score(SurfaceDistance(store), moved, None, None, AdjustmentOptions())
    result = search_translation(score, np.array([3.0, 3.0, 5.0]))
    # Back along the facade's normal (along the facade, a wall fixes nothing).
    normal = store.normals[facade]
    assert result.shift @ normal == pytest.approx(-shift @ normal, abs=0.5)
