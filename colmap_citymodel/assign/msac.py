"""MSAC plane estimation and alpha-shape components of planar point sets, for the indirect
assignment methods (assign/indirect.py; Unger 4.3, Mulder 4.4).

MSAC (Torr and Zisserman 2000) scores a hypothesis by the truncated quadratic cost sum
min(d^2, T^2) rather than RANSAC's inlier count: of two planes with equally many inliers the closer
fit wins. Here hypotheses are drawn in batches and scored, vectorised, on a random subsample of at
most `msac_sample_points` points; the best few are scored again on a four times larger one. The
number of hypotheses follows the best inlier fraction so far (`msac_confidence`), bounded by
`msac_max_trials`. The winner is refit by least squares to its inliers twice (the local
optimisation of LO-RANSAC), so that a hypothesis from three nearby points extends to the whole
plane. Optional, as the caller needs them: a reference normal the plane must stay close to
(method (c)); local sampling, two of the three points from the first one's cell (method (b): three
random points of a street's cloud almost never lie on one of its hundreds of planes); a point
normal test (method (b)).

Weighted RANSAC (Mulder 4.4): with per-point weights (higher = better), sample points are drawn
with probability proportional to their weight and refits are weighted least squares; the MSAC
cost stays unweighted. Mulder's second inlier test, the point normal (from its nearest
neighbours) close to the plane normal, is `msac_point_normal_angle`.

Libraries considered. Open3D's `PointCloud.segment_plane` is RANSAC (inlier count, ties by
RMSE) with uniform sampling that scores every hypothesis on every point: no weights, no normal
constraint, no local sampling. Its `detect_planar_patches` (robust statistics on an octree,
Araujo and Oliveira 2020) is another detector altogether and returns oriented boxes, not point
memberships. shapely's `concave_hull` gives one hull polygon, not connected components. So MSAC
is written here in numpy; Open3D gives the point normals (`estimate_normals`), a grid the
alpha-shape components (`alpha_components`) and scipy's Delaunay triangulation the alpha-shape
boundary (`boundary_centroid`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError

from ..options import AssignmentOptions

#: Hypotheses drawn per vectorised batch; how many of a run's best are scored again, on a
#: subsample this many times larger.
_BATCH = 64
_RESCORED = 8
_RESCORE_FACTOR = 4
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
    if not w.sum() > 0:
        w = np.ones(len(points))
    centre = (w[:, None] * points).sum(0) / w.sum()
    centred = points - centre
    _, vectors = np.linalg.eigh((w[:, None] * centred).T @ centred)
    normal = vectors[:, 0]
    return normal, float(-normal @ centre)


def _runs(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For nondecreasing `keys`: first and one-past-last position of each run of equal keys."""
    starts = np.r_[0, np.flatnonzero(np.diff(keys)) + 1]
    return starts, np.r_[starts[1:], len(keys)]


class _Sampler:
    """Draws point triples: globally, or (with `cell_keys`) two more points from the first
    point's cell; with `weights`, each draw has probability proportional to the weight."""

    def __init__(self, n: int, rng: np.random.Generator, weights: np.ndarray | None,
                 cell_keys: np.ndarray | None):
        self.n, self.rng = n, rng
        # cumulative weights; None for uniform draws (the cumulative sum of ones, 1, 2, ..., n,
        # is then implicit: no O(n) array per MSAC run)
        self.cumulative = None
        if weights is not None:
            w = np.maximum(np.asarray(weights, float), 0.0)
            if w.sum() > 0:
                self.cumulative = np.cumsum(w)
        self.local = None
        if cell_keys is not None:
            starts, ends = _runs(cell_keys)
            if np.any(ends - starts >= 3):
                self.local = (starts, ends)

    def _draw(self, low: np.ndarray, high: np.ndarray) -> np.ndarray:
        """Indices drawn in [low, high) with probability proportional to the weights."""
        c = self.cumulative
        if c is None:  # the weighted draw below with c = 1, 2, ..., n, in the same arithmetic
            below = low.astype(np.float64)
            u = below + self.rng.random(len(low)) * (high - below)
            return np.minimum(np.floor(u).astype(np.int64), high - 1)
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
        run = np.searchsorted(self.local[0], first, side="right") - 1
        lo, hi = self.local[0][run], self.local[1][run]
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
        cosine = point_normals @ normals.T
        np.abs(cosine, out=cosine)
        # T^2 where the normal test fails: as 0 <= d2 <= T^2, the maximum with T^2 there and 0
        # elsewhere (twice as fast as a masked copy)
        np.maximum(d2, np.multiply(cosine < min_cos, d2.dtype.type(t2)), out=d2)
    return d2.T.sum(1, dtype=np.float64)  # the same sums as d2.sum(0), in half the time


