"""The ground beside the buildings: a terrain surface the street-level and aerial tie points on
road, pavement and open ground can be held to.

A LOD2 city model holds walls and roofs; the ground between the buildings is not in it. This
module builds a `Terrain` (a regular height grid in the model CRS with a sigma and a tile id
per node) from, in order of preference:

1. DTM rasters (`read_dtm`): GeoTIFF / Cloud-Optimised GeoTIFF tiles in any CRS, read with
   rasterio, only the block's window of each, reprojected onto the model CRS grid, nodata left
   out, tiles mosaicked (each node keeps the tile it came from: one random offset per tile);
2. relief in the city model files (`read_relief`): CityGML `dem:TINRelief` triangles and
   CityJSON `TINRelief` objects;
3. the buildings' own feet (`feet_terrain`): the lowest edges of the walls and the ground
   surfaces, interpolated over the open ground between them. Their error is one offset per
   building (its ground height) plus a local error that grows away from the feet: beyond a
   pavement's width the road lies a kerb lower and falls to its gutter.

Each source's units (a DTM's tiles, the buildings' feet) are checked against the ground's tie
points before they are used (citymodel.terrain_check): a unit the ground and the other units
contradict (a wrong tile, a building whose walls reach metres below its street) is dropped
with a warning, not followed. citymodel.ground_faces turns the terrain near the tie points
into planar faces of the plane store.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .archives import model_suffix, open_model, read_model_text
from .raw_model import CRSInfo

logger = logging.getLogger(__name__)

#: Spacing (m) of the grid every source is resampled onto: a DGM1's own spacing.
GRID_SPACING = 1.0

#: Metres by which the block's area is grown before a raster window is read.
READ_MARGIN = 20.0


@dataclass
class Terrain:
    """Heights on a regular grid in the model CRS: node (i, j) lies at x = x0 + j * spacing,
    y = y0 + i * spacing; nan where no source covers it."""

    source: str  # "dtm", "relief" or "building_feet"
    x0: float
    y0: float
    spacing: float
    heights: np.ndarray  # (ny, nx) CRS heights (m), nan: no data
    sigmas: np.ndarray  # (ny, nx) stated sigma of each height (m)
    tiles: np.ndarray  # (ny, nx) int32 index into tile_names, -1: no data
    tile_names: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    # (ny, nx) each height's own error beyond its tile's offset (m); None: none (a DTM's
    # noise per post, which the cells average away)
    local_sigmas: np.ndarray | None = None
    # shapely geometry (CRS xy) along whose edge the ground steps (the feet terrain: the
    # footprints with their pavements); the cells are split there; None: not split
    band: object = None
    # metres the ground lies below `heights` outside `band` (the feet terrain: a kerb); how
    # far off that is, is one error of all the ground there (citymodel.ground_faces: the road
    # is one terrain unit)
    band_drop: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.heights.shape

    def _fractional(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return (xy[:, 1] - self.y0) / self.spacing, (xy[:, 0] - self.x0) / self.spacing

    def height(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bilinear heights at CRS `xy` (N, 2), less `band_drop` outside the band; nan
        outside or next to missing data."""
        z = self.grid_height(xy)
        if self.band is not None and self.band_drop:
            import shapely

            xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
            z = z - self.band_drop * ~shapely.contains_xy(self.band, xy[:, 0], xy[:, 1])
        return z

    def grid_height(self, xy: np.ndarray) -> np.ndarray:
        """(N,) bilinear heights of the grid at CRS `xy` (N, 2) (no band drop); nan outside
        or next to missing data."""
        fi, fj = self._fractional(xy)
        ny, nx = self.shape
        i0 = np.clip(np.floor(fi).astype(np.int64), 0, max(ny - 2, 0))
        j0 = np.clip(np.floor(fj).astype(np.int64), 0, max(nx - 2, 0))
        inside = (fi >= 0) & (fi <= ny - 1) & (fj >= 0) & (fj <= nx - 1) & (ny > 1) & (nx > 1)
        i1, j1 = np.minimum(i0 + 1, ny - 1), np.minimum(j0 + 1, nx - 1)
        u, v = fj - j0, fi - i0
        h = self.heights
        z = ((1 - u) * (1 - v) * h[i0, j0] + u * (1 - v) * h[i0, j1]
             + (1 - u) * v * h[i1, j0] + u * v * h[i1, j1])
        return np.where(inside, z, np.nan)

    def normal(self, xy: np.ndarray) -> np.ndarray:
        """(N, 3) upward unit normals from the height differences a spacing around `xy`."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        d = self.spacing
        gx = (self.height(xy + [d, 0]) - self.height(xy - [d, 0])) / (2 * d)
        gy = (self.height(xy + [0, d]) - self.height(xy - [0, d])) / (2 * d)
        n = np.stack([-gx, -gy, np.ones(len(xy))], axis=1)
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    def _nearest(self, values: np.ndarray, xy: np.ndarray, fill):
        fi, fj = self._fractional(xy)
        i, j = np.round(fi).astype(np.int64), np.round(fj).astype(np.int64)
        ny, nx = self.shape
        ok = (i >= 0) & (i < ny) & (j >= 0) & (j < nx)
        out = np.full(len(fi), fill, dtype=values.dtype)
        out[ok] = values[i[ok], j[ok]]
        return out

    def sigma(self, xy: np.ndarray) -> np.ndarray:
        """(N,) the stated sigma (m) of the offset of the tile at `xy` (nearest node; nan
        outside)."""
        return self._nearest(self.sigmas, xy, np.nan)

    def local_sigma(self, xy: np.ndarray) -> np.ndarray:
        """(N,) the sigma (m) of the height at `xy` beyond its tile's offset (nearest node;
        0 for a terrain without local errors, nan outside). The band drop's own error is not
        in it: it is one error of all the ground beyond the band, not one per place."""
        if self.local_sigmas is None:
            return np.where(np.isfinite(self.sigma(xy)), 0.0, np.nan)
        return self._nearest(self.local_sigmas, xy, np.nan)

    def tile(self, xy: np.ndarray) -> np.ndarray:
        """(N,) the tile index at `xy` (nearest node; -1 outside or without data)."""
        return self._nearest(self.tiles, xy, -1)

    def node_xy(self) -> tuple[np.ndarray, np.ndarray]:
        ny, nx = self.shape
        return (self.x0 + self.spacing * np.arange(nx), self.y0 + self.spacing * np.arange(ny))

    def summary(self) -> dict:
        """report.json `terrain.surface`: source, tiles, grid and coverage."""
        valid = np.isfinite(self.heights)
        return {"source": self.source, "tiles": list(self.tile_names),
                "grid_spacing_m": self.spacing, "grid_shape": list(self.shape),
                "covered_share": float(valid.mean()) if valid.size else 0.0,
                "sigma_m": float(np.nanmedian(self.sigmas[valid])) if valid.any() else None,
                "local_sigma_max_m": (float(np.nanmax(self.local_sigmas[valid]))
                                      + self.band_drop
                                      if valid.any() and self.local_sigmas is not None
                                      else 0.0),
                "band_drop_m": self.band_drop, "notes": list(self.notes)}


def empty_grid(bbox_xy: np.ndarray, spacing: float = GRID_SPACING):
    """(x0, y0, nx, ny) of the grid of `spacing` covering bbox [[xmin, ymin], [xmax, ymax]]."""
    lo = np.floor(np.asarray(bbox_xy[0], float) / spacing) * spacing
    hi = np.ceil(np.asarray(bbox_xy[1], float) / spacing) * spacing
    nx, ny = (np.round((hi - lo) / spacing).astype(int) + 1)
    return float(lo[0]), float(lo[1]), int(nx), int(ny)


# -- 1. DTM rasters ------------------------------------------------------------------------------


def _raster_crs(crs: CRSInfo):
    """The model CRS's horizontal part as rasterio takes it."""
    from rasterio.crs import CRS

    from .crs import _horizontal

    return CRS.from_wkt(_horizontal(crs).to_wkt())


