"""The initial alignment rounds (the block moved onto its assigned planes by similarities) on
the synthetic street: a round whose similarity does not lower the block objective takes the
first shorter step towards it that does, or is undone."""

import copy

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.steps import (STEP_FRACTIONS, align_block_to_planes,
                                           align_to_planes, partial_similarity,
                                           step2_bundle_adjustment)
from colmap_citymodel.align.block_to_model import georegister
from colmap_citymodel.align.georegister import transform_points
from colmap_citymodel.assign.schedule import assign
from colmap_citymodel.block.reconstruction import tie_points
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.simulate.synthetic import centre_errors


def rotation_angle(matrix: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(matrix) - 1) / 2, -1, 1)))


def test_a_fraction_of_a_similarity_scales_its_angle_scale_and_the_centres_shift():
    rng = np.random.default_rng(2)
    rotation = pycolmap.Rotation3d(np.array([0.1, -0.2, 0.05, 1.0]) / np.linalg.norm(
        [0.1, -0.2, 0.05, 1.0]))
    move = pycolmap.Sim3d(1.02, rotation, np.array([3.0, -1.0, 0.5]))
    centre = np.array([10.0, 10.0, 40.0])
    full = partial_similarity(move, 1.0, centre)
    np.testing.assert_allclose(np.asarray(full.matrix()), np.asarray(move.matrix()), atol=1e-9)
    for fraction in STEP_FRACTIONS:
        part = partial_similarity(move, fraction, centre)
        assert part.scale == pytest.approx(1.02 ** fraction)
        angle = rotation_angle(np.asarray(move.rotation.matrix()))
        assert rotation_angle(np.asarray(part.rotation.matrix())) == pytest.approx(
            fraction * angle)
        shift = transform_points(move, centre[None])[0] - centre
        np.testing.assert_allclose(transform_points(part, centre[None])[0] - centre,
                                   fraction * shift, atol=1e-9)
    points = rng.normal(size=(5, 3))
    np.testing.assert_allclose(transform_points(partial_similarity(move, 0.0, centre), points),
                               points, atol=1e-12)


class CentroidObjective:
    """Distance of the camera centres' centroid (after `moved`) from a target: lower is
    better, as refine's block objective."""

    def __init__(self, target: np.ndarray):
        self.target = target

    def __call__(self, rec: pycolmap.Reconstruction, moved: pycolmap.Sim3d | None = None):
        centres = np.array([im.projection_center() for im in rec.images.values()
                            if im.has_pose])
        if moved is not None:
            centres = transform_points(moved, centres)
        return float(np.linalg.norm(centres.mean(0) - self.target))


@pytest.fixture(scope="module")
def start(street_scene):
    """The block after step 2, its tie points assigned at 2 m, and the first round's fit."""
    rec = pycolmap.Reconstruction(street_scene.sfm)
    options = RefineOptions()
    options.assignment.method = "direct"
    _, priors, _ = georegister(rec, street_scene.store, street_scene.gnss(), None)
    step2_bundle_adjustment(rec, priors, options)
    point_ids, points = tie_points(rec)
    assignment = assign(points, point_ids, street_scene.store, 2.0, options.assignment)
    move, _ = align_to_planes(rec, points, assignment, street_scene.store, priors,
                              options.adjustment)
    return rec, priors, point_ids, points, assignment, move, options


def run_one_round(street_scene, start, objective):
    rec, priors, point_ids, points, assignment, _, options = start
    rec = pycolmap.Reconstruction(rec)
    options = copy.deepcopy(options)
    options.workflow.alignment_rounds = 1
    total, _, _ = align_block_to_planes(rec, point_ids, points, assignment, street_scene.store,
                                        priors, 2.0, options, objective=objective)
    return rec, total


def test_a_round_that_overshoots_takes_the_first_shorter_step_that_helps(street_scene, start):
    rec0, _, _, points, _, move, _ = start
    centres = np.array([im.projection_center() for im in rec0.images.values()])
    # The best the objective knows lies a fifth of the way: the whole move and half of it are
    # worse than staying, a quarter of it is better.
    full_shift = transform_points(move, centres).mean(0) - centres.mean(0)
    assert np.linalg.norm(full_shift) > 0.5
    objective = CentroidObjective(centres.mean(0) + 0.2 * full_shift)
    assert objective(rec0, move) > objective(rec0)
    rec, total = run_one_round(street_scene, start, objective)
    expected = partial_similarity(move, 0.25, points.mean(0))
    np.testing.assert_allclose(np.asarray(total.matrix()), np.asarray(expected.matrix()),
                               atol=1e-9)
    assert objective(rec) < objective(rec0)
    # The cameras moved with the block: a quarter of the way to where the whole fit puts them.
    moved = np.array([im.projection_center() for im in rec.images.values()])
    np.testing.assert_allclose(moved.mean(0) - centres.mean(0), 0.25 * full_shift, atol=0.02)


def test_a_round_that_no_step_improves_is_undone(street_scene, start):
    rec0 = start[0]
    centres = np.array([im.projection_center() for im in rec0.images.values()])
    objective = CentroidObjective(centres.mean(0))  # where the block already is
    rec, total = run_one_round(street_scene, start, objective)
    np.testing.assert_allclose(np.asarray(total.matrix()), np.eye(4)[:3], atol=1e-12)
    assert np.max(centre_errors(rec, rec0)) == 0.0
