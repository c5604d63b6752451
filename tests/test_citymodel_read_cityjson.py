"""CityJSON reader on the real files in tests/data/cityjson (3DBAG 2.0, Rotterdam 2.0,
Den Haag 1.1) and on small synthetic documents (1.0, CityJSONSeq, MultiSolid, LOD choice).
Expected counts are computed here straight from the JSON, independently of the reader."""

from __future__ import annotations

import copy
import json

import numpy as np
import pyproj
import pytest

from colmap_citymodel.citymodel.read_cityjson import read_cityjson
from colmap_citymodel.citymodel.build import build_store
from colmap_citymodel.errors import CityGMLError, CRSError, InputError, NoOverlapError
from data_paths import CITYJSON

CJ = CITYJSON

FILES = {  # file -> CRS to give (None: the file names one)
    "3dbag_b2.city.json": None,
    "rotterdam_subset.json": "EPSG:7415",
    "DH_01_subs.city.json": "EPSG:7415",
}


def independent_counts(doc, lod=2):
    """Buildings, parts, surfaces and surfaces with < 3 distinct points, from the raw JSON."""
    objs = doc["CityObjects"]
    tr = doc.get("transform", {"scale": [1, 1, 1], "translate": [0, 0, 0]})
    V = np.array(doc["vertices"], float) * tr["scale"] + tr["translate"]

    def root(k):
        while objs[k]["type"] == "BuildingPart":
            k = objs[k]["parents"][0]
        return k

    buildings, parts, surfaces, degenerate = set(), set(), 0, 0
    for k, o in objs.items():
        gs = [g for g in o.get("geometry", []) if int(float(g["lod"])) == lod]
        if not gs:
            continue
        top = max(float(g["lod"]) for g in gs)
        buildings.add(root(k))
        if o["type"] == "BuildingPart":
            parts.add(k)
        for g in gs:
            if float(g["lod"]) != top:
                continue
            b = g["boundaries"]
            if g["type"] == "Solid":
                surfs = b[0]
            elif g["type"] in ("MultiSolid", "CompositeSolid"):
                surfs = [s for solid in b for s in solid[0]]
            else:
                surfs = b
            for s in surfs:
                surfaces += 1
                if len(np.unique(V[s[0]], axis=0)) < 3:
                    degenerate += 1
    return len(buildings), len(parts), surfaces, degenerate


@pytest.mark.parametrize("name", list(FILES))
def test_real_files_load_with_independent_counts(name):
    doc = json.loads((CJ / name).read_text())
    raw = read_cityjson(CJ / name, crs=FILES[name])
    store = build_store(raw)
    n_b, n_p, n_s, n_deg = independent_counts(doc)
    assert store.num_buildings == n_b
    assert store.num_parts == n_p
    assert len(raw.polygons) == n_s
    assert store.num_dropped_degenerate == n_deg
    assert store.num_faces == n_s - n_deg
    assert raw.version == doc["version"]
    assert store.crs.horizontal_epsg == 28992 and store.crs.vertical_epsg == 5709
    # bbox equals the extent of the used vertices (CRS), origin its floor
    tr = doc["transform"]
    V = np.array(doc["vertices"], float) * tr["scale"] + tr["translate"]
    assert np.all(store.bbox_crs[0] >= V.min(0) - 1e-6)
    np.testing.assert_array_equal(store.origin, np.floor(store.bbox_crs[0]))
    # planes: walls vertical, roofs up, ground down; vertices on their planes
    sem = np.array([f.semantic for f in store.faces])
    n = store.normals
    assert (sem == "WallSurface").sum() > 10
    assert np.abs(n[sem == "WallSurface", 2]).max() < 1e-3
    assert n[sem == "RoofSurface", 2].min() > 0.2
    assert n[sem == "GroundSurface", 2].max() < -0.99
    assert store.nonplanar.sum() == 0
    assert np.median(store.rms_out_of_plane) < 1e-3


@pytest.mark.parametrize("name", ["3dbag_b2.city.json", "DH_01_subs.city.json"])
def test_solids_are_closed_and_outward(name):
    """Closed solids: every edge used twice in opposite directions; positive volume per part."""
    store = build_store(read_cityjson(CJ / name, crs=FILES[name]))
    volumes: dict[str, float] = {}
    for f, face in enumerate(store.faces):
        key = face.part_id or face.building_id
        # divergence theorem: V = 1/3 sum area * (n . P0)
        P0 = store.to_crs(store.centroids[f]) - store.bbox_crs[0]
        volumes[key] = volumes.get(key, 0.0) + store.areas[f] * (store.normals[f] @ P0) / 3
    assert all(v > 0.1 for v in volumes.values()), volumes
    # closed and consistently oriented: each directed edge of a part has its reverse
    edges: dict[str, list] = {}
    for face in store.faces:
        ring = face.exterior
        edges.setdefault(face.part_id or face.building_id, []).extend(
            zip(ring.tolist(), np.roll(ring, -1).tolist())
        )
    for key, e in edges.items():
        assert sorted(e) == sorted((b, a) for a, b in e), key


