"""Ground tie points: which points an assigner gave to a terrain face stay on it.

Terrain faces (citymodel.ground_faces, class "TerrainSurface") take the points of open ground:
road, pavement, lawn. Cars, poles, hedges and trees stand on the same ground within an
assignment threshold of it; their points are left off the terrain when their neighbourhood is
not a near-horizontal surface: its normal (the smallest principal direction of the
`GROUND_NEIGHBOURS` nearest tie points) more than `MAX_GROUND_SLOPE_DEG` from the vertical, or
the neighbourhood not flat (its surface variation above `GROUND_VARIATION`).
"""

from __future__ import annotations

import logging

import numpy as np

from ..citymodel.ground_faces import terrain_mask
from ..citymodel.store import PlaneStore
from .assignment import Assignment

logger = logging.getLogger(__name__)

#: Steepest ground (deg) a terrain point's neighbourhood may have: streets and pavements rise
#: a few per cent, ramps and slopes up to about 20 deg; car sides and walls stand at 90.
MAX_GROUND_SLOPE_DEG = 25.0

#: Tie points whose neighbourhood gives a ground point's local surface.
GROUND_NEIGHBOURS = 12

#: Largest surface variation (smallest covariance eigenvalue over their sum) of a ground
#: point's neighbourhood: a pavement's points lie within centimetres of a plane, a hedge's
#: or a tree's spread in all directions (1/3 without structure).
GROUND_VARIATION = 0.08


def off_ground(points: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(len(rows),) bool: the points `points[rows]` whose neighbourhood among all `points` is
    no near-horizontal surface."""
    from scipy.spatial import cKDTree

    if len(points) < 3 or not len(rows):
        return np.zeros(len(rows), bool)
    k = min(GROUND_NEIGHBOURS, len(points))
    _, index = cKDTree(points).query(points[rows], k=k)
    near = points[index]
    centred = near - near.mean(axis=1, keepdims=True)
    values, vectors = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred) / k)
    variation = values[:, 0] / np.maximum(values.sum(axis=1), 1e-18)
    vertical = np.abs(vectors[:, 2, 0])
    return (variation > GROUND_VARIATION) | (vertical < np.cos(np.radians(MAX_GROUND_SLOPE_DEG)))


def without_clutter_on_terrain(assignment: Assignment, points: np.ndarray, store: PlaneStore,
                               options, kept_faces: np.ndarray | None = None) -> Assignment:
    """`assignment` without the terrain points that are not on open ground (`off_ground`);
    faces left too small are dropped as usual. Unchanged for a store without terrain faces."""
    terrain = terrain_mask(store)
    if not terrain.any():
        return assignment
    on = assignment.assigned & terrain[np.maximum(assignment.face_index, 0)]
    rows = np.flatnonzero(on)
    if not len(rows):
        return assignment
    off = np.zeros(len(points), bool)
    off[rows] = off_ground(points, rows)
    if not off.any():
        return assignment
    logger.debug("%d of %d terrain points not on open ground left unassigned",
                 int(off.sum()), len(rows))
    return assignment.eliminate(off, points, options, kept_faces)
