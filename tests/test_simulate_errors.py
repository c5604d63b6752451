"""The simulator's errors of the inputs: GNSS outliers, steps and RTK-grade noise; buildings
the given model lacks or adds; a given model with a wrong datum (turned and moved)."""

import json

import numpy as np
import pycolmap
import pytest
import shapely

from colmap_citymodel.citymodel.read import read_city_model
from colmap_citymodel.errors import InputError
from colmap_citymodel.simulate.flight import Flight
from colmap_citymodel.simulate.observations import gnss_gross_errors, simulate_gnss
from colmap_citymodel.simulate.scenario import GNSSOptions, SimulationOptions, load_scenario, \
    sequence_key
from colmap_citymodel.simulate.scene import LABEL_DETAIL, LABEL_ROOF, LABEL_WALL, \
    building_footprints
from colmap_citymodel.simulate.sequence import build_sequence, main


def line_flight(n: int, spacing: float = 2.0) -> Flight:
    arc = spacing * np.arange(n, dtype=float)
    centres = np.c_[arc, np.zeros(n), np.full(n, 10.0)]
    return Flight([f"frame_{i:05d}.jpg" for i in range(n)], centres,
                  np.repeat(np.eye(3)[None], n, 0), arc, 100, 100, 100.0)


def test_gnss_outliers_and_step():
    n = 80
    fl = line_flight(n)
    quiet = dict(white_sigma=(0.0, 0.0, 0.0), bias_sigma=(0.0, 0.0, 0.0))
    opt = GNSSOptions(outliers=3, outlier_range=(10.0, 30.0), step_magnitude=4.0,
                      step_range=(0.4, 0.6), **quiet)
    err = simulate_gnss(fl, opt, seed=5) - fl.centres
    _, info = gnss_gross_errors(fl, opt, 5)
    outliers = [fl.names.index(o["image"]) for o in info["outliers"]]
    first = fl.names.index(info["step"]["from_image"])
    step = np.asarray(info["step"]["vector_m"])
    # the step: 4 m from a key frame between 40 % and 60 % of the path on, nothing before
    assert np.linalg.norm(step) == pytest.approx(4.0)
    assert 0.4 * fl.arc[-1] <= fl.arc[first] <= 0.6 * fl.arc[-1] + 2.0
    clean = np.setdiff1d(np.arange(n), outliers)
    before, after = clean[clean < first], clean[clean >= first]
    np.testing.assert_allclose(err[before], 0.0, atol=1e-12)
    np.testing.assert_allclose(err[after], np.repeat(step[None], len(after), 0), atol=1e-12)
    # three outliers, none at the ends, each 10-30 m off the track (step included)
    assert len(set(outliers)) == 3 and 0 not in outliers and n - 1 not in outliers
    off = np.linalg.norm(err[outliers] - np.where(np.array(outliers)[:, None] >= first, step, 0),
                         axis=1)
    assert np.all((off >= 10.0) & (off <= 30.0))
    # the gross errors add to the noise without changing its draws; the same seed, the same
    noisy = GNSSOptions(outliers=3, step_magnitude=4.0, bias_magnitude=2.0)
    base = simulate_gnss(fl, GNSSOptions(bias_magnitude=2.0), seed=5)
    np.testing.assert_allclose(simulate_gnss(fl, noisy, seed=5) - base,
                               gnss_gross_errors(fl, noisy, 5)[0], atol=1e-9)
    np.testing.assert_array_equal(simulate_gnss(fl, noisy, seed=5),
                                  simulate_gnss(fl, noisy, seed=5))
    assert gnss_gross_errors(fl, GNSSOptions(), 5)[1] == {}


def test_rtk_grade_white_noise():
    """RTK: white noise of a few centimetres, no bias: the positions scatter with the stated
    sigma around the truth."""
    n = 3000
    fl = line_flight(n, spacing=0.5)
    sigma = (0.03, 0.03, 0.045)
    err = simulate_gnss(fl, GNSSOptions(sigma=sigma, white_sigma=sigma,
                                        bias_sigma=(0.0, 0.0, 0.0)), seed=2) - fl.centres
    np.testing.assert_allclose(err.std(axis=0), sigma, rtol=0.06)
    assert np.all(np.abs(err.mean(axis=0)) < 0.003)
    assert np.max(np.abs(err) / np.asarray(sigma)) < 5.0


def tiny_street(**model_errors) -> SimulationOptions:
    o = SimulationOptions(name="errors", seed=3)
    o.scene.procedural.num_buildings = 5
    o.scene.procedural.gap_probability = 1.0  # gaps between the houses: room for a box
    o.scene.procedural.gap_range = (14.0, 20.0)
    o.flight.num_key_frames = 16
    o.flight.spacing = 3.0
    o.flight.image_width, o.flight.image_height, o.flight.focal_length = 1024, 540, 600.0
    o.observations.points_per_m2 = 0.5
    o.checkpoints.count = 4
    o.mapping.run = False
    for name, value in model_errors.items():
        setattr(o.model_errors, name, value)
    return o


def _buildings(path) -> dict:
    return building_footprints(read_city_model(path))


