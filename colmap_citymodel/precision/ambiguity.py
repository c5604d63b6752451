"""Is the block's placement on the model unique? The refined tie points, moved rigidly across
the model, fit it at other horizontal placements too (a neighbouring house of the same shape, a
regular facade row); the best placement is compared with the best distinct one that GNSS does
not rule out, as a ratio of their fits.

The fit at a placement is the smooth share of tie points within `radius` of the city model's
faces (as align.coarse.near_share); the terrain refine adds (TerrainSurface faces, from a DTM or
the buildings' feet) is left out: it is level and runs on round the block, so the tie points
on the ground fit it at every horizontal shift alike and would only pull the ratio towards 1.
Placements are scored on a grid of horizontal shifts; the alternative is the best local
maximum at least `distinct` metres from the best one and inside the region GNSS allows (a
callable telling, per shift, whether GNSS admits it).

The height is tested apart (height_fit): the same fit over vertical shifts of the tie points
at the refined horizontal placement. Walls fit most heights alike, so two heights may fit
nearly equally well and a ratio would not separate them; what is tested is whether another
height fits significantly better than the refined one (a one-sided paired test of the tie
points' fits at both, the points of one CELL metres cell counting as one sample). Where GNSS
does not hold the height (its bias estimated), only the model tells a block that settled a
storey off from one that did not.
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass

import numpy as np
from scipy import stats

from .._ext import load_core
from ..align.coarse import near_weights, subsample
from ..citymodel.ground_faces import TERRAIN_CLASS

logger = logging.getLogger(__name__)

#: Tie points scored per placement: enough for a share to 1-2 %, few enough for a grid of
#: thousands of placements in seconds.
SAMPLE_POINTS = 3000
#: Finest grid step of the shifts (m), the near radius; larger reaches take a coarser step
#: (at most GRID_SIDE steps a side) and score with a near radius of that step.
STEP = 0.5
GRID_SIDE = 61
#: Step (m) of the vertical shifts: half the near radius, so that a level face's peak (2 radii
#: wide) is sampled close to its top.
HEIGHT_STEP = 0.25
#: Side (m) of the cells whose tie points count as one sample in the height test: about a LOD2
#: face's extent; the points of one face share its generalisation error, not independent ones.
CELL = 10.0


@dataclass
class Placement:
    """The best placement's fit, the best distinct alternative's and its shift (m, E N)."""

    best_share: float
    alternative_share: float
    alternative_shift: np.ndarray | None
    best_shift: np.ndarray

    @property
    def ratio(self) -> float:
        """best / alternative fit; inf without an alternative."""
        if self.alternative_shift is None or self.alternative_share <= 0:
            return float("inf")
        return self.best_share / self.alternative_share

    def todict(self) -> dict:
        return {"best_share": self.best_share, "alternative_share": self.alternative_share,
                "ratio": None if not np.isfinite(self.ratio) else float(self.ratio),
                "alternative_shift_m": None if self.alternative_shift is None
                else [float(v) for v in self.alternative_shift],
                "best_shift_m": [float(v) for v in self.best_shift]}


def _local_maxima(scores: np.ndarray) -> np.ndarray:
    """bool mask of the cells of a grid (a line, a plane) no lower than any of their
    neighbours (2 on a line, 8 on a plane)."""
    padded = np.pad(scores, 1, constant_values=-np.inf)
    mask = np.ones_like(scores, bool)
    for step in itertools.product((-1, 0, 1), repeat=scores.ndim):
        if any(step):
            mask &= scores >= padded[tuple(slice(1 + d, 1 + d + n)
                                           for d, n in zip(step, scores.shape))]
    return mask


class _Triangles:
    """Distances (m, up to `within`) to some of a surface's triangles, as
    align.coarse.SurfaceDistance."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, threads: int):
        self.vertices, self.triangles, self.threads = vertices, triangles, threads
        self._grids: dict[float, object] = {}

    def __call__(self, points: np.ndarray, within: float) -> np.ndarray:
        grid = self._grids.get(within)
        if grid is None:
            grid = self._grids[within] = load_core().TriangleDistance(
                self.vertices, np.ascontiguousarray(self.triangles, np.int64), float(within))
        return grid(np.ascontiguousarray(points, np.float64).reshape(-1, 3), self.threads)


def without_terrain(surface):
    """`surface` (align.coarse.SurfaceDistance) without its TerrainSurface triangles; None when
    it has nothing else. A surface that does not tell its triangles' faces is returned as is."""
    faces = getattr(surface, "triangle_faces", None)
    classes = getattr(surface, "face_classes", None)
    if faces is None or classes is None or not len(faces):
        return surface
    keep = ~classes.mask(TERRAIN_CLASS)[faces]
    if keep.all():
        return surface
    if not keep.any():
        return None
    return _Triangles(surface.vertices, surface.triangles[keep], getattr(surface, "threads", 0))


