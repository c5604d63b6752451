"""Step 2, the bundle adjustment with GNSS and no model, on the synthetic street: image
observations far off are eliminated and the adjustment without them ends where the block without
them ends."""

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.problem import HybridProblem
from colmap_citymodel.adjust.steps import step2_bundle_adjustment
from colmap_citymodel.align.block_to_model import georegister
from colmap_citymodel.options import RefineOptions

GROSS_PX = 12.0


def corrupt(rec: pycolmap.Reconstruction, share: float, seed: int) -> set[tuple[int, int]]:
    """Moves `share` of the image observations by GROSS_PX in a random direction; returns
    them as (image id, point2D index)."""
    rng = np.random.default_rng(seed)
    moved = set()
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        for index, point2D in enumerate(image.points2D):
            if point2D.has_point3D() and rng.random() < share:
                angle = rng.uniform(0, 2 * np.pi)
                point2D.xy = point2D.xy + GROSS_PX * np.array([np.cos(angle), np.sin(angle)])
                moved.add((image_id, index))
    return moved


def still_observed(rec: pycolmap.Reconstruction, observations) -> int:
    return sum(rec.image(i).points2D[k].has_point3D() for i, k in observations)


def centres(rec: pycolmap.Reconstruction) -> np.ndarray:
    return np.array([rec.image(i).projection_center() for i in sorted(rec.reg_image_ids())])


@pytest.fixture(scope="module")
def clean(street_scene):
    rec = pycolmap.Reconstruction(street_scene.sfm)
    _, priors, _ = georegister(rec, street_scene.store, street_scene.gnss(), None)
    step2_bundle_adjustment(rec, priors, RefineOptions())
    return rec


@pytest.mark.parametrize("image_loss", ["none", "huber"])
def test_gross_image_errors_are_eliminated_and_leave_no_trace(street_scene, clean, image_loss):
    rec = pycolmap.Reconstruction(street_scene.sfm)
    moved = corrupt(rec, 0.01, seed=3)
    assert len(moved) > 100
    _, priors, _ = georegister(rec, street_scene.store, street_scene.gnss(), None)
    options = RefineOptions()
    options.adjustment.image_loss = image_loss
    report, eliminated = step2_bundle_adjustment(rec, priors, options)
    assert still_observed(rec, moved) <= 0.02 * len(moved)
    assert eliminated >= 0.98 * len(moved)
    # Camera centres where the block without the gross errors ends (GNSS is metres off, so
    # this compares two adjustments, not one with the truth).
    apart = np.linalg.norm(centres(rec) - centres(clean), axis=1)
    assert np.sqrt(np.mean(apart ** 2)) < 0.006, apart.max()
    if image_loss == "none":
        # The figures are those of the repeated solve, without the eliminated observations.
        assert report.rms["image"] * options.adjustment.sigma_image < 0.6


def test_the_repeated_solve_takes_out_what_the_eliminated_observations_did(street_scene, clean):
    def apart_rms(rec):
        apart = np.linalg.norm(centres(rec) - centres(clean), axis=1)
        return float(np.sqrt(np.mean(apart ** 2)))

    options = RefineOptions()
    assert options.adjustment.image_loss == "none"
    results = {}
    for repeat in (False, True):
        rec = pycolmap.Reconstruction(street_scene.sfm)
        corrupt(rec, 0.01, seed=3)
        _, priors, _ = georegister(rec, street_scene.store, street_scene.gnss(), None)
        if repeat:
            step2_bundle_adjustment(rec, priors, options)
        else:
            HybridProblem(rec, None, None, priors, options.adjustment, robust_images=False,
                          robust_planes=False).solve()
            o = options.adjustment
            pycolmap.ObservationManager(rec).filter_all_points3D(
                o.elimination_threshold * o.sigma_image, o.min_triangulation_angle)
        results[repeat] = apart_rms(rec)
    assert results[True] < 0.6 * results[False], results


def stated_k1(rec: pycolmap.Reconstruction, k1: float) -> None:
    """Every camera becomes a SIMPLE_RADIAL one that states a radial distortion `k1` (the
    images have none)."""
    for camera in rec.cameras.values():
        fx, _, cx, cy = camera.params
        camera.model = pycolmap.CameraModelId.SIMPLE_RADIAL
        camera.params = np.array([fx, cx, cy, k1])


def test_the_interior_orientation_is_refined_only_where_the_images_show_it_off(street_scene):
    from colmap_citymodel.adjust.steps import check_intrinsics

    results = {}
    for k1 in (0.0, -0.003):
        rec = pycolmap.Reconstruction(street_scene.sfm)
        stated_k1(rec, k1)
        _, priors, _ = georegister(rec, street_scene.store, street_scene.gnss(), None)
        options = RefineOptions()
        report, _ = step2_bundle_adjustment(rec, priors, options)
        results[k1] = check_intrinsics(rec, priors, options, report)
    held = results[0.0]
    assert not held.refined and held.p_value > 0.001, held
    found = results[-0.003]
    assert found.refined and found.p_value < 1e-6, found
    # The distortion went back most of the way to what the images have (0).
    camera = next(iter(found.freed.cameras.values()))
    assert abs(camera.params[3]) < 0.3 * 0.003, camera.params
    options = RefineOptions()
    options.adjustment.intrinsics_test_alpha = None
    assert check_intrinsics(found.freed, None, options, report) is None
