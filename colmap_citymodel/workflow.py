"""The refine step (`colmap_citymodel.refine`): global workflow of Unger Table 3 with any
assignment method (direct (a) by default; (b), (c), auto).

1. SfM (COLMAP, done before) + 7-parameter similarity to GNSS (or a given initial transform;
   along a straight line the cameras' upright orientation fixes the roll);
2. bundle adjustment with GNSS priors and no model, robust on image observations; image
   observations with normalised residual > 3 eliminated. This is the GNSS-only result that
   the quality gate compares with and hands back when the model cannot help;
   then coarse alignment: the block's shift (and roll about a straight line) against the
   model surfaces within a few GNSS sigma (align.coarse);
3. assign tie points to model planes (the first time followed by similarity rounds that must
   lower the block objective);
4. hybrid bundle adjustment, robust on f_dTP; fictitious observations with normalised residual
   > 3 eliminated and the adjustment repeated with the original weights.
Steps 3-4 repeat (adjust.loop; assignments recomputed from the current estimate every
iteration; vertex-plane relations never change; the threshold never grows) until the relative
change of the RMS of normalised residuals < 1e-5 or 10 iterations, or until the block objective
worsens (the best iterate is kept). The scale is held from the GNSS-only block where the planes
cannot give it. At the end: observability of the datum (adjust.observability) and the quality
verdict (precision.quality).

Everything happens in the plane store's local frame (model CRS minus `store.origin`).
`refine()` works on pycolmap objects in memory and never modifies its inputs; `main()` is the
CLI's entry: read inputs, refine, write outputs atomically.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import pycolmap

from .adjust.loop import adjustment_loop
from .adjust.observability import assigned_observability, datum_line
from .adjust.steps import model_after_solve, step2_bundle_adjustment
from .align.block_to_model import crop_to_reconstruction, georegister
from .align.objective import BlockObjective
from .block.gnss import read_gnss
from .block.priors import scale_sigma_from_gnss
from .block.reconstruction import camera_up_and_view, read_reconstruction, tie_points
from .citymodel.read import peek_crs
from .citymodel.store import PlaneStore
from .errors import NoOverlapError
from .options import RefineOptions
from .output.result import RefineResult
from .precision.quality import measure_quality

logger = logging.getLogger(__name__)


def refine(reconstruction: pycolmap.Reconstruction, city_model: PlaneStore, gnss=None,
           options: RefineOptions | None = None, *, initial_transform: pycolmap.Sim3d | None = None,
           exclude_point_ids: set[int] | None = None, progress: bool = True,
           checkpoints: dict | None = None, checkpoint_observations: list | None = None
           ) -> RefineResult:
    """Georeference `reconstruction` and adjust it together with `city_model`.

    `gnss` is a `block.gnss.GNSSObservations` (model CRS) or None; `initial_transform` maps the
    input frame to model CRS coordinates (used instead of a GNSS similarity when given).
    `exclude_point_ids` are never assigned to planes (e.g. check points in the model).
    The input reconstruction is not modified; the result holds a refined copy, or, when the
    quality gate fails, the GNSS-only adjustment (`result.quality`, `result.gnss_only`).
    `checkpoints` ({id: XYZ} model CRS) and `checkpoint_observations` ([(image, id, x, y)],
    precision.checkpoints.read_*) are only evaluated at the end (Delta, and sigma when
    covariances are on).
    """
    from .align.coarse import SurfaceDistance, coarse_alignment

    options = options or RefineOptions()
    timer = {"start": time.perf_counter()}
    rec = pycolmap.Reconstruction(reconstruction)
    details: dict = {}
    sim3, priors, geo_rms = georegister(rec, city_model, gnss, initial_transform, details)
    store = crop_to_reconstruction(city_model, rec, options.workflow.overlap_margin)
    logger.info("model: %d faces, %d vertices near the reconstruction", len(store.faces),
                len(store.vertices))
    timer["georegistration"] = time.perf_counter() - timer["start"]

    warnings: list[str] = []
    report2, eliminated2 = step2_bundle_adjustment(rec, priors, options)
    gnss_only = gnss_only_sim3 = None
    if priors is not None:
        gnss_only, gnss_only_sim3 = pycolmap.Reconstruction(rec), sim3
    timer["step2"] = time.perf_counter() - timer["start"] - timer["georegistration"]

    o_a, o_adj, o_w = options.assignment, options.adjustment, options.workflow
    surface = SurfaceDistance(store, o_a.excluded_classes)
    all_ids, points = tie_points(rec, exclude_point_ids)
    objective = BlockObjective(surface, priors, all_ids, 2 * o_adj.sigma_dtp)
    scale_sigma = scale_sigma_from_gnss(priors) if priors is not None else None
    coarse = None
    if priors is not None and initial_transform is None and o_w.coarse_search_sigmas > 0:
        # The GNSS-only block is off the model by the GNSS error (metres, mostly a bias):
        # search the shift (and, along a straight line, the roll) that puts the tie points
        # on the model before any of them is assigned.
        t_coarse = time.perf_counter()
        # The images with GNSS fixed the georegistration; if they lie on a line, its rotation
        # about that line came from the cameras' upright orientation and is searched again.
        centres = np.array([rec.image(int(i)).projection_center() for i in priors.image_ids])
        straight = "roll_about_line" in details.get("cues", {})
        up, view = camera_up_and_view(rec, priors.image_ids)
        coarse = coarse_alignment(points, centres, up, view, store, surface,
                                  np.median(priors.sigmas, axis=0), straight,
                                  o_w.coarse_search_sigmas)
        if objective(rec, coarse.sim3) < objective(rec):
            rec.transform(coarse.sim3)
            sim3 = coarse.sim3 * sim3
        else:
            logger.info("coarse alignment kept the GNSS-only position (no better objective)")
        timer["coarse_alignment"] = time.perf_counter() - t_coarse

    loop = adjustment_loop(rec, store, priors, options, objective, all_ids,
                           exclude_point_ids=exclude_point_ids, gnss_only=gnss_only,
                           scale_sigma=scale_sigma, progress=progress)
    rec, current, assignment, last = loop.reconstruction, loop.current, loop.assignment, loop.last
    sim3 = loop.move * sim3
    warnings += loop.warnings
    timer.update(loop.seconds)

    from .precision.estimate import precision_after_refine
    from .precision.variance_components import final_solve_in_refine

    vce = None
    if last.blocks.faces.size:  # VCE and/or estimated generalisation offsets, if asked
        last, vce = final_solve_in_refine(rec, store, assignment, priors, options, current,
                                          last)
        current = model_after_solve(current, last)
    point_ids, points = tie_points(rec, exclude_point_ids)
    observability = assigned_observability(points, assignment, current, priors, rec, options)
    quality = measure_quality(rec, gnss_only, surface, priors, assignment, last, observability,
                              points, options, loop.diverged, scale_sigma)
    logger.info("datum fixed by: %s", datum_line(observability))
    logger.info(quality.line())
    precision = evaluation = None
    refined = rec
    if quality.verdict == "failed" and gnss_only is not None:
        # Never hand back a block worse than GNSS alone: the result is the GNSS-only one.
        rec, sim3 = gnss_only, gnss_only_sim3
    else:
        precision = precision_after_refine(last, options.precision, checkpoint_observations)
    if checkpoints is not None and checkpoint_observations is not None:
        from .precision.checkpoints import evaluate_with_precision

        evaluation = evaluate_with_precision(rec, checkpoints, checkpoint_observations,
                                             store.origin, precision)
    blocks = last.blocks
    timer["total"] = time.perf_counter() - timer["start"]
    del timer["start"]
    return RefineResult(
        reconstruction=rec, store=store, adjusted_store=current, assignment=assignment,
        plane_faces=blocks.faces, plane_normals=blocks.normal_array,
        plane_offsets=blocks.offset_array, input_to_local=sim3, georegistration_rms=geo_rms,
        step2=report2, step2_eliminated=eliminated2, iterations=loop.iterations,
        options=options, warnings=warnings, seconds=timer, gnss_priors=priors, precision=precision,
        variance_components=vce, checkpoints=evaluation, gnss_only=gnss_only,
        quality=quality, observability=observability,
        observability_before=loop.observability_before, refined=refined,
        datum_cues=details.get("cues", {}),
        coarse_alignment=coarse.todict() if coarse is not None else None)


# -- CLI entry: read inputs, refine, write outputs ------------------------------------------------

#: Metres around the GNSS positions in which city model buildings are read.
GNSS_READ_MARGIN = 250.0


def main(input_path, citymodel, output_path, *, database=None, gnss=None, gnss_crs=None,
         exif=None, initial_transform=None, preset="generalised", options_file=None,
         lod=2, model_crs=None, target_crs=None, output_type="bin", output_frame="crs",
         progress=True, precision=None, gnss_height_offset=None, lever_arm=None,
         checkpoints=None, checkpoint_observations=None, sigma_generalisation=None,
         variance_components=None, assignment=None, num_threads=None) -> RefineResult:
    """`colmap-citymodel refine`: read everything, refine, write `output_path` atomically.
    `checkpoints` / `checkpoint_observations`: files (evaluate's formats) of check points that
    are evaluated at the end (Delta, sigma; report.json `checkpoints`)."""
    from .align.georegister import read_initial_transform
    from .citymodel.crs import user_crs
    from .citymodel.read import read_city_model
    from .files import atomic_directory
    from .output.write import write_refined

    options = (RefineOptions.from_toml(options_file, preset) if options_file
               else RefineOptions.preset(preset))
    if precision is not None:  # --precision on/off/auto overrides the options file
        options.precision.covariances = precision
    if sigma_generalisation is not None:
        options.adjustment.sigma_generalisation = float(sigma_generalisation)
    if variance_components is not None:
        options.precision.variance_components = bool(variance_components)
    if assignment is not None:  # --assignment overrides the options file
        options.assignment.method = assignment
    if num_threads is not None:  # threads of each Ceres solve (a batch worker uses one)
        options.adjustment.num_threads = int(num_threads)
    cp_known = cp_observations = None
    if (checkpoints is None) != (checkpoint_observations is None):
        from .errors import InputError

        raise InputError("give --checkpoints and --checkpoint_observations together")
    if checkpoints is not None:
        from .precision.checkpoints import (
            read_checkpoint_observations,
            read_checkpoints,
        )

        cp_known = read_checkpoints(checkpoints)
        cp_observations = read_checkpoint_observations(checkpoint_observations)
    # Fail on a taken output directory before the expensive work.
    with atomic_directory(output_path):
        pass
    Path(output_path).rmdir()
    reconstruction = read_reconstruction(input_path)
    crs = user_crs(target_crs) if target_crs else peek_crs(citymodel, model_crs)
    observations = None
    if crs is not None:
        observations = read_gnss(database=database, gnss=gnss, gnss_crs=gnss_crs, exif=exif,
                                 target_crs=crs, default_sigma=options.adjustment.sigma_gnss)
    bbox = None
    if observations is not None:
        bbox = np.array([observations.positions.min(0) - GNSS_READ_MARGIN,
                         observations.positions.max(0) + GNSS_READ_MARGIN])
    try:
        store = read_city_model(citymodel, lod=lod, crs=model_crs, target_crs=target_crs,
                                bbox_crs=bbox)
    except NoOverlapError as error:
        raise NoOverlapError(
            f"the city model does not overlap the GNSS positions ({observations.source}, "
            f"{GNSS_READ_MARGIN:.0f} m margin): {error.message}; check the GNSS CRS and the "
            "model tiles", error.path) from None
    if observations is None and crs is None:
        observations = read_gnss(database=database, gnss=gnss, gnss_crs=gnss_crs, exif=exif,
                                 target_crs=store.crs, default_sigma=options.adjustment.sigma_gnss)
    if observations is not None and lever_arm is not None:
        observations.lever_arm = np.asarray(lever_arm, dtype=np.float64).reshape(3)
    if observations is not None and gnss_height_offset is not None:
        observations.positions = observations.positions + [0.0, 0.0, float(gnss_height_offset)]
        observations.vertical_applied = True
        observations.notes.append(f"GNSS heights shifted by {float(gnss_height_offset):+.3f} m "
                                  "(--gnss_height_offset)")
    transform = read_initial_transform(initial_transform) if initial_transform else None
    result = refine(reconstruction, store, observations, options,
                    initial_transform=transform, progress=progress, checkpoints=cp_known,
                    checkpoint_observations=cp_observations)
    inputs = {"input_path": str(input_path),
              "citymodel": [str(p) for p in np.atleast_1d(citymodel)],
              "gnss_source": observations.source if observations is not None else None,
              "initial_transform": str(initial_transform) if initial_transform else None,
              "preset": preset, "options_file": str(options_file) if options_file else None}
    write_refined(result, output_path, output_type=output_type, output_frame=output_frame,
                  inputs=inputs)
    last = result.iterations[-1]
    # s0 of the final solve: the variance-component re-solve when there was one.
    s0 = (result.precision.variance.sigma0 if result.precision is not None
          else np.sqrt(last.final.sigma0_squared))
    if result.handed_back == "gnss_only":
        print(f"the city model could not help: wrote the GNSS-only adjustment of "
              f"{result.reconstruction.num_reg_images()} images")
    elif result.quality.verdict == "failed":
        print("the city model could not help, and without GNSS there is no other result: the "
              "refined block is written, but do not trust it")
    else:
        print(f"refined {result.reconstruction.num_reg_images()} images, "
              f"{result.reconstruction.num_points3D()} points; {last.num_assigned} tie points "
              f"on {last.num_faces} planes; s0 {s0:.3f}")
    print(result.quality.line())
    if result.observability:
        print(f"datum fixed by: {datum_line(result.observability)}")
    print(f"output: {output_path} (COLMAP model in {store.crs.label}"
          f"{'' if output_frame == 'crs' else ' minus origin'}, report.md, assignments.ply)")
    return result
