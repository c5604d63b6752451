"""Write building polygons as a CityGML 2.0 file (the simulator's given models, test fixtures).

One `bldg:Building` per building id (with `bldg:BuildingPart`s when polygons name a part), one
thematic surface (`WallSurface`, `RoofSurface`, `GroundSurface`, `ClosureSurface`,
`OuterCeilingSurface`, `OuterFloorSurface`) per polygon with a `lod{N}MultiSurface` holding one
`gml:Polygon` (exterior and interior rings as `gml:posList`, rings closed, coordinates written with
full float64 precision). Polygons with another semantic go into the building's own
`lod{N}MultiSurface`. Every feature, surface and polygon gets a `gml:id`. `srsName` is set on the
envelope and on every geometry, so readers that look at either find it.

The output round-trips through `read_city_model` (tests/test_citymodel_write_citygml.py).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Iterable

import numpy as np
from lxml import etree

from .raw_model import RawCityModel, RawPolygon
from .store import THEMATIC_CLASSES

NS = {
    "core": "http://www.opengis.net/citygml/2.0",
    "bldg": "http://www.opengis.net/citygml/building/2.0",
    "gml": "http://www.opengis.net/gml",
    "xlink": "http://www.w3.org/1999/xlink",
    "xsi": "http://www.w3.org/2001/XMLSchema-instance",
}
SCHEMA_LOCATION = (
    "http://www.opengis.net/citygml/building/2.0 "
    "http://schemas.opengis.net/citygml/building/2.0/building.xsd"
)
# The thematic surface classes the store knows are the ones written as such.
THEMATIC = THEMATIC_CLASSES


def _q(prefix: str, name: str) -> str:
    return f"{{{NS[prefix]}}}{name}"


def _fmt(values: Iterable[float]) -> str:
    # repr() is the shortest text that reads back to the same float64
    return " ".join(repr(float(v)) for v in values)


def _ring_text(ring: np.ndarray) -> str:
    ring = np.asarray(ring, dtype=np.float64).reshape(-1, 3)
    closed = np.vstack([ring, ring[:1]])
    return _fmt(closed.ravel())


def _safe_id(text: str) -> str:
    """An xs:ID (NCName): letters, digits, '_', '-', '.'; must not start with a digit."""
    out = "".join(c if (c.isalnum() or c in "_-.") else "_" for c in text)
    if not out or not (out[0].isalpha() or out[0] == "_"):
        out = "_" + out
    return out


class _Ids:
    """Unique gml:ids: keep given ids when valid and unused, else make one up."""

    def __init__(self):
        self.used: set[str] = set()
        self.counter = 0

    def take(self, wanted: str, prefix: str) -> str:
        candidate = _safe_id(wanted) if wanted else ""
        if not candidate or candidate in self.used:
            while True:
                self.counter += 1
                candidate = f"{prefix}_{self.counter}"
                if candidate not in self.used:
                    break
        self.used.add(candidate)
        return candidate


def _polygon_element(poly: RawPolygon, srs_name: str, ids: _Ids) -> etree._Element:
    el = etree.Element(_q("gml", "Polygon"))
    el.set(_q("gml", "id"), ids.take(poly.gml_id, "poly"))
    el.set("srsName", srs_name)
    el.set("srsDimension", "3")
    rings = [("exterior", poly.exterior)] + [("interior", h) for h in poly.holes]
    for tag, ring in rings:
        wrapper = etree.SubElement(el, _q("gml", tag))
        lin = etree.SubElement(wrapper, _q("gml", "LinearRing"))
        pos = etree.SubElement(lin, _q("gml", "posList"))
        pos.set("srsDimension", "3")
        pos.text = _ring_text(ring)
    return el


def _multi_surface(parent, lod: int, polys: list[RawPolygon], srs_name: str, ids: _Ids):
    prop = etree.SubElement(parent, _q("bldg", f"lod{lod}MultiSurface"))
    ms = etree.SubElement(prop, _q("gml", "MultiSurface"))
    ms.set("srsName", srs_name)
    ms.set("srsDimension", "3")
    for poly in polys:
        member = etree.SubElement(ms, _q("gml", "surfaceMember"))
        member.append(_polygon_element(poly, srs_name, ids))


def _fill_building(el, polys: list[RawPolygon], lod: int, srs_name: str, ids: _Ids) -> None:
    """Thematic surfaces under boundedBy; other semantics in the building's own multisurface."""
    others = [p for p in polys if p.semantic not in THEMATIC]
    # CityGML 2.0 schema order: lodXMultiSurface comes before boundedBy
    if others:
        _multi_surface(el, lod, others, srs_name, ids)
    for poly in polys:
        if poly.semantic not in THEMATIC:
            continue
        bounded = etree.SubElement(el, _q("bldg", "boundedBy"))
        surface = etree.SubElement(bounded, _q("bldg", poly.semantic))
        base = poly.gml_id or poly.semantic
        surface.set(_q("gml", "id"), ids.take(f"{base}_surface", "surface"))
        _multi_surface(surface, lod, [poly], srs_name, ids)


