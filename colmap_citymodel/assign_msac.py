"""Indirect assignment: planes found in the tie point cloud by MSAC, then related to model planes
(Unger 4.3; method.md section 6 (b) and (c)).

(b) "msac", without ROIs (Unger 4.3.1). Planes are extracted one after the other from the whole
cloud: the best MSAC plane, its inliers projected into it and split into connected components of
their alpha shape (radius `alpha_radius`), the largest component kept, the plane refit to it and
its points removed from the cloud; until the best plane's largest component has too few points
`msac_max_failures` times in a row. Then each extracted plane is matched to the model face with
normal within `max_normal_angle`, whose plane is closer than `threshold` to the centroid of the
extracted plane's boundary points, and whose polygon contains that centroid's projection (the
closest such face if several do). Points whose projection falls outside the matched polygon are
dropped. Several extracted planes may match one model face.

(c) "roi_msac", with ROIs (Unger 4.3.2). A face's ROI is the tie points closer than `threshold`
to its plane whose projection lies inside its polygon; a point in several ROIs belongs to the
closest face: these are exactly the candidates of direct assignment, `PlaneStore.closest_faces`.
In each ROI, MSAC searches one plane whose normal is within `max_normal_angle` of the model normal;
its inliers (inside the polygon by construction of the ROI) are assigned.

Both end with the minimum-count and planarity tests of every method (`filter_faces`).

MSAC (Torr and Zisserman 2000) scores a hypothesis by the truncated quadratic cost
sum min(d^2, T^2) rather than RANSAC's inlier count: of two planes with equally many inliers the
closer fit wins. Here hypotheses are drawn in batches and scored, vectorised, on a random
subsample of at most `msac_sample_points` points; the best few are scored again on all points.
The number of hypotheses follows the best inlier fraction so far (`msac_confidence`), bounded by
`msac_max_trials`. The winner is refit by least squares to its inliers twice (the local
optimisation of LO-RANSAC), so that a hypothesis from three nearby points extends to the whole
plane. In (b), half the samples take their three points from one cube of side
`msac_sample_cell`: three random points of a street's cloud almost never lie on one of its
hundreds of planes.

Weighted RANSAC (Mulder 4.4), with `weighted_sampling` and per-point weights (higher = better,
e.g. `point_quality_weights`): sample points are drawn with probability proportional to their
weight, and refits are weighted least squares; the MSAC cost stays unweighted. Mulder's second
inlier test (the point normal from six neighbours close to the plane normal) is left out: tie
points are too sparse and noisy for such normals.

Libraries considered. Open3D's `PointCloud.segment_plane` is RANSAC (inlier count, ties by
RMSE) with uniform sampling that scores every hypothesis on every point: no weights, no normal
constraint for (c), no local sampling. Its `detect_planar_patches` (robust statistics on an
octree, Araujo and Oliveira 2020) is another detector altogether and returns oriented boxes, not
point memberships. shapely's `concave_hull` gives one hull polygon, not connected components.
So MSAC is written here in numpy, the alpha-shape components come from a grid (`alpha_components`)
and the boundary from scipy's Delaunay triangulation (`boundary_centroid`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError

from .assign_planes import Assignment, excluded_faces, filter_faces
from .options import AssignmentOptions
from .plane_store import PlaneStore

logger = logging.getLogger("colmap_citymodel.assign_msac")

#: Hypotheses drawn per vectorised batch, and how many of a run's best are scored on all points.
_BATCH = 64
_RESCORED = 8
#: Smallest number of hypotheses even when the first batch looks all-inlier.
_MIN_TRIALS = 64


# ----------------------------------------------------------------------------------------------
# plane fitting and MSAC
# ----------------------------------------------------------------------------------------------


def fit_plane(points: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(Weighted) least-squares plane: unit normal n and offset d with n.X + d = 0; n is the
    eigenvector of the smallest eigenvalue of the weighted covariance about the weighted
    centroid."""
    w = np.ones(len(points)) if weights is None else np.asarray(weights, float)
    centre = (w[:, None] * points).sum(0) / w.sum()
    centred = points - centre
    _, vectors = np.linalg.eigh((w[:, None] * centred).T @ centred)
    normal = vectors[:, 0]
    return normal, float(-normal @ centre)


