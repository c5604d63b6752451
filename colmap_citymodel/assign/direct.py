"""Direct assignment (method (a)): each tie point to the nearest model plane within the
threshold."""

from __future__ import annotations

import numpy as np

from ..citymodel.store import PlaneStore
from ..citymodel.visibility import visibility
from ..options import AssignmentOptions
from .assignment import Assignment, excluded_faces, filter_faces


def assign_direct(points: np.ndarray, point_ids: np.ndarray, store: PlaneStore,
                  threshold: float, options: AssignmentOptions,
                  weights: np.ndarray | None = None,
                  kept_faces: np.ndarray | None = None) -> Assignment:
    """Method (a): each tie point to its closest model face, if closer than `threshold`.

    "Closest" is the smallest absolute distance to a face's plane among the faces whose polygon
    contains the point's orthogonal projection (grown by `polygon_margin`) and that a camera
    can see there (citymodel.visibility: not inside the city's volume). `weights` play no
    part; `kept_faces`: see `filter_faces`.
    """
    vis = visibility(store)
    face_index, distance = store.closest_faces(
        points, max_distance=threshold, margin=options.polygon_margin, allowed=~vis.hidden,
        hidden=lambda feet, faces: vis.hidden_at(feet, faces, store.normals[faces]))
    excluded = excluded_faces(store, options)
    if len(excluded):
        face_index = np.where(np.isin(face_index, excluded), -1, face_index)
    rejected: dict[str, int] = {}
    face_index = filter_faces(points, face_index, options, rejected, kept_faces)
    distance = np.where(face_index >= 0, distance, np.nan)
    return Assignment(np.asarray(point_ids, dtype=np.int64), face_index, distance, threshold,
                      rejected)
