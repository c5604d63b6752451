"""CityGML reader: every file in tests/data/citygml plus small synthetic files for the
cases the real files do not show (ring xlinks, references across buildings, bbox filter, ...).

Expected counts of the files come from inspecting them independently of the reader
(grep for `<gml:Polygon`, `<gml:interior`, `<bldg:Building`, `<bldg:BuildingPart`, and the
files' README in tests/data). Real files: openNRW (dl-de/zero-2.0), Berlin (dl-de/by-2.0),
tum-gis Berlin Moabit (MIT), OGC CityGML examples (MIT), PLATEAU (CC BY 4.0), tum2twin
(CC BY 4.0); synthetic files (tests/data/citygml/synthetic, written by its make_synthetic.py):
a building of three parts with xlinked solids (CityGML 1.0), a house part with no CRS.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from colmap_citymodel.citymodel.read import read_city_model
from colmap_citymodel.citymodel.read_citygml import read_citygml
from colmap_citymodel.citymodel.build import build_store
from colmap_citymodel.errors import CityGMLError, CRSError, InputError, NoOverlapError
from data_paths import CITYGML


# file -> (reader kwargs, version, crs label, buildings, parts, polygons, holes, {semantic: n})
REAL = {
    "nrw/LoD2_32_328_5725_1_NW.gml": (
        {}, "1.0", "EPSG:25832+7837", 2, 0, 15, 0,
        {"WallSurface": 10, "RoofSurface": 3, "GroundSurface": 2},
    ),
    "berlin/3920_5820.gml": (
        {}, "2.0", "EPSG:25833", 6, 0, 133, 0,
        {"WallSurface": 76, "RoofSurface": 36, "GroundSurface": 21},
    ),
    "berlin/3910_5819.gml": (
        {}, "2.0", "EPSG:25833", 35, 0, 1207, 1,
        {"WallSurface": 867, "RoofSurface": 210, "GroundSurface": 130},
    ),
    "berlin/Berlin_Moabit_1Bldg_v2.gml": (
        {}, "2.0", "EPSG:25833+5783", 1, 0, 6, 0,
        {"WallSurface": 4, "RoofSurface": 1, "GroundSurface": 1},
    ),
    "berlin/Berlin_Moabit_1Bldg_v3.gml": (
        {}, "3.0", "EPSG:25833+5783", 1, 0, 6, 0,
        {"WallSurface": 4, "RoofSurface": 1, "GroundSurface": 1},
    ),
    "ogc/Building_CityGML3.0_LOD2_with_several_attributes.gml": (
        {}, "3.0", "EPSG:31468+5783", 1, 0, 11, 0,
        {"WallSurface": 8, "RoofSurface": 2, "GroundSurface": 1},
    ),
    # 13 gml:Polygon elements; the garage's west wall is the building's east wall 2, referenced
    # through OrientableSurface orientation="-": one face
    "ogc/Building_and_garage_LOD2-EPSG25832_v2.gml": (
        {}, "2.0", "EPSG:25832+5783", 1, 1, 13, 0,
        {"WallSurface": 8, "RoofSurface": 3, "GroundSurface": 2},
    ),
    "ogc/Building_and_garage_LOD2-EPSG25832_v3.gml": (
        {}, "3.0", "EPSG:25832+5783", 1, 1, 13, 0,
        {"WallSurface": 8, "RoofSurface": 3, "GroundSurface": 2},
    ),
    "plateau/53394517_bldg_6697_op_CityGML2.gml": (
        {"target_crs": "EPSG:6677"}, "2.0", "EPSG:6677+6695", 1, 0, 650, 0,
        {"WallSurface": 370, "RoofSurface": 279, "GroundSurface": 1},
    ),
    "synthetic/parts_xlinked_solids_v1.gml": (
        {}, "1.0", "EPSG:28992", 1, 3, 19, 0,
        {"WallSurface": 12, "RoofSurface": 4, "GroundSurface": 3},
    ),
    "synthetic/no_crs_house_part.gml": (
        {"crs": "EPSG:3946"}, "2.0", "EPSG:3946", 1, 1, 7, 0,
        {"WallSurface": 4, "RoofSurface": 2, "GroundSurface": 1},
    ),
    # a house beside a dem:ReliefFeature (TINRelief): the relief is no building face
    "synthetic/relief_tin_house.gml": (
        {}, "2.0", "EPSG:25832+7837", 1, 0, 6, 0,
        {"WallSurface": 4, "RoofSurface": 1, "GroundSurface": 1},
    ),
    "tum2twin/DEBY_LOD2_4906970.gml": ({}, "2.0", "EPSG:25832", 1, 0, 13, 0, None),
    "tum2twin/DEBY_LOD2_4906972.gml": ({}, "2.0", "EPSG:25832", 1, 0, 24, 0, None),
    "tum2twin/DEBY_LOD2_4959321.gml": ({}, "2.0", "EPSG:25832", 1, 0, 8, 0, None),
    "tum2twin/DEBY_LOD2_4959322.gml": ({}, "2.0", "EPSG:25832", 1, 0, 7, 0, None),
    "tum2twin/DEBY_LOD2_4959323.gml": ({}, "2.0", "EPSG:25832", 1, 0, 14, 0, None),
    "tum2twin/DEBY_LOD2_4959324.gml": ({}, "2.0", "EPSG:25832", 1, 0, 7, 0, None),
    "tum2twin/DEBY_LOD2_4959457.gml": ({}, "2.0", "EPSG:25832", 1, 0, 84, 6, None),
}

# max distance of a store vertex to its face's plane, per file (the producers' rounding is 1 mm;
# merging moves corners by up to 1 mm; Berlin 3910 holds a few genuinely warped faces)
PLANE_TOLERANCE = {"berlin/3910_5819.gml": 0.05}
DEFAULT_PLANE_TOLERANCE = 0.004


def test_every_real_file_is_covered():
    on_disk = {str(p.relative_to(CITYGML)) for p in CITYGML.rglob("*.gml")}
    assert on_disk == set(REAL)


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_file_counts(name):
    kwargs, version, label, buildings, parts, polygons, holes, classes = REAL[name]
    raw = read_citygml(CITYGML / name, **kwargs)
    assert raw.format == "CityGML" and raw.version == version
    assert raw.crs.label == label and raw.crs.is_projected
    assert len(raw.building_ids) == buildings == len(set(raw.building_ids))
    assert len(raw.part_ids) == parts
    assert len(raw.polygons) == polygons
    assert sum(len(p.holes) for p in raw.polygons) == holes
    if classes is not None:
        assert Counter(p.semantic for p in raw.polygons) == classes
    ids = [p.gml_id for p in raw.polygons if p.gml_id]
    assert len(ids) == len(set(ids)), "a polygon became two faces"
    for p in raw.polygons:
        assert p.exterior.ndim == 2 and p.exterior.shape[1] == 3 and len(p.exterior) >= 3
        assert not np.array_equal(p.exterior[0], p.exterior[-1]), "closing point kept"
        assert p.lod == 2
        assert p.building_id in raw.building_ids
        assert p.part_id == "" or p.part_id in raw.part_ids


def test_berlin_block_has_exactly_one_face_with_a_hole():
    store = read_city_model(CITYGML / "berlin/3910_5819.gml")
    assert store.num_buildings == 35
    assert sum(1 for f in store.faces if f.holes) == 1
    # two of the 1207 polygons are slivers the store drops as degenerate
    assert store.num_faces + store.num_dropped_degenerate == 1207


def test_building_parts_all_from_xlinked_solids():
    raw = read_citygml(CITYGML / "synthetic/parts_xlinked_solids_v1.gml")
    assert len(raw.building_ids) == 1 and len(raw.part_ids) == 3
    assert {p.part_id for p in raw.polygons} == set(raw.part_ids)
    # every thematic polygon is referenced by its part's lod2Solid: one face each, in the solid
    assert all(p.from_solid for p in raw.polygons)


def test_nrw_solid_made_only_of_references():
    raw = read_citygml(CITYGML / "nrw/LoD2_32_328_5725_1_NW.gml")
    assert all(p.from_solid for p in raw.polygons)
    assert raw.crs.srs_name == "urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH*GCG2016"
    x = np.concatenate([p.exterior for p in raw.polygons])
    assert np.all((x[:, 0] >= 328000) & (x[:, 0] <= 329000) & (x[:, 1] >= 5725000) & (x[:, 1] <= 5726000))


def test_tum2twin_holes():
    raw = read_citygml(CITYGML / "tum2twin/DEBY_LOD2_4959457.gml")
    holes = [h for p in raw.polygons for h in p.holes]
    assert len(holes) == 6
    assert all(len(h) >= 3 for h in holes)


def test_no_crs_needs_a_crs():
    path = CITYGML / "synthetic/no_crs_house_part.gml"
    with pytest.raises(CRSError) as info:
        read_citygml(path)
    assert "no CRS in the file; pass --crs EPSG:N" in str(info.value)
    assert info.value.path == path
    raw = read_citygml(path, crs="EPSG:3946")
    x = np.concatenate([p.exterior for p in raw.polygons])
    # Lyon in CC46: E ~1.84e6, N ~5.18e6
    assert np.all((x[:, 0] > 1.84e6) & (x[:, 0] < 1.85e6) & (x[:, 1] > 5.17e6) & (x[:, 1] < 5.18e6))


def test_plateau_needs_a_projected_target_and_lands_in_tokyo():
    path = CITYGML / "plateau/53394517_bldg_6697_op_CityGML2.gml"
    with pytest.raises(CRSError) as info:
        read_citygml(path)
    assert "geographic" in str(info.value) and "--target_crs EPSG:6677" in str(info.value)
    with pytest.raises(CRSError, match="not projected"):
        read_citygml(path, target_crs="EPSG:4326")
    raw = read_citygml(path, target_crs="EPSG:6677")
    x = np.concatenate([p.exterior for p in raw.polygons])
    # metres in Japan plane rectangular CS IX (origin 36N, 139d50'E): Shibuya/Sendagaya is
    # ~35.6 km south and ~10.5 km west of the origin; a building is < 200 m across
    assert np.all((x[:, 0] > -10_700) & (x[:, 0] < -10_300))
    assert np.all((x[:, 1] > -35_800) & (x[:, 1] < -35_500))
    assert np.ptp(x[:, 0]) < 200 and np.ptp(x[:, 1]) < 200
    assert 30 < x[:, 2].min() < x[:, 2].max() < 80  # heights pass through (metres)
    # the first vertex of polygon poly_STAD0158_b_0 (lat, lon, h in the file), reprojected
    # independently with the CRSs' own axis order (EPSG:6677 is northing, easting)
    import pyproj

    north, east = pyproj.Transformer.from_crs("EPSG:6668", "EPSG:6677").transform(
        35.67868063499655, 139.7175193440728
    )
    first = next(p for p in raw.polygons if p.gml_id == "poly_STAD0158_b_0").exterior[0]
    np.testing.assert_allclose(first, [east, north, 34.50698481], atol=1e-6)
    # LOD1 is the block model: one solid of 134 polygons
    lod1 = read_citygml(path, target_crs="EPSG:6677", lod=1)
    assert len(lod1.polygons) == 134 and all(p.from_solid and p.lod == 1 for p in lod1.polygons)


def test_missing_lod_names_the_available_ones():
    with pytest.raises(CityGMLError, match=r"no building geometry at LOD 3 \(it has LOD 2"):
        read_citygml(CITYGML / "nrw/LoD2_32_328_5725_1_NW.gml", lod=3)


# ---------------------------------------------------------------------------------------------
# stores of the real files: planes, shared vertices, orientation
# ---------------------------------------------------------------------------------------------


def _store(name):
    return read_city_model(CITYGML / name, **REAL[name][0])


@pytest.mark.parametrize("name", sorted(REAL))
def test_real_file_planes(name):
    store = _store(name)
    n = store.normals
    tol = PLANE_TOLERANCE.get(name, DEFAULT_PLANE_TOLERANCE)
    for f in range(store.num_faces):
        ids = store.face_vertex_ids(f)
        d = (store.vertices[ids] - store.centroids[f]) @ n[f]
        assert np.abs(d).max() <= tol, (name, store.faces[f].gml_id, np.abs(d).max())
    sem = np.array([f.semantic for f in store.faces])
    # ground faces look down, roofs up (PLATEAU has a few vertical roof faces: n_z = 0)
    assert np.all(n[sem == "GroundSurface", 2] < -0.99)
    assert np.all(n[sem == "RoofSurface", 2] > -1e-3)
    # walls are vertical: horizontal normals, except slivers and PLATEAU's underside faces
    big_walls = (sem == "WallSurface") & (store.areas >= 0.1)
    tilted = np.flatnonzero(big_walls & (np.abs(n[:, 2]) >= 0.01))
    if name.startswith("plateau"):
        # downward-facing faces of three overhanging structures, labelled WallSurface by the producer
        assert {store.faces[f].gml_id.rsplit("_", 1)[0] for f in tilted} == {
            "poly_STAD0158_p1939", "poly_STAD0158_p1940", "poly_STAD0158_p1941"
        }
    else:
        assert len(tilted) == 0, [store.faces[f].gml_id for f in tilted]
    assert np.count_nonzero(sem == "WallSurface") > 0


@pytest.mark.parametrize(
    "name",
    ["nrw/LoD2_32_328_5725_1_NW.gml", "synthetic/parts_xlinked_solids_v1.gml",
     "ogc/Building_and_garage_LOD2-EPSG25832_v2.gml", "berlin/Berlin_Moabit_1Bldg_v2.gml"],
)
def test_closed_solids_share_every_corner(name):
    """In closed solids every corner is shared by at least three faces."""
    store = _store(name)
    indptr, _ = store.vertex_faces
    assert np.all(np.diff(indptr) >= 3)


def test_tum2twin_corners_are_shared_after_merging():
    """tum2twin walls and roofs disagree by 1 mm at shared corners: merged within 1 mm they share
    vertex indices, unmerged they do not (DEBY_LOD2_4959457: 278 distinct corners, 272 merged)."""
    raw = read_citygml(CITYGML / "tum2twin/DEBY_LOD2_4959457.gml")
    merged = build_store(raw, merge_tolerance=0.001)
    apart = build_store(raw, merge_tolerance=1e-7)
    deg_merged = np.diff(merged.vertex_faces[0])
    deg_apart = np.diff(apart.vertex_faces[0])
    assert np.all(deg_merged >= 2)  # every corner belongs to two faces at least
    assert np.any(deg_apart == 1)  # ... which only merging achieves
    assert len(merged.vertices) < len(apart.vertices)
    # roofs and walls meet: some vertex belongs to both a roof and a wall
    sem = np.array([f.semantic for f in merged.faces])
    indptr, idx = merged.vertex_faces
    both = [
        v for v in range(len(merged.vertices))
        if {"RoofSurface", "WallSurface"} <= set(sem[idx[indptr[v]:indptr[v + 1]]])
    ]
    assert len(both) >= 4


def _sorted_vertices(store):
    v = store.to_crs(store.vertices)
    return v[np.lexsort(np.round(v, 3).T[::-1])]


@pytest.mark.parametrize(
    "v2, v3",
    [
        ("berlin/Berlin_Moabit_1Bldg_v2.gml", "berlin/Berlin_Moabit_1Bldg_v3.gml"),
        ("ogc/Building_and_garage_LOD2-EPSG25832_v2.gml", "ogc/Building_and_garage_LOD2-EPSG25832_v3.gml"),
    ],
)
def test_citygml_2_and_3_give_the_same_store(v2, v3):
    a, b = _store(v2), _store(v3)
    assert a.version == "2.0" and b.version == "3.0"
    assert a.num_faces == b.num_faces and len(a.vertices) == len(b.vertices)
    assert Counter(f.semantic for f in a.faces) == Counter(f.semantic for f in b.faces)
    assert np.abs(_sorted_vertices(a) - _sorted_vertices(b)).max() < 1e-3
    assert a.crs.label == b.crs.label
    # same faces: centroids and normals match after sorting by centroid
    ka = np.lexsort(np.round(a.centroids, 3).T[::-1])
    kb = np.lexsort(np.round(b.centroids, 3).T[::-1])
    np.testing.assert_allclose(a.to_crs(a.centroids)[ka], b.to_crs(b.centroids)[kb], atol=1e-3)
    np.testing.assert_allclose(a.normals[ka], b.normals[kb], atol=1e-6)


def test_directory_of_tiles_and_crs_mismatch():
    store = read_city_model(CITYGML / "tum2twin")
    assert store.num_buildings == 7
    assert store.num_faces == 13 + 24 + 8 + 7 + 14 + 7 + 84
    with pytest.raises(CRSError, match="all tiles must share one CRS"):
        read_city_model([CITYGML / "nrw/LoD2_32_328_5725_1_NW.gml", CITYGML / "berlin/3920_5820.gml"])
    with pytest.raises(InputError, match="no such file"):
        read_city_model(CITYGML / "nope.gml")


def test_bbox_filter_on_real_block():
    path = CITYGML / "berlin/3910_5819.gml"
    full = read_citygml(path)
    # a box around one building's footprint
    target = full.building_ids[10]
    pts = np.concatenate([p.exterior for p in full.polygons if p.building_id == target])
    lo, hi = pts.min(0), pts.max(0)
    box = np.array([lo[:2] + 0.2 * (hi[:2] - lo[:2]), hi[:2] - 0.2 * (hi[:2] - lo[:2])])
    part = read_citygml(path, bbox_crs=box)
    assert target in part.building_ids
    assert 1 <= len(part.building_ids) < 35
    # independent check: exactly the buildings whose xy bbox meets the box were kept
    expected = []
    for b in full.building_ids:
        q = np.concatenate([p.exterior for p in full.polygons if p.building_id == b])
        if np.all(q.min(0)[:2] <= box[1]) and np.all(q.max(0)[:2] >= box[0]):
            expected.append(b)
    assert part.building_ids == expected
    with pytest.raises(NoOverlapError):
        read_citygml(path, bbox_crs=np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]))


def test_malformed_and_foreign_xml(tmp_path):
    src = (CITYGML / "berlin/3920_5820.gml").read_bytes()
    truncated = tmp_path / "truncated.gml"
    truncated.write_bytes(src[: len(src) // 2])
    with pytest.raises(CityGMLError, match="malformed XML") as info:
        read_citygml(truncated)
    assert info.value.path == truncated
    foreign = tmp_path / "foreign.xml"
    foreign.write_text('<?xml version="1.0"?><kml xmlns="http://www.opengis.net/kml/2.2"><Document/></kml>')
    with pytest.raises(CityGMLError, match="not a CityGML file"):
        read_citygml(foreign)
    with pytest.raises(InputError, match="no such file"):
        read_citygml(tmp_path / "missing.gml")


# ---------------------------------------------------------------------------------------------
# synthetic files
# ---------------------------------------------------------------------------------------------

VERSIONS = {
    "1.0": dict(
        core="http://www.opengis.net/citygml/1.0", bldg="http://www.opengis.net/citygml/building/1.0",
        con="http://www.opengis.net/citygml/building/1.0", gml="http://www.opengis.net/gml",
        boundary="bldg:boundedBy", surface_prefix="bldg", geom_prefix="bldg", shell="CompositeSurface",
    ),
    "2.0": dict(
        core="http://www.opengis.net/citygml/2.0", bldg="http://www.opengis.net/citygml/building/2.0",
        con="http://www.opengis.net/citygml/building/2.0", gml="http://www.opengis.net/gml",
        boundary="bldg:boundedBy", surface_prefix="bldg", geom_prefix="bldg", shell="CompositeSurface",
    ),
    "3.0": dict(
        core="http://www.opengis.net/citygml/3.0", bldg="http://www.opengis.net/citygml/building/3.0",
        con="http://www.opengis.net/citygml/construction/3.0", gml="http://www.opengis.net/gml/3.2",
        boundary="core:boundary", surface_prefix="con", geom_prefix="core", shell="Shell",
    ),
}


def box_faces(x0, y0, w=10.0, d=8.0, h=6.0, z0=30.0):
    """The six outward-oriented faces of a box: {semantic: [ring (4,3)]}."""
    p = np.array([
        [x0, y0, z0], [x0 + w, y0, z0], [x0 + w, y0 + d, z0], [x0, y0 + d, z0],
        [x0, y0, z0 + h], [x0 + w, y0, z0 + h], [x0 + w, y0 + d, z0 + h], [x0, y0 + d, z0 + h],
    ])
    return {
        "GroundSurface": [p[[0, 3, 2, 1]]],
        "RoofSurface": [p[[4, 5, 6, 7]]],
        "WallSurface": [p[[0, 1, 5, 4]], p[[1, 2, 6, 5]], p[[2, 3, 7, 6]], p[[3, 0, 4, 7]]],
    }


def pos_list(ring):
    closed = np.vstack([ring, ring[:1]])
    return " ".join(f"{v:.3f}" for v in closed.ravel())


def polygon_xml(pid, ring, holes=()):
    inner = "".join(
        f"<gml:interior><gml:LinearRing><gml:posList>{pos_list(h)}</gml:posList></gml:LinearRing></gml:interior>"
        for h in holes
    )
    return (
        f'<gml:Polygon gml:id="{pid}"><gml:exterior><gml:LinearRing>'
        f"<gml:posList>{pos_list(ring)}</gml:posList></gml:LinearRing></gml:exterior>{inner}</gml:Polygon>"
    )


def building_xml(bid, x0=0.0, y0=0.0, *, version="2.0", solid="refs", srs="EPSG:25832", extra_solid_refs=(),
                 omit=()):
    """A box building: thematic surfaces with inline polygons and a lod2Solid.

    solid="refs": the solid references the thematic polygons; "inline": the solid holds the
    polygons and the thematic surfaces reference them; None: no solid."""
    v = VERSIONS[version]
    faces = box_faces(x0, y0)
    ids = []
    thematic = []
    solid_members = []
    for sem, rings in faces.items():
        for k, ring in enumerate(rings):
            pid = f"{bid}_{sem}_{k}"
            if pid in omit:
                continue
            ids.append(pid)
            if solid == "inline":
                member = f'<gml:surfaceMember xlink:href="#{pid}"/>'
                solid_members.append(f"<gml:surfaceMember>{polygon_xml(pid, ring)}</gml:surfaceMember>")
            else:
                member = f"<gml:surfaceMember>{polygon_xml(pid, ring)}</gml:surfaceMember>"
                solid_members.append(f'<gml:surfaceMember xlink:href="#{pid}"/>')
            sp, gp = v["surface_prefix"], v["geom_prefix"]
            thematic.append(
                f'<{v["boundary"]}><{sp}:{sem} gml:id="{pid}_ts"><{gp}:lod2MultiSurface><gml:MultiSurface>'
                f"{member}</gml:MultiSurface></{gp}:lod2MultiSurface></{sp}:{sem}></{v['boundary']}>"
            )
    solid_members += [f'<gml:surfaceMember xlink:href="{r}"/>' for r in extra_solid_refs]
    solid_xml = ""
    if solid:
        gp, shell = v["geom_prefix"], v["shell"]
        solid_xml = (
            f'<{gp}:lod2Solid><gml:Solid srsName="{srs}"><gml:exterior><gml:{shell}>'
            f'{"".join(solid_members)}</gml:{shell}></gml:exterior></gml:Solid></{gp}:lod2Solid>'
        )
    env = f'<gml:boundedBy><gml:Envelope srsName="{srs}"/></gml:boundedBy>' if srs else ""
    return f'<bldg:Building gml:id="{bid}">{env}{"".join(thematic)}{solid_xml}</bldg:Building>', ids


def city_xml(members, *, version="2.0", srs=None):
    v = VERSIONS[version]
    env = (
        f'<gml:boundedBy><gml:Envelope srsName="{srs}" srsDimension="3"><gml:lowerCorner>0 0 0</gml:lowerCorner>'
        f"<gml:upperCorner>1 1 1</gml:upperCorner></gml:Envelope></gml:boundedBy>"
        if srs else ""
    )
    body = "".join(f"<core:cityObjectMember>{m}</core:cityObjectMember>" for m in members)
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<core:CityModel xmlns:core="{v["core"]}" xmlns:bldg="{v["bldg"]}" xmlns:con="{v["con"]}" '
        f'xmlns:gml="{v["gml"]}" xmlns:xlink="http://www.w3.org/1999/xlink">{env}{body}</core:CityModel>\n'
    )


def write(tmp_path, text, name="city.gml"):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.mark.parametrize("version", ["1.0", "2.0", "3.0"])
@pytest.mark.parametrize("solid", ["refs", "inline"])
def test_box_solid_and_thematic_become_one_face_each(tmp_path, version, solid):
    xml, ids = building_xml("B1", 100.0, 200.0, version=version, solid=solid)
    raw = read_citygml(write(tmp_path, city_xml([xml], version=version)))
    assert raw.version == version
    assert sorted(p.gml_id for p in raw.polygons) == sorted(ids)
    assert Counter(p.semantic for p in raw.polygons) == {"WallSurface": 4, "RoofSurface": 1, "GroundSurface": 1}
    assert all(p.from_solid for p in raw.polygons)
    store = build_store(raw)
    assert store.num_faces == 6 and len(store.vertices) == 8
    assert np.all(np.diff(store.vertex_faces[0]) == 3)
    sem = np.array([f.semantic for f in store.faces])
    n = store.normals
    np.testing.assert_allclose(n[sem == "RoofSurface"], [[0, 0, 1]], atol=1e-9)
    np.testing.assert_allclose(n[sem == "GroundSurface"], [[0, 0, -1]], atol=1e-9)
    centre = store.to_local(np.array([[105.0, 204.0, 33.0]]))[0]
    for f in np.flatnonzero(sem == "WallSurface"):
        assert abs(n[f, 2]) < 1e-12
        assert n[f] @ (store.centroids[f] - centre) > 0  # outward


def test_reference_to_a_later_building(tmp_path):
    """B1's solid references a polygon defined in B2 (forward, across city objects)."""
    b1, _ = building_xml("B1", 0, 0, extra_solid_refs=["#B2_WallSurface_3"])
    b2, _ = building_xml("B2", 10, 0, solid=None)
    raw = read_citygml(write(tmp_path, city_xml([b1, b2])))
    shared = [p for p in raw.polygons if p.gml_id == "B2_WallSurface_3"]
    assert len(shared) == 1 and shared[0].building_id == "B2" and shared[0].from_solid
    assert len(raw.polygons) == 12


