"""write_citygml: CityGML 2.0 output that round-trips through read_city_model."""

import numpy as np
import pytest
from lxml import etree

from colmap_citymodel.citymodel.raw_model import RawPolygon
from colmap_citymodel.citymodel.read import read_city_model
from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.citymodel.write_citygml import raw_from_store, write_citygml
from data_paths import CITYGML


def _same_store(a, b, tol=1e-9):
    assert a.num_faces == b.num_faces
    assert a.num_buildings == b.num_buildings
    assert a.crs.label == b.crs.label
    np.testing.assert_array_equal(a.origin, b.origin)
    for fa, fb in zip(a.faces, b.faces):
        assert (fa.semantic, fa.building_id, fa.part_id, fa.gml_id) == (
            fb.semantic, fb.building_id, fb.part_id, fb.gml_id)
        np.testing.assert_allclose(a.vertices[fa.exterior], b.vertices[fb.exterior], atol=tol)
        assert len(fa.holes) == len(fb.holes)
        for ha, hb in zip(fa.holes, fb.holes):
            np.testing.assert_allclose(a.vertices[ha], b.vertices[hb], atol=tol)


def test_box_with_hole_round_trip(tmp_path):
    # a 10 x 6 x 5 m box in UTM-sized coordinates; its front wall has a door hole
    o = np.array([691000.0, 5336000.0, 515.0])
    rings = {
        "front": [[0, 0, 0], [10, 0, 0], [10, 0, 5], [0, 0, 5]],
        "right": [[10, 0, 0], [10, 6, 0], [10, 6, 5], [10, 0, 5]],
        "back": [[10, 6, 0], [0, 6, 0], [0, 6, 5], [10, 6, 5]],
        "left": [[0, 6, 0], [0, 0, 0], [0, 0, 5], [0, 6, 5]],
        "roof": [[0, 0, 5], [10, 0, 5], [10, 6, 5], [0, 6, 5]],
        "ground": [[0, 0, 0], [0, 6, 0], [10, 6, 0], [10, 0, 0]],
    }
    sems = ["WallSurface"] * 4 + ["RoofSurface", "GroundSurface"]
    door = np.array([[4, 0, 0.5], [4, 0, 2.5], [6, 0, 2.5], [6, 0, 0.5]]) + o
    polys = [
        RawPolygon(exterior=np.array(r, float) + o, holes=[door] if k == "front" else [],
                   semantic=s, building_id="B1", gml_id=f"poly-{k}")
        for (k, r), s in zip(rings.items(), sems)
    ]
    path = write_citygml(tmp_path / "box.gml", polys, "EPSG:25832")
    root = etree.parse(str(path)).getroot()
    ns = {"gml": "http://www.opengis.net/gml", "bldg": "http://www.opengis.net/citygml/building/2.0"}
    assert len(root.findall(".//bldg:Building", ns)) == 1
    assert len(root.findall(".//bldg:WallSurface", ns)) == 4
    assert len(root.findall(".//gml:interior", ns)) == 1
    ids = [el.get("{http://www.opengis.net/gml}id") for el in root.iter()]
    ids = [i for i in ids if i]
    assert len(ids) == len(set(ids))  # unique gml:ids

    store = read_city_model(path)
    assert store.num_faces == 6 and store.crs.horizontal_epsg == 25832
    front = next(f for f in store.faces if f.gml_id == "poly-front")
    assert len(front.holes) == 1
    np.testing.assert_allclose(store.to_crs(store.vertices[front.holes[0]]), door, atol=1e-9)
    semantics = sorted(f.semantic for f in store.faces)
    assert semantics == sorted(sems)
    # full precision: the written text reads back to the same float64 values
    roof = next(f for f in store.faces if f.semantic == "RoofSurface")
    np.testing.assert_array_equal(store.to_crs(store.vertices[roof.exterior]).max(0),
                                  np.array([10, 6, 5.0]) + o)


def test_store_round_trip_synthetic(tmp_path):
    ring = np.array([[0, 0, 0], [4, 0, 0], [4, 0, 3], [0, 0, 3]], float) + [391000.25, 5819000.5,
                                                                            34.125]
    store = store_from_polygons([ring, ring + [0, 10, 0]], semantics=["WallSurface"] * 2,
                                building_ids=["a", "b"])
    path = write_citygml(tmp_path / "s.gml", raw_from_store(store), "EPSG:25833")
    back = read_city_model(path)
    assert back.num_buildings == 2
    np.testing.assert_allclose(back.to_crs(back.vertices), store.to_crs(store.vertices),
                               atol=1e-9)


@pytest.mark.parametrize("name", ["berlin/3910_5819.gml", "tum2twin",
                                  "ogc/Building_and_garage_LOD2-EPSG25832_v2.gml"])
def test_real_models_round_trip(tmp_path, name):
    store = read_city_model(CITYGML / name)
    path = write_citygml(tmp_path / "out.gml", raw_from_store(store))
    back = read_city_model(path)
    _same_store(store, back)
    if name == "tum2twin":  # DEBY_LOD2_4959457 has interior rings: they survive
        assert sum(len(f.holes) for f in back.faces) == sum(len(f.holes) for f in store.faces) > 0
    if "ogc" in name:  # BuildingPart survives
        assert back.num_parts == store.num_parts == 1


def test_needs_srs(tmp_path):
    with pytest.raises(ValueError):
        write_citygml(tmp_path / "x.gml", [], None)
