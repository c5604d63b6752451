"""The terrain beside the buildings: DTM rasters in another CRS with nodata and two tiles, the
TIN relief of CityGML and CityJSON files, the buildings' feet, a DTM that stands metres off
(caught, not followed), the faces and their weights, and clutter kept off the ground."""

from __future__ import annotations

import json

import numpy as np
import pytest

from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.citymodel.ground_faces import (
    ROAD_UNIT,
    TERRAIN_CLASS,
    TERRAIN_PREFIX,
    block_terrain,
    checked_tiles,
    terrain_face_sigmas,
    terrain_mask,
    terrain_units,
    with_terrain_faces,
)
from colmap_citymodel.citymodel.terrain import (
    building_feet,
    feet_terrain,
    read_dtm,
    read_relief,
    terrain_options,
)
from colmap_citymodel.errors import InputError
from colmap_citymodel.options import RefineOptions, TerrainOptions
from colmap_citymodel.simulate.dtm import write_dtm
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, ground_height, make_street_scene
from data_paths import CITYGML

X0, Y0, Z0 = 691000.0, 5335000.0, 500.0
UTM32 = user_crs("EPSG:25832")


def plane(xy):
    xy = np.asarray(xy, float)
    return Z0 + 0.03 * (xy[:, 0] - X0) - 0.02 * (xy[:, 1] - Y0)


def test_a_dtm_in_geographic_coordinates_with_nodata_in_two_tiles(tmp_path):
    def ground(xy):  # the plane, with a hole of nodata 6 m around (X0 + 20, Y0 + 30)
        z = plane(xy)
        z[np.hypot(xy[:, 0] - X0 - 20, xy[:, 1] - Y0 - 30) < 6.0] = np.nan
        return z

    bbox = np.array([[X0 - 30, Y0 - 30], [X0 + 130, Y0 + 90]])
    files = write_dtm(tmp_path, ground, bbox, "EPSG:25832", tiles=2, crs="EPSG:4326",
                      offsets=[0.0, 0.0])
    block = np.array([[X0, Y0], [X0 + 100, Y0 + 60]])
    terrain = read_dtm(files, UTM32, block, sigma=0.15)
    assert terrain.source == "dtm" and terrain.tile_names == ["dtm_0.tif", "dtm_1.tif"]
    xs, ys = terrain.node_xy()
    # only the block's area (plus the margin) is on the grid, not the tiles' whole extent
    assert xs[0] >= X0 - 21 and xs[-1] <= X0 + 121 and ys[-1] <= Y0 + 81
    gx, gy = np.meshgrid(xs, ys)
    xy = np.c_[gx.ravel(), gy.ravel()]
    z = terrain.heights.ravel()
    hole = np.hypot(xy[:, 0] - X0 - 20, xy[:, 1] - Y0 - 30)
    assert np.all(np.isnan(z[hole < 5.0]))  # nodata stays no data
    inside = np.all((xy >= block[0]) & (xy <= block[1]), axis=1) & (hole > 8.0)
    assert np.all(np.isfinite(z[inside]))  # no gap along the seam between the tiles
    assert np.max(np.abs(z[inside] - plane(xy[inside]))) < 0.02
    tiles = terrain.tiles.ravel()[inside]
    assert set(np.unique(tiles)) == {0, 1}
    # the surface's functions at a point
    probe = np.array([[X0 + 50.3, Y0 + 10.7]])
    assert terrain.height(probe)[0] == pytest.approx(plane(probe)[0], abs=0.02)
    n = terrain.normal(probe)[0]
    assert n == pytest.approx(np.array([-0.03, 0.02, 1.0]) / np.sqrt(1.0013), abs=5e-3)
    assert terrain.sigma(probe)[0] == pytest.approx(0.15)


def test_dtm_files_that_are_missing_or_not_rasters_name_the_file(tmp_path):
    options = TerrainOptions()
    with pytest.raises(InputError, match="does not exist") as error:
        terrain_options(options, [str(tmp_path / "none.tif")], None)
    assert "none.tif" in str(error.value.path)
    bad = tmp_path / "dtm.tif"
    bad.write_text("not a raster")
    with pytest.raises(InputError, match="not a readable raster"):
        terrain_options(options, [str(bad)], None)
    with pytest.raises(InputError, match="positive"):
        terrain_options(options, None, -1.0)
    terrain_options(options, ["none"], 0.1)
    assert options.source == "none" and options.sigma == 0.1


