"""Faces as units (adjust.faces, adjust.problem.face_sigmas): each face one observation of its
offset, the faces' offset sigma from their own spread, and a face the model got wrong weighed
less instead of pulling the block."""

import numpy as np
import pytest

from colmap_citymodel.adjust.faces import (FaceOffsets, MIN_FACES_FOR_SIGMA,
                                           SIGMA_FACE_FLOOR, estimate_sigma_face)
from colmap_citymodel.adjust.problem import face_sigmas
from colmap_citymodel.options import AdjustmentOptions, RefineOptions
from colmap_citymodel.output.write import face_table
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
    # ... each that of one observation of its offset with its points' own noise.
    np.testing.assert_allclose(
        face_weight[:3], 1 / (0.2 ** 2 + options.sigma_dtp ** 2 / counts[:3]), rtol=1e-12)
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


def test_terrain_cells_do_not_set_the_faces_offset_sigma():
    # 20 walls and roofs off by 0.25 m, 200 terrain cells that fit a DTM to a centimetre (or,
    # from the buildings' feet, 0.6 m off): the faces' sigma is the walls' and roofs' spread.
    rng = np.random.default_rng(1)
    options = AdjustmentOptions(face_weighting="offsets")
    model = rng.normal(0, 0.25, 20)
    for terrain in (rng.normal(0, 0.01, 200), rng.normal(0, 0.6, 200)):
        found = offsets(np.concatenate([model, terrain]), np.full(220, 300))
        is_model = np.arange(220) < 20
        alone = estimate_sigma_face(offsets(model, np.full(20, 300)), options)
        assert estimate_sigma_face(found, options, is_model) == pytest.approx(alone, rel=1e-12)
        assert abs(estimate_sigma_face(found, options) - alone) > 0.1
    assert 0.15 < alone < 0.35
    # Fewer model faces than it takes: none, however many terrain cells.
    assert estimate_sigma_face(found, options, np.arange(220) < MIN_FACES_FOR_SIGMA - 1) is None


@pytest.fixture(scope="module")
def arcade(street_scene):
    """The street's largest street-facing facade modelled 0.6 m in front of its true surface
    (an arcade or recessed ground floor the model does not have)."""
    return arcade_model(street_scene, 0.6)


@pytest.fixture(scope="module")
def deep_arcade(street_scene):
    """The same facade 2 m in front of its true surface."""
    return arcade_model(street_scene, 2.0)


def arcade_model(street_scene, metres: float):
    store = street_scene.store
    cameras = np.array([im.projection_center() for im in street_scene.truth.images.values()])
    walls = [f for f in range(store.num_faces) if store.faces[f].semantic == "WallSurface"
             and (cameras.mean(0) - store.centroids[f]) @ store.normals[f] > 0
             and abs(store.normals[f][1]) > 0.99]
    face = max(walls, key=lambda f: store.areas[f])
    vertices = store.vertices.copy()
    vertices[store.face_vertex_ids(face)] += metres * store.normals[face]
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


def box(x0: float, y0: float, x: float, y: float, h: float) -> list[np.ndarray]:
    """The four walls and the roof of a box building."""
    c = np.array([[x0, y0], [x0 + x, y0], [x0 + x, y0 + y], [x0, y0 + y]])
    walls = [np.array([[*c[i], 0], [*c[(i + 1) % 4], 0], [*c[(i + 1) % 4], h], [*c[i], h]])
             for i in range(4)]
    return [w.astype(float) for w in walls] + [np.array([[*p, h] for p in c], float)]


def faces_scene(offset_of_face0: float, seed: int = 0):
    """Points on the walls and roofs of three box buildings around a square, each face off by
    its own generalisation error (0.1 m), the first wall's points `offset_of_face0` in front
    of it; that face also holds the most points."""
    from colmap_citymodel.assign.assignment import Assignment
    from colmap_citymodel.citymodel.build import store_from_polygons

    rng = np.random.default_rng(seed)
    polygons = box(0, 0, 40, 20, 12) + box(60, 0, 20, 30, 15) + box(0, 40, 30, 20, 9)
    store = store_from_polygons(polygons, origin=np.zeros(3))
    points, faces = [], []
    for f in range(store.num_faces):
        n = 1500 if f == 0 else 300
        local = store.vertices[store.face_vertex_ids(f)]
        p = rng.uniform(local.min(0), local.max(0), (n, 3))
        p -= np.outer(p @ store.normals[f] + store.offsets[f], store.normals[f])
        error = rng.normal(0, 0.1) + (offset_of_face0 if f == 0 else 0.0)
        points.append(p + store.normals[f] * (error + rng.normal(0, 0.05, (n, 1))))
        faces.append(np.full(n, f))
    points, faces = np.vstack(points), np.concatenate(faces)
    distance = np.einsum("ij,ij->i", points, store.normals[faces]) + store.offsets[faces]
    assignment = Assignment(np.arange(len(points)), faces, distance, 1.5)
    return points, assignment, store


