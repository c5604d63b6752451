"""Indirect assignment: planes found in the tie point cloud by MSAC, then related to model planes
(Unger 4.3; method.md section 6 (b) and (c)). The estimator is in assign/msac.py.

(b) "msac", without ROIs (Unger 4.3.1). Planes are extracted one after the other from the whole
cloud: the best MSAC plane, its inliers projected into it and split into connected components of
their alpha shape (radius `alpha_radius`), the largest component kept, the plane refit to it and
its points removed from the cloud; until the best plane's largest component has too few points
`msac_max_failures` times in a row. Then each extracted plane is matched to the model face with
normal within `max_normal_angle`, whose plane is closer than `threshold` to the centroid of the
extracted plane's boundary points, and whose polygon contains that centroid's projection (the
closest such face if several do). Points whose projection falls outside the matched polygon are
dropped. Several extracted planes may match one model face. Beyond Unger: half the MSAC samples
are local (`msac_sample_cell`), and an inlier's point normal must agree with the plane's
(`msac_point_normal_angle`, as in Mulder's RANSAC): once the large planes are gone, a slab that
cuts every facade of a street otherwise holds more points than any one facade, and is extracted
as strips. Also beyond Unger: the segmentation is made once and followed through the iterations
while its planes stay planar (`msac_keep_segmentation`); a new random extraction in every
iteration assigns differently each time, and the loop does not settle.

(c) "roi_msac", with ROIs (Unger 4.3.2). A face's ROI is the tie points closer than `threshold`
to its plane whose projection lies inside its polygon; a point in several ROIs belongs to the
closest face: these are exactly the candidates of direct assignment, `PlaneStore.closest_faces`.
In each ROI, MSAC searches one plane whose normal is within `max_normal_angle` of the model normal;
its inliers (inside the polygon by construction of the ROI) are assigned.

Both end with the minimum-count and planarity tests of every method (`filter_faces`; the
faces of the previous assignment at `face_hysteresis` times the planarity limit). With
`weighted_sampling` and per-point weights (`point_quality_weights`), both sample by weight
(weighted RANSAC, Mulder 4.4).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from ..citymodel.store import PlaneStore
from ..options import AssignmentOptions
from .assignment import Assignment, excluded_faces, filter_faces
from .msac import alpha_components, boundary_centroid, fit_plane, msac_plane, plane_coordinates, point_normals

logger = logging.getLogger(__name__)


# ----------------------------------------------------------------------------------------------
# (b): sequential extraction and plane matching
# ----------------------------------------------------------------------------------------------


@dataclass
class ExtractedPlane:
    """A plane found in the tie point cloud: n.X + d = 0 (sign of n arbitrary), its points
    (indices into the cloud) and the centroid of its alpha shape's boundary (3D, on the plane)."""

    normal: np.ndarray
    offset: float
    members: np.ndarray
    centroid: np.ndarray
    #: share of the members within the inlier distance of the plane (refitted to them)
    inlier_share: float = 1.0


#: The last extraction with the default generator: (points, weights, options, planes, point
#: ids). Refine assigns the same tie points again in every iteration, moved by the last solve;
#: when it undoes an iteration they are the extraction's points moved by a similarity and back.
_last_extraction: tuple | None = None
#: Points no farther (m, per coordinate) from the last call's count as the same points.
_SAME_POINTS = 1e-9


def _same_setting(last: tuple | None, points: np.ndarray, weights: np.ndarray | None,
                  options: AssignmentOptions) -> bool:
    if last is None:
        return False
    last_points, last_weights, last_options = last[:3]
    return (points.shape == last_points.shape and repr(options) == last_options
            and (weights is None) == (last_weights is None)
            and (weights is None or np.array_equal(weights, last_weights)))


#: The segmentation is kept (msac_keep_segmentation) while no extracted plane, refitted to its
#: moved points, has lost more than this share of them from its inlier band.
MAX_LOST_SHARE = 0.05


def _followed_planes(points: np.ndarray, planes: list[ExtractedPlane], moved: np.ndarray,
                     weights: np.ndarray | None, inlier_distance: float
                     ) -> list[ExtractedPlane] | None:
    """The planes of the last extraction refitted to their moved members, each boundary
    centroid moved with its members' mean displacement onto the refitted plane; None when a
    plane's members no longer lie on one plane (MAX_LOST_SHARE more of them outside
    `inlier_distance` than at the extraction)."""
    out = []
    for plane in planes:
        members = plane.members
        on_plane = points[members]
        normal, offset = fit_plane(on_plane, None if weights is None else weights[members])
        share = float(np.mean(np.abs(on_plane @ normal + offset) <= inlier_distance))
        if share < plane.inlier_share - MAX_LOST_SHARE:
            return None
        centroid = plane.centroid + moved[members].mean(0)
        centroid = centroid - (normal @ centroid + offset) * normal
        out.append(ExtractedPlane(normal, offset, members, centroid, plane.inlier_share))
    return out


