"""CityJSON reader: CityJSON 1.0, 1.1, 2.0 files and CityJSONSeq (`.jsonl`) into a RawCityModel.

- Vertices are integers with `transform` (scale, translate) in 1.1/2.0 and CityJSONSeq, plain
  floats in 1.0 files without a transform.
- CRS from `metadata.referenceSystem` (URL `https://www.opengis.net/def/crs/EPSG/0/7415` or URN
  `urn:ogc:def:crs:EPSG::7415`), resolved by `crs.resolve_crs`.
- Building and BuildingPart objects (parts found through `parents`, nested parts allowed);
  geometry types MultiSurface, CompositeSurface, Solid, MultiSolid, CompositeSolid with
  `semantics` (surfaces + values). Only the outer shell of a solid is read (inner shells are
  voids nobody sees). GeometryInstance (templates) is skipped with a warning.
- LOD: an integer `lod` selects every geometry whose LOD is `lod` or `lod.x`; per object the
  highest such LOD wins (3DBAG: 2.2 for lod=2).
- CityJSONSeq: first line is the header (`"type": "CityJSON"`, transform, metadata), every
  further line a `CityJSONFeature` with its own `vertices` and `CityObjects`.

Polygons carry no ids in CityJSON: `gml_id` is "" (the store de-duplicates by vertex ring).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import CityGMLError, CRSError, InputError, NoOverlapError
from .archives import model_suffix, read_model_text
from .crs import lat_first, output_crs, reproject_points, resolve_crs, user_crs
from .raw_model import (
    CRSInfo,
    RawCityModel,
    RawPolygonBuilder,
    RawPolygonTable,
    coordinate_problem,
)

logger = logging.getLogger(__name__)

BUILDING_TYPES = ("Building", "BuildingPart")
SOLID_TYPES = ("Solid", "MultiSolid", "CompositeSolid")
SURFACE_TYPES = ("MultiSurface", "CompositeSurface")


def _load(path: Path) -> tuple[dict, list[dict]]:
    """(header document, list of CityJSONFeature documents; empty for a plain CityJSON file)."""
    try:
        text = read_model_text(path)
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"cannot read the file: {error}", path) from error
    is_seq = model_suffix(path) == ".jsonl"
    if not is_seq:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as error:
            # a CityJSONSeq stream saved under another name: several JSON objects, one a line
            if "Extra data" in error.msg and error.lineno > 1:
                is_seq = True
            else:
                raise InputError(f"not valid JSON: {error}", path) from error
    if is_seq:
        docs = []
        for n, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            try:
                docs.append(json.loads(line))
            except json.JSONDecodeError as error:
                raise InputError(f"line {n} is not valid JSON: {error}", path) from error
        if not docs:
            raise InputError("empty CityJSONSeq file", path)
        doc, features = docs[0], docs[1:]
    else:
        features = []
    if not isinstance(doc, dict) or doc.get("type") != "CityJSON":
        found = doc.get("type") if isinstance(doc, dict) else type(doc).__name__
        raise InputError(f"not a CityJSON file (type is {found!r}, expected 'CityJSON')", path)
    for n, feature in enumerate(features, 2):
        if not isinstance(feature, dict) or feature.get("type") != "CityJSONFeature":
            raise InputError(f"line {n} is not a CityJSONFeature", path)
    return doc, features


def _vertices(doc: dict, transform: dict | None, path: Path) -> np.ndarray:
    raw = doc.get("vertices", [])
    try:
        V = np.asarray(raw, dtype=np.float64).reshape(-1, 3)
    except (ValueError, TypeError, OverflowError) as error:
        raise InputError(f"malformed 'vertices' array: {error}", path) from None
    if transform:
        try:
            scale = np.asarray(transform.get("scale", [1, 1, 1]), np.float64).reshape(3)
            translate = np.asarray(transform.get("translate", [0, 0, 0]), np.float64).reshape(3)
        except (AttributeError, ValueError, TypeError, OverflowError):
            raise InputError("malformed 'transform': 'scale' and 'translate' must be three "
                             "numbers each", path) from None
        with np.errstate(over="ignore", invalid="ignore"):
            V = V * scale + translate
    return V


def _check_vertices(V: np.ndarray, objects: dict, crs: CRSInfo, path: Path) -> None:
    """Vertices no CRS can hold (nan, inf, 1e308, latitude 95, ...) fail, naming the vertex and
    the first CityObject that uses it."""
    geographic = not crs.is_projected
    problem = coordinate_problem(V, geographic=geographic,
                                 lat_first=geographic and lat_first(V, crs))
    if problem is None:
        return
    row, why = problem
    user = next((oid for oid, obj in objects.items() if isinstance(obj, dict)
                 and _uses_vertex(obj.get("geometry"), row)), None)
    where = f" (used by CityObject {user!r})" if user is not None else ""
    raise InputError(f"vertex {row}{where}: {why}", path)


def _uses_vertex(boundaries, row: int) -> bool:
    """Whether nested lists of geometries or boundaries hold vertex index `row`."""
    if isinstance(boundaries, dict):
        return _uses_vertex(boundaries.get("boundaries"), row)
    if isinstance(boundaries, list):
        return any(_uses_vertex(b, row) for b in boundaries)
    return isinstance(boundaries, int) and not isinstance(boundaries, bool) and boundaries == row


def _lod_value(lod: Any) -> float | None:
    try:
        value = float(lod)
    except (TypeError, ValueError, OverflowError):
        return None
    return value if 0.0 <= value < 10.0 else None


def _root_building(obj_id: str, objects: dict) -> str:
    """Follow `parents` up to the Building (nested BuildingParts allowed)."""
    seen = {obj_id}
    cur = obj_id
    while objects.get(cur, {}).get("type") == "BuildingPart":
        parents = objects[cur].get("parents") or []
        if not parents or not isinstance(parents[0], str) or parents[0] in seen:
            break
        cur = parents[0]
        seen.add(cur)
    return cur


def _surfaces(geom: dict) -> list[tuple[list, Any]]:
    """(surface = [ring, ring, ...], semantic value index) for the outer shells of a geometry."""
    gtype = geom.get("type")
    b = geom.get("boundaries") or []
    values = (geom.get("semantics") or {}).get("values")
    out: list[tuple[list, Any]] = []

    def val(v, *idx):
        try:
            for i in idx:
                v = v[i]
            return v
        except (TypeError, IndexError):
            return None

    if gtype in SURFACE_TYPES:
        for i, surf in enumerate(b):
            out.append((surf, val(values, i)))
    elif gtype == "Solid":
        for i, surf in enumerate(b[0] if b else []):
            out.append((surf, val(values, 0, i)))
    elif gtype in ("MultiSolid", "CompositeSolid"):
        for s, solid in enumerate(b):
            for i, surf in enumerate(solid[0] if solid else []):
                out.append((surf, val(values, s, 0, i)))
    return out


def _read_objects(
    objects: dict,
    V: np.ndarray,
    lod: int,
    found_lods: set,
    warnings: list[str],
    path: Path,
    polygons: RawPolygonBuilder,
) -> None:
    """Append the building polygons of one CityObjects dictionary to `polygons`."""
    if not isinstance(objects, dict):
        raise InputError("'CityObjects' is not a JSON object", path)
    skipped_templates = 0
    obj_id = None
    try:
        for obj_id, obj in objects.items():
            if obj.get("type") not in BUILDING_TYPES:
                continue
            geoms = obj.get("geometry") or []
            for g in geoms:
                v = _lod_value(g.get("lod"))
                if v is not None:
                    found_lods.add(g.get("lod"))
            chosen = [
                g for g in geoms
                if g.get("type") != "GeometryInstance"
                and _lod_value(g.get("lod")) is not None
                and int(_lod_value(g.get("lod"))) == lod
            ]
            skipped_templates += sum(
                1 for g in geoms
                if g.get("type") == "GeometryInstance" and int(_lod_value(g.get("lod")) or -1) == lod
            )
            if not chosen:
                continue
            best = max(_lod_value(g["lod"]) for g in chosen)
            chosen = [g for g in chosen if _lod_value(g["lod"]) == best]
            is_part = obj["type"] == "BuildingPart"
            building = _root_building(obj_id, objects) if is_part else obj_id
            for g in chosen:
                gtype = g.get("type")
                if gtype not in SOLID_TYPES + SURFACE_TYPES:
                    warnings.append(f"{obj_id}: geometry type {gtype!r} ignored")
                    continue
                sem_surfaces = (g.get("semantics") or {}).get("surfaces") or []
                for surf, sv in _surfaces(g):
                    if not surf:
                        continue
                    semantic = "Unknown"
                    if isinstance(sv, int) and 0 <= sv < len(sem_surfaces):
                        semantic = sem_surfaces[sv].get("type", "Unknown")
                        if not isinstance(semantic, str):
                            semantic = "Unknown"
                    rings = [V[_ring_indices(r, len(V), obj_id, gtype, path)] for r in surf]
                    polygons.add(
                        rings[0], rings[1:], semantic, building, obj_id if is_part else "", "", lod,
                        gtype in SOLID_TYPES,
                    )
    except (AttributeError, TypeError, KeyError) as error:
        # JSON of the wrong shape (a number where a list belongs, ...)
        raise InputError(f"CityObject {obj_id!r} is malformed ({type(error).__name__}: "
                         f"{error})", path) from None

    if skipped_templates:
        warnings.append(f"{skipped_templates} template geometries (GeometryInstance) ignored")


def _ring_indices(ring, num_vertices: int, obj_id: str, gtype, path: Path) -> np.ndarray:
    """A ring's vertex indices as int64; anything but integers in [0, num_vertices) fails."""
    try:
        idx = np.asarray(ring)
    except (ValueError, TypeError, OverflowError):
        idx = None
    if idx is None or idx.ndim != 1 or (idx.size and idx.dtype.kind not in "iu"):
        raise InputError(f"CityObject {obj_id!r}: bad vertex index in its {gtype}: a ring is "
                         f"not a list of vertex indices: {str(ring)[:80]}", path)
    idx = idx.astype(np.int64, copy=False)
    if idx.size and (idx.min() < 0 or idx.max() >= num_vertices):
        bad = int(idx[(idx < 0) | (idx >= num_vertices)][0])
        raise InputError(f"CityObject {obj_id!r}: bad vertex index {bad} in its {gtype} (the "
                         f"file has {num_vertices} vertices)", path)
    return idx


