"""Faces' generalisation errors as random effects (AdjustmentOptions.face_weighting
"offsets"): each face's offset and tilts are unknowns with priors, shared by its points, and
what is left of a point's distance (the surface's relief, its noise) is measured in the
block's own units, so that free offsets do not let the block shrink."""

import numpy as np
import pytest

from colmap_citymodel.adjust import problem as problem_module
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.precision.checkpoints import helmert_transform
from colmap_citymodel.simulate.synthetic import (StreetSceneOptions, centre_errors,
                                                 make_street_scene)
from colmap_citymodel.workflow import refine


def face_effects(gnss_offset: str = "all") -> RefineOptions:
    options = RefineOptions()
    options.adjustment.face_weighting = "offsets"
    options.adjustment.gnss_offset = gnss_offset
    return options


def camera_rms(result, scene) -> float:
    return float(np.sqrt(np.mean(np.square(centre_errors(result.reconstruction,
                                                         scene.truth)))))


def block_scale(result, scene) -> float:
    """The refined block's scale against the truth's (1: right; < 1: too large)."""
    truth = {im.name: im.projection_center() for im in scene.truth.images.values()}
    images = [im for im in result.reconstruction.images.values() if im.has_pose]
    return helmert_transform(np.array([truth[im.name] for im in images]),
                             np.array([im.projection_center() for im in images])).scale


@pytest.fixture(scope="module")
def rough_street():
    """The synthetic street with 0.25 m of relief on every facade and roof (window recesses,
    balconies, roof furniture), which no LOD2 model holds."""
    return make_street_scene(StreetSceneOptions(seed=7, relief_sigma=0.25))


def test_free_offsets_keep_the_block_scale_with_the_relief_in_block_units(rough_street,
                                                                          monkeypatch):
    scene = rough_street
    result = refine(scene.sfm, scene.store, scene.gnss(), face_effects(), progress=False)
    assert abs(block_scale(result, scene) - 1) < 2e-3
    assert camera_rms(result, scene) < 0.05
    # The same model with the distances in metres: shrinking the block shrinks the relief's
    # residuals, and the faces' free offsets let it.
    monkeypatch.setattr(problem_module, "MIN_SCALE_BASE", float("inf"))
    metres = refine(scene.sfm, scene.store, scene.gnss(), face_effects(), progress=False)
    assert block_scale(metres, scene) - 1 > 5e-3
    assert camera_rms(metres, scene) > 4 * camera_rms(result, scene)


def test_the_faces_effects_stay_within_their_priors_on_a_right_model(street_scene):
    result = refine(street_scene.sfm, street_scene.store, street_scene.gnss(), face_effects(),
                    progress=False)
    assert camera_rms(result, street_scene) < 0.02
    precision = result.precision
    offsets = precision.plane_generalisation
    sigmas = precision.plane_generalisation_sigma
    assert len(offsets) and np.all(np.isfinite(sigmas))
    # The model is right up to 3 cm of relief: no face's offset beyond 3 of its sigmas, the
    # sigmas no larger than the prior's (the faces' own estimate of it).
    assert np.all(np.abs(offsets) < 3 * sigmas)
    assert np.all(sigmas <= result.assignment.face_sigma + 1e-9)


def test_an_arcade_behind_the_model_does_not_pull_the_block(street_scene):
    from test_adjust_faces import arcade_model

    store, _ = arcade_model(street_scene, 2.0)
    result = refine(street_scene.sfm, store, street_scene.gnss(), face_effects(),
                    progress=False)
    assert camera_rms(result, street_scene) < 0.03


def biased_gnss(scene, bias):
    from colmap_citymodel.block.gnss import GNSSObservations

    return GNSSObservations(scene.gnss_names, scene.gnss_positions_crs + np.asarray(bias),
                            scene.gnss_sigmas, scene.store.crs, "synthetic")


def test_the_gnss_bias_is_a_random_effect_beside_the_faces(street_scene):
    """A 5.4 m GNSS bias, not asked for: the faces' effects estimate it beside them with its
    prior (its share of the stated sigmas), and the block lands on the model."""
    options = face_effects(gnss_offset="none")
    result = refine(street_scene.sfm, street_scene.store,
                    biased_gnss(street_scene, [3.0, -4.0, 2.0]), options, progress=False)
    assert camera_rms(result, street_scene) < 0.02
    offset = result.gnss_offset
    assert offset is not None and offset["random_effect"]
    share = options.adjustment.gnss_bias_share
    assert np.allclose(offset["prior_sigma_used_m"], share * np.array([3.0, 3.0, 5.0]))
    assert result.quality.verdict != "failed"


