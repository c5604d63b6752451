"""Query speed of the plane store: closest_faces for 1e5 points against 1e4 synthetic faces.

A synthetic city of gable-roof houses (7 faces each) on a grid; points near the faces (tie
points: +-0.5 m off the planes) and random points in the block. Prints points/s of the indexed
query and of a brute-force baseline (every plane tested per point, then point-in-polygon on all
faces within max_distance, same kernel, no spatial index) measured in the same run, their
ratio, and whether both answer the same on the baseline's points.

    python benchmarks/bench_store_queries.py [--faces 10000] [--points 100000]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from colmap_citymodel.citymodel.build import store_from_polygons


def house(x, y, w, d, h, ridge):
    """Box w x d x h with a gable roof along x; rings counter-clockwise from outside."""
    v = np.array(
        [[0, 0, 0], [w, 0, 0], [w, d, 0], [0, d, 0], [0, 0, h], [w, 0, h], [w, d, h], [0, d, h],
         [0, d / 2, h + ridge], [w, d / 2, h + ridge]], float
    ) + [x, y, 0]
    faces = [
        ([0, 3, 2, 1], "GroundSurface"),
        ([0, 1, 5, 4], "WallSurface"),
        ([2, 3, 7, 6], "WallSurface"),
        ([1, 2, 6, 9, 5], "WallSurface"),
        ([3, 0, 4, 8, 7], "WallSurface"),
        ([4, 5, 9, 8], "RoofSurface"),
        ([6, 7, 8, 9], "RoofSurface"),
    ]
    return [v[f] for f, _ in faces], [s for _, s in faces]


def synthetic_city(n_faces, rng):
    n_houses = n_faces // 7
    side = int(np.ceil(np.sqrt(n_houses)))
    polys, sems = [], []
    for k in range(n_houses):
        i, j = divmod(k, side)
        w, d = rng.uniform(8, 14), rng.uniform(8, 12)
        p, s = house(500000 + 20 * i, 5400000 + 20 * j, w, d, rng.uniform(6, 15), rng.uniform(2, 5))
        polys += p
        sems += s
    return store_from_polygons(polys, semantics=sems)


def sample_points(store, n, rng):
    n_near = int(0.7 * n)
    f = rng.integers(0, store.num_faces, n_near)
    R = store.rotations[f]
    uv = rng.uniform(-6, 6, (n_near, 2))
    near = store.centroids[f] + np.einsum("kij,kj->ki", R[:, :, :2], uv)
    near += R[:, :, 2] * rng.normal(0, 0.5, (n_near, 1))
    lo, hi = store.bbox_local
    return np.vstack([near, rng.uniform(lo, hi, (n - n_near, 3))])


def brute_force(store, pts, max_distance, margin):
    best = np.full(len(pts), -1)
    dist = np.full(len(pts), np.nan)
    n, off = store.normals, store.offsets
    for s in range(0, len(pts), 64):
        chunk = pts[s : s + 64]
        d = chunk @ n.T + off
        p, f = np.nonzero(np.abs(d) <= max_distance)
        u, v = store._to_face_2d(f, chunk[p])
        inside = store._inside_pairs(f, u, v, margin)
        p, f = p[inside], f[inside]
        score = np.full(d.shape, np.inf)
        score[p, f] = np.abs(d[p, f])
        b = np.argmin(score, axis=1)
        ok = np.isfinite(score[np.arange(len(chunk)), b])
        best[s : s + 64] = np.where(ok, b, -1)
        dist[s : s + 64] = np.where(ok, d[np.arange(len(chunk)), b], np.nan)
    return best, dist


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faces", type=int, default=10_000)
    ap.add_argument("--points", type=int, default=100_000)
    ap.add_argument("--brute_points", type=int, default=2_000)
    ap.add_argument("--max_distance", type=float, default=1.0)
    ap.add_argument("--margin", type=float, default=0.1)
    args = ap.parse_args()
    rng = np.random.default_rng(0)

    t = time.perf_counter()
    store = synthetic_city(args.faces, rng)
    print(f"store: {store.num_faces} faces, {len(store.vertices)} vertices, "
          f"built in {time.perf_counter() - t:.2f} s")
    pts = sample_points(store, args.points, rng)

    t = time.perf_counter()
    store.closest_faces(pts[:10], args.max_distance, args.margin)
    t_index = time.perf_counter() - t
    t = time.perf_counter()
    face, d = store.closest_faces(pts, args.max_distance, args.margin)
    t_query = time.perf_counter() - t
    print(f"index build (first query): {t_index:.3f} s")
    print(f"indexed: {len(pts)} points in {t_query:.3f} s = {len(pts) / t_query:,.0f} points/s "
          f"({np.count_nonzero(face >= 0)} assigned)")

    sub = pts[rng.choice(len(pts), args.brute_points, replace=False)]
    t = time.perf_counter()
    bf_face, bf_d = brute_force(store, sub, args.max_distance, args.margin)
    t_bf = time.perf_counter() - t
    print(f"brute force: {len(sub)} points in {t_bf:.3f} s = {len(sub) / t_bf:,.0f} points/s")
    ix_face, _ = store.closest_faces(sub, args.max_distance, args.margin, candidates=None)
    agree = np.mean(ix_face == bf_face)
    print(f"speed-up indexed / brute force: {(len(pts) / t_query) / (len(sub) / t_bf):.1f}x; "
          f"same answer on {agree * 100:.2f} % of the brute-force points")


if __name__ == "__main__":
    main()
