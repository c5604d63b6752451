"""A simulated DTM: the true ground written as GeoTIFF tiles with a DTM's own errors.

Each tile gets one height offset (a tile's reference error, drawn from N(0, offset_sigma^2)
unless given) plus white noise per post (noise_sigma); posts where the ground function is nan
(outside the simulated terrain) are nodata. The tiles are written in the model CRS, or in
`crs` when given (the posts then lie on that CRS's grid and the ground is evaluated at their
model CRS position).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

NODATA = -9999.0


def write_dtm(directory, ground, bbox_xy, model_crs: str, *, spacing: float = 1.0,
              tiles: int = 1, offset_sigma: float = 0.0, offsets=None, noise_sigma: float = 0.0,
              seed: int = 0, crs: str | None = None, name: str = "dtm") -> list[Path]:
    """Writes the ground `ground(xy) -> z` (model CRS xy (N, 2) -> heights, nan: none) over
    `bbox_xy` [[xmin, ymin], [xmax, ymax]] (model CRS) as `tiles` GeoTIFF tiles side by side
    along x (`name`_<k>.tif in `directory`); returns their paths. `offsets`: the tiles' height
    offsets (m) instead of random ones."""
    import rasterio
    from pyproj import Transformer
    from rasterio.transform import from_origin

    rng = np.random.default_rng([seed, 4711])
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    out_crs = crs or model_crs
    to_file = Transformer.from_crs(model_crs, out_crs, always_xy=True)
    to_model = Transformer.from_crs(out_crs, model_crs, always_xy=True)
    bbox_xy = np.asarray(bbox_xy, float)
    corners = np.array([[x, y] for x in bbox_xy[:, 0] for y in bbox_xy[:, 1]])
    fx, fy = to_file.transform(corners[:, 0], corners[:, 1])
    step = spacing if out_crs == model_crs else _spacing_in(out_crs, spacing, fx, fy, to_model)
    x_edges = np.linspace(min(fx), max(fx), tiles + 1)
    offsets = (rng.normal(0.0, offset_sigma, tiles) if offsets is None
               else np.asarray(offsets, float))
    paths = []
    for k in range(tiles):
        cols = max(1, int(np.ceil((x_edges[k + 1] - x_edges[k]) / step)))
        rows = max(1, int(np.ceil((max(fy) - min(fy)) / step)))
        left, top = x_edges[k], max(fy)
        px = left + (np.arange(cols) + 0.5) * step
        py = top - (np.arange(rows) + 0.5) * step
        gx, gy = np.meshgrid(px, py)
        mx, my = to_model.transform(gx.ravel(), gy.ravel())
        z = ground(np.c_[mx, my]).reshape(rows, cols) + offsets[k]
        z = z + rng.normal(0.0, noise_sigma, z.shape) if noise_sigma > 0 else z
        z = np.where(np.isfinite(z), z, NODATA).astype(np.float32)
        path = directory / f"{name}_{k}.tif"
        with rasterio.open(path, "w", driver="GTiff", width=cols, height=rows, count=1,
                           dtype="float32", crs=out_crs, nodata=NODATA,
                           transform=from_origin(left, top, step, step)) as dst:
            dst.write(z, 1)
        paths.append(path)
    logger.info("DTM: %d tile(s) in %s, offsets %s m, noise %.2f m", tiles, out_crs,
                np.round(offsets, 3).tolist(), noise_sigma)
    return paths


def _spacing_in(crs: str, spacing: float, fx, fy, to_model) -> float:
    """About `spacing` metres in the units of `crs` (degrees for a geographic one)."""
    x, y = float(np.mean(fx)), float(np.mean(fy))
    d = 1e-5 if abs(x) < 400 and abs(y) < 400 else 1.0
    ax, ay = to_model.transform([x, x + d], [y, y])
    metres = float(np.hypot(ax[1] - ax[0], ay[1] - ay[0]))
    return spacing * d / metres


def true_ground_grid(triangles: np.ndarray, spacing: float = 1.0):
    """The height of the ground triangles (T, 3, 3), local frame, at posts `spacing` apart
    over their extent (vertical rays from above): (x0, y_top, heights (rows, cols) with row 0
    at the top, nan where no triangle is)."""
    import open3d as o3d

    lo, hi = triangles[:, :, :2].min((0, 1)), triangles[:, :, :2].max((0, 1))
    xs = np.arange(np.ceil(lo[0]), hi[0], spacing)
    ys = np.arange(np.floor(hi[1]), lo[1], -spacing)
    gx, gy = np.meshgrid(xs, ys)
    scene = o3d.t.geometry.RaycastingScene()
    vertices = triangles.reshape(-1, 3).astype(np.float32)
    scene.add_triangles(o3d.core.Tensor(vertices),
                        o3d.core.Tensor(np.arange(len(vertices), dtype=np.uint32).reshape(-1, 3)))
    top = float(triangles[:, :, 2].max()) + 10.0
    rays = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, top),
                 np.zeros(gx.size), np.zeros(gx.size), -np.ones(gx.size)].astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    heights = np.where(np.isfinite(hit), top - hit, np.nan).reshape(gx.shape)
    return float(xs[0]), float(ys[0]), heights


def write_grid(path, x0: float, y_top: float, spacing: float, heights: np.ndarray,
               crs: str) -> Path:
    """`heights` (rows, cols; row 0 at y_top, posts at their cell centres' coordinates
    x0 + j * spacing, y_top - i * spacing) as a float32 GeoTIFF in `crs`; nan -> nodata."""
    import rasterio
    from rasterio.transform import from_origin

    path = Path(path)
    with rasterio.open(path, "w", driver="GTiff", width=heights.shape[1],
                       height=heights.shape[0], count=1, dtype="float32", crs=crs,
                       nodata=NODATA, transform=from_origin(x0 - spacing / 2, y_top + spacing / 2,
                                                            spacing, spacing)) as dst:
        dst.write(np.where(np.isfinite(heights), heights, NODATA).astype(np.float32), 1)
    return path


def dtm_from_truth(truth_tif, directory, *, tiles: int, offset_sigma: float,
                   noise_sigma: float, seed: int) -> list[Path]:
    """The true ground grid `truth_tif` cut into `tiles` tiles along x, each with its own
    height offset (N(0, offset_sigma^2)) and white noise per post, written as
    `directory`/dtm_<k>.tif; returns their paths."""
    import rasterio

    rng = np.random.default_rng([seed, 4712])
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    with rasterio.open(truth_tif) as src:
        z = src.read(1, masked=True).filled(np.nan).astype(np.float64)
        transform, crs = src.transform, src.crs
    spacing = transform.a
    x0, y_top = transform.c + spacing / 2, transform.f - spacing / 2
    edges = np.linspace(0, z.shape[1], tiles + 1).astype(int)
    offsets = rng.normal(0.0, offset_sigma, tiles)
    paths = []
    for k in range(tiles):
        part = z[:, edges[k]:edges[k + 1]] + offsets[k]
        part = part + rng.normal(0.0, noise_sigma, part.shape)
        paths.append(write_grid(directory / f"dtm_{k}.tif", x0 + edges[k] * spacing, y_top,
                                spacing, part, crs))
    logger.info("DTM: %d tile(s), offsets %s m, noise %.2f m", tiles,
                np.round(offsets, 3).tolist(), noise_sigma)
    return paths
