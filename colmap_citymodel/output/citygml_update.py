"""Write corrected vertex coordinates back into the CityGML file the model was read from.

The file is parsed whole with lxml and written back in its own CityGML version (1.0, 2.0 or
3.0); only the text of coordinate elements (`gml:posList`, `gml:pos`, `gml:coordinates`) that
hold a moved vertex changes, and within it only the numbers of that vertex: every gml:id, xlink,
attribute, appearance, comment and untouched building is kept as it is (lxml writes the same
XML content; quoting of the XML declaration may differ).

Which coordinates: those the reader read (citymodel.read_citygml: buildings and their parts at
the chosen LOD, thematic surfaces' lodNMultiSurface, the building's lodNSolid/lodNMultiSurface,
exterior shells of solids, polygon rings with their holes) of the buildings in the store. Each
is found by its value in the store's provenance (`PlaneStore.provenance`: every distinct
coordinate read, and the vertex it was merged into), so all raw coordinates merged into one
vertex (up to the merge tolerance apart) move by that vertex's shift and the file stays as
consistent as it was. Coordinates are written in the file's CRS and axis order (a model read
with --target_crs is projected back) with the file's number of decimals (the most any
coordinate of the read geometry has, but at least millimetres; full float precision files get
the shortest text that reads back to the same float64). Envelopes (gml:boundedBy) are left as
they are.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from lxml import etree

from ..citymodel import crs as crs_mod
from ..citymodel.archives import open_model, read_model_head
from ..citymodel.raw_model import CRSInfo
from ..citymodel.read_citygml import (
    MEMBER_TAGS,
    PART_PROPERTIES,
    THEMATIC_PROPERTIES,
    _gml_id,
    _local,
)
from ..citymodel.store import PlaneStore

logger = logging.getLogger(__name__)

#: A file whose coordinates have at least this many decimals is written at full precision.
FULL_PRECISION_DECIMALS = 10
#: At least this many decimals are written (millimetres; 1e-8 deg is about 1 mm), so that a
#: correction survives in a file that writes whole metres or decimetres.
MIN_DECIMALS_METRES = 3
MIN_DECIMALS_DEGREES = 8
COORDINATE_ELEMENTS = ("posList", "pos", "coordinates")


@dataclass
class UpdateReport:
    """What a write-back changed in one file."""

    source: str
    target: str
    num_coordinates: int = 0  # coordinates of the read geometry looked at
    num_moved: int = 0  # coordinates written with a shift
    num_elements: int = 0  # coordinate elements whose text changed
    vertices_written: set = field(default_factory=set)  # store vertices found in the file
    num_not_in_store: int = 0  # read-geometry coordinates the store does not know (cropped)
    num_2d: int = 0  # 2D coordinates (the store has them at z = 0): not moved
    decimals: int | None = None  # None: full precision

    def todict(self) -> dict:
        return {"source": self.source, "target": self.target,
                "num_coordinates": self.num_coordinates, "num_moved": self.num_moved,
                "num_elements_changed": self.num_elements,
                "num_vertices_written": len(self.vertices_written),
                "num_not_in_store": self.num_not_in_store, "num_2d": self.num_2d,
                "decimals": self.decimals}


@dataclass
class Moves:
    """Shifts of store vertices (local frame = model CRS axes), and the store they refer to."""

    store: PlaneStore
    vertex_ids: np.ndarray  # (K,)
    shifts: np.ndarray  # (K, 3)

    def __post_init__(self) -> None:
        self.table = np.zeros((len(self.store.vertices), 3))
        self.moved = np.zeros(len(self.store.vertices), dtype=bool)
        self.table[self.vertex_ids] = self.shifts
        self.moved[self.vertex_ids] = np.any(self.shifts != 0, axis=1)

    @property
    def buildings(self) -> set[str]:
        return self.store.faces.building_id.unique()


# -- the geometry the reader reads ----------------------------------------------------------------

def _read_geometry(building, lod: int):
    """The geometry property elements of a Building (and its parts) that read_citygml reads."""
    prefix = f"lod{lod}"
    for child in building:
        name = _local(child.tag)
        if not name:
            continue
        if name in PART_PROPERTIES:
            for part in child:
                if _local(part.tag) == "BuildingPart":
                    yield from _read_geometry(part, lod)
        elif name in THEMATIC_PROPERTIES:
            if child.tag.startswith("{http://www.opengis.net/gml"):
                continue  # gml:boundedBy: an envelope
            for surface in child:
                for prop in surface:
                    pname = _local(prop.tag)
                    if (pname.startswith(prefix) and pname.endswith("MultiSurface")
                            and len(pname) > 4 and pname[3].isdigit()):
                        yield prop
        elif (name.startswith(prefix) and len(name) > 4 and name[3].isdigit()
              and name[4:] in ("Solid", "MultiSurface")):
            yield child


def _coordinate_elements(prop):
    """posList / pos / coordinates under a geometry property, without the interior shells of
    solids (the reader reads exterior shells only)."""
    stack = [prop]
    while stack:
        el = stack.pop()
        name = _local(el.tag)
        if name in COORDINATE_ELEMENTS:
            yield el
            continue
        solid = name == "Solid"
        for child in reversed(el):
            if not isinstance(child.tag, str):
                continue
            if solid and _local(child.tag) == "interior":
                continue
            stack.append(child)


def _buildings(root):
    """(building id as read_citygml names it, element) of every top-level Building."""
    count = 0
    for member in root:
        if _local(member.tag) not in MEMBER_TAGS:
            continue
        for feature in member:
            if _local(feature.tag) == "Building":
                count += 1
                yield _gml_id(feature) or f"building_{count}", feature


def _dimension(el) -> int:
    for node in (el, *el.iterancestors()):
        d = node.get("srsDimension")
        if d:
            return int(d)
    return 3


# -- numbers --------------------------------------------------------------------------------------

class _CoordinateText:
    """The numbers of a coordinate element with the text between them, so that single numbers
    can be replaced and everything else stays as written."""

    def __init__(self, el):
        self.el = el
        text = el.text or ""
        self.decimal = "."
        if _local(el.tag) == "coordinates":
            cs, ts = el.get("cs", ","), el.get("ts", " ")
            self.decimal = el.get("decimal", ".")
            separators = re.escape(cs + ts) + r"\s"
            pattern = f"[^{separators}]+"
        else:
            pattern = r"\S+"
        self.spans = [m.span() for m in re.finditer(pattern, text)]
        self.text = text
        self.values = np.array([float(text[a:b].replace(self.decimal, "."))
                                for a, b in self.spans], dtype=np.float64)
        self.dimension = _dimension(el)
        if _local(el.tag) == "coordinates":
            first = re.split(f"[{re.escape(el.get('ts', ' '))}\\s]+", text.strip())[0]
            self.dimension = len([t for t in first.split(el.get("cs", ",")) if t])

    def decimals(self) -> int:
        """The most decimals of any number here (FULL_PRECISION_DECIMALS for exponents)."""
        most = 0
        for a, b in self.spans:
            token = self.text[a:b]
            if "e" in token or "E" in token:
                return FULL_PRECISION_DECIMALS
            _, _, fraction = token.replace(self.decimal, ".").partition(".")
            most = max(most, len(fraction))
        return most

    def replace(self, index: np.ndarray, values: np.ndarray, decimals: int | None) -> None:
        """Numbers `index` become `values` (formatted with `decimals`, None: shortest exact)."""
        new = dict(zip(index.tolist(), values.tolist()))
        pieces, last = [], 0
        for k, (a, b) in enumerate(self.spans):
            pieces.append(self.text[last:a])
            if k in new:
                number = repr(float(new[k])) if decimals is None else f"{new[k]:.{decimals}f}"
                pieces.append(number.replace(".", self.decimal))
            else:
                pieces.append(self.text[a:b])
            last = b
        pieces.append(self.text[last:])
        self.el.text = "".join(pieces)


# -- the write-back -------------------------------------------------------------------------------

def file_crs(path: Path, assumed: CRSInfo | None, store_crs: CRSInfo) -> CRSInfo:
    """The CRS the file's coordinates are in: its first srsName, else the assumed one, else
    the store's."""
    head = read_model_head(path, 1 << 22).decode("utf-8", errors="ignore")
    found = re.search(r'srsName="([^"]+)"', head)
    if found:
        return crs_mod.resolve_crs(found.group(1), path=path)
    return assumed if assumed is not None else store_crs


