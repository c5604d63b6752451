"""The tile index on real tiles from tests/data (Berlin, PLATEAU, CityJSON from 3DBAG and
Rotterdam): boxes equal to what the readers read, exactly the overlapping tiles selected (also
across CRSs), and the cache next to the data or, for a read-only directory, elsewhere."""

from __future__ import annotations

import os
import shutil

import numpy as np
import pytest

from colmap_citymodel.citymodel.crs import reproject_points, user_crs
from colmap_citymodel.citymodel.read_citygml import read_citygml
from colmap_citymodel.citymodel.tiles import INDEX_NAME, build_tile_index, scan_tile
from data_paths import CITYGML, CITYJSON

BERLIN = CITYGML / "berlin"
PLATEAU = CITYGML / "plateau"

UTM33 = user_crs("EPSG:25833")


def names(tiles):
    return sorted(t.path.name for t in tiles)


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    """One index over the Berlin CityGML tiles and the CityJSON files (mixed formats and CRSs),
    read from read-only copies of tests/data, so the cache goes to a scratch directory."""
    root = tmp_path_factory.mktemp("data")
    dirs = [root / "berlin", root / "cityjson"]
    for source, copy in zip((BERLIN, CITYJSON), dirs):
        shutil.copytree(source, copy, ignore=shutil.ignore_patterns(INDEX_NAME))
        copy.chmod(0o555)
    try:
        before = [sorted(os.listdir(d)) for d in dirs]
        index = build_tile_index(dirs, cache_dir=tmp_path_factory.mktemp("cache"))
        assert [sorted(os.listdir(d)) for d in dirs] == before  # nothing written into the data
    finally:
        for d in dirs:
            d.chmod(0o755)
    return index


@pytest.mark.parametrize("name", ["3910_5819.gml", "3920_5820.gml", "Berlin_Moabit_1Bldg_v3.gml"])
def test_box_is_what_the_reader_reads(name):
    tile = scan_tile(BERLIN / name)
    raw = read_citygml(BERLIN / name)
    coords = raw.polygon_table().coords
    assert tile.error is None and tile.kind == "citygml"
    np.testing.assert_allclose(tile.bbox, [*coords.min(0)[:2], *coords.max(0)[:2]], atol=1e-6)


def test_geometry_in_another_crs_is_not_in_the_box():
    # a Gauss-Krueger building whose address point is in EPSG:4326
    tile = scan_tile(CITYGML / "ogc"
                     / "Building_CityGML3.0_LOD2_with_several_attributes.gml")
    assert tile.bbox[0] > 4e6 and tile.bbox[1] > 5e6


def test_selects_exactly_the_overlapping_tiles(mixed):
    assert len(mixed.tiles) == 7 and not mixed.errors
    # the vehicle drive of workspaces/robust_drive.toml plus 250 m
    drive = np.array([[390993.0, 5818973.0], [391273.0, 5818995.0]]) + [[-250.0], [250.0]]
    assert names(mixed.select(drive, UTM33)) == ["3910_5819.gml"]
    moabit = [[388600.0, 5818700.0], [388700.0, 5818800.0]]
    assert names(mixed.select(moabit, UTM33)) == ["Berlin_Moabit_1Bldg_v2.gml",
                                                  "Berlin_Moabit_1Bldg_v3.gml"]
    # from Moabit to the western end of 3910_5819: three tiles, not 3920_5820
    across = [[388650.0, 5818800.0], [391004.0, 5818990.0]]
    assert names(mixed.select(across, UTM33)) == ["3910_5819.gml", "Berlin_Moabit_1Bldg_v2.gml",
                                                  "Berlin_Moabit_1Bldg_v3.gml"]
    # a box that touches 3910_5819 only at its eastern edge, then one 1 m beyond it
    edge = [[392008.6, 5819000.0], [392030.0, 5819100.0]]
    assert names(mixed.select(edge, UTM33)) == ["3910_5819.gml"]
    beyond = [[392009.0, 5819000.0], [392030.0, 5819100.0]]
    assert names(mixed.select(beyond, UTM33)) == []