def test_bare_href_and_reference_to_an_earlier_building(tmp_path):
    b1, _ = building_xml("B1", 10, 0, solid=None)
    b2, _ = building_xml("B2", 0, 0, extra_solid_refs=["B1_WallSurface_3"])  # bare id form
    raw = read_citygml(write(tmp_path, city_xml([b1, b2])))
    assert len(raw.polygons) == 12
    assert [p.from_solid for p in raw.polygons if p.gml_id == "B1_WallSurface_3"] == [True]


def test_unresolved_xlink_names_the_id(tmp_path):
    b1, _ = building_xml("B1", extra_solid_refs=["#does_not_exist"])
    path = write(tmp_path, city_xml([b1]))
    with pytest.raises(CityGMLError) as info:
        read_citygml(path)
    assert "does_not_exist" in str(info.value) and info.value.path == path


def test_bbox_filter_and_reference_into_a_dropped_building(tmp_path):
    """B1 is far away and dropped; B2 (kept) references one of B1's walls: the wall is found by a
    second pass and attributed to B2."""
    b1, _ = building_xml("B1", 1000, 1000, solid=None)
    b2, _ = building_xml("B2", 0, 0, extra_solid_refs=["#B1_WallSurface_0"])
    b3, _ = building_xml("B3", 50, 0)
    path = write(tmp_path, city_xml([b1, b2, b3]))
    raw = read_citygml(path, bbox_crs=np.array([[-5.0, -5.0], [5.0, 5.0]]))
    assert raw.building_ids == ["B2"]
    moved = [p for p in raw.polygons if p.gml_id == "B1_WallSurface_0"]
    assert len(moved) == 1 and moved[0].building_id == "B2" and moved[0].from_solid
    assert moved[0].exterior[:, 0].min() == pytest.approx(1000.0)
    assert len(raw.polygons) == 7
    # z limits count too when given
    with pytest.raises(NoOverlapError) as info:
        read_citygml(path, bbox_crs=np.array([[-5.0, -5.0, 100.0], [5.0, 5.0, 200.0]]))
    assert info.value.path == path


