"""One entry for every assignment method, the automatic choice between them, and the
threshold schedule of the refine loop."""

from __future__ import annotations

import logging

import numpy as np

from ..citymodel.store import PlaneStore
from ..options import AssignmentOptions
from .assignment import (Assignment, Observers, PlaneAssigner, hidden_points,
                         roof_points_seen_from_below)
from .direct import assign_direct
from .ground import without_clutter_on_terrain
from .indirect import assign_msac, assign_roi_msac

logger = logging.getLogger(__name__)



def resolve_method(options: AssignmentOptions, threshold: float) -> str:
    """The method to run: `options.method`, or for "auto" the indirect method while
    `threshold` exceeds `options.auto_switch_threshold` and "direct" after."""
    if options.method != "auto":
        return options.method
    if threshold > options.auto_switch_threshold:
        return options.auto_indirect_method
    return "direct"


def assign(points: np.ndarray, point_ids: np.ndarray, store: PlaneStore, threshold: float,
           options: AssignmentOptions, weights: np.ndarray | None = None,
           observers: Observers | None = None, kept_faces: np.ndarray | None = None
           ) -> Assignment:
    """Assign tie points (local frame) to faces with the method of `options`. `weights`: per-point
    quality (higher = better, e.g. indirect.point_quality_weights), used by the MSAC methods
    when `options.weighted_sampling` is on. `observers`: where the points were seen from; with
    `options.roofs_seen_from_above` a roof keeps only the points seen from above it.
    `kept_faces`: the faces of the previous assignment, which keep their points at
    `options.face_hysteresis` times the planarity limit."""
    method = resolve_method(options, threshold)
    try:
        assigner = ASSIGNERS[method]
    except KeyError:
        from ..errors import InputError

        raise InputError(f"unknown assignment method {method!r}; "
                         f"available: {', '.join(sorted(ASSIGNERS))}, auto") from None
    if options.method == "auto":
        logger.info("assignment method auto: %s at threshold %.2f m (switch at %.2f m)",
                    method, threshold, options.auto_switch_threshold)
    result = assigner(points, point_ids, store, threshold, options, weights=weights,
                      kept_faces=kept_faces)
    result.method = method
    # Direct assignment chooses among the visible parts of faces already.
    hidden = (hidden_points(points, result.face_index, store) if method != "direct"
              else np.zeros(len(points), bool))
    if np.any(hidden):
        logger.debug("%d points on hidden parts of faces left unassigned",
                     int(np.count_nonzero(hidden)))
        result = result.eliminate(hidden, points, options, kept_faces)
    result = without_clutter_on_terrain(result, points, store, options, kept_faces)
    if observers is not None:
        result = without_roof_points_seen_from_below(result, points, store, observers, options,
                                                     kept_faces)
    logger.debug("assigned %d of %d points to %d faces (threshold %.3f m, rejected %s)",
                 result.num_assigned, len(point_ids), result.num_faces, threshold,
                 result.rejected_faces)
    return result


def without_roof_points_seen_from_below(assignment: Assignment, points: np.ndarray,
                                        store: PlaneStore, observers: Observers,
                                        options: AssignmentOptions,
                                        kept_faces: np.ndarray | None = None) -> Assignment:
    """`assignment` without the points on roofs that most of their images see from below
    (`options.roofs_seen_from_above`; faces left too small are dropped as usual)."""
    if not options.roofs_seen_from_above:
        return assignment
    below = roof_points_seen_from_below(points, assignment.face_index, store, observers)
    if not np.any(below):
        return assignment
    logger.debug("%d points near roofs but seen from below them left unassigned",
                 int(np.count_nonzero(below)))
    return assignment.eliminate(below, points, options, kept_faces)


def initial_threshold(options: AssignmentOptions) -> float:
    """Upper limit of the threshold, used in the first iteration: `max_threshold` (2 m) for
    direct assignment, `indirect_max_threshold` (3 m) for (b), (c) and "auto" (Unger 5.3)."""
    if options.method in ("msac", "roi_msac", "auto"):
        return options.indirect_max_threshold
    return options.max_threshold


def next_threshold(previous: Assignment, points: np.ndarray, store: PlaneStore,
                   options: AssignmentOptions, sigma: float) -> float:
    """Threshold schedule (Unger 4.2, 5.3): 3.5 x the mean over faces of the per-face mean
    |distance| of the previously assigned points (at their current coordinates), bounded to
    [2 sigma, initial_threshold(options)]; `sigma`: of a point's distance from its face's
    plane (sigma_dTP; adjust.loop.window_sigma)."""
    lower = options.min_threshold_sigmas * sigma
    upper = initial_threshold(options)
    assigned = previous.assigned
    if not np.any(assigned):
        return upper
    faces = previous.face_index[assigned]
    pts = points[assigned]
    distances = np.abs(np.einsum("ij,ij->i", pts, store.normals[faces]) + store.offsets[faces])
    unique_faces, inverse = np.unique(faces, return_inverse=True)
    per_face_mean = np.bincount(inverse, weights=distances) / np.bincount(inverse)
    threshold = options.threshold_factor * float(np.mean(per_face_mean))
    return float(np.clip(threshold, lower, upper))


ASSIGNERS: dict[str, PlaneAssigner] = {
    "direct": assign_direct,
    "msac": assign_msac,
    "roi_msac": assign_roi_msac,
}
