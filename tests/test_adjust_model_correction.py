"""adjust.model_correction: which faces the images correct, the datum the corrected model
keeps, and a hybrid solve that moves a wrongly placed facade back to its true plane while the
faces the images do not correct keep their planes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.model_correction import (
    datum_condition,
    plane_fit_sigma,
    select_corrected_faces,
    summarise_correction,
)
from colmap_citymodel.adjust.correction_loop import CorrectionProblem
from colmap_citymodel.adjust.problem import HybridProblem
from colmap_citymodel.adjust.steps import model_after_solve
from colmap_citymodel.assign.assignment import Assignment
from colmap_citymodel.assign.schedule import assign
from colmap_citymodel.block.priors import GNSSPriors
from colmap_citymodel.block.reconstruction import tie_points
from colmap_citymodel.options import AdjustmentOptions, AssignmentOptions
from colmap_citymodel.precision.estimate import cofactors, vertex_covariances
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene

from conftest import box_store

A = 10.0  # the box's size


def _assignment(points: np.ndarray, faces: np.ndarray) -> Assignment:
    return Assignment(np.arange(len(points)), np.asarray(faces, np.int64),
                      np.zeros(len(points)), 0.5)


def _grid_on_wall(u_range, v_range, n=12):
    """Points on the y = 0 wall of the box (x along u, z along v)."""
    u, v = np.meshgrid(np.linspace(*u_range, n), np.linspace(*v_range, n))
    return np.column_stack([u.ravel(), np.zeros(u.size), v.ravel()])


def test_selection_needs_a_plane_the_points_determine_at_every_vertex():
    store = box_store()
    rng = np.random.default_rng(0)
    wall = _grid_on_wall((0.5, 9.5), (0.5, 9.5))  # face 0, covers it
    wall[:, 1] += rng.normal(0, 0.05, len(wall))
    strip = np.column_stack([np.full(144, A), np.linspace(0.5, 9.5, 144),
                             np.linspace(4.5, 5.5, 144)])  # face 1, one metre high
    strip[:, 0] += rng.normal(0, 0.05, len(strip))
    roof = np.column_stack([rng.uniform(1, 9, 20), rng.uniform(1, 9, 20), np.full(20, A)])
    roof[:, 2] += rng.normal(0, 0.05, len(roof))  # face 4: 20 points over all of it
    scattered = _grid_on_wall((0.5, 9.5), (0.5, 9.5))[:, [1, 0, 2]]  # face 3 (x = 0)
    scattered[:, 0] += rng.normal(0, 0.4, len(scattered))  # another surface's points among them
    points = np.vstack([wall, strip, roof, scattered])
    faces = np.r_[np.zeros(len(wall)), np.ones(len(strip)), np.full(len(roof), 4),
                  np.full(len(scattered), 3)]
    options = AdjustmentOptions(correction_max_sigma=0.02)
    selection = select_corrected_faces(store, _assignment(points, faces), points, options)
    assert selection.faces.tolist() == [0]
    assert selection.not_corrected == {"plane_sigma_too_large": 3}
    # the wall: sigma of the plane at its corners about 0.05 * sqrt(4 / 144) (offset and tilts)
    s0, sigma = plane_fit_sigma(store, 0, wall)
    assert s0 == pytest.approx(0.05, rel=0.15)
    assert 0.005 < sigma < 0.02
    assert selection.plane_sigma[0] == pytest.approx(sigma)
    # the strip: as many points, as little scatter, but the plane is extrapolated 4.5 m up
    # and down; the roof: few points; face 3: points that scatter by 0.4 m
    assert plane_fit_sigma(store, 1, strip)[1] > 3 * sigma
    assert plane_fit_sigma(store, 4, roof)[1] > 0.02
    assert plane_fit_sigma(store, 3, scattered)[0] > 0.3
    assert plane_fit_sigma(store, 4, roof[:3])[1] == np.inf
    # the wall's four corners are released; the walls beside it and the roof keep their planes
    np.testing.assert_allclose(np.sort(store.vertices[selection.released][:, [0, 2]], axis=0),
                               [[0, 0], [0, 0], [A, A], [A, A]])
    assert selection.held.tolist() == [1, 3, 4]


def test_datum_condition_sees_plane_moves_not_slides():
    store = box_store()
    faces = np.zeros(144)
    wall = _grid_on_wall((0.5, 9.5), (0.5, 9.5))
    selection = select_corrected_faces(store, _assignment(wall, faces), wall,
                                       AdjustmentOptions())
    ids, matrix, reference = datum_condition(store, selection, 0.05)
    assert len(ids) == 4 and matrix.shape[1] == 12
    # one wall fixes its shift along its normal and its two tilts, nothing within its plane
    assert matrix.shape[0] == 3

    def residual(moves):
        return matrix @ (reference + np.asarray(moves, float).ravel() - reference)

    slide = np.zeros((4, 3))
    slide[:, 0] = 0.3  # along the wall
    slide[1, 2] = -0.2
    assert np.abs(residual(slide)).max() < 1e-12
    shift = np.tile([0.0, 0.1, 0.0], (4, 1))  # the whole wall 0.1 m along its normal
    assert np.linalg.norm(residual(shift)) == pytest.approx(0.1 / 0.05, rel=1e-6)
    one_corner = np.zeros((4, 3))
    one_corner[0, 1] = 0.1  # a tilt
    assert np.linalg.norm(residual(one_corner)) > 0.5


# -- a hybrid solve on the synthetic street ---------------------------------------------------

SHIFTED_FACE = 7  # a street facade with 60 tie points spread over it (seed 3)
SHIFT = 0.3


@pytest.fixture(scope="module")
def corrected():
    scene = make_street_scene(StreetSceneOptions(num_stations=6, point_spacing=1.2, seed=3))
    truth = scene.store
    # the given model: the facade 0.3 m in front of its true plane; its corners move with it,
    # so the faces that share them change as well (as in Unger's "original" model)
    vertices = truth.vertices.copy()
    moved = truth.face_vertex_ids(SHIFTED_FACE)
    vertices[moved] += SHIFT * truth.normals[SHIFTED_FACE]
    given = truth.with_vertices(vertices)
    rec = pycolmap.Reconstruction(scene.truth)
    ids = np.array(rec.reg_image_ids())
    centres = np.array([rec.image(i).projection_center() for i in ids])
    priors = GNSSPriors(ids, centres, np.full((len(ids), 3), 0.5))
    point_ids, xyz = tie_points(rec)
    assignment = assign(xyz, point_ids, truth, 0.5, AssignmentOptions(min_points_per_plane=5))
    # the facade's plane sigma is 0.0557 m (its points have 0.09 m of relief): corrected with
    # the faces whose planes are better determined
    options = AdjustmentOptions(correct_model=True, sigma_dtp=0.05, correction_max_sigma=0.056)
    problem = CorrectionProblem(rec, given, assignment, priors, options, robust_images=False,
                                robust_planes=False)
    problem.solve()
    return truth, given, model_after_solve(given, problem), problem


def _offset_at(store, face: int, point: np.ndarray) -> float:
    return float(store.normals[face] @ point + store.offsets[face])


def test_the_images_move_a_shifted_facade_back(corrected):
    truth, given, adjusted, problem = corrected
    selection = problem.blocks.correction
    assert SHIFTED_FACE in selection.faces
    centre = truth.centroids[SHIFTED_FACE]
    assert abs(_offset_at(given, SHIFTED_FACE, centre)) == pytest.approx(SHIFT)
    assert abs(_offset_at(adjusted, SHIFTED_FACE, centre)) < 0.1  # from 0.3
    # topology unchanged, every corrected face planar
    assert adjusted.faces.ring_vertex.tolist() == given.faces.ring_vertex.tolist()
    assert adjusted.rms_out_of_plane[selection.faces].max() < 0.005


def test_faces_not_corrected_keep_their_planes(corrected):
    truth, given, adjusted, problem = corrected
    selection = problem.blocks.correction
    kept = np.setdiff1d(np.arange(given.num_faces), selection.faces)
    assert len(selection.held) and np.isin(selection.held, kept).all()
    for f in kept:
        points = adjusted.vertices[adjusted.face_vertex_ids(f)]
        # every vertex of the face, moved or not, is on the face's given plane
        np.testing.assert_allclose(points @ given.normals[f] + given.offsets[f], 0,
                                   atol=max(0.003, 2 * given.rms_out_of_plane[f]))
    untouched = np.setdiff1d(kept, selection.held)
    np.testing.assert_allclose(adjusted.vertices[np.unique(np.concatenate(
        [given.face_vertex_ids(f) for f in untouched]))], given.vertices[np.unique(
            np.concatenate([given.face_vertex_ids(f) for f in untouched]))], atol=0.003)


def test_corrected_vertices_get_sigmas_and_a_significance_test(corrected):
    truth, given, adjusted, problem = corrected
    # held planes are constant blocks the precision stage knows (no unknown block left over)
    cof = cofactors(problem, redundancy=False, points=False)
    assert cof.datum_defect == 0
    ids, cov, note = vertex_covariances(problem, None)
    assert ids.tolist() == problem.blocks.vertex_ids.tolist() and "s0" in note
    correction = summarise_correction(given, adjusted, problem.blocks.correction, ids, cov, 3.0)
    assert np.isfinite(correction.sigma).all() and (correction.sigma > 0).all()
    # the sigma of a corrected vertex: far below the 0.5 m of its observation
    assert np.median(correction.sigma) < 0.1
    moved = np.isin(correction.vertex_ids, given.face_vertex_ids(SHIFTED_FACE))
    assert correction.significant[moved].all()
    assert (correction.shift_length[moved] > SHIFT / 2).all()
    summary = correction.todict()
    assert summary["num_corrected_vertices"] == len(correction.vertex_ids)
    assert summary["num_significant_vertices"] >= int(moved.sum())
    # what is written back: the given model with only the corrected vertices moved
    written = correction.corrected_store(given)
    same = np.setdiff1d(np.arange(len(given.vertices)), correction.vertex_ids)
    np.testing.assert_array_equal(written.vertices[same], given.vertices[same])


def test_a_plain_problem_releases_nothing_and_a_held_block_does_not_move(corrected):
    truth, given, adjusted, problem = corrected
    rec = pycolmap.Reconstruction(problem.reconstruction)
    point_ids, xyz = tie_points(rec)
    assignment = assign(xyz, point_ids, truth, 0.5, AssignmentOptions(min_points_per_plane=5))
    plain = HybridProblem(rec, given, assignment, None, problem.options, robust_images=False,
                          robust_planes=False)
    assert plain.blocks.correction is None and not plain.blocks.held_normals
    assert plain.counts["VT"] == 3 * len(plain.blocks.vertex_ids)
    assert problem.counts["VT"] > 3 * len(problem.blocks.vertex_ids)  # the datum condition
    # without the datum condition, block held: only the model moves
    options = dataclasses.replace(problem.options, sigma_correction_datum=None)
    held = CorrectionProblem(rec, given, assignment, None, options, robust_images=False,
                             robust_planes=False)
    assert held.counts["VT"] == 3 * len(held.blocks.vertex_ids)
    held.hold_block()
    centres = {i: rec.image(i).projection_center() for i in rec.reg_image_ids()}
    points = {i: rec.point3D(i).xyz.copy() for i in list(rec.point3D_ids())[:50]}
    held.solve()
    for i, centre in centres.items():
        np.testing.assert_array_equal(rec.image(i).projection_center(), centre)
    for i, xyz in points.items():
        np.testing.assert_array_equal(rec.point3D(i).xyz, xyz)
    moved = model_after_solve(given, held)
    face = list(given.faces.gml_id).index(given.faces.gml_id[SHIFTED_FACE])
    assert abs(_offset_at(moved, face, truth.centroids[SHIFTED_FACE])) < 0.1


def test_a_held_block_with_free_tie_points_keeps_its_poses(corrected):
    truth, given, adjusted, problem = corrected
    rec = pycolmap.Reconstruction(problem.reconstruction)
    point_ids, xyz = tie_points(rec)
    assignment = assign(xyz, point_ids, truth, 0.5, AssignmentOptions(min_points_per_plane=5))
    options = dataclasses.replace(problem.options, sigma_correction_datum=None)
    held = CorrectionProblem(rec, given, assignment, None, options, robust_images=False,
                             robust_planes=False)
    held.hold_block(free_assigned_points=True)
    assert held.points_free == assignment.num_assigned
    assert held.num_unknowns() == 3 * (len(held.blocks.faces) + len(held.blocks.vertex_ids)
                                       + assignment.num_assigned)
    centres = {i: rec.image(i).projection_center() for i in rec.reg_image_ids()}
    free = set(held.point_ids.tolist())
    other = [i for i in rec.point3D_ids() if i not in free][:50]
    before = {i: rec.point3D(i).xyz.copy() for i in other}
    held.solve()
    for i, centre in centres.items():
        np.testing.assert_array_equal(rec.image(i).projection_center(), centre)
    for i, xyz in before.items():
        np.testing.assert_array_equal(rec.point3D(i).xyz, xyz)
    moved = model_after_solve(given, held)
    face = list(given.faces.gml_id).index(given.faces.gml_id[SHIFTED_FACE])
    assert abs(_offset_at(moved, face, truth.centroids[SHIFTED_FACE])) < 0.1