def read_dtm(paths, crs: CRSInfo, bbox_xy: np.ndarray, sigma: float,
             spacing: float = GRID_SPACING) -> Terrain:
    """The DTM tiles `paths` resampled (bilinear) onto the model CRS grid over `bbox_xy`
    ([[xmin, ymin], [xmax, ymax]], model CRS, grown by READ_MARGIN); only each file's window
    over that area is read. Heights are taken as in the model's height system. Nodes no tile
    covers stay nan; where tiles overlap the first file given wins. Unreadable files and files
    without a CRS are an InputError naming the file."""
    bbox = np.asarray(bbox_xy, float) + [[-READ_MARGIN, -READ_MARGIN], [READ_MARGIN, READ_MARGIN]]
    x0, y0, nx, ny = empty_grid(bbox, spacing)
    heights = np.full((ny, nx), np.nan)
    tiles = np.full((ny, nx), -1, np.int32)
    names: list[str] = []
    warped = [(path, _warp_tile(path, crs, x0, y0, nx, ny, spacing))
              for path in [Path(p) for p in paths]]
    # Bilinear first; a node within half a post of a tile's edge (a seam between tiles) has
    # no bilinear value, and takes the nearest post of whichever tile has one.
    for k in (0, 1):
        for path, pair in warped:
            if pair is None:
                continue
            fill = np.isnan(heights) & np.isfinite(pair[k])
            if fill.any():
                if path.name not in names:
                    names.append(path.name)
                heights[fill] = pair[k][fill]
                tiles[fill] = names.index(path.name)
    if not names:
        raise InputError("no DTM tile covers the block's area "
                         f"({np.round(bbox.ravel(), 1).tolist()} in {crs.label}); check the "
                         "DTM's extent and CRS", Path(list(paths)[0]))
    sigmas = np.where(np.isfinite(heights), float(sigma), np.nan)
    logger.info("terrain: DTM from %d of %d tile(s), %.0f %% of %d x %d m covered", len(names),
                len(list(paths)), 100 * np.isfinite(heights).mean(), nx * spacing, ny * spacing)
    return Terrain("dtm", x0, y0, spacing, heights, sigmas, tiles, names)


