"""Procedural materials: the reflectance (linear RGB) and glossiness of each ray hit from its
part of the scene (wall, roof, window, door, tree, car, ...), its object's style and noise at
several scales.

Every material mixes a regular pattern (brick courses, roof tile rows, window frames, paving
joints) with band-limited noise anchored to the surface (stains, grain, dirt, per-brick and
per-tile variation). The noise makes every metre of a facade look different to SIFT; the
patterns keep what makes real cities hard to match: rows of like windows, repeated tiles.
Patterns finer than the pixel footprint fade to their mean (noise.fade), so that they never
alias into noise that differs between images.
"""

from __future__ import annotations

import numpy as np

from .. import scene as sc
from . import palette as pal
from .noise import Noise, edge, fade, grid_lines, line_coverage
from .palette import Styles
from .surfaces import Hits

#: |normal z| from which a roof counts as flat (gravel, bitumen) rather than tiled.
FLAT_ROOF_NZ = 0.97


class Materials:
    """Reflectance and gloss of ray hits; `ground` paints the terrain (GroundPaint)."""

    def __init__(self, styles: Styles, noise: Noise, ground):
        self.st = styles
        self.nz = noise
        self.ground = ground
        self._by_part = {
            sc.PART_WALL: self._wall, sc.PART_PILASTER: self._pilaster,
            sc.PART_REVEAL: self._reveal, sc.PART_ROOF: self._roof,
            sc.PART_WINDOW: self._window, sc.PART_DOOR: self._door,
            sc.PART_GARAGE: self._garage, sc.PART_BALCONY: self._concrete,
            sc.PART_PARAPET: self._concrete, sc.PART_OVERHANG: self._overhang,
            sc.PART_CHIMNEY: self._chimney, sc.PART_CROWN: self._crown,
            sc.PART_TRUNK: self._trunk, sc.PART_CAR: self._car,
            sc.PART_FURNITURE: self._furniture, sc.PART_GROUND: self._ground,
        }

    def __call__(self, h: Hits) -> tuple[np.ndarray, np.ndarray]:
        """(N,3) reflectance and (N,) gloss (0 matt .. 1 a mirror such as glass)."""
        albedo = np.empty((len(h), 3), np.float32)
        gloss = np.zeros(len(h), np.float32)
        order = np.argsort(h.part, kind="stable")
        bounds = np.searchsorted(h.part[order], np.arange(len(sc.PART_NAMES) + 1))
        for part in range(len(sc.PART_NAMES)):
            i = order[bounds[part]:bounds[part + 1]]
            if len(i):
                fn = self._by_part.get(part, self._concrete)
                albedo[i], gloss[i] = fn(h, i)
        return albedo, gloss

    # ------------------------------------------------------------------------------------------
    # helpers

    def _xy(self, h: Hits, i: np.ndarray):
        """Texture coordinates shifted by the object's offset, and the footprint."""
        off = self.st.offset[self.st.row(h.obj[i])]
        return h.s[i] + off[:, 0], h.t[i] + off[:, 1], h.footprint[i]

    @staticmethod
    def _matt(colour: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return colour.astype(np.float32), np.zeros(len(colour), np.float32)

    def _stains(self, x, y, w, layer: int, strength: float = 0.25) -> np.ndarray:
        """1 + weathering at every scale: blotches of metres, the material's grain down to
        millimetres, vertical run-off streaks, sparse dark spots (dirt, chips)."""
        nz = self.nz
        big = nz.fbm(x, y, w, largest=3.0, smallest=0.25, gain=0.6, layer=layer)
        grain = nz.fbm(x, y, w, largest=0.2, smallest=0.004, gain=0.8, layer=layer + 1)
        streak = nz.fbm(x, y, w, largest=1.2, smallest=0.05, gain=0.55, layer=layer + 2,
                        stretch=5.0)
        spots = nz.speckle(x, y, w, 0.05, layer=layer + 3, threshold=0.62)
        return 1.0 + strength * (0.6 * big + grain + 0.35 * streak) - 0.2 * spots

    # ------------------------------------------------------------------------------------------
    # walls

    def _wall_colour(self, h: Hits, i: np.ndarray) -> np.ndarray:
        row = self.st.row(h.obj[i])
        x, y, w = self._xy(h, i)
        colour = self.st.plaster[row] * self._stains(x, y, w, 1)[:, None]
        brick = self.st.brick[row]
        if brick.any():
            colour[brick] = self._brick(x[brick], y[brick], w[brick], colour[brick])
        return colour

    def _brick(self, x, y, w, base) -> np.ndarray:
        """Running bond: 0.24 x 0.071 m bricks, 1 cm joints; each brick its own shade."""
        course, length, joint = 0.0813, 0.25, 0.005
        row = np.floor(y / course)
        along = x / length + 0.5 * (row % 2)
        col = np.floor(along)
        show = fade(course, w)
        shade = 1.0 + 0.2 * show * self.nz.cell(col, row, 3)
        tint = 0.07 * show * self.nz.cell(col, row, 4)
        colour = base * shade[:, None] * np.stack([1 + tint, 1 + 0.3 * tint, 1 - tint], 1)
        horizontal = grid_lines(y, course, joint, w)
        vertical = grid_lines(along * length, length, joint, w)
        mortar = horizontal + (1 - horizontal) * vertical
        return colour * (1 - mortar)[:, None] + pal.MORTAR * mortar[:, None]

    def _wall(self, h: Hits, i: np.ndarray):
        colour = self._wall_colour(h, i)
        _, b, _, _ = h.local(i)
        plinth = np.clip(1.0 - b / 0.5, 0.0, 1.0)  # splash and dirt along the foot
        return self._matt(colour * (1.0 - 0.25 * plinth)[:, None])

    def _pilaster(self, h: Hits, i: np.ndarray):
        return self._matt(self._wall_colour(h, i) * 1.07)

    def _reveal(self, h: Hits, i: np.ndarray):
        return self._matt(self._wall_colour(h, i) * 0.92)

    def _concrete(self, h: Hits, i: np.ndarray):
        x, y, w = self._xy(h, i)
        return self._matt(pal.CONCRETE * self._stains(x, y, w, 12, 0.3)[:, None])

    # ------------------------------------------------------------------------------------------
    # roofs

    def _roof(self, h: Hits, i: np.ndarray):
        flat = np.abs(h.normal[i, 2]) >= FLAT_ROOF_NZ
        colour = np.empty((len(i), 3), np.float32)
        if flat.any():
            colour[flat] = self._flat_roof(h, i[flat])
        if (~flat).any():
            colour[~flat] = self._tiles(h, i[~flat])
        return self._matt(colour)

    def _tiles(self, h: Hits, i: np.ndarray) -> np.ndarray:
        """Rows of 0.32 m up the slope, tiles 0.21 m wide, staggered; the row above shades the
        top of each row; each tile its own shade; moss and dirt over all."""
        x, y, w = self._xy(h, i)
        row_h, tile_w = 0.32, 0.21
        row = np.floor(y / row_h)
        frac = y / row_h - row
        along = x / tile_w + 0.5 * (row % 2)
        show_row, show_tile = fade(row_h, w), fade(tile_w, w)
        shadow = 1.0 - 0.45 * edge(frac, 0.86, w / row_h)
        shadow = show_row * shadow + (1 - show_row) * 0.94
        gap = line_coverage(((along + 0.5) % 1.0 - 0.5) * tile_w, 0.006, w) * show_tile
        shade = 1.0 + 0.14 * show_tile * self.nz.cell(np.floor(along), row, 5)
        dirt = 1.0 + 0.25 * self.nz.fbm(x, y, w, largest=4.0, smallest=0.01, gain=0.7,
                                       layer=6)
        base = self.st.roof[self.st.row(h.obj[i])]
        return base * (shadow * shade * (1 - 0.6 * gap) * dirt)[:, None]

    def _flat_roof(self, h: Hits, i: np.ndarray) -> np.ndarray:
        x, y, w = self._xy(h, i)
        gravel = self.nz.fbm(x, y, w, largest=3.0, smallest=0.005, gain=0.8, layer=7)
        return self.st.flat_roof[self.st.row(h.obj[i])] * (1.0 + 0.35 * gravel)[:, None]

    def _overhang(self, h: Hits, i: np.ndarray):
        """Eaves: the roof's tiles from above, a wooden soffit from below."""
        below = h.normal[i, 2] < 0
        colour = np.empty((len(i), 3), np.float32)
        if (~below).any():
            colour[~below] = self._tiles(h, i[~below])
        if below.any():
            j = i[below]
            x, y, w = self._xy(h, j)
            grain = self.nz.fbm(x, y, w, largest=0.8, smallest=0.005, gain=0.7, layer=8,
                                stretch=0.15)
            colour[below] = pal.DOOR[0] * (1.0 + 0.25 * grain)[:, None]
        return self._matt(colour)

    def _chimney(self, h: Hits, i: np.ndarray):
        """Brick stacks on some buildings, metal or rendered boxes (vents, lift rooms) on
        others."""
        row = self.st.row(h.obj[i])
        x, y, w = self._xy(h, i)
        metal = self.st.rand[row, 0] < 0.5
        colour = pal.METAL[2] * self._stains(x, y, w, 13, 0.25)[:, None]
        brick = ~metal
        if brick.any():
            colour[brick] = self._brick(x[brick], y[brick], w[brick],
                                        pal.BRICK[0] * np.ones((brick.sum(), 3), np.float32))
        return self._matt(colour)

    # ------------------------------------------------------------------------------------------
    # openings

    def _window(self, h: Hits, i: np.ndarray):
        """Frame (7 cm), mullion and transom on the window's face; behind the glass a dark
        room, a curtain or blinds, one per window; the glass reflects the sky (gloss)."""
        a, b, width, height = h.local(i)
        w = h.footprint[i]
        frame = np.maximum.reduce([1 - edge(a, 0.07, w), edge(a, width - 0.07, w),
                                   1 - edge(b, 0.07, w), edge(b, height - 0.07, w)])
        frame = np.maximum(frame, line_coverage(a - width / 2, 0.03, w) * (width > 0.9))
        frame = np.maximum(frame, line_coverage(b - 0.7 * height, 0.03, w) * (height > 1.2))
        rect = h.rect[i]
        which = self.nz.cell(np.floor(rect[:, 0] * 7.0), np.floor(rect[:, 1] * 7.0), 8)
        inside = self._room(a, b, width, height, w, which, h, i)
        row = self.st.row(h.obj[i])
        colour = inside * (1 - frame)[:, None] + self.st.frame[row] * frame[:, None]
        return colour.astype(np.float32), (0.9 * (1 - frame)).astype(np.float32)

    def _room(self, a, b, width, height, w, which, h, i) -> np.ndarray:
        """What is seen through a window: dark, a curtain with folds, or blinds."""
        x, y, _ = self._xy(h, i)
        dark = pal.GLASS * (1.0 + 0.4 * self.nz.fbm(x, y, w, largest=0.6, smallest=0.02,
                                                    layer=9))[:, None]
        folds = 1.0 + 0.18 * fade(0.12, w) * np.sin(2 * np.pi * a / 0.12)
        drop = height * (0.25 + 0.5 * (which * 0.5 + 0.5))
        curtain = (which > 0.1) & (b > height - drop)
        blinds = which < -0.55
        colour = dark
        light = np.array([0.55, 0.52, 0.46], np.float32)
        colour = np.where(curtain[:, None], light * folds[:, None], colour)
        slats = 0.25 + 0.12 * grid_lines(b, 0.05, 0.006, w)
        colour = np.where(blinds[:, None], slats[:, None] * np.array([0.9, 0.9, 0.88]), colour)
        return colour.astype(np.float32)

    def _door(self, h: Hits, i: np.ndarray):
        """Wood with grain, a frame, two inset panels, glass in the upper panel of some."""
        a, b, width, height = h.local(i)
        x, y, w = self._xy(h, i)
        row = self.st.row(h.obj[i])
        grain = self.nz.fbm(x, y, w, largest=0.6, smallest=0.004, gain=0.7, layer=10,
                            stretch=8.0)
        colour = self.st.door[row] * (1.0 + 0.22 * grain)[:, None]
        lines = np.maximum.reduce([line_coverage(a - 0.14, 0.01, w),
                                   line_coverage(a - (width - 0.14), 0.01, w),
                                   line_coverage(b - 0.2, 0.01, w),
                                   line_coverage(b - 0.55 * height, 0.01, w),
                                   line_coverage(b - (height - 0.14), 0.01, w)])
        frame = np.maximum.reduce([1 - edge(a, 0.06, w), edge(a, width - 0.06, w),
                                   edge(b, height - 0.06, w)])
        glass = (self.st.rand[row, 1] < 0.5) & (a > 0.16) & (a < width - 0.16) & (
            b > 0.6 * height) & (b < height - 0.16)
        colour = colour * (1 - 0.45 * np.maximum(lines, frame))[:, None]
        colour[glass] = pal.GLASS
        return colour.astype(np.float32), (0.9 * glass).astype(np.float32)

    def _garage(self, h: Hits, i: np.ndarray):
        """A sectional door: panels 0.5 m high with grooves, the building's frame colour."""
        _, b, _, _ = h.local(i)
        x, y, w = self._xy(h, i)
        grooves = grid_lines(b, 0.5, 0.012, w)
        fine = self.nz.fbm(x, y, w, largest=1.0, smallest=0.005, gain=0.6, layer=11)
        colour = self.st.frame[self.st.row(h.obj[i])] * 0.85
        return self._matt(colour * ((1 - 0.5 * grooves) * (1 + 0.12 * fine))[:, None])

    # ------------------------------------------------------------------------------------------
    # clutter

    def _crown(self, h: Hits, i: np.ndarray):
        """Foliage: strong noise from leaf clusters to single leaves, darker gaps."""
        x, y, w = self._xy(h, i)
        row = self.st.row(h.obj[i])
        base = pal.FOLIAGE[(self.st.rand[row, 2] * len(pal.FOLIAGE)).astype(int)]
        leaves = self.nz.fbm(x, y, w, largest=1.2, smallest=0.01, gain=0.85, layer=14)
        return self._matt(base * np.clip(0.9 + 1.1 * leaves, 0.15, 2.0)[:, None])

    def _trunk(self, h: Hits, i: np.ndarray):
        x, y, w = self._xy(h, i)
        bark = self.nz.fbm(x, y, w, largest=0.5, smallest=0.005, gain=0.75, layer=15,
                           stretch=6.0)
        return self._matt(pal.BARK * (1.0 + 0.35 * bark)[:, None])

    def _car(self, h: Hits, i: np.ndarray):
        """Paint with a band of windows along the sides, dark sills and wheels below."""
        _, b, _, height = h.local(i)
        x, y, w = self._xy(h, i)
        side = np.abs(h.normal[i, 2]) < 0.5
        rel = b / np.maximum(height, 1e-3)
        paint = self.st.paint[self.st.row(h.obj[i])]
        dirt = 1.0 + 0.08 * self.nz.fbm(x, y, w, largest=1.0, smallest=0.01, layer=16)
        colour = paint * dirt[:, None]
        glass = side & (rel > 0.55) & (rel < 0.92)
        sill = side & (rel < 0.2)
        colour[glass] = pal.GLASS
        colour[sill] = 0.03
        gloss = np.where(glass, 0.9, np.where(sill, 0.0, 0.35)).astype(np.float32)
        return colour.astype(np.float32), gloss

    def _furniture(self, h: Hits, i: np.ndarray):
        x, y, w = self._xy(h, i)
        row = self.st.row(h.obj[i])
        base = pal.METAL[(self.st.rand[row, 3] * len(pal.METAL)).astype(int)]
        return self._matt(base * self._stains(x, y, w, 17, 0.2)[:, None])

    def _ground(self, h: Hits, i: np.ndarray):
        return self._matt(self.ground(h.p[i, 0], h.p[i, 1], h.footprint[i], self.nz))
