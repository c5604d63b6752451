"""Read building geometry from CityGML 1.0, 2.0 and 3.0 (GML 3.1.1 and 3.2) into a RawCityModel.

Streaming: `lxml.etree.iterparse` delivers one top-level `cityObjectMember` / `featureMember` /
`member` at a time; it is turned into polygons, appended to a flat RawPolygonTable (one coordinate
array, no object per polygon), then cleared and its previous siblings deleted, so memory holds one
city object plus the table of the polygons kept so far (the output), however large the file.

What is read (namespace-agnostic, by local element name, so 1.0/2.0/3.0 and producers' prefix
quirks all pass): `Building` and (nested) `BuildingPart` (`consistsOfBuildingPart`, 3.0
`buildingPart`); thematic surfaces (`WallSurface`, `RoofSurface`, `GroundSurface`,
`ClosureSurface`, `OuterCeilingSurface`, `OuterFloorSurface`, ...) under `boundedBy` (3.0
`boundary`) with their `lodNMultiSurface`; the building's own `lodNSolid` / `lodNMultiSurface`;
GML `Solid` (exterior shell), `CompositeSurface`, `Shell`, `MultiSurface`, `OrientableSurface`
(orientation "-" reverses), `Polygon`, `Surface`/`PolygonPatch`, `Triangle`/`Rectangle`; exterior
and interior rings of `posList`, `pos` sequences or `coordinates`; `srsDimension` inherited from
ancestors (default 3). Openings (windows, doors), installations and rooms are skipped.

xlinks: `xlink:href` on a surface member (`#id` or bare `id`) names a polygon defined elsewhere;
a polygon referenced from a solid and defined in a thematic surface (or the other way round)
becomes ONE polygon with the thematic semantics and `from_solid=True`. References are resolved
per city object first; the few that point to other city objects are kept in a small pending list
(target id + context, a few hundred bytes each) and resolved at the end against the kept polygons'
ids; anything still open (the target lies in a building dropped by the bbox filter, or a ring
reference across city objects) triggers one more streaming pass over the file that looks only for
those ids. An id found nowhere is a CityGMLError naming it.

CRS: `srsName` on the model envelope, building envelopes or any geometry element read; all must
agree (else CRSError). No CRS at all: CRSError unless `crs` is given (the file's own CRS wins over
a given one, which then only adds a warning, as in read_cityjson). Geographic CRS (e.g. PLATEAU EPSG:6697): CRSError unless
`target_crs` names a projected CRS; then coordinates are reprojected city object by city object
(see crs.py for axis order). The first city object with geometry must carry or follow a CRS: the
reader fails then rather than buffering a whole file it cannot place.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from lxml import etree

from ..errors import CityGMLError, CRSError, InputError, NoOverlapError
from . import crs as crs_mod
from .archives import open_model
from .raw_model import (
    CRSInfo,
    RawCityModel,
    RawPolygon,
    RawPolygonBuilder,
    RawPolygonTable,
    coordinate_problem,
)

logger = logging.getLogger(__name__)

XLINK_HREF = "{http://www.w3.org/1999/xlink}href"
GML_NAMESPACES = ("http://www.opengis.net/gml", "http://www.opengis.net/gml/3.2")
GML_IDS = tuple(f"{{{ns}}}id" for ns in GML_NAMESPACES)
_VERSION_RE = re.compile(r"opengis\.net/citygml/(?:[A-Za-z]+/)?(\d\.\d)")

MEMBER_TAGS = ("cityObjectMember", "featureMember", "member", "featureMembers")
# top-level siblings we also listen for, only to clear them early (global appearances can be large)
_CLEAR_TAGS = ("appearanceMember",)
PART_PROPERTIES = ("consistsOfBuildingPart", "buildingPart")
THEMATIC_PROPERTIES = ("boundedBy", "boundary")
# GML aggregates whose members are surfaces
_SURFACE_AGGREGATES = ("MultiSurface", "CompositeSurface", "Shell")
_PATCHED_SURFACES = ("Surface", "PolyhedralSurface", "TriangulatedSurface", "Tin")
_PATCHES = ("PolygonPatch", "Triangle", "Rectangle")
_PLANAR = ("Polygon",) + _PATCHES

_local_cache: dict[str, str] = {}


def _local(tag) -> str:
    """Local name of an element tag ('' for comments and processing instructions)."""
    if not isinstance(tag, str):
        return ""
    name = _local_cache.get(tag)
    if name is None:
        name = tag.rpartition("}")[2]
        _local_cache[tag] = name
    return name


def _gml_id(el) -> str:
    return el.get(GML_IDS[0]) or el.get(GML_IDS[1]) or ""


def _href_id(href: str) -> str:
    """'#id', 'id' and 'file.gml#id' all name `id` (other files are not followed)."""
    return href.rpartition("#")[2].strip()


@dataclass
class _Ref:
    """A surface member given by reference."""

    target: str
    semantic: str
    in_solid: bool
    reversed: bool
    building_id: str
    part_id: str


@dataclass
class _RingRef:
    target: str
    reversed: bool = False


_EMPTY = np.zeros((0, 3))


def _inherited_dim(el, walker) -> int:
    """srsDimension of the nearest ancestor that names one (GML default 3)."""
    for anc in el.iterancestors():
        d = anc.get("srsDimension")
        if d:
            return walker._dim(d)
    return 3


class _Pending:
    """A polygon of a kept building with a ring given by a reference not resolvable in its member."""

    def __init__(self, polygon: RawPolygon, rings: list):
        self.polygon = polygon
        self.rings = rings  # exterior first; np.ndarray or _RingRef


class _Walker:
    """Turns one city object (an lxml subtree) into polygons and references."""

    def __init__(self, path: Path, lod: int):
        self.path = path
        self.lod = lod
        self.lod_prefix = f"lod{lod}"
        self.srs_names: set[str] = set()
        self.lods_seen: set[int] = set()
        self.num_2d_rings = 0
        self.reset(None)

    def reset(self, member) -> None:
        self.member = member
        self.polygons: list[RawPolygon] = []
        self.refs: list[_Ref] = []
        self.containers: dict[str, tuple[int, int]] = {}  # aggregate gml:id -> polygon index range
        self.pending: list[_Pending] = []
        self.poly_rings: list[tuple[RawPolygon, list, bool]] = []
        self.tokens: list[str] = []
        self.ring_start: list[int] = []
        self.ring_len: list[int] = []
        self.ring_dim: list[int] = []
        self.ring_gid: list[str] = []
        self.buildings: list[str] = []
        self.parts: list[str] = []
        self._ring_index: dict | None = None
        self.building = ""
        self.part = ""

    # -- features -----------------------------------------------------------------------------
    def feature(self, el, counter: list[int]) -> None:
        name = _local(el.tag)
        if name == "Building":
            counter[0] += 1
            bid = _gml_id(el) or f"building_{counter[0]}"
            self.buildings.append(bid)
            self.building, self.part = bid, ""
            self._building(el)

    def _building(self, el) -> None:
        for child in el:
            name = _local(child.tag)
            if not name:
                continue
            if name in PART_PROPERTIES:
                for part in child:
                    if _local(part.tag) == "BuildingPart":
                        outer = self.part
                        self.part = _gml_id(part) or f"{self.building}_part_{len(self.parts) + 1}"
                        self.parts.append(self.part)
                        self._building(part)
                        self.part = outer
            elif name in THEMATIC_PROPERTIES:
                if child.tag.startswith("{http://www.opengis.net/gml"):
                    self._envelope(child)
                    continue
                for surface in child:
                    semantic = _local(surface.tag)
                    if semantic:
                        self._thematic(surface, semantic)
            elif name.startswith("lod") and len(name) > 4 and name[3].isdigit():
                kind = name[4:]
                if kind in ("Solid", "MultiSurface"):
                    self.lods_seen.add(int(name[3]))
                    if name.startswith(self.lod_prefix):
                        self._property(child, "Unknown", kind == "Solid", False, 3)

    def _thematic(self, surface, semantic: str) -> None:
        for child in surface:
            name = _local(child.tag)
            if name.startswith("lod") and name.endswith("MultiSurface") and name[3].isdigit():
                self.lods_seen.add(int(name[3]))
                if name.startswith(self.lod_prefix):
                    self._property(child, semantic, False, False, 3)
            elif name == "boundedBy":
                self._envelope(child)

    def _envelope(self, bounded_by) -> None:
        for env in bounded_by:
            srs = env.get("srsName") if _local(env.tag) == "Envelope" else None
            if srs:
                self.srs_names.add(srs)

    # -- GML geometry -------------------------------------------------------------------------
    # Coordinates are not parsed ring by ring: the text of every ring of the city object is split
    # into one token list and converted by one numpy call in finalize() (per-ring numpy calls
    # cost more than the conversion itself). Rings are referred to by index until then.
    def _property(self, prop, semantic: str, in_solid: bool, rev: bool, dim: int) -> None:
        """A property element (surfaceMember, baseSurface, lod2Solid, exterior of a Solid, ...):
        either a reference or inline geometry."""
        href = prop.get(XLINK_HREF)
        if href is not None:
            self.refs.append(
                _Ref(_href_id(href), semantic, in_solid, rev, self.building, self.part)
            )
            return
        for child in prop:
            tag = child.tag
            if isinstance(tag, str):
                if _local_cache.get(tag) == "Polygon":  # fast path for the common case
                    self._polygon(child, semantic, in_solid, rev, dim, _gml_id(child))
                else:
                    self._geometry(child, semantic, in_solid, rev, dim)

    def _geometry(self, el, semantic: str, in_solid: bool, rev: bool, dim: int) -> None:
        srs = el.get("srsName")
        if srs:
            self.srs_names.add(srs)
        d = el.get("srsDimension")
        if d:
            dim = self._dim(d)
        name = _local(el.tag)
        if name in _PLANAR:
            self._polygon(el, semantic, in_solid, rev, dim, _gml_id(el))
            return
        start = len(self.polygons)
        if name in _SURFACE_AGGREGATES:
            for member in el:
                mname = _local(member.tag)
                if mname in ("surfaceMember", "surfaceMembers"):
                    self._property(member, semantic, in_solid, rev, dim)
        elif name == "Solid":
            for member in el:
                if _local(member.tag) == "exterior":  # interior shells (cavities) are skipped
                    self._property(member, semantic, True, rev, dim)
        elif name in ("MultiSolid", "CompositeSolid"):
            for member in el:
                if _local(member.tag) in ("solidMember", "solidMembers"):
                    self._property(member, semantic, True, rev, dim)
        elif name == "OrientableSurface":
            flip = el.get("orientation", "+").strip() == "-"
            for member in el:
                if _local(member.tag) == "baseSurface":
                    self._property(member, semantic, in_solid, rev != flip, dim)
        elif name in _PATCHED_SURFACES:
            gid = _gml_id(el)
            for patches in el:
                if _local(patches.tag) in ("patches", "polygonPatches", "trianglePatches"):
                    for k, patch in enumerate(p for p in patches if isinstance(p.tag, str)):
                        pid = gid if (k == 0 or not gid) else f"{gid}_{k}"
                        self._polygon(patch, semantic, in_solid, rev, dim, pid)
        else:
            return  # curves, points, implicit geometry: not building surfaces
        gid = _gml_id(el)
        if gid:
            self.containers.setdefault(gid, (start, len(self.polygons)))

    def _dim(self, text: str) -> int:
        try:
            dim = int(text)
        except ValueError:
            raise CityGMLError(f"bad srsDimension {text!r}", self.path) from None
        if dim not in (2, 3):
            raise CityGMLError(f"unsupported srsDimension {dim} (only 2 and 3)", self.path)
        return dim

    def _polygon(self, el, semantic: str, in_solid: bool, rev: bool, dim: int, gid: str) -> None:
        d = el.get("srsDimension")
        if d:
            dim = self._dim(d)
        srs = el.get("srsName")
        if srs:
            self.srs_names.add(srs)
        rings: list = []
        for child in el:
            tag = child.tag
            name = _local_cache.get(tag) if isinstance(tag, str) else ""
            if name is None:
                name = _local(tag)
            if name == "exterior" or name == "interior":
                ring = self._fast_ring(child, dim, gid)
                if ring is None:
                    ring = self._ring_property(child, dim, gid)
            elif name == "outerBoundaryIs" or name == "innerBoundaryIs":
                ring = self._ring_property(child, dim, gid)
            else:
                continue
            if name == "exterior" or name == "outerBoundaryIs":
                rings.insert(0, ring)
            else:
                rings.append(ring)
        if not rings:
            raise CityGMLError(f"polygon {gid or '(without gml:id)'} has no exterior ring", self.path)
        polygon = RawPolygon(
            exterior=_EMPTY,
            semantic=semantic,
            building_id=self.building,
            part_id=self.part,
            gml_id=gid,
            lod=self.lod,
            from_solid=in_solid and not rev,
        )
        self.polygons.append(polygon)
        self.poly_rings.append((polygon, rings, rev))

    def _fast_ring(self, prop, dim: int, gid: str) -> int | None:
        """The common case inline: <exterior><LinearRing><posList>...; None for anything else."""
        if len(prop) != 1 or prop.get(XLINK_HREF) is not None:
            return None
        ring = prop[0]
        if _local_cache.get(ring.tag) != "LinearRing" or ring.get("srsDimension") or len(ring) != 1:
            return None
        pos_list = ring[0]
        if _local_cache.get(pos_list.tag) != "posList" or pos_list.get("srsDimension") not in (None, "3"):
            return None
        if dim != 3 and pos_list.get("srsDimension") is None:
            return None
        start = len(self.tokens)
        text = pos_list.text
        if text:
            self.tokens.extend(text.split())
        self.ring_start.append(start)
        self.ring_len.append(len(self.tokens) - start)
        self.ring_dim.append(3)
        self.ring_gid.append(gid)
        return len(self.ring_start) - 1

    def _ring_property(self, prop, dim: int, gid: str):
        """Index of the ring of an exterior/interior property, or a _RingRef to resolve later."""
        href = prop.get(XLINK_HREF)
        if href is not None:
            target = _href_id(href)
            ring = self._ring_by_id(target)
            return ring if ring is not None else _RingRef(target)
        for ring in prop:
            if isinstance(ring.tag, str):
                return self._ring(ring, dim, gid)
        raise CityGMLError(f"polygon {gid or '(without gml:id)'} has an empty ring", self.path)

    def _ring_by_id(self, target: str) -> int | None:
        """A ring referenced by id inside the current city object (index built on first need)."""
        if self.member is None:
            return None
        if self._ring_index is None:
            self._ring_index = {}
            for el in self.member.iter("{*}LinearRing", "{*}Ring"):
                rid = _gml_id(el)
                if rid:
                    self._ring_index.setdefault(rid, el)
        el = self._ring_index.get(target)
        if el is None:
            return None
        return self._ring(el, _inherited_dim(el, self), target)

    def _ring(self, ring, dim: int, gid: str) -> int:
        d = ring.get("srsDimension")
        if d:
            dim = self._dim(d)
        name = _local(ring.tag)
        start = len(self.tokens)
        if name == "LinearRing":
            dim = self._collect(ring, dim, gid)
        elif name == "Ring":  # a ring of curve members: concatenate their points
            for member in ring:
                if _local(member.tag) == "curveMember":
                    for el in member.iter("{*}LineString", "{*}LineStringSegment"):
                        dim = self._collect(el, dim, gid)
        else:
            raise CityGMLError(f"polygon {gid or '(without gml:id)'}: unsupported ring {name}", self.path)
        self.ring_start.append(start)
        self.ring_len.append(len(self.tokens) - start)
        self.ring_dim.append(dim)
        self.ring_gid.append(gid)
        return len(self.ring_start) - 1

    def _collect(self, el, dim: int, gid: str) -> int:
        """Append the coordinate tokens of a LinearRing/LineString (posList, pos sequence or
        coordinates) to the token list; returns the dimension."""
        tokens = self.tokens
        for child in el:
            name = _local(child.tag)
            if name in ("posList", "pos"):
                d = child.get("srsDimension")
                if d:
                    dim = self._dim(d)
                text = child.text
                if text:
                    values = text.split()
                    if name == "pos" and len(values) != dim:
                        raise CityGMLError(f"polygon {gid or '(without gml:id)'}: a gml:pos with "
                                           f"{len(values)} values (srsDimension {dim})", self.path)
                    tokens.extend(values)
                if name == "posList":  # one posList holds the whole ring
                    break
            elif name == "coordinates":
                cs = child.get("cs", ",")
                ts = child.get("ts", " ")
                decimal = child.get("decimal", ".")
                where = f"polygon {gid or '(without gml:id)'}: gml:coordinates"
                if not cs or not ts or cs == ts or not decimal:
                    raise CityGMLError(f"{where} with an empty or repeated separator (cs {cs!r}, "
                                       f"ts {ts!r}, decimal {decimal!r})", self.path)
                text = child.text or ""
                if decimal != ".":
                    text = text.replace(decimal, ".")
                tuples = [t.split(cs) for t in (text.split() if ts.isspace() else text.split(ts)) if t.strip()]
                if tuples:
                    dim = len(tuples[0])
                    if dim not in (2, 3) or any(len(t) != dim for t in tuples):
                        raise CityGMLError(f"{where} tuples of {sorted({len(t) for t in tuples})} "
                                           "values (2 or 3 each, all alike)", self.path)
                for t in tuples:
                    tokens.extend(t)
        return dim

    def finalize(self) -> list[np.ndarray]:
        """Convert all ring tokens to arrays (one numpy call) and attach them to the polygons.

        Returns the ring arrays (N,3), closing points removed."""
        arrays = self._ring_arrays()
        for polygon, rings, rev in self.poly_rings:
            out = []
            unresolved = False
            for r in rings:
                if isinstance(r, _RingRef):
                    unresolved = True
                    out.append(_RingRef(r.target, r.reversed != rev))
                else:
                    a = arrays[r]
                    out.append(a[::-1].copy() if rev else a)
            if unresolved:
                self.pending.append(_Pending(polygon, out))
            else:
                polygon.exterior = out[0]
                if len(out) > 1:
                    polygon.holes = out[1:]
        self.poly_rings = []
        return arrays

    def _ring_arrays(self) -> list[np.ndarray]:
        if not self.ring_start:
            return []
        try:
            vals = np.array(self.tokens, dtype=np.float64)
        except ValueError:
            for k, (s, n) in enumerate(zip(self.ring_start, self.ring_len)):
                try:
                    np.array(self.tokens[s:s + n], dtype=np.float64)
                except ValueError:
                    gid = self.ring_gid[k]
                    raise CityGMLError(
                        f"polygon {gid or '(without gml:id)'}: coordinates that are not numbers", self.path
                    ) from None
            raise
        start = np.array(self.ring_start, dtype=np.int64)
        length = np.array(self.ring_len, dtype=np.int64)
        dim = np.array(self.ring_dim, dtype=np.int64)
        bad = np.flatnonzero(length % dim)
        if len(bad):
            k = int(bad[0])
            gid = self.ring_gid[k]
            raise CityGMLError(
                f"polygon {gid or '(without gml:id)'}: {length[k]} coordinate values are not a "
                f"multiple of srsDimension {dim[k]}",
                self.path,
            )
        # rings are closed in GML (last point = first point); the store wants them open
        closed = np.zeros(len(start), dtype=bool)
        check = np.flatnonzero(length >= 2 * dim)
        if len(check):
            first, last, d = start[check], start[check] + length[check] - dim[check], dim[check]
            eq = (vals[first] == vals[last]) & (vals[first + 1] == vals[last + 1])
            three = d == 3
            eq[three] &= vals[first[three] + 2] == vals[last[three] + 2]
            closed[check] = eq
        end = (start + length - closed * dim).tolist()
        arrays = []
        for s, e, d in zip(self.ring_start, end, self.ring_dim):
            if d == 3:
                arrays.append(vals[s:e].reshape(-1, 3))
            else:
                flat = vals[s:e].reshape(-1, 2)
                self.num_2d_rings += 1
                arrays.append(np.column_stack([flat, np.zeros(len(flat))]))
        self._check_coordinates(arrays)
        return arrays

    def _check_coordinates(self, arrays: list[np.ndarray]) -> None:
        """Numbers no CRS can hold (nan, inf, 1e308, ...) fail here, naming the polygon."""
        xyz = np.concatenate(arrays) if len(arrays) > 1 else arrays[0]
        problem = coordinate_problem(xyz)
        if problem is None:
            return
        row, why = problem
        k = int(np.searchsorted(np.cumsum([len(a) for a in arrays]), row, side="right"))
        gid = self.ring_gid[k]
        where = f" of building {self.building}" if self.building else ""
        raise CityGMLError(f"polygon {gid or '(without gml:id)'}{where}: {why}", self.path)

    # -- per city object resolution ------------------------------------------------------------
    def resolve_local(self) -> list[_Ref]:
        """Merge references with their targets inside this city object; return the others."""
        index: dict[str, RawPolygon] = {}
        for p in self.polygons:
            if p.gml_id:
                index.setdefault(p.gml_id, p)
        unresolved = []
        for ref in self.refs:
            targets = self._targets(ref.target, index)
            if targets is None:
                unresolved.append(ref)
            else:
                for t in targets:
                    merge_reference(t, ref)
        return unresolved

    def _targets(self, target: str, index: dict[str, RawPolygon]):
        p = index.get(target)
        if p is not None:
            return [p]
        rng = self.containers.get(target)
        if rng is not None:
            return self.polygons[rng[0]:rng[1]]
        return None

    def dedupe(self) -> int:
        """Drop repeated definitions of the same gml:id (invalid GML, but seen); returns count."""
        seen: set[str] = set()
        keep = []
        for p in self.polygons:
            if p.gml_id and p.gml_id in seen:
                continue
            if p.gml_id:
                seen.add(p.gml_id)
            keep.append(p)
        dropped = len(self.polygons) - len(keep)
        self.polygons = keep
        return dropped


def merge_reference(target: RawPolygon, ref: _Ref) -> None:
    """A second use of a polygon: keep one polygon, with thematic semantics and solid membership."""
    if ref.in_solid and not ref.reversed:
        target.from_solid = True
    if target.semantic == "Unknown" and ref.semantic != "Unknown":
        target.semantic = ref.semantic


def _xml_error(error: etree.XMLSyntaxError) -> str:
    """lxml's message on one line ("malformed XML: ..., line N, column M")."""
    text = " ".join((error.msg or str(error)).split()).replace(" ,", ",")
    if error.lineno and f"line {error.lineno}" not in text:
        text += f", line {error.lineno}"
    return f"malformed XML: {text}"