def test_no_crs_is_a_clear_error():
    with pytest.raises(CRSError) as info:
        read_cityjson(CJ / "rotterdam_subset.json")
    assert "no CRS" in str(info.value) and "--crs" in str(info.value)
    assert info.value.path == CJ / "rotterdam_subset.json"


def to_cityjsonseq(doc):
    """CityJSON -> CityJSONSeq text: header line + one CityJSONFeature per Building."""
    header = {k: v for k, v in doc.items() if k not in ("CityObjects", "vertices", "appearance")}
    header["CityObjects"] = {}
    header["vertices"] = []
    lines = [json.dumps(header)]
    objs = doc["CityObjects"]
    for k, o in objs.items():
        if o["type"] != "Building":
            continue
        members = {k: copy.deepcopy(o), **{c: copy.deepcopy(objs[c]) for c in o.get("children", [])}}
        remap: dict[int, int] = {}

        def walk(x):
            if isinstance(x, list):
                return [walk(y) for y in x]
            return remap.setdefault(x, len(remap))

        for m in members.values():
            for g in m.get("geometry", []):
                g["boundaries"] = walk(g["boundaries"])
                g.pop("texture", None)
                g.pop("material", None)
        verts = [None] * len(remap)
        for old, new in remap.items():
            verts[new] = doc["vertices"][old]
        feature = {"type": "CityJSONFeature", "id": k, "CityObjects": members, "vertices": verts}
        lines.append(json.dumps(feature))
    return "\n".join(lines) + "\n"


def test_cityjsonseq_gives_the_same_store(tmp_path):
    doc = json.loads((CJ / "DH_01_subs.city.json").read_text())
    jsonl = tmp_path / "dh.jsonl"
    jsonl.write_text(to_cityjsonseq(doc))
    seq = build_store(read_cityjson(jsonl, crs="EPSG:7415"))
    ref = build_store(read_cityjson(CJ / "DH_01_subs.city.json", crs="EPSG:7415"))
    assert seq.num_faces == ref.num_faces > 0
    assert seq.num_buildings == ref.num_buildings and seq.num_parts == ref.num_parts
    np.testing.assert_allclose(seq.bbox_crs, ref.bbox_crs, atol=1e-9)
    a = np.sort(seq.to_crs(seq.vertices), axis=0)
    b = np.sort(ref.to_crs(ref.vertices), axis=0)
    np.testing.assert_allclose(a, b, atol=1e-6)
    assert read_cityjson(jsonl, crs="EPSG:7415").format == "CityJSONSeq"


def test_cityjson_1_0_float_vertices_and_urn_crs(tmp_path):
    doc = json.loads((CJ / "DH_01_subs.city.json").read_text())
    tr = doc.pop("transform")
    doc["vertices"] = (np.array(doc["vertices"], float) * tr["scale"] + tr["translate"]).tolist()
    doc["version"] = "1.0"
    doc["metadata"] = {"referenceSystem": "urn:ogc:def:crs:EPSG::7415"}
    for o in doc["CityObjects"].values():
        for g in o.get("geometry", []):
            g["lod"] = 2  # 1.0 writes a number
    p = tmp_path / "v10.json"
    p.write_text(json.dumps(doc))
    v10 = build_store(read_cityjson(p))
    ref = build_store(read_cityjson(CJ / "DH_01_subs.city.json", crs="EPSG:7415"))
    assert v10.version == "1.0" and v10.crs.horizontal_epsg == 28992
    assert v10.num_faces == ref.num_faces
    np.testing.assert_allclose(v10.bbox_crs, ref.bbox_crs, atol=1e-9)


CUBE_V = [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]]
CUBE_SHELL = [[[0, 3, 2, 1]], [[4, 5, 6, 7]], [[0, 1, 5, 4]], [[1, 2, 6, 5]], [[2, 3, 7, 6]],
              [[3, 0, 4, 7]]]
CUBE_SEM = {"surfaces": [{"type": "GroundSurface"}, {"type": "RoofSurface"},
                         {"type": "WallSurface"}], "values": [[0, 1, 2, 2, 2, 2]]}


