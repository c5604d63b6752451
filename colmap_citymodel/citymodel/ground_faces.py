"""The terrain near the tie points as planar faces of the plane store (class "TerrainSurface").

The terrain (citymodel.terrain) is cut into square cells of `TerrainOptions.cell` metres; each
cell that holds tie points (or borders one that does), and whose centre is not under a
building's footprint, becomes one quadrilateral face whose corners are the terrain heights
averaged over a cell's width around them (a DTM's own noise per post is smoothed away, its
slope and steps of more than a cell are kept). Neighbouring cells share their corners. The
assignment and the hybrid adjustment then treat the cells like model faces: a ground tie point
gets the same point-to-plane residual as a point on a wall.

A terrain's error is mostly one offset per source tile (a DTM tile's height reference, the
feet of one building), not independent per cell: the tie points of all cells of one tile form
one unit (`terrain_face_sigmas`), whose points together count as one observation of that
offset with the terrain's sigma. Each terrain face names its unit in its building id
("terrain:<tile>") and its sigma in its part id ("sigma=<m>"), so every copy of the store
(moved vertices, shifted planes) keeps both.
"""

from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from .faces import FaceList, compute_planes, offsets_from_counts
from .raw_model import CodedStrings, PackedStrings
from .terrain import Terrain

logger = logging.getLogger(__name__)

TERRAIN_CLASS = "TerrainSurface"
TERRAIN_PREFIX = "terrain:"
SIGMA_PREFIX = "sigma="


def smoothed(terrain: Terrain, width: float) -> Terrain:
    """`terrain` with each height the mean of the valid heights within a box `width` metres
    wide around it (nan-aware)."""
    from scipy.ndimage import uniform_filter

    size = max(1, int(round(width / terrain.spacing)) | 1)
    valid = np.isfinite(terrain.heights)
    total = uniform_filter(np.where(valid, terrain.heights, 0.0), size, mode="nearest")
    count = uniform_filter(valid.astype(float), size, mode="nearest")
    heights = np.where(valid & (count > 1e-9), total / np.maximum(count, 1e-9), np.nan)
    return replace(terrain, heights=heights)


