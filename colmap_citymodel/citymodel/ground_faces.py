"""The terrain near the tie points as planar faces of the plane store (class "TerrainSurface").

The terrain (citymodel.terrain) is cut into square cells of `TerrainOptions.cell` metres; each
cell that holds tie points (or borders one that does), and whose centre is not under a
building's footprint, becomes one face whose corners are the terrain heights averaged over a
cell's width around them (a DTM's own noise per post is smoothed away, its slope and steps of
more than a cell are kept). Neighbouring cells share their corners. The feet terrain's cells
are cut at the pavements' outer edge and around the footprints (`split_pieces`): a piece lies
either where the feet hold the ground or beyond. The assignment and the hybrid adjustment then
treat the cells like model faces: a ground tie point gets the same point-to-plane residual as
a point on a wall.

A terrain's error is mostly one offset per source tile (a DTM tile's height reference, the
feet of one building), not independent per cell: the tie points of all cells of one tile form
one unit (`terrain_face_sigmas`), whose points together count as one observation of that
offset with the terrain's sigma. The feet terrain's road beyond the pavements is one unit of
its own: it lies a kerb below the feet, or none where there is no kerb, and that error is the
same along the whole road (its sigma: the feet's and the kerb's). Within a unit each cell
weighs by how well it knows the unit's height: its points' mean, with the cell's local error
(growing away from the feet), shared by its points. Each terrain face names its unit in its
building id ("terrain:<tile>") and its sigmas in its part id ("sigma=<offset m>/<local m>"),
so every copy of the store (moved vertices, shifted planes) keeps them.
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
#: Between a terrain face's unit sigma and its own local sigma in its part id.
LOCAL_SEPARATOR = "/"
#: The terrain unit of the ground beyond a terrain's band (the feet terrain's road, a kerb
#: below its pavements): how far off the drop is, is one error of all of it.
ROAD_UNIT = "road beyond the pavements"


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


#: Smallest piece (share of a cell's area) a cell split at the terrain's band keeps: a sliver
#: cannot hold the assignment's minimum of points.
MIN_PIECE = 0.1


def split_pieces(terrain: Terrain, quads: np.ndarray, corners: np.ndarray, cell: float,
                 footprints=None) -> tuple[list[np.ndarray], np.ndarray]:
    """The cells `quads` (corner indices into `corners`) as xy rings (counter-clockwise, CRS):
    each cell cut at the edge of `terrain.band` (inside and outside it a piece of its own) and
    without the `footprints`; a cell that needs no cut keeps its four corners. Returns the
    rings and the cell each came from."""
    import shapely
    from shapely.geometry.polygon import orient

    rings, source = [], []
    cut = terrain.band
    for k, quad in enumerate(quads):
        square = shapely.Polygon(corners[quad, :2])
        if cut is None or not shapely.intersects(cut, square) or shapely.contains(cut, square):
            if footprints is None or not shapely.intersects(footprints, square):
                rings.append(corners[quad, :2])
                source.append(k)
                continue
        open_ground = square if footprints is None else square.difference(footprints)
        parts = [open_ground] if cut is None else [open_ground.intersection(cut),
                                                   open_ground.difference(cut)]
        for part in parts:
            for piece in shapely.get_parts(part):
                if piece.geom_type == "Polygon" and piece.area >= MIN_PIECE * cell ** 2:
                    rings.append(np.asarray(orient(piece, 1.0).exterior.coords)[:-1])
                    source.append(k)
    return rings, np.asarray(source, np.int64)


def _ring_faces(terrain: Terrain, rings: list[np.ndarray], cell: float):
    """Per ring: its corners (CRS, the terrain averaged over a cell's width) and its unit
    name, offset sigma and local sigma (at the ring's centre); only rings with heights."""
    import shapely

    smooth = smoothed(terrain, cell)
    xy = np.concatenate(rings) if rings else np.zeros((0, 2))
    z = smooth.grid_height(xy)
    counts = np.array([len(r) for r in rings], np.int64)
    starts = np.r_[0, np.cumsum(counts)[:-1]]
    centres = np.array([shapely.Polygon(r).representative_point().coords[0] for r in rings]
                       ).reshape(-1, 2)
    beyond = np.zeros(len(rings), bool)
    if terrain.band is not None and terrain.band_drop:  # a piece lies wholly in or out
        beyond = ~shapely.contains_xy(terrain.band, centres[:, 0], centres[:, 1])
        z = z - terrain.band_drop * np.repeat(beyond, counts)
    tile = terrain.tile(centres)
    sigma, local = terrain.sigma(centres), terrain.local_sigma(centres)
    out = []
    for k, (start, n) in enumerate(zip(starts, counts)):
        heights = z[start:start + n]
        if tile[k] < 0 or not (np.isfinite(sigma[k]) and np.all(np.isfinite(heights))):
            continue
        name = (terrain.tile_names[tile[k]] if tile[k] < len(terrain.tile_names)
                else str(tile[k]))
        unit_sigma = float(sigma[k])
        if beyond[k]:  # the drop's error is one for all the road, not one per building
            name, unit_sigma = ROAD_UNIT, float(np.hypot(unit_sigma, terrain.band_drop))
        out.append((np.c_[rings[k], heights], TERRAIN_PREFIX + str(name), unit_sigma,
                    float(local[k]) if np.isfinite(local[k]) else 0.0))
    return out


def with_terrain_faces(store, terrain: Terrain, points_local: np.ndarray, cell: float,
                       footprints=None):
    """`store` (citymodel.store.PlaneStore) with the terrain cells near `points_local` (tie
    points, the store's local frame) appended as "TerrainSurface" faces (cut at the terrain's
    band, see split_pieces); the store unchanged when no cell has terrain heights."""
    points_xy = np.asarray(points_local, float)[:, :2] + store.origin[:2]
    split = terrain.band is not None  # the cut drops the footprints, not the cell centres
    cells, _ = terrain_cells(terrain, points_xy, cell, None if split else footprints)
    corner_cells = (cells[:, None, :] + np.array([[0, 0], [1, 0], [1, 1], [0, 1]])).reshape(-1, 2)
    nodes, inverse = np.unique(corner_cells, axis=0, return_inverse=True)
    rings, _ = split_pieces(terrain, inverse.reshape(-1, 4), nodes * float(cell), cell,
                            footprints if split else None)
    faces = _ring_faces(terrain, rings, cell)
    if not faces:
        logger.info("terrain: no terrain under the tie points")
        return store
    return _append_faces(store, faces, cell, terrain.source)


def _append_faces(store, faces: list, cell: float, source: str):
    """`store` with the terrain `faces` ((corners CRS, unit name, sigma, local sigma) each)
    appended; corners within a millimetre are one vertex."""
    corners = np.concatenate([f[0] for f in faces])
    key = np.round(corners, 3)  # the pieces on either side of a step keep their own corners
    _, first, remap = np.unique(key, axis=0, return_index=True, return_inverse=True)
    base = len(store.vertices)
    vertices = np.vstack([store.vertices, corners[first] - store.origin])
    counts = np.array([len(f[0]) for f in faces])
    names = [f[1] for f in faces]
    new = FaceList(base + remap.ravel(), offsets_from_counts(counts),
                   np.arange(len(faces) + 1), [TERRAIN_CLASS] * len(faces), names,
                   [f"{SIGMA_PREFIX}{f[2]:.3f}{LOCAL_SEPARATOR}{f[3]:.3f}" for f in faces],
                   [f"terrain_{k}" for k in range(len(faces))],
                   np.full(len(faces), int(store.faces.lod.max()) if store.num_faces else 2,
                           np.int16))
    planes = compute_planes(vertices, new, extras=False)
    old = store.faces
    merged = FaceList._own(
        np.concatenate([old.ring_vertex, new.ring_vertex]),
        np.concatenate([old.ring_ptr, old.ring_ptr[-1] + new.ring_ptr[1:]]),
        np.concatenate([old.face_ring, old.face_ring[-1] + new.face_ring[1:]]),
        CodedStrings.concatenate([old.semantic, new.semantic]),
        CodedStrings.concatenate([old.building_id, new.building_id]),
        CodedStrings.concatenate([old.part_id, new.part_id]),
        PackedStrings.concatenate([old.gml_id, new.gml_id]),
        np.concatenate([old.lod, new.lod]))
    rms = planes["rms"]
    logger.info("terrain: %d faces of %g m cells near the tie points (%s, %d tile(s)), plane "
                "fit RMS %.3f m", len(faces), cell, source, len(set(names)),
                float(np.mean(rms)))
    return replace(
        store, vertices=vertices, faces=merged,
        centroids=np.vstack([store.centroids, planes["centroids"]]),
        rotations=np.concatenate([store.rotations, planes["rotations"]]),
        areas=np.concatenate([store.areas, planes["areas"]]),
        rms_out_of_plane=np.concatenate([store.rms_out_of_plane, rms]),
        # Terrain cells are planes through smoothed heights: their bend is the terrain's,
        # which the terrain's sigma covers; none is flagged.
        nonplanar=np.concatenate([store.nonplanar, np.zeros(len(faces), bool)]),
        warnings=list(store.warnings), _cache={})


def terrain_mask(store) -> np.ndarray:
    """(F,) bool: the store's terrain faces."""
    return store.faces.semantic.mask(TERRAIN_CLASS)


def terrain_units(store) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Per face of `store`: its terrain unit (-1: not terrain) and the sigma (m; nan: not
    terrain) of its unit's offset; and the units' names."""
    unit, sigma, _, names = terrain_unit_sigmas(store)
    return unit, sigma, names


def terrain_unit_sigmas(store) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """Per face of `store`: its terrain unit (-1: not terrain), the sigma of its unit's
    offset and its own local sigma (m; nan: not terrain); and the units' names."""
    mask = terrain_mask(store)
    unit = np.full(store.num_faces, -1, np.int64)
    sigma = np.full(store.num_faces, np.nan)
    local = np.full(store.num_faces, np.nan)
    if not mask.any():
        return unit, sigma, local, []
    codes = store.faces.building_id.codes
    names = store.faces.building_id.categories
    rows = np.flatnonzero(mask)
    used, unit[rows] = np.unique(codes[rows], return_inverse=True)
    parts = store.faces.part_id
    parsed = np.array([_sigmas_of(p) for p in parts.categories]).reshape(-1, 2)
    sigma[rows] = parsed[parts.codes[rows], 0]
    local[rows] = parsed[parts.codes[rows], 1]
    return unit, sigma, local, [names[c] for c in used]


def _sigmas_of(part: str) -> tuple[float, float]:
    """(offset sigma, local sigma) of a part id "sigma=<m>[/<m>]"; nan when not one."""
    if part.startswith(SIGMA_PREFIX):
        try:
            values = [float(v) for v in part[len(SIGMA_PREFIX):].split(LOCAL_SEPARATOR)]
        except ValueError:
            return np.nan, np.nan
        return values[0], values[1] if len(values) > 1 else 0.0
    return np.nan, np.nan


def unit_weights(face_unit: np.ndarray, counts: np.ndarray, sigma: np.ndarray,
                 local: np.ndarray, sigma_dtp: float) -> tuple[np.ndarray, np.ndarray]:
    """Per terrain face (`face_unit` >= 0, `counts` its points, `sigma` its unit's offset
    sigma, `local` its own sigma): its share of its unit, 1 / (local^2 + sigma_dtp^2 / n)
    normalised over the unit (a cell's points share its local error; without local errors
    the shares are the points'); and its unit's sigma, sqrt(sum share sigma^2 + sum
    share^2 local^2), the offset's and the weighted mean's local error (m)."""
    n = np.maximum(counts, 1e-9)
    precision = 1.0 / (local ** 2 + sigma_dtp ** 2 / n)
    precision = np.where(counts > 0, precision, 0.0)
    units = max(int(face_unit.max()) + 1, 1) if len(face_unit) else 1
    total = np.bincount(face_unit, weights=precision, minlength=units)
    share = precision / np.maximum(total[face_unit], 1e-300)
    var = (np.bincount(face_unit, weights=share * sigma ** 2, minlength=units)
           + np.bincount(face_unit, weights=share ** 2 * local ** 2, minlength=units))
    return share, np.sqrt(var)


def terrain_face_sigmas(store, faces: np.ndarray, rows: np.ndarray, sigmas: np.ndarray,
                        sigma_dtp: float) -> np.ndarray:
    """`sigmas` (the f_dTP sigma of each face of `faces`, adjust.problem.face_sigmas) with
    those of terrain faces replaced by their unit's: a face with n points and share w of its
    unit (`unit_weights`) at sqrt(sigma_dtp^2 + n sigma_u^2 / w), sigma_u its unit's sigma,
    so that a unit weighs as one observation of its offset however many points it has, and
    within it each face by its share. `rows`: the slot in `faces` of each assigned point."""
    if store is None or not len(faces):
        return sigmas
    unit, sigma, local, _ = terrain_unit_sigmas(store)
    face_unit = unit[faces]
    on = face_unit >= 0
    if not on.any():
        return sigmas
    counts = np.bincount(rows, minlength=len(faces)).astype(float)
    share, unit_sigma = unit_weights(face_unit[on], counts[on], sigma[faces][on],
                                     local[faces][on], sigma_dtp)
    out = np.array(sigmas, dtype=float)
    out[on] = np.sqrt(sigma_dtp ** 2 + counts[on] * unit_sigma[face_unit[on]] ** 2
                      / np.maximum(share, 1e-12))
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


def block_terrain(store, points_local: np.ndarray, options, checked: bool = True) -> tuple:
    """`store` with the terrain under the block's tie points (`points_local`, local frame) as
    faces, and report.json's `terrain` record. `options`: options.TerrainOptions. The source:
    the DTM files of `options.files`, else the TIN relief of the model files (`store.source`),
    else the buildings' feet. With `checked`, each source's units (tiles, buildings) are
    checked against the ground's tie points and the buildings' feet first
    (citymodel.terrain_check): the tie points must lie on the block as the model placed it
    (after the coarse search), not as GNSS did (metres off, and along a straight line turned
    about it)."""
    from pathlib import Path

    from .terrain import building_feet, feet_terrain, read_dtm, read_model_ground, read_relief

    if options.source == "none" or not len(points_local):
        return store, {"source": "none"}
    files = [Path(p) for p in str(store.source).split(";") if p and Path(p).is_file()]
    ground = read_model_ground(files, store.crs) if files and not options.files else None
    feet = building_feet(store, ground.intersections if ground is not None else None)
    points = np.asarray(points_local, float) + store.origin
    bbox = np.array([points[:, :2].min(0) - 2 * options.cell,
                     points[:, :2].max(0) + 2 * options.cell])
    warnings: list[str] = []
    terrain = None
    if options.files:
        terrain = read_dtm(options.files, store.crs, bbox, options.sigma)
    elif files:
        terrain = read_relief(files, store.crs, bbox, options.sigma, ground=ground)
    if terrain is not None:
        if checked:
            warnings += checked_tiles(terrain, points, feet, options)
        if not np.isfinite(terrain.heights).any():
            warnings.append(f"no {'DTM' if options.files else 'relief'} tile agrees with the "
                            "ground's tie points and the buildings' feet: the terrain comes "
                            "from the buildings' feet instead")
            terrain = None
    if terrain is None:
        terrain = (checked_feet_terrain(store, bbox, feet, points, options, warnings)
                   if checked else feet_terrain(store, bbox, options.feet_sigma,
                                                options.feet_sigma_growth, feet=feet))
    if terrain is None:
        return store, {"source": "none", "warnings": warnings or ["no building feet to "
                                                                  "build a terrain from"]}
    # The feet terrain covers the whole street, not a band along the facades: a band's
    # pattern of cells would let the coarse search match ground points along the street.
    cell = cell_size(points[:, :2], options.cell)
    out = with_terrain_faces(store, terrain, points_local, cell, feet.footprints)
    record = {**terrain.summary(), "num_faces": out.num_faces - store.num_faces,
              "cell_m": cell, "warnings": warnings, "units_dropped": len(warnings)}
    return out, record


def _open_ground(points: np.ndarray, footprints) -> np.ndarray:
    """(n,) bool: the tie points (CRS) whose xy lies outside the buildings' footprints grown
    by terrain_check.FACADE_BAND (the facades' own points stand there at every height)."""
    import shapely

    from .terrain_check import FACADE_BAND

    if footprints is None or footprints.is_empty or not len(points):
        return np.ones(len(points), bool)
    return ~shapely.contains_xy(footprints.buffer(FACADE_BAND), points[:, 0], points[:, 1])


def checked_tiles(terrain: Terrain, points: np.ndarray, feet, options) -> list[str]:
    """Drops (sets to nan) the tiles of a DTM or relief `terrain` that the ground's tie points
    (`points`, CRS) or the buildings' feet contradict (citymodel.terrain_check): a tile off
    the other tiles by more than its sigma allows, or off the feet of the buildings it covers
    (a building whose own feet are metres off does not count against it). `options`:
    TerrainOptions. Returns one warning per dropped tile."""
    from .terrain_check import consensus, feet_offset, ground_offsets, off_feet

    open_ground = points[_open_ground(points, feet.footprints)]
    above = open_ground[:, 2] - terrain.height(open_ground[:, :2])
    tiles = len(terrain.tile_names)
    offsets, counts = ground_offsets(above, terrain.tile(open_ground[:, :2]), tiles)
    found = consensus(offsets, counts, np.full(tiles, options.sigma))
    warnings, drop = [], found.contradicts.copy()
    for k in np.flatnonzero(found.contradicts):
        warnings.append(f"terrain tile {terrain.tile_names[k]} stands {-offsets[k]:+.2f} m off "
                        f"the ground's tie points, {found.consensus - offsets[k]:+.2f} m off "
                        "the other tiles: left out (a wrong tile or another height system?)")
    on_feet = terrain.tile(feet.points[:, :2]) if len(feet.points) else np.zeros(0, int)
    differences = (terrain.height(feet.points[:, :2]) - feet.points[:, 2] if len(feet.points)
                   else np.zeros(0))
    for k in range(tiles):
        mine = (on_feet == k) & np.isfinite(differences)
        offset, sigma = feet_offset(differences[mine], feet.building[mine],
                                    len(feet.building_ids), options.feet_sigma,
                                    options.feet_spread)
        if not drop[k] and off_feet(offset, sigma, options.sigma):
            drop[k] = True
            warnings.append(f"terrain tile {terrain.tile_names[k]} stands {offset:+.2f} m off "
                            f"the buildings' feet it covers (their sigma {sigma:.2f} m): left "
                            "out (another height system or a wrong tile?)")
    _drop_tiles(terrain, drop, offsets, counts)
    for message in warnings:
        logger.warning(message)
    return warnings


def _drop_tiles(terrain: Terrain, drop: np.ndarray, offsets: np.ndarray, counts: np.ndarray
                ) -> None:
    """`terrain` without the tiles `drop` marks; a note on each kept tile's ground points."""
    for k in np.flatnonzero(drop):
        gone = terrain.tiles == k
        terrain.heights[gone] = np.nan
        terrain.sigmas[gone] = np.nan
        terrain.tiles[gone] = -1
    for k in np.flatnonzero(~drop & (counts > 0)):
        terrain.notes.append(f"tile {terrain.tile_names[k]}: the ground's tie points "
                             f"{offsets[k]:+.2f} m above it ({counts[k]} points)")


def checked_feet_terrain(store, bbox: np.ndarray, feet, points: np.ndarray, options,
                         warnings: list[str]) -> Terrain | None:
    """The terrain from the buildings' feet (citymodel.terrain.feet_terrain) without the
    buildings whose feet the ground's tie points beside them and the other buildings' feet
    contradict (named in `warnings`); a building's ground height trusted to
    `options.feet_sigma` where enough neighbours checked it, else to `options.feet_spread`
    (LoD2 takes walls down to the lowest ground of a footprint: metres below a street on a
    slope, a ramp, a courtyard)."""
    from .terrain import feet_terrain, without_buildings
    from .terrain_check import consensus, ground_offsets

    if not len(feet.points):
        return None
    from scipy.spatial import cKDTree

    open_ground = points[_open_ground(points, feet.footprints)]
    distance, nearest = cKDTree(feet.points[:, :2]).query(open_ground[:, :2])
    near = distance < options.cell + FEET_CHECK_REACH
    above = np.where(near, open_ground[:, 2] - feet.points[nearest, 2], np.nan)
    count = len(feet.building_ids)
    offsets, counts = ground_offsets(above, np.where(near, feet.building[nearest], -1), count)
    found = consensus(offsets, counts, np.full(count, options.feet_sigma))
    for k in np.flatnonzero(found.contradicts):
        off = found.consensus - offsets[k]  # its feet's height off the ground beside it
        warnings.append(f"the feet of building {feet.building_ids[k]} stand {abs(off):.2f} m "
                        f"{'below' if off < 0 else 'above'} the ground's tie points beside it, "
                        "where the other buildings' feet have them (walls taken down to the "
                        "lowest ground of its footprint?): left out of the terrain")
        logger.warning(warnings[-1])
    sigmas = np.where(found.checked, options.feet_sigma, options.feet_spread)
    return feet_terrain(store, bbox, sigmas, options.feet_sigma_growth,
                        feet=without_buildings(feet, np.flatnonzero(found.contradicts)))


#: Metres beyond a terrain cell from a building's feet within which the ground's tie points
#: are compared with its feet: the pavement and the road in front of it.
FEET_CHECK_REACH = 3.0


#: A terrain unit whose ground points lie further from it on average than this many of its
#: sigmas does not match the block (flagged `off` in report.json, with a warning).
UNIT_OFF_SIGMAS = 3.0


#: A tie point's own scatter about its face (m), options.AdjustmentOptions.sigma_dtp's
#: default: weighs a cell's points against its local error where no adjustment gives it.
POINT_SIGMA = 0.20


def _unit_shares(store, face_of_point: np.ndarray, sigma_dtp: float = POINT_SIGMA):
    """For the terrain faces among `face_of_point` (a face per point): the faces, their
    units, shares and their units' sigmas (unit_weights); None without terrain faces."""
    unit, sigma, local, names = terrain_unit_sigmas(store)
    faces, counts = np.unique(np.asarray(face_of_point, np.int64), return_counts=True)
    keep = (faces >= 0) & (unit[np.maximum(faces, 0)] >= 0)
    faces, counts = faces[keep], counts[keep]
    if not len(faces):
        return None
    share, unit_sigma = unit_weights(unit[faces], counts.astype(float), sigma[faces],
                                     local[faces], sigma_dtp)
    return faces, unit[faces], share, unit_sigma, names


def terrain_residuals(store, assignment, points: np.ndarray) -> dict:
    """report.json `terrain.residuals`: per terrain unit its assigned tie points, their mean
    signed distance (m) from the terrain faces as the adjustment weighs them (each face by
    its share, `unit_weights`), their RMS distance, and the unit's sigma; `points` in the
    order of `assignment.point_ids` (local frame)."""
    found = None if assignment is None else _unit_shares(store, assignment.face_index)
    if found is None:
        return {"num_points": 0, "units": {}}
    faces, face_unit, share, unit_sigma, names = found
    face = assignment.face_index
    rows = np.flatnonzero(np.isin(face, faces))
    slot = np.searchsorted(faces, face[rows])
    d = (np.einsum("ij,ij->i", points[rows], store.normals[face[rows]])
         + store.offsets[face[rows]])
    face_mean = np.bincount(slot, weights=d, minlength=len(faces)) / np.maximum(
        np.bincount(slot, minlength=len(faces)), 1)
    units = {}
    for k, name in enumerate(names):
        mine = face_unit[slot] == k
        if mine.any():
            mean = float(np.sum((share * face_mean)[face_unit == k]))
            stated = float(unit_sigma[k])
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
    """{face: (terrain unit, sigma m)} for the terrain faces among `faces` (a face per
    point; None: none), for the datum's observability (adjust.observability): a unit's
    points share its offset, whose sigma (`unit_weights`) is that of the unit's weighted
    mean."""
    found = _unit_shares(store, faces)
    if found is None:
        return None
    on, face_unit, _, unit_sigma, _ = found
    return {int(f): (int(u), float(unit_sigma[u])) for f, u in zip(on, face_unit)}


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
