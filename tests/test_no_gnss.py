"""Georegistration without GNSS: the city model as the only control, from a location hint.

The synthetic street's SfM input lies in an arbitrary frame (a random rotation, a scale of
0.2-0.6 and a drift): the search must recover heading, tilt, scale and position from the
model alone. A street of identical houses fits several places equally well and must fail
with the ambiguity reported; a hint far from any building must fail with a clear message.
"""

import json

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.align.coarse import SurfaceDistance
from colmap_citymodel.align.locate import AmbiguousLocationError, LocateOptions, locate
from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.citymodel.ground_faces import TERRAIN_CLASS
from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.citymodel.write_citygml import raw_from_store, write_citygml
from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.errors import GeoregistrationError
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.precision.ambiguity import placement_fit
from colmap_citymodel.precision.quality import DISTINCT, NEAR_DISTANCE, QualityThresholds, \
    placement_metrics
from colmap_citymodel.simulate import synthetic
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, centre_errors
from colmap_citymodel.workflow import refine


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


def true_centre(scene) -> np.ndarray:
    """Mean true camera centre, model CRS."""
    return np.mean([im.projection_center() for im in scene.truth.images.values()],
                   axis=0) + scene.store.origin


@pytest.fixture(scope="module")
def turned_scene(street_scene):
    """The street's SfM block turned by another 137 deg about a tilted axis and scaled by 7.3
    on top of its random similarity."""
    sfm = pycolmap.Reconstruction(street_scene.sfm)
    axis = np.array([0.2, -0.1, 1.0])
    axis *= np.radians(137.0) / np.linalg.norm(axis)
    sfm.transform(pycolmap.Sim3d(7.3, pycolmap.Rotation3d(axis), [12.0, -40.0, 3.0]))
    return street_scene, sfm


def test_a_turned_and_scaled_block_is_registered_from_a_hint_40_m_off(turned_scene):
    scene, sfm = turned_scene
    hint = true_centre(scene)[:2] + 40.0 * np.array([np.cos(2.0), np.sin(2.0)])
    result = refine(sfm, scene.store, None, RefineOptions(), location=hint, progress=False)
    assert rms(centre_errors(result.reconstruction, scene.truth)) < 0.10
    assert result.quality.verdict != "failed"
    geo = result.georegistration
    assert geo["method"] == "model only"
    assert geo["hypotheses_2d"] > 1 and geo["best_score"] > geo["runner_up_score"]
    assert geo["score_ratio"] < LocateOptions().max_ratio
    assert 30.0 < geo["hint_distance_m"] < 50.0
    assert result.iterations[-1].final.count["gnss"] == 0  # the model is the only datum
    assert result.datum_cues["scale"] == "model only"


@pytest.mark.slow
def test_useless_gnss_is_replaced_by_the_model_search(street_scene):
    """GNSS stated at 50 m (and 30 m off): the search runs around its mean, without it."""
    gnss = street_scene.gnss()
    gnss.positions = np.asarray(gnss.positions) + [30.0, -20.0, 0.0]
    gnss.sigmas = np.full_like(np.asarray(gnss.sigmas, float), 50.0)
    result = refine(street_scene.sfm, street_scene.store, gnss, RefineOptions(),
                    progress=False)
    assert result.georegistration["gnss_ignored"] is True
    assert result.gnss_priors is None
    assert rms(centre_errors(result.reconstruction, street_scene.truth)) < 0.10


def test_gnss_too_short_to_turn_a_block_finds_it_on_the_model_and_keeps_its_priors():
    """A short sequence (eight stations 0.8 m apart: its GNSS positions spread less than twice
    their 3 m sigma, too little for a similarity): the GNSS mean is the model search's hint,
    the block is found on the model, and GNSS stays as its priors."""
    scene = synthetic.make_street_scene(StreetSceneOptions(seed=3, num_stations=8,
                                                           station_spacing=0.8))
    result = refine(scene.sfm, scene.store, scene.gnss(), RefineOptions(), progress=False)
    assert result.georegistration["short_baseline"] is True
    assert result.gnss_priors is not None and result.quality.verdict != "failed"
    assert rms(centre_errors(result.reconstruction, scene.truth)) < 0.10


def identical_houses(options, rng):
    """Both sides of the street: the same gabled house every 16 m, far beyond the block."""
    rings, semantics, buildings = [], [], []
    for side in (1.0, -1.0):
        near = side * options.street_half_width
        y0, y1 = sorted((near, side * (options.street_half_width + 10.0)))
        for k, x in enumerate(np.arange(-150.0, 200.0, 16.0)):
            r, s = synthetic.building_polygons(x, x + 12.0, y0, y1, 10.0, 14.0, near)
            rings += r
            semantics += s
            buildings += [f"b{side:+.0f}{k}"] * len(r)
    return rings, semantics, buildings