def test_tin_relief_of_a_citygml_file():
    def relief_height(x, y):  # make_relief.py's relief
        return 100.0 + 0.03 * (x - X0) + 0.01 * (y - Y0)

    path = CITYGML / "synthetic/relief_tin_house.gml"
    terrain = read_relief([path], user_crs("EPSG:25832+7837"),
                          np.array([[X0 + 10, Y0 + 10], [X0 + 50, Y0 + 50]]), sigma=0.1)
    assert terrain is not None and terrain.source == "relief"
    xs, ys = terrain.node_xy()
    covered = np.isfinite(terrain.heights)
    assert covered.mean() > 0.5
    gx, gy = np.meshgrid(xs, ys)
    expected = np.vectorize(relief_height)(gx, gy)
    assert np.max(np.abs(terrain.heights[covered] - expected[covered])) < 1e-6


def test_tin_relief_of_a_cityjson_file(tmp_path):
    vertices = [[0, 0, 0], [100000, 0, 3000], [100000, 100000, 5000], [0, 100000, 2000]]
    doc = {"type": "CityJSON", "version": "2.0",
           "transform": {"scale": [0.001, 0.001, 0.001], "translate": [X0, Y0, 100.0]},
           "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/25832"},
           "CityObjects": {"relief": {"type": "TINRelief", "geometry": [
               {"type": "CompositeSurface", "lod": "2",
                "boundaries": [[[0, 1, 2]], [[0, 2, 3]]]}]}},
           "vertices": vertices}
    path = tmp_path / "relief.city.json"
    path.write_text(json.dumps(doc))
    terrain = read_relief([path], UTM32, np.array([[X0 + 10, Y0 + 10], [X0 + 90, Y0 + 90]]),
                          sigma=0.1)
    assert terrain is not None
    probe = np.array([[X0 + 60.0, Y0 + 20.0]])  # in the triangle 0-1-2: z = 0.03 x + 0.02 y
    assert terrain.height(probe)[0] == pytest.approx(100.0 + 0.03 * 60 + 0.02 * 20, abs=1e-6)


@pytest.fixture(scope="module")
def street():
    options = StreetSceneOptions(num_stations=20, flight_height=2.5, tilt_deg=8.0,
                                 forward_tilt_deg=5.0, ground_spacing=1.0, ground_slope=0.04,
                                 kerb_height=0.15)
    return options, make_street_scene(options, crs=UTM32)


def street_dtm(directory, options, offsets, noise=0.15):
    origin = np.array([X0, Y0, Z0])

    def ground(xy):
        return ground_height(options, xy - origin[:2]) + origin[2]

    bbox = np.array([origin[:2] + [-40, -30], origin[:2] + [80, 30]])
    return write_dtm(directory, ground, bbox, "EPSG:25832", tiles=2, offsets=offsets,
                     noise_sigma=noise, seed=1)


