"""City models as they are downloaded: real tiles from tests/data, gzip-compressed and packed
into ZIP archives in the test, read to the same store as the plain files; the tile index over
compressed tiles; damaged archives fail with one message that names the file."""

from __future__ import annotations

import gzip
import shutil
import zipfile

import numpy as np
import pytest

from colmap_citymodel.citymodel.archives import expand_archive
from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.citymodel.read import city_model_files, peek_crs, read_city_model
from colmap_citymodel.citymodel.tiles import build_tile_index, files_near, scan_tile
from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.errors import InputError
from colmap_citymodel.output.corrected_model import target_names
from data_paths import CITYGML, CITYJSON

BERLIN = CITYGML / "berlin"
TILES = ("3910_5819.gml", "3920_5820.gml")


def gzipped(source, target):
    target.write_bytes(gzip.compress(source.read_bytes()))
    return target


def same_store(a, b):
    assert (a.num_buildings, a.num_faces) == (b.num_buildings, b.num_faces)
    np.testing.assert_allclose(a.origin, b.origin)
    np.testing.assert_allclose(a.vertices, b.vertices)
    assert a.crs.label == b.crs.label


def test_gzip_citygml_reads_as_the_plain_file(tmp_path):
    path = gzipped(BERLIN / TILES[1], tmp_path / (TILES[1] + ".gz"))
    same_store(read_city_model(path), read_city_model(BERLIN / TILES[1]))
    assert peek_crs(path).label == peek_crs(BERLIN / TILES[1]).label


def test_gzip_cityjson_reads_as_the_plain_file(tmp_path):
    path = gzipped(CITYJSON / "3dbag_b2.city.json", tmp_path / "3dbag_b2.city.json.gz")
    same_store(read_city_model(path), read_city_model(CITYJSON / "3dbag_b2.city.json"))


def test_zip_of_tiles_reads_as_the_directory(tmp_path):
    archive = tmp_path / "berlin_lod2.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as z:
        z.write(BERLIN / TILES[0], f"LoD2/{TILES[0]}")
        z.writestr(f"LoD2/{TILES[1]}.gz", gzip.compress((BERLIN / TILES[1]).read_bytes()))
        z.writestr("LoD2/README.txt", "not a tile")
    files = city_model_files(archive)
    assert [f.name for f in files] == [TILES[0], TILES[1] + ".gz"]
    plain = read_city_model([BERLIN / t for t in TILES])
    same_store(read_city_model(archive), plain)
    # a directory that holds the archive, and the archive again: unpacked once per process
    folder = tmp_path / "download"
    folder.mkdir()
    shutil.copy(archive, folder / archive.name)
    same_store(read_city_model(folder), plain)
    assert expand_archive(archive) == files


def test_tile_index_over_gzip_tiles(tmp_path):
    for name in TILES:
        gzipped(BERLIN / name, tmp_path / (name + ".gz"))
    for name in TILES:
        assert scan_tile(tmp_path / (name + ".gz")).bbox == scan_tile(BERLIN / name).bbox
    index = build_tile_index(tmp_path)
    assert index.scanned == 2 and not index.errors
    assert build_tile_index(tmp_path).scanned == 0  # cached by the compressed file
    small = read_city_model(BERLIN / TILES[1])
    box = small.vertices.min(0)[:2] + small.origin[:2], small.vertices.max(0)[:2] + small.origin[:2]
    near = files_near(tmp_path, np.array(box), user_crs("EPSG:25833"))
    assert [p.name for p in near] == [TILES[1] + ".gz"]


def test_damaged_gzip_names_the_file(tmp_path):
    data = gzip.compress((BERLIN / TILES[0]).read_bytes())
    cut = tmp_path / "cut.gml.gz"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="damaged gzip") as error:
        read_city_model(cut)
    assert error.value.path == cut
    not_gzip = tmp_path / "plain.gml.gz"
    shutil.copy(BERLIN / TILES[1], not_gzip)
    with pytest.raises(InputError, match="damaged gzip") as error:
        read_city_model(not_gzip)
    assert error.value.path == not_gzip


def test_damaged_zip_names_the_archive(tmp_path, capsys):
    archive = tmp_path / "tiles.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as z:
        z.write(BERLIN / TILES[0], TILES[0])
    data = bytearray(archive.read_bytes())
    data[len(data) // 3: len(data) // 3 + 64] = b"\0" * 64  # inside the deflated member
    archive.write_bytes(bytes(data))
    with pytest.raises(InputError, match="damaged ZIP archive") as error:
        read_city_model(archive)
    assert error.value.path == archive
    cut = tmp_path / "cut.zip"
    cut.write_bytes(bytes(data[: len(data) // 2]))
    assert cli_main(["model-info", str(cut)]) == 2
    assert "cut.zip: damaged ZIP archive" in capsys.readouterr().err
    empty = tmp_path / "empty.zip"
    with zipfile.ZipFile(empty, "w") as z:
        z.writestr("readme.txt", "no tiles")
    with pytest.raises(InputError, match="no CityGML"):
        read_city_model(empty)


def test_model_info_and_write_back_names(tmp_path, capsys):
    path = gzipped(BERLIN / TILES[1], tmp_path / (TILES[1] + ".gz"))
    assert cli_main(["model-info", str(path)]) == 0
    assert "buildings   6" in capsys.readouterr().out
    assert target_names([path]) == ["corrected_model.gml"]
    assert target_names([path, BERLIN / TILES[0]]) == [f"corrected_model/{TILES[1]}",
                                                       f"corrected_model/{TILES[0]}"]