def terrain_cells(terrain: Terrain, points_xy: np.ndarray, cell: float, footprints=None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(C, 2) int cell indices (cell (a, b) spans x in [a, a + 1] * cell, y in [b, b + 1] *
    cell, CRS) that hold a point of `points_xy` (CRS) or border one that does, without those
    whose centre lies in `footprints` (shapely, CRS xy); and their centres (C, 2)."""
    import shapely

    if not len(points_xy):
        return np.zeros((0, 2), np.int64), np.zeros((0, 2))
    occupied = np.unique(np.floor(np.asarray(points_xy) / cell).astype(np.int64), axis=0)
    grown = (occupied[:, None, :] + np.array([[a, b] for a in (-1, 0, 1) for b in (-1, 0, 1)])
             ).reshape(-1, 2)
    cells = np.unique(grown, axis=0)
    centres = (cells + 0.5) * cell
    if footprints is not None and not footprints.is_empty:
        inside = shapely.contains_xy(footprints, centres[:, 0], centres[:, 1])
        cells, centres = cells[~inside], centres[~inside]
    return cells, centres


def terrain_polygons(terrain: Terrain, points_xy: np.ndarray, cell: float, footprints=None):
    """The cells' quadrilaterals: corner node indices (C, 4) into the returned corners (K, 3)
    (CRS, counter-clockwise seen from above), each cell's unit name and sigma."""
    cells, centres = terrain_cells(terrain, points_xy, cell, footprints)
    smooth = smoothed(terrain, cell)
    corner_cells = (cells[:, None, :] + np.array([[0, 0], [1, 0], [1, 1], [0, 1]])).reshape(-1, 2)
    nodes, inverse = np.unique(corner_cells, axis=0, return_inverse=True)
    xy = nodes * cell
    corners = np.c_[xy, smooth.height(xy)]
    quads = inverse.reshape(-1, 4)
    tile = terrain.tile(centres)
    sigma = terrain.sigma(centres)
    ok = (np.all(np.isfinite(corners[quads, 2]), axis=1) & (tile >= 0) & np.isfinite(sigma))
    names = [TERRAIN_PREFIX + str(terrain.tile_names[t]) if 0 <= t < len(terrain.tile_names)
             else TERRAIN_PREFIX + str(t) for t in tile[ok]]
    return quads[ok], corners, names, sigma[ok]


def with_terrain_faces(store, terrain: Terrain, points_local: np.ndarray, cell: float,
                       footprints=None):
    """`store` (citymodel.store.PlaneStore) with the terrain cells near `points_local` (tie
    points, the store's local frame) appended as "TerrainSurface" faces; the store unchanged
    when no cell has terrain heights."""
    points_xy = np.asarray(points_local, float)[:, :2] + store.origin[:2]
    quads, corners, names, sigmas = terrain_polygons(terrain, points_xy, cell, footprints)
    if not len(quads):
        logger.info("terrain: no terrain under the tie points")
        return store
    used, remap = np.unique(quads, return_inverse=True)
    base = len(store.vertices)
    vertices = np.vstack([store.vertices, corners[used] - store.origin])
    ring_vertex = base + remap.reshape(-1, 4).ravel()
    new = FaceList(ring_vertex, offsets_from_counts(np.full(len(quads), 4)),
                   np.arange(len(quads) + 1), [TERRAIN_CLASS] * len(quads), names,
                   [f"{SIGMA_PREFIX}{s:.3f}" for s in sigmas],
                   [f"terrain_{k}" for k in range(len(quads))],
                   np.full(len(quads), int(store.faces.lod.max()) if store.num_faces else 2,
                           np.int16))
    planes = compute_planes(vertices, new, extras=False)
    old = store.faces
    faces = FaceList._own(
        np.concatenate([old.ring_vertex, new.ring_vertex]),
        np.concatenate([old.ring_ptr, old.ring_ptr[-1] + new.ring_ptr[1:]]),
        np.concatenate([old.face_ring, old.face_ring[-1] + new.face_ring[1:]]),
        CodedStrings.concatenate([old.semantic, new.semantic]),
        CodedStrings.concatenate([old.building_id, new.building_id]),
        CodedStrings.concatenate([old.part_id, new.part_id]),
        PackedStrings.concatenate([old.gml_id, new.gml_id]),
        np.concatenate([old.lod, new.lod]))
    rms = planes["rms"]
    logger.info("terrain: %d cells of %g m near the tie points (%s, %d tile(s)), plane fit RMS "
                "%.3f m", len(quads), cell, terrain.source, len(set(names)), float(np.mean(rms)))
    return replace(
        store, vertices=vertices, faces=faces,
        centroids=np.vstack([store.centroids, planes["centroids"]]),
        rotations=np.concatenate([store.rotations, planes["rotations"]]),
        areas=np.concatenate([store.areas, planes["areas"]]),
        rms_out_of_plane=np.concatenate([store.rms_out_of_plane, rms]),
        # Terrain cells are planes through four smoothed heights: their bend is the
        # terrain's, which the terrain's sigma covers; none is flagged.
        nonplanar=np.concatenate([store.nonplanar, np.zeros(len(quads), bool)]),
        warnings=list(store.warnings), _cache={})


def terrain_mask(store) -> np.ndarray:
    """(F,) bool: the store's terrain faces."""
    return store.faces.semantic.mask(TERRAIN_CLASS)


def terrain_units(store) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Per face of `store`: its terrain unit (-1: not terrain) and sigma (m; nan: not
    terrain); and the units' names."""
    mask = terrain_mask(store)
    unit = np.full(store.num_faces, -1, np.int64)
    sigma = np.full(store.num_faces, np.nan)
    if not mask.any():
        return unit, sigma, []
    codes = store.faces.building_id.codes
    names = store.faces.building_id.categories
    rows = np.flatnonzero(mask)
    used, unit[rows] = np.unique(codes[rows], return_inverse=True)
    parts = store.faces.part_id
    part_sigma = np.array([_sigma_of(p) for p in parts.categories])
    sigma[rows] = part_sigma[parts.codes[rows]]
    return unit, sigma, [names[c] for c in used]


def _sigma_of(part: str) -> float:
    if part.startswith(SIGMA_PREFIX):
        try:
            return float(part[len(SIGMA_PREFIX):])
        except ValueError:
            return np.nan
    return np.nan


def terrain_face_sigmas(store, faces: np.ndarray, rows: np.ndarray, sigmas: np.ndarray,
                        sigma_dtp: float) -> np.ndarray:
    """`sigmas` (the f_dTP sigma of each face of `faces`, adjust.problem.face_sigmas) with
    those of terrain faces replaced by their unit's: every point of a unit of n points at
    sqrt(sigma_dtp^2 + n sigma_u^2), sigma_u^2 the mean of its points' faces' sigma^2, so
    that a unit weighs as one observation of its offset however many points it has. `rows`:
    the slot in `faces` of each assigned point."""
    if store is None or not len(faces):
        return sigmas
    unit, sigma, _ = terrain_units(store)
    face_unit = unit[faces]
    on = face_unit >= 0
    if not on.any():
        return sigmas
    counts = np.bincount(rows, minlength=len(faces)).astype(float)
    units = max(int(face_unit.max()) + 1, 1)
    n_unit = np.bincount(face_unit[on], weights=counts[on], minlength=units)
    var_unit = np.bincount(face_unit[on], weights=counts[on] * sigma[faces][on] ** 2,
                           minlength=units) / np.maximum(n_unit, 1)
    out = np.array(sigmas, dtype=float)
    out[on] = np.sqrt(sigma_dtp ** 2 + n_unit[face_unit[on]] * var_unit[face_unit[on]])
    return out


#: Tie points a terrain cell should hold (twice the assignment's default minimum per face):
#: where the tie points are sparser (an aerial block), the cells grow until they do.
POINTS_PER_CELL = 30

#: The largest cell (m) the sparsest block gets.
MAX_CELL = 30.0


def cell_size(points_xy: np.ndarray, cell: float) -> float:
    """`cell` (m), grown where the median cell of that size that holds tie points holds fewer
    than POINTS_PER_CELL of them (at most MAX_CELL)."""
    if not len(points_xy):
        return cell
    _, counts = np.unique(np.floor(points_xy / cell).astype(np.int64), axis=0,
                          return_counts=True)
    grow = np.sqrt(max(1.0, POINTS_PER_CELL / float(np.median(counts))))
    return float(min(MAX_CELL, max(cell, np.ceil(cell * grow))))


def block_terrain(store, points_local: np.ndarray, options) -> tuple:
    """`store` with the terrain under the block's tie points (`points_local`, local frame) as
    faces, and report.json's `terrain` record. `options`: options.TerrainOptions. The source:
    the DTM files of `options.files` (tiles checked against the buildings' feet), else the TIN
    relief of the model files (`store.source`), else the buildings' feet."""
    from pathlib import Path

    from .terrain import building_feet, check_against_feet, feet_terrain, read_dtm, read_relief

    if options.source == "none" or not len(points_local):
        return store, {"source": "none"}
    feet = building_feet(store)
    xy = np.asarray(points_local, float)[:, :2] + store.origin[:2]
    bbox = np.array([xy.min(0) - 2 * options.cell, xy.max(0) + 2 * options.cell])
    warnings: list[str] = []
    terrain = None
    if options.files:
        terrain = read_dtm(options.files, store.crs, bbox, options.sigma)
        warnings += check_against_feet(terrain, feet, options.feet_tolerance)
        if not np.isfinite(terrain.heights).any():
            warnings.append("no DTM tile agrees with the buildings' feet: the terrain comes "
                            "from the model instead")
            terrain = None
    if terrain is None:
        files = [Path(p) for p in str(store.source).split(";") if p and Path(p).is_file()]
        terrain = read_relief(files, store.crs, bbox, options.sigma) if files else None
        if terrain is not None:
            warnings += check_against_feet(terrain, feet, options.feet_tolerance)
            if not np.isfinite(terrain.heights).any():
                terrain = None
    if terrain is None:
        terrain = feet_terrain(store, bbox, options.feet_sigma, options.feet_sigma_growth,
                               feet=feet)
    if terrain is None:
        return store, {"source": "none", "warnings": warnings or ["no building feet to "
                                                                  "build a terrain from"]}
    # The feet terrain covers the whole street, not a band along the facades: a band's
    # pattern of cells would let the coarse search match ground points along the street.
    cell = cell_size(xy, options.cell)
    out = with_terrain_faces(store, terrain, points_local, cell, feet.footprints)
    record = {**terrain.summary(), "num_faces": out.num_faces - store.num_faces,
              "cell_m": cell, "warnings": warnings}
    return out, record


#: A terrain unit whose ground points lie further from it on average than this many of its
#: sigmas does not match the block (flagged `off` in report.json, with a warning).
UNIT_OFF_SIGMAS = 3.0


def terrain_residuals(store, assignment, points: np.ndarray) -> dict:
    """report.json `terrain.residuals`: per terrain unit its assigned tie points and their
    mean and RMS signed distance (m) from the terrain faces; `points` in the order of
    `assignment.point_ids` (local frame)."""
    unit, sigma, names = terrain_units(store)
    if not names or assignment is None:
        return {"num_points": 0, "units": {}}
    face = assignment.face_index
    on = (face >= 0) & (unit[np.maximum(face, 0)] >= 0)
    rows = np.flatnonzero(on)
    d = (np.einsum("ij,ij->i", points[rows], store.normals[face[rows]])
         + store.offsets[face[rows]])
    units = {}
    for k, name in enumerate(names):
        mine = unit[face[rows]] == k
        if mine.any():
            mean = float(np.mean(d[mine]))
            stated = float(np.sqrt(np.mean(sigma[face[rows][mine]] ** 2)))
            units[name[len(TERRAIN_PREFIX):]] = {
                "num_points": int(mine.sum()), "mean_m": mean,
                "rms_m": float(np.sqrt(np.mean(d[mine] ** 2))), "sigma_m": stated,
                # the block sits further from this unit than its sigma explains
                "off": bool(abs(mean) > UNIT_OFF_SIGMAS * stated)}
    off = [name for name, row in units.items() if row["off"]]
    if off:
        logger.warning("terrain: the ground tie points lie further from %s than its sigma "
                       "explains (another height system, a wrong tile?)", ", ".join(off))
    return {"num_points": int(len(rows)),
            "rms_m": float(np.sqrt(np.mean(d ** 2))) if len(rows) else None, "units": units,
            "off_units": off}


def terrain_faces(store, faces: np.ndarray) -> dict[int, tuple[int, float]] | None:
    """{face: (terrain unit, sigma m)} for the terrain faces among `faces` (None: none), for
    the datum's observability (adjust.observability): a unit's points share its offset."""
    unit, sigma, _ = terrain_units(store)
    faces = np.unique(np.asarray(faces, np.int64))
    on = faces[unit[faces] >= 0]
    if not len(on):
        return None
    return {int(f): (int(unit[f]), float(sigma[f])) for f in on}


def terrain_groups(groups: np.ndarray, terrain: dict[int, tuple[int, float]]):
    """`groups` (a face per point) with the terrain faces' points grouped by unit (keys
    -1 - unit, apart from every face), the units' sigmas by key, and the set of those keys."""
    groups = np.asarray(groups, np.int64).copy()
    shared, keys = {}, set()
    for face, (unit, sigma) in terrain.items():
        key = -1 - unit
        groups[groups == face] = key
        keys.add(key)
        shared.setdefault(key, []).append(sigma)
    return groups, {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in shared.items()}, keys
