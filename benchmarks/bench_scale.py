"""Refine against COLMAP's bundle adjustment as the block grows: 250 to 2,000 images.

The blocks are `simulate.synthetic` street scenes (two rows of LOD2 buildings, a UAV flying
along the street with a left, a right and a forward camera per station, tie points on the true
facades and roofs with relief and clutter the model lacks, image noise 0.5 px, GNSS with a bias
of metres). Every size has the same street density (2 m between stations, one tie point per
square metre of visible surface); only the street's length grows with the number of images.

COLMAP's mapper is skipped: the "SfM" input is the true block bent by a smooth drift
(z += bend x^2 / length, the far end bent by `--bend` of the street length, default 0.5 %), moved
into an arbitrary similarity frame, with the noisy image observations and the tie points at
their bent (not re-triangulated) positions. Neither it nor refine's input is a bundle
adjustment optimum, so both adjustments below start from the same unconverged state.

Each size runs in its own process (peak memory per size, nothing cached between sizes) and
prints, on copies of the same input:
- colmap_ba_s: COLMAP's bundle adjustment with its defaults (`pycolmap.bundle_adjustment`
  with default BundleAdjustmentOptions = `colmap bundle_adjuster`), one run;
- refine_s: refine() as the CLI runs it, with its default precision step (per-image and
  per-tie-point covariances, `PrecisionOptions.covariances` auto), and refine_ratio =
  refine_s / colmap_ba_s;
- sigma_s: that precision step's seconds (variance factors, selected inversion, image and
  point covariances under the full stochastic model) and sigma_ratio = sigma_s / (refine_s -
  sigma_s), its share against the refine's own time; the median image centre sigma (the
  largest axis, m), the generalisation sigma the precision step propagated (m; the one given
  with `--sigma_generalisation`, else the data's estimate) and coverage95, the share of
  images whose true centre error lies inside their stated 95 % ellipsoid (chi-square, 3
  degrees of freedom);
- peak_rss_mb: the process's peak resident memory (ru_maxrss) at the end, and scene_rss_mb,
  its peak after synthesising the scene (before either adjustment);
- the refine's iterations and seconds per stage, the camera centre RMS against the truth (m),
  the verdict, and the machine's load average.

    .venv/bin/python benchmarks/bench_scale.py [--sizes 250 500 1000 2000] [--results FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

SIZES = (250, 500, 1000, 2000)
IMAGES_PER_STATION = 3  # left, right, forward (simulate.synthetic)


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB on Linux


def run_size(num_images: int, bend: float, seed: int, colmap_limit: float | None = None,
             sigma_generalisation: float | None = None) -> dict:
    """One size, in this process: synthesise, COLMAP's BA, refine. Returns the figures."""
    import logging

    import numpy as np
    import pycolmap

    from colmap_citymodel import logger
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.simulate.synthetic import (
        StreetSceneOptions,
        centre_errors,
        make_street_scene,
    )
    from colmap_citymodel.workflow import refine

    logger.setLevel(logging.WARNING)
    stations = num_images // IMAGES_PER_STATION
    options = StreetSceneOptions(num_stations=stations, seed=seed)
    length = stations * options.station_spacing
    options.drift = bend  # the far end bent by bend * length
    t = time.perf_counter()
    scene = make_street_scene(options)
    scene_s = time.perf_counter() - t
    sfm = scene.sfm
    figures = {
        "images": sfm.num_reg_images(), "tie_points": sfm.num_points3D(),
        "observations": sfm.compute_num_observations(), "faces": len(scene.store.faces),
        "street_m": length, "scene_s": scene_s, "scene_rss_mb": peak_rss_mb(),
    }

    plain = pycolmap.Reconstruction(sfm)
    colmap_options = pycolmap.BundleAdjustmentOptions()
    if colmap_limit:
        colmap_options.ceres.solver_options.max_solver_time_in_seconds = colmap_limit
    t = time.perf_counter()
    pycolmap.bundle_adjustment(plain, colmap_options)
    figures["colmap_ba_s"] = time.perf_counter() - t
    # stopped by the time limit: COLMAP's own time is at least this, the ratio at most
    figures["colmap_ba_stopped"] = bool(colmap_limit and figures["colmap_ba_s"] >= colmap_limit)
    del plain

    refine_options = RefineOptions()
    refine_options.adjustment.sigma_generalisation = sigma_generalisation
    t, c = time.perf_counter(), time.process_time()
    result = refine(sfm, scene.store, scene.gnss(), refine_options, progress=False)
    figures["refine_s"] = time.perf_counter() - t
    figures["refine_cpu_s"] = time.process_time() - c
    figures["refine_ratio"] = figures["refine_s"] / figures["colmap_ba_s"]
    figures.update(sigma_figures(result, scene, figures["refine_s"]))
    figures["iterations"] = len(result.iterations)
    figures["stages_s"] = {k: round(v, 2) for k, v in result.seconds.items()}
    truth = pycolmap.Reconstruction(scene.truth)
    truth.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), scene.store.origin))
    errors = centre_errors(result.reconstruction_in_crs(), truth)
    figures["camera_rms_m"] = float(np.sqrt(np.mean(errors ** 2)))
    figures["verdict"] = result.quality.verdict if result.quality is not None else "n/a"
    figures["assigned_points"] = int(result.assignment.num_assigned)
    figures["planes"] = int(result.assignment.num_faces)
    figures["peak_rss_mb"] = peak_rss_mb()
    figures["load"] = os.getloadavg()
    return figures


