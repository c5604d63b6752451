"""A constant GNSS offset estimated from the model: GNSS heights in another height system
(`--gnss_height_offset auto`), a constant 3D bias (`--gnss_bias auto`), and the refusal where
the model planes cannot fix them. The synthetic street with known truth (tests/conftest.py)."""

import numpy as np
import pytest

from colmap_citymodel.adjust.observability import gnss_information, observability, offset_refusal
from colmap_citymodel.align.initial_alignment import similarity_to_planes
from colmap_citymodel.block.priors import GNSSPriors
from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.errors import DatumError, GNSSError
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.simulate.synthetic import centre_errors
from colmap_citymodel.workflow import refine

#: GNSS heights above take-off instead of in the model's height system.
HEIGHT_OFFSET = 120.0


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


def gnss_mean_error(scene) -> np.ndarray:
    """The simulated GNSS's own mean error (GNSS minus true camera centre), E N U."""
    truth = {im.name: im.projection_center() for im in scene.truth.images.values()}
    local = scene.store.to_local(scene.gnss_positions_crs)
    return np.mean([p - truth[n] for n, p in zip(scene.gnss_names, local)], axis=0)


@pytest.fixture(scope="module")
def above_take_off(street_scene):
    """Refine with GNSS heights 120 m too high and the height offset estimated."""
    gnss = street_scene.gnss()
    gnss.positions = gnss.positions + [0.0, 0.0, HEIGHT_OFFSET]
    options = RefineOptions()
    options.adjustment.gnss_offset = "height"
    return refine(street_scene.sfm, street_scene.store, gnss, options, progress=False)


def test_height_offset_of_120_m_is_found_from_the_roofs(street_scene, above_take_off):
    result = above_take_off
    # Model minus GNSS: the applied 120 m and the GNSS's own mean height error.
    expected = -(HEIGHT_OFFSET + gnss_mean_error(street_scene)[2])
    offset = result.gnss_offset
    assert offset["value_m"] == pytest.approx(expected, abs=0.2)
    assert offset["estimated"] == "height" and offset["prior_dropped"]
    # Its sigma: the planes' hold on the height and the mean of 72 GNSS heights (5 m each).
    assert 0.5 < offset["sigma_m"] < 0.7
    assert result.gnss_priors.offset[:2].tolist() == [0.0, 0.0]
    # The block is as good as with heights in the model's system (test_workflow: < 0.10 m),
    # and the 120 m move counts as explained, not as the model pulling the block away.
    assert rms(centre_errors(result.reconstruction, street_scene.truth)) < 0.10
    assert result.quality.verdict == "ok", result.quality.todict()
    assert abs(result.quality.metrics["shift_enu_m"][2]) < 0.5  # the GNSS bias is horizontal
    assert result.observability["U"]["source"] == "planes"
    assert result.observability["U"]["sigma_gnss"] is None  # GNSS's level is not used


