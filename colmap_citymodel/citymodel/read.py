"""The one entry point that turns city model files into a PlaneStore.

`read_city_model` accepts one file, several files or a directory of tiles (CityGML `*.gml`,
`*.xml`; CityJSON `*.json`, `*.city.json`, `*.jsonl`; each also gzip-compressed, `*.gml.gz`, and
ZIP archives of them, citymodel.archives), reads each with its format's reader, checks that all
share one CRS, merges them into one RawCityModel and builds the store (vertex merging, planes,
spatial index: citymodel.store.build_store).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import CRSError, InputError, NoOverlapError
from . import crs as crs_mod
from .archives import (CITYGML_SUFFIXES, CITYJSON_SUFFIXES, expand_archive, is_model_file, is_zip,
                       model_suffix, read_model_head)
from .raw_model import RawCityModel, RawPolygonTable
from .store import PlaneStore
from .build import build_store

logger = logging.getLogger(__name__)


def _kind(path: Path) -> str:
    """'citygml' or 'cityjson' from the suffix (under a gzip suffix: "x.gml.gz"), or the first
    character of the (decompressed) content for other names."""
    suffix = model_suffix(path)
    if suffix in CITYGML_SUFFIXES:
        return "citygml"
    if suffix in CITYJSON_SUFFIXES:
        return "cityjson"
    try:
        head = read_model_head(path, 4096).lstrip(b"\xef\xbb\xbf \t\r\n")
    except OSError as error:
        raise InputError(f"cannot read file: {error}", path) from None
    if head.startswith(b"<"):
        return "citygml"
    if head.startswith(b"{"):
        return "cityjson"
    raise InputError("neither CityGML (XML) nor CityJSON; expected *.gml, *.xml, *.json or "
                     "*.jsonl, each also as *.gz, or a *.zip of them", path)


def city_model_files(paths: str | Path | list) -> list[Path]:
    """The files named by `paths`: files as given, directories expanded to their tiles (sorted),
    ZIP archives (given, or in a directory) to the model files they hold (unpacked once per
    process, citymodel.archives)."""
    if isinstance(paths, (str, Path)):
        paths = [paths]
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            tiles = sorted(f for f in p.iterdir()
                           if f.is_file() and (is_model_file(f) or is_zip(f)))
            if not tiles:
                raise InputError("directory has no CityGML (*.gml, *.xml) or CityJSON (*.json, "
                                 "*.jsonl) files, plain, *.gz or in a *.zip", p)
            for tile in tiles:
                files.extend(expand_archive(tile) if is_zip(tile) else [tile])
        elif p.is_file():
            files.extend(expand_archive(p) if is_zip(p) else [p])
        else:
            raise InputError("no such file or directory", p)
    if not files:
        raise InputError("no city model file given")
    return files


def read_raw(path: Path, *, lod: int, crs, target_crs, bbox_crs) -> RawCityModel:
    """Read one file with the reader of its format."""
    if _kind(path) == "citygml":
        from .read_citygml import read_citygml

        return read_citygml(path, lod=lod, crs=crs, target_crs=target_crs, bbox_crs=bbox_crs)
    from .read_cityjson import read_cityjson

    return read_cityjson(path, lod=lod, crs=crs, target_crs=target_crs, bbox_crs=bbox_crs)


def merge_raw(models: list[RawCityModel]) -> RawCityModel:
    """One RawCityModel from several tiles; all must share a CRS (else CRSError)."""
    first = models[0]
    model_crs = first.crs
    for m in models[1:]:
        if not crs_mod.same_crs(model_crs, m.crs):
            raise CRSError(
                f"CRS {m.crs.label} differs from {model_crs.label} of {first.source}; "
                "all tiles must share one CRS (or pass --target_crs)",
                m.source,
            )
        model_crs = crs_mod.more_complete(model_crs, m.crs)
    if len(models) == 1:
        return first
    warnings: list[str] = []
    for m in models:
        warnings += [f"{Path(m.source).name}: {w}" for w in m.warnings]
    building_ids = [b for m in models for b in m.building_ids]
    seen: set[str] = set()
    repeated = {b for b in building_ids if b in seen or seen.add(b)}
    if repeated:
        warnings.append(f"{len(repeated)} building ids occur in more than one tile")
    formats = sorted({m.format for m in models})
    versions = sorted({m.version for m in models})
    return RawCityModel(
        source=";".join(m.source for m in models),
        format="+".join(formats),
        version="+".join(versions),
        crs=model_crs,
        polygons=RawPolygonTable.concatenate([m.polygon_table() for m in models]),  # no copy
        building_ids=building_ids,
        part_ids=[p for m in models for p in m.part_ids],
        warnings=warnings,
    )


def read_city_model(
    paths: str | Path | list,
    *,
    lod: int = 2,
    crs: str | None = None,
    target_crs: str | None = None,
    bbox_crs: np.ndarray | None = None,
    merge_tolerance: float = 0.001,
) -> PlaneStore:
    """Read a city model (file, files or directory of tiles) into a PlaneStore.

    lod: level of detail (1, 2 or 3); crs: CRS to assume when a file names none ("EPSG:3946");
    target_crs: projected CRS to reproject to (needed for geographic data such as PLATEAU);
    bbox_crs: (2,2) or (2,3) [min, max] in the model CRS, buildings outside are dropped (tiles
    entirely outside are skipped; NoOverlapError when nothing is left);
    merge_tolerance: vertices closer than this (metres) are merged.
    """
    files = city_model_files(paths)
    models: list[RawCityModel] = []
    misses: list[NoOverlapError] = []
    for f in files:
        try:
            models.append(read_raw(f, lod=lod, crs=crs, target_crs=target_crs, bbox_crs=bbox_crs))
        except NoOverlapError as error:
            if len(files) == 1:
                raise
            misses.append(error)
    if not models:
        where = files[0].parent if len(files) > 1 else files[0]
        raise NoOverlapError(
            f"none of the {len(files)} tiles has a building inside the bounding box "
            f"{np.round(np.asarray(bbox_crs, float), 3).tolist()}",
            where,
        )
    if misses:
        logger.info("skipped %d of %d tiles outside the bounding box", len(misses), len(files))
    raw = merge_raw(models)
    del models
    # build_store owns the raw model: its coordinates are freed once they are in the local frame
    store = build_store(raw, merge_tolerance=merge_tolerance, release_raw=True)
    del raw
    logger.info(
        "read %d buildings, %d faces, %d vertices from %d file(s) (%s)",
        store.num_buildings, store.num_faces, len(store.vertices), len(files), store.crs.label,
    )
    return store


def peek_crs(citymodel, assumed: str | None = None):
    """The CRS of the first city model file from its first srsName / referenceSystem, read
    from the file's head only (so GNSS can bound what is read of a large model); None when
    the head names none (the model is then read whole first)."""
    import re

    from .crs import resolve_crs, user_crs

    files = city_model_files(citymodel)
    try:
        head = read_model_head(files[0], 1 << 20).decode("utf-8", errors="ignore")
    except OSError as error:
        raise InputError(f"cannot read file: {error}", files[0]) from None
    found = re.search(r'srsName="([^"]+)"', head) or \
        re.search(r'"referenceSystem"\s*:\s*"([^"]+)"', head)
    if found:
        info = resolve_crs(found.group(1), path=files[0])
        return info if info.is_projected else None
    return user_crs(assumed) if assumed else None