def test_selects_across_crs_and_formats(mixed):
    # the same drive, queried in the neighbouring UTM zone: the tile's box is reprojected
    utm32 = user_crs("EPSG:25832")
    corners = reproject_points(np.array([[390993.0, 5818973.0], [391273.0, 5818995.0]]), UTM33,
                               utm32)
    assert names(mixed.select([corners.min(0) - 50, corners.max(0) + 50], utm32)) \
        == ["3910_5819.gml"]
    # CityJSON in EPSG:7415 (RD New + NAP); files that name no CRS only with an assumed one
    rd = user_crs("EPSG:7415")
    near_3dbag = [[84990.0, 446530.0], [85000.0, 446540.0]]
    assert names(mixed.select(near_3dbag, rd)) == ["3dbag_b2.city.json"]
    rotterdam = [[90500.0, 435700.0], [90600.0, 435800.0]]
    assert names(mixed.select(rotterdam, rd)) == []
    assert names(mixed.select(rotterdam, rd, assumed=rd)) == ["rotterdam_subset.json"]
    labels = sorted(c.label for c in mixed.crs_groups())
    assert labels == ["EPSG:25833+5783", "EPSG:28992+5709"]


def test_geographic_tile_is_selected_in_a_projected_crs(tmp_path):
    data = tmp_path / "plateau"  # a copy: the index caches next to a writable directory
    shutil.copytree(PLATEAU, data, ignore=shutil.ignore_patterns(INDEX_NAME))
    index = build_tile_index(data, cache_dir=tmp_path)
    (tile,) = index.tiles
    assert tile.bbox[0] < 90  # latitude first, as the file writes it
    jgd = user_crs("EPSG:6677")  # Japan plane rectangular CS IX
    box = index.box_in(tile, jgd)
    assert box is not None and np.all(box[1] - box[0] < 200)
    assert index.select(box.mean(0) + [[-10.0], [10.0]], jgd) == [tile]
    assert index.select(box.mean(0) + [[1000.0], [1100.0]], jgd) == []


def test_cache_next_to_the_data_is_reused_until_a_file_changes(tmp_path):
    data = tmp_path / "tiles"
    data.mkdir()
    for name in ("3920_5820.gml", "Berlin_Moabit_1Bldg_v2.gml"):
        shutil.copy(BERLIN / name, data / name)
    first = build_tile_index(data)
    assert first.scanned == 2 and (data / INDEX_NAME).is_file()
    again = build_tile_index(data)
    assert again.scanned == 0 and [t.bbox for t in again.tiles] == [t.bbox for t in first.tiles]
    # a changed file (size and modification time) is read again, the other one is not
    with open(data / "Berlin_Moabit_1Bldg_v2.gml", "a") as f:
        f.write("\n<!-- edited -->\n")
    changed = build_tile_index(data)
    assert changed.scanned == 1
    # the cache is no tile: a directory with it still reads as the same two tiles
    assert names(changed.tiles) == ["3920_5820.gml", "Berlin_Moabit_1Bldg_v2.gml"]


def test_read_only_data_directory_caches_under_the_output(tmp_path):
    data, out = tmp_path / "tiles", tmp_path / "out"
    data.mkdir()
    shutil.copy(BERLIN / "3920_5820.gml", data / "3920_5820.gml")
    (data / "broken.gml").write_text("<CityModel><cityObjectMember>")
    data.chmod(0o555)
    try:
        index = build_tile_index(data, cache_dir=out)
        assert not (data / INDEX_NAME).exists()
        assert len(list(out.glob("tile_index-tiles-*.json"))) == 1
        assert build_tile_index(data, cache_dir=out).scanned == 0
    finally:
        data.chmod(0o755)
    # an unreadable tile is recorded, never selected, and does not stop the index
    (broken,) = index.errors
    assert broken.path.name == "broken.gml" and broken.bbox is None
    assert names(index.select([[0.0, 0.0], [1e7, 1e7]], UTM33)) == ["3920_5820.gml"]


def test_refine_reads_only_the_tiles_near_its_block(tmp_path):
    from colmap_citymodel.citymodel.tiles import files_near

    tiles = tmp_path / "berlin"
    shutil.copytree(BERLIN, tiles, ignore=shutil.ignore_patterns(INDEX_NAME))
    tiles.chmod(0o755)  # writable, as a user's tile directory is, whatever the checkout's modes
    drive = np.array([[390993.0, 5818973.0], [391273.0, 5818995.0]]) + [[-250.0], [250.0]]
    assert [p.name for p in files_near(tiles, drive, UTM33)] == ["3910_5819.gml"]
    assert (tiles / INDEX_NAME).is_file()  # the next refine reads the index, not the tiles
    # a damaged tile is kept, so that the reader names it; far from every tile: all files
    (tiles / "broken.gml").write_text("<CityModel")
    assert [p.name for p in files_near(tiles, drive, UTM33)] == ["3910_5819.gml", "broken.gml"]
    far = drive + 50_000.0
    assert len(files_near(tiles, far, UTM33)) == 5
    # one file is read as given
    one = tiles / "3920_5820.gml"
    assert files_near(one, drive, UTM33) == [one]