def sigma_figures(result, scene, refine_s: float) -> dict:
    """The precision step's seconds, its ratio to the rest of the refine, the median image
    centre sigma and how often the stated 95 % ellipsoids hold the true centre."""
    import numpy as np
    from scipy.stats import chi2

    precision = result.precision
    if precision is None or not precision.has_covariances:
        return {"sigma_s": None, "sigma_ratio": None, "centre_sigma_m": None,
                "coverage95": None}
    sigma_s = precision.seconds["total"]
    used = precision.generalisation_sigma if precision.generalisation == "consider" else None
    cov = precision.aware("image_cov")[:, :3, :3]
    truth = {im.name: np.asarray(im.projection_center()) for im in scene.truth.images.values()}
    origin = np.asarray(scene.store.origin)
    refined = result.reconstruction_in_crs()
    by_name = {im.name: np.asarray(im.projection_center()) for im in refined.images.values()
               if im.has_pose}
    inside = []
    for name, c in zip(precision.image_names, cov):
        error = by_name[name] - (truth[name] + origin)
        inside.append(float(error @ np.linalg.solve(c, error)) <= chi2.ppf(0.95, 3))
    sigma = np.sqrt(np.diagonal(cov, axis1=1, axis2=2)).max(axis=1)
    return {"sigma_s": sigma_s, "sigma_ratio": sigma_s / max(refine_s - sigma_s, 1e-9),
            "centre_sigma_m": float(np.median(sigma)), "coverage95": float(np.mean(inside)),
            "sigma_generalisation_m": used,
            "sigma_stages_s": {k: round(v, 2) for k, v in precision.seconds.items()}}


def _opt(value, fmt: str) -> str:
    return "n/a" if value is None else format(value, fmt)


def line(r: dict) -> str:
    return (f"{r['images']} images ({r['street_m']:.0f} m of street, {r['tie_points']} tie "
            f"points, {r['observations']} observations): colmap_ba_s {_bound(r)}"
            f"{r['colmap_ba_s']:.1f} refine_s {r['refine_s']:.1f} refine_ratio "
            f"{_bound(r, upper=True)}{r['refine_ratio']:.3f} peak_rss_mb "
            f"{r['peak_rss_mb']:.0f} (after the scene {r['scene_rss_mb']:.0f}); sigma_s "
            f"{_opt(r.get('sigma_s'), '.1f')} sigma_ratio {_opt(r.get('sigma_ratio'), '.3f')} "
            f"({r.get('sigma_stages_s')}), centre sigma {_opt(r.get('centre_sigma_m'), '.3f')} "
            f"m, coverage95 {_opt(r.get('coverage95'), '.2f')}; "
            f"{r['iterations']} iterations, stages {r['stages_s']}, camera centres "
            f"{r['camera_rms_m']:.3f} m, verdict {r['verdict']}, load "
            f"{' '.join(f'{v:.1f}' for v in r['load'])}")


