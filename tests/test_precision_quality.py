"""The quality gate and the start-up that must not run away: a good run says "ok", a model that
does not fit says "failed" and hands back the GNSS-only result (CLI exit 3), a block that starts
metres off the model still lands on it, and the alignment's scale stays where GNSS holds it."""

import json

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.observability import DATUM, observability
from colmap_citymodel.align.initial_alignment import similarity_to_planes
from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.citymodel.write_citygml import raw_from_store, write_citygml
from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.precision.quality import QualityThresholds, gnss_axis_shifts, quality_verdict
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, centre_errors, make_street_scene
from colmap_citymodel.workflow import refine


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


@pytest.fixture(scope="module")
def scene(street_scene):
    return street_scene


def shifted(store, shift):
    return store.with_vertices(store.vertices + np.asarray(shift, float))


def test_a_model_of_another_street_fails_and_hands_back_gnss_only(scene):
    """The street's model moved 30 m across the street: it still overlaps the block's area, but
    no facade is where the tie points are."""
    result = refine(scene.sfm, shifted(scene.store, [0.0, 30.0, 0.0]), scene.gnss(),
                    RefineOptions(), progress=False)
    assert result.quality.verdict == "failed", result.quality.todict()
    assert result.handed_back == "gnss_only"
    assert result.reconstruction is result.gnss_only
    # What is handed back is no worse than GNSS alone: it is GNSS alone.
    errors = centre_errors(result.reconstruction, scene.truth)
    assert rms(errors) == pytest.approx(rms(centre_errors(result.gnss_only, scene.truth)))
    assert result.quality.reasons


def test_gnss_metres_off_with_a_bias_still_lands_on_the_model():
    """A constant GNSS bias of 5.4 m (and 2 m white noise): more than a 2 m first assignment
    threshold can bridge; the coarse search brings the block within reach."""
    scene = make_street_scene(StreetSceneOptions(seed=5, gnss_bias=(4.0, -3.0, 2.0),
                                                 gnss_sigma=(2.0, 2.0, 2.0)))
    result = refine(scene.sfm, scene.store, scene.gnss(), RefineOptions(), progress=False)
    before = rms(centre_errors(result.gnss_only, scene.truth))
    after = rms(centre_errors(result.reconstruction, scene.truth))
    assert before > 3.0
    assert after < 0.15, (before, after, result.quality.todict())
    assert result.quality.verdict in ("ok", "weak")
    assert result.coarse_alignment["translation"]["near_share_after"] > \
        result.coarse_alignment["translation"]["near_share_before"]


def test_cli_exits_3_and_writes_the_gnss_only_result(tmp_path, capsys):
    scene = make_street_scene(StreetSceneOptions(seed=11), crs=user_crs("EPSG:25832"))
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    scene.sfm.write_binary(str(tmp_path / "sparse" / "0"))
    write_citygml(tmp_path / "model.gml", raw_from_store(shifted(scene.store, [0, 30.0, 0])))
    (tmp_path / "gnss.txt").write_text("\n".join(
        f"{n} {x:.4f} {y:.4f} {z:.4f} 3 3 5"
        for n, (x, y, z) in zip(scene.gnss_names, scene.gnss_positions_crs)) + "\n")
    out = tmp_path / "refined"
    code = cli_main(["refine", "--no_progress", "--input_path", str(tmp_path / "sparse" / "0"),
                     "--citymodel", str(tmp_path / "model.gml"), "--output_path", str(out),
                     "--gnss", str(tmp_path / "gnss.txt"), "--gnss_crs", "EPSG:25832"])
    stdout = capsys.readouterr().out
    assert code == 3
    assert "quality: failed" in stdout and "GNSS-only" in stdout
    geo = json.loads((out / "georeference.json").read_text())
    report = json.loads((out / "report.json").read_text())
    assert geo["result"] == "gnss_only" and report["result"] == "gnss_only"
    assert report["quality"]["verdict"] == "failed"
    assert set(report["observability"]) == set(DATUM)
    assert "Verdict: failed" in (out / "report.md").read_text()
    assert pycolmap.Reconstruction(str(out)).num_reg_images() == scene.sfm.num_reg_images()