def extract_planes(points: np.ndarray, options: AssignmentOptions,
                   weights: np.ndarray | None = None,
                   rng: np.random.Generator | None = None,
                   point_ids: np.ndarray | None = None) -> list[ExtractedPlane]:
    """Sequential MSAC with connected components (method (b)'s first stage, Unger 4.3.1).
    Without `rng` (the generator seeded by `options.random_seed`) the result depends on the
    points, weights and options only, as far as `msac_keep_segmentation` allows: a call with
    the last extraction's points (to `_SAME_POINTS`), weights and options returns its planes
    again; one with the same `point_ids` (the same tie points, moved) gets them refitted while
    they stay planar."""
    global _last_extraction
    points = np.asarray(points, dtype=np.float64)
    if rng is not None:
        return _extract_planes(points, options, weights, rng)
    last = _last_extraction  # read once: refines in other threads may replace it
    if _same_setting(last, points, weights, options):
        last_points, _, _, last_planes, last_ids = last
        moved = points - last_points
        if bool(np.all(np.abs(moved) <= _SAME_POINTS)):
            logger.debug("extraction reused: the same %d points as the last call", len(points))
            return list(last_planes)
        if options.msac_keep_segmentation and point_ids is not None \
                and last_ids is not None and np.array_equal(point_ids, last_ids):
            # Always against the extraction's own points, so that moves cannot add up unseen.
            followed = _followed_planes(points, last_planes, moved, weights,
                                        options.msac_inlier_distance)
            if followed is not None:
                logger.debug("segmentation kept: %d planes refitted to their moved points",
                             len(followed))
                return followed
    planes = _extract_planes(points, options, weights, np.random.default_rng(options.random_seed))
    _last_extraction = (points.copy(), None if weights is None else np.array(weights, float),
                        repr(options), planes,
                        None if point_ids is None else np.array(point_ids, np.int64))
    return list(planes)


def _extract_planes(points: np.ndarray, options: AssignmentOptions,
                    weights: np.ndarray | None, rng: np.random.Generator
                    ) -> list[ExtractedPlane]:
    threshold, min_points = options.msac_inlier_distance, options.min_points_per_plane
    if len(points) < max(min_points, 3):
        return []
    cells = np.floor((points - points.min(0)) / options.msac_sample_cell).astype(np.int64)
    dims = cells.max(0) + 1
    keys = cells[:, 0] + dims[0] * (cells[:, 1] + dims[1] * cells[:, 2])
    order = np.argsort(keys, kind="stable")  # the remaining points stay sorted by cell
    normals = (point_normals(points, options.msac_point_normal_neighbours)
               if options.msac_point_normal_angle < 90.0 else None)
    # the points not yet in a plane, kept sorted by cell and compacted after each plane
    remaining = order
    # (take: row gathers several times faster than fancy or boolean indexing)
    pts, cell_keys = points.take(order, 0), keys[order]
    w = None if weights is None else weights[order]
    pts_normals = None if normals is None else normals.take(order, 0)
    planes: list[ExtractedPlane] = []
    failures = 0
    while len(planes) < options.msac_max_planes and len(remaining) >= min_points:
        found = msac_plane(pts, threshold, options, rng, weights=w, cell_keys=cell_keys,
                           normals_of_points=pts_normals)
        if found is None:
            break
        normal, offset, inlier_mask = found
        inliers = np.flatnonzero(inlier_mask)
        if len(inliers) < min_points:
            break
        labels = alpha_components(plane_coordinates(pts.take(inliers, 0), normal),
                                  options.alpha_radius)
        sizes = np.bincount(labels)
        if sizes.max() < min_points:
            failures += 1
            if failures >= options.msac_max_failures:
                break
            continue
        failures = 0
        component = inliers[labels == int(np.argmax(sizes))]
        component_points = pts.take(component, 0)
        normal, offset = fit_plane(component_points, None if w is None else w[component])
        uv = plane_coordinates(component_points, normal)
        centre_uv = boundary_centroid(uv, options.alpha_radius)
        # back to 3D: the point on the plane with those in-plane coordinates
        basis = plane_coordinates(np.eye(3), normal)  # rows: e_k -> (u_k, v_k)
        centroid = basis @ centre_uv - offset * normal
        share = float(np.mean(np.abs(component_points @ normal + offset) <= threshold))
        planes.append(ExtractedPlane(normal, offset, remaining[component], centroid, share))
        keep = np.ones(len(remaining), bool)
        keep[component] = False
        kept = np.flatnonzero(keep)
        remaining, pts, cell_keys = remaining[kept], pts.take(kept, 0), cell_keys[kept]
        w = None if w is None else w[kept]
        pts_normals = None if pts_normals is None else pts_normals.take(kept, 0)
    logger.debug("extracted %d planes holding %d of %d points", len(planes),
                 len(points) - len(remaining), len(points))
    return planes