def _warp_tile(path: Path, crs: CRSInfo, x0, y0, nx, ny, spacing) -> tuple | None:
    """One tile's heights on the grid, resampled bilinear and nearest (nan where it has
    none), or None when it misses the grid."""
    import rasterio
    from rasterio.errors import RasterioIOError
    from rasterio.transform import Affine
    from rasterio.warp import Resampling, reproject, transform_bounds
    from rasterio.windows import from_bounds

    if not path.is_file():
        raise InputError("DTM file does not exist", path)
    try:
        src = rasterio.open(path)
    except RasterioIOError as error:
        raise InputError(f"not a readable raster: {error}", path) from None
    with src:
        if src.crs is None:
            raise InputError("the DTM names no CRS (a GeoTIFF needs its georeference)", path)
        dst_crs = _raster_crs(crs)
        half = 0.5 * spacing
        bounds = (x0 - half, y0 - half, x0 + (nx - 0.5) * spacing, y0 + (ny - 0.5) * spacing)
        left, bottom, right, top = transform_bounds(dst_crs, src.crs, *bounds, densify_pts=21)
        s = src.bounds
        if right < s.left or left > s.right or top < s.bottom or bottom > s.top:
            logger.info("terrain: %s lies outside the block's area", path.name)
            return None
        found = from_bounds(max(left, s.left), max(bottom, s.bottom), min(right, s.right),
                            min(top, s.top), src.transform)
        # Whole posts, one more on every side: the resampling needs the posts around a node.
        col0 = max(int(np.floor(found.col_off)) - 1, 0)
        row0 = max(int(np.floor(found.row_off)) - 1, 0)
        col1 = min(int(np.ceil(found.col_off + found.width)) + 1, src.width)
        row1 = min(int(np.ceil(found.row_off + found.height)) + 1, src.height)
        window = rasterio.windows.Window(col0, row0, col1 - col0, row1 - row0)
        data = src.read(1, window=window, out_dtype="float64", masked=True)
        values = np.where(np.ma.getmaskarray(data), np.nan, np.ma.getdata(data))
        # North-up destination grid: row 0 at the top (largest y); flipped below.
        transform = Affine(spacing, 0, x0 - half, 0, -spacing, y0 + (ny - 0.5) * spacing)
        out = []
        for resampling in (Resampling.bilinear, Resampling.nearest):
            grid = np.full((ny, nx), np.nan)
            reproject(values, grid, src_transform=src.window_transform(window),
                      src_crs=src.crs, src_nodata=np.nan, dst_transform=transform,
                      dst_crs=dst_crs, dst_nodata=np.nan, resampling=resampling)
            out.append(grid[::-1])
    return tuple(out)


