"""pairs: the image pairs worth matching in a known-pose block, from overlapping footprints.

Each registered image of the known-pose model (import-eo's ``sparse``, or any COLMAP model in
the same local frame) gets its footprint on the city model and the terrain
(`footprints.py`); pairs whose footprints overlap by more than `min_overlap` of the smaller one
are written one a line, ``image_name1 image_name2``, the pair list of ``colmap
matches_importer --match_type pairs`` and of pycolmap's ``match_from_pairs`` / hloc.

Frames: the model's coordinates are the model CRS minus `origin` (import-eo's origin.json, found
beside the model directory); the city model is read in the model CRS and shifted by the same
origin; `terrain_height` is a height of the model CRS. Without it the terrain is the lowest
vertex of the city model (the buildings' ground).
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..errors import InputError
from .footprints import FootprintOptions, GroundSurface, footprints, overlapping_pairs

logger = logging.getLogger(__name__)


@dataclass
class PairOptions:
    min_overlap: float = 0.2
    """A pair is kept when the footprints' intersection exceeds this share of the smaller
    footprint's area."""
    footprint: FootprintOptions = field(default_factory=FootprintOptions)
    model_margin: float = 200.0
    """Metres around the footprints on the terrain within which the city model is read."""


@dataclass
class PairsResult:
    output: Path
    num_images: int
    pairs: list[tuple[str, str, float]]

    @property
    def num_exhaustive(self) -> int:
        return self.num_images * (self.num_images - 1) // 2

    def summary(self) -> str:
        ratio = self.num_exhaustive / max(len(self.pairs), 1)
        return (f"pairs: {len(self.pairs)} pair(s) of {self.num_images} image(s) "
                f"(exhaustive: {self.num_exhaustive}, {ratio:.1f}x fewer) written to "
                f"{self.output}")


def read_origin(path) -> np.ndarray:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
        return np.asarray(data["origin"], dtype=np.float64).reshape(3)
    except FileNotFoundError:
        raise InputError("origin file does not exist", path) from None
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise InputError(f"no usable 'origin' in JSON: {error}", path) from None


def _read_model(input_path) -> pycolmap.Reconstruction:
    input_path = Path(input_path)
    if not input_path.is_dir():
        raise InputError("model directory does not exist", input_path)
    try:
        return pycolmap.Reconstruction(str(input_path))
    except Exception as error:  # pycolmap raises RuntimeError/ValueError
        raise InputError(f"cannot read COLMAP model: {error}", input_path) from None


def _database_names(database) -> set[str]:
    database = Path(database)
    if not database.is_file():
        raise InputError("COLMAP database does not exist", database)
    import shutil

    with tempfile.TemporaryDirectory(prefix="colmap_citymodel_db_") as scratch:
        copy = Path(scratch) / "database.db"  # pycolmap rewrites what it opens
        shutil.copyfile(database, copy)
        db = pycolmap.Database.open(str(copy))
        try:
            return {image.name for image in db.read_all_images()}
        finally:
            db.close()


def write_pairs(path, pairs) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp_", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        for a, b, _ in pairs:
            f.write(f"{a} {b}\n")
    os.replace(tmp, path)
    return path


def main(input_path, output, *, citymodel=None, terrain_height: float | None = None,
         database=None, origin_file=None, lod: int = 2, model_crs: str | None = None,
         options: PairOptions | None = None) -> PairsResult:
    """Footprints of the model's images on the city model and/or terrain; overlapping pairs
    written to `output`."""
    options = options or PairOptions()
    if citymodel is None and terrain_height is None:
        raise InputError("give the city model (--citymodel), a terrain height "
                         "(--terrain_height) or both")
    rec = _read_model(input_path)
    if origin_file is None:
        candidate = Path(input_path).parent / "origin.json"
        origin = read_origin(candidate) if candidate.is_file() else np.zeros(3)
    else:
        origin = read_origin(origin_file)
    if database is not None:
        known = _database_names(database)
        missing = [i.name for i in rec.images.values() if i.name not in known]
        if missing:
            raise InputError(f"{len(missing)} image(s) of the model are not in the database, "
                             f"e.g. {missing[:3]}", database)
    vertices = triangles = None
    if citymodel is not None:
        from ..citymodel.mesh import store_to_trimesh
        from ..citymodel.read import read_city_model

        flat = GroundSurface(0.0 if terrain_height is None else terrain_height - origin[2])
        plans = footprints(rec, flat, options.footprint)
        bounds = np.array([p.bounds for p in plans.values() if not p.is_empty])
        lo = bounds[:, :2].min(0) - options.model_margin + origin[:2]
        hi = bounds[:, 2:].max(0) + options.model_margin + origin[:2]
        store = read_city_model(citymodel, lod=lod, crs=model_crs, bbox_crs=np.array([lo, hi]))
        mesh, _ = store_to_trimesh(store, frame="local")
        vertices = np.asarray(mesh.vertices) + store.origin - origin
        triangles = np.asarray(mesh.faces)
        if terrain_height is None:
            terrain_height = float(np.min(vertices[:, 2]) + origin[2])
    ground = GroundSurface(terrain_height - origin[2], vertices, triangles)
    plans = footprints(rec, ground, options.footprint)
    pairs = overlapping_pairs(plans, options.min_overlap)
    write_pairs(output, pairs)
    return PairsResult(Path(output), len(plans), pairs)
