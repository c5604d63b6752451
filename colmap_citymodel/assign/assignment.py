"""Assignment of tie points to model planes (Unger chapter 4; method.md section 6).

Every method answers the same question: given the current tie point coordinates (local frame)
and the plane store, which tie point belongs to which model face? At most one face per point
per iteration. All methods finish with the same two tests per face: a minimum number of points
and a planarity test on the eigenvalues l1 >= l2 >= l3 of the assigned points' covariance,
(l2 - l3) / l1 > threshold (rejects point sets close to a line).

Methods, by `AssignmentOptions.method` (registered in `ASSIGNERS`):
- "direct", (a): each point to its closest face within the threshold (here).
- "msac", (b): planes extracted from the whole cloud by MSAC, matched to faces (assign/indirect.py).
- "roi_msac", (c): one plane searched by MSAC near each face (assign/indirect.py).
- "auto": (b) or (c) while the threshold is large (the block is still far from the model),
  (a) once it is small.
(b) and (c) can weight the points' chances of entering an MSAC sample (weighted RANSAC,
Mulder 4.4): `assign(..., weights=...)` with `AssignmentOptions.weighted_sampling`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from ..citymodel.store import PlaneStore
from ..citymodel.visibility import class_mask, visibility
from ..options import AssignmentOptions

logger = logging.getLogger(__name__)


@dataclass
class Assignment:
    """Result of one assignment: `face_index[i]` is the face of tie point `point_ids[i]` (-1: none)."""

    point_ids: np.ndarray  # (P,) int64 COLMAP point3D ids, all candidates (check points excluded)
    face_index: np.ndarray  # (P,) int64
    distance: np.ndarray  # (P,) float64 signed distance to the assigned plane, nan if none
    threshold: float
    rejected_faces: dict[str, int] = field(default_factory=dict)  # reason -> number of faces
    method: str = "direct"  # the method that made it ("auto" resolves to one)
    # Faces whose f_dTP the adjustment weighs less (face -> sigma factor >= 1): their points'
    # mean offset lies further from the model than its generalisation error explains
    # (adjust.faces.outlier_factors).
    face_factors: dict[int, float] = field(default_factory=dict)
    # The sigma (m) of the faces' offsets the adjustment weighs them with (None: the option's).
    face_sigma: float | None = None
    # Faces that take no tie points (face -> test statistic): the other faces place the block
    # so that their points lie further from them than the generalisation error explains
    # (adjust.faces.snooped_faces).
    dropped_faces: dict[int, float] = field(default_factory=dict)

    @property
    def assigned(self) -> np.ndarray:
        return self.face_index >= 0

    @property
    def num_assigned(self) -> int:
        return int(np.count_nonzero(self.assigned))

    @property
    def faces(self) -> np.ndarray:
        """Sorted unique face indices with at least one assigned point."""
        return np.unique(self.face_index[self.assigned])

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    def points_of_face(self, face: int) -> np.ndarray:
        return self.point_ids[self.face_index == face]

    def without(self, point_mask: np.ndarray) -> "Assignment":
        """A copy in which the points selected by `point_mask` are unassigned (eliminated)."""
        face_index = self.face_index.copy()
        distance = self.distance.copy()
        face_index[point_mask] = -1
        distance[point_mask] = np.nan
        return Assignment(self.point_ids, face_index, distance, self.threshold,
                          dict(self.rejected_faces), self.method, dict(self.face_factors),
                          self.face_sigma, dict(self.dropped_faces))

    def eliminate(self, point_mask: np.ndarray, points: np.ndarray,
                  options: AssignmentOptions, kept_faces: np.ndarray | None = None
                  ) -> "Assignment":
        """`without(point_mask)`, then the faces left with too few points (or not planar)
        dropped as the assignment drops them (counted in the copy's `rejected_faces`);
        `points`: the tie points' coordinates, in the order of `point_ids`; `kept_faces`: as
        for `filter_faces`."""
        out = self.without(point_mask)
        out.face_index = filter_faces(points, out.face_index, options, out.rejected_faces,
                                      kept_faces)
        out.distance[out.face_index < 0] = np.nan
        return out


@dataclass
class Observers:
    """Where the tie points were seen from: observation k is of the tie point in row `rows[k]`
    of the arrays being assigned, made by a camera at `centres[k]` (local frame)."""

    rows: np.ndarray  # (O,) int64
    centres: np.ndarray  # (O, 3) float64


def front_share(points: np.ndarray, face_index: np.ndarray, normals: np.ndarray,
                observers: Observers) -> np.ndarray:
    """Per point, the share of its observations made from the side of its face's plane that
    the face's normal points to (nan for unassigned points and points nobody observes)."""
    share = np.full(len(points), np.nan)
    face_of_obs = face_index[observers.rows]
    on = (face_of_obs >= 0) & np.isfinite(observers.centres[:, 0])
    rows = observers.rows[on]
    rays = observers.centres[on] - points[rows]
    front = np.einsum("ij,ij->i", rays, normals[face_of_obs[on]]) > 0
    seen = np.bincount(rows, minlength=len(points))
    in_front = np.bincount(rows, weights=front, minlength=len(points))
    observed = seen > 0
    share[observed] = in_front[observed] / seen[observed]
    return share


def roof_points_seen_from_below(points: np.ndarray, face_index: np.ndarray,
                                store: PlaneStore, observers: Observers) -> np.ndarray:
    """(P,) bool: points assigned to a roof face that most of their images see from below its
    plane (`AssignmentOptions.roofs_seen_from_above`). Roofs steeper than about 84 deg are left
    alone: reading the model turns a roof's normal up only where it has a vertical component of
    0.1 or more."""
    roofs = store.faces.semantic.mask("RoofSurface") & (store.normals[:, 2] > 0.1)
    on_roof = (face_index >= 0) & roofs[np.maximum(face_index, 0)]
    if not np.any(on_roof):
        return np.zeros(len(points), bool)
    share = front_share(points, np.where(on_roof, face_index, -1), store.normals, observers)
    return on_roof & (share < 0.5)


class PlaneAssigner(Protocol):
    """Interface of an assignment method. `weights`: per-point quality (higher = better) for
    methods that sample points; others ignore it. `kept_faces`: the faces of the previous
    assignment, tested with `AssignmentOptions.face_hysteresis` (`filter_faces`)."""

    def __call__(self, points: np.ndarray, point_ids: np.ndarray, store: PlaneStore,
                 threshold: float, options: AssignmentOptions,
                 weights: np.ndarray | None = None,
                 kept_faces: np.ndarray | None = None) -> Assignment: ...


def planarity(points: np.ndarray) -> float:
    """(l2 - l3) / l1 of the covariance eigenvalues l1 >= l2 >= l3 (0 for a line or a point)."""
    if len(points) < 3:
        return 0.0
    eigenvalues = np.linalg.eigvalsh(np.cov(points.T))[::-1]
    if eigenvalues[0] <= 0:
        return 0.0
    return float((eigenvalues[1] - eigenvalues[2]) / eigenvalues[0])


def filter_faces(points: np.ndarray, face_index: np.ndarray, options: AssignmentOptions,
                 rejected: dict[str, int], kept_faces: np.ndarray | None = None) -> np.ndarray:
    """Unassign the points of faces that fail the minimum-count or planarity test. Faces in
    `kept_faces` (those of the previous assignment) are tested at `options.face_hysteresis`
    times the planarity limit: a face whose points are close to a line would otherwise come and
    go from one iteration to the next."""
    face_index = face_index.copy()
    faces, counts = np.unique(face_index[face_index >= 0], return_counts=True)
    kept = np.isin(faces, kept_faces) if kept_faces is not None else np.zeros(len(faces), bool)
    for face, count, relaxed in zip(faces, counts, kept):
        members = face_index == face
        factor = options.face_hysteresis if relaxed else 1.0
        if count < options.min_points_per_plane:
            reason = "too_few_points"
        elif planarity(points[members]) <= factor * options.planarity_threshold:
            reason = "not_planar"
        else:
            continue
        face_index[members] = -1
        rejected[reason] = rejected.get(reason, 0) + 1
    return face_index


def excluded_faces(store: PlaneStore, options: AssignmentOptions) -> np.ndarray:
    """Indices of faces that take no tie points: their semantic class is excluded, or they lie
    inside the city's volume as a whole (citymodel.visibility)."""
    return np.flatnonzero(class_mask(store, options.excluded_classes)
                          | visibility(store).hidden).astype(np.int64)


#: A neighbourhood is flat where its smallest covariance eigenvalue is below this share of
#: their sum (its "surface variation"; 1/3 for points without structure).
FLAT_VARIATION = 0.05


def local_surfaces(points: np.ndarray, neighbours: int) -> tuple[np.ndarray, np.ndarray]:
    """Per point: the unit normal of its `neighbours` nearest points (itself included) and
    whether they form a flat surface (`FLAT_VARIATION`; spread along two directions)."""
    from scipy.spatial import cKDTree

    n = len(points)
    if n < 3:
        return np.zeros((n, 3)), np.zeros(n, bool)
    k = min(int(neighbours), n)
    _, index = cKDTree(points).query(points, k=k)
    near = points[index]  # (n, k, 3)
    centred = near - near.mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", centred, centred) / k
    values, vectors = np.linalg.eigh(cov)
    total = np.maximum(values.sum(axis=1), 1e-18)
    # Flat: thin across, and spread along two directions (a line has no normal).
    flat = (values[:, 0] / total < FLAT_VARIATION) & (values[:, 1] / total > 2 * FLAT_VARIATION)
    return vectors[:, :, 0], flat


def hidden_points(points: np.ndarray, face_index: np.ndarray, store: PlaneStore) -> np.ndarray:
    """(P,) bool: assigned points whose projection onto their face meets a part of it that
    lies inside the city's volume (citymodel.visibility)."""
    out = np.zeros(len(points), bool)
    rows = np.flatnonzero(face_index >= 0)
    if not len(rows):
        return out
    faces = face_index[rows]
    normals = store.normals[faces]
    d = np.einsum("ij,ij->i", points[rows], normals) + store.offsets[faces]
    out[rows] = visibility(store).hidden_at(points[rows] - d[:, None] * normals, faces, normals)
    return out