def test_ring_references(tmp_path):
    """A polygon whose exterior is a reference to a ring: in the same city object and in another."""
    ring = box_faces(0, 0)["RoofSurface"][0]
    ring2 = ring + [20.0, 0, 0]
    b1 = (
        '<bldg:Building gml:id="B1"><bldg:lod2MultiSurface><gml:MultiSurface srsName="EPSG:25832">'
        f'<gml:surfaceMember><gml:Polygon gml:id="P1"><gml:exterior><gml:LinearRing gml:id="R1">'
        f"<gml:posList>{pos_list(ring)}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>"
        '<gml:surfaceMember><gml:Polygon gml:id="P2"><gml:exterior xlink:href="#R1"/></gml:Polygon></gml:surfaceMember>'
        '<gml:surfaceMember><gml:Polygon gml:id="P3"><gml:exterior xlink:href="#R2"/></gml:Polygon></gml:surfaceMember>'
        "</gml:MultiSurface></bldg:lod2MultiSurface></bldg:Building>"
    )
    b2 = (
        '<bldg:Building gml:id="B2"><bldg:lod2MultiSurface><gml:MultiSurface>'
        f'<gml:surfaceMember><gml:Polygon gml:id="P4"><gml:exterior><gml:LinearRing gml:id="R2">'
        f"<gml:posList>{pos_list(ring2)}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>"
        "</gml:MultiSurface></bldg:lod2MultiSurface></bldg:Building>"
    )
    raw = read_citygml(write(tmp_path, city_xml([b1, b2])))
    by_id = {p.gml_id: p for p in raw.polygons}
    assert set(by_id) == {"P1", "P2", "P3", "P4"}
    np.testing.assert_array_equal(by_id["P2"].exterior, ring)
    np.testing.assert_array_equal(by_id["P3"].exterior, ring2)
    assert by_id["P3"].building_id == "B1"
    bad = b1.replace("#R2", "#R9")
    with pytest.raises(CityGMLError, match="R9"):
        read_citygml(write(tmp_path, city_xml([bad, b2]), "bad.gml"))