def synthetic_doc():
    """Building A: LOD 1 + LOD 2.0 + LOD 2.2 (a shifted cube) + a template; building B: two
    cubes as a MultiSolid; building C: a roof-only CompositeSurface; no transform."""
    V = [[int(a) for a in np.add(v, off)] for off in ([0, 0, 0], [10, 0, 0], [20, 0, 0], [22, 0, 0],
                                          [30, 0, 0]) for v in CUBE_V]

    def shell(k):
        return [[[i + 8 * k for i in ring] for ring in s] for s in CUBE_SHELL]

    return {
        "type": "CityJSON", "version": "2.0",
        "metadata": {"referenceSystem": "https://www.opengis.net/def/crs/EPSG/0/25832"},
        "transform": {"scale": [1, 1, 1], "translate": [600000, 5300000, 500]},
        "CityObjects": {
            "A": {"type": "Building", "geometry": [
                {"type": "Solid", "lod": "1", "boundaries": [shell(0)]},
                {"type": "Solid", "lod": "2", "boundaries": [shell(0)], "semantics": CUBE_SEM},
                {"type": "Solid", "lod": "2.2", "boundaries": [shell(1)], "semantics": CUBE_SEM},
                {"type": "GeometryInstance", "lod": "2", "template": 0,
                 "boundaries": [0], "transformationMatrix": np.eye(4).ravel().tolist()},
            ]},
            "B": {"type": "Building", "geometry": [
                {"type": "MultiSolid", "lod": "2", "boundaries": [[shell(2)], [shell(3)]],
                 "semantics": {"surfaces": CUBE_SEM["surfaces"],
                               "values": [CUBE_SEM["values"], CUBE_SEM["values"]]}},
            ]},
            "C": {"type": "Building", "geometry": [
                {"type": "CompositeSurface", "lod": "2", "boundaries": [shell(4)[1]],
                 "semantics": {"surfaces": [{"type": "RoofSurface"}], "values": [0]}},
            ]},
            "T": {"type": "TINRelief", "geometry": []},
        },
        "vertices": V,
    }


def test_lod_choice_geometry_types_and_semantics(tmp_path):
    p = tmp_path / "syn.city.json"
    p.write_text(json.dumps(synthetic_doc()))
    raw = read_cityjson(p)
    assert any("GeometryInstance" in w for w in raw.warnings)
    store = build_store(raw)
    assert store.num_buildings == 3
    assert store.crs.horizontal_epsg == 25832
    by_b = {b: [f for f in store.faces if f.building_id == b] for b in "ABC"}
    assert [len(by_b[b]) for b in "ABC"] == [6, 12, 1]
    # A: only the LOD 2.2 cube (x in 10..11), not the LOD 2.0 one
    a_ids = np.unique(np.concatenate([f.exterior for f in by_b["A"]]))
    np.testing.assert_allclose(store.to_crs(store.vertices[a_ids])[:, 0].min(), 600010)
    # B: the two cubes of the MultiSolid touch at x = 22? no: 20..21 and 22..23, 16 vertices
    b_ids = np.unique(np.concatenate([f.exterior for f in by_b["B"]]))
    assert len(b_ids) == 16
    assert sum(f.semantic == "RoofSurface" for f in by_b["B"]) == 2
    assert by_b["C"][0].semantic == "RoofSurface" and by_b["C"][0].part_id == ""
    assert all(p.from_solid for p in raw.polygons if p.building_id in "AB")
    # LOD 1 picks the LOD 1 solid of A only
    lod1 = build_store(read_cityjson(p, lod=1))
    assert lod1.num_buildings == 1 and lod1.num_faces == 6
    with pytest.raises(CityGMLError, match="no building geometry at LOD 3"):
        read_cityjson(p, lod=3)


def test_bbox_filter_and_reprojection(tmp_path):
    p = tmp_path / "syn.city.json"
    p.write_text(json.dumps(synthetic_doc()))
    raw = read_cityjson(p, bbox_crs=np.array([[600029, 5299999], [600040, 5300002]]))
    assert raw.building_ids == ["C"]
    with pytest.raises(NoOverlapError):
        read_cityjson(p, bbox_crs=np.array([[0, 0], [1, 1]]))
    # reprojection UTM 32 -> UTM 33, against pyproj directly
    rep = read_cityjson(p, target_crs="EPSG:25833")
    assert rep.crs.horizontal_epsg == 25833
    t = pyproj.Transformer.from_crs(25832, 25833, always_xy=True)
    x, y = t.transform(600020.0, 5300000.0)  # a corner of B (LOD 2)
    got = np.concatenate([q.exterior for q in rep.polygons])
    assert np.min(np.hypot(got[:, 0] - x, got[:, 1] - y)) < 1e-6
    with pytest.raises(CRSError):
        read_cityjson(p, target_crs="EPSG:4326")


def test_bad_input_errors(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="not valid JSON"):
        read_cityjson(bad)
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"type": "FeatureCollection", "features": []}))
    with pytest.raises(InputError, match="not a CityJSON file"):
        read_cityjson(other)
    doc = synthetic_doc()
    doc["CityObjects"]["C"]["geometry"][0]["boundaries"] = [[[0, 1, 999]]]
    idx = tmp_path / "idx.json"
    idx.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="bad vertex index"):
        read_cityjson(idx)
    with pytest.raises(InputError):
        read_cityjson(tmp_path / "missing.json")