def test_the_buildings_feet_give_a_terrain_whose_local_sigma_grows_away_from_them(street):
    import shapely

    _, scene = street
    store = scene.store
    feet = building_feet(store)
    assert len(feet.points) > 100 and not feet.footprints.is_empty
    bbox = np.array([[X0 - 10, Y0 - 12], [X0 + 40, Y0 + 12]])
    terrain = feet_terrain(store, bbox, sigma=0.3, growth=0.02, feet=feet, reach=3.0,
                           kerb=0.15)
    assert terrain.source == "building_feet"
    near = np.argmin(np.hypot(feet.points[:, 0] - X0 - 20, feet.points[:, 1] - Y0 - 10))
    at_foot = feet.points[near:near + 1, :2]
    # one offset per building (its ground height), no local error at a foot
    assert terrain.sigma(at_foot)[0] == pytest.approx(0.3)
    assert terrain.local_sigma(at_foot)[0] < 0.03
    mid_street = np.array([[X0 + 20.0, Y0 + 0.0]])  # 10 m from the facades, beyond the kerb
    assert terrain.sigma(mid_street)[0] == pytest.approx(0.3)
    # its local error grows with the distance from the feet; the kerb's is the road unit's
    assert terrain.local_sigma(mid_street)[0] == pytest.approx(0.02 * 10, abs=0.05)
    # the road lies a kerb below the feet; the pavement (3 m) at their height
    assert terrain.grid_height(mid_street)[0] - terrain.height(mid_street)[0] == \
        pytest.approx(0.15)
    edge = shapely.distance(feet.footprints, shapely.points(at_foot + [0.0, -2.0]))[0]
    assert edge < 3.0 and terrain.height(at_foot + [0.0, -2.0])[0] == pytest.approx(
        terrain.grid_height(at_foot + [0.0, -2.0])[0])
    # the buildings stand at their centres' street heights: the feet follow the slope
    assert terrain.height(np.array([[X0 + 40, Y0]]))[0] - terrain.height(
        np.array([[X0, Y0]]))[0] == pytest.approx(1.6, abs=0.5)


def test_terrain_faces_skip_the_footprints_and_weigh_as_one_observation_per_tile(street,
                                                                                  tmp_path):
    options, scene = street
    store = scene.store
    files = street_dtm(tmp_path, options, [0.0, 0.0], noise=0.0)
    points = np.array([p.xyz for p in scene.truth.points3D.values()])
    terrain = read_dtm(files, UTM32, np.array([[X0 - 20, Y0 - 20], [X0 + 60, Y0 + 20]]), 0.15)
    feet = building_feet(store)
    out = with_terrain_faces(store, terrain, points, 6.0, feet.footprints)
    mask = terrain_mask(out)
    assert mask.sum() > 20 and not terrain_mask(store).any()
    assert set(out.faces.semantic[int(f)] for f in np.flatnonzero(mask)) == {TERRAIN_CLASS}
    import shapely

    centres = out.centroids[mask][:, :2] + out.origin[:2]
    assert not shapely.contains_xy(feet.footprints, centres[:, 0], centres[:, 1]).any()
    assert np.all(out.normals[mask][:, 2] > 0.99)  # upward, the street's slope
    unit, sigma, names = terrain_units(out)
    assert set(names) == {"terrain:dtm_0.tif", "terrain:dtm_1.tif"}
    assert np.allclose(sigma[mask], 0.15)
    # n points of one unit: each at sqrt(s_dtp^2 + n s_u^2), together one observation
    faces = np.flatnonzero(mask)[:3]
    faces = faces[unit[faces] == unit[faces[0]]]
    rows = np.repeat(np.arange(len(faces)), 100)
    sigmas = terrain_face_sigmas(out, faces, rows, np.full(len(faces), 0.2), 0.2)
    n = 100 * len(faces)
    assert np.allclose(sigmas, np.sqrt(0.2 ** 2 + n * 0.15 ** 2))
    assert np.sum(np.full(n, 1.0) / sigmas[0] ** 2) == pytest.approx(1 / 0.15 ** 2, rel=0.01)
    walls = np.flatnonzero(~mask)[:2]
    assert np.allclose(terrain_face_sigmas(out, walls, np.zeros(5, int), np.full(2, 0.2), 0.2),
                       0.2)


