"""A model face's tilt error in its tie points' weights (AdjustmentOptions.face_tilt_weights,
adjust.faces.tilt_axes / tilt_variances, adjust.problem.tie_point_sigmas): a point far from
its face's centroid, where a tilt of the model moves the surface most, weighs less."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.faces import tilt_axes, tilt_variances
from colmap_citymodel.adjust.problem import (TILT_SIGMA_STEP, HybridProblem, face_sigmas,
                                             tie_point_sigmas)
from colmap_citymodel.assign.assignment import Assignment
from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.options import AdjustmentOptions

SIGMA = 0.2  # the faces' offset sigma (m): each vertex of the model off by about this


def wall(x: float, y0: float, y1: float, z1: float, lean: float = 0.0) -> np.ndarray:
    """A free-standing wall facing -x at x (its foot), from y0 to y1 and 0 to z1 high, its top
    `lean` metres further along +x than its foot."""
    return np.array([[x, y1, 0], [x, y0, 0], [x + lean, y0, z1], [x + lean, y1, z1]], float)


def test_the_tilt_moves_nothing_at_the_centroid_and_most_at_the_rim():
    store = store_from_polygons([wall(0, 0, 20, 10)], origin=np.zeros(3))
    centroid = store.vertices.mean(0)
    corner, edge = store.vertices[0], np.array([0.0, 20.0, 5.0])
    variance = tilt_variances(store, np.zeros(3, np.int64), np.array([centroid, edge, corner]),
                              SIGMA)
    assert variance[0] == pytest.approx(0.0, abs=1e-12)
    # Each vertex off by SIGMA: along the 20 m axis the plane fitted to the four vertices
    # tilts by SIGMA / 20 m, so the middle of the short edge (10 m out) moves SIGMA / 2 ...
    assert np.sqrt(variance[1]) == pytest.approx(SIGMA / 2, rel=1e-6)
    # ... and about the 10 m axis the tilt would be SIGMA / 10 m, more than the farthest
    # vertex off by SIGMA allows (SIGMA / 11.2 m): the corner moves by about SIGMA / sqrt(2).
    radius = np.linalg.norm(corner - centroid)
    expected = (SIGMA / 2) ** 2 + (5.0 * SIGMA / radius) ** 2
    assert variance[2] == pytest.approx(expected, rel=1e-6)
    assert np.linalg.norm(tilt_axes(store, 0, SIGMA), axis=1).max() <= SIGMA / radius + 1e-12


def scene(seed: int = 0):
    """Three walls facing -x along a street and a long wall facing -y: the first 60 m tall,
    seen only along its foot (the bottom 10 m), its model leaning 0.8 deg about its
    centroid (0.35 m behind the true surface there); the two small walls seen only around
    their middles. Returns the model and the tie points on the true surfaces."""
    rng = np.random.default_rng(seed)
    lean = 60.0 * np.tan(np.radians(0.8))
    true_walls = [wall(0, 0, 30, 60), wall(40, 0, 10, 10), wall(80, 0, 10, 10)]
    model_walls = [wall(-lean / 2, 0, 30, 60, lean)] + true_walls[1:]
    long_wall = np.array([[0, -5, 0], [90, -5, 0], [90, -5, 10], [0, -5, 10]], float)
    store = store_from_polygons(model_walls + [long_wall], origin=np.zeros(3))
    points, faces = [], []
    boxes = [([0, 1, 0], [0, 29, 10], 400), ([40, 3, 3], [40, 7, 7], 150),
             ([80, 3, 3], [80, 7, 7], 150), ([5, -5, 0], [85, -5, 10], 300)]
    for face, (low, high, n) in enumerate(boxes):
        points.append(rng.uniform(low, high, (n, 3)))
        faces.append(np.full(n, face))
    points, faces = np.vstack(points), np.concatenate(faces)
    # The tie points' own scatter about their true surface.
    true_normals = np.array([[-1.0, 0, 0]] * 3 + [[0, -1.0, 0]])
    points += true_normals[faces] * rng.normal(0.0, 0.05, (len(points), 1))
    return store, points, faces


def block_shift(store, points, faces, sigmas) -> np.ndarray:
    """The block's horizontal shift (2) that puts its tie points on their model planes, each
    weighted by its sigma (m): weighted least squares of n . (X + t) + d (the walls leave the
    height to others: held)."""
    normals = store.normals[faces]
    distance = np.einsum("ij,ij->i", normals, points) + store.offsets[faces]
    weights = 1.0 / np.asarray(sigmas) ** 2
    design = normals[:, :2]
    return np.linalg.solve((design * weights[:, None]).T @ design,
                           -(design * weights[:, None]).T @ distance)


def test_a_wall_seen_at_its_foot_pulls_the_block_less_with_its_tilt_in_the_weights():
    store, points, faces = scene()
    slots = np.arange(store.num_faces)
    plain = AdjustmentOptions(sigma_dtp=SIGMA)
    tilted = AdjustmentOptions(sigma_dtp=SIGMA, face_tilt_weights=True)
    base = face_sigmas(plain, faces, store.num_faces)
    assert np.allclose(tie_point_sigmas(plain, store, slots, faces, points, base), SIGMA)
    sigmas = tie_point_sigmas(tilted, store, slots, faces, points, base)
    # The truth: the block sits where its points are (no shift); along the street (x) the
    # tall wall's model pulls it towards its lean.
    alike = block_shift(store, points, faces, np.full(len(points), SIGMA))
    weighted = block_shift(store, points, faces, sigmas)
    assert abs(alike[0]) > 0.15
    # Closer by what the weights take from the tall wall: its foot's points at about 0.82 of
    # their weight move the block about 1.5 cm towards the truth. (Each vertex off by SIGMA
    # tilts the 60 m wall by 0.2 deg only: the weights cannot take the pull of a 0.8 deg lean.)
    assert abs(weighted[0]) < abs(alike[0]) - 0.01
    assert abs(weighted[1]) < 0.02 and abs(alike[1]) < 0.02  # the long wall holds y alike
    # The small walls, seen at their middles, keep nearly their full weight; the tall wall's
    # foot (25-30 m below its centroid) is near its rim.
    assert np.median(sigmas[faces == 1]) <= SIGMA * (1 + TILT_SIGMA_STEP)
    assert np.median(sigmas[faces == 0]) > 1.08 * SIGMA


@pytest.fixture(scope="module")
def street():
    from colmap_citymodel.assign.schedule import assign
    from colmap_citymodel.block.reconstruction import tie_points
    from colmap_citymodel.options import AssignmentOptions
    from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene

    scene = make_street_scene(StreetSceneOptions(num_stations=5, point_spacing=2.0, seed=4))
    rec = pycolmap.Reconstruction(scene.truth)
    point_ids, xyz = tie_points(rec)
    full = assign(xyz, point_ids, scene.store, 0.5, AssignmentOptions(min_points_per_plane=5))
    return scene, rec, full


def test_the_problem_weighs_each_tie_point_with_its_own_sigma(street):
    """The f_dTP rows of a problem carry their points' sigmas (the whitened residuals times
    the sigmas are the points' distances), also after `reassign` exchanged some of them."""
    scene, rec, full = street
    options = AdjustmentOptions(face_tilt_weights=True)
    problem = HybridProblem(pycolmap.Reconstruction(rec), scene.store, full, None, options,
                            robust_images=False, robust_planes=False)

    def check(problem: HybridProblem) -> None:
        points = np.array([problem.reconstruction.point3D(int(i)).xyz
                           for i in problem.point_ids])
        expected = tie_point_sigmas(options, scene.store, problem.blocks.faces,
                                    problem.point_faces, points, problem.face_sigmas)
        np.testing.assert_allclose(problem.dtp_sigmas(), expected)
        normals = scene.store.normals[problem.point_faces]
        distance = (np.einsum("ij,ij->i", normals, points)
                    + scene.store.offsets[problem.point_faces])
        whitened = problem.group_residuals()["dTP"]
        np.testing.assert_allclose(whitened * problem.dtp_sigmas(), distance, atol=1e-9)

    check(problem)
    sigmas = problem.dtp_sigmas()
    assert sigmas.min() == pytest.approx(options.sigma_dtp, rel=TILT_SIGMA_STEP)
    assert sigmas.max() > 1.1 * options.sigma_dtp  # points near a face's rim weigh less
    assigned = np.flatnonzero(full.assigned)
    fewer = full.without(np.isin(np.arange(len(full.point_ids)), assigned[::9]))
    assert problem.reassign(fewer, scene.store)
    assert problem.exchanged > 0
    check(problem)
