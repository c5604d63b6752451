"""Direct assignment (method (a)): each tie point to the nearest model plane within the
threshold."""

from __future__ import annotations

import numpy as np

from ..citymodel.store import PlaneStore
from ..citymodel.visibility import visibility
from ..options import AssignmentOptions
from .assignment import Assignment, excluded_faces, filter_faces, local_surfaces


def assign_direct(points: np.ndarray, point_ids: np.ndarray, store: PlaneStore,
                  threshold: float, options: AssignmentOptions,
                  weights: np.ndarray | None = None,
                  kept_faces: np.ndarray | None = None) -> Assignment:
    """Method (a): each tie point to its closest model face, if closer than `threshold`.

    "Closest" is the smallest absolute distance to a face's plane among the faces whose polygon
    contains the point's orthogonal projection (grown by `polygon_margin`) and that a camera
    can see there (citymodel.visibility: not inside the city's volume). A point whose next face
    off that plane is not `ambiguity_margin` further away, or (an option) whose flat
    neighbourhood turns more than `point_normal_angle` from the face, is not assigned. `weights` play no
    part; `kept_faces`: see `filter_faces`.
    """
    vis = visibility(store)
    runner_up = np.full(len(points), np.inf)
    face_index, distance = store.closest_faces(
        points, max_distance=threshold, margin=options.polygon_margin, allowed=~vis.hidden,
        hidden=lambda feet, faces: vis.hidden_at(feet, faces, store.normals[faces]),
        runner_up=runner_up)
    assigned = face_index >= 0
    if options.ambiguity_margin > 0:
        ambiguous = assigned & (runner_up - np.abs(np.nan_to_num(distance))
                                < options.ambiguity_margin)
        face_index[ambiguous] = -1
    if options.point_normal_angle < 180 and np.any(face_index >= 0):
        rows = np.flatnonzero(face_index >= 0)
        normals, flat = local_surfaces(points, options.point_normal_neighbours)
        cos = np.abs(np.einsum("ij,ij->i", normals[rows], store.normals[face_index[rows]]))
        off = flat[rows] & (cos < np.cos(np.radians(options.point_normal_angle)))
        face_index[rows[off]] = -1
    excluded = excluded_faces(store, options)
    if len(excluded):
        face_index = np.where(np.isin(face_index, excluded), -1, face_index)
    rejected: dict[str, int] = {}
    face_index = filter_faces(points, face_index, options, rejected, kept_faces)
    distance = np.where(face_index >= 0, distance, np.nan)
    return Assignment(np.asarray(point_ids, dtype=np.int64), face_index, distance, threshold,
                      rejected)


def centred_surfaces(points: np.ndarray, point_ids: np.ndarray, store: PlaneStore,
                     threshold: float, options: AssignmentOptions) -> PlaneStore:
    """`store` with each face moved to its own surface: the median signed distance of the
    points `assign_direct` gives it within `threshold + options.window_reach` (faces without
    points stay). An assignment within `threshold` of these takes a face's points evenly from
    both sides of where they lie, so that it does not follow the block towards the plane."""
    wide = assign_direct(points, point_ids, store, threshold + options.window_reach, options)
    faces = wide.face_index[wide.assigned]
    distance = wide.distance[wide.assigned]
    shifts = np.zeros(store.num_faces)
    order = np.argsort(faces, kind="stable")
    faces, distance = faces[order], distance[order]
    starts = np.flatnonzero(np.r_[True, faces[1:] != faces[:-1]]) if len(faces) else []
    for begin, end in zip(starts, list(starts[1:]) + [len(faces)]):
        shifts[faces[begin]] = -np.median(distance[begin:end])
    return store.with_plane_shifts(shifts)