def test_feet_cells_split_at_the_pavement_and_the_road_does_not_outweigh_it(street):
    import shapely

    from colmap_citymodel.citymodel.ground_faces import smoothed, terrain_unit_sigmas, unit_weights

    _, scene = street
    store = scene.store
    feet = building_feet(store)
    points = np.array([p.xyz for p in scene.truth.points3D.values()])
    xy = points[:, :2] + store.origin[:2]
    bbox = np.array([xy.min(0) - 12, xy.max(0) + 12])
    terrain = feet_terrain(store, bbox, sigma=0.3, growth=0.02, feet=feet)
    out = with_terrain_faces(store, terrain, points, 6.0, feet.footprints)
    mask = terrain_mask(out)
    unit, sigma, local, _ = terrain_unit_sigmas(out)
    pieces = [shapely.Polygon(out.vertices[out.faces[int(f)].exterior][:, :2] + out.origin[:2])
              for f in np.flatnonzero(mask)]
    assert not any(shapely.intersection(p, feet.footprints).area > 1e-3 for p in pieces)
    centres = np.array([p.representative_point().coords[0] for p in pieces])
    pavement = shapely.contains_xy(feet.footprints.buffer(3.0), centres[:, 0], centres[:, 1])
    assert pavement.sum() >= 5 and (~pavement).sum() >= 5  # cells cut at the pavement's edge
    assert np.all(local[mask][pavement] < 0.1)
    # the pavements keep their buildings' units; all the road beyond them is one unit, the
    # kerb's error (none where there is no kerb) one error of all of it
    names = np.array(terrain_units(out)[2])
    assert np.allclose(sigma[mask][pavement], 0.3)
    assert np.allclose(sigma[mask][~pavement], np.hypot(0.3, 0.15), atol=1e-3)
    road = set(unit[mask][~pavement])
    assert len(road) == 1 and names[road.pop()] == TERRAIN_PREFIX + ROAD_UNIT
    assert not set(unit[mask][pavement]) & set(unit[mask][~pavement])
    # the road pieces lie a kerb below the feet's heights, the pavement's at them
    plane_z = np.array([out.vertices[out.faces[int(f)].exterior][:, 2].mean()
                        for f in np.flatnonzero(mask)]) + out.origin[2]
    ring_xy = [out.vertices[out.faces[int(f)].exterior][:, :2] + out.origin[:2]
               for f in np.flatnonzero(mask)]
    drop = np.array([smoothed_grid.mean() for smoothed_grid in
                     (smoothed(terrain, 6.0).grid_height(r) for r in ring_xy)]) - plane_z
    assert np.median(drop[~pavement]) == pytest.approx(0.15, abs=0.05)
    assert np.median(np.abs(drop[pavement])) < 0.05
    # However many points the road holds, together they are one observation of its unit's
    # offset: a road whose kerb is not there (a square) moves the block by one such error,
    # not by the kerb's height.
    road_faces = np.flatnonzero(mask)[~pavement][:4]
    rows = np.repeat(np.arange(len(road_faces)), 300)
    sigmas = terrain_face_sigmas(out, road_faces, rows, np.full(len(road_faces), 0.2), 0.2)
    weight = np.sum(1.0 / np.repeat(sigmas, 300) ** 2)
    assert weight <= 1.0 / np.hypot(0.3, 0.15) ** 2 * 1.01
    # One building's unit: 50 points near its foot, 1200 further out where its local error
    # is larger, 0.2 m lower. The unit's offset as the adjustment weighs it (a weighted mean,
    # 1 / sigma^2 per point) follows the points near the foot.
    face_unit = np.zeros(7, np.int64)
    counts = np.array([50.0] + [200.0] * 6)
    loc = np.array([0.03] + [0.3] * 6)
    share, unit_sigma = unit_weights(face_unit, counts, np.full(7, 0.3), loc, 0.2)
    assert share[0] > 0.8 and unit_sigma[0] == pytest.approx(0.3, abs=0.01)
    residual = np.r_[np.zeros(50), np.full(1200, -0.2)]
    point_sigma = np.sqrt(0.2 ** 2 + counts * unit_sigma[0] ** 2 / share)
    weight = 1.0 / np.repeat(point_sigma, counts.astype(int)) ** 2
    assert abs(np.sum(weight * residual) / np.sum(weight)) < 0.04
    assert np.sum(weight) == pytest.approx(1 / 0.3 ** 2, rel=0.02)  # still one observation
    # without local errors (a DTM) every point weighs alike, as before
    share, unit_sigma = unit_weights(face_unit, counts, np.full(7, 0.15), np.zeros(7), 0.2)
    assert np.allclose(share, counts / counts.sum()) and unit_sigma[0] == pytest.approx(0.15)


