"""output.citygml_update and output.cityjson_update on every file of tests/data: written without
a correction, the file has the same XML / JSON content and reads back to the same store; with
vertices moved, only their coordinates change, by their shift, and nothing else."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from lxml import etree

from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.citymodel.read import read_city_model
from colmap_citymodel.output.citygml_update import Moves, update_citygml
from colmap_citymodel.output.cityjson_update import read_vertex_indices, update_cityjson
from data_paths import CITYGML, CITYJSON

#: read_city_model arguments per file (the files that name no CRS, the geographic one)
CITYGML_FILES = {
    "berlin/3910_5819.gml": {}, "berlin/3920_5820.gml": {},
    "berlin/Berlin_Moabit_1Bldg_v2.gml": {}, "berlin/Berlin_Moabit_1Bldg_v3.gml": {},
    "nrw/LoD2_32_328_5725_1_NW.gml": {},
    "ogc/Building_CityGML3.0_LOD2_with_several_attributes.gml": {},
    "ogc/Building_and_garage_LOD2-EPSG25832_v2.gml": {},
    "ogc/Building_and_garage_LOD2-EPSG25832_v3.gml": {},
    "plateau/53394517_bldg_6697_op_CityGML2.gml": {"target_crs": "EPSG:6677"},
    "synthetic/no_crs_house_part.gml": {"crs": "EPSG:3946"},
    "synthetic/parts_xlinked_solids_v1.gml": {},
    "tum2twin/DEBY_LOD2_4906970.gml": {}, "tum2twin/DEBY_LOD2_4906972.gml": {},
    "tum2twin/DEBY_LOD2_4959321.gml": {}, "tum2twin/DEBY_LOD2_4959322.gml": {},
    "tum2twin/DEBY_LOD2_4959323.gml": {}, "tum2twin/DEBY_LOD2_4959324.gml": {},
    "tum2twin/DEBY_LOD2_4959457.gml": {},
}
CITYJSON_FILES = {"3dbag_b2.city.json": {}, "DH_01_subs.city.json": {"crs": "EPSG:7415"},
                  "rotterdam_subset.json": {"crs": "EPSG:7415"}}
SHIFT = np.array([0.0123, -0.0456, 0.0789])


def _moves(store, every: int = 3, shift=SHIFT) -> Moves:
    ids = np.arange(0, len(store.vertices), every)
    return Moves(store, ids, np.tile(shift, (len(ids), 1)))


def _update(path: Path, target: Path, moves: Moves, kwargs: dict):
    update = update_citygml if path.suffix == ".gml" else update_cityjson
    assumed = user_crs(kwargs["crs"]) if "crs" in kwargs else None
    return update(path, target, moves, assumed_crs=assumed)


def _same_store(a, b, tolerance: float, moved: np.ndarray | None = None, shift=SHIFT):
    assert b.num_faces == a.num_faces and len(b.vertices) == len(a.vertices)
    assert b.faces.ring_vertex.tolist() == a.faces.ring_vertex.tolist()
    assert list(b.faces.gml_id) == list(a.faces.gml_id)
    expected = a.vertices + a.origin
    if moved is not None:
        expected[moved] += shift
    np.testing.assert_allclose(b.vertices + b.origin, expected, atol=tolerance, rtol=0)


# -- CityGML ----------------------------------------------------------------------------------------

COORDINATES = ("posList", "pos", "coordinates")


def _local(tag) -> str:
    return tag.rpartition("}")[2] if isinstance(tag, str) else ""


def _numbers(text: str) -> list[str]:
    return re.findall(r"[^\s,]+", text or "")


@pytest.mark.parametrize("name", sorted(CITYGML_FILES))
def test_citygml_written_unchanged_is_the_same_document_and_model(name, tmp_path):
    kwargs = CITYGML_FILES[name]
    store = read_city_model(CITYGML / name, **kwargs)
    target = tmp_path / "out.gml"
    report = _update(CITYGML / name, target, _moves(store, shift=np.zeros(3)), kwargs)
    assert report.num_moved == 0 and report.num_coordinates > 0
    # every vertex of the store is found among the file's coordinates
    assert report.vertices_written == set(range(len(store.vertices)))
    parser = etree.XMLParser(huge_tree=True)
    before = etree.tostring(etree.parse(str(CITYGML / name), parser), method="c14n")
    after = etree.tostring(etree.parse(str(target), parser), method="c14n")
    assert after == before
    _same_store(store, read_city_model(target, **kwargs), 0.0)


@pytest.mark.parametrize("name", sorted(CITYGML_FILES))
def test_citygml_corrected_differs_only_in_the_moved_coordinates(name, tmp_path):
    kwargs = CITYGML_FILES[name]
    store = read_city_model(CITYGML / name, **kwargs)
    moves = _moves(store)
    target = tmp_path / "out.gml"
    report = _update(CITYGML / name, target, moves, kwargs)
    assert report.num_moved > 0
    parser = etree.XMLParser(huge_tree=True)
    old = list(etree.parse(str(CITYGML / name), parser).iter())
    new = list(etree.parse(str(target), parser).iter())
    assert len(old) == len(new)
    changed = 0
    for a, b in zip(old, new):
        assert (a.tag, dict(a.attrib), a.tail) == (b.tag, dict(b.attrib), b.tail)
        if _local(a.tag) not in COORDINATES or a.text == b.text:
            assert a.text == b.text
            continue
        changed += 1
        ta, tb = _numbers(a.text), _numbers(b.text)
        assert len(ta) == len(tb)
        # the whitespace between the numbers is kept
        assert re.sub(r"[^\s,]+", "", a.text) == re.sub(r"[^\s,]+", "", b.text)
        diff = np.array(tb, float) - np.array(ta, float)
        assert np.count_nonzero(diff) > 0
    assert changed == report.num_elements
    geographic = "target_crs" in kwargs
    corrected = read_city_model(target, **kwargs)
    # the vertices that did not move are where they were (arbitrary moves of every third
    # vertex may turn a degenerate face into a valid one: compare by coordinates)
    keep = np.setdiff1d(np.arange(len(store.vertices)), moves.vertex_ids)
    now = corrected.vertices + corrected.origin
    for v in keep:
        distance = np.min(np.linalg.norm(now - (store.vertices[v] + store.origin), axis=1))
        assert distance <= (1e-6 if geographic else 0.0)
    # a move of the whole model reads back as the same model, moved
    target_all = tmp_path / "all.gml"
    _update(CITYGML / name, target_all, _moves(store, every=1), kwargs)
    _same_store(store, read_city_model(target_all, **kwargs),
                2e-3 if geographic else 0.5e-3 + 1e-9, moved=np.arange(len(store.vertices)))


def test_citygml_numbers_keep_the_file_s_decimals(tmp_path):
    name = "nrw/LoD2_32_328_5725_1_NW.gml"  # millimetres
    store = read_city_model(CITYGML / name)
    report = update_citygml(CITYGML / name, tmp_path / "out.gml", _moves(store))
    assert report.decimals == 3
    text = (tmp_path / "out.gml").read_text()
    numbers = [n for el in etree.fromstring(text.encode()).iter("{*}posList")
               for n in _numbers(el.text)]
    assert all(len(n.partition(".")[2]) <= 3 for n in numbers)


# -- CityJSON -------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", sorted(CITYJSON_FILES))
def test_cityjson_written_unchanged_is_the_same_document_and_model(name, tmp_path):
    kwargs = CITYJSON_FILES[name]
    store = read_city_model(CITYJSON / name, **kwargs)
    target = tmp_path / "out.city.json"
    report = _update(CITYJSON / name, target, _moves(store, shift=np.zeros(3)), kwargs)
    assert report.num_moved == 0
    assert report.vertices_written == set(range(len(store.vertices)))
    assert json.loads(target.read_text()) == json.loads((CITYJSON / name).read_text())
    _same_store(store, read_city_model(target, **kwargs), 0.0)


@pytest.mark.parametrize("name", sorted(CITYJSON_FILES))
def test_cityjson_corrected_differs_only_in_the_moved_vertices(name, tmp_path):
    kwargs = CITYJSON_FILES[name]
    store = read_city_model(CITYJSON / name, **kwargs)
    moves = _moves(store)
    target = tmp_path / "out.city.json"
    report = _update(CITYJSON / name, target, moves, kwargs)
    assert report.num_moved > 0
    old, new = json.loads((CITYJSON / name).read_text()), json.loads(target.read_text())
    assert {k: v for k, v in old.items() if k != "vertices"} == \
        {k: v for k, v in new.items() if k != "vertices"}
    assert len(old["vertices"]) == len(new["vertices"])
    differ = [i for i, (a, b) in enumerate(zip(old["vertices"], new["vertices"])) if a != b]
    read = set(read_vertex_indices(old["CityObjects"], 2,
                                   store.faces.building_id.unique()).tolist())
    assert len(differ) == report.num_moved and set(differ) <= read
    scale = np.asarray(old.get("transform", {}).get("scale", [1, 1, 1]), float)
    target_all = tmp_path / "all.city.json"
    _update(CITYJSON / name, target_all, _moves(store, every=1), kwargs)
    _same_store(store, read_city_model(target_all, **kwargs), float(scale.max()) / 2 + 1e-9,
                moved=np.arange(len(store.vertices)))


def test_cityjson_sequence_round_trip(tmp_path):
    doc = json.loads((CITYJSON / "DH_01_subs.city.json").read_text())
    header = {k: v for k, v in doc.items() if k not in ("CityObjects", "vertices")}
    header.update(CityObjects={}, vertices=[])
    feature = {"type": "CityJSONFeature", "id": next(iter(doc["CityObjects"])),
               "CityObjects": doc["CityObjects"], "vertices": doc["vertices"]}
    source = tmp_path / "tile.jsonl"
    source.write_text(json.dumps(header) + "\n" + json.dumps(feature) + "\n")
    store = read_city_model(source, crs="EPSG:7415")
    moves = _moves(store, every=1)
    target = tmp_path / "out.city.jsonl"
    update_cityjson(source, target, moves)
    lines = target.read_text().splitlines()
    assert len(lines) == 2 and json.loads(lines[0]) == header
    _same_store(store, read_city_model(target, crs="EPSG:7415"),
                float(np.max(doc["transform"]["scale"])) / 2 + 1e-9, moved=moves.vertex_ids)


# -- tiles in, tiles out --------------------------------------------------------------------------

def test_tiles_in_tiles_out(tmp_path):
    from colmap_citymodel.adjust.model_correction import ModelCorrection
    from colmap_citymodel.output.corrected_model import write_corrected_model

    names = ["tum2twin/DEBY_LOD2_4959321.gml", "tum2twin/DEBY_LOD2_4959322.gml"]
    store = read_city_model([CITYGML / n for n in names])
    ids = np.arange(len(store.vertices))
    correction = ModelCorrection(
        faces=np.arange(store.num_faces), held_faces=np.zeros(0, np.int64), vertex_ids=ids,
        given=store.vertices[ids], corrected=store.vertices[ids] + SHIFT, covariance=None,
        threshold=3.0)
    written, warnings = write_corrected_model(correction, store, tmp_path)
    assert not warnings
    assert [w["target"] for w in written] == [f"corrected_model/{Path(n).name}" for n in names]
    assert sum(w["num_vertices_moved"] for w in written) >= len(store.vertices)
    for n in names:  # each tile reads back as itself, moved
        before = read_city_model(CITYGML / n)
        after = read_city_model(tmp_path / "corrected_model" / Path(n).name)
        _same_store(before, after, 0.5e-3 + 1e-9, moved=np.arange(len(before.vertices)))
    # one file in, one file out, named after its format
    single = read_city_model(CITYJSON / "3dbag_b2.city.json")
    none_moved = ModelCorrection(np.zeros(0, np.int64), np.zeros(0, np.int64),
                                 np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)),
                                 None, 3.0)
    written, _ = write_corrected_model(none_moved, single, tmp_path / "one")
    assert [w["target"] for w in written] == ["corrected_model.city.json"]
    assert json.loads((tmp_path / "one" / "corrected_model.city.json").read_text()) == \
        json.loads((CITYJSON / "3dbag_b2.city.json").read_text())