def terrain_options(options, terrain, sigma) -> None:
    """Sets options.TerrainOptions `options` from the command line: `terrain` ["none"] or DTM
    files (each opened here, so that a missing or unreadable file fails before any work),
    `sigma` the DTM's stated accuracy (m)."""
    if sigma is not None:
        if not (np.isfinite(sigma) and sigma > 0):
            raise InputError(f"--terrain_sigma must be a positive number of metres, got {sigma}")
        options.sigma = float(sigma)
    if terrain is None:
        return
    terrain = [str(t) for t in np.atleast_1d(terrain)]
    if [t.lower() for t in terrain] == ["none"]:
        options.source, options.files = "none", ()
        return
    for path in map(Path, terrain):
        check_dtm_file(path)
    options.source, options.files = "auto", tuple(terrain)


def check_dtm_file(path: Path) -> None:
    """InputError naming `path` unless it is a raster with a CRS and one band of heights."""
    import rasterio
    from rasterio.errors import RasterioIOError

    if not path.is_file():
        raise InputError("DTM file does not exist", path)
    try:
        with rasterio.open(path) as src:
            if src.crs is None:
                raise InputError("the DTM names no CRS (a GeoTIFF needs its georeference)",
                                 path)
            if src.count < 1:
                raise InputError("the DTM raster has no band", path)
    except RasterioIOError as error:
        raise InputError(f"not a readable raster: {error}", path) from None


# -- 2. relief in the city model -----------------------------------------------------------------


@dataclass
class ModelGround:
    """What the city model files say of the ground (model CRS): TIN relief triangles, and the
    lines where each building meets the terrain (CityGML `lod1-4TerrainIntersection`)."""

    triangles: np.ndarray  # (T, 3, 3)
    intersections: dict[str, np.ndarray]  # building id -> (K, 3) points along its lines
    names: list[str]  # the files


def read_model_ground(paths, crs: CRSInfo) -> ModelGround:
    """The relief triangles and terrain intersections of the city model files `paths`, in
    `crs` (reprojected from the CRS a file names)."""
    from .crs import reproject_points, same_crs

    triangles, lines = [], {}
    paths = [Path(p) for p in np.atleast_1d(paths)]
    for path in paths:
        if model_suffix(path) in (".json", ".cityjson", ".jsonl"):
            found, file_crs = _cityjson_relief(path)
            found_lines = {}
        else:
            found, found_lines, file_crs = _citygml_ground(path)
        other = file_crs is not None and not same_crs(file_crs, crs)
        if len(found):
            triangles.append(reproject_points(found.reshape(-1, 3), file_crs, crs).reshape(
                -1, 3, 3) if other else found)
        for building, points in found_lines.items():
            points = reproject_points(points, file_crs, crs) if other else points
            lines[building] = np.vstack([lines[building], points]) if building in lines \
                else points
    return ModelGround(np.concatenate(triangles) if triangles else np.zeros((0, 3, 3)), lines,
                       [p.name for p in paths])