def test_feet_from_terrain_intersection_lines_follow_the_ground_along_the_walls():
    import shapely

    from colmap_citymodel.citymodel.read import read_city_model
    from colmap_citymodel.citymodel.terrain import read_model_ground

    # NRW LoD2: the walls reach down to the lowest ground around a building; its
    # lod2TerrainIntersection follows the ground along them
    path = CITYGML / "nrw/LoD2_32_328_5725_1_NW.gml"
    store = read_city_model(path)
    ground = read_model_ground([path], store.crs)
    assert set(ground.intersections) == {"DENW34AL0000qS9h", "DENW34AL0002jQAV"}
    assert [328156.107, 5725316.049, 19.054] in ground.intersections[
        "DENW34AL0000qS9h"].tolist()
    walls = building_feet(store)
    lines = building_feet(store, ground.intersections)
    k = lines.building_ids.index("DENW34AL0000qS9h")
    by_walls, by_lines = walls.points[walls.building == k], lines.points[lines.building == k]
    assert np.ptp(by_walls[:, 2]) < 0.15 and np.ptp(by_lines[:, 2]) > 0.4
    assert by_lines[:, 2].mean() - by_walls[:, 2].mean() > 0.2
    assert np.max(shapely.distance(lines.footprints.boundary,
                                   shapely.points(by_lines[:, :2]))) < 0.05


def test_a_dtm_five_metres_off_is_left_out_not_followed(street, tmp_path):
    options, scene = street
    store = scene.store
    files = street_dtm(tmp_path, options, [5.0, 0.0], noise=0.05)
    terrain = read_dtm(files, UTM32, np.array([[X0 - 20, Y0 - 20], [X0 + 60, Y0 + 20]]), 0.15)
    points = np.array([p.xyz for p in scene.truth.points3D.values()]) + store.origin
    warnings = checked_tiles(terrain, points, building_feet(store), TerrainOptions())
    assert len(warnings) == 1 and "dtm_0.tif" in warnings[0] and "+5" in warnings[0]
    assert terrain.tile_names[0] == "dtm_0.tif" and not (terrain.tiles == 0).any()
    assert (terrain.tiles == 1).any()  # the tile that agrees with the feet stays
    # every tile off: the terrain comes from the buildings' feet
    files = street_dtm(tmp_path / "off", options, [5.0, 5.0], noise=0.05)
    points = np.array([p.xyz for p in scene.truth.points3D.values()])
    terrain_options_ = TerrainOptions(files=tuple(str(f) for f in files))
    out, record = block_terrain(store, points, terrain_options_)
    assert record["source"] == "building_feet" and len(record["warnings"]) == 3
    assert terrain_mask(out).sum() > 20


def test_clutter_is_kept_off_the_terrain():
    from colmap_citymodel.assign.ground import off_ground

    rng = np.random.default_rng(3)
    ground = np.c_[rng.uniform(0, 20, 400), rng.uniform(0, 20, 400), rng.normal(0, 0.02, 400)]
    car_side = np.c_[rng.uniform(5, 9, 60), np.full(60, 10.0), rng.uniform(0.3, 1.5, 60)]
    bush = rng.normal([15, 15, 1.0], 0.5, (60, 3))
    points = np.vstack([ground, car_side, bush])
    off = off_ground(points, np.arange(len(points)))
    assert off[:400].mean() < 0.05
    assert off[400:460].mean() > 0.8 and off[460:].mean() > 0.8


def refine_with_dtm(scene, files):
    """refine of the street's block with the DTM `files`: the result and its camera-centre
    errors (estimated - true, one row per image)."""
    from colmap_citymodel.workflow import refine

    options = RefineOptions()
    options.terrain.files = tuple(str(f) for f in files)
    result = refine(scene.sfm, scene.store, scene.gnss(), options, progress=False)
    true = {im.name: im.projection_center() for im in scene.truth.images.values()}
    errors = np.array([im.projection_center() - true[im.name]
                       for im in result.reconstruction.images.values()])
    return result, errors


