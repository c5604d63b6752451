"""Assignment of tie points to model planes (Unger chapter 4; method.md section 6).

Every method answers the same question: given the current tie point coordinates (local frame)
and the plane store, which tie point belongs to which model face? At most one face per point
per iteration. All methods finish with the same tests per face: a minimum number of points,
a planarity test on the eigenvalues l1 >= l2 >= l3 of the assigned points' covariance,
(l2 - l3) / l1 > threshold (rejects point sets close to a line), and a face seen only along
its outline (`edge_band`) is kept only where faces seen inside their outline already fix its
normal direction: alone, its eaves and parapets would set the block's position there.

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
                          dict(self.rejected_faces), self.method)


class PlaneAssigner(Protocol):
    """Interface of an assignment method. `weights`: per-point quality (higher = better) for
    methods that sample points; others ignore it."""

    def __call__(self, points: np.ndarray, point_ids: np.ndarray, store: PlaneStore,
                 threshold: float, options: AssignmentOptions,
                 weights: np.ndarray | None = None) -> Assignment: ...


def planarity(points: np.ndarray) -> float:
    """(l2 - l3) / l1 of the covariance eigenvalues l1 >= l2 >= l3 (0 for a line or a point)."""
    if len(points) < 3:
        return 0.0
    eigenvalues = np.linalg.eigvalsh(np.cov(points.T))[::-1]
    if eigenvalues[0] <= 0:
        return 0.0
    return float((eigenvalues[1] - eigenvalues[2]) / eigenvalues[0])


def filter_faces(points: np.ndarray, face_index: np.ndarray, options: AssignmentOptions,
                 rejected: dict[str, int], store: PlaneStore | None = None) -> np.ndarray:
    """Unassign the points of faces that fail the minimum-count or planarity test, and, given
    the `store` the faces belong to, of faces seen only along their outline (fewer than the
    minimum count farther than `edge_band` inside it) whose normal direction no face seen
    inside its outline fixes (edge_only_alone)."""
    face_index = face_index.copy()
    faces, counts = np.unique(face_index[face_index >= 0], return_counts=True)
    interior = None
    if store is not None and options.edge_band > 0 and len(faces):
        on = face_index >= 0
        interior = np.zeros(len(face_index), bool)
        interior[on] = store.edge_distance(face_index[on], points[on]) > options.edge_band
    edge_only = []
    for face, count in zip(faces, counts):
        members = face_index == face
        if count < options.min_points_per_plane:
            reason = "too_few_points"
        elif planarity(points[members]) <= options.planarity_threshold:
            reason = "not_planar"
        else:
            if (interior is not None
                    and np.count_nonzero(interior[members]) < options.min_points_per_plane):
                edge_only.append(int(face))
            continue
        face_index[members] = -1
        rejected[reason] = rejected.get(reason, 0) + 1
    if edge_only:
        kept = np.setdiff1d(np.unique(face_index[face_index >= 0]), edge_only)
        for face in unsupported_directions(store.normals[kept], store.normals[edge_only]):
            face_index[face_index == edge_only[face]] = -1
            rejected["edge_only_alone"] = rejected.get("edge_only_alone", 0) + 1
    return face_index


def unsupported_directions(normals: np.ndarray, candidates: np.ndarray,
                           max_sigma: float = 2.0) -> np.ndarray:
    """Indices of `candidates` (unit normals) along which the planes with `normals` fix a
    translation only to more than `max_sigma` times what one plane along it does (each plane
    one unit of information along its normal: its points share its generalisation error)."""
    information = normals.T @ normals + 1e-9 * np.eye(3)
    variance = np.einsum("ij,jk,ik->i", candidates, np.linalg.inv(information), candidates)
    return np.flatnonzero(variance > max_sigma ** 2)


def excluded_faces(store: PlaneStore, options: AssignmentOptions) -> np.ndarray:
    """Indices of faces whose semantic class takes no tie points."""
    return np.array([i for i, f in enumerate(store.faces)
                     if f.semantic in options.excluded_classes], dtype=np.int64)


