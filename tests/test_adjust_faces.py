"""Faces as units (adjust.faces, adjust.problem.face_sigmas): each face one observation of its
offset, the faces' offset sigma from their own spread, and a face the model got wrong weighed
less instead of pulling the block."""

import numpy as np
import pytest

from colmap_citymodel.adjust.faces import (FaceOffsets, MIN_FACES_FOR_SIGMA,
                                           SIGMA_FACE_FLOOR, estimate_sigma_face)
from colmap_citymodel.adjust.problem import face_sigmas
from colmap_citymodel.options import AdjustmentOptions, RefineOptions
from colmap_citymodel.simulate.synthetic import centre_errors
from colmap_citymodel.workflow import refine


def test_per_point_weights_every_face_alike():
    options = AdjustmentOptions(face_weighting="per_point")
    rows = np.repeat([0, 1, 2], [3000, 100, 20])
    np.testing.assert_allclose(face_sigmas(options, rows, 3), options.sigma_dtp)


def test_a_face_counts_as_one_observation_of_its_offset():
    options = AdjustmentOptions(face_weighting="face", sigma_face=0.2)
    counts = np.array([3000, 100, 20, 0])
    sigmas = face_sigmas(options, np.repeat(np.arange(4), counts), 4)
    face_weight = counts / sigmas ** 2  # what each face's points weigh together
    # Within a few per cent of one another however many points a face has ...
    assert face_weight[:3].max() / face_weight[:3].min() < 1.25
    # ... and the tie points together weigh as many points at sigma_dtp would.
    assert face_weight.sum() == pytest.approx(counts.sum() / options.sigma_dtp ** 2)
    # A small sigma_face leaves small faces nearly per point and caps the large ones.
    tight = face_sigmas(AdjustmentOptions(face_weighting="face", sigma_face=0.02),
                        np.repeat(np.arange(4), counts), 4)
    weight = counts / tight ** 2
    assert 3 < weight[0] / weight[2] < 0.1 * counts[0] / counts[2]


def offsets(values, counts):
    values = np.asarray(values, float)
    return FaceOffsets(np.arange(len(values)), np.asarray(counts), values,
                       np.zeros(len(values)))


def test_the_faces_offset_sigma_comes_from_their_spread():
    rng = np.random.default_rng(0)
    options = AdjustmentOptions(face_weighting="face")
    estimates = [estimate_sigma_face(offsets(rng.normal(0, 0.15, 60), np.full(60, 400)),
                                     options) for _ in range(20)]
    assert np.median(estimates) == pytest.approx(0.15 * np.sqrt(60 / 53), rel=0.15)
    # Faces that fit their points better than the points' noise: the floor, not zero.
    assert estimate_sigma_face(offsets(np.zeros(30), np.full(30, 20)), options) \
        == SIGMA_FACE_FLOOR
    # Too few faces to tell: none.
    few = MIN_FACES_FOR_SIGMA - 1
    assert estimate_sigma_face(offsets(np.full(few, 0.3), np.full(few, 50)), options) is None


@pytest.fixture(scope="module")
def arcade(street_scene):
    """The street's largest street-facing facade modelled 0.6 m in front of its true surface
    (an arcade or recessed ground floor the model does not have)."""
    store = street_scene.store
    cameras = np.array([im.projection_center() for im in street_scene.truth.images.values()])
    walls = [f for f in range(store.num_faces) if store.faces[f].semantic == "WallSurface"
             and (cameras.mean(0) - store.centroids[f]) @ store.normals[f] > 0
             and abs(store.normals[f][1]) > 0.99]
    face = max(walls, key=lambda f: store.areas[f])
    vertices = store.vertices.copy()
    vertices[store.face_vertex_ids(face)] += 0.6 * store.normals[face]
    return store.with_vertices(vertices), face


def faces_as_units(sigma_face=None) -> RefineOptions:
    options = RefineOptions()
    options.adjustment.face_weighting = "face"
    options.adjustment.sigma_face = sigma_face
    return options


def test_a_face_off_its_true_surface_does_not_pull_the_block(street_scene, arcade):
    store, face = arcade
    result = refine(street_scene.sfm, store, street_scene.gnss(), faces_as_units(),
                    progress=False)
    rms = float(np.sqrt(np.mean(np.square(centre_errors(result.reconstruction,
                                                          street_scene.truth)))))
    assert rms < 0.03
    # The face is weighed less, or keeps too few points to matter.
    points = int(np.count_nonzero(result.assignment.face_index == face))
    assert face in result.assignment.face_factors or points < 0.02 * result.assignment.num_assigned
    # With its offset sigma fixed at a LOD2 model's 0.2 m, the face pulls: the estimate is what
    # tells it apart.
    pulled = refine(street_scene.sfm, store, street_scene.gnss(), faces_as_units(0.2),
                    progress=False)
    rms_fixed = float(np.sqrt(np.mean(np.square(centre_errors(pulled.reconstruction,
                                                                street_scene.truth)))))
    assert rms_fixed > 2 * rms