def update_citygml(source: str | Path, target: str | Path, moves: Moves, *, lod: int = 2,
                   assumed_crs: CRSInfo | None = None) -> UpdateReport:
    """Write `source` to `target` with the vertices of `moves` shifted (see module doc)."""
    source, target = Path(source), Path(target)
    store = moves.store
    if store.provenance is None:
        raise ValueError("the store has no provenance: read it with read_city_model")
    parser = etree.XMLParser(huge_tree=True, remove_blank_text=False, strip_cdata=False,
                             resolve_entities=False)
    with open_model(source) as stream:
        tree = etree.parse(stream, parser)
    src_crs = file_crs(source, assumed_crs, store.crs)
    reproject = not crs_mod.same_crs(src_crs, store.crs)
    report = UpdateReport(str(source), str(target))
    buildings = moves.buildings
    elements = []
    for building_id, building in _buildings(tree.getroot()):
        if building_id not in buildings:
            continue
        for prop in _read_geometry(building, lod):
            elements.extend(_CoordinateText(el) for el in _coordinate_elements(prop))
    most = max((t.decimals() for t in elements), default=0)
    decimals = None if most >= FULL_PRECISION_DECIMALS else max(
        most, MIN_DECIMALS_METRES if src_crs.is_projected else MIN_DECIMALS_DEGREES)
    report.decimals = decimals
    for tokens in elements:
        dim = tokens.dimension
        if len(tokens.values) == 0:
            continue
        if dim != 3 or len(tokens.values) % 3:
            report.num_2d += len(tokens.values) // max(dim, 1)
            continue
        points = tokens.values.reshape(-1, 3)
        report.num_coordinates += len(points)
        in_crs = crs_mod.reproject_points(points, src_crs, store.crs) if reproject else points
        vertex = store.provenance.vertex_of(in_crs - store.origin)
        report.num_not_in_store += int(np.count_nonzero(vertex < 0))
        report.vertices_written.update(vertex[vertex >= 0].tolist())
        hit = vertex >= 0
        hit[hit] = moves.moved[vertex[hit]]
        if not hit.any():
            continue
        rows = np.flatnonzero(hit)
        shift = moves.table[vertex[rows]]
        if reproject:
            swap = crs_mod.lat_first(points, src_crs)
            new = crs_mod.reproject_points(in_crs[rows] + shift, store.crs, src_crs)
            if swap:
                new[:, [0, 1]] = new[:, [1, 0]]
        else:
            new = points[rows] + shift
        index = (3 * rows[:, None] + np.arange(3)).ravel()
        tokens.replace(index, new.ravel(), decimals)
        report.num_moved += len(rows)
        report.num_elements += 1
    target.parent.mkdir(parents=True, exist_ok=True)
    docinfo = tree.docinfo
    tree.write(str(target), encoding=docinfo.encoding or "UTF-8", xml_declaration=True,
               standalone=docinfo.standalone)
    logger.info("%s: %d coordinates of %d vertices moved in %d elements", target.name,
                report.num_moved, int(np.count_nonzero(moves.moved)), report.num_elements)
    return report
