"""Terrain units checked against the ground's tie points before they are used.

A terrain source is made of units, each with one error of its own: a DTM tile (its height
reference), a building's feet (the ground height its LoD2 walls reach down to). The tie points
on the road and pavement beside each unit show where the ground is, up to the block's own
height error, which all units share (GNSS puts the block metres off in height). So each unit's
offset from its ground points (`ground_offsets`: the mode of the tie points' heights above the
unit, where ground points pile up among facade and tree points spread over every height) is
compared with the other units' (their median, `Consensus`): a unit further from it than its
own error allows contradicts the ground and the other units and is left out, named. Where too
few units see ground points to check each other, none is trusted to its stated sigma.

A DTM tile is also held against the buildings' feet it covers (`feet_offset`), robustly: per
building, then their median, trusted to the feet's sigma only where enough buildings agree. A
terrain in another height system, tens of metres from where GNSS puts the ground, moves the
block that far: the verdict's test of the refined block against GNSS fails it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

#: Histogram bin (m) of the tie points' heights above a unit: finer than a kerb, coarser than
#: the ground points' own scatter.
BIN = 0.1
#: Heights (m) above or below a unit that its ground points may have: a GNSS height error of
#: metres, plus a building's feet well below its street.
SPAN = 40.0
#: Tie points within this height (m) of a unit's mode make its ground; fewer than
#: MIN_GROUND_POINTS there, or fewer than PEAK_FACTOR times as many as the unit's points spread
#: evenly over their heights would put there (no ground layer stands out: facades, trees),
#: leave the unit unchecked.
GROUND_BAND = 0.3
MIN_GROUND_POINTS = 15
PEAK_FACTOR = 3.0
#: The least height span (m) over which a unit's points count as spread evenly: a storey.
STOREY = 3.0
#: Metres from the buildings' outlines within which tie points are left out of the ground:
#: facades, balconies and eaves stand there at every height.
FACADE_BAND = 1.5
#: Units that must see ground points to check each other: with two, a disagreement cannot
#: say which is wrong.
MIN_UNITS_TO_CHECK = 3
#: Significance level (two-sided) of each unit's test against the consensus and of the
#: consensus's test against GNSS's height sigma.
ALPHA = 0.001


def ground_offsets(heights_above: np.ndarray, unit: np.ndarray, num_units: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Per unit the mode (m) of `heights_above` (each tie point's height above its unit,
    `unit` its unit, -1: none) within +- SPAN, smoothed over three bins, and the number of
    points within GROUND_BAND of it (0 and nan where the unit has no points)."""
    modes, counts = np.full(num_units, np.nan), np.zeros(num_units, np.int64)
    edges = np.arange(-SPAN, SPAN + BIN, BIN)
    for k in range(num_units):
        d = heights_above[(unit == k) & np.isfinite(heights_above)]
        d = d[np.abs(d) < SPAN]
        if len(d) < MIN_GROUND_POINTS:
            continue
        hist, _ = np.histogram(d, edges)
        smooth = np.convolve(hist, np.ones(3), mode="same")
        centre = edges[int(np.argmax(smooth))] + 0.5 * BIN
        near = np.abs(d - centre) < GROUND_BAND
        even = len(d) * 2 * GROUND_BAND / max(float(np.ptp(d)), STOREY)
        if near.sum() < max(MIN_GROUND_POINTS, PEAK_FACTOR * even):
            continue
        modes[k] = float(np.median(d[near]))
        counts[k] = int(near.sum())
    return modes, counts


@dataclass
class Consensus:
    """The units' offsets from their ground points, their consensus and the test of each."""

    offsets: np.ndarray  # (U,) m, nan: no ground points
    counts: np.ndarray  # (U,) ground points of each
    consensus: float | None  # m: the median offset of the units with ground points
    checked: np.ndarray  # (U,) bool: tested against enough others
    contradicts: np.ndarray  # (U,) bool: further from the consensus than its sigma allows
    notes: list[str] = field(default_factory=list)


def consensus(offsets: np.ndarray, counts: np.ndarray, sigma: np.ndarray) -> Consensus:
    """Each unit's offset against the median of the others' (`sigma` (U,): each unit's
    sigma; the difference of two units has sqrt(2) of it at most), at level ALPHA."""
    seen = (counts >= MIN_GROUND_POINTS) & np.isfinite(offsets)
    checked = np.zeros(len(offsets), bool)
    contradicts = np.zeros(len(offsets), bool)
    if not seen.any():
        return Consensus(offsets, counts, None, checked, contradicts)
    middle = float(np.median(offsets[seen]))
    if seen.sum() >= MIN_UNITS_TO_CHECK:
        limit = float(stats.norm.isf(ALPHA / 2))
        checked = seen.copy()
        contradicts = seen & (np.abs(offsets - middle) > limit * np.sqrt(2.0) * sigma)
        if contradicts.any():  # the consensus of the units that agree
            middle = float(np.median(offsets[seen & ~contradicts]))
    return Consensus(offsets, counts, middle, checked, contradicts)


def feet_offset(differences: np.ndarray, building: np.ndarray, num_buildings: int,
                feet_sigma: float, feet_spread: float) -> tuple[float | None, float]:
    """A terrain tile's offset from the buildings' feet it covers, robust to a building whose
    feet are metres off: `differences` (the tile's height minus each foot point's) by
    `building`; each building's median, then their median. Returns (that offset or None
    without feet, its sigma): the feet's `feet_sigma` where at least MIN_UNITS_TO_CHECK
    buildings agree with it within their own error, else `feet_spread` (nothing checks the
    one or two buildings it rests on)."""
    per_building = np.array([np.median(differences[building == k])
                             for k in range(num_buildings) if np.any(building == k)])
    per_building = per_building[np.isfinite(per_building)]
    if not len(per_building):
        return None, feet_spread
    middle = float(np.median(per_building))
    limit = float(stats.norm.isf(ALPHA / 2)) * np.sqrt(2.0) * feet_sigma
    agreeing = np.abs(per_building - middle) <= limit
    if agreeing.sum() >= MIN_UNITS_TO_CHECK:
        return float(np.median(per_building[agreeing])), feet_sigma
    return middle, feet_spread


def off_feet(offset: float | None, sigma: float, tile_sigma: float) -> bool:
    """Whether a tile's offset from the buildings' feet (`feet_offset`: `offset`, `sigma`)
    exceeds what the tile's own `tile_sigma` and the feet's allow at ALPHA."""
    if offset is None:
        return False
    return abs(offset) > float(stats.norm.isf(ALPHA / 2)) * float(np.hypot(sigma, tile_sigma))
