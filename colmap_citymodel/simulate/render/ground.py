"""The terrain's paint: pavements along the buildings, asphalt with lane markings, manholes and
repairs beyond them, grass further out, chosen by the distance to the building footprints.

The distance (Euclidean distance transform of the rasterised footprints) and the coordinate
along the footprints' outlines of the nearest footprint point (which dashes, manholes and
paving joints follow) are rasters over the terrain (10 cm cells), read bilinearly per hit.
"""

from __future__ import annotations

import numpy as np

from . import palette as pal
from .noise import Noise, edge, fade, grid_lines, line_coverage

#: Cell of the distance raster (m): fine enough for kerbs and 12 cm markings after bilinear
#: reading, coarse enough for a few hundred metres of street (a few million cells).
CELL = 0.1
#: Width (m) of the kerb stones along the pavement's edge.
KERB_WIDTH = 0.2
#: Lane markings: edge lines 0.35 m off the kerb, dashed centre line (3 m dashes every 9 m);
#: half widths of the lines (m).
EDGE_LINE, EDGE_HALF, CENTRE_HALF, DASH, DASH_PERIOD = 0.35, 0.06, 0.06, 3.0, 9.0
#: Manholes: one per MANHOLE_SPACING m of lane, radius (m).
MANHOLE_SPACING, MANHOLE_RADIUS = 14.0, 0.32