def test_geometry_variants(tmp_path):
    """gml:Surface/PolygonPatch, gml:pos sequences, gml:coordinates, inherited srsDimension,
    OrientableSurface orientation="-", interior rings, comments inside geometry."""
    f = box_faces(0, 0)
    roof, ground = f["RoofSurface"][0], f["GroundSurface"][0]
    walls = f["WallSurface"]
    pos_seq = "".join(f"<gml:pos>{x:.3f} {y:.3f} {z:.3f}</gml:pos>" for x, y, z in np.vstack([walls[0], walls[0][:1]]))
    coords = " ".join(f"{x:.3f},{y:.3f},{z:.3f}" for x, y, z in np.vstack([walls[1], walls[1][:1]]))
    flat = " ".join(f"{x:.3f} {y:.3f}" for x, y, _ in np.vstack([roof, roof[:1]]))
    hole = np.array([[4, 3, 36], [6, 3, 36], [6, 5, 36], [4, 5, 36]], float)[::-1]
    xml = (
        '<bldg:Building gml:id="B1">'
        '<bldg:boundedBy><bldg:RoofSurface><bldg:lod2MultiSurface><gml:MultiSurface srsName="EPSG:25832" srsDimension="3">'
        "<!-- a comment -->"
        f'<gml:surfaceMember><gml:Surface gml:id="S1"><gml:patches><gml:PolygonPatch><gml:exterior><gml:LinearRing>'
        f"<gml:posList>{pos_list(roof)}</gml:posList></gml:LinearRing></gml:exterior>"
        f"<gml:interior><gml:LinearRing><gml:posList>{pos_list(hole)}</gml:posList></gml:LinearRing></gml:interior>"
        "</gml:PolygonPatch></gml:patches></gml:Surface></gml:surfaceMember>"
        "</gml:MultiSurface></bldg:lod2MultiSurface></bldg:RoofSurface></bldg:boundedBy>"
        '<bldg:boundedBy><bldg:WallSurface><bldg:lod2MultiSurface><gml:MultiSurface>'
        f'<gml:surfaceMember><gml:Polygon gml:id="W0"><gml:exterior><gml:LinearRing>{pos_seq}</gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>'
        f'<gml:surfaceMember><gml:Polygon gml:id="W1"><gml:exterior><gml:LinearRing><gml:coordinates>{coords}</gml:coordinates></gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>'
        "</gml:MultiSurface></bldg:lod2MultiSurface></bldg:WallSurface></bldg:boundedBy>"
        '<bldg:boundedBy><bldg:GroundSurface><bldg:lod2MultiSurface><gml:MultiSurface>'
        f'<gml:surfaceMember><gml:OrientableSurface orientation="-"><gml:baseSurface>{polygon_xml("G0", ground[::-1])}'
        "</gml:baseSurface></gml:OrientableSurface></gml:surfaceMember>"
        "</gml:MultiSurface></bldg:lod2MultiSurface></bldg:GroundSurface></bldg:boundedBy>"
        '<bldg:lod2MultiSurface><gml:MultiSurface srsDimension="2">'
        f'<gml:surfaceMember><gml:Polygon gml:id="F0"><gml:exterior><gml:LinearRing><gml:posList>{flat}</gml:posList>'
        "</gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod2MultiSurface>"
        "</bldg:Building>"
    )
    raw = read_citygml(write(tmp_path, city_xml([xml])))
    by_id = {p.gml_id: p for p in raw.polygons}
    assert set(by_id) == {"S1", "W0", "W1", "G0", "F0"}
    np.testing.assert_array_equal(by_id["S1"].exterior, roof)
    np.testing.assert_array_equal(by_id["S1"].holes[0], hole)
    assert by_id["S1"].semantic == "RoofSurface"
    np.testing.assert_array_equal(by_id["W0"].exterior, walls[0])
    np.testing.assert_array_equal(by_id["W1"].exterior, walls[1])
    # the reversed base surface is given back in outward order
    np.testing.assert_array_equal(by_id["G0"].exterior, ground)
    assert by_id["G0"].semantic == "GroundSurface"
    # srsDimension=2 inherited from the MultiSurface: z = 0 and a warning
    np.testing.assert_array_equal(by_id["F0"].exterior, np.column_stack([roof[:, :2], np.zeros(4)]))
    assert by_id["F0"].semantic == "Unknown"
    assert any("2D coordinates" in w for w in raw.warnings)


