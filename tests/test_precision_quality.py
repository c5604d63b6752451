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
from colmap_citymodel.precision.quality import gnss_alone
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


def test_a_height_on_one_roof_is_flagged_and_states_the_roofs_sigma():
    """Facades on both sides plus one small roof: the roof alone fixes the height, so leaving
    it out leaves the height to GNSS. It is flagged, and its sigma is the roof's (its
    generalisation error), not GNSS's: whether the roof is the right one the verdict's tests
    judge."""
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
    # The roof's at the images: sharpened a little by the facades' and GNSS's hold on the
    # rotations, widened a little by the block's tilt, which moves its far images.
    assert 0.7 * height["sigma_planes"] < height["sigma"] <= 1.25 * height["sigma_planes"]
    assert height["sigma"] < 0.5 * 5.0 / np.sqrt(30)
    assert "U" not in gnss_alone(result)


def test_only_directions_no_plane_holds_rest_on_gnss_alone():
    rows = {"E": {"source": "planes"}, "N": {"source": "gnss", "one_plane": False},
            "U": {"source": "gnss", "one_plane": True}}
    assert gnss_alone(rows) == ["N"]  # E: the planes'; U: one roof holds it


def test_a_loop_stopped_before_it_settled_is_weak(scene, street_refined):
    """No similarity rounds and one iteration only: the first solve moves the block by metres
    onto its planes, so the loop has not settled, and the verdict says so. Every tie point
    alike: one loop (with the faces' errors estimated a second one runs from its block)."""
    options = RefineOptions()
    options.adjustment.face_weighting = "per_point"
    options.workflow.max_iterations = 1
    options.workflow.alignment_rounds = 0
    result = refine(scene.sfm, scene.store, scene.gnss(), options, progress=False)
    metrics = result.quality.metrics
    assert metrics["loop_iterations"] == 1
    assert metrics["unsettled_shift_m"] > metrics["position_sigma_m"]
    assert result.quality.verdict == "weak"
    assert any("had not settled after 1 iterations" in r for r in result.quality.reasons)
    # One step tells no rate: the stated sigmas count it whole as the move still to come.
    for axis in "ENU":
        row = result.observability[axis]
        assert row["sigma"] >= row["remaining_move_m"] > 0
    settled = street_refined  # the default options on the same street
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