def test_the_face_test_drops_the_face_the_others_contradict():
    from colmap_citymodel.adjust.faces import snooped_faces

    points, assignment, store = faces_scene(1.0)
    dropped = snooped_faces(points, assignment, store, sigma_dtp=0.2, sigma_face=0.2)
    assert list(dropped) == [0] and dropped[0] > 3.3
    # Faces within their generalisation error stay, also the one with the most points.
    points, assignment, store = faces_scene(0.0)
    assert snooped_faces(points, assignment, store, sigma_dtp=0.2, sigma_face=0.2) == {}


def test_the_face_test_judges_only_its_candidates():
    from colmap_citymodel.adjust.faces import snooped_faces

    # The contradicted face is not a candidate (a terrain cell, with its own error model): it
    # stays, and still helps place the block for the others, none of which is dropped.
    points, assignment, store = faces_scene(1.0)
    candidates = np.arange(store.num_faces) != 0
    assert snooped_faces(points, assignment, store, sigma_dtp=0.2, sigma_face=0.2,
                         candidates=candidates) == {}
    # As a candidate the same face is dropped, with or without the mask naming it.
    assert list(snooped_faces(points, assignment, store, sigma_dtp=0.2, sigma_face=0.2,
                              candidates=np.ones(store.num_faces, bool))) == [0]


def test_a_face_no_other_face_checks_is_kept():
    from colmap_citymodel.adjust.faces import snooped_faces

    points, assignment, store = faces_scene(1.0)
    # With only the roofs and the walls facing it (none parallel), nothing checks its offset.
    parallel = np.abs(store.normals @ store.normals[0]) > 0.9
    alone = assignment.without(parallel[assignment.face_index] & (assignment.face_index != 0))
    assert 0 not in snooped_faces(points, alone, store, sigma_dtp=0.2, sigma_face=0.2)


def camera_rms(result, street_scene) -> float:
    return float(np.sqrt(np.mean(np.square(centre_errors(result.reconstruction,
                                                         street_scene.truth)))))


def same_face(result, store, face) -> int:
    """The face of `store` in the model refine kept near the block (numbered anew)."""
    same = np.flatnonzero(np.linalg.norm(result.store.centroids - store.centroids[face],
                                         axis=1) < 1e-6)
    assert len(same) == 1
    return int(same[0])


def test_an_arcade_2_m_behind_the_model_does_not_pull_the_block(street_scene, deep_arcade):
    store, face = deep_arcade
    result = refine(street_scene.sfm, store, street_scene.gnss(), RefineOptions(),
                    progress=False)
    assert not np.any(result.assignment.face_index == same_face(result, store, face))
    assert camera_rms(result, street_scene) < 0.03


def test_faces_as_units_want_the_gnss_bias_estimated(street_scene, arcade):
    """Faces as units weigh the model as one observation per face, so a GNSS bias the
    adjustment does not know pulls the block further than per point; estimated beside them
    (--gnss_bias auto) it does not."""
    from colmap_citymodel.block.gnss import GNSSObservations

    store, _ = arcade
    scene = street_scene
    biased = GNSSObservations(scene.gnss_names, scene.gnss_positions_crs + [3.0, -4.0, 2.0],
                              scene.gnss_sigmas, scene.store.crs, "synthetic")

    def error(gnss_offset: str) -> float:
        options = faces_as_units()
        options.adjustment.gnss_offset = gnss_offset
        result = refine(scene.sfm, store, biased, options, progress=False)
        return float(np.sqrt(np.mean(np.square(centre_errors(result.reconstruction,
                                                               scene.truth)))))

    pulled, estimated = error("none"), error("all")
    assert estimated < 0.008
    assert estimated < 0.7 * pulled