class GroundPaint:
    """Paint of the ground at local (x, y): see the module docstring."""

    def __init__(self, footprints, lo: np.ndarray, hi: np.ndarray, sidewalk_width: float,
                 road_width: float):
        from rasterio import features, transform
        from scipy import ndimage

        self.sidewalk = float(sidewalk_width)
        self.road = float(road_width)
        self.x0, self.y0 = float(lo[0]) - 2.0, float(lo[1]) - 2.0
        nx = int(np.ceil((hi[0] + 2.0 - self.x0) / CELL)) + 1
        ny = int(np.ceil((hi[1] + 2.0 - self.y0) / CELL)) + 1
        # raster row r covers y0 + r*CELL (north up is irrelevant here: a plain grid)
        affine = transform.Affine(CELL, 0.0, self.x0 - CELL / 2, 0.0, CELL, self.y0 - CELL / 2)
        inside = np.zeros((ny, nx), np.uint8)
        if footprints is not None and not footprints.is_empty:
            inside = features.rasterize([(footprints, 1)], out_shape=(ny, nx),
                                        transform=affine, all_touched=False, dtype=np.uint8)
        if inside.any():
            dist, (iy, ix) = ndimage.distance_transform_edt(inside == 0, return_indices=True)
            self.along = self._arc_lengths(footprints, iy * nx + ix, nx)
        else:  # no buildings: everything far away, one direction
            dist = np.full((ny, nx), 1e3)
            self.along = (self.x0 + CELL * np.arange(nx, dtype=np.float32))[None].repeat(ny, 0)
        self.distance = (dist * CELL).astype(np.float32)

    def _arc_lengths(self, footprints, nearest: np.ndarray, nx: int) -> np.ndarray:
        """Per cell, how far along the footprints' outlines (m) the nearest footprint cell
        lies: the coordinate along the kerb that dashes and paving joints follow."""
        from scipy.spatial import cKDTree

        points, arcs = [], []
        geoms = getattr(footprints, "geoms", [footprints])
        for poly in geoms:
            for ring in [poly.exterior, *poly.interiors]:
                n = max(int(ring.length / (CELL / 2)), 4)
                t = np.linspace(0.0, ring.length, n, endpoint=False)
                points.append(np.array([ring.interpolate(v).coords[0][:2] for v in t]))
                arcs.append(t + (arcs[-1][-1] + 100.0 if arcs else 0.0))
        cells, inverse = np.unique(nearest.ravel(), return_inverse=True)
        xy = np.c_[self.x0 + CELL * (cells % nx), self.y0 + CELL * (cells // nx)]
        _, which = cKDTree(np.concatenate(points)).query(xy)
        return np.concatenate(arcs)[which][inverse].reshape(nearest.shape).astype(np.float32)

    def _sample(self, x: np.ndarray, y: np.ndarray):
        """Bilinear distance (m) and coordinate along the outlines (bilinear where the four
        cells agree within a metre, else the nearest cell's)."""
        fx = np.clip((x - self.x0) / CELL, 0, self.distance.shape[1] - 1.001)
        fy = np.clip((y - self.y0) / CELL, 0, self.distance.shape[0] - 1.001)
        ix, iy = fx.astype(np.int64), fy.astype(np.int64)
        tx, ty = (fx - ix).astype(np.float32), (fy - iy).astype(np.float32)
        out = []
        for grid in (self.distance, self.along):
            a, b = grid[iy, ix], grid[iy, ix + 1]
            c, d = grid[iy + 1, ix], grid[iy + 1, ix + 1]
            top = a + (b - a) * tx
            out.append(top + (c + (d - c) * tx - top) * ty)
        a, b = self.along[iy, ix], self.along[iy, ix + 1]
        c, d = self.along[iy + 1, ix], self.along[iy + 1, ix + 1]
        jump = np.maximum.reduce([a, b, c, d]) - np.minimum.reduce([a, b, c, d]) > 1.0
        out[1][jump] = self.along[np.rint(fy[jump]).astype(np.int64),
                                  np.rint(fx[jump]).astype(np.int64)]
        return out[0], out[1]

    def __call__(self, x: np.ndarray, y: np.ndarray, w: np.ndarray,
                 noise: Noise) -> np.ndarray:
        x = x.astype(np.float64)
        y = y.astype(np.float64)
        dist, along = self._sample(x, y)
        sw = self.sidewalk
        colour = self._asphalt(x, y, w, dist - sw, along, noise)
        pave = dist < sw
        if pave.any():
            colour[pave] = self._paving(x[pave], y[pave], w[pave], dist[pave], along[pave],
                                        noise)
        kerb = line_coverage(dist - (sw - KERB_WIDTH / 2), KERB_WIDTH / 2, w)
        colour = colour * (1 - kerb)[:, None] + pal.KERB * kerb[:, None]
        grass = edge(dist, sw + self.road, w + 0.3)
        if grass.any():
            g = grass > 0
            colour[g] = colour[g] * (1 - grass[g])[:, None] + self._grass(
                x[g], y[g], w[g], noise) * grass[g][:, None]
        return colour

    def _asphalt(self, x, y, w, off, along, noise: Noise) -> np.ndarray:
        """Asphalt at `off` m beyond the kerb: aggregate grain, patches, tyre tracks, lines."""
        grain = noise.fbm(x, y, w, largest=0.08, smallest=0.004, gain=0.9, layer=20)
        patches = noise.fbm(x, y, w, largest=6.0, smallest=0.3, gain=0.6, layer=21)
        lane = self.road / 2
        track = sum(line_coverage(off - c, 0.35, w + 0.4) for c in
                    (lane * 0.3, lane * 0.7, lane * 1.3, lane * 1.7))
        shade = (1.0 + 0.3 * grain + 0.25 * patches) * (1.0 - 0.12 * track)
        colour = pal.ASPHALT * shade[:, None]
        dash = edge(np.abs((along / DASH_PERIOD) % 1.0 - 0.5) * DASH_PERIOD,
                    0.5 * (DASH_PERIOD - DASH), w)
        paint = np.maximum(line_coverage(off - EDGE_LINE, EDGE_HALF, w),
                           line_coverage(off - lane, CENTRE_HALF, w) * dash)
        paint *= 0.8 + 0.2 * noise.fbm(x, y, w, largest=0.5, smallest=0.01, layer=22)
        colour = colour * (1 - paint)[:, None] + pal.MARKING * paint[:, None]
        return self._manholes(colour, off, along, w, noise)

    def _manholes(self, colour, off, along, w, noise: Noise) -> np.ndarray:
        """Round cast-iron covers in the lanes, each with a cross-hatch."""
        cell = np.floor(along / MANHOLE_SPACING)
        centre = (cell + 0.5 + 0.3 * noise.cell(cell, cell * 0 + 1, 23)) * MANHOLE_SPACING
        lane_pos = self.road * (0.25 + 0.5 * (noise.cell(cell, cell * 0 + 2, 23) > 0))
        da, do = along - centre, off - lane_pos
        r = np.hypot(da, do)
        cover = edge(MANHOLE_RADIUS - r, 0.0, w)
        if not cover.any():
            return colour
        hatch = np.maximum(grid_lines(da + do, 0.06, 0.01, w), grid_lines(da - do, 0.06, 0.01, w))
        iron = (0.05 + 0.04 * hatch)[:, None] * np.ones(3, np.float32)
        rim = line_coverage(r - MANHOLE_RADIUS, 0.03, w)[:, None]
        iron = iron * (1 - rim) + 0.02 * rim
        return colour * (1 - cover)[:, None] + iron * cover[:, None]

    def _paving(self, x, y, w, dist, along, noise: Noise) -> np.ndarray:
        """Concrete slabs 0.4 m square along the kerb, each its own shade, joints, stains."""
        size = 0.4
        i, j = np.floor(along / size), np.floor(dist / size)
        show = fade(size, w)
        shade = 1.0 + 0.12 * show * noise.cell(i, j, 24)
        which = ((noise.cell(i, j, 25) * 0.5 + 0.5) * 3).astype(int).clip(0, 2)
        base = pal.PAVING[np.where(show > 0.5, which, 0)]
        joints = np.maximum(grid_lines(along, size, 0.004, w), grid_lines(dist, size, 0.004, w))
        stains = 1.0 + 0.22 * noise.fbm(x, y, w, largest=2.5, smallest=0.006, gain=0.7,
                                        layer=26)
        return base * (shade * stains * (1 - 0.5 * joints))[:, None]

    def _grass(self, x, y, w, noise: Noise) -> np.ndarray:
        patch = noise.fbm(x, y, w, largest=8.0, smallest=0.5, gain=0.6, layer=27)
        blades = noise.fbm(x, y, w, largest=0.3, smallest=0.005, gain=0.85, layer=28)
        base = pal.GRASS[0] * (1 - 0.5 * patch)[:, None] + pal.GRASS[1] * (0.5 * patch)[:, None]
        return base * np.clip(1.0 + 0.5 * blades + 0.2 * patch, 0.3, 2.0)[:, None]