def detect_version(namespaces) -> str | None:
    """CityGML version ("1.0", "2.0", "3.0") from namespace URIs, None if none is CityGML."""
    found = []
    for uri in namespaces:
        m = _VERSION_RE.search(uri or "")
        if m:
            found.append(m.group(1))
    if not found:
        return None
    return max(set(found), key=found.count)


def _read_root(path: Path):
    """Tag and namespaces of the root element (parses only the first start tag)."""
    try:
        with open_model(path) as source:
            for _event, el in etree.iterparse(source, events=("start",), huge_tree=True):
                return el.tag, dict(el.nsmap)
    except etree.XMLSyntaxError as error:
        raise CityGMLError(_xml_error(error), path) from None
    except OSError as error:
        raise InputError(f"cannot read file: {error}", path) from None
    raise CityGMLError("empty XML document", path)


class _CRSState:
    """The file's CRS, checked for consistency as srsNames appear."""

    def __init__(self, path: Path, user: CRSInfo | None, target: CRSInfo | None):
        self.path = path
        self.user = user
        self.target = target
        self.file: CRSInfo | None = None
        self.file_names: list[str] = []
        self._seen: set[str] = set()
        self.warnings: list[str] = []
        self._out_key = None
        self._out: CRSInfo | None = None
        self._reproject = False

    def add(self, names: set[str]) -> None:
        for name in names - self._seen:
            self._seen.add(name)
            info = crs_mod.resolve_crs(name, path=self.path)
            if self.file is None:
                self.file = info
                self.file_names.append(name)
                self._check()
            elif crs_mod.same_crs(self.file, info):
                self.file = crs_mod.more_complete(self.file, info)
            else:
                raise CRSError(
                    f"mixed CRSs in one file: {self.file_names[0]!r} ({self.file.label}) and "
                    f"{name!r} ({info.label})",
                    self.path,
                )

    def _check(self) -> None:
        if self.user is not None and self.file is not None and not crs_mod.same_crs(self.user, self.file):
            self.warnings.append(
                f"the file names CRS {self.file.label}; the given CRS {self.user.label} is ignored"
            )

    @property
    def source(self) -> CRSInfo | None:
        return self.file if self.file is not None else self.user

    def require(self) -> CRSInfo:
        src = self.source
        if src is None:
            raise CRSError("no CRS in the file; pass --crs EPSG:N", self.path)
        if not src.is_projected and self.target is None:
            raise CRSError(
                f"the file's CRS {src.srs_name or src.label} ({src.label}) is geographic (degrees); "
                "give a projected CRS to "
                "reproject to, e.g. --target_crs EPSG:6677 for PLATEAU (Japan plane rectangular "
                "CS IX) or the local UTM zone",
                self.path,
            )
        return src

    def output(self) -> CRSInfo:
        """The CRS of the polygons returned: the source CRS, or the target CRS (keeping the
        source's height system when the target names none)."""
        src = self.require()
        key = (src.wkt, None if self.target is None else self.target.wkt)
        if key != self._out_key:
            self._out_key = key
            if self.target is None or (
                crs_mod.same_crs(src, self.target)
                and self.target.vertical_epsg in (None, src.vertical_epsg)
            ):
                self._out, self._reproject = src, False
            else:
                self._out, self._reproject = crs_mod.output_crs(src, self.target), True
        return self._out

    def needs_reprojection(self) -> bool:
        self.output()
        return self._reproject

    def reproject(self, xyz: np.ndarray) -> np.ndarray:
        try:
            return crs_mod.reproject_points(xyz, self.source, self.output())
        except CRSError as error:
            if error.path is not None:
                raise
            raise CRSError(error.message, self.path) from None