def match_planes(planes: list[ExtractedPlane], store: PlaneStore, threshold: float,
                 options: AssignmentOptions) -> np.ndarray:
    """Model face of each extracted plane, -1 for none: normal angle below `max_normal_angle`,
    boundary centroid closer than `threshold` to the model plane and projecting inside its
    polygon (grown by `polygon_margin`); the closest of several candidates."""
    match = np.full(len(planes), -1, np.int64)
    if not planes or store.num_faces == 0:
        return match
    normals = np.array([p.normal for p in planes])
    centroids = np.array([p.centroid for p in planes])
    cosine = np.abs(normals @ store.normals.T)
    distance = np.abs(centroids @ store.normals.T + store.offsets)
    candidate = (cosine >= math.cos(math.radians(options.max_normal_angle))) \
        & (distance < threshold)
    candidate[:, excluded_faces(store, options)] = False
    plane, face = np.nonzero(candidate)
    inside = np.array([store.contains_projection(int(f), centroids[p], options.polygon_margin)[0]
                       for p, f in zip(plane, face)], dtype=bool)
    plane, face = plane[inside], face[inside]
    order = np.lexsort((distance[plane, face], plane))
    plane, face = plane[order], face[order]
    first = np.r_[True, plane[1:] != plane[:-1]] if len(plane) else np.zeros(0, bool)
    match[plane[first]] = face[first]
    return match


def _finish(points: np.ndarray, point_ids: np.ndarray, store: PlaneStore, face_index: np.ndarray,
            threshold: float, options: AssignmentOptions, rejected: dict[str, int],
            method: str, kept_faces: np.ndarray | None) -> Assignment:
    face_index = filter_faces(points, face_index, options, rejected, kept_faces)
    distance = np.full(len(points), np.nan)
    on = face_index >= 0
    distance[on] = (np.einsum("ij,ij->i", points[on], store.normals[face_index[on]])
                    + store.offsets[face_index[on]])
    return Assignment(np.asarray(point_ids, dtype=np.int64), face_index, distance, threshold,
                      rejected, method)


def _weights_for(weights: np.ndarray | None, options: AssignmentOptions, n: int
                 ) -> np.ndarray | None:
    if not options.weighted_sampling:
        return None
    if weights is None:
        logger.warning("weighted_sampling is on but no point weights were given; sampling "
                       "uniformly")
        return None
    weights = np.asarray(weights, dtype=np.float64)
    if weights.shape != (n,):
        raise ValueError(f"weights must have shape ({n},), got {weights.shape}")
    return weights


