"""Refine speed on a synthetic street of ~300 images and ~100k tie points (issue 3).

Measured in one run, all on copies of the same georegistered reconstruction:
- plain_solve_s: one COLMAP bundle adjustment solve with GNSS priors and no model (the
  baseline a user already pays for);
- hybrid_solve_s: one hybrid solve from the same state: the same problem plus f_dTP, f_dVT and
  f_VT for the tie points assigned at that state;
- assignment time per iteration and total refine time (refine() as the CLI runs it).
Prints the figures and, last, the lines `plain_solve_s`, `hybrid_solve_s`, `hybrid_solve_ratio`,
`assignment_fraction`, `refine_ratio` (targets: <= 1.2, <= 0.10, <= 4).

    .venv/bin/python benchmarks/bench_refine.py [--quick]
"""

from __future__ import annotations

import argparse
import logging
import time

import numpy as np
import pycolmap

from colmap_citymodel import logger
from colmap_citymodel.assign_planes import assign
from colmap_citymodel.hybrid_adjustment import HybridProblem
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.workflow import georegister, refine, tie_points
from colmap_citymodel.synthetic_scene import StreetSceneOptions, centre_errors, make_street_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true", help="a ~5x smaller scene")
    args = parser.parse_args()
    logger.setLevel(logging.WARNING)
    # Three images per station: 100 stations = 300 images; ~100k tie points (quick: ~5x less).
    stations = 20 if args.quick else 100
    options = StreetSceneOptions(num_stations=stations, point_spacing=0.38, seed=3)
    t = time.perf_counter()
    scene = make_street_scene(options)
    print(f"scene: {scene.sfm.num_reg_images()} images, {scene.sfm.num_points3D()} tie points, "
          f"{scene.sfm.compute_num_observations()} image observations, "
          f"{len(scene.store.faces)} model faces (built in {time.perf_counter() - t:.1f} s)")
    refine_options = RefineOptions()

    start = pycolmap.Reconstruction(scene.sfm)
    _, priors, _ = georegister(start, scene.store, scene.gnss(), None)

    plain_rec = pycolmap.Reconstruction(start)
    plain = HybridProblem(plain_rec, None, None, priors, refine_options.adjustment,
                          robust_images=False, robust_planes=False)
    plain_report = plain.solve()

    hybrid_rec = pycolmap.Reconstruction(start)
    ids, xyz = tie_points(hybrid_rec)
    t = time.perf_counter()
    assignment = assign(xyz, ids, scene.store, refine_options.assignment.max_threshold,
                        refine_options.assignment)
    first_assignment_s = time.perf_counter() - t
    hybrid = HybridProblem(hybrid_rec, scene.store, assignment, priors,
                           refine_options.adjustment, robust_images=False, robust_planes=False)
    hybrid_report = hybrid.solve()

    t = time.perf_counter()
    result = refine(scene.sfm, scene.store, scene.gnss(), refine_options, progress=False)
    refine_s = time.perf_counter() - t
    iterations = len(result.iterations)
    error = float(np.sqrt(np.mean(centre_errors(result.reconstruction, scene.truth) ** 2)))

    print(f"plain solve: {plain_report.ceres_iterations} Ceres iterations, "
          f"{plain_report.count['image']} image residuals")
    print(f"hybrid solve: {hybrid_report.ceres_iterations} Ceres iterations, "
          f"{assignment.num_assigned} points on {assignment.num_faces} planes "
          f"(assignment {first_assignment_s:.3f} s)")
    print(f"refine: {iterations} iterations, {refine_s:.1f} s "
          f"({', '.join(f'{k} {v:.1f}' for k, v in result.seconds.items())}), "
          f"camera centre RMS vs truth {error:.3f} m")
    print(f"assignment_s_per_iteration {result.seconds['assignment'] / iterations:.3f}")
    print(f"plain_solve_s {plain_report.seconds:.3f}")
    print(f"hybrid_solve_s {hybrid_report.seconds:.3f}")
    print(f"hybrid_solve_ratio {hybrid_report.seconds / plain_report.seconds:.3f}")
    print(f"assignment_fraction {result.seconds['assignment'] / refine_s:.4f}")
    print(f"refine_ratio {refine_s / plain_report.seconds:.3f}")


if __name__ == "__main__":
    main()