def inliers_of(points: np.ndarray, normal: np.ndarray, offset: float, inlier_distance: float,
               point_normals: np.ndarray | None = None, min_cos: float = 0.0) -> np.ndarray:
    """Inlier mask of one plane (distance, and with `point_normals` the normal angle)."""
    inside = np.abs(points @ normal + offset) < inlier_distance
    if point_normals is not None:  # the normal test only where the distance test passed
        near = np.flatnonzero(inside)
        inside[near] = np.abs(point_normals.take(near, 0) @ normal) >= min_cos
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
               ) -> tuple[np.ndarray, float, np.ndarray] | None:
    """The best plane of `points` by MSAC, refit to its inliers: unit normal, offset and the
    inlier mask; None if no hypothesis exists (fewer than three points, all collinear, or none
    within the angle).

    `reference`: unit normal; only planes whose normal is within `options.max_normal_angle`
    of it (either sign) are considered. `cell_keys`: nondecreasing cell id per point for local
    sampling. `weights`: weighted sampling and weighted refits. `normals_of_points`: a point is
    an inlier only if its normal is within `options.msac_point_normal_angle` of the plane's.
    """
    n = len(points)
    if n < 3:
        return None
    sampler = _Sampler(n, rng, weights, cell_keys)
    # subsamples drawn with replacement: a repeated point hardly changes a cost, and drawing
    # without replacement costs a permutation of all points
    subset = (rng.integers(0, n, options.msac_sample_points)
              if n > options.msac_sample_points else np.arange(n))
    # (take: a row gather several times faster than fancy indexing, the same rows)
    sub_points = points.take(subset, 0)
    sub_normals = None if normals_of_points is None else normals_of_points.take(subset, 0)
    # the subset in single precision about its centre: half the memory traffic, and 1e-7
    # relative to tens of metres is far below any inlier distance
    centre = sub_points.mean(0)
    scored = (sub_points - centre).astype(np.float32)
    scored_normals = None if sub_normals is None else sub_normals.astype(np.float32)
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
        cost = _msac_cost(scored, normals.astype(np.float32),
                          (offsets + normals @ centre).astype(np.float32), inlier_distance,
                          scored_normals, point_cos)
        top = np.argsort(cost)[:_RESCORED]
        kept_normals.append(normals[top])
        kept_offsets.append(offsets[top])
        kept_costs.append(cost[top])
        inliers = inliers_of(sub_points, normals[top[0]], offsets[top[0]], inlier_distance,
                             sub_normals, point_cos)
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
    if len(subset) < n:  # the best few again, on a larger subsample
        if n > _RESCORE_FACTOR * len(subset):
            again = rng.integers(0, n, _RESCORE_FACTOR * len(subset))
            again_points = points.take(again, 0)
            again_normals = (None if normals_of_points is None
                             else normals_of_points.take(again, 0))
        else:
            again_points, again_normals = points, normals_of_points
        best = int(np.argmin(_msac_cost(again_points, normals, offsets, inlier_distance,
                                        again_normals, point_cos)))
    else:
        best = 0
    normal, offset = normals[best], float(offsets[best])
    inliers = inliers_of(points, normal, offset, inlier_distance, normals_of_points, point_cos)
    for _ in range(2):  # local optimisation: least squares on the inliers
        if np.count_nonzero(inliers) < 3:
            break
        members = np.flatnonzero(inliers)
        refit, refit_offset = fit_plane(points.take(members, 0),
                                        None if weights is None else weights[members])
        if reference is not None and abs(refit @ reference) < min_cos:
            break
        normal, offset = refit, refit_offset
        inliers = inliers_of(points, normal, offset, inlier_distance, normals_of_points,
                             point_cos)
    return normal, offset, inliers