def _as_bbox(bbox_crs) -> np.ndarray | None:
    if bbox_crs is None:
        return None
    b = np.asarray(bbox_crs, dtype=np.float64)
    if b.shape not in ((2, 2), (2, 3)):
        raise ValueError(f"bbox_crs must have shape (2, 2) or (2, 3), got {b.shape}")
    return b


def read_citygml(
    path: str | Path,
    *,
    lod: int = 2,
    crs: str | CRSInfo | None = None,
    target_crs: str | CRSInfo | None = None,
    bbox_crs: np.ndarray | None = None,
) -> RawCityModel:
    """Read the buildings of a CityGML file at level of detail `lod` (1, 2 or 3).

    crs: CRS to assume when the file names none (the file's own CRS wins; a different one warns).
    target_crs: projected CRS to reproject to (required for geographic files).
    bbox_crs: (2,2) or (2,3) [min, max] in the output CRS; buildings whose bounding box does not
        intersect it are dropped (NoOverlapError if none is left).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file", path)
    if lod not in (0, 1, 2, 3, 4):
        raise InputError(f"unsupported level of detail {lod} (use 1, 2 or 3)", path)
    user = crs if isinstance(crs, CRSInfo) or crs is None else crs_mod.user_crs(crs)
    target = (
        target_crs
        if isinstance(target_crs, CRSInfo) or target_crs is None
        else crs_mod.resolve_crs(target_crs, path="--target_crs")
    )
    if target is not None and not target.is_projected:
        raise CRSError(f"target CRS {target.label} is not projected (metres needed)", "--target_crs")
    bbox = _as_bbox(bbox_crs)

    root_tag, nsmap = _read_root(path)
    root_name = _local(root_tag)
    version = detect_version([root_tag.partition("}")[0][1:], *nsmap.values()])
    if version is None or root_name not in ("CityModel", "FeatureCollection"):
        raise CityGMLError(
            f"not a CityGML file (root element {root_name or root_tag!r}"
            + ("" if version else ", no CityGML namespace")
            + ")",
            path,
        )

    walker = _Walker(path, lod)
    state = _CRSState(path, user, target)
    builder = RawPolygonBuilder()
    pending_rows: list[tuple[int, _Pending]] = []  # rows whose rings come from other objects
    building_ids: list[str] = []
    part_ids: list[str] = []
    pending_refs: list[_Ref] = []
    num_features = [0]
    num_dropped = 0
    num_duplicates = 0
    num_without = 0

    tags = [f"{{*}}{t}" for t in MEMBER_TAGS + _CLEAR_TAGS] + ["{*}Envelope"]
    source = None  # closed on every way out (lxml keeps it open until garbage collection)
    try:
        source = open_model(path)
        context = etree.iterparse(source, events=("end",), tag=tags, huge_tree=True, remove_comments=True)
        for _event, el in context:
            parent = el.getparent()
            name = _local(el.tag)
            if name == "Envelope":
                grand = parent.getparent() if parent is not None else None
                if grand is not None and grand.getparent() is None:  # the model's envelope
                    srs = el.get("srsName")
                    if srs:
                        state.add({srs})
                continue
            if parent is None or parent.getparent() is not None:
                continue  # not a top-level member (nested featureMember etc.)
            if name in MEMBER_TAGS:
                for feature in el:
                    if not isinstance(feature.tag, str):
                        continue
                    walker.reset(el)
                    walker.feature(feature, num_features)
                    if not walker.buildings:
                        continue
                    walker.finalize()
                    num_duplicates += walker.dedupe()
                    unresolved = walker.resolve_local()
                    state.add(walker.srs_names)
                    walker.srs_names = set()
                    if not walker.polygons:
                        num_without += len(walker.buildings)  # no geometry at this LOD
                        continue
                    state.require()
                    keep = _place(walker, state, bbox)
                    if not keep:
                        num_dropped += len(walker.buildings)
                        continue
                    _add_member(builder, walker, pending_rows)
                    building_ids.extend(walker.buildings)
                    part_ids.extend(walker.parts)
                    pending_refs.extend(unresolved)
            # free the member and everything before it
            el.clear()
            while el.getprevious() is not None:
                del parent[0]
        del context
    except etree.XMLSyntaxError as error:
        raise CityGMLError(_xml_error(error), path) from None
    except OSError as error:
        raise InputError(f"cannot read file: {error}", path) from None
    finally:
        if source is not None:
            source.close()

    if num_features[0] == 0:
        raise CityGMLError("no buildings in the file", path)
    polygons = builder.finish()
    if not polygons and num_dropped == 0:
        seen = sorted(walker.lods_seen)
        other = f" (it has LOD {', '.join(map(str, seen))}; pass --lod {seen[-1] if 2 not in seen else 2})" if seen else ""
        raise CityGMLError(f"no building geometry at LOD {lod}{other}", path)
    if not polygons:
        raise NoOverlapError(
            f"none of the {num_dropped} buildings intersects the bounding box "
            f"{np.round(bbox, 3).tolist()} ({state.output().label})",
            path,
        )
    warnings = list(state.warnings)
    if pending_refs or pending_rows:
        polygons = _resolve_pending(path, walker, state, polygons, pending_refs, pending_rows)
    if num_without:
        warnings.append(f"{num_without} buildings without LOD {lod} geometry skipped")
    if num_duplicates:
        warnings.append(f"{num_duplicates} polygons defined twice with the same gml:id (kept the first)")
    if walker.num_2d_rings:
        warnings.append(f"{walker.num_2d_rings} rings with 2D coordinates (z set to 0)")
    if num_dropped:
        logger.info("%s: kept %d buildings, dropped %d outside the bounding box", path.name, len(building_ids), num_dropped)
    return RawCityModel(
        source=str(path),
        format="CityGML",
        version=version,
        crs=state.output(),
        polygons=polygons,
        building_ids=building_ids,
        part_ids=part_ids,
        warnings=warnings,
    )


def _place(walker: _Walker, state: _CRSState, bbox: np.ndarray | None) -> bool:
    """Reproject the city object's polygons if needed and apply the bbox filter."""
    polys = [p for p in walker.polygons if len(p.exterior)]
    if state.needs_reprojection():
        arrays = [a for p in polys for a in (p.exterior, *p.holes)]
        if arrays:
            xyz = np.concatenate(arrays)
            src = state.source
            if not src.is_projected:
                problem = coordinate_problem(xyz, geographic=True,
                                             lat_first=crs_mod.lat_first(xyz, src))
                if problem is not None:
                    row, why = problem
                    ends = np.cumsum([sum(len(a) for a in (p.exterior, *p.holes)) for p in polys])
                    p = polys[int(np.searchsorted(ends, row, side="right"))]
                    raise CityGMLError(
                        f"polygon {p.gml_id or '(without gml:id)'} of building {p.building_id}: "
                        f"{why} in {src.label}", state.path)
            xyz = state.reproject(xyz)
            k = 0
            for p in polys:
                n = len(p.exterior)
                p.exterior = xyz[k:k + n]
                k += n
                holes = []
                for h in p.holes:
                    holes.append(xyz[k:k + len(h)])
                    k += len(h)
                p.holes = holes
    if bbox is None or not polys:
        return True
    lo = np.min([p.exterior.min(axis=0) for p in polys], axis=0)
    hi = np.max([p.exterior.max(axis=0) for p in polys], axis=0)
    d = bbox.shape[1]
    return bool(np.all(lo[:d] <= bbox[1]) and np.all(hi[:d] >= bbox[0]))


