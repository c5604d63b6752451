"""Refine speed on a simulated flight mapped by COLMAP.

Default: the long sequence's Scn3 workspace (340 images, ~100k tie points, ~680k image
observations; built by `colmap-citymodel simulate workspaces/long_scn3.toml ...` if missing);
`--quick`: the short sequence's Scn3 (90 images, ~28k tie points), about 4x smaller.
Measured in one run, on copies of the same input:
- plain_solve_s: COLMAP's bundle adjustment of the input reconstruction as COLMAP ships it
  (`pycolmap.bundle_adjustment` with default BundleAdjustmentOptions = `colmap
  bundle_adjuster`), median of 3 runs: the baseline a user already pays for;
- hybrid_solve_s: one hybrid adjustment as refine's first iteration does it, set-up included:
  from the georegistered block, assign at 2 m, move the block onto the planes (similarity),
  assign again, build the problem (COLMAP's problem + GNSS + f_dTP, f_dVT, f_VT), solve;
- assignment time per iteration and total refine time (refine() as the CLI runs it).
Also printed for transparency: a GNSS-prior BA of the georegistered block with refine's solver
settings (`plain_gnss_solve_s`): from COLMAP's converged output it stops after one step, so it
is a lower bound no adjustment that has to move the block can reach.
Prints the figures and, last, the lines `plain_solve_s`, `hybrid_solve_s`, `hybrid_solve_ratio`,
`assignment_fraction`, `refine_ratio` (targets: <= 1.2, <= 0.10, <= 4).

    .venv/bin/python benchmarks/bench_refine.py [--quick] [--workspace DIR]
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
import pycolmap

from colmap_citymodel import logger
from colmap_citymodel.adjust.problem import HybridProblem
from colmap_citymodel.adjust.steps import align_block_to_planes
from colmap_citymodel.align.block_to_model import crop_to_reconstruction, georegister
from colmap_citymodel.assign.schedule import assign
from colmap_citymodel.block.reconstruction import tie_points
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.simulate.synthetic import centre_errors
from colmap_citymodel.workflow import refine


def workspace_for(sequence: str) -> Path:
    from colmap_citymodel.simulate import sequence as simulate

    root = Path(__file__).resolve().parents[1] / "workspaces"
    out = root / "generated" / sequence / "Scn3"
    if not (out / "sparse" / "0").is_dir():
        simulate.main(root / f"{sequence}_scn3.toml", out,
                      cache_path=root / "generated" / "cache", overwrite=out.exists())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="the short sequence (~4x smaller)")
    parser.add_argument("--workspace", type=Path, help="a simulated workspace to use instead")
    parser.add_argument("--methods", nargs="*", default=["msac", "roi_msac", "auto"],
                        help="assignment methods to time besides direct, each in a full refine "
                             "(assignment_fraction_<method>)")
    args = parser.parse_args()
    logger.setLevel(logging.WARNING)
    workspace = args.workspace or workspace_for("short" if args.quick else "long")
    from colmap_citymodel.block.gnss import read_gnss
    from colmap_citymodel.block.reconstruction import read_reconstruction
    from colmap_citymodel.citymodel.read import read_city_model

    store = read_city_model(workspace / "given_model.gml")
    gnss = read_gnss(database=workspace / "database.db", target_crs=store.crs)
    sfm = read_reconstruction(workspace / "sparse" / "0")
    print(f"workspace {workspace}: {sfm.num_reg_images()} images, {sfm.num_points3D()} tie "
          f"points, {sfm.compute_num_observations()} image observations, "
          f"{len(store.faces)} model faces")
    refine_options = RefineOptions()
    refine_options.precision.covariances = "off"  # timed separately (precision.py)

    plain_seconds = []
    for _ in range(3):
        plain_rec = pycolmap.Reconstruction(sfm)
        t = time.perf_counter()
        pycolmap.bundle_adjustment(plain_rec, pycolmap.BundleAdjustmentOptions())
        plain_seconds.append(time.perf_counter() - t)
    plain_s = float(np.median(plain_seconds))

    start = pycolmap.Reconstruction(sfm)
    _, priors, _ = georegister(start, store, gnss, None)
    store_near = crop_to_reconstruction(store, start, refine_options.workflow.overlap_margin)
    gnss_rec = pycolmap.Reconstruction(start)
    gnss_problem = HybridProblem(gnss_rec, None, None, priors, refine_options.adjustment,
                                 robust_images=False, robust_planes=False)
    gnss_report = gnss_problem.solve()

    hybrid_rec = pycolmap.Reconstruction(start)
    t = time.perf_counter()
    ids, xyz = tie_points(hybrid_rec)
    assignment = assign(xyz, ids, store_near, refine_options.assignment.max_threshold,
                        refine_options.assignment)
    first_assignment_s = time.perf_counter() - t
    t = time.perf_counter()
    _, xyz, assignment = align_block_to_planes(  # as refine's iteration 0
        hybrid_rec, ids, xyz, assignment, store_near, priors,
        refine_options.assignment.max_threshold, refine_options)
    hybrid = HybridProblem(hybrid_rec, store_near, assignment, priors,
                           refine_options.adjustment, robust_images=False, robust_planes=False)
    hybrid_report = hybrid.solve()
    hybrid_s = time.perf_counter() - t

    t = time.perf_counter()
    result = refine(sfm, store, gnss, refine_options, progress=False)
    refine_s = time.perf_counter() - t
    iterations = len(result.iterations)
    # Compare in model CRS: truth/ is local to the sequence's origin, the result to the store's.
    truth = pycolmap.Reconstruction(str(workspace / "truth"))
    truth_origin = np.loadtxt(workspace / "truth" / "origin.txt", comments="#")
    truth.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), truth_origin))
    error = float(np.sqrt(np.mean(centre_errors(result.reconstruction_in_crs(), truth) ** 2)))

    print(f"plain COLMAP bundle adjustment (defaults): "
          f"{', '.join(f'{v:.2f}' for v in plain_seconds)} s")
    print(f"plain GNSS-prior solve of the georegistered block (refine's settings): "
          f"{gnss_report.ceres_iterations} Ceres iterations, {gnss_report.seconds:.3f} s, "
          f"{gnss_report.count['image']} image residuals")
    print(f"hybrid solve: {hybrid_report.ceres_iterations} Ceres iterations "
          f"({hybrid_report.seconds:.3f} s of {hybrid_s:.3f} s with alignment and set-up), "
          f"{assignment.num_assigned} points on {assignment.num_faces} planes "
          f"(assignment {first_assignment_s:.3f} s)")
    print(f"refine: {iterations} iterations, {refine_s:.1f} s "
          f"({', '.join(f'{k} {v:.1f}' for k, v in result.seconds.items())}), "
          f"camera centre RMS vs truth {error:.3f} m")
    print(f"assignment_s_per_iteration {result.seconds['assignment'] / iterations:.3f}")
    print(f"plain_gnss_solve_s {gnss_report.seconds:.3f}")
    print(f"refine_ratio_vs_plain_gnss_solve {refine_s / gnss_report.seconds:.3f}")
    print(f"plain_solve_s {plain_s:.3f}")
    print(f"hybrid_solve_s {hybrid_s:.3f}")
    print(f"hybrid_solve_ratio {hybrid_s / plain_s:.3f}")
    print(f"assignment_fraction {result.seconds['assignment'] / refine_s:.4f}")
    print(f"refine_ratio {refine_s / plain_s:.3f}")
    print(f"assignment_fraction_direct {result.seconds['assignment'] / refine_s:.4f} "
          f"(camera centres {error:.3f} m)")
    for method in args.methods:
        options = RefineOptions()
        options.precision.covariances = "off"
        options.assignment.method = method
        t = time.perf_counter()
        other = refine(sfm, store, gnss, options, progress=False)
        seconds = time.perf_counter() - t
        other_error = float(np.sqrt(np.mean(
            centre_errors(other.reconstruction_in_crs(), truth) ** 2)))
        print(f"assignment_fraction_{method} {other.seconds['assignment'] / seconds:.4f} "
              f"(refine {seconds:.1f} s, assignment {other.seconds['assignment']:.1f} s, "
              f"camera centres {other_error:.3f} m, verdict {other.quality.verdict})")


if __name__ == "__main__":
    main()
