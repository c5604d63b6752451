"""The extension's TriangleDistance (distance from points to the city model's surfaces, up to a
radius): against a brute-force distance to every triangle, against Open3D's RaycastingScene on a
real CityGML tile, and SurfaceDistance with it."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_citymodel import _ext
from colmap_citymodel.align.coarse import SurfaceDistance
from data_paths import CITYGML

BERLIN = CITYGML / "berlin" / "3920_5820.gml"


@pytest.fixture(scope="module")
def core():
    return _ext.load_core()


def segment_distances(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((points - a) @ ab) / max(ab @ ab, 1e-300), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def brute_force(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Distance to the nearest triangle: to its plane where the foot lies inside, else to the
    nearest of its edges."""
    best = np.full(len(points), np.inf)
    for i, j, k in triangles:
        a, b, c = vertices[i], vertices[j], vertices[k]
        normal = np.cross(b - a, c - a)
        normal /= np.linalg.norm(normal)
        height = (points - a) @ normal
        foot = points - height[:, None] * normal
        inside = np.ones(len(points), bool)
        for p, q in ((a, b), (b, c), (c, a)):
            inside &= (np.cross(q - p, foot - p) @ normal) >= 0
        edges = np.minimum.reduce([segment_distances(points, a, b),
                                   segment_distances(points, b, c),
                                   segment_distances(points, c, a)])
        best = np.minimum(best, np.where(inside, np.abs(height), edges))
    return best


def test_distances_equal_brute_force_below_the_reach(core):
    rng = np.random.default_rng(3)
    vertices = rng.uniform(-10.0, 10.0, (60, 3))
    triangles = rng.integers(0, 60, (40, 3))
    triangles = triangles[(triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2])
                          & (triangles[:, 0] != triangles[:, 2])]
    points = rng.uniform(-14.0, 14.0, (4000, 3))
    exact = brute_force(points, vertices, triangles)
    for reach in (0.5, 2.0, 50.0):
        distance = core.TriangleDistance(vertices, triangles, reach)
        got = distance(points)
        assert distance.reach == reach
        np.testing.assert_allclose(got, np.minimum(exact, reach), rtol=0, atol=1e-9)
        assert np.any(got < reach) and (reach > 40 or np.any(got == reach))
    # The same on one thread, and with a grid whose cell limit makes its cells larger.
    np.testing.assert_allclose(core.TriangleDistance(vertices, triangles, 2.0)(points, threads=1),
                               np.minimum(exact, 2.0), rtol=0, atol=1e-9)
    np.testing.assert_allclose(core.TriangleDistance(vertices, triangles, 0.5, max_cells=8)(points),
                               np.minimum(exact, 0.5), rtol=0, atol=1e-9)


def test_points_far_away_or_without_triangles_get_the_reach(core):
    vertices = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0]])
    distance = core.TriangleDistance(vertices, np.array([[0, 1, 2]]), 1.5)
    got = distance(np.array([[1.0, 1, 0.25], [1.0, 1, -1.0], [500.0, 0, 0], [1.0, 1, 1e9]]))
    np.testing.assert_allclose(got, [0.25, 1.0, 1.5, 1.5])
    empty = core.TriangleDistance(np.zeros((0, 3)), np.zeros((0, 3), np.int64), 1.0)
    np.testing.assert_array_equal(empty(np.zeros((3, 3))), [1.0, 1.0, 1.0])


def test_bad_input_is_refused(core):
    vertices = np.eye(3)
    with pytest.raises(ValueError, match="reach"):
        core.TriangleDistance(vertices, np.array([[0, 1, 2]]), 0.0)
    with pytest.raises(ValueError, match="index"):
        core.TriangleDistance(vertices, np.array([[0, 1, 3]]), 1.0)
    with pytest.raises(ValueError, match="shape"):
        core.TriangleDistance(vertices, np.array([[0, 1, 2]]), 1.0)(np.zeros((4, 2)))


def test_surface_distance_of_a_real_tile_equals_open3d_below_the_radius():
    """SurfaceDistance of an official LoD2 tile against Open3D's RaycastingScene of the same
    triangles (float32 there: agreement to its precision at the tile's local coordinates)."""
    import open3d as o3d

    from colmap_citymodel.citymodel.read import read_city_model

    store = read_city_model(BERLIN)
    surface = SurfaceDistance(store)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(surface.vertices.astype(np.float32)),
                        o3d.core.Tensor(surface.triangles.astype(np.uint32)))
    rng = np.random.default_rng(0)
    low, high = surface.vertices.min(0), surface.vertices.max(0)
    on = rng.integers(0, len(surface.triangles), 20000)
    weights = rng.dirichlet([1.0, 1.0, 1.0], 20000)
    near = np.einsum("nk,nkd->nd", weights, surface.vertices[surface.triangles[on]])
    points = np.vstack([rng.uniform(low - 5, high + 5, (20000, 3)),
                        near + rng.normal(0.0, 0.5, near.shape)])
    reference = scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()
    scale = float(np.abs(surface.vertices).max())
    for radius in (0.45, 2.0):
        got = surface(points, radius)
        assert got.shape == (len(points),) and np.all(got <= radius)
        np.testing.assert_allclose(got, np.minimum(reference, radius), rtol=0,
                                   atol=1e-6 * scale + 1e-5)
        assert np.count_nonzero(got < radius) > 5000


def test_coarse_grid_shares_are_the_same_for_whole_and_any_shifts_and_near_the_exact_share():
    """The translation search's coarse level on an official LoD2 tile: shifts of whole and half
    grid cells (one cell index per point and fraction) give the shares that rounding each
    shifted point gives, and both are close to the exact smooth share of the shifted points."""
    from colmap_citymodel.align.coarse import _grid_scores_builder, near_share, near_weights
    from colmap_citymodel.citymodel.read import read_city_model

    store = read_city_model(BERLIN)
    surface = SurfaceDistance(store)
    rng = np.random.default_rng(2)
    on = rng.integers(0, len(surface.triangles), 2000)
    weights = rng.dirichlet([1.0, 1.0, 1.0], 2000)
    points = np.einsum("nk,nkd->nd", weights, surface.vertices[surface.triangles[on]])
    points += rng.normal(0.0, 0.3, points.shape) + np.array([1.2, -0.7, 2.1])  # off the model
    high = np.array([6.0, 6.0, 9.0])
    shares = _grid_scores_builder(points, np.full(len(points), 1.0 / len(points)), surface,
                                  -high, high, 1.0, 2.0, lambda d: near_weights(d, 2.0))
    axes = [np.arange(-h, h + 1e-9, 1.5) for h in high]
    shifts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # whole and half
    fast = shares(shifts)
    # Shifts with many different fractions of a cell take the path that rounds each point.
    odd = rng.uniform(-high, high, (40, 3))
    general = shares(np.vstack([shifts, odd]))
    np.testing.assert_array_equal(fast, general[:len(shifts)])
    exact = np.array([near_share(surface(points + s, 2.0), 2.0) for s in shifts[::50]])
    # nearest-cell lookups (cells of 1 m): within a few points in a hundred of the exact share
    assert np.max(np.abs(fast[::50] - exact)) < 0.05
    best = shifts[int(np.argmax(fast))]
    np.testing.assert_allclose(best, [-1.5, 0.0, -1.5], atol=1.5)  # back onto the model