def test_crs_from_geometry_only_and_mixed(tmp_path):
    b1, _ = building_xml("B1", srs="urn:ogc:def:crs:EPSG::25832")
    b2, _ = building_xml("B2", 20, srs="EPSG:25832")  # same CRS, another spelling
    raw = read_citygml(write(tmp_path, city_xml([b1, b2])))
    assert raw.crs.horizontal_epsg == 25832
    b3, _ = building_xml("B3", 40, srs="EPSG:25833")
    path = write(tmp_path, city_xml([b1, b3]), "mixed.gml")
    with pytest.raises(CRSError, match="mixed CRSs") as info:
        read_citygml(path)
    assert info.value.path == path
    # the file's CRS wins over a different given one, with a warning
    raw = read_citygml(write(tmp_path, city_xml([b1]), "one.gml"), crs="EPSG:25833")
    assert raw.crs.horizontal_epsg == 25832 and any("ignored" in w for w in raw.warnings)
    # no CRS anywhere
    b4, _ = building_xml("B4", srs=None)
    with pytest.raises(CRSError, match="no CRS in the file"):
        read_citygml(write(tmp_path, city_xml([b4.replace(' srsName="None"', "")]), "none.gml"))


def test_lod_selection(tmp_path):
    f = box_faces(0, 0)
    lod1 = "".join(
        f"<gml:surfaceMember>{polygon_xml(f'L1_{k}', r)}</gml:surfaceMember>"
        for k, r in enumerate([x for rings in f.values() for x in rings])
    )
    b, _ = building_xml("B1")
    b = b.replace(
        "</bldg:Building>",
        f"<bldg:lod1Solid><gml:Solid><gml:exterior><gml:CompositeSurface>{lod1}</gml:CompositeSurface>"
        "</gml:exterior></gml:Solid></bldg:lod1Solid></bldg:Building>",
    )
    only_lod2, _ = building_xml("B2", 20.0)
    path = write(tmp_path, city_xml([b, only_lod2], srs="EPSG:25832"))
    raw1 = read_citygml(path, lod=1)
    assert len(raw1.polygons) == 6 and all(p.gml_id.startswith("L1_") and p.lod == 1 for p in raw1.polygons)
    assert raw1.building_ids == ["B1"]
    assert "1 buildings without LOD 1 geometry skipped" in raw1.warnings
    assert all(p.from_solid and p.semantic == "Unknown" for p in raw1.polygons)
    raw2 = read_citygml(path, lod=2)
    assert raw2.building_ids == ["B1", "B2"]
    assert len(raw2.polygons) == 12 and not any(p.gml_id.startswith("L1_") for p in raw2.polygons)
    with pytest.raises(CityGMLError, match=r"no building geometry at LOD 3 \(it has LOD 1, 2"):
        read_citygml(path, lod=3)


def test_many_members_stream(tmp_path):
    """Members are cleared as they are read: the result does not depend on it, and a file of
    hundreds of buildings reads in order with unique ids."""
    members = [building_xml(f"B{k}", 20.0 * k, 0.0)[0] for k in range(300)]
    raw = read_citygml(write(tmp_path, city_xml(members, srs="EPSG:25832")))
    assert raw.building_ids == [f"B{k}" for k in range(300)]
    assert len(raw.polygons) == 1800