def _file_crs(doc: dict, path: Path) -> CRSInfo | None:
    meta = doc.get("metadata") or {}
    if not isinstance(meta, dict):
        raise InputError("'metadata' is not a JSON object", path)
    ref = meta.get("referenceSystem") or meta.get("referencesystem")
    if not ref:
        return None
    return resolve_crs(str(ref), path=path)


def _bbox_filter(polygons: RawPolygonTable, bbox: np.ndarray, path: Path) -> RawPolygonTable:
    """Keep whole buildings whose vertex bbox intersects `bbox` ((2,2) or (2,3), model CRS)."""
    bbox = np.asarray(bbox, dtype=np.float64)
    dim = bbox.shape[1]
    lo: dict[str, np.ndarray] = {}
    hi: dict[str, np.ndarray] = {}
    for p in polygons:
        a, b = p.exterior.min(0)[:dim], p.exterior.max(0)[:dim]
        lo[p.building_id] = np.minimum(lo.get(p.building_id, a), a)
        hi[p.building_id] = np.maximum(hi.get(p.building_id, b), b)
    keep = {k for k in lo if np.all(hi[k] >= bbox[0]) and np.all(lo[k] <= bbox[1])}
    out = polygons.take(np.fromiter((b in keep for b in polygons.building_id), bool, len(polygons)))
    if len(polygons) and not len(out):
        raise NoOverlapError(
            f"no building intersects the bounding box {bbox.tolist()} (model CRS)", path
        )
    return out