def test_alignment_scale_stays_where_gnss_holds_it():
    """Tie points wrongly assigned to one plane through their middle: the planes alone are
    best served by shrinking the block onto that plane. With the GNSS scale prior the fit
    keeps the scale within a few of its sigmas."""
    rng = np.random.default_rng(0)
    points = rng.uniform([-40, -10, -10], [40, 10, 10], (2000, 3))
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    offsets = np.zeros(len(points))
    antennas = np.column_stack([np.linspace(-40, 40, 16), np.zeros(16), np.full(16, 15.0)])
    sigmas = np.tile([3.0, 3.0, 5.0], (16, 1))
    gnss = antennas + rng.normal(0, 1, antennas.shape) * sigmas
    free = similarity_to_planes(points, normals, offsets, 0.2, 2.0, antennas=antennas,
                                gnss=gnss, gnss_sigmas=sigmas)
    scale_sigma = 3.0 / np.sqrt(np.sum((antennas - antennas.mean(0)) ** 2))
    held = similarity_to_planes(points, normals, offsets, 0.2, 2.0, antennas=antennas,
                                gnss=gnss, gnss_sigmas=sigmas, scale_sigma=scale_sigma)
    assert free.sim3.scale < 0.8  # what happens without the prior
    assert abs(np.log(held.sim3.scale)) < 4 * scale_sigma


def test_observability_of_one_facade_row_is_cross_track_only():
    """Points on two parallel facades (normals +-y) fix the cross-track shift; the along-track
    shift and the height are left to GNSS."""
    rng = np.random.default_rng(1)
    left = np.column_stack([rng.uniform(-50, 50, 500), np.full(500, 10.0), rng.uniform(0, 15, 500)])
    right = left * [1, -1, 1]
    points = np.vstack([left, right])
    normals = np.vstack([np.tile([0, 1.0, 0], (500, 1)), np.tile([0, -1.0, 0], (500, 1))])
    groups = np.repeat([0, 1], 500)
    cams = np.column_stack([np.linspace(-50, 50, 30), np.zeros(30), np.full(30, 18.0)])
    result = observability(points, normals, groups, cams, np.tile([3.0, 3.0, 5.0], (30, 1)),
                           0.2, 0.2)
    assert result["N"]["source"] == "planes"
    assert result["E"]["source"] == "gnss" and result["U"]["source"] == "gnss"
    assert result["E"]["sigma_planes"] is None
    # A plane's many points count about once: two planes, sigma ~ 0.2 / sqrt(2).
    assert 0.1 < result["N"]["sigma"] < 0.2


def test_a_height_on_one_roof_is_flagged_and_only_as_precise_as_gnss():
    """Facades on both sides plus one small roof: the roof alone fixes the height, so leaving
    it out leaves the height to GNSS. It is flagged, and its sigma is GNSS's, not the roof's."""
    rng = np.random.default_rng(2)
    left = np.column_stack([rng.uniform(-50, 50, 500), np.full(500, 10.0), rng.uniform(0, 15, 500)])
    right = left * [1, -1, 1]
    roof = np.column_stack([rng.uniform(20, 30, 60), rng.uniform(12, 20, 60), np.full(60, 15.0)])
    points = np.vstack([left, right, roof])
    normals = np.vstack([np.tile([0, 1.0, 0], (500, 1)), np.tile([0, -1.0, 0], (500, 1)),
                         np.tile([0, 0, 1.0], (60, 1))])
    groups = np.repeat([0, 1, 2], [500, 500, 60])
    cams = np.column_stack([np.linspace(-50, 50, 30), np.zeros(30), np.full(30, 2.0)])
    sigmas = np.tile([3.0, 3.0, 5.0], (30, 1))
    result = observability(points, normals, groups, cams, sigmas, 0.2, 0.2)
    height = result["U"]
    assert height["one_plane"] and height["source"] == "gnss"
    assert height["sigma_planes"] < height["sigma_gnss"] / 2  # the roof, if it is right
    assert height["sigma"] == pytest.approx(height["sigma_gnss"])
    assert height["sigma"] == pytest.approx(5.0 / np.sqrt(30), rel=0.05)


def test_only_directions_left_to_gnss_are_compared_with_gnss():
    rows = {"E": {"source": "planes", "sigma_gnss": 0.5},
            "N": {"source": "gnss", "one_plane": False, "sigma_gnss": 0.5},
            "U": {"source": "gnss", "one_plane": True, "sigma_gnss": 0.8}}
    shifts = gnss_axis_shifts(np.array([2.0, -1.0, 4.0]), rows)
    assert shifts == {"N": pytest.approx(2.0)}  # E: the planes' own; U: a roof may move it
    assert gnss_axis_shifts(np.array([2.0, -1.0, 4.0]), rows, one_plane=True) == \
        {"U": pytest.approx(5.0)}


