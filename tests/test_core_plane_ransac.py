"""The extension's segment_plane (RANSAC's dominant plane of a point cloud) and the sequential
plane extraction built on it: known planes recovered from noisy clouds with clutter, the same
result for a seed on any number of threads, the dominant plane Open3D's segment_plane finds, and
clear errors for bad input."""

from __future__ import annotations

import numpy as np
import pytest

from colmap_citymodel import _ext
from colmap_citymodel.align.coarse import point_cloud_planes, wall_points


@pytest.fixture(scope="module")
def core():
    return _ext.load_core()


def street_cloud(seed: int = 0, noise: float = 0.05):
    """A facade (x = 2, 8,000 points), a flat roof (z = 12, 4,000 points) and 3,000 clutter
    points in the box around them, in projected coordinates (UTM-sized numbers)."""
    rng = np.random.default_rng(seed)
    origin = np.array([389_000.0, 5_819_000.0, 40.0])
    wall = np.c_[np.full(8000, 2.0), rng.uniform(0, 40, 8000), rng.uniform(0, 12, 8000)]
    roof = np.c_[rng.uniform(2, 14, 4000), rng.uniform(0, 40, 4000), np.full(4000, 12.0)]
    wall[:, 0] += rng.normal(0, noise, 8000)
    roof[:, 2] += rng.normal(0, noise, 4000)
    clutter = rng.uniform([-10, 0, 0], [14, 40, 20], (3000, 3))
    points = np.vstack([wall, roof, clutter]) + origin
    return points, origin


def test_the_dominant_plane_is_recovered_from_a_noisy_cloud_with_clutter(core):
    points, origin = street_cloud()
    plane, inliers = core.segment_plane(points, 0.3, 500, seed=1)
    normal, offset = plane[:3], plane[3]
    assert abs(np.linalg.norm(normal) - 1.0) < 1e-12
    angle = np.degrees(np.arccos(min(1.0, abs(normal[0]))))
    assert angle < 1.0
    # the facade x = origin_x + 2, in the caller's coordinates: its corners on the plane
    corners = origin + np.array([[2.0, 0, 0], [2.0, 40, 0], [2.0, 0, 12], [2.0, 40, 12]])
    assert np.all(np.abs(corners @ normal + offset) < 0.02)
    # every facade point (noise 5 cm) and the clutter within 0.3 m of it
    expected = np.abs(points[:, 0] - origin[0] - 2.0) < 0.3
    assert np.all(np.diff(inliers) > 0)
    assert abs(len(inliers) - expected.sum()) <= 0.01 * expected.sum()
    assert np.isin(np.arange(8000), inliers).mean() > 0.999


def test_the_same_seed_gives_the_same_plane_on_any_number_of_threads(core):
    points, _ = street_cloud(seed=3)
    one = core.segment_plane(points, 0.3, 500, seed=5, threads=1)
    two = core.segment_plane(points, 0.3, 500, seed=5, threads=2)
    four = core.segment_plane(points, 0.3, 500, seed=5, threads=4)
    for other in (two, four):
        assert np.array_equal(one[0], other[0]) and np.array_equal(one[1], other[1])


def test_sequential_extraction_finds_the_facade_and_the_roof_and_only_the_facade_is_a_wall():
    points, origin = street_cloud(seed=2)
    normals, counts = point_cloud_planes(points)
    assert len(normals) >= 2
    assert np.degrees(np.arccos(min(1.0, abs(normals[0][0])))) < 1.0  # facade first
    assert np.degrees(np.arccos(min(1.0, abs(normals[1][2])))) < 1.0  # then the roof
    assert counts[0] > counts[1] > 3900
    walls = wall_points(points)
    on_facade = np.abs(walls[:, 0] - origin[0] - 2.0) < 0.3
    assert on_facade.mean() > 0.99 and len(walls) >= 8000
    # the same planes on every call (seeded)
    again, counts_again = point_cloud_planes(points)
    assert np.array_equal(normals, again) and np.array_equal(counts, counts_again)


def test_the_dominant_plane_is_the_one_open3d_finds(core):
    o3d = pytest.importorskip("open3d")
    points, origin = street_cloud(seed=4)
    local = points - origin
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(local))
    o3d.utility.random.seed(0)
    model, theirs = cloud.segment_plane(0.3, 3, 500)
    plane, ours = core.segment_plane(local, 0.3, 500, seed=0)
    theirs_normal = np.asarray(model[:3]) / np.linalg.norm(model[:3])
    assert abs(abs(theirs_normal @ plane[:3]) - 1.0) < 1e-4
    assert abs(len(ours) - len(theirs)) <= 0.002 * len(theirs)


def test_no_plane_in_collinear_or_too_few_points_and_errors_for_bad_input(core):
    line = np.c_[np.linspace(0, 10, 50), np.zeros(50), np.zeros(50)]
    plane, inliers = core.segment_plane(line, 0.3, 100)
    assert not np.any(plane) and len(inliers) == 0
    plane, inliers = core.segment_plane(line[:2], 0.3, 100)
    assert not np.any(plane) and len(inliers) == 0
    with pytest.raises(ValueError, match="shape"):
        core.segment_plane(np.zeros((10, 2)), 0.3)
    with pytest.raises(ValueError, match="distance"):
        core.segment_plane(np.zeros((10, 3)), 0.0)
    with pytest.raises(ValueError, match="finite"):
        core.segment_plane(np.full((10, 3), np.nan), 0.3)
    with pytest.raises(ValueError, match="iterations"):
        core.segment_plane(np.zeros((10, 3)), 0.3, 0)