# ----------------------------------------------------------------------------------------------
# alpha shapes of an extracted plane's points
# ----------------------------------------------------------------------------------------------


def plane_coordinates(points: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """2D coordinates of the points' orthogonal projections in a frame of the plane."""
    helper = np.eye(3)[int(np.argmin(np.abs(normal)))]
    u = np.cross(normal, helper)
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    return points @ np.column_stack([u, v])  # one product for both coordinates


def _cell_link(cell: float, link: float, di: np.ndarray, dj: np.ndarray) -> np.ndarray:
    """Are two cells (side `cell`) `di`, `dj` cells apart linked: is their closest distance at
    most `link`?"""
    gap = cell * np.hypot(np.maximum(np.abs(di) - 1, 0), np.maximum(np.abs(dj) - 1, 0))
    return gap <= link


#: (cell, link) -> [(block row offset, block column offset, table)]: for the 4 x 4-cell blocks
#: of alpha_components, table[mask] is the 16-bit mask of the cells of the block at that offset
#: linked to any cell of `mask` (bit 4 r + c: the cell in row r, column c of its block).
_BLOCK_LINKS: dict[tuple[float, float], list[tuple[int, int, np.ndarray]]] = {}


def _block_links(cell: float, link: float) -> list[tuple[int, int, np.ndarray]]:
    """The block offsets (one of each pair +-) at which some cell pair is linked, with their
    tables (`_BLOCK_LINKS`); computed once per cell size and link length."""
    key = (cell, link)
    if key not in _BLOCK_LINKS:
        r, c = np.divmod(np.arange(16), 4)
        reach = int(math.ceil(link / cell)) + 1  # the farthest linked cells, in cells
        block_reach = (reach + 3) // 4 + 1  # ... in blocks, with a margin
        tables = []
        for bi in range(0, block_reach + 1):
            for bj in range(-block_reach, block_reach + 1):
                if bi == 0 and bj <= 0:  # each unordered pair of blocks once
                    continue
                # linked[a, b]: cell a of this block and cell b of the one at (bi, bj)
                linked = _cell_link(cell, link, 4 * bi + r[None, :] - r[:, None],
                                    4 * bj + c[None, :] - c[:, None])
                if not linked.any():
                    continue
                reached = (linked * (1 << np.arange(16))).sum(1)  # per cell a: mask of b
                table = np.zeros(1 << 16, np.int64)
                for bit in range(16):  # table[m] = OR of reached[a] over the bits a of m
                    table[1 << bit:2 << bit] = table[:1 << bit] | reached[bit]
                tables.append((bi, bj, table.astype(np.uint16)))
        _BLOCK_LINKS[key] = tables
    return _BLOCK_LINKS[key]


def alpha_components(uv: np.ndarray, radius: float) -> np.ndarray:
    """Connected-component label (0, 1, ...) of each 2D point under alpha shapes of `radius`.

    The alpha complex of radius r has the connectivity of the union of discs of radius r around
    the points (Edelsbrunner et al. 1983): two points are connected when a chain of points at
    most 2r apart joins them. It is computed on a grid of cell side r/4, linking occupied cells
    whose closest distance is at most 2r: points at most 2r apart always share a component, and
    no link is longer than 2r plus a cell diagonal (2.71 r). Linear in the number of points,
    whatever their density. Unlike MATLAB's alphaShape regions, a component need not contain a
    triangle (two isolated points 1.5 r apart form one). Labels are numbered in the order of
    each component's first cell (by row, then column).

    The cells are grouped into blocks of 4 x 4: any two cells of one block are linked (at most
    two cells apart), so the components are those of the blocks, two blocks linked when a cell
    of one is linked to a cell of the other (a table lookup on the blocks' 16-bit occupancy
    masks, `_block_links`). The cell graph itself (about 140 links per occupied cell) is never
    built.
    """
    if len(uv) == 0:
        return np.zeros(0, np.int64)
    cell, link = radius / 4.0, 2.0 * radius
    tables = _block_links(cell, link)
    block_reach = max(max(abs(bi), abs(bj)) for bi, bj, _ in tables)
    ij = np.floor((uv - uv.min(0)) / cell).astype(np.int64)
    bi, bj = ij[:, 0] >> 2, ij[:, 1] >> 2
    stride = int(bj.max()) + 1 + 2 * block_reach
    # occupied cells sorted by block, then by their bit in the block's mask
    cells, cell_of_point = np.unique(((bi * stride + bj + block_reach) << 4)
                                     | ((ij[:, 0] & 3) << 2) | (ij[:, 1] & 3),
                                     return_inverse=True)
    block_key = cells >> 4
    first = np.flatnonzero(np.r_[True, block_key[1:] != block_key[:-1]])
    keys = block_key[first]
    block_of_cell = np.cumsum(np.r_[False, block_key[1:] != block_key[:-1]])
    masks = np.bitwise_or.reduceat(np.left_shift(1, cells & 15), first).astype(np.int64)
    size = int(keys[-1]) + block_reach * stride + block_reach + 1
    lookup = None
    if size <= 16_000_000:  # a dense table of block ids: gathers, no search
        lookup = np.full(size, -1, np.int64)
        lookup[keys] = np.arange(len(keys))
    rows, cols = [], []
    for di, dj, table in tables:
        target = keys + (di * stride + dj)
        if lookup is not None:
            neighbour = lookup[target]
        else:
            neighbour = np.minimum(np.searchsorted(keys, target), len(keys) - 1)
            neighbour[keys[neighbour] != target] = -1
        a = np.flatnonzero(neighbour >= 0)
        b = neighbour[a]
        linked = (table[masks[a]] & masks[b]) != 0
        rows.append(a[linked])
        cols.append(b[linked])
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(len(keys),) * 2)
    _, block_label = connected_components(graph, directed=False)
    # number the components by their first cell in (row, column) order, as a labelling of the
    # cell graph in that order would: a block's first cell is its lowest mask bit
    low = (masks & -masks).astype(np.float64)
    bit = np.log2(low).astype(np.int64)
    block_row, block_col = np.divmod(keys, stride)
    first_cell = (4 * block_row + (bit >> 2)) * (4 * stride) + 4 * block_col + (bit & 3)
    order = np.argsort(first_cell, kind="stable")
    _, first_seen = np.unique(block_label[order], return_index=True)
    rank = np.empty(len(first_seen), np.int64)
    rank[np.argsort(first_seen)] = np.arange(len(first_seen))
    return rank[block_label[block_of_cell[cell_of_point.ravel()]]]


def boundary_centroid(uv: np.ndarray, radius: float) -> np.ndarray:
    """Centroid (2D) of the boundary points of the alpha shape of `uv` (Unger's centre of
    gravity of an extracted plane's boundary points). The points are first thinned to one per
    cell of side r/4; the alpha shape's triangles are the Delaunay triangles of circumradius at
    most r, its boundary the edges of exactly one of them. Without such triangles (very sparse
    points), the convex hull's points."""
    cell = radius / 4.0
    ij = np.floor((uv - uv.min(0)) / cell).astype(np.int64)
    _, first = np.unique(ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1], return_index=True)
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
    alpha = circumradius <= radius
    if not alpha.any():
        return points[np.unique(tri.convex_hull)].mean(0)
    # an edge of an alpha triangle is on the boundary when the triangle across it (opposite
    # vertex k) is not one or there is none: the edges of exactly one alpha triangle
    triangle, k = np.nonzero(alpha[:, None] & ~np.r_[alpha, False][tri.neighbors])
    ends = np.r_[tri.simplices[triangle, (k + 1) % 3], tri.simplices[triangle, (k + 2) % 3]]
    return points[np.unique(ends)].mean(0)