def _add_member(builder: RawPolygonBuilder, walker: _Walker, pending_rows: list) -> None:
    """Append a kept city object's polygons to the table; polygons with a ring from another
    city object get empty rings for now (filled by _resolve_pending)."""
    polys = walker.polygons
    waiting = {id(pp.polygon): pp for pp in walker.pending} if walker.pending else None
    rings: list[np.ndarray] = []
    ring_len: list[int] = []
    nring: list[int] = []
    row0 = len(builder)
    for i, p in enumerate(polys):
        pp = waiting.get(id(p)) if waiting else None
        if pp is not None:
            pending_rows.append((row0 + i, pp))
            ring_len += [0] * len(pp.rings)
            nring.append(len(pp.rings))
            continue
        rings.append(p.exterior)
        ring_len.append(len(p.exterior))
        if p.holes:
            rings += p.holes
            ring_len += [len(h) for h in p.holes]
        nring.append(1 + len(p.holes))
    builder.add_block(
        np.concatenate(rings) if rings else _EMPTY, ring_len, nring,
        [p.semantic for p in polys], [p.building_id for p in polys], [p.part_id for p in polys],
        [p.gml_id for p in polys], [p.lod for p in polys], [p.from_solid for p in polys],
    )


def _merge_reference_row(table: RawPolygonTable, row: int, ref: _Ref) -> None:
    """merge_reference for a polygon of the table."""
    if ref.in_solid and not ref.reversed:
        table.from_solid[row] = True
    if table.semantic[row] == "Unknown" and ref.semantic != "Unknown":
        table.semantic[row] = ref.semantic