@pytest.fixture(scope="module")
def identical_street():
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(synthetic, "street_polygons", identical_houses)
        return synthetic.make_street_scene(StreetSceneOptions(seed=3, num_stations=12),
                                           crs=user_crs("EPSG:25832"))


def test_a_street_of_identical_houses_is_ambiguous_and_fails(identical_street):
    scene = identical_street
    hint = true_centre(scene)[:2] - scene.store.origin[:2] + [20.0, 5.0]
    with pytest.raises(AmbiguousLocationError) as caught:
        locate(scene.sfm, scene.store, hint)
    report = caught.value.report
    assert report["verdict"] == "failed"
    assert report["score_ratio"] > LocateOptions().max_ratio
    assert report["runner_up_offset_m"] > 5.0
    assert caught.value.exit_code == 3


def house_on_ground(houses_x):
    """Flat-roofed houses 12 x 10 x 6 m at `houses_x` on a terrain face 120 m square (as
    refine adds from a DTM or the buildings' feet)."""
    rings = [np.array([(-60, -60, 0), (60, -60, 0), (60, 60, 0), (-60, 60, 0)], float)]
    semantics = [TERRAIN_CLASS]
    for x0 in houses_x:
        semantics += ["WallSurface"] * 4 + ["RoofSurface"]
        x1, y0, y1, h = x0 + 12.0, 0.0, 10.0, 6.0
        rings += [np.array(r, float) for r in (
            [(x0, y0, 0), (x1, y0, 0), (x1, y0, h), (x0, y0, h)],
            [(x1, y0, 0), (x1, y1, 0), (x1, y1, h), (x1, y0, h)],
            [(x1, y1, 0), (x0, y1, 0), (x0, y1, h), (x1, y1, h)],
            [(x0, y1, 0), (x0, y0, 0), (x0, y0, h), (x0, y1, h)],
            [(x0, y0, h), (x1, y0, h), (x1, y1, h), (x0, y1, h)])]
    store = store_from_polygons(rings, semantics=semantics, origin=np.zeros(3))
    return SurfaceDistance(store, threads=1)


def loop_round_a_house(rng):
    """Tie points of a drone loop round the house at x 0..12: 90 % on the ground around it,
    the rest on its walls and roof."""
    ground = np.column_stack([rng.uniform(-25, 37, 5000), rng.uniform(-20, 30, 5000),
                              np.zeros(5000)])
    ground = ground[~((ground[:, 0] > 0) & (ground[:, 0] < 12) & (ground[:, 1] > 0)
                      & (ground[:, 1] < 10))][:3000]
    u, v = rng.uniform(0, 1, (2, 60))
    walls = [np.column_stack([12 * u, np.zeros(60), 6 * v]),
             np.column_stack([np.full(60, 12.0), 10 * u, 6 * v]),
             np.column_stack([12 * u, np.full(60, 10.0), 6 * v]),
             np.column_stack([np.zeros(60), 10 * u, 6 * v]),
             np.column_stack([12 * u, 10 * v, np.full(60, 6.0)])]
    return np.vstack([ground] + walls)


def test_the_ground_around_a_house_does_not_make_its_placement_ambiguous():
    """A house alone on the terrain, most tie points on the ground round it: the terrain fits
    every horizontal shift alike, so scored with it a shift by one house width fits almost as
    well; the placement test scores the city model's faces, which hold the house in one place.
    Two such houses side by side stay ambiguous."""
    rng = np.random.default_rng(7)
    points = loop_round_a_house(rng)
    alone = house_on_ground([0.0])
    t = QualityThresholds()

    class Opaque:  # the same distances without the faces' classes
        def __call__(self, p, within):
            return alone(p, within)

    diluted = placement_fit(points, Opaque(), 30.0, lambda g: np.ones(len(g), bool),
                            radius=NEAR_DISTANCE, distinct=DISTINCT)
    assert diluted.ratio < t.ambiguity_ratio  # the ground alone nearly fits any shift
    placement = placement_metrics(points, alone, None, None, t)
    assert placement["ratio"] is None or placement["ratio"] > 1.5
    assert placement["best_shift_m"] == pytest.approx([0.0, 0.0])
    twins = placement_metrics(points, house_on_ground([0.0, 16.0]), None, None, t)
    assert twins["ratio"] < t.ambiguity_ratio
    assert np.abs(np.subtract(twins["alternative_shift_m"], twins["best_shift_m"])) \
        == pytest.approx([16.0, 0.0], abs=1.1)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory, street_scene):
    """The synthetic street written as a user without GNSS would have it."""
    root = tmp_path_factory.mktemp("nognss")
    scene = synthetic.make_street_scene(StreetSceneOptions(seed=7), crs=user_crs("EPSG:25832"))
    (root / "sparse" / "0").mkdir(parents=True)
    scene.sfm.write_binary(str(root / "sparse" / "0"))
    write_citygml(root / "model.gml", raw_from_store(scene.store))
    return root, scene