def assign_msac(points: np.ndarray, point_ids: np.ndarray, store: PlaneStore, threshold: float,
                options: AssignmentOptions, weights: np.ndarray | None = None,
                kept_faces: np.ndarray | None = None) -> Assignment:
    """Method (b): planes extracted from the whole cloud, matched to model faces; `threshold`
    bounds the distance of an extracted plane's boundary centroid to the model plane."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    weights = _weights_for(weights, options, len(points))
    planes = extract_planes(points, options, weights, point_ids=point_ids)
    match = match_planes(planes, store, threshold, options)
    face_index = np.full(len(points), -1, np.int64)
    for plane, face in zip(planes, match):
        if face < 0:
            continue
        inside = store.contains_projection(int(face), points[plane.members],
                                           options.polygon_margin)
        face_index[plane.members[inside]] = face
    rejected = {"unmatched_extracted_planes": int(np.count_nonzero(match < 0))} \
        if np.any(match < 0) else {}
    logger.debug("msac: %d extracted planes, %d matched to %d faces", len(planes),
                 int(np.count_nonzero(match >= 0)), len(np.unique(match[match >= 0])))
    return _finish(points, point_ids, store, face_index, threshold, options, rejected, "msac",
                   kept_faces)


# ----------------------------------------------------------------------------------------------
# (c): MSAC in the ROI of each model plane
# ----------------------------------------------------------------------------------------------


def assign_roi_msac(points: np.ndarray, point_ids: np.ndarray, store: PlaneStore,
                    threshold: float, options: AssignmentOptions,
                    weights: np.ndarray | None = None,
                    kept_faces: np.ndarray | None = None) -> Assignment:
    """Method (c): per model face, MSAC with the normal constraint on the points of its ROI
    (search distance `threshold`); the inliers are assigned."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    weights = _weights_for(weights, options, len(points))
    rng = np.random.default_rng(options.random_seed)
    roi, _ = store.closest_faces(points, max_distance=threshold, margin=options.polygon_margin)
    excluded = excluded_faces(store, options)
    if len(excluded):
        roi = np.where(np.isin(roi, excluded), -1, roi)
    face_index = np.full(len(points), -1, np.int64)
    rejected: dict[str, int] = {}
    members = np.flatnonzero(roi >= 0)
    members = members[np.argsort(roi[members], kind="stable")]
    faces, starts, counts = np.unique(roi[members], return_index=True, return_counts=True)
    inlier_distance = options.roi_inlier_distance
    for face, start, count in zip(faces, starts, counts):
        if count < options.min_points_per_plane:
            rejected["too_few_points"] = rejected.get("too_few_points", 0) + 1
            continue
        idx = members[start:start + count]
        pts = points[idx]
        found = msac_plane(pts, inlier_distance, options, rng,
                           weights=None if weights is None else weights[idx],
                           reference=store.normals[face])
        if found is None:
            rejected["no_plane_in_roi"] = rejected.get("no_plane_in_roi", 0) + 1
            continue
        face_index[idx[found[2]]] = face
    return _finish(points, point_ids, store, face_index, threshold, options, rejected,
                   "roi_msac", kept_faces)


# ----------------------------------------------------------------------------------------------
# quality weights for weighted RANSAC
# ----------------------------------------------------------------------------------------------


def point_quality_weights(reconstruction, point_ids: np.ndarray) -> np.ndarray:
    """Per tie point a quality weight (higher = better), normalised to median 1:
    sqrt(track length) x sin(largest angle between two of its image rays).

    A point's depth error from two rays meeting at angle theta grows like 1 / sin(theta), and
    averaging over L rays divides it by about sqrt(L), so the weight is proportional to the
    inverse of that error at a given distance (Mulder 4.4.1 weights by the points' a posteriori
    sigma, which depends on the same two quantities). Points with fewer than two images get 0.
    """
    point_ids = np.asarray(point_ids, dtype=np.int64)
    xyz = np.zeros((len(point_ids), 3))
    lengths = np.zeros(len(point_ids), np.int64)
    image_ids: list[int] = []
    for k, pid in enumerate(point_ids):
        point = reconstruction.point3D(int(pid))
        elements = point.track.elements
        lengths[k] = len(elements)
        image_ids.extend(e.image_id for e in elements)
        xyz[k] = point.xyz
    image_ids = np.asarray(image_ids, np.int64)
    registered = list(reconstruction.reg_image_ids())
    centres = np.full((max(registered + [int(image_ids.max(initial=0))]) + 1, 3), np.nan)
    for i in registered:  # images without a pose give no ray (nan, ignored)
        centres[i] = reconstruction.image(i).projection_center()
    rays = np.repeat(xyz, lengths, axis=0) - centres[image_ids]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    # largest pairwise angle per point, in blocks of points with equal track length
    sine = np.zeros(len(point_ids))
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    for length in np.unique(lengths[lengths >= 2]):
        which = np.flatnonzero(lengths == length)
        for chunk in np.array_split(which, max(1, len(which) * length * length // 4_000_000)):
            block = rays[starts[chunk, None] + np.arange(length)]  # (m, L, 3)
            cosine = np.einsum("mai,mbi->mab", block, block)
            cosine = np.where(np.isnan(cosine), 1.0, cosine).min(axis=(1, 2))
            angle = np.arccos(np.clip(cosine, -1.0, 1.0))
            sine[chunk] = np.sin(np.minimum(angle, np.pi / 2))
    weights = np.sqrt(lengths) * sine
    positive = weights[weights > 0]
    return weights / np.median(positive) if len(positive) else weights