def _resolve_pending(
    path: Path,
    walker: _Walker,
    state: _CRSState,
    polygons: RawPolygonTable,
    refs: list[_Ref],
    pending: list[tuple[int, _Pending]],
) -> RawPolygonTable:
    """Resolve references across city objects; returns the table with the rings of pending
    polygons filled in and the polygons added for targets that lie in dropped buildings
    (attributed to the referencing building)."""
    index: dict[str, int] = {}
    for row, gid in enumerate(polygons.gml_id):
        if gid:
            index.setdefault(gid, row)
    open_refs = []
    for ref in refs:
        target = index.get(ref.target)
        if target is not None:
            _merge_reference_row(polygons, target, ref)
        else:
            open_refs.append(ref)
    ring_ids = {r.target for _, pp in pending for r in pp.rings if isinstance(r, _RingRef)}
    if not open_refs and not ring_ids:
        return polygons
    found_surfaces, found_rings = _rescan(path, walker.lod, {r.target for r in open_refs}, ring_ids)
    added: list[RawPolygon] = []
    added_by_id: dict[str, list[RawPolygon]] = {}
    reproject = state.needs_reprojection()
    for ref in open_refs:
        if ref.target in added_by_id:
            for p in added_by_id[ref.target]:
                merge_reference(p, ref)
            continue
        surfaces = found_surfaces.get(ref.target)
        if surfaces is None:
            raise CityGMLError(f"unresolved xlink:href to '{ref.target}': no element has this gml:id", path)
        new = []
        for rings in surfaces:
            if ref.reversed:
                rings = [r[::-1].copy() for r in rings]
            if reproject:
                rings = [state.reproject(r) for r in rings]
            new.append(
                RawPolygon(
                    exterior=rings[0], holes=rings[1:], semantic=ref.semantic,
                    building_id=ref.building_id, part_id=ref.part_id, gml_id=ref.target,
                    lod=walker.lod, from_solid=ref.in_solid and not ref.reversed,
                )
            )
        added_by_id[ref.target] = new
        added.extend(new)
    filled: dict[int, list[np.ndarray]] = {}
    for row, pp in pending:
        rings = []
        for r in pp.rings:
            if isinstance(r, _RingRef):
                ring = found_rings.get(r.target)
                if ring is None:
                    raise CityGMLError(f"unresolved xlink:href to ring '{r.target}': no ring has this gml:id", path)
                if r.reversed:
                    ring = ring[::-1].copy()
                rings.append(ring)
            else:
                rings.append(r)
        if reproject:  # _place() skipped these polygons: all their rings are still in the source CRS
            rings = [state.reproject(r) for r in rings]
        filled[row] = rings
    if filled:
        polygons = _fill_rows(polygons, filled)
    if added:
        polygons = RawPolygonTable.concatenate([polygons, RawPolygonTable.from_polygons(added)])
    return polygons