def _crs_footprints(path) -> dict:
    """Footprints in CRS xy (each model file has its own local origin)."""
    store = read_city_model(path)
    return {b: shapely.affinity.translate(p, *store.origin[:2])
            for b, p in building_footprints(store).items()}


def test_missing_and_extra_buildings(tmp_path):
    out = tmp_path / "seq"
    build_sequence(tiny_street(missing_buildings=1, extra_buildings=1), out, progress=False)
    stats = json.loads((out / "simulation.json").read_text())
    missing, extra = stats["model_buildings"]["missing"], stats["model_buildings"]["extra"]
    assert len(missing) == 1 and extra == ["EXTRA_0"]
    true = _crs_footprints(out / "truth" / "true_model.gml")
    assert len(true) == 5 and missing[0] in true
    for variant in ("corrected", "original", "detailed"):
        given = _crs_footprints(out / "models" / f"{variant}.gml")
        assert set(given) == (set(true) - set(missing)) | {"EXTRA_0"}, variant
    box = _crs_footprints(out / "models" / "corrected.gml")["EXTRA_0"]
    assert box.area >= 8.0 ** 2 * 0.99
    assert box.distance(shapely.unary_union(list(true.values()))) >= 2.0 - 1e-6
    # the true scene has no building surface where the box stands, and the missing building
    # is there: its walls and roofs hold true tie points
    origin = np.array([float(v) for v in
                       (out / "truth" / "origin.txt").read_text().splitlines()[1].split()])
    scene = pycolmap.Reconstruction(str(out / "truth"))
    points = np.array([p.xyz for p in scene.points3D.values()]) + origin
    on_missing = shapely.contains_xy(true[missing[0]].buffer(1.0), points[:, 0], points[:, 1])
    assert on_missing.sum() >= 20
    import trimesh

    mesh = trimesh.load(out / "truth" / "true_scene.ply", process=False)
    labels = np.load(out / "truth" / "true_scene_labels.npy")
    centroids = mesh.triangles_center[np.isin(labels, (LABEL_WALL, LABEL_ROOF, LABEL_DETAIL))]
    inside = shapely.contains_xy(box.buffer(-0.5), centroids[:, 0] + origin[0],
                                 centroids[:, 1] + origin[1])
    assert not inside.any()
    # the box is in view: within the observations' reach of a camera
    cams = np.array([im.projection_center() for im in scene.images.values()]) + origin
    assert box.distance(shapely.MultiPoint(cams[:, :2])) < 40.0


def test_defaults_change_nothing(tmp_path):
    """Without missing or extra buildings the given model is the true one and no true model
    is written beside it; the keys of sequences cached before these options existed stay."""
    out = tmp_path / "seq"
    build_sequence(tiny_street(), out, progress=False)
    assert not (out / "truth" / "true_model.gml").exists()
    assert "model_buildings" not in json.loads((out / "simulation.json").read_text())
    assert "gnss_gross_errors" not in json.loads((out / "simulation.json").read_text())
    # the key of the default options as it was before the options of this module existed
    assert sequence_key(SimulationOptions()) == "e0837886f6fb"
    for group, name, value in (("gnss", "outliers", 2), ("gnss", "step_magnitude", 3.0),
                               ("model_errors", "missing_buildings", 1),
                               ("model_errors", "extra_buildings", 1),
                               ("scene", "target_crs", "EPSG:25832")):
        changed = SimulationOptions()
        setattr(getattr(changed, group), name, value)
        assert sequence_key(changed) != sequence_key(SimulationOptions()), name


def test_wrong_datum_of_the_given_model(tmp_path):
    """scenario.model_turn_deg / model_shift: the given model turned about a point and moved;
    the models/ variants and the truth stay."""
    toml = tmp_path / "wrong.toml"
    toml.write_text(
        'name = "wrong"\nseed = 4\n[scene.procedural]\nnum_buildings = 3\n'
        '[flight]\nnum_key_frames = 6\nimage_width = 1024\nimage_height = 540\n'
        'focal_length = 600.0\n[observations]\npoints_per_m2 = 0.3\n[checkpoints]\ncount = 0\n'
        '[mapping]\nrun = false\n[scenario]\nmodel = "corrected"\nmodel_turn_deg = 10.0\n'
        'model_turn_centre = [20.0, 5.0]\nmodel_shift = [12.0, -5.0, 0.5]\n')
    ws = main(toml, tmp_path / "ws", progress=False)
    corrected = read_city_model(ws / "models" / "corrected.gml")
    given = read_city_model(ws / "given_model.gml")
    origin = np.array([float(v) for v in
                       (ws / "truth" / "origin.txt").read_text().splitlines()[1].split()])
    a = np.radians(10.0)
    turn = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    expected = corrected.to_crs(corrected.centroids) - origin
    expected[:, :2] = (expected[:, :2] - [20.0, 5.0]) @ turn.T + [20.0, 5.0]
    expected += [12.0, -5.0, 0.5]
    np.testing.assert_allclose(given.to_crs(given.centroids) - origin, expected, atol=1e-6)
    bad = tmp_path / "bad.toml"
    bad.write_text('[scenario]\nmodel = "none"\nmodel_shift = [10.0, 0.0, 0.0]\n')
    with pytest.raises(InputError, match="model_shift"):
        load_scenario(bad)