def run(args, capsys):
    code = cli_main(["refine", "--no_progress", *map(str, args)])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_a_hint_300_m_off_fails_with_a_clear_message(workspace, tmp_path, capsys):
    root, scene = workspace
    x, y = true_centre(scene)[:2] + [0.0, 300.0]
    out = tmp_path / "out"
    code, _, err = run(["--input_path", root / "sparse" / "0", "--citymodel",
                        root / "model.gml", "--output_path", out, "--location", x, y,
                        "--location_radius", 100], capsys)
    assert code == 2
    assert "location hint" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


def test_an_ambiguous_block_writes_only_its_report(identical_street, tmp_path, capsys):
    scene = identical_street
    root = tmp_path / "ws"
    (root / "sparse" / "0").mkdir(parents=True)
    scene.sfm.write_binary(str(root / "sparse" / "0"))
    write_citygml(root / "model.gml", raw_from_store(scene.store))
    x, y = true_centre(scene)[:2] + [20.0, 5.0]
    out = tmp_path / "out"
    code, stdout, err = run(["--input_path", root / "sparse" / "0", "--citymodel",
                             root / "model.gml", "--output_path", out, "--location", x, y],
                            capsys)
    assert code == 3
    assert "two places" in err
    assert sorted(p.name for p in out.iterdir()) == ["report.json"]
    report = json.loads((out / "report.json").read_text())
    assert report["quality"]["verdict"] == "failed"
    assert report["georegistration"]["method"] == "model only"



@pytest.mark.slow
def test_refine_cli_without_gnss_reports_the_search(workspace, tmp_path, capsys):
    root, scene = workspace
    x, y = true_centre(scene)[:2] + [-30.0, 25.0]
    out = tmp_path / "out"
    code, stdout, err = run(["--input_path", root / "sparse" / "0", "--citymodel",
                             root / "model.gml", "--output_path", out, "--location", x, y,
                             "--precision", "off"], capsys)
    assert code == 0, err
    report = json.loads((out / "report.json").read_text())
    geo = report["georegistration"]
    assert geo["method"] == "model only" and geo["score_ratio"] < LocateOptions().max_ratio
    assert 30.0 < geo["hint_distance_m"] < 50.0
    assert report["quality"]["metrics"]["location_score_ratio"] == geo["score_ratio"]
    assert "model alone" in (out / "report.md").read_text()
    rec = pycolmap.Reconstruction(str(out))
    truth = {im.name: im.projection_center() + scene.store.origin
             for im in scene.truth.images.values()}
    errors = [np.linalg.norm(im.projection_center() - truth[im.name])
              for im in rec.images.values()]
    assert rms(errors) < 0.10


@pytest.mark.slow
def test_each_part_of_a_model_is_registered_on_its_own(workspace, tmp_path, capsys):
    """A mapper's sparse/ with two parts (here the same block twice): each is found on the
    model and refined into its own output directory."""
    root, scene = workspace
    sparse = tmp_path / "sparse"
    for part in ("0", "1"):
        (sparse / part).mkdir(parents=True)
        scene.sfm.write_binary(str(sparse / part))
    x, y = true_centre(scene)[:2] + [25.0, -30.0]
    out = tmp_path / "out"
    code, _, err = run(["--input_path", sparse, "--citymodel", root / "model.gml",
                        "--output_path", out, "--location", x, y, "--precision", "off"], capsys)
    assert code == 0, err
    assert sorted(p.name for p in out.iterdir()) == ["0", "1"]
    for part in ("0", "1"):
        report = json.loads((out / part / "report.json").read_text())
        assert report["georegistration"]["method"] == "model only"
        assert report["inputs"]["input_path"].endswith(f"sparse/{part}")


def test_a_block_that_fits_nowhere_near_the_hint_fails_with_a_verdict(street_scene):
    """Tie points scattered through the street's volume lie on no surface of the model: the
    search ends with the verdict "failed" (exit 3, what it found in its report), not as a
    refused input."""
    from colmap_citymodel.align.locate import ModelOnlyFailure

    sfm = pycolmap.Reconstruction(street_scene.sfm)
    rng = np.random.default_rng(3)
    xyz = np.array([p.xyz for p in sfm.points3D.values()])
    low, high = xyz.min(axis=0), xyz.max(axis=0)
    for point in sfm.points3D.values():
        point.xyz = rng.uniform(low, high)
    hint = true_centre(street_scene)[:2] - street_scene.store.origin[:2]
    with pytest.raises(ModelOnlyFailure) as caught:
        locate(sfm, street_scene.store, hint)
    assert "fits nowhere" in str(caught.value) and caught.value.exit_code == 3
    assert caught.value.report["verdict"] == "failed"
    assert caught.value.report["best_score"] < LocateOptions().min_share