def read_relief(paths, crs: CRSInfo, bbox_xy: np.ndarray, sigma: float,
                spacing: float = GRID_SPACING, ground: ModelGround | None = None
                ) -> Terrain | None:
    """The TIN relief of the city model files (CityGML `dem:TINRelief`, CityJSON
    `TINRelief`) interpolated onto the grid over `bbox_xy`; None when the files hold none.
    `ground`: the files' read_model_ground, when read already."""
    from scipy.interpolate import LinearNDInterpolator

    ground = ground if ground is not None else read_model_ground(paths, crs)
    if not len(ground.triangles):
        return None
    points = np.unique(ground.triangles.reshape(-1, 3), axis=0)
    bbox = np.asarray(bbox_xy, float) + [[-READ_MARGIN, -READ_MARGIN], [READ_MARGIN, READ_MARGIN]]
    x0, y0, nx, ny = empty_grid(bbox, spacing)
    near = np.all((points[:, :2] >= bbox[0] - 50) & (points[:, :2] <= bbox[1] + 50), axis=1)
    if np.count_nonzero(near) < 3:
        return None
    gx, gy = np.meshgrid(x0 + spacing * np.arange(nx), y0 + spacing * np.arange(ny))
    heights = LinearNDInterpolator(points[near, :2], points[near, 2])(gx, gy)
    if not np.isfinite(heights).any():
        return None
    sigmas = np.where(np.isfinite(heights), float(sigma), np.nan)
    tiles = np.where(np.isfinite(heights), 0, -1).astype(np.int32)
    logger.info("terrain: TIN relief of the city model, %d triangles", len(ground.triangles))
    return Terrain("relief", x0, y0, spacing, heights, sigmas, tiles, ground.names[:1])


def _citygml_ground(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray], CRSInfo | None]:
    """(T, 3, 3) relief triangles, {building id: (K, 3) terrain intersection points} of one
    CityGML file, and the CRS it names."""
    from lxml import etree

    from .crs import resolve_crs

    triangles, lines, buildings, srs = [], {}, [], None
    with open_model(path) as source:
        for event, element in etree.iterparse(source, events=("start", "end"), huge_tree=True):
            if not isinstance(element.tag, str):
                continue
            name = etree.QName(element).localname
            if name == "Building":
                if event == "start":
                    buildings.append(next((v for k, v in element.attrib.items()
                                           if k.endswith("}id")), ""))
                else:
                    buildings.pop()
                continue
            if event != "end":
                continue
            if srs is None and element.get("srsName"):
                srs = element.get("srsName")
            if name == "TINRelief":
                for ring in element.iter("{*}LinearRing"):
                    coords = _ring_coordinates(ring)
                    if len(coords) >= 3:
                        triangles.append(coords[:3])
                element.clear()
            elif name.endswith("TerrainIntersection") and buildings:
                found = [_ring_coordinates(curve) for curve in element.iter("{*}LineString")]
                found = [c for c in found if len(c)]
                if found:
                    lines.setdefault(buildings[0], []).extend(found)
                element.clear()
    crs = resolve_crs(srs, path=path) if srs else None
    return (np.array(triangles, float).reshape(-1, 3, 3),
            {b: np.vstack(c) for b, c in lines.items()}, crs)


def _ring_coordinates(ring) -> np.ndarray:
    pos_list = ring.find("{*}posList")
    if pos_list is not None and pos_list.text:
        values = np.array(pos_list.text.split(), float)
    else:
        values = np.array([v for p in ring.iter("{*}pos") for v in (p.text or "").split()], float)
    return values.reshape(-1, 3) if len(values) % 3 == 0 else np.zeros((0, 3))


def _cityjson_relief(path: Path) -> tuple[np.ndarray, CRSInfo | None]:
    import json

    from .crs import resolve_crs

    try:
        doc = json.loads(read_model_text(path))
    except (OSError, ValueError) as error:
        raise InputError(f"not a readable CityJSON file: {error}", path) from None
    transform = doc.get("transform", {})
    scale = np.asarray(transform.get("scale", [1, 1, 1]), float)
    translate = np.asarray(transform.get("translate", [0, 0, 0]), float)
    vertices = np.asarray(doc.get("vertices", []), float).reshape(-1, 3) * scale + translate
    triangles = []
    for obj in doc.get("CityObjects", {}).values():
        if obj.get("type") != "TINRelief":
            continue
        for geometry in obj.get("geometry", []):
            for surface in geometry.get("boundaries", []):
                ring = surface[0] if surface and isinstance(surface[0], list) else surface
                if len(ring) >= 3:
                    triangles.append(vertices[np.asarray(ring[:3], np.int64)])
    srs = doc.get("metadata", {}).get("referenceSystem")
    crs = resolve_crs(srs, path=path) if srs else None
    return np.array(triangles, float).reshape(-1, 3, 3), crs


