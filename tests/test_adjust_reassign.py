"""adjust.problem.HybridProblem.reassign: one problem kept across the assignment iterations
reaches the solution a problem built anew reaches, and the loop with it refines as before."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.problem import GROUPS, HybridProblem
from colmap_citymodel.adjust.steps import model_after_solve
from colmap_citymodel.assign.schedule import assign
from colmap_citymodel.block.priors import GNSSPriors
from colmap_citymodel.block.reconstruction import tie_points
from colmap_citymodel.options import AdjustmentOptions, AssignmentOptions, RefineOptions
from colmap_citymodel.precision.estimate import cofactors, whitened_jacobian
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, centre_errors, make_street_scene
from colmap_citymodel.workflow import refine

GNSS_SIGMA = np.array([0.5, 0.5, 0.8])


def _options(face_weighting: str = "per_point") -> AdjustmentOptions:
    # Tight tolerances: both problems end at the optimum, not where a tolerance stops them.
    # Per point: the faces' weights do not follow their numbers of points, so a kept problem
    # is exactly the new one.
    return AdjustmentOptions(sigma_dtp=0.05, function_tolerance=1e-14,
                             max_solver_iterations=100, face_weighting=face_weighting)


def test_faces_weighed_as_units_refuse_reuse_when_a_face_weight_changes(scene):
    """With each face one observation of its offset, a face's f_dTP sigma follows its number of
    points: a problem is kept only while no face's sigma moves by more than the tolerance."""
    from colmap_citymodel.adjust.problem import REWEIGHT_TOLERANCE, face_sigmas

    scene, rec, priors, first, second = scene
    options = _options("face")
    kept = HybridProblem(pycolmap.Reconstruction(rec), scene.store, first, priors, options,
                         robust_images=False, robust_planes=False)
    slots = np.searchsorted(first.faces, second.face_index[second.assigned])
    changed = np.abs(face_sigmas(options, slots, len(first.faces)) / kept.face_sigmas - 1)
    assert kept.reassign(second, scene.store) == bool(np.all(changed <= REWEIGHT_TOLERANCE))
    # Half of one face's points gone: its sigma drops by about 1 - sqrt(1/2).
    face = int(first.faces[0])
    drop = np.flatnonzero(first.face_index == face)[::2]
    halved = first.without(np.isin(np.arange(len(first.point_ids)), drop))
    fresh = HybridProblem(pycolmap.Reconstruction(rec), scene.store, first, priors, options,
                          robust_images=False, robust_planes=False)
    assert not fresh.reassign(halved, scene.store)


@pytest.fixture(scope="module")
def scene():
    """A drifted street block, GNSS priors, the model, and two assignments on the same
    planes that differ in some tie points (some dropped, others added, others on another
    plane would need another face set: dropped and added is what the loop sees)."""
    scene = make_street_scene(StreetSceneOptions(num_stations=5, point_spacing=2.0, seed=4))
    rec = pycolmap.Reconstruction(scene.truth)
    rng = np.random.default_rng(4)
    for point in rec.points3D.values():  # start away from the optimum
        point.xyz = point.xyz + rng.normal(0.0, 0.05, 3)
    ids = np.array(rec.reg_image_ids())
    centres = np.array([rec.image(i).projection_center() for i in ids])
    priors = GNSSPriors(ids, centres + rng.normal(size=centres.shape) * GNSS_SIGMA,
                        np.tile(GNSS_SIGMA, (len(ids), 1)))
    point_ids, xyz = tie_points(rec)
    full = assign(xyz, point_ids, scene.store, 0.5, AssignmentOptions(min_points_per_plane=5))
    assigned = np.flatnonzero(full.assigned)
    first = full.without(np.isin(np.arange(len(full.point_ids)), assigned[::7]))
    second = full.without(np.isin(np.arange(len(full.point_ids)), assigned[3::5]))
    assert np.array_equal(first.faces, second.faces) and len(first.faces) >= 5
    changed = np.count_nonzero(first.face_index != second.face_index)
    assert changed > 20
    return scene, rec, priors, first, second


def _poses(rec: pycolmap.Reconstruction) -> np.ndarray:
    return np.array([rec.frame(f).rig_from_world.params for f in sorted(rec.frames)])


def _points(rec: pycolmap.Reconstruction) -> np.ndarray:
    return np.array([rec.point3D(i).xyz for i in sorted(rec.points3D)])


