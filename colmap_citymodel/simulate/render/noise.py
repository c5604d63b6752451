"""Band-limited procedural noise and anti-aliased patterns for the renderer's textures.

Textures are functions of surface coordinates in metres, evaluated per pixel. Each pixel covers
`footprint` metres of the surface; a pattern finer than about two footprints cannot be shown
and would alias into noise that changes from image to image, so every function here fades its
detail out where it is finer than the footprint (frequency clamping), as a mip-map does.
"""

from __future__ import annotations

import numpy as np

#: Side of the random lattice behind value noise (cells); the noise of one octave repeats
#: after this many of its cells, far beyond the surfaces it covers at any octave.
LATTICE = 1024
#: Ratio of the wavelengths of successive octaves: not 2, so that the octaves' lattices never
#: line up and the sum never repeats.
LACUNARITY = 1.93


def smooth(t: np.ndarray) -> np.ndarray:
    """Smoothstep 3t^2 - 2t^3 on [0, 1]."""
    return t * t * (3.0 - 2.0 * t)


def fade(size: float | np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """How much of a pattern of period `size` (m) a pixel of `footprint` (m) shows: 1 from
    four footprints on, 0 below two."""
    return np.clip(np.asarray(size, np.float32) / (2.0 * footprint) - 1.0, 0.0, 1.0)


class Noise:
    """Value noise and its fractal sums from one seeded random lattice."""

    def __init__(self, seed: int):
        rng = np.random.default_rng([seed, 7])
        self.table = rng.uniform(-1.0, 1.0, LATTICE * LATTICE).astype(np.float32)
        # a lattice offset per (layer, octave) of value noise, and per layer of cell noise
        self.offsets = rng.uniform(0.0, LATTICE, (64 * 16, 2)).astype(np.float32)
        self.cell_offsets = rng.integers(0, LATTICE, (64, 2))

    def value(self, x: np.ndarray, y: np.ndarray, octave: int = 0) -> np.ndarray:
        """Value noise in [-1, 1] at (x, y) in lattice units; `octave` picks a lattice offset
        so that octaves and layers are independent."""
        ox, oy = self.offsets[octave % len(self.offsets)]
        x = np.asarray(x, np.float32) + ox
        y = np.asarray(y, np.float32) + oy
        xi = np.floor(x)
        yi = np.floor(y)
        fx = smooth(x - xi)
        fy = smooth(y - yi)
        mask = LATTICE - 1
        ix = xi.astype(np.int32) & mask
        iy = yi.astype(np.int32) & mask
        ix1 = (ix + 1) & mask
        row0 = iy * LATTICE
        row1 = ((iy + 1) & mask) * LATTICE
        t = self.table
        a = t[row0 + ix]
        top = a + (t[row0 + ix1] - a) * fx
        c = t[row1 + ix]
        bottom = c + (t[row1 + ix1] - c) * fx
        return top + (bottom - top) * fy

    def fbm(self, x: np.ndarray, y: np.ndarray, footprint: np.ndarray, *, largest: float,
            smallest: float, gain: float = 0.6, layer: int = 0,
            stretch: float = 1.0) -> np.ndarray:
        """Fractal sum of value noise from wavelength `largest` down to `smallest` (m), each
        octave `gain` times the amplitude of the one above, faded out where finer than the
        pixel footprint. `stretch` > 1 elongates the pattern along y (streaks). Roughly in
        [-1, 1] (normalised by the sum of amplitudes)."""
        out = np.zeros(len(x), np.float32)
        total = 0.0
        wavelength, amplitude, octave = float(largest), 1.0, 0
        while wavelength >= smallest * 0.999:
            weight = fade(wavelength, footprint)
            live = np.flatnonzero(weight > 0)
            if len(live) > 0.7 * len(out):  # most pixels: evaluate everywhere
                n = self.value(x / wavelength, y / (wavelength * stretch), layer * 16 + octave)
                out += (amplitude * weight) * n
            elif len(live):  # a fine octave only near pixels resolve: evaluate only there
                n = self.value(x[live] / wavelength, y[live] / (wavelength * stretch),
                               layer * 16 + octave)
                out[live] += (amplitude * weight[live]) * n
            total += amplitude
            wavelength /= LACUNARITY
            amplitude *= gain
            octave += 1
        return out / max(total, 1e-9) * 2.0

    def speckle(self, x: np.ndarray, y: np.ndarray, footprint: np.ndarray, size: float,
                layer: int = 0, threshold: float = 0.5) -> np.ndarray:
        """Sparse blobs about `size` m across (dirt, holes, chips) in [0, 1]: where one octave
        of value noise exceeds `threshold`; faded out where smaller than the footprint."""
        n = self.value(x / size, y / size, layer * 16 + 15)
        return np.clip((n - threshold) / 0.15, 0.0, 1.0) * fade(2.0 * size, footprint)

    def cell(self, i: np.ndarray, j: np.ndarray, layer: int = 0) -> np.ndarray:
        """A random number in [-1, 1] per integer cell (i, j) (bricks, tiles, slabs)."""
        ox, oy = self.cell_offsets[layer % len(self.cell_offsets)]
        ix = (i.astype(np.int64) + ox) & (LATTICE - 1)
        iy = (j.astype(np.int64) + oy) & (LATTICE - 1)
        return self.table[iy * LATTICE + ix]


def line_coverage(distance: np.ndarray, half_width: float | np.ndarray,
                  footprint: np.ndarray) -> np.ndarray:
    """Fraction of a pixel (a box `footprint` m wide at `distance` m from a line's centre)
    covered by the line of half width `half_width`: the line box-filtered by the pixel."""
    d = np.abs(distance)
    lo = np.maximum(-half_width, d - footprint / 2)
    hi = np.minimum(half_width, d + footprint / 2)
    return np.clip(hi - lo, 0.0, None) / footprint


def grid_lines(coord: np.ndarray, period: float, half_width: float,
               footprint: np.ndarray) -> np.ndarray:
    """Coverage of lines every `period` m (at multiples of it), box-filtered; where the period
    is below two footprints, the lines' mean share of the surface."""
    d = (coord / period + 0.5) % 1.0 - 0.5
    cov = line_coverage(d * period, half_width, footprint)
    w = fade(period, footprint)
    return w * cov + (1.0 - w) * min(2.0 * half_width / period, 1.0)


def edge(value: np.ndarray, threshold: float | np.ndarray, footprint: np.ndarray) -> np.ndarray:
    """0 below `threshold`, 1 above, box-filtered over one footprint (an anti-aliased step)."""
    return np.clip((value - threshold) / footprint + 0.5, 0.0, 1.0)