def test_verdict_rules():
    good = {"assigned_share": 0.6, "near_share": 0.8, "near_share_gnss_only": 0.1,
            "shift_m": 4.0, "shift_sigmas": 1.5, "planes_fix": ["E", "N", "U"]}
    assert quality_verdict(good).verdict == "ok"
    assert quality_verdict({**good, "shift_sigmas": 3.5}).verdict == "weak"
    # A move further than GNSS can be off fails, unless it brought a quarter of the tie points
    # near the model that were not near it before (here 10 % -> 80 %): weak, saying so.
    unbacked = {**good, "near_share_gnss_only": 0.7}
    assert quality_verdict({**unbacked, "shift_sigmas": 6.0}).verdict == "failed"
    backed = quality_verdict({**good, "shift_sigmas": 6.0})
    assert backed.verdict == "weak" and "10 % -> 80 %" in backed.reasons[0]
    height = {**good, "planes_fix": ["E", "N"], "shift_enu_m": [0.1, 0.2, 7.0],
              "gnss_axis_shift_sigmas": {"U": 8.8}}
    assert quality_verdict({**height, "near_share_gnss_only": 0.7}).verdict == "failed"
    assert quality_verdict(height).verdict == "weak"
    # The evidence must be the height's own: moved back to the GNSS-only height the tie
    # points fall off the model (a drive onto its walls and eaves) or stay on it (a horizontal
    # fit that carried the height along).
    onto_walls = quality_verdict({**height, "near_share_moved_back": {"U": 0.3}})
    assert onto_walls.verdict == "weak" and "10 % -> 80 %" in onto_walls.reasons[0]
    carried = quality_verdict({**height, "near_share_moved_back": {"U": 0.72}})
    assert carried.verdict == "failed" and "moved back in U, 72 %" in carried.reasons[0]
    assert quality_verdict({**good, "near_share": 0.05}).verdict == "failed"
    assert quality_verdict({**good, "planes_fix": []}).verdict == "weak"
    one_roof = quality_verdict({**good, "planes_fix": ["E", "N"], "one_plane": ["U"]})
    assert one_roof.verdict == "weak" and "single model plane" in one_roof.reasons[0]
    assert quality_verdict({**good, "position_sigma_m": 0.3}).verdict == "weak"
    # Half the walls off the model's: maybe the wrong building, whose sigmas say nothing.
    walls = quality_verdict({**good, "wall_near_share": 0.55})
    assert walls.verdict == "weak" and "wrong buildings" in walls.reasons[0]
    assert quality_verdict({**good, "wall_near_share": 0.4}).verdict == "failed"
    # GNSS residuals that grow but stay within their sigmas: the slow GNSS bias exposed.
    assert quality_verdict({**good, "gnss_scatter": 0.4, "gnss_scatter_ratio": 2.5}
                           ).verdict == "ok"
    assert quality_verdict({**good, "gnss_scatter": 2.0, "gnss_scatter_ratio": 2.5}
                           ).verdict == "weak"
    assert quality_verdict({**good, "diverged": "objective rose"}).verdict == "weak"
    # A scale change of 4 GNSS sigma: the planes may have seen it; GNSS alone may not.
    scaled = {**good, "scale_change": -0.04, "scale_change_sigmas": 4.0}
    assert quality_verdict({**scaled, "planes_fix": ["E", "N", "U", "scale"]}).verdict == "ok"
    assert quality_verdict(scaled).verdict == "failed"
    # A direction only GNSS fixes, moved several of its sigmas: not by GNSS.
    free_u = {**good, "planes_fix": ["E", "N"], "shift_enu_m": [0.1, 0.2, 3.0],
              "near_share_gnss_only": 0.7}
    assert quality_verdict({**free_u, "gnss_axis_shift_sigmas": {"U": 1.0}}).verdict == "weak"
    moved = quality_verdict({**free_u, "gnss_axis_shift_sigmas": {"U": 6.0}})
    assert moved.verdict == "failed" and "3.00 m in U" in moved.reasons[0]
    # A single roof that moved the block in height: said in so many words; weak up to 5 GNSS
    # sigma there, failed beyond unless the move brought the tie points onto the model.
    roof = {**free_u, "one_plane": ["U"]}
    assert not any("alone moved" in r for r in quality_verdict(
        {**roof, "one_plane_shift_sigmas": {"U": 2.0}}).reasons)
    near = quality_verdict({**roof, "one_plane_shift_sigmas": {"U": 4.0}})
    assert near.verdict == "weak" and any("alone moved the cameras 3.00 m in U (4.0 sigma" in r
                                          for r in near.reasons)
    far = quality_verdict({**roof, "one_plane_shift_sigmas": {"U": 8.0}})
    assert far.verdict == "failed" and any("alone moved the cameras 3.00 m in U (8.0 sigma" in r
                                           for r in far.reasons)
    far_backed = quality_verdict({**roof, "near_share_gnss_only": 0.1,
                                  "one_plane_shift_sigmas": {"U": 8.0}})
    assert far_backed.verdict == "weak" and any("10 % -> 80 %" in r for r in far_backed.reasons)
    # Fewer tie points near the model than with GNSS only, however few fewer: failed, with
    # the two shares printed so that they differ.
    fewer = quality_verdict({**good, "near_share": 0.8087, "near_share_gnss_only": 0.8112})
    assert fewer.verdict == "failed" and "(80.9 %) than with GNSS only (81.1 %)" in \
        fewer.reasons[0]
    assert "(70 %) than with GNSS only (81 %)" in quality_verdict(
        {**good, "near_share": 0.7, "near_share_gnss_only": 0.81}).reasons[0]
    t = QualityThresholds()
    assert quality_verdict({**good, "near_share": (t.min_near_share + t.failed_near_share) / 2}
                           ).verdict == "weak"
    # Out of iterations, still moving: weak; out of iterations but settled: nothing to say.
    moving = quality_verdict({**good, "loop_iterations": 10, "unsettled_shift_m": 0.3})
    assert moving.verdict == "weak" and "had not settled after 10 iterations" in \
        moving.reasons[0] and "0.30 m" in moving.reasons[0]
    assert quality_verdict({**good, "loop_iterations": 10, "unsettled_shift_m": 0.002}
                           ).verdict == "ok"