def read_cityjson(
    path: str | Path,
    *,
    lod: int = 2,
    crs: str | None = None,
    target_crs: str | None = None,
    bbox_crs: np.ndarray | None = None,
) -> RawCityModel:
    """Read a CityJSON (1.0, 1.1, 2.0) or CityJSONSeq file into plain polygons.

    crs: CRS to assume when the file names none (e.g. "EPSG:7415"); the file's own CRS wins
        (a different user CRS only adds a warning).
    target_crs: projected CRS to reproject to (required for geographic data).
    bbox_crs: (2,2) or (2,3) box in the output CRS; only buildings touching it are kept
        (NoOverlapError when none does).
    Raises InputError (not JSON / not CityJSON / bad indices), CRSError (no or unusable CRS),
    CityGMLError (no building geometry at this LOD).
    """
    path = Path(path)
    doc, features = _load(path)
    version = str(doc.get("version", ""))
    warnings: list[str] = []
    transform = doc.get("transform")

    file_crs = _file_crs(doc, path)
    given = user_crs(crs) if crs else None
    if file_crs is None and given is None:
        raise CRSError("no CRS in the file; pass --crs EPSG:N", path)
    if file_crs is not None and given is not None and file_crs.label != given.label:
        warnings.append(f"file CRS {file_crs.label} used; --crs {crs} ignored")
    src = file_crs or given

    found_lods: set = set()
    builder = RawPolygonBuilder()
    documents = [doc] if not features else features
    for d in documents:
        V = _vertices(d, transform, path)
        objects = d.get("CityObjects")
        try:
            _check_vertices(V, objects if isinstance(objects, dict) else {}, src, path)
        except InputError as error:
            if d is doc:
                raise
            raise InputError(f"CityJSONFeature {str(d.get('id'))[:80]!r}: {error.message}",
                             path) from None
        _read_objects(d.get("CityObjects") or {}, V, lod, found_lods, warnings, path, builder)
    polygons = builder.finish()
    if not len(polygons):
        have = ", ".join(sorted({str(x) for x in found_lods})) or "none"
        raise CityGMLError(
            f"no building geometry at LOD {lod} (LODs in the file: {have})", path
        )

    out_crs = src
    if target_crs:
        dst = user_crs(target_crs)
        if not dst.is_projected:
            raise CRSError(f"target CRS {target_crs} is not projected", path)
        try:
            polygons.coords = reproject_points(polygons.coords, src, dst)
        except CRSError as error:
            raise CRSError(error.message, path) from None
        out_crs = output_crs(src, dst)
    elif not src.is_projected:
        raise CRSError(
            f"the CRS {src.label} is geographic (degrees); pass --target_crs EPSG:N "
            "(a projected CRS) to reproject",
            path,
        )
    if bbox_crs is not None:
        polygons = _bbox_filter(polygons, bbox_crs, path)

    building_ids = sorted(set(polygons.building_id))
    part_ids = sorted(set(polygons.part_id) - {""})
    logger.debug(
        "%s: CityJSON %s, %d buildings, %d parts, %d polygons",
        path, version, len(building_ids), len(part_ids), len(polygons),
    )
    return RawCityModel(
        source=str(path),
        format="CityJSONSeq" if features else "CityJSON",
        version=version,
        crs=out_crs,
        polygons=polygons,
        building_ids=building_ids,
        part_ids=part_ids,
        warnings=warnings,
    )