def placement_fit(points: np.ndarray, surface, reach: float, admitted, *,
                  radius: float = 0.5, distinct: float = 2.0) -> Placement:
    """The best horizontal placement of `points` within +- `reach` m and the best distinct
    one (a local maximum at least `distinct` m away) that `admitted` ((K, 2) shifts -> (K,)
    bool, whether GNSS allows the block there) lets through. `surface(points, within)`:
    distances to the model (align.coarse.SurfaceDistance); its terrain does not score
    (without_terrain). Without other faces, no alternative."""
    surface = without_terrain(surface)
    if surface is None:
        logger.info("placement test: no model face but the terrain near the block")
        return Placement(0.0, 0.0, None, np.zeros(2))
    sample = subsample(np.asarray(points, float), SAMPLE_POINTS)
    step = max(STEP, 2.0 * reach / (GRID_SIDE - 1))
    radius = max(radius, step)
    offsets = np.arange(-np.floor(reach / step), np.floor(reach / step) + 1) * step
    grid = np.stack(np.meshgrid(offsets, offsets, indexing="ij"), -1).reshape(-1, 2)
    scores = np.empty(len(grid))
    batch = 64  # shifts per distance query
    for start in range(0, len(grid), batch):
        chunk = grid[start:start + batch]
        shifts = np.column_stack([chunk, np.zeros(len(chunk))])
        moved = (sample[None, :, :] + shifts[:, None, :]).reshape(-1, 3)
        scores[start:start + batch] = np.mean(
            near_weights(surface(moved, radius).reshape(len(shifts), -1), radius), axis=1)
    best = int(np.argmax(scores))
    maxima = _local_maxima(scores.reshape(len(offsets), len(offsets))).ravel()
    far = np.linalg.norm(grid - grid[best], axis=1) >= distinct
    candidates = np.flatnonzero(maxima & far & np.asarray(admitted(grid), bool))
    if not len(candidates):
        return Placement(float(scores[best]), 0.0, None, grid[best])
    alternative = candidates[int(np.argmax(scores[candidates]))]
    return Placement(float(scores[best]), float(scores[alternative]), grid[alternative],
                     grid[best])


@dataclass
class HeightFit:
    """The refined height's fit and the best distinct height's (vertical shifts, m), with the
    one-sided p-value that the other fits better (number of heights tried taken into
    account); 1 without another height."""

    here_share: float
    here_shift: float
    other_share: float
    other_shift: float | None
    z: float
    p: float

    def todict(self) -> dict:
        return {"here_share": self.here_share, "here_shift_m": self.here_shift,
                "other_share": self.other_share, "other_shift_m": self.other_shift,
                "z": float(self.z) if np.isfinite(self.z) else None, "p": self.p}


def _point_fits(sample: np.ndarray, surface, shifts: np.ndarray, radius: float) -> np.ndarray:
    """(len(shifts), len(sample)) smooth fit of each point moved up by each shift: 1 on the
    surface, 0 from `radius` on."""
    return np.array([near_weights(surface(sample + [0.0, 0.0, dz], radius), radius)
                     for dz in shifts]).reshape(len(shifts), len(sample))


def paired_z(gain: np.ndarray, positions: np.ndarray, cell: float) -> float:
    """Mean of `gain` (per point) over its standard error, the points of one `cell` m cube of
    `positions` summed into one sample (cluster-robust): inf where every cell gains alike."""
    n = len(gain)
    _, cells = np.unique(np.floor(positions / cell).astype(np.int64), axis=0,
                         return_inverse=True)
    sums = np.bincount(cells.ravel(), weights=gain - gain.mean())
    variance = np.sum(sums ** 2) / n ** 2 * len(sums) / max(len(sums) - 1, 1)
    if variance <= 0:
        return float(np.copysign(np.inf, gain.mean())) if gain.mean() else 0.0
    return float(gain.mean() / np.sqrt(variance))


def height_fit(points: np.ndarray, surface, reach: float, admitted, *, radius: float = 0.5,
               distinct: float = 2.0) -> HeightFit:
    """Vertical shifts of `points` within +- `reach` m: the refined height's fit (the best
    within `radius` of it) against the best local maximum at least `distinct` away that
    `admitted` ((K,) shifts -> (K,) bool, GNSS allows it) lets through; `surface` as in
    placement_fit (its terrain does not score)."""
    surface = without_terrain(surface)
    sample = subsample(np.asarray(points, float), SAMPLE_POINTS)
    shifts = np.arange(-np.floor(reach / HEIGHT_STEP), np.floor(reach / HEIGHT_STEP) + 1
                       ) * HEIGHT_STEP
    if surface is None or not len(sample):
        return HeightFit(0.0, 0.0, 0.0, None, 0.0, 1.0)
    fits = _point_fits(sample, surface, shifts, radius)
    scores = fits.mean(axis=1)
    own = np.abs(shifts) <= radius  # the refined height's own peak
    here = int(np.flatnonzero(own)[np.argmax(scores[own])])
    near = np.abs(shifts) < distinct
    candidates = np.flatnonzero(_local_maxima(scores) & ~near & (scores > 0)
                                & np.asarray(admitted(shifts), bool))
    if not len(candidates):
        return HeightFit(float(scores[here]), float(shifts[here]), 0.0, None, 0.0, 1.0)
    other = int(candidates[np.argmax(scores[candidates])])
    z = paired_z(fits[other] - fits[here], sample, CELL)
    p = min(1.0, float(stats.norm.sf(z)) * len(candidates))
    return HeightFit(float(scores[here]), float(shifts[here]), float(scores[other]),
                     float(shifts[other]), z, p)
