"""The corrected model in the user's own format: each file the model was read from, written
again with the corrected vertices moved (output.citygml_update, output.cityjson_update).

One file in, `corrected_model.gml` (CityGML, any version: the one read) or
`corrected_model.city.json` / `.city.jsonl` (CityJSON / CityJSONSeq) out; tiles in (several
files or a directory), the directory `corrected_model/` out with one file per tile under its
own name, also the tiles nothing moved in, so the set stays complete.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..adjust.model_correction import ModelCorrection
from ..citymodel.archives import inner_name, model_suffix
from ..citymodel.crs import user_crs
from ..citymodel.read import _kind
from ..citymodel.store import PlaneStore
from .citygml_update import Moves, UpdateReport, update_citygml
from .cityjson_update import update_cityjson

logger = logging.getLogger(__name__)


def source_files(store: PlaneStore) -> list[Path]:
    """The files the store was read from (`store.source`, ';'-separated for tiles)."""
    return [Path(p) for p in str(store.source).split(";") if p and Path(p).is_file()]


def target_names(sources: list[Path]) -> list[str]:
    """Where each source goes, relative to the output directory."""
    def suffix(path: Path) -> str:
        if _kind(path) == "citygml":
            return ".gml"
        return ".city.jsonl" if model_suffix(path) == ".jsonl" else ".city.json"

    if len(sources) == 1:
        return ["corrected_model" + suffix(sources[0])]
    names, seen = [], set()
    for k, path in enumerate(sources):
        name = inner_name(path)  # written uncompressed
        name = name if name not in seen else f"{k:03d}_{name}"
        seen.add(name)
        names.append(f"corrected_model/{name}")
    return names


def write_corrected_model(correction: ModelCorrection, store: PlaneStore, directory: Path, *,
                          lod: int = 2, model_crs: str | None = None
                          ) -> tuple[list[dict], list[str]]:
    """Write every source file of `store` into `directory` with the corrected vertices moved;
    returns what each file got (UpdateReport.todict() plus `num_vertices_moved`, target
    relative to `directory`) and warnings (a moved vertex found in no file, say)."""
    sources = source_files(store)
    if not sources:
        return [], [f"the model's files ({store.source}) are not there any more: the "
                    "corrected model is not written"]
    if store.provenance is None:
        return [], ["the model was not read from files with provenance: the corrected model "
                    "is not written"]
    moves = Moves(store, correction.vertex_ids, correction.shift)
    moved = set(np.flatnonzero(moves.moved).tolist())
    assumed = user_crs(model_crs) if model_crs else None
    written, found = [], set()
    for source, name in zip(sources, target_names(sources)):
        update = update_citygml if _kind(source) == "citygml" else update_cityjson
        report: UpdateReport = update(source, directory / name, moves, lod=lod,
                                      assumed_crs=assumed)
        found |= report.vertices_written
        entry = report.todict()
        entry["target"] = name
        entry["num_vertices_moved"] = len(report.vertices_written & moved)
        written.append(entry)
    warnings = []
    if moved - found:
        warnings.append(f"{len(moved - found)} corrected vertices were found in none of the "
                        "model's files: not written")
    return written, warnings