def test_report_and_console_name_the_offset(tmp_path, above_take_off):
    import json

    from colmap_citymodel.output.write import write_refined
    from colmap_citymodel.workflow import offset_line

    write_refined(above_take_off, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["gnss_height_offset"]["value_m"] == pytest.approx(
        above_take_off.gnss_offset["value_m"])
    assert "GNSS height offset" in (tmp_path / "out" / "report.md").read_text()
    line = offset_line(report["gnss_height_offset"])
    assert line.startswith("GNSS height offset") and "+-" in line


@pytest.mark.slow
def test_without_auto_120_m_off_heights_are_not_found(street_scene):
    # The ordinary start-up searches the height within 4 GNSS sigma only: the model cannot
    # help, and refine says so instead of handing back a block on the wrong roofs.
    gnss = street_scene.gnss()
    gnss.positions = gnss.positions + [0.0, 0.0, HEIGHT_OFFSET]
    result = refine(street_scene.sfm, street_scene.store, gnss, RefineOptions(), progress=False)
    assert result.quality.verdict == "failed"
    # No offset estimated: at most the GNSS bias as a random effect with its prior.
    assert result.gnss_offset is None or result.gnss_offset["random_effect"]


def test_height_offset_is_refused_where_no_roof_fixes_the_height(street_scene):
    store = street_scene.store
    walls = [f for f, face in enumerate(store.faces) if face.semantic == "WallSurface"]
    walls_only = store_from_polygons(
        [store.to_crs(store.vertices[store.face_vertex_ids(f)]) for f in walls],
        semantics=["WallSurface"] * len(walls), origin=store.origin, crs=store.crs)
    gnss = street_scene.gnss()
    options = RefineOptions()
    options.adjustment.gnss_offset = "height"
    with pytest.raises(DatumError, match=r"GNSS height offset .* cannot be estimated .* height"):
        refine(street_scene.sfm, walls_only, gnss, options, progress=False)


def test_unconverted_heights_are_accepted_only_with_auto(street_scene):
    from colmap_citymodel.align.block_to_model import georegister
    import pycolmap

    gnss = street_scene.gnss()
    gnss.vertical_applied = False  # ellipsoidal, no geoid at all
    with pytest.raises(GNSSError, match="--gnss_height_offset auto"):
        georegister(pycolmap.Reconstruction(street_scene.sfm), street_scene.store, gnss, None)
    _, priors, _ = georegister(pycolmap.Reconstruction(street_scene.sfm), street_scene.store,
                               gnss, None, gnss_offset="height")
    assert priors.offset_axes.tolist() == [False, False, True]


def test_gnss_keeps_its_shape_but_not_its_level_along_a_free_axis():
    rng = np.random.default_rng(0)
    positions = rng.uniform(-50, 50, size=(30, 3)) * [1, 1, 0.1]
    sigmas = np.tile([3.0, 3.0, 5.0], (30, 1))
    fixed = gnss_information(positions, sigmas, positions.mean(0))
    free = gnss_information(positions, sigmas, positions.mean(0), [False, False, True])
    assert fixed[2, 2] == pytest.approx(30 / 25.0)
    assert free[2, 2] == pytest.approx(0.0, abs=1e-12)
    # E, N, scale and the rotation about U do not depend on the heights' level.
    np.testing.assert_allclose(free[[0, 1, 3, 6]][:, [0, 1, 3, 6]],
                               fixed[[0, 1, 3, 6]][:, [0, 1, 3, 6]], atol=1e-9)
    # A flat roof fixes the height; GNSS with a free offset no longer does.
    roof = np.column_stack([rng.uniform(0, 10, 200), rng.uniform(0, 10, 200), np.full(200, 12)])
    normals = np.tile([0.0, 0.0, 1.0], (200, 1))
    result = observability(roof, normals, np.zeros(200, int), positions, sigmas, 0.2, 0.2,
                           [False, False, True])
    assert result["U"]["sigma_gnss"] is None
    assert offset_refusal(result, [False, False, True]) is not None  # one roof: refused
    two_roofs = observability(np.vstack([roof, roof + [20, 0, 3]]), np.vstack([normals] * 2),
                              np.repeat([0, 1], 200), positions, sigmas, 0.2, 0.2,
                              [False, False, True])
    assert two_roofs["U"]["source"] == "planes"
    assert offset_refusal(two_roofs, [False, False, True]) is None
    assert "E position" in offset_refusal(two_roofs, [True, True, True])


def test_similarity_to_planes_ignores_the_gnss_level_along_a_free_axis():
    rng = np.random.default_rng(1)
    # Tie points on two roofs (z = 10 and z = 14) and two walls; the block is 0.3 m too high.
    pts, normals, offsets = [], [], []
    for n, d in (([0, 0, 1], -10.0), ([0, 0, 1], -14.0), ([1, 0, 0], -3.0), ([0, 1, 0], -4.0)):
        n = np.array(n, float)
        p = rng.uniform(-10, 10, size=(100, 3))
        p -= np.outer(p @ n + d, n)
        pts.append(p + [0, 0, 0.3])
        normals.append(np.tile(n, (100, 1)))
        offsets.append(np.full(100, d))
    pts, normals, offsets = np.vstack(pts), np.vstack(normals), np.concatenate(offsets)
    antennas = rng.uniform(-10, 10, size=(20, 3)) + [0, 0, 30.3]
    gnss = antennas - [0, 0, 0.3] + [0, 0, 40.0]  # GNSS heights 40 m too high
    sigmas = np.tile([3.0, 3.0, 5.0], (20, 1))
    free = similarity_to_planes(pts, normals, offsets, 0.2, antennas=antennas, gnss=gnss,
                                gnss_sigmas=sigmas, gnss_free_axes=[False, False, True])
    assert np.asarray(free.sim3.translation)[2] == pytest.approx(-0.3, abs=0.01)
    assert free.rms_after < 0.005
    pulled = similarity_to_planes(pts, normals, offsets, 0.2, antennas=antennas, gnss=gnss,
                                  gnss_sigmas=sigmas)
    assert pulled.rms_after > 0.03  # without it the GNSS level pulls the block off its planes


def test_priors_fit_and_remove_the_offset():
    priors = GNSSPriors(np.arange(3), np.zeros((3, 3)), np.ones((3, 3)),
                        offset_axes=np.array([False, False, True]))
    antennas = np.array([[1.0, 0.0, 10.0], [0.0, 1.0, 12.0], [0.0, 0.0, 14.0]])
    v = priors.normalised_residuals(antennas)
    np.testing.assert_allclose(v[:, 2], [-2.0, 0.0, 2.0])  # the level is removed
    np.testing.assert_allclose(v[:, :2], antennas[:, :2])
    assert priors.offset_directions().shape == (3, 1)


@pytest.mark.slow
def test_constant_3d_bias_is_found_where_the_planes_fix_all_directions(street_scene):
    # A constant bias of 6 m, 5 m, -4 m on top of the simulated GNSS's own error.
    applied = np.array([6.0, 5.0, -4.0])
    gnss = street_scene.gnss()
    gnss.positions = gnss.positions + applied
    options = RefineOptions()
    options.adjustment.gnss_offset = "all"
    result = refine(street_scene.sfm, street_scene.store, gnss, options, progress=False)
    expected = -(applied + gnss_mean_error(street_scene))
    np.testing.assert_allclose(result.gnss_offset["bias_enu_m"], expected, atol=0.2)
    assert all(s is not None and s < 1.0 for s in result.gnss_offset["bias_sigma_enu_m"])
    assert rms(centre_errors(result.reconstruction, street_scene.truth)) < 0.10
    assert result.quality.verdict == "ok", result.quality.todict()