def _cell_ranges(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For nondecreasing `keys`: first and one-past-last position of each element's run."""
    change = np.flatnonzero(np.diff(keys)) + 1
    starts = np.r_[0, change]
    ends = np.r_[change, len(keys)]
    run = np.repeat(np.arange(len(starts)), ends - starts)
    return starts[run], ends[run]


class _Sampler:
    """Draws point triples: globally, or (with `cell_keys`) two more points from the first
    point's cell; with `weights`, each draw has probability proportional to the weight."""

    def __init__(self, n: int, rng: np.random.Generator, weights: np.ndarray | None,
                 cell_keys: np.ndarray | None):
        self.n, self.rng = n, rng
        w = np.ones(n) if weights is None else np.maximum(np.asarray(weights, float), 0.0)
        if not w.sum() > 0:
            w = np.ones(n)
        self.cumulative = np.cumsum(w)
        self.local = None
        if cell_keys is not None:
            start, end = _cell_ranges(cell_keys)
            if np.any(end - start >= 3):
                self.local = (start, end)

    def _draw(self, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """Indices drawn in [low, high) with probability proportional to the weights."""
        c = self.cumulative
        below = np.where(low > 0, c[np.maximum(low - 1, 0)], 0.0)
        u = below + self.rng.random(len(low)) * (c[high - 1] - below)
        return np.minimum(np.searchsorted(c, u, side="right"), high - 1)

    def triples(self, k: int) -> np.ndarray:
        zeros, full = np.zeros(k, np.int64), np.full(k, self.n, np.int64)
        if self.local is None:
            return np.stack([self._draw(zeros, full) for _ in range(3)], 1)
        half = k // 2
        glob = np.stack([self._draw(zeros[:half], full[:half]) for _ in range(3)], 1)
        first = self._draw(zeros[half:], full[half:])
        lo, hi = self.local[0][first], self.local[1][first]
        loc = np.stack([first, self._draw(lo, hi), self._draw(lo, hi)], 1)
        return np.vstack([glob, loc])


def _hypotheses(points: np.ndarray, triples: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planes through point triples; degenerate (repeated or nearly collinear) ones dropped."""
    a, b, c = points[triples[:, 0]], points[triples[:, 1]], points[triples[:, 2]]
    ab, ac = b - a, c - a
    normals = np.cross(ab, ac)
    length = np.linalg.norm(normals, axis=1)
    scale = np.linalg.norm(ab, axis=1) * np.linalg.norm(ac, axis=1)
    ok = length > 1e-3 * np.maximum(scale, 1e-300)  # sine of the angle at a above 1e-3
    normals = normals[ok] / length[ok, None]
    return normals, -np.einsum("ki,ki->k", normals, a[ok])


def _msac_cost(points: np.ndarray, normals: np.ndarray, offsets: np.ndarray,
               inlier_distance: float, point_normals: np.ndarray | None = None,
               min_cos: float = 0.0) -> np.ndarray:
    """MSAC's cost of each hypothesis: sum over points of min(d^2, T^2) (lower is better); with
    `point_normals`, points whose normal is farther than acos(min_cos) from the plane's count
    as outliers (T^2)."""
    t2 = inlier_distance * inlier_distance
    d2 = points @ normals.T
    d2 += offsets
    np.square(d2, out=d2)
    np.minimum(d2, t2, out=d2)
    if point_normals is not None:
        d2[np.abs(point_normals @ normals.T) < min_cos] = t2
    return d2.sum(0)


def _inliers(points: np.ndarray, normal: np.ndarray, offset: float, inlier_distance: float,
             point_normals: np.ndarray | None = None, min_cos: float = 0.0) -> np.ndarray:
    """Inlier mask of one plane (distance, and with `point_normals` the normal angle)."""
    inside = np.abs(points @ normal + offset) < inlier_distance
    if point_normals is not None:
        inside &= np.abs(point_normals @ normal) >= min_cos
    return inside


def point_normals(points: np.ndarray, neighbours: int) -> np.ndarray:
    """Unit normal of each point from its `neighbours` nearest neighbours (itself included):
    Open3D's `estimate_normals`, the smallest principal axis of the neighbourhood."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(neighbours))
    return np.asarray(cloud.normals)


def msac_plane(points: np.ndarray, inlier_distance: float, options: AssignmentOptions,
               rng: np.random.Generator, *, weights: np.ndarray | None = None,
               cell_keys: np.ndarray | None = None, reference: np.ndarray | None = None,
               normals_of_points: np.ndarray | None = None
               ) -> tuple[np.ndarray, float] | None:
    """The best plane of `points` by MSAC (unit normal, offset), refit to its inliers; None if
    no hypothesis exists (fewer than three points, all collinear, or none within the angle).

    `reference`: unit normal; only planes whose normal is within `options.max_normal_angle`
    of it (either sign) are considered. `cell_keys`: nondecreasing cell id per point for local
    sampling. `weights`: weighted sampling and weighted refits. `normals_of_points`: a point is
    an inlier only if its normal is within `options.msac_point_normal_angle` of the plane's.
    """
    n = len(points)
    if n < 3:
        return None
    sampler = _Sampler(n, rng, weights, cell_keys)
    subset = (rng.choice(n, options.msac_sample_points, replace=False)
              if n > options.msac_sample_points else np.arange(n))
    scored = points[subset]
    scored_normals = None if normals_of_points is None else normals_of_points[subset]
    min_cos = math.cos(math.radians(options.max_normal_angle))
    point_cos = math.cos(math.radians(options.msac_point_normal_angle))
    log_fail = math.log(max(1.0 - options.msac_confidence, 1e-12))
    kept_normals, kept_offsets, kept_costs = [], [], []
    best_fraction, trials, needed = 0.0, 0, options.msac_max_trials
    while trials < needed:
        normals, offsets = _hypotheses(points, sampler.triples(_BATCH))
        trials += _BATCH
        if reference is not None:
            ok = np.abs(normals @ reference) >= min_cos
            normals, offsets = normals[ok], offsets[ok]
        if len(normals) == 0:
            continue
        cost = _msac_cost(scored, normals, offsets, inlier_distance, scored_normals, point_cos)
        top = np.argsort(cost)[:_RESCORED]
        kept_normals.append(normals[top])
        kept_offsets.append(offsets[top])
        kept_costs.append(cost[top])
        inliers = _inliers(scored, normals[top[0]], offsets[top[0]], inlier_distance,
                           scored_normals, point_cos)
        best_fraction = max(best_fraction, np.count_nonzero(inliers) / len(scored))
        if best_fraction > 0:
            miss = 1.0 - best_fraction ** 3
            adaptive = (log_fail / math.log(miss) if 0.0 < miss < 1.0
                        else 0.0 if miss <= 0.0 else math.inf)
            needed = int(min(options.msac_max_trials, max(_MIN_TRIALS, adaptive)))
    if not kept_normals:
        return None
    normals, offsets = np.vstack(kept_normals), np.concatenate(kept_offsets)
    top = np.argsort(np.concatenate(kept_costs))[:_RESCORED]
    normals, offsets = normals[top], offsets[top]
    if len(subset) < n:  # the best few again, on all points
        best = int(np.argmin(_msac_cost(points, normals, offsets, inlier_distance,
                                        normals_of_points, point_cos)))
    else:
        best = 0
    normal, offset = normals[best], float(offsets[best])
    for _ in range(2):  # local optimisation: least squares on the inliers
        inliers = _inliers(points, normal, offset, inlier_distance, normals_of_points,
                           point_cos)
        if np.count_nonzero(inliers) < 3:
            break
        refit, refit_offset = fit_plane(points[inliers],
                                        None if weights is None else weights[inliers])
        if reference is not None and abs(refit @ reference) < min_cos:
            break
        normal, offset = refit, refit_offset
    return normal, offset


# ----------------------------------------------------------------------------------------------
# alpha shapes of an extracted plane's points
# ----------------------------------------------------------------------------------------------


def plane_coordinates(points: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """2D coordinates of the points' orthogonal projections in a frame of the plane."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    return np.column_stack([points @ u, points @ v])


def alpha_components(uv: np.ndarray, radius: float) -> np.ndarray:
    """Connected-component label (0, 1, ...) of each 2D point under alpha shapes of `radius`.

    The alpha complex of radius r has the connectivity of the union of discs of radius r around
    the points (Edelsbrunner et al. 1983): two points are connected when a chain of points at
    most 2r apart joins them. It is computed on a grid of cell side r/4, linking occupied cells
    whose closest distance is at most 2r: points at most 2r apart always share a component, and
    no link is longer than 2r plus a cell diagonal (2.71 r). Linear in the number of points,
    whatever their density. Unlike MATLAB's alphaShape regions, a component need not contain a
    triangle (two isolated points 1.5 r apart form one).
    """
    if len(uv) == 0:
        return np.zeros(0, np.int64)
    cell, link = radius / 4.0, 2.0 * radius
    reach = int(math.ceil(link / cell)) + 1
    ij = np.floor((uv - uv.min(0)) / cell).astype(np.int64)
    stride = int(ij[:, 1].max()) + 1 + 2 * reach
    keys, inverse = np.unique(ij[:, 0] * stride + ij[:, 1] + reach, return_inverse=True)
    di, dj = np.meshgrid(np.arange(reach + 1), np.arange(-reach, reach + 1), indexing="ij")
    gap = cell * np.hypot(np.maximum(di - 1, 0), np.maximum(np.abs(dj) - 1, 0))
    forward = ((di > 0) | (dj > 0)) & (gap <= link)
    shifts = (di * stride + dj)[forward]
    rows, cols = [], []
    step = max(1, 4_000_000 // len(shifts))
    for start in range(0, len(keys), step):  # chunks bound the (cells x shifts) arrays
        target = keys[start:start + step, None] + shifts
        pos = np.minimum(np.searchsorted(keys, target), len(keys) - 1)
        cell_index, _ = np.nonzero(keys[pos] == target)
        rows.append(cell_index + start)
        cols.append(pos[keys[pos] == target])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(len(keys),) * 2)
    _, labels = connected_components(graph, directed=False)
    return labels[inverse.ravel()]


def boundary_centroid(uv: np.ndarray, radius: float) -> np.ndarray:
    """Centroid (2D) of the boundary points of the alpha shape of `uv` (Unger's centre of
    gravity of an extracted plane's boundary points). The points are first thinned to one per
    cell of side r/4; the alpha shape's triangles are the Delaunay triangles of circumradius at
    most r, its boundary the edges of exactly one of them. Without such triangles (very sparse
    points), the convex hull's points."""
    cell = radius / 4.0
    _, first = np.unique(np.floor((uv - uv.min(0)) / cell).astype(np.int64), axis=0,
                         return_index=True)
    points = uv[first]
    if len(points) < 3:
        return points.mean(0)
    try:
        tri = Delaunay(points)
    except QhullError:  # collinear
        return points.mean(0)
    a, b, c = (points[tri.simplices[:, k]] for k in range(3))
    la, lb, lc = (np.linalg.norm(b - c, axis=1), np.linalg.norm(c - a, axis=1),
                  np.linalg.norm(a - b, axis=1))
    area2 = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        circumradius = la * lb * lc / (2.0 * area2)
    simplices = tri.simplices[circumradius <= radius]
    if len(simplices) == 0:
        return points[np.unique(tri.convex_hull)].mean(0)
    edges = np.sort(np.vstack([simplices[:, [0, 1]], simplices[:, [1, 2]],
                               simplices[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    return points[np.unique(unique[counts == 1])].mean(0)


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


def extract_planes(points: np.ndarray, options: AssignmentOptions,
                   weights: np.ndarray | None = None,
                   rng: np.random.Generator | None = None) -> list[ExtractedPlane]:
    """Sequential MSAC with connected components (method (b)'s first stage, Unger 4.3.1)."""
    rng = rng or np.random.default_rng(options.random_seed)
    threshold, min_points = options.msac_inlier_distance, options.min_points_per_plane
    cells = np.floor((points - points.min(0)) / options.msac_sample_cell).astype(np.int64)
    dims = cells.max(0) + 1
    keys = cells[:, 0] + dims[0] * (cells[:, 1] + dims[1] * cells[:, 2])
    order = np.argsort(keys, kind="stable")  # the remaining points stay sorted by cell
    normals = (point_normals(points, options.msac_point_normal_neighbours)
               if options.msac_point_normal_angle < 90.0 else None)
    point_cos = math.cos(math.radians(options.msac_point_normal_angle))
    # the points not yet in a plane, kept sorted by cell and compacted after each plane
    remaining = order
    pts, cell_keys = points[order], keys[order]
    w = None if weights is None else weights[order]
    pts_normals = None if normals is None else normals[order]
    planes: list[ExtractedPlane] = []
    failures = 0
    while len(planes) < options.msac_max_planes and len(remaining) >= min_points:
        found = msac_plane(pts, threshold, options, rng, weights=w, cell_keys=cell_keys,
                           normals_of_points=pts_normals)
        if found is None:
            break
        normal, offset = found
        inliers = np.flatnonzero(_inliers(pts, normal, offset, threshold, pts_normals,
                                          point_cos))
        if len(inliers) < min_points:
            break
        labels = alpha_components(plane_coordinates(pts[inliers], normal), options.alpha_radius)
        sizes = np.bincount(labels)
        if sizes.max() < min_points:
            failures += 1
            if failures >= options.msac_max_failures:
                break
            continue
        failures = 0
        component = inliers[labels == int(np.argmax(sizes))]
        normal, offset = fit_plane(pts[component], None if w is None else w[component])
        uv = plane_coordinates(pts[component], normal)
        centre_uv = boundary_centroid(uv, options.alpha_radius)
        # back to 3D: the point on the plane with those in-plane coordinates
        basis = plane_coordinates(np.eye(3), normal)  # rows: e_k -> (u_k, v_k)
        centroid = basis @ centre_uv - offset * normal
        planes.append(ExtractedPlane(normal, offset, remaining[component], centroid))
        keep = np.ones(len(remaining), bool)
        keep[component] = False
        remaining, pts, cell_keys = remaining[keep], pts[keep], cell_keys[keep]
        w = None if w is None else w[keep]
        pts_normals = None if pts_normals is None else pts_normals[keep]
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
    u, v = store._to_face_2d(face, centroids[plane])
    inside = store._inside_pairs(face, u, v, options.polygon_margin)
    plane, face = plane[inside], face[inside]
    order = np.lexsort((distance[plane, face], plane))
    plane, face = plane[order], face[order]
    first = np.r_[True, plane[1:] != plane[:-1]] if len(plane) else np.zeros(0, bool)
    match[plane[first]] = face[first]
    return match


def _finish(points: np.ndarray, point_ids: np.ndarray, store: PlaneStore, face_index: np.ndarray,
            threshold: float, options: AssignmentOptions, rejected: dict[str, int],
            method: str) -> Assignment:
    face_index = filter_faces(points, face_index, options, rejected)
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
                options: AssignmentOptions, weights: np.ndarray | None = None) -> Assignment:
    """Method (b): planes extracted from the whole cloud, matched to model faces; `threshold`
    bounds the distance of an extracted plane's boundary centroid to the model plane."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    weights = _weights_for(weights, options, len(points))
    planes = extract_planes(points, options, weights)
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
    return _finish(points, point_ids, store, face_index, threshold, options, rejected, "msac")


# ----------------------------------------------------------------------------------------------
# (c): MSAC in the ROI of each model plane
# ----------------------------------------------------------------------------------------------


def assign_roi_msac(points: np.ndarray, point_ids: np.ndarray, store: PlaneStore,
                    threshold: float, options: AssignmentOptions,
                    weights: np.ndarray | None = None) -> Assignment:
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
        normal, offset = found
        face_index[idx[np.abs(pts @ normal + offset) < inlier_distance]] = face
    return _finish(points, point_ids, store, face_index, threshold, options, rejected,
                   "roi_msac")


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
    centres = {i: np.asarray(reconstruction.image(i).projection_center())
               for i in reconstruction.reg_image_ids()}
    rays, lengths = [], np.zeros(len(point_ids), np.int64)
    for k, pid in enumerate(point_ids):
        point = reconstruction.point3D(int(pid))
        ids = [e.image_id for e in point.track.elements]
        if not ids:
            continue
        lengths[k] = len(ids)
        rays.append(point.xyz - np.array([centres[i] for i in ids]))
    weights = np.zeros(len(point_ids))
    if not rays:
        return weights
    rays = np.vstack(rays)
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    # largest pairwise angle per point, over groups of equal track length (padded blocks)
    sine = np.zeros(len(point_ids))
    starts = np.r_[0, np.cumsum(lengths)[:-1]]
    for length in np.unique(lengths[lengths >= 2]):
        which = np.flatnonzero(lengths == length)
        for chunk in np.array_split(which, max(1, len(which) * length * length // 4_000_000)):
            block = rays[starts[chunk, None] + np.arange(length)]  # (m, L, 3)
            cosine = np.einsum("mai,mbi->mab", block, block).min(axis=(1, 2))
            angle = np.arccos(np.clip(cosine, -1.0, 1.0))
            sine[chunk] = np.sin(np.minimum(angle, np.pi / 2))
    weights = np.sqrt(lengths) * sine
    positive = weights[weights > 0]
    return weights / np.median(positive) if len(positive) else weights
