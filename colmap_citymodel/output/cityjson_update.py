"""Write corrected vertex coordinates back into the CityJSON file the model was read from.

CityJSON 1.0, 1.1, 2.0 and CityJSONSeq (`.jsonl`): the document is loaded, the entries of its
`vertices` array that the reader turned into moved store vertices are changed, and it is
written back with the same structure (objects, ids, attributes, semantics, appearances,
`transform` and `metadata` as they were; integer vertices stay integers in the file's
`transform`, float vertices of files without one are written with full precision).

Which vertices: those referenced by the geometry the reader read (citymodel.read_cityjson:
Building / BuildingPart objects of the buildings in the store, geometries at the chosen LOD,
the highest such LOD per object, outer shells of solids), found by value in the store's
provenance as in output.citygml_update. A vertex index that other geometry shares as well
(another LOD of the same building, say) moves for it too: CityJSON stores a position once.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ..citymodel import crs as crs_mod
from ..citymodel.archives import read_model_text
from ..citymodel.raw_model import CRSInfo
from ..citymodel.read_cityjson import BUILDING_TYPES, SOLID_TYPES, SURFACE_TYPES, _lod_value
from .citygml_update import Moves, UpdateReport

logger = logging.getLogger(__name__)


def _root_building(obj_id: str, objects: dict) -> str:
    seen = {obj_id}
    current = obj_id
    while objects.get(current, {}).get("type") == "BuildingPart":
        parents = objects[current].get("parents") or []
        if not parents or parents[0] in seen:
            break
        current = parents[0]
        seen.add(current)
    return current


def _ring_indices(boundaries, gtype: str) -> list[int]:
    """Vertex indices of the surfaces the reader reads (outer shells of solids)."""
    if gtype in SURFACE_TYPES:
        surfaces = boundaries
    elif gtype == "Solid":
        surfaces = boundaries[0] if boundaries else []
    else:  # MultiSolid, CompositeSolid
        surfaces = [s for solid in boundaries if solid for s in solid[0]]
    return [int(i) for surface in surfaces for ring in surface for i in ring]


def read_vertex_indices(objects: dict, lod: int, buildings: set[str]) -> np.ndarray:
    """Sorted vertex indices of the geometry read_cityjson reads for `buildings`."""
    out: list[int] = []
    for obj_id, obj in objects.items():
        if obj.get("type") not in BUILDING_TYPES:
            continue
        building = _root_building(obj_id, objects) if obj["type"] == "BuildingPart" else obj_id
        if building not in buildings:
            continue
        chosen = [g for g in obj.get("geometry") or []
                  if g.get("type") != "GeometryInstance" and _lod_value(g.get("lod")) is not None
                  and int(_lod_value(g.get("lod"))) == lod]
        if not chosen:
            continue
        best = max(_lod_value(g["lod"]) for g in chosen)
        for g in chosen:
            if _lod_value(g["lod"]) == best and g.get("type") in SOLID_TYPES + SURFACE_TYPES:
                out += _ring_indices(g.get("boundaries") or [], g["type"])
    return np.unique(np.array(out, dtype=np.int64))


def _update_document(doc: dict, transform: dict | None, moves: Moves, lod: int,
                     src_crs: CRSInfo, reproject: bool, report: UpdateReport) -> None:
    store = moves.store
    indices = read_vertex_indices(doc.get("CityObjects") or {}, lod, moves.buildings)
    raw = doc.get("vertices") or []
    if not len(indices):
        return
    file_values = np.asarray([raw[i] for i in indices], dtype=np.float64).reshape(-1, 3)
    scale = translate = None
    points = file_values
    if transform:  # as read_cityjson computes it, to the last bit
        scale = np.asarray(transform.get("scale", [1, 1, 1]), np.float64)
        translate = np.asarray(transform.get("translate", [0, 0, 0]), np.float64)
        points = file_values * scale + translate
    report.num_coordinates += len(points)
    in_crs = crs_mod.reproject_points(points, src_crs, store.crs) if reproject else points
    vertex = store.provenance.vertex_of(in_crs - store.origin)
    report.num_not_in_store += int(np.count_nonzero(vertex < 0))
    report.vertices_written.update(vertex[vertex >= 0].tolist())
    hit = vertex >= 0
    hit[hit] = moves.moved[vertex[hit]]
    rows = np.flatnonzero(hit)
    if not len(rows):
        return
    shift = moves.table[vertex[rows]]
    if reproject:
        new = crs_mod.reproject_points(in_crs[rows] + shift, store.crs, src_crs)
        if crs_mod.lat_first(points, src_crs):
            new[:, [0, 1]] = new[:, [1, 0]]
    else:
        new = points[rows] + shift
    for row, value in zip(rows.tolist(), new):
        if scale is not None:
            raw[int(indices[row])] = [int(v) for v in np.rint((value - translate) / scale)]
        else:
            raw[int(indices[row])] = [float(v) for v in value]
    report.num_moved += len(rows)
    report.num_elements += len(rows)


def _dumps(doc: dict, compact: bool) -> str:
    if compact:
        return json.dumps(doc, ensure_ascii=False, separators=(",", ":"))
    return json.dumps(doc, ensure_ascii=False, indent=2)


def update_cityjson(source: str | Path, target: str | Path, moves: Moves, *, lod: int = 2,
                    assumed_crs: CRSInfo | None = None) -> UpdateReport:
    """Write `source` (CityJSON or CityJSONSeq) to `target` with the vertices of `moves`
    shifted (see module doc)."""
    source, target = Path(source), Path(target)
    store = moves.store
    if store.provenance is None:
        raise ValueError("the store has no provenance: read it with read_city_model")
    text = read_model_text(source)
    report = UpdateReport(str(source), str(target))
    lines = [line for line in text.splitlines() if line.strip()]
    try:
        documents = [json.loads(text)]
        sequence = False
    except json.JSONDecodeError:
        documents = [json.loads(line) for line in lines]
        sequence = True
    header = documents[0]
    transform = header.get("transform")
    meta = header.get("metadata") or {}
    reference = meta.get("referenceSystem") or meta.get("referencesystem")
    src_crs = (crs_mod.resolve_crs(str(reference), path=source) if reference
               else assumed_crs if assumed_crs is not None else store.crs)
    reproject = not crs_mod.same_crs(src_crs, store.crs)
    for doc in (documents[1:] if sequence else documents):
        _update_document(doc, transform if not sequence or "transform" not in doc
                         else doc["transform"], moves, lod, src_crs, reproject, report)
    target.parent.mkdir(parents=True, exist_ok=True)
    if sequence:
        out = "\n".join(_dumps(d, True) for d in documents) + "\n"
    else:
        compact = "\n" not in text.strip()[:4096]
        out = _dumps(documents[0], compact) + ("\n" if text.endswith("\n") else "")
    target.write_text(out, encoding="utf-8")
    logger.info("%s: %d vertices moved", target.name, report.num_moved)
    return report
