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