def citygml_tree(
    polygons: list[RawPolygon], srs_name: str, *, lod: int = 2, name: str = ""
) -> etree._ElementTree:
    """The XML tree of a CityGML 2.0 CityModel with the given polygons (CRS coordinates)."""
    if lod not in (1, 2, 3, 4):
        raise ValueError(f"lod must be 1..4, got {lod}")
    root = etree.Element(_q("core", "CityModel"), nsmap=NS)
    root.set(_q("xsi", "schemaLocation"), SCHEMA_LOCATION)
    if name:
        etree.SubElement(root, _q("gml", "name")).text = name
    if polygons:
        pts = np.concatenate(
            [np.asarray(p.exterior, dtype=np.float64).reshape(-1, 3) for p in polygons]
        )
        bounded = etree.SubElement(root, _q("gml", "boundedBy"))
        env = etree.SubElement(bounded, _q("gml", "Envelope"))
        env.set("srsName", srs_name)
        env.set("srsDimension", "3")
        etree.SubElement(env, _q("gml", "lowerCorner")).text = _fmt(pts.min(0))
        etree.SubElement(env, _q("gml", "upperCorner")).text = _fmt(pts.max(0))
    ids = _Ids()
    # group by building, then by part, keeping first-seen order (deterministic output)
    buildings: dict[str, dict[str, list[RawPolygon]]] = {}
    for poly in polygons:
        buildings.setdefault(poly.building_id or "building", {}).setdefault(
            poly.part_id or "", []
        ).append(poly)
    for building_id, parts in buildings.items():
        member = etree.SubElement(root, _q("core", "cityObjectMember"))
        building = etree.SubElement(member, _q("bldg", "Building"))
        building.set(_q("gml", "id"), ids.take(building_id, "building"))
        if "" in parts:
            _fill_building(building, parts[""], lod, srs_name, ids)
        for part_id, polys in parts.items():
            if part_id == "":
                continue
            prop = etree.SubElement(building, _q("bldg", "consistsOfBuildingPart"))
            part = etree.SubElement(prop, _q("bldg", "BuildingPart"))
            part.set(_q("gml", "id"), ids.take(part_id, "part"))
            _fill_building(part, polys, lod, srs_name, ids)
    return etree.ElementTree(root)


def write_citygml(
    path: str | Path,
    model: RawCityModel | list[RawPolygon],
    srs_name: str | None = None,
    *,
    lod: int = 2,
    name: str = "",
) -> Path:
    """Write polygons (CRS coordinates, as a RawCityModel or a list) to a CityGML 2.0 file.

    srs_name: defaults to the model's `crs.srs_name` as read from its source (else "EPSG:<h>+<v>"
    or "EPSG:<h>" from its codes); written
    atomically (temporary file beside the target, then renamed). Returns the path.
    """
    path = Path(path)
    if isinstance(model, RawCityModel):
        polygons = model.polygons
        if srs_name is None:
            crs = model.crs
            if crs.srs_name and crs.srs_name != "local":
                srs_name = crs.srs_name
            elif crs.horizontal_epsg and crs.vertical_epsg:
                srs_name = f"EPSG:{crs.horizontal_epsg}+{crs.vertical_epsg}"
            elif crs.horizontal_epsg:
                srs_name = f"EPSG:{crs.horizontal_epsg}"
    else:
        polygons = list(model)
    if not srs_name:
        raise ValueError("write_citygml needs an srsName (the model has no CRS)")
    tree = citygml_tree(polygons, srs_name, lod=lod, name=name)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        tree.write(tmp, xml_declaration=True, encoding="UTF-8", pretty_print=True)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def raw_from_store(store) -> RawCityModel:
    """A PlaneStore's faces as CRS-coordinate polygons (for write_citygml)."""
    polygons = [
        RawPolygon(
            exterior=store.to_crs(store.vertices[f.exterior]),
            holes=[store.to_crs(store.vertices[h]) for h in f.holes],
            semantic=f.semantic,
            building_id=f.building_id,
            part_id=f.part_id,
            gml_id=f.gml_id,
            lod=f.lod,
        )
        for f in store.faces
    ]
    return RawCityModel(
        source=store.source,
        format="CityGML",
        version="2.0",
        crs=store.crs,
        polygons=polygons,
        building_ids=sorted({p.building_id for p in polygons}),
        part_ids=sorted({p.part_id for p in polygons if p.part_id}),
    )