def _fill_rows(table: RawPolygonTable, filled: dict[int, list[np.ndarray]]) -> RawPolygonTable:
    """The table with the rings of the rows in `filled` replaced (same number of rings)."""
    coords, rp, pp = table.coords, table.ring_ptr, table.poly_ptr
    rings = [coords[rp[r]:rp[r + 1]] for r in range(table.num_rings)]
    for row, new in filled.items():
        rings[pp[row]:pp[row + 1]] = [np.asarray(r, dtype=np.float64).reshape(-1, 3) for r in new]
    return RawPolygonTable(
        np.concatenate(rings) if rings else _EMPTY, [len(r) for r in rings], table.poly_nring,
        table.semantic, table.building_id, table.part_id, table.gml_id, table.lod,
        table.from_solid,
    )


def _rescan(path: Path, lod: int, surface_ids: set[str], ring_ids: set[str]):
    """Second streaming pass: geometry of the elements with the given gml:ids.

    Returns ({id: [rings of each polygon]}, {ring id: (N,3) array})."""
    surfaces: dict[str, list[list[np.ndarray]]] = {}
    rings: dict[str, np.ndarray] = {}
    walker = _Walker(path, lod)
    tags = ["{*}Polygon", "{*}Surface", "{*}CompositeSurface", "{*}MultiSurface", "{*}OrientableSurface",
            "{*}LinearRing", "{*}Ring"] + [f"{{*}}{t}" for t in MEMBER_TAGS]
    source = None
    try:
        source = open_model(path)
        for _event, el in etree.iterparse(source, events=("end",), tag=tags, huge_tree=True, remove_comments=True):
            parent = el.getparent()
            if _local(el.tag) in MEMBER_TAGS:
                if parent is not None and parent.getparent() is None:
                    el.clear()
                    while el.getprevious() is not None:
                        del parent[0]
                continue
            gid = _gml_id(el)
            if not gid or (gid not in surface_ids and gid not in ring_ids):
                continue
            dim = _inherited_dim(el, walker)
            walker.reset(None)
            if _local(el.tag) in ("LinearRing", "Ring"):
                k = walker._ring(el, dim, gid)
                rings.setdefault(gid, walker.finalize()[k])
                continue
            walker._geometry(el, "Unknown", False, False, dim)
            walker.finalize()
            if walker.refs or walker.pending:
                raise CityGMLError(f"xlink:href to '{gid}' leads to further references (not supported)", path)
            surfaces.setdefault(gid, [[p.exterior, *p.holes] for p in walker.polygons])
    except etree.XMLSyntaxError as error:
        raise CityGMLError(_xml_error(error), path) from None
    except OSError as error:
        raise InputError(f"cannot read file: {error}", path) from None
    finally:
        if source is not None:
            source.close()
    return surfaces, rings