def test_a_loop_stopped_before_it_settled_is_weak(scene):
    """No similarity rounds and one iteration only: the first solve moves the block by metres
    onto its planes, so the loop has not settled, and the verdict says so."""
    options = RefineOptions()
    options.workflow.max_iterations = 1
    options.workflow.alignment_rounds = 0
    result = refine(scene.sfm, scene.store, scene.gnss(), options, progress=False)
    metrics = result.quality.metrics
    assert metrics["loop_iterations"] == 1
    assert metrics["unsettled_shift_m"] > QualityThresholds().unsettled_shift
    assert result.quality.verdict == "weak"
    assert any("had not settled after 1 iterations" in r for r in result.quality.reasons)
    settled = refine(scene.sfm, scene.store, scene.gnss(), RefineOptions(), progress=False)
    assert settled.quality.metrics["unsettled_shift_m"] is None


def test_an_exact_initial_transform_is_not_lost_to_biased_gnss():
    """A user's transform puts the block on the model, but the bundle adjustment with GNSS
    that follows moves it by the GNSS bias (5.4 m): the coarse search must bring it back."""
    scene = make_street_scene(StreetSceneOptions(seed=5, gnss_bias=(4.0, -3.0, 2.0),
                                                 gnss_sigma=(2.0, 2.0, 2.0)))
    names = [im.name for im in scene.sfm.images.values()]
    exact = pycolmap.estimate_sim3d(
        np.array([scene.sfm.find_image_with_name(n).projection_center() for n in names]),
        np.array([scene.truth.find_image_with_name(n).projection_center() for n in names])
        + scene.store.origin)
    result = refine(scene.sfm, scene.store, scene.gnss(), RefineOptions(),
                    initial_transform=exact, progress=False)
    before = rms(centre_errors(result.gnss_only, scene.truth))
    after = rms(centre_errors(result.reconstruction, scene.truth))
    assert before > 3.0
    assert after < 0.15, (before, after, result.quality.todict())
    assert result.coarse_alignment is not None