def _bound(r: dict, upper: bool = False) -> str:
    """'>= ' before COLMAP's seconds (and '<= ' before the ratio) where the time limit stopped
    COLMAP's adjustment."""
    if not r.get("colmap_ba_stopped"):
        return ""
    return "<= " if upper else ">= "


def table(rows: list[dict]) -> str:
    out = ["| images | tie points | observations | colmap_ba_s | refine_s | refine_ratio | "
           "sigma_s | sigma_ratio | generalisation sigma m | peak_rss_mb | iterations | "
           "camera centre RMS m | centre sigma m | coverage95 | verdict | load (1/5/15 min) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        out.append(f"| {r['images']} | {r['tie_points']} | {r['observations']} | "
                   f"{_bound(r)}{r['colmap_ba_s']:.1f} | {r['refine_s']:.1f} | "
                   f"{_bound(r, upper=True)}{r['refine_ratio']:.3f} | "
                   f"{_opt(r.get('sigma_s'), '.1f')} | {_opt(r.get('sigma_ratio'), '.3f')} | "
                   f"{_opt(r.get('sigma_generalisation_m'), '.3f')} | {r['peak_rss_mb']:.0f} | "
                   f"{r['iterations']} | {r['camera_rms_m']:.3f} | "
                   f"{_opt(r.get('centre_sigma_m'), '.3f')} | "
                   f"{_opt(r.get('coverage95'), '.2f')} | {r['verdict']} | {' / '.join(f'{v:.1f}' for v in r['load'])} |")
    return "\n".join(out) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES),
                        help="numbers of images (default 250 500 1000 2000)")
    parser.add_argument("--bend", type=float, default=0.005,
                        help="the drift's bend at the far end, relative to the street length")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--results", type=Path, help="write the table to this markdown file")
    parser.add_argument("--colmap_limit", type=float, default=None,
                        help="stop COLMAP's adjustment after this many seconds (Ceres' "
                             "max_solver_time_in_seconds): its time is then a lower bound and "
                             "refine_ratio an upper bound, marked '>=' / '<='")
    parser.add_argument("--sigma_generalisation", type=float, default=None,
                        help="the model's generalisation sigma (m, AdjustmentOptions."
                             "sigma_generalisation): the precision step then propagates the "
                             "planes' offsets and tilts at this sigma (consider parameters); "
                             "default: none given, the sigma estimated from the data")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # a child process's size
    args = parser.parse_args()
    if args.one is not None:
        print("RESULT " + json.dumps(run_size(args.one, args.bend, args.seed,
                                              args.colmap_limit, args.sigma_generalisation)),
              flush=True)
        return

    from bench_refine import code_version

    version = code_version()
    print(f"code {version}")
    rows = []
    for size in args.sizes:
        child = subprocess.run(
            [sys.executable, __file__, "--one", str(size), "--bend", str(args.bend),
             "--seed", str(args.seed)]
            + (["--colmap_limit", str(args.colmap_limit)] if args.colmap_limit else [])
            + (["--sigma_generalisation", str(args.sigma_generalisation)]
               if args.sigma_generalisation is not None else []),
            capture_output=True, text=True)
        found = [ln for ln in child.stdout.splitlines() if ln.startswith("RESULT ")]
        if child.returncode or not found:
            print(f"{size} images: failed (exit {child.returncode})\n{child.stderr[-3000:]}")
            continue
        rows.append(json.loads(found[-1][len("RESULT "):]))
        print(line(rows[-1]), flush=True)
    print(table(rows))
    for r in rows:
        print(f"images {r['images']} colmap_ba_s {_bound(r)}{r['colmap_ba_s']:.3f} refine_s "
              f"{r['refine_s']:.3f} refine_ratio {_bound(r, upper=True)}"
              f"{r['refine_ratio']:.3f} sigma_s {_opt(r.get('sigma_s'), '.3f')} sigma_ratio "
              f"{_opt(r.get('sigma_ratio'), '.3f')} peak_rss_mb {r['peak_rss_mb']:.0f}")
    if args.results is not None:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        extra = ("" if args.sigma_generalisation is None
                 else f" --sigma_generalisation {args.sigma_generalisation}")
        args.results.write_text(f"code {version}, `benchmarks/bench_scale.py --sizes "
                                f"{' '.join(map(str, args.sizes))}{extra}`\n\n" + table(rows))
        print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
