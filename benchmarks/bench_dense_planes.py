"""Weighted vs unweighted RANSAC plane extraction on dense points whose noise follows their
propagated sigma (Mulder 4.4 and 5.4), on the block of benchmarks/bench_oblique.py.

1. Dense points: sampled on the simulation's true scene (buildings with generalisation effects
   and terrain, rebuilt from the workspace's options) in a square around the block centre.
2. Their covariances: `precision/dense.py` (`dense-quality`'s propagation) from the refined
   block (`refined/`) and the cameras' a posteriori sigmas of the `both` subset
   (`precision/both_images.csv`), visibility from the refined tie points.
3. Noisy dense points: true + N(0, Sigma_i) with each point's own covariance.
4. Planes extracted from the noisy points (`extract_planes`: MSAC, point normal test) with weights
   1 / sigma_3d^2 (weighted sampling and weighted least squares) and without, for several seeds.
   Scored with the TRUE positions of each plane's inliers: their RMS distance to the extracted
   plane (how well it represents the surface, generalisation effects included), the deviation
   of the extracted plane from the plane the same estimator (same weights) fits to the same
   inliers' true positions (RMS over the inliers: the noise's effect alone), the share of points on a plane, the number of
   planes.

    .venv/bin/python benchmarks/bench_dense_planes.py [--work /tmp/bench_oblique]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def main(argv=None) -> int:
    import pycolmap

    from colmap_citymodel.assign.msac import fit_plane
    from colmap_citymodel.citymodel.read import read_city_model
    from colmap_citymodel.precision.dense import (DenseOptions, PlaneOptions, camera_set,
                                                  extract_planes, propagate,
                                                  read_image_covariances, visibility)
    from colmap_citymodel.simulate.oblique import ObliqueOptions, block_centre, true_scene
    from colmap_citymodel.simulate.observations import sample_surface_points

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_oblique"))
    parser.add_argument("--half_size", type=float, default=40.0, help="m around the centre")
    parser.add_argument("--density", type=float, default=3.0, help="dense points per m^2")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--output", type=Path, default=RESULTS / "dense_planes.md")
    args = parser.parse_args(argv)
    work = args.work
    sim = json.loads((work / "ws" / "truth" / "simulation.json").read_text())
    options = ObliqueOptions(**{k: tuple(v) if isinstance(v, list) else v
                                for k, v in sim["options"].items()})
    store = read_city_model(options.citymodel)
    centre = block_centre(options, store)
    scene = true_scene(options, store, centre)
    rng = np.random.default_rng(7)
    points, _ = sample_surface_points(scene, args.density, rng)
    inside = np.all(np.abs(points[:, :2] - centre[:2]) < args.half_size, axis=1)
    truth = points[inside] + store.origin  # model CRS, the refined block's frame
    rec = pycolmap.Reconstruction(str(work / "refined"))
    cams = camera_set(rec, read_image_covariances(work / "precision" / "both_images.csv"))
    dense_options = DenseOptions()
    seen, decided = visibility(rec, cams, truth, dense_options)
    sig = propagate(cams, truth, seen, dense_options)
    ok = np.isfinite(sig.sigma_3d)
    truth, cov = truth[ok], sig.covariances[ok]
    noise_rng = np.random.default_rng(11)
    noisy = truth + np.einsum("pij,pj->pi", np.linalg.cholesky(cov),
                              noise_rng.normal(size=truth.shape))
    sigma_3d = sig.sigma_3d[ok]
    offset = noisy.mean(0)
    plane_options = PlaneOptions(inlier_distance=0.15, min_inliers=100, max_planes=30)
    rows = []
    for seed in range(args.seeds):
        for name, weights in (("weighted", 1.0 / sigma_3d ** 2), ("unweighted", None)):
            planes = extract_planes(noisy - offset, weights, plane_options,
                                    np.random.default_rng(seed))
            dist, counts, dev = [], [], []
            for plane in planes:
                true_pts = truth[plane.inliers] - offset
                d = true_pts @ plane.normal + plane.offset
                dist.append(float(np.sqrt(np.mean(d ** 2))))
                counts.append(len(plane.inliers))
                # the plane the same estimator (same weights) gives from the same points
                # without noise; the extracted plane's deviation from it over the points'
                # extent isolates the noise's effect (relief such as window recesses pulls both
                # alike)
                ideal_normal, ideal_offset = fit_plane(
                    true_pts, None if weights is None else weights[plane.inliers])
                sign = 1.0 if ideal_normal @ plane.normal >= 0 else -1.0
                d_ideal = sign * (true_pts @ ideal_normal + ideal_offset)
                dev.append(float(np.sqrt(np.mean((d - d_ideal) ** 2))))
            counts = np.asarray(counts)
            rows.append({"seed": seed, "method": name, "planes": len(planes),
                         "inlier_share": float(counts.sum() / len(noisy)) if len(planes) else 0,
                         "rms_true_to_plane_m": float(np.average(dist, weights=counts))
                         if len(planes) else None,
                         "median_plane_rms_m": float(np.median(dist)) if len(planes) else None,
                         "plane_deviation_m": float(np.average(dev, weights=counts))
                         if len(planes) else None})
            print(json.dumps(rows[-1]), flush=True)
    summary = {"points": int(len(noisy)), "seen_by_tie_point_tracks": float(decided[ok].mean()),
               "sigma_3d_percentiles_m": np.percentile(sigma_3d, [5, 25, 50, 75, 95]).tolist(),
               "views_median": float(np.median(sig.num_views[ok])), "rows": rows,
               "plane_options": vars(plane_options)}
    args.output.with_suffix(".json").write_text(json.dumps(summary, indent=2))
    args.output.write_text(markdown(summary, args))
    print(markdown(summary, args))
    return 0


def markdown(summary: dict, args) -> str:
    p = summary["sigma_3d_percentiles_m"]
    lines = ["# Weighted vs unweighted RANSAC planes on dense points", "",
             f"`benchmarks/bench_dense_planes.py` on the bench_oblique block: "
             f"{summary['points']} dense points sampled on the true scene ({args.density}/m^2, "
             f"{2 * args.half_size:.0f} m square at the block centre), each moved by noise drawn "
             "from its own propagated covariance (cameras of the `both` subset, 1 px matching "
             f"noise); sigma_3d percentiles 5/25/50/75/95: "
             + " / ".join(f"{100 * v:.1f}" for v in p) + " cm; median views "
             f"{summary['views_median']:.0f}. Planes: MSAC, inlier distance "
             f"{summary['plane_options']['inlier_distance']} m, point normals within "
             f"{summary['plane_options']['normal_angle']} deg, at least "
             f"{summary['plane_options']['min_inliers']} inliers. Scores (inlier-weighted over "
             "planes): RMS distance of the inliers' TRUE positions to their extracted plane "
             "(window recesses and other relief included), and the RMS deviation of the "
             "extracted plane from the plane the same estimator fits to those true positions "
             "(the noise's effect).",
             "", "| method | seeds | planes (mean) | points on planes | RMS true to plane (cm), "
             "mean (min-max) | plane deviation (cm), mean (min-max) |", "|---|---|---|---|---|---|"]
    for method in ("weighted", "unweighted"):
        r = [x for x in summary["rows"] if x["method"] == method]
        rms = np.array([x["rms_true_to_plane_m"] for x in r], float)
        dev = np.array([x["plane_deviation_m"] for x in r], float)
        lines.append(f"| {method} | {len(r)} | {np.mean([x['planes'] for x in r]):.1f} | "
                     f"{100 * np.mean([x['inlier_share'] for x in r]):.1f} % | "
                     f"{100 * np.nanmean(rms):.2f} ({100 * np.nanmin(rms):.2f}-"
                     f"{100 * np.nanmax(rms):.2f}) | {100 * np.nanmean(dev):.2f} "
                     f"({100 * np.nanmin(dev):.2f}-{100 * np.nanmax(dev):.2f}) |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