@pytest.fixture(scope="module")
def one_large_face(street_scene):
    """The street with most of its street-facing tie points on one facade: every other facade
    along the street keeps 30 of its points, the largest keeps all of its own (about as many
    as the others together). That facade is modelled 0.3 m in front of its surface, within
    what a LOD2 model's generalisation error allows. Returns the reconstruction, the model,
    the facade and the true tie points that remain (by id)."""
    import pycolmap

    from colmap_citymodel.assign.direct import assign_direct
    from colmap_citymodel.options import AssignmentOptions

    scene, store = street_scene, street_scene.store
    ids = np.array(sorted(scene.truth.points3D))
    points = np.array([scene.truth.point3D(int(i)).xyz for i in ids])
    found = assign_direct(points, ids, store, 0.3, AssignmentOptions())
    along = [f for f in np.unique(found.face_index[found.assigned])
             if abs(store.normals[f][1]) > 0.9]
    counts = [int(np.sum(found.assigned & (found.face_index == f))) for f in along]
    face = int(along[int(np.argmax(counts))])
    rng = np.random.default_rng(0)
    dropped = []
    for f in along:
        if f != face:
            rows = np.flatnonzero(found.assigned & (found.face_index == f))
            dropped += list(np.asarray(found.point_ids)[rng.permutation(rows)[30:]])
    sfm = pycolmap.Reconstruction(scene.sfm)
    for point_id in dropped:
        sfm.delete_point3D(int(point_id))
    kept = ~np.isin(ids, dropped)
    vertices = store.vertices.copy()
    vertices[store.face_vertex_ids(face)] += 0.3 * store.normals[face]
    return sfm, store.with_vertices(vertices), face, ids[kept], points[kept]


def planes_alone_floors(scene, store, ids, points) -> dict[str, float]:
    """The camera-centre RMS 3D (m) that fitting the true tie points onto `store`'s planes by a
    similarity (linearised about the cameras' centroid, no other prior) gives the true cameras,
    every point alike and each face once (its points' weights divided by their number)."""
    from colmap_citymodel.assign.direct import assign_direct
    from colmap_citymodel.options import AssignmentOptions

    found = assign_direct(points, ids, store, 0.45, AssignmentOptions())
    faces, xyz = found.face_index[found.assigned], points[found.assigned]
    normals = store.normals[faces]
    cameras = np.array([im.projection_center() for im in scene.truth.images.values()])
    centre = cameras.mean(0)
    lever = xyz - centre
    design = np.c_[normals, np.cross(lever, normals), np.einsum("ij,ij->i", normals, lever)]
    distance = np.einsum("ij,ij->i", normals, xyz) + store.offsets[faces]
    unique, inverse, count = np.unique(faces, return_inverse=True, return_counts=True)
    out = {}
    for name, weight in (("per point", np.ones(len(faces))), ("per face", 1.0 / count[inverse])):
        root = np.sqrt(weight)
        p, *_ = np.linalg.lstsq(design * root[:, None], -distance * root, rcond=None)
        move = p[:3] + np.cross(p[3:6], cameras - centre) + p[6] * (cameras - centre)
        out[name] = float(np.sqrt(np.mean(np.sum(move ** 2, axis=1))))
    return out


def test_a_block_mostly_on_one_large_face_lands_at_its_floor(street_scene, one_large_face):
    """Where most tie points lie on one facade whose model stands 0.3 m off it, every point
    alike lets that one face's error carry the block; with the faces' errors as unknowns
    (the default) the block lands within 1.3x the lower of its planes-alone floors."""
    sfm, store, face, ids, points = one_large_face
    floors = planes_alone_floors(street_scene, store, ids, points)
    assert floors["per face"] < 0.5 * floors["per point"]  # the scene is what it claims
    result = refine(sfm, store, street_scene.gnss(), RefineOptions(), progress=False)
    assert camera_rms(result, street_scene) <= 1.3 * min(floors.values())
    # The facade's error is its own: the other faces contradict it, and the report says so.
    row = {row["face"]: row for row in face_table(result)}[same_face(result, store, face)]
    assert row["status"] == "dropped" and "face test" in row["why"]
    alike = RefineOptions()
    alike.adjustment.face_weighting = "per_point"
    result = refine(sfm, store, street_scene.gnss(), alike, progress=False)
    assert camera_rms(result, street_scene) > 1.3 * floors["per face"]