def test_reassigned_problem_solves_as_a_new_one(scene):
    scene, rec, priors, first, second = scene
    options = _options()
    kept_rec = pycolmap.Reconstruction(rec)
    kept = HybridProblem(kept_rec, scene.store, first, priors, options, robust_images=False,
                         robust_planes=False)
    kept.solve()
    current = model_after_solve(scene.store, kept)
    new_rec = pycolmap.Reconstruction(kept_rec)  # the same state, for the new problem

    assert kept.reassign(second, current)
    report = kept.solve()
    new = HybridProblem(new_rec, scene.store, second, priors, options, robust_images=False,
                        robust_planes=False, current=current)
    new_report = new.solve()

    # The same observations, unknowns and solution.
    assert kept.counts == new.counts
    assert sorted(kept.point_ids) == sorted(new.point_ids)
    faces_kept = dict(zip(kept.point_ids.tolist(), kept.point_faces.tolist()))
    assert faces_kept == dict(zip(new.point_ids.tolist(), new.point_faces.tolist()))
    assert report.num_unknowns == new_report.num_unknowns
    np.testing.assert_allclose(_poses(kept_rec), _poses(new_rec), atol=1e-6)
    np.testing.assert_allclose(_points(kept_rec), _points(new_rec), atol=1e-6)
    np.testing.assert_allclose(kept.blocks.vertex_array, new.blocks.vertex_array, atol=1e-6)
    np.testing.assert_allclose(kept.blocks.offset_array, new.blocks.offset_array, atol=1e-6)
    for g in GROUPS:
        assert report.count[g] == new_report.count[g]
        np.testing.assert_allclose(report.sum_squares[g], new_report.sum_squares[g],
                                   rtol=1e-6, atol=1e-9)
    # The residual rows stay in group order with the f_dTP rows in `point_ids` order: the
    # dTP residuals of each point are the same in both problems, and so are the precisions.
    by_point = dict(zip(new.point_ids.tolist(), new.residuals["dTP"]))
    np.testing.assert_allclose(kept.residuals["dTP"],
                               [by_point[i] for i in kept.point_ids.tolist()], atol=1e-8)
    jacobian, _ = whitened_jacobian(kept)
    assert jacobian.shape[0] == sum(kept.counts.values())
    # (Pose cofactors: the plane offsets refer to other points on their planes in the two
    # problems, which changes their own cofactors, not those of the poses.)
    q = []
    for problem in (kept, new):
        cof = cofactors(problem)
        rec_ = problem.reconstruction
        slices = [cof.layout.columns("frame", f) for f in sorted(rec_.frames)]
        columns = np.concatenate([np.arange(c.start, c.stop) for c in slices if c is not None])
        q.append(cof.q_cc[np.ix_(columns, columns)])
    np.testing.assert_allclose(q[0], q[1], rtol=1e-4, atol=1e-6 * np.abs(q[1]).max())


def test_reassign_refuses_other_planes(scene):
    scene, rec, priors, first, second = scene
    problem = HybridProblem(pycolmap.Reconstruction(rec), scene.store, first, priors,
                            _options(), robust_images=False, robust_planes=False)
    face = first.faces[0]
    fewer = first.without(first.face_index == face)
    counts = dict(problem.counts)
    assert not problem.reassign(fewer, scene.store)
    assert problem.counts == counts  # nothing changed
    assert problem.reassign(first, scene.store)  # the same assignment: nothing to exchange
    assert problem.counts == counts


def test_a_kept_problem_switched_to_the_robust_loss_solves_as_a_new_robust_one(scene):
    """The robust solve of an iteration and the solve with the original weights share one
    problem: switched robust, it reaches the robust problem's solution, with its
    downweighted f_dTP; switched back, the non-robust one's."""
    scene, rec, priors, first, second = scene
    options = _options()
    options.plane_loss_scale = 0.5  # Huber bends at 0.5 sigma_dtp: many f_dTP downweighted
    solutions = {}
    for robust in (True, False):
        kept_rec, new_rec = pycolmap.Reconstruction(rec), pycolmap.Reconstruction(rec)
        kept = HybridProblem(kept_rec, scene.store, first, priors, options,
                             robust_images=False, robust_planes=not robust)
        assert kept.reassign(second, scene.store, robust_planes=robust)
        assert kept.robust_planes == robust
        kept.solve()
        new = HybridProblem(new_rec, scene.store, second, priors, options,
                            robust_images=False, robust_planes=robust)
        new.solve()
        np.testing.assert_allclose(_poses(kept_rec), _poses(new_rec), atol=1e-6)
        np.testing.assert_allclose(_points(kept_rec), _points(new_rec), atol=1e-6)
        solutions[robust] = _points(kept_rec)
    # The loss did act: the robust and the non-robust solutions differ.
    assert np.max(np.abs(solutions[True] - solutions[False])) > 1e-4


def test_refine_with_one_problem_equals_refine_with_new_problems(street_scene, street_refined):
    scene = street_scene
    assert RefineOptions().workflow.reuse_problem  # street_refined kept its problems
    options = RefineOptions()
    options.precision.covariances = "off"
    options.workflow.reuse_problem = False
    results = {True: street_refined,
               False: refine(scene.sfm, scene.store, scene.gnss(), options, progress=False)}
    truth = pycolmap.Reconstruction(scene.truth)
    truth.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), scene.store.origin))
    errors = {k: float(np.sqrt(np.mean(centre_errors(r.reconstruction_in_crs(), truth) ** 2)))
              for k, r in results.items()}
    # The same solution up to the solver's tolerances (a few mm of a metre-level error).
    assert abs(errors[True] - errors[False]) < 0.01, errors
    assert results[True].assignment.num_assigned == pytest.approx(
        results[False].assignment.num_assigned, rel=0.01)
    assert len(results[True].iterations) <= len(results[False].iterations)