def test_a_sloped_street_drive_lands_within_a_quarter_metre_in_height_with_a_dtm(street,
                                                                                tmp_path):
    options, scene = street
    result, errors = refine_with_dtm(scene, street_dtm(tmp_path, options, [0.10, -0.05]))
    assert abs(errors[:, 2].mean()) < 0.25
    assert np.sqrt(np.mean(errors ** 2, axis=0)).max() < 0.25
    terrain = result.terrain
    assert terrain["source"] == "dtm" and terrain["residuals"]["num_points"] > 300
    assert set(terrain["residuals"]["units"]) == {"dtm_0.tif", "dtm_1.tif"}
    assert terrain["residuals"]["rms_m"] < 0.2


def test_the_cli_names_a_bad_dtm_file_in_one_line_and_exits_2(tmp_path, capsys):
    from colmap_citymodel.cli import main as cli_main

    bad = tmp_path / "dgm1.tif"
    bad.write_bytes(b"II*\x00 not really a tiff")
    code = cli_main(["refine", "--input_path", str(tmp_path), "--citymodel",
                     str(CITYGML / "synthetic/relief_tin_house.gml"), "--output_path",
                     str(tmp_path / "out"), "--terrain", str(bad)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and err.startswith("error: ")
    assert "dgm1.tif" in err and "raster" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_terrain_units_off_the_block_are_flagged_and_terrain_is_never_corrected(street,
                                                                               tmp_path):
    from colmap_citymodel.adjust.model_correction import select_corrected_faces
    from colmap_citymodel.assign.assignment import Assignment
    from colmap_citymodel.citymodel.ground_faces import terrain_residuals
    from colmap_citymodel.options import AdjustmentOptions

    options, scene = street
    files = street_dtm(tmp_path, options, [0.0, 0.0], noise=0.0)
    terrain = read_dtm(files, UTM32, np.array([[X0 - 20, Y0 - 20], [X0 + 60, Y0 + 20]]), 0.15)
    rng = np.random.default_rng(5)
    ground = np.c_[rng.uniform(2, 36, 400), rng.uniform(-6, 6, 400)]
    z = ground_height(options, ground)
    points = np.c_[ground, z] + (np.array([X0, Y0, Z0]) - scene.store.origin)
    store = with_terrain_faces(scene.store, terrain, points, 6.0,
                               building_feet(scene.store).footprints)
    faces, _ = store.closest_faces(points, max_distance=0.5)
    assert np.mean(faces >= 0) > 0.9 and terrain_mask(store)[faces[faces >= 0]].all()
    assignment = Assignment(np.arange(len(points)), faces, np.zeros(len(points)), 0.5)
    right = terrain_residuals(store, assignment, points)
    assert right["num_points"] == np.sum(faces >= 0) and right["off_units"] == []
    assert right["rms_m"] < 0.05
    lifted = terrain_residuals(store, assignment, points + [0, 0, 1.0])  # a block 1 m high
    assert lifted["off_units"] and all(u["mean_m"] == pytest.approx(1.0, abs=0.05)
                                       for u in lifted["units"].values())
    selection = select_corrected_faces(store, assignment, points, AdjustmentOptions())
    assert len(selection.faces) == 0 and selection.not_corrected.get("terrain", 0) > 5


def test_a_drive_given_a_dtm_five_metres_off_does_not_follow_it(street, tmp_path):
    options, scene = street
    result, errors = refine_with_dtm(scene, street_dtm(tmp_path, options, [5.0, 5.0]))
    assert abs(errors[:, 2].mean()) < 0.3  # not 5 m
    assert result.terrain["source"] == "building_feet"
    assert sum("left out" in w for w in result.terrain["warnings"]) == 2


def test_terrain_cells_grow_where_tie_points_are_sparse():
    from colmap_citymodel.citymodel.ground_faces import POINTS_PER_CELL, cell_size

    rng = np.random.default_rng(0)
    dense = rng.uniform(0, 100, (30000, 2))  # 3 points per m^2: a street camera's ground
    assert cell_size(dense, 6.0) == 6.0
    sparse = rng.uniform(0, 600, (40000, 2))  # 0.11 per m^2: an aerial block
    cell = cell_size(sparse, 6.0)
    assert 15.0 <= cell <= 20.0 and 0.11 * cell ** 2 >= POINTS_PER_CELL


def test_a_nadir_mapping_flight_looks_straight_down_along_its_strips(street):
    from colmap_citymodel.simulate.flight import plan_flight
    from colmap_citymodel.simulate.scenario import FlightOptions
    from colmap_citymodel.simulate.scene import GroundModel

    _, scene = street
    options = FlightOptions(mode="forward", waypoints=[[0, -10], [60, -10], [60, 10], [0, 10]],
                            num_key_frames=12, spacing=10.0, spacing_jitter=0.5,
                            distance_amplitude=0.0, flight_height=50.0, height_amplitude=0.0,
                            pitch_deg=90.0, turn_smoothing=2.0,
                            attitude_sigma_deg=(0.5, 0.5, 0.5))
    flight = plan_flight(scene.store, options, 3, GroundModel(scene.store))
    ground = GroundModel(scene.store)(flight.centres[:, :2])
    assert np.allclose(flight.centres[:, 2] - ground, 50.0)
    R = flight.rotations
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.all(R[:, 2, 2] < -0.999)  # the optical axis points down (within the jitter)
    # the image's x axis is the heading's right: (0, -1) on the first strip (east), (0, 1) on
    # the way back (west), the same for every image of a strip (no flip)
    east, west = flight.centres[:, 1] < -9.5, flight.centres[:, 1] > 9.5
    assert east.sum() >= 4 and west.sum() >= 3
    assert np.all(R[east, 0, 1] < -0.99) and np.all(R[west, 0, 1] > 0.99)


def test_a_building_whose_feet_stand_5_m_below_its_street_does_not_move_the_block(street):
    """Official LoD2 takes a building's walls down to the lowest ground of its footprint: here
    one building's walls reach 5 m below the street in front of it. Its feet are checked
    against the road's tie points beside it and the other buildings' feet, named and left out
    of the terrain, and the drive lands where it lands with honest feet (within 0.25 m in U),
    not 5 m down."""
    from colmap_citymodel.citymodel.terrain import LOWEST_EDGE
    from colmap_citymodel.workflow import refine

    options, scene = street
    store = scene.store
    building = "bL2"
    faces = np.flatnonzero(np.asarray(store.faces.building_id.codes)
                           == store.faces.building_id.categories.index(building))
    ids = np.unique(np.concatenate([store.face_vertex_ids(int(f)) for f in faces]))
    vertices = store.vertices.copy()
    low = ids[vertices[ids, 2] <= vertices[ids, 2].min() + LOWEST_EDGE]
    vertices[low, 2] -= 5.0
    sunk = store.with_vertices(vertices)
    result = refine(scene.sfm, sunk, scene.gnss(), RefineOptions(), progress=False)
    true = {im.name: im.projection_center() for im in scene.truth.images.values()}
    errors = np.array([im.projection_center() - true[im.name]
                       for im in result.reconstruction.images.values()])
    assert abs(errors[:, 2].mean()) < 0.25, errors.mean(0)
    named = [w for w in result.terrain["warnings"] if building in w]
    assert len(named) == 1 and "left out" in named[0] and "5.0" in named[0]
    assert "below" in named[0]


def test_a_drive_s_coarse_search_puts_it_at_the_dtm_s_height(street, tmp_path, monkeypatch):
    """A drive 2.5 m above a sloped street, a third of its tie points on the road, with the
    street's DTM (GNSS 1.2 m off in height): the coarse search scores the road's points on
    the terrain as well as the facades' on the walls, so it puts the block at the DTM's height
    (within two of its 0.15 m sigma) before any tie point is assigned."""
    import colmap_citymodel.workflow as workflow

    options, scene = street
    placed = []
    real = workflow.coarse_start

    def spy(rec, *args, **kwargs):
        found = real(rec, *args, **kwargs)
        placed.append({im.name: im.projection_center() for im in rec.images.values()})
        return found

    monkeypatch.setattr(workflow, "coarse_start", spy)
    refine_with_dtm(scene, street_dtm(tmp_path, options, [0.05, -0.05]))
    true = {im.name: im.projection_center() for im in scene.truth.images.values()}
    errors = np.array([centre - true[name] for name, centre in placed[-1].items()])
    assert abs(errors[:, 2].mean()) < 0.30, errors.mean(0)