def test_a_model_placed_elsewhere_is_not_taken_for_a_gnss_bias(street_scene):
    """The model 25 m off where the GNSS puts the block: the bias the faces would need lies far
    outside its prior, and the verdict fails."""
    store = street_scene.store
    shifted = store.with_vertices(store.vertices + [25.0, 0.0, 0.0])
    result = refine(street_scene.sfm, shifted, street_scene.gnss(), face_effects("none"),
                    progress=False)
    assert result.quality.verdict == "failed"


def test_the_placement_test_sees_the_points_where_their_faces_estimates_put_them(
        street_scene, monkeypatch):
    """A model whose vertices are each off by 0.15 m: the faces' estimated effects leave the
    tie points off the given faces, and the placement test scores them where those estimates
    put them, so they fit the model better there than as they lie."""
    rng = np.random.default_rng(3)
    store = street_scene.store
    rough = store.with_vertices(store.vertices + rng.normal(0, 0.15, store.vertices.shape))

    def best_share():
        result = refine(street_scene.sfm, rough, street_scene.gnss(), face_effects("none"),
                        progress=False)
        assert camera_rms(result, street_scene) < 0.05
        return result.quality.metrics["placement"]["best_share"]

    seen = best_share()
    monkeypatch.setattr(problem_module.HybridProblem, "face_effect_shifts",
                        lambda self, ids: np.zeros((len(ids), 3)))
    as_they_lie = best_share()
    assert seen > as_they_lie + 0.03


def test_the_faces_errors_start_where_every_point_alike_placed_the_block(street_scene):
    """Two loops: every tie point alike from the wide first threshold on, then the faces'
    errors as unknowns from that block, never at a wider threshold than the first loop's last;
    the block lands on the model with GNSS 5.4 m off."""
    result = refine(street_scene.sfm, street_scene.store,
                    biased_gnss(street_scene, [3.0, -4.0, 2.0]), face_effects("none"),
                    progress=False)
    phases = [record.phase for record in result.iterations]
    first = [record for record in result.iterations if record.phase == "loop"]
    second = [record for record in result.iterations if record.phase == "faces"]
    assert first and second and phases == ["loop"] * len(first) + ["faces"] * len(second)
    assert [record.iteration for record in result.iterations] == list(range(len(phases)))
    assert first[0].threshold > 1.0
    assert max(record.threshold for record in second) <= first[-1].threshold + 1e-9
    assert camera_rms(result, street_scene) < 0.03


def test_a_model_correction_and_the_sliding_windows_weigh_every_point_alike(street_scene):
    """A model correction frees the faces' vertices, which estimate their errors there: with
    it refine weighs every tie point alike throughout. The sliding window's windows do too,
    and the global loop after them estimates the faces' errors from where they left it."""
    options = face_effects("none")
    options.adjustment.correct_model = True
    corrected = refine(street_scene.sfm, street_scene.store, street_scene.gnss(), options,
                       progress=False)
    phases = {record.phase for record in corrected.iterations}
    assert "correction" in phases and "faces" not in phases
    assert camera_rms(corrected, street_scene) < 0.02
    options = face_effects("none")
    options.workflow.mode = "sliding_window"
    options.workflow.window_size, options.workflow.window_new = 30, 10
    windows = refine(street_scene.sfm, street_scene.store, street_scene.gnss(), options,
                     progress=False)
    assert "faces" in {record.phase for record in windows.iterations}
    assert camera_rms(windows, street_scene) < 0.02


def test_the_faces_errors_do_not_establish_a_placement_the_first_loop_fails():
    """The street's model 30 m north of where GNSS puts the block: every point alike, a
    neighbouring placement fits about as well (the gate fails it as ambiguous). Estimated
    from there, the faces' effects would make that placement look unique; they refine a
    placement, they do not establish one, so they are not estimated and the block fails."""
    from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene

    scene = make_street_scene(StreetSceneOptions(seed=11))
    store = scene.store.with_vertices(scene.store.vertices + [0.0, 30.0, 0.0])
    result = refine(scene.sfm, store, scene.gnss(), face_effects("none"), progress=False)
    assert "faces" not in {record.phase for record in result.iterations}
    assert result.quality.verdict == "failed"


def test_a_face_no_tie_point_lies_on_keeps_its_offset_at_zero(street_scene):
    """Each face's offset and tilts are unknowns only where tie points lie on it: the faces
    of the model near the block that hold none get no effect (their offset stays 0), and
    every estimated effect belongs to a face with points."""
    from colmap_citymodel.output.write import face_table

    result = refine(street_scene.sfm, street_scene.store, street_scene.gnss(), face_effects(),
                    progress=False)
    rows = [row for row in face_table(result) if row["status"] != "dropped"]
    with_points = {row["face"] for row in rows if row["points"] > 0}
    assert with_points and all(row["points"] > 0 for row in rows)
    assert len(result.store.faces) > len(with_points)  # faces near the block hold none
    assert len(result.precision.plane_generalisation) == len(with_points)