# -- 3. the buildings' feet ----------------------------------------------------------------------


@dataclass
class Feet:
    """Where the buildings meet the ground: points (CRS) along the walls' lowest edges and the
    ground surfaces' rings, each with its building's index; the footprints (shapely, CRS xy)."""

    points: np.ndarray  # (K, 3)
    building: np.ndarray  # (K,) int64
    building_ids: list[str]
    footprints: object  # shapely geometry, the union of the footprints


#: Spacing (m) of the foot points along the lowest edges.
FOOT_SPACING = 2.0

#: A wall vertex within this height (m) of its face's lowest vertex lies on its lowest edge.
LOWEST_EDGE = 0.05

#: A foot point lies within this distance (m) of the footprints' outline.
FOOT_OUTLINE = 0.3


def building_feet(store, intersections: dict[str, np.ndarray] | None = None) -> Feet:
    """The feet of the buildings of `store` (citymodel.store.PlaneStore): a building's terrain
    intersection lines where the model has them (`intersections`, model CRS, by building
    id: the terrain along its walls, where a wall reaches down to the lowest ground around
    it), else the lowest edges of its walls on the footprints' outline and its ground
    surfaces."""
    import shapely

    walls = store.faces.semantic.mask("WallSurface")
    grounds = store.faces.semantic.mask("GroundSurface")
    points, owner, rings = [], [], []
    codes = store.faces.building_id.codes
    for f in np.flatnonzero(walls | grounds):
        ring = store.vertices[store.faces[int(f)].exterior]
        if grounds[f]:
            low = ring
            if len(ring) >= 3:
                rings.append(shapely.Polygon(ring[:, :2]).buffer(0))
        else:
            low = ring[ring[:, 2] <= ring[:, 2].min() + LOWEST_EDGE]
        dense = _densify(low) if grounds[f] else _densify_edge(low)
        points.append(dense)
        owner.append(np.full(len(dense), codes[f], np.int64))
    if not points:
        return Feet(np.zeros((0, 3)), np.zeros(0, np.int64), [], shapely.Polygon())
    if not rings:  # no ground surfaces: the roofs' outlines stand for the footprints
        for f in np.flatnonzero(store.faces.semantic.mask("RoofSurface")):
            ring = store.vertices[store.faces[int(f)].exterior]
            if len(ring) >= 3:
                rings.append(shapely.Polygon(ring[:, :2]).buffer(0))
    footprints = shapely.unary_union(rings) if rings else shapely.Polygon()
    pts, owner = np.concatenate(points), np.concatenate(owner)
    if not footprints.is_empty:
        # A wall standing on a lower roof (a set-back storey, a tower on its building) has
        # its lowest edge inside the footprint, above the ground: only the outline's count.
        edge = shapely.distance(footprints.boundary, shapely.points(pts[:, :2]))
        pts, owner = pts[edge < FOOT_OUTLINE], owner[edge < FOOT_OUTLINE]
    ids = list(store.faces.building_id.categories)
    pts, owner = _with_intersections(pts + store.origin, owner, ids, intersections or {})
    return Feet(pts, owner, ids, shapely.transform(footprints, lambda xy: xy + store.origin[:2]))


def _with_intersections(points: np.ndarray, owner: np.ndarray, ids: list[str],
                        intersections: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The foot `points` (CRS) of `owner` (index into `ids`), those of each building with
    terrain intersection lines replaced by them."""
    index = {b: k for k, b in enumerate(ids)}
    found = [(index[b], np.asarray(line, float).reshape(-1, 3))
             for b, line in intersections.items() if b in index and len(line)]
    if not found:
        return points, owner
    replaced = np.isin(owner, [k for k, _ in found])
    logger.info("terrain: the feet of %d building(s) from their terrain intersection lines",
                len(found))
    return (np.vstack([points[~replaced]] + [line for _, line in found]),
            np.concatenate([owner[~replaced]] + [np.full(len(line), k, np.int64)
                                                 for k, line in found]))


def _densify(ring: np.ndarray) -> np.ndarray:
    closed = np.vstack([ring, ring[:1]])
    return np.concatenate([_densify_edge(closed[k:k + 2]) for k in range(len(ring))])


def _densify_edge(points: np.ndarray) -> np.ndarray:
    """The points and, between the two furthest apart, one every FOOT_SPACING."""
    if len(points) < 2:
        return points
    d = np.linalg.norm(points[:, None, :2] - points[None, :, :2], axis=2)
    a, b = np.unravel_index(np.argmax(d), d.shape)
    n = int(np.ceil(d[a, b] / FOOT_SPACING))
    t = np.linspace(0.0, 1.0, n + 1)[:, None]
    return np.vstack([points, points[a] + t * (points[b] - points[a])])


#: Width (m) of the pavement along a facade: within it the ground lies at the feet's height
#: (falling a few centimetres to the kerb); the feet terrain's cells are split at its edge.
FEET_REACH = 3.0

#: Height (m) of a kerb: beyond the pavement the road lies about this much below the feet
#: (city kerbs stand 0.10-0.18 m). The feet do not show it: the feet terrain puts the ground
#: beyond its pavements this much lower. A square or a courtyard has no kerb, so the drop may
#: be off by as much as itself, and by the same everywhere: all the ground beyond the
#: pavements is one terrain unit whose offset sigma adds the kerb's (citymodel.ground_faces).
KERB = 0.15


def feet_terrain(store, bbox_xy: np.ndarray, sigma, growth: float,
                 spacing: float = GRID_SPACING, feet: Feet | None = None,
                 reach: float = FEET_REACH, kerb: float = KERB) -> Terrain | None:
    """The buildings' feet interpolated (linear between them, nearest beyond) over the grid on
    `bbox_xy`; one tile per building (the nearest foot's), whose offset has the sigma `sigma`
    (the building's ground height: one for all, or one per building of `feet`); a local sigma
    of `growth` per metre from the nearest foot. Beyond `reach` metres of the footprints (the
    pavement) the ground lies `kerb` lower, its error one for all of it
    (citymodel.ground_faces: the road unit). None without feet."""
    from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator
    from scipy.spatial import cKDTree

    feet = feet or building_feet(store)
    if len(feet.points) < 3:
        return None
    x0, y0, nx, ny = empty_grid(np.asarray(bbox_xy, float), spacing)
    gx, gy = np.meshgrid(x0 + spacing * np.arange(nx), y0 + spacing * np.arange(ny))
    xy = np.c_[gx.ravel(), gy.ravel()]
    heights = np.full(len(xy), np.nan)
    unique, index = np.unique(np.round(feet.points[:, :2], 3), axis=0, return_index=True)
    if len(unique) >= 3 and np.ptp(unique[:, 0]) > 1 and np.ptp(unique[:, 1]) > 1:
        heights = LinearNDInterpolator(unique, feet.points[index, 2])(xy)
    missing = ~np.isfinite(heights)
    if missing.any():
        heights[missing] = NearestNDInterpolator(unique, feet.points[index, 2])(xy[missing])
    distance, nearest = cKDTree(feet.points[:, :2]).query(xy)
    tiles = feet.building[nearest].astype(np.int32)
    band = None if feet.footprints.is_empty else feet.footprints.buffer(reach)
    note = f"interpolated from {len(unique)} points on the feet of {len(set(feet.building))} buildings"
    logger.info("terrain: from the buildings' feet (%s)", note)
    sigmas = np.broadcast_to(np.asarray(sigma, float), (len(feet.building_ids),))[tiles]
    return Terrain("building_feet", x0, y0, spacing, heights.reshape(ny, nx),
                   sigmas.reshape(ny, nx), tiles.reshape(ny, nx),
                   list(feet.building_ids), [note], (growth * distance).reshape(ny, nx), band,
                   kerb if band is not None else 0.0)


def without_buildings(feet: Feet, buildings) -> Feet:
    """`feet` without the foot points of `buildings` (indices into its building ids; the
    footprints stay: the buildings still stand)."""
    keep = ~np.isin(feet.building, np.asarray(list(buildings), np.int64))
    return Feet(feet.points[keep], feet.building[keep], feet.building_ids, feet.footprints)
