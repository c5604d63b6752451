"""The refine step (`colmap_citymodel.refine`): global workflow of Unger Table 3 with any
assignment method ("auto" by default: (c), then (a); or (a), (b), (c) throughout), or the
sliding-window workflow (`[workflow] mode = "sliding_window"`, Unger Table 5;
adjust.sliding_window) whose windows run between the coarse alignment and the final global
adjustment below.

1. SfM (COLMAP, done before) + 7-parameter similarity to GNSS (or a given initial transform;
   along a straight line the cameras' upright orientation fixes the roll);
2. bundle adjustment with GNSS priors and no model; image observations with normalised
   residual > 3 eliminated and the adjustment repeated without them (AdjustmentOptions.
   image_loss). This is the GNSS-only result that
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

import copy
import logging
import time
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
import pycolmap

from .adjust.correction_loop import every_point_alike
from .adjust.datum import hold_where_gnss_alone
from .adjust.marks import (active_marks, control_marks, mark_test, marks_in_adjustment,
                           marks_record, similarity_from_marks, snoop_marks)
from .adjust.staged import staged_adjustment_loop
from .adjust.observability import (DATUM, assigned_observability, datum_line,
                                   gnss_only_observability, left_to_gnss,
                                   unsettled_observability, weighting_observability)
from .adjust.problem import HybridProblem
from .adjust.steps import check_intrinsics, model_after_solve, step2_bundle_adjustment
from .align.block_to_model import crop_to_reconstruction, georegister
from .align.objective import BlockObjective
from .block.gnss import read_gnss
from .block.marks import read_gcp_list
from .block.priors import scale_sigma_from_gnss
from .block.reconstruction import camera_up_and_view, read_reconstruction, tie_points
from .citymodel.ground_faces import block_terrain, terrain_residuals
from .citymodel.read import peek_crs
from .citymodel.store import PlaneStore
from .errors import DatumError, NoOverlapError
from .options import RefineOptions
from .output.result import RefineResult
from .precision.accuracy import check_accuracy
from .precision.estimate import precision_after_refine
from .precision.quality import QualityThresholds, checkpoint_verdict, measure_quality

logger = logging.getLogger(__name__)


def refine(reconstruction: pycolmap.Reconstruction, city_model: PlaneStore, gnss=None,
           options: RefineOptions | None = None, *, initial_transform: pycolmap.Sim3d | None = None,
           exclude_point_ids: set[int] | None = None, progress: bool = True,
           checkpoints: dict | None = None, checkpoint_observations: list | None = None,
           location=None, location_radius: float = 100.0, marks=None,
           check_marks=None) -> RefineResult:
    """Georeference `reconstruction` and adjust it together with `city_model` (`refine_block`
    gives the other arguments' meaning).

    `marks` (block.marks.GroundMarks, model CRS): ground control marks, in every adjustment
    (adjust.marks); without GNSS, an initial transform or a location, they place the block.
    `check_marks` (the same): check points, only compared with the refined block
    (report.json `checkpoints`, precision.accuracy; they replace `checkpoints`)."""
    options = options or RefineOptions()
    control = None
    if marks is not None:
        control = control_marks(marks, reconstruction, city_model.origin,
                                options.marks.sigma_pixel)
        if initial_transform is None and gnss is None and location is None:
            initial_transform = similarity_from_marks(marks, reconstruction,
                                                      options.marks.sigma_pixel)
            if initial_transform is None:
                raise DatumError("without GNSS the control marks must place the block, but "
                                 "fewer than three of them (not on a line) are measured in two "
                                 "or more registered images", marks.path)
    if check_marks is not None:
        checkpoints, checkpoint_observations = check_marks.checkpoints()
    with marks_in_adjustment(control):
        result = refine_block(reconstruction, city_model, gnss, options,
                              initial_transform=initial_transform,
                              exclude_point_ids=exclude_point_ids, progress=progress,
                              checkpoints=checkpoints,
                              checkpoint_observations=checkpoint_observations,
                              location=location, location_radius=location_radius)
        result.control_marks = marks_after_refine(control, result.reconstruction,
                                                  result.warnings)
    if check_marks is not None and result.checkpoints is not None:
        check_points_into_verdict(result, check_marks)
    return result


def marks_after_refine(control, rec: pycolmap.Reconstruction, warnings: list[str]
                       ) -> dict | None:
    """report.json `control_marks`: each mark's test against the returned block; a warning
    per mark in the adjustment beyond its bound (one the blunder test could not leave out:
    too few marks to test, or the model and the marks disagree there)."""
    if control is None:
        return None
    for k in control.used:
        name, test = control.names[k], mark_test(control, rec, k)
        if test is None:
            continue
        control.tests[name] = {**control.tests.get(name, {}), **test}
        bound = control.tests[name].get("bound")
        if bound is not None and test["statistic"] > bound:
            warnings.append(f"control mark {name}: the block puts it "
                            f"{np.linalg.norm(test['offset_m']):.3f} m from its surveyed "
                            f"position (test {test['statistic']:.1f} > {bound:.1f}): check its "
                            "coordinates and its measurements")
    return marks_record(control)


def check_points_into_verdict(result: RefineResult, check_marks) -> None:
    """The check marks' accuracy (precision.accuracy) onto the check point evaluation, and its
    independent test of the block into the verdict (precision.quality.checkpoint_verdict)."""
    alpha = QualityThresholds().alpha
    result.checkpoints.accuracy = check_accuracy(result.checkpoints, check_marks,
                                                 alpha, options=result.options.marks,
                                                 reconstruction=result.reconstruction)
    if result.quality is not None:
        before = list(result.quality.reasons)
        checkpoint_verdict(result.quality, result.checkpoints.accuracy)
        if result.quality.reasons != before:
            logger.info(result.quality.line())


def refine_block(reconstruction: pycolmap.Reconstruction, city_model: PlaneStore, gnss=None,
                 options: RefineOptions | None = None, *,
                 initial_transform: pycolmap.Sim3d | None = None,
                 exclude_point_ids: set[int] | None = None, progress: bool = True,
                 checkpoints: dict | None = None, checkpoint_observations: list | None = None,
                 location=None, location_radius: float = 100.0) -> RefineResult:
    """Georeference `reconstruction` and adjust it together with `city_model`.

    `gnss` is a `block.gnss.GNSSObservations` (model CRS) or None; `initial_transform` maps the
    input frame to model CRS coordinates (used instead of a GNSS similarity when given).
    `exclude_point_ids` are never assigned to planes (e.g. check points in the model).
    The input reconstruction is not modified; the result holds a refined copy, or, when the
    quality gate fails, the GNSS-only adjustment (`result.quality`, `result.gnss_only`).
    `checkpoints` ({id: XYZ} model CRS) and `checkpoint_observations` ([(image, id, x, y)],
    precision.checkpoints.read_*) are only evaluated at the end (Delta, and sigma when
    covariances are on). `location` (x, y, model CRS): without GNSS (or with GNSS whose stated
    sigma is useless) the block is found on the model within `location_radius` m of it
    (align.locate) and refined with the model as the only datum.
    """
    options = with_correction_alike(options or RefineOptions())
    if options.workflow.mode == "sliding_window":  # bad window sizes before any work
        from .adjust.sliding_window import check_window_options

        check_window_options(options)
    run = Run(time.perf_counter(), exclude_point_ids, progress)
    rec = pycolmap.Reconstruction(reconstruction)
    start = place_on_model(rec, city_model, gnss, options, initial_transform, exclude_point_ids,
                           location, location_radius)
    run.lap("georegistration")
    rec, options, report2, eliminated2, intrinsics = adjust_without_model(rec, start.priors,
                                                                          options)
    gnss_only = pycolmap.Reconstruction(rec) if start.priors is not None else None
    run.lap("step2")
    placed = coarse_placement(rec, start, options, run)
    windows, loop = adjust_with_model(rec, placed.store, start.priors, options, placed.surface,
                                      placed.objective, placed.all_ids, exclude_point_ids,
                                      gnss_only, placed.scale_sigma, start.located, progress,
                                      run.timer, run.warnings)
    run.warnings += loop.warnings
    run.timer.update(loop.seconds)
    final = after_loop(loop, placed, start.priors, options, run)
    judged = judge(final, loop, placed, start, gnss_only, options, run, gnss)
    judged.sim3 = judged.sim3 * loop.move * placed.sim3  # input frame to local
    if judged.gnss_only_handed_back and gnss_only is not None:
        # Never hand back a block worse than GNSS alone, nor one moved without evidence.
        judged.reconstruction, judged.sim3 = gnss_only, start.sim3
        judged.observability = gnss_only_observability(judged.observability)
    precision = None if judged.reconstruction is gnss_only else precision_after_refine(
        final.last, options.precision, checkpoint_observations, judged.observability)
    correction = (_model_correction(placed.store, final.current, final.corrected, final.last,
                                    precision, options, run.warnings,
                                    handed_back=judged.reconstruction is gnss_only)
                  if final.corrected is not None and final.corrected.selection is not None
                  else None)
    evaluation = None
    if checkpoints is not None and checkpoint_observations is not None:
        from .precision.checkpoints import evaluate_with_precision

        evaluation = evaluate_with_precision(judged.reconstruction, checkpoints,
                                             checkpoint_observations, placed.store.origin,
                                             precision)
    return refine_result(start, placed, loop, final, judged, options, run, windows,
                         precision=precision, correction=correction, evaluation=evaluation,
                         step2=(report2, eliminated2, intrinsics), gnss_only=gnss_only)


@dataclass
class Run:
    """What one refine collects along the way: its seconds per stage, its warnings."""

    started: float
    exclude_point_ids: set[int] | None
    progress: bool
    timer: dict = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def lap(self, name: str) -> None:
        """The seconds since the last lap (or the start) as stage `name`."""
        self.timer[name] = time.perf_counter() - self.started - sum(self.timer.values())


@dataclass
class Placed:
    """The block on the model before the assign/adjust loop: the model with its checked
    terrain, the surfaces and the objective every stage scores against, the tie points, the
    coarse search's record and the similarity it applied (`sim3`, input frame to local)."""

    store: PlaneStore
    terrain: dict  # report.json `terrain`
    surface: object  # align.coarse.SurfaceDistance
    objective: BlockObjective
    all_ids: np.ndarray
    scale_sigma: float | None
    sim3: pycolmap.Sim3d
    coarse: object | None  # align.coarse.CoarseAlignment
    estimate_offset: bool
    offset_start: dict | None


def coarse_placement(rec: pycolmap.Reconstruction, start: "ModelStart", options: RefineOptions,
                     run: Run) -> Placed:
    """The block GNSS placed (`rec`, moved in place) onto the model: the terrain as it comes
    for the coarse search (align.coarse), then each terrain unit checked against the ground's
    tie points of the block on the model (citymodel.ground_faces), and the search again where
    the check dropped a unit that may have drawn it."""
    from .align.coarse import SurfaceDistance

    o_a, o_adj, o_w = options.assignment, options.adjustment, options.workflow
    priors, ids = start.priors, run.exclude_point_ids
    t0 = time.perf_counter()
    store, terrain = block_terrain(start.store, tie_points(rec, ids)[1], options.terrain,
                                   checked=start.located is not None)
    estimate_offset = gnss_offset_unknowns(priors, o_adj, rec)
    surface = SurfaceDistance(store, o_a.excluded_classes, o_adj.num_threads)
    all_ids, points = tie_points(rec, ids)
    objective = BlockObjective(surface, priors, all_ids, o_adj, o_w.divergence_alpha)
    straight = "roll_about_line" in start.details.get("cues", {})
    coarse = None
    # Also after a given initial transform: the bundle adjustment with GNSS has just moved
    # the block onto the GNSS, and with it by the GNSS's bias.
    if priors is not None and o_w.coarse_search_sigmas > 0:
        coarse = coarse_start(rec, points, store, surface, priors, objective, options,
                              straight=straight)
    if start.located is None:
        store, terrain = block_terrain(start.store, tie_points(rec, ids)[1], options.terrain)
        surface = SurfaceDistance(store, o_a.excluded_classes, o_adj.num_threads)
        objective = BlockObjective(surface, priors, all_ids, o_adj, o_w.divergence_alpha)
        if coarse is not None and coarse.moved and terrain.get("units_dropped"):
            # A terrain unit the check dropped may have drawn the search: again without it.
            rec.transform(coarse.sim3.inverse())
            coarse = coarse_start(rec, points, store, surface, priors, objective, options,
                                  straight=straight)
    if coarse is not None:
        run.timer["coarse_alignment"] = time.perf_counter() - t0
    sim3 = coarse.sim3 * start.sim3 if coarse is not None and coarse.moved else start.sim3
    return Placed(store, terrain, surface, objective, all_ids,
                  scale_sigma_from_gnss(priors) if priors is not None else None, sim3, coarse,
                  estimate_offset, start_gnss_offset(priors, rec) if estimate_offset else None)


@dataclass
class Final:
    """The block after the loop and what follows it (variance components, model correction):
    the reconstruction, the adjusted model, the last problem, the assignment."""

    reconstruction: pycolmap.Reconstruction
    current: PlaneStore
    last: object  # adjust.problem.HybridProblem
    assignment: object  # assign.assignment.Assignment
    vce: object | None
    corrected: object | None  # adjust.correction_loop.CorrectionResult


def after_loop(loop, placed: Placed, priors, options: RefineOptions, run: Run) -> Final:
    """The variance components or estimated generalisation offsets where asked, the GNSS
    offset the last solve estimated, and the model correction where asked."""
    from .precision.variance_components import final_solve_in_refine

    rec, current, assignment, last = loop.reconstruction, loop.current, loop.assignment, loop.last
    vce = None
    if last.blocks.faces.size:
        last, vce = final_solve_in_refine(rec, placed.store, assignment, priors, options,
                                          current, last)
        current = model_after_solve(current, last)
    if placed.estimate_offset:  # the last solve's priors (a re-weighted copy after VCE) hold it
        priors.offset = np.array(last.gnss.offset if last.gnss is not None else priors.offset)
    corrected = None
    if options.adjustment.correct_model and last.blocks.faces.size:
        corrected, rec, current, last, assignment = correct_model(
            rec, placed.store, current, last, assignment, priors, options, loop,
            placed.objective, run.exclude_point_ids, run.timer, run.warnings)
    return Final(rec, current, last, assignment, vce, corrected)


@dataclass
class Judged:
    """The verdict on the refined block and what it states: its observability, the GNSS
    offset, the shift that held it to GNSS where the planes leave it (`sim3`), the block."""

    reconstruction: pycolmap.Reconstruction
    observability: dict
    quality: object  # precision.quality.QualityReport
    gnss_offset: dict | None
    sim3: pycolmap.Sim3d | None

    # The planes and terrain fix no datum parameter (shifts, scale, rotations) that GNSS does
    # not fix better (adjust.observability.left_to_gnss): what the model changed is the
    # block's shape alone, under GNSS's own precision, no evidence to move on, so the
    # GNSS-only block is the result (not where the images correct the model: there GNSS's
    # block is the datum the model is corrected to).
    gnss_fixes_all: bool = False

    @property
    def verdict_failed(self) -> bool:
        return self.quality.verdict == "failed"

    @property
    def gnss_only_handed_back(self) -> bool:
        """Whether the GNSS-only block is the result: the verdict failed, or `gnss_fixes_all`."""
        return self.verdict_failed or self.gnss_fixes_all


def judge(final: Final, loop, placed: Placed, start: "ModelStart", gnss_only, options,
          run: Run, gnss) -> Judged:
    """The observability and the verdict (block_quality, the block held to GNSS where the
    planes leave it), the terrain's residuals, the GNSS offset's record; logged."""
    priors, rec = start.priors, final.reconstruction
    observability, quality, sim3 = block_quality(
        rec, final.assignment, final.current, final.last, loop, options,
        surface=placed.surface, priors=priors, gnss_only=gnss_only,
        scale_sigma=placed.scale_sigma, exclude_point_ids=run.exclude_point_ids, hold=True)
    if placed.terrain.get("num_faces"):
        placed.terrain["residuals"] = terrain_residuals(final.current, final.assignment, np.array(
            [rec.point3D(int(i)).xyz for i in final.assignment.point_ids]).reshape(-1, 3))
    gnss_offset = (offset_report(priors, observability, placed.offset_start, gnss)
                   if placed.estimate_offset else None)
    if gnss_offset is not None:
        logger.info(offset_line(gnss_offset))
    if start.located is not None and isinstance(quality.metrics, dict):
        quality.metrics["location_score_ratio"] = start.located["score_ratio"]
    logger.info("datum fixed by: %s", datum_line(observability))
    fixes_all = (priors is not None and quality.verdict != "failed"
                 and not options.adjustment.correct_model
                 and bool(np.all(left_to_gnss(observability, DATUM))))
    if fixes_all:
        quality.reasons.append("the planes and terrain fix no datum parameter that GNSS does "
                               "not fix better: the GNSS-only block is handed back")
    logger.info(quality.line())
    return Judged(rec, observability, quality, gnss_offset, sim3, fixes_all)


def refine_result(start, placed: Placed, loop, final: Final, judged: Judged, options,
                  run: Run, windows, *, precision, correction, evaluation, step2, gnss_only
                  ) -> RefineResult:
    """The RefineResult of one refine."""
    report2, eliminated2, intrinsics = step2
    blocks = final.last.blocks
    run.timer["total"] = time.perf_counter() - run.started
    result = RefineResult(
        reconstruction=judged.reconstruction, store=placed.store,
        adjusted_store=final.current, assignment=final.assignment,
        plane_faces=blocks.faces, plane_normals=blocks.normal_array,
        plane_offsets=blocks.offset_array, input_to_local=judged.sim3,
        georegistration_rms=start.rms, step2=report2, step2_eliminated=eliminated2,
        iterations=loop.iterations, options=options, warnings=run.warnings,
        seconds=run.timer, gnss_priors=start.priors, precision=precision,
        variance_components=final.vce, checkpoints=evaluation, gnss_only=gnss_only,
        quality=judged.quality, observability=judged.observability,
        observability_before=loop.observability_before, refined=final.reconstruction,
        datum_cues=start.details.get("cues", {}),
        coarse_alignment=placed.coarse.todict() if placed.coarse is not None else None,
        gnss_offset=judged.gnss_offset, model_correction=correction,
        sliding_window=windows.todict(options) if windows is not None else None,
        loop_stopped_by=loop.stopped_by, georegistration=start.located)
    result.terrain = placed.terrain
    result.intrinsics = intrinsics.todict() if intrinsics is not None else None
    return result


def with_correction_alike(options: RefineOptions) -> RefineOptions:
    """`options`, or with `correct_model` a copy that weighs every tie point alike
    (adjust.correction_loop.every_point_alike) in the loop before the correction too."""
    alike = every_point_alike(options.adjustment)
    if not options.adjustment.correct_model or alike is options.adjustment:
        return options
    options = copy.deepcopy(options)
    options.adjustment = alike
    return options


def adjust_without_model(rec: pycolmap.Reconstruction, priors, options: RefineOptions):
    """Step 2 and its test of the interior orientation (adjust.steps.check_intrinsics). Returns
    the block to go on with (step 2's, or the one solved with focal length and distortion free
    where the test finds them off, with options that refine them from then on), the options,
    step 2's report, its eliminated observations and the test (None: not run)."""
    before = pycolmap.Reconstruction(rec) if active_marks() is not None else None
    report, eliminated = step2_bundle_adjustment(rec, priors, options)
    if before is not None:  # the control marks' blunders (step 2 again without them)
        rec, report, eliminated = snoop_control_marks(rec, before, priors, options, report,
                                                      eliminated)
    intrinsics = check_intrinsics(rec, priors, options, report)
    if intrinsics is not None and intrinsics.refined:
        rec = intrinsics.freed
        options = copy.deepcopy(options)
        options.adjustment.refine_intrinsics = True
    return rec, options, report, eliminated, intrinsics


#: Solver iterations of each trial adjustment without a suspect control mark: a clean block
#: converges in a few, and where another blunder still pulls the block it only has to show
#: which mark stands out most (the one excluded is then solved without it in full).
SNOOP_ITERATIONS = 25


def snoop_control_marks(rec: pycolmap.Reconstruction, before: pycolmap.Reconstruction, priors,
                        options: RefineOptions, report, eliminated: int):
    """The control marks' blunder test on step 2's block `rec` (adjust.marks.snoop_marks), each
    trial and each repeat of step 2 from the block `before` step 2, so that a blunder's pull
    leaves nothing behind (no tie point observation eliminated for it). Returns the block,
    step 2's report and its eliminations."""
    marks = active_marks()
    solved = [(rec, report, eliminated)]

    def solve() -> pycolmap.Reconstruction:  # step 2 again without the excluded marks
        again = pycolmap.Reconstruction(before)
        solved.append((again, *step2_bundle_adjustment(again, priors, options)))
        return again

    def solve_without() -> pycolmap.Reconstruction:  # one plain solve, the mark under test out
        trial = pycolmap.Reconstruction(before)
        o = options.adjustment
        HybridProblem(trial, None, None, priors, replace(o, max_solver_iterations=min(
            o.max_solver_iterations, SNOOP_ITERATIONS)), robust_images=False,
            robust_planes=False).solve()
        return trial

    snoop_marks(marks, rec, solve, solve_without, options.marks.blunder_alpha)
    return solved[-1]


def gnss_offset_unknowns(priors, o_adj, rec: pycolmap.Reconstruction) -> bool:
    """Whether a GNSS offset common to the block is an unknown (`gnss_offset`, or the random
    effect of `face_weighting` "offsets"); if so, its prior set and its start fitted to `rec`."""
    estimate_offset = priors is not None and priors.estimates_offset
    if o_adj.face_weighting == "face" and priors is not None and not estimate_offset:
        logger.warning("faces as units weigh each face as one observation of its offset: "
                       "the GNSS's common bias, not estimated (--gnss_bias auto), pulls the "
                       "block as far as the faces let it")
    if estimate_offset:
        priors.offset_prior_sigma = o_adj.sigma_gnss_offset or None
    elif o_adj.face_weighting == "offsets" and priors is not None:
        estimate_offset = gnss_bias_as_random_effect(priors, o_adj)
    if estimate_offset:
        priors.fit_offset(rec)
    return estimate_offset


def adjust_with_model(rec, store, priors, options, surface, objective, all_ids,
                      exclude_point_ids, gnss_only, scale_sigma, located, progress: bool,
                      timer: dict, warnings: list[str]):
    """Steps 3-4: the sliding window's windows (with `workflow.mode` "sliding_window"), then
    the assign/adjust loop over the whole block. Returns (the windows or None, the loop's
    adjust.loop.LoopResult). A block found on the model alone whose planes leave its datum
    open ends as a failed model-only registration."""
    windows = None
    loop_options = options
    if options.workflow.mode == "sliding_window":
        # The windows' iterations and those of the global loop after them each end on a solve
        # with the original weights, which ends the sliding window closer to the truth
        # (docs/defaults.md, `solve_again_after_elimination`).
        loop_options = copy.deepcopy(options)
        loop_options.workflow.solve_again_after_elimination = True
        # Windows along the sequence, each on the model; the loop below is then the final
        # global hybrid adjustment of all images, starting from where the windows left them.
        from .adjust.sliding_window import sliding_window

        windows = sliding_window(rec, store, priors, loop_options, surface,
                                 exclude_point_ids=exclude_point_ids, progress=progress)
        warnings += windows.warnings
        timer["sliding_window"] = windows.seconds
    try:
        loop = staged_adjustment_loop(
            rec, store, priors, loop_options, objective, all_ids,
            placed=partial(first_loop_gate, surface=surface, priors=priors, gnss_only=gnss_only,
                           scale_sigma=scale_sigma, exclude_point_ids=exclude_point_ids),
            exclude_point_ids=exclude_point_ids, gnss_only=gnss_only, scale_sigma=scale_sigma,
            progress=progress)
    except DatumError as error:
        if located is None:
            raise
        from .align.locate import ModelOnlyFailure

        raise ModelOnlyFailure(f"the block was found on the model, yet {error.message}",
                               {**located, "verdict": "failed"}, error.path) from None
    return windows, loop


def block_quality(rec, assignment, current, last, loop, options, *,
                  surface, priors, gnss_only, scale_sigma, exclude_point_ids,
                  hold: bool = False):
    """The observability (from the data) of an adjusted block and the quality gate's verdict
    on it (precision.quality.measure_quality); `loop` (adjust.loop.LoopResult) tells whether
    the assignment loop diverged or ended unsettled, and how far the faces' weighting moved
    the block. `hold`: then `rec` is moved back to the GNSS-only block along the datum
    parameters the planes leave to GNSS (adjust.datum.hold_where_gnss_alone); the similarity
    that moved it is returned third (identity: none)."""
    _, points = tie_points(rec, exclude_point_ids)
    observability = weighting_observability(unsettled_observability(
        assigned_observability(points, assignment, current, priors, rec, options,
                               from_data=True), loop.unsettled_move), loop.weighting_move)
    quality = measure_quality(rec, gnss_only, surface, priors, assignment, last, observability,
                              points, options, loop.diverged, scale_sigma,
                              loop.unsettled_shift, store=current)
    moved = pycolmap.Sim3d()
    if hold and priors is not None:  # after the verdict measured what the model moved
        held, moved = hold_where_gnss_alone(rec, gnss_only, priors.image_ids,
                                            left_to_gnss(observability, DATUM))
        if np.any(held) and isinstance(quality.metrics, dict):
            quality.metrics["moved_back_to_gnss"] = dict(zip(DATUM, held.tolist()))
    return observability, quality, moved


def first_loop_gate(first, options, **context) -> str | None:
    """The quality gate on the block the loop with every tie point alike placed (before the
    faces' errors are estimated from it, adjust.staged): its reasons when it fails, else None.
    `context`: block_quality's keywords."""
    _, quality, _ = block_quality(first.reconstruction, first.assignment, first.current,
                                  first.last, first, options, **context)
    return "; ".join(quality.reasons) if quality.verdict == "failed" else None


@dataclass
class ModelStart:
    """Where refine starts: the block in the store's local frame (`sim3` from the input frame),
    its GNSS priors, the model near it with its terrain faces, and how it got there."""

    sim3: pycolmap.Sim3d
    priors: object  # block.priors.GNSSPriors | None
    rms: float | None  # the GNSS similarity's RMS (m)
    store: PlaneStore
    details: dict  # the georegistration's cues
    located: dict | None  # the model-only search's record (align.locate), None with GNSS


def place_on_model(rec: pycolmap.Reconstruction, city_model: PlaneStore, gnss, options,
                   initial_transform, exclude_point_ids, location, location_radius
                   ) -> ModelStart:
    """Step 1: `rec` (modified) into the model's local frame, by GNSS, a given transform or the
    model-only search around `location`; the model cropped to the block."""
    details: dict = {}
    located = None
    if initial_transform is None:
        from .align.locate import start_from_model

        start, gnss, located = start_from_model(rec, city_model, gnss, location,
                                                location_radius)
        if start is not None:
            initial_transform = start
    sim3, priors, geo_rms = georegister(rec, city_model, gnss, initial_transform, details,
                                        options.adjustment.gnss_offset)
    store = crop_to_reconstruction(city_model, rec, options.workflow.overlap_margin)
    logger.info("model: %d faces, %d vertices near the reconstruction", len(store.faces),
                len(store.vertices))
    if located is not None:
        details["cues"] = {k: "model only" for k in ("translation", "scale", "rotation")}
    return ModelStart(sim3, priors, geo_rms, store, details, located)


def correct_model(rec, store, current, last, assignment, priors, options, loop, objective,
                  exclude_point_ids, timer: dict, warnings: list[str]):
    """The model correction after the loop (adjust.correction_loop). Returns (the correction
    or None where it was undone, and the reconstruction, model, last problem and assignment
    refine goes on with)."""
    from .adjust.correction_loop import correction_loop

    t_correction = time.perf_counter()
    corrected = correction_loop(rec, store, current, priors, options, loop.threshold,
                                exclude_point_ids=exclude_point_ids,
                                baselines=loop.baselines, weights=loop.weights,
                                objective=objective, first_iteration=len(loop.iterations))
    loop.iterations += corrected.iterations
    timer["model_correction"] = time.perf_counter() - t_correction
    if corrected.undone is not None:
        warnings.append(f"model correction undone: {corrected.undone}")
        return None, corrected.reconstruction, current, last, assignment
    if corrected.last is not None:  # the block moved with the model
        return (corrected, corrected.reconstruction, corrected.current, corrected.last,
                corrected.assignment)
    return corrected, rec, corrected.current, last, assignment


def coarse_start(rec: pycolmap.Reconstruction, points: np.ndarray, store: PlaneStore, surface,
                 priors, objective: BlockObjective, options: RefineOptions, *, straight: bool):
    """The coarse alignment (align.coarse) of a GNSS-registered block: the GNSS-only block is
    off the model by the GNSS error (metres, mostly a bias) that a 2 m assignment threshold
    cannot bridge, so the shift (and the heading within GNSS's heading sigmas; along a straight
    line, the roll) that puts the tie points on the model is searched before any of them is
    assigned. `rec` is moved when that lowers the block objective. `points`: the tie points
    that may lie on the model (not the check points). Returns the search's result
    (align.coarse.CoarseAlignment, `moved`: whether `rec` moved)."""
    from .align.coarse import coarse_alignment, heading_sigma_deg
    from .errormodel.model import placement_score

    # The images with GNSS fixed the georegistration; if they lie on a line (`straight`), its
    # rotation about that line came from the cameras' upright orientation and is searched again.
    centres = np.array([rec.image(int(i)).projection_center() for i in priors.image_ids])
    up, view = camera_up_and_view(rec, priors.image_ids)
    sigmas = np.median(priors.sigmas, axis=0)
    score = placement_score(surface, points, priors, priors.observed_points(rec),
                            options.adjustment)
    coarse = coarse_alignment(points, centres, up, view, store, score, sigmas, straight,
                              options.workflow.coarse_search_sigmas,
                              free_height=bool(priors.free_offset_axes[2]),
                              heading_sigma=heading_sigma_deg(centres, sigmas))
    if objective(rec, coarse.sim3) < objective(rec):
        rec.transform(coarse.sim3)
        coarse.moved = True
        return coarse
    logger.info("coarse alignment kept the GNSS-only position (no better objective)")
    return coarse


def _sigma_record(sigma) -> float | list[float] | None:
    """A prior sigma (one, or one per axis) as report.json holds it."""
    if sigma is None or np.ndim(sigma) == 0:
        return None if sigma is None else float(sigma)
    return [float(v) for v in sigma]


def gnss_bias_as_random_effect(priors, o_adj) -> bool:
    """With the faces' errors as unknowns (`face_weighting` "offsets") the GNSS error common to
    the block is one too, with the prior N(0, b^2) per axis, b its share of the stated sigmas
    (`gnss_bias_share`, observability.gnss_bias_sigmas): the model, which then weighs about
    as many observations as it has faces, is not pulled by a bias GNSS shares over all its
    images. True if set (GNSS with sigmas and a share > 0)."""
    from .adjust.observability import gnss_bias_sigmas

    bias = gnss_bias_sigmas(priors, o_adj.gnss_bias_share)
    if bias is None:
        return False
    priors.offset_axes = np.ones(3, bool)
    priors.offset_prior_sigma = bias
    priors.bias_is_random = True
    return True


def start_gnss_offset(priors, rec: pycolmap.Reconstruction) -> dict:
    """The GNSS offset where the start-up (coarse search, or the georegistration) put the
    block; drops its prior when the block is further off than 3 prior sigmas (heights in
    another system, above take-off), leaving the offset free."""
    offset = priors.fit_offset(rec).copy()
    axes = np.asarray(priors.offset_axes, bool)
    prior = priors.offset_prior_sigma
    record = {"start_m": offset[axes].tolist(), "prior_sigma_m": _sigma_record(prior),
              "prior_dropped": False}
    if priors.bias_is_random:
        logger.info("GNSS bias at the start: %s m (prior sigma %s m)",
                    np.round(offset[axes], 2).tolist(), np.round(prior, 2).tolist())
    elif prior and np.any(np.abs(offset[axes]) > 3.0 * prior):
        logger.info("the GNSS positions are %s m off the block on the model: more than 3 x %g m, "
                    "so the GNSS offset is estimated without its prior (another height system, "
                    "heights above take-off?)", np.round(offset[axes], 2).tolist(), prior)
        priors.offset_prior_sigma = None
        record["prior_dropped"] = True
    else:
        logger.info("GNSS offset at the start: %s m", np.round(offset[axes], 2).tolist())
    return record


def offset_report(priors, observability: dict, start: dict | None, gnss) -> dict:
    """report.json `gnss_height_offset` (and the 3D bias): the estimated constant GNSS offset
    (model minus GNSS, m) with its a posteriori sigma (the planes' hold on the block's
    position, each plane with its generalisation error, and the GNSS mean)."""
    from .adjust.observability import offset_sigma

    axes = np.asarray(priors.offset_axes, bool)
    sigma = offset_sigma(observability, priors)
    geoid = getattr(gnss, "geoid", None)
    out = {"estimated": "all" if axes.all() else "height",
           "value_m": float(priors.offset[2]),
           "sigma_m": None if np.isnan(sigma[2]) else float(sigma[2]),
           "relative_to": ("GNSS heights converted with the fallback geoid "
                           f"{geoid['name']} ({geoid['grid']})" if geoid else
                           "GNSS heights as read"),
           "geoid": geoid,
           "prior_m": 0.0, **(start or {}),
           "prior_sigma_used_m": _sigma_record(priors.offset_prior_sigma),
           "random_effect": bool(priors.bias_is_random)}
    if axes.all():
        out["bias_enu_m"] = priors.offset.tolist()
        out["bias_sigma_enu_m"] = [None if np.isnan(v) else float(v) for v in sigma]
    return out


def offset_line(report: dict) -> str:
    """One line for the log and the console."""
    sigma = f" +- {report['sigma_m']:.2f}" if report["sigma_m"] is not None else ""
    line = (f"GNSS height offset (model minus GNSS, estimated from the model): "
            f"{report['value_m']:+.2f}{sigma} m")
    if report.get("geoid"):
        line += f" relative to {report['geoid']['name']} heights"
    if "bias_enu_m" in report:
        bias = ", ".join(f"{v:+.2f}" for v in report["bias_enu_m"][:2])
        sigmas = [s for s in report["bias_sigma_enu_m"][:2]]
        line += (f"; horizontal GNSS bias E, N: {bias} m" + (
            f" (+- {sigmas[0]:.2f}, {sigmas[1]:.2f})" if None not in sigmas else ""))
    return line


def _model_correction(store: PlaneStore, current: PlaneStore, corrected, last, precision,
                      options, warnings: list[str], *, handed_back: bool):
    """The record of what the images corrected in the model (adjust.model_correction), with
    each corrected vertex's sigma from the precision stage; None when the GNSS-only result is
    handed back (a block the model could not help does not correct the model either)."""
    from .adjust.model_correction import summarise_correction
    from .precision.estimate import vertex_covariances

    if handed_back:
        warnings.append("the model is not corrected: the GNSS-only block is handed back")
        return None
    ids = cov = None
    note = "no covariances"
    problem = corrected.covariance_problem
    try:
        ids, cov, note = vertex_covariances(problem, precision if problem is last else None)
    except (RuntimeError, np.linalg.LinAlgError, MemoryError) as error:
        logger.warning("model correction: vertex covariances failed (%s); shifts without "
                       "sigmas", error)
        note = f"covariances failed: {error}"
    correction = summarise_correction(store, current, corrected.selection, ids, cov,
                                      options.adjustment.correction_significance, note,
                                      options.adjustment.correction_max_sigma)
    summary = correction.todict()
    logger.info("model correction: %d faces corrected, %d vertices moved (RMS %.3f m), %d of "
                "them significantly (> %.1f sigma)", summary["num_corrected_faces"],
                summary["num_corrected_vertices"], summary["shift_rms_m"] or 0.0,
                summary["num_significant_vertices"], correction.threshold)
    return correction


# -- CLI entry: read inputs, refine, write outputs ------------------------------------------------

#: Metres around the GNSS positions in which city model buildings are read.
GNSS_READ_MARGIN = 250.0


@dataclass
class RefineInputs:
    """What refine reads besides the reconstruction: the options, the city model, the GNSS
    and the check points, with the arguments the outputs need (shared by `refine` and `map`)."""

    options: RefineOptions
    store: PlaneStore
    observations: object  # block.gnss.GNSSObservations or None
    initial_transform: pycolmap.Sim3d | None
    checkpoints: dict | None
    checkpoint_observations: list | None
    write_model: bool
    inputs: dict  # report.json `inputs`
    reconstruction: pycolmap.Reconstruction | None = None  # of `input_path`, when given
    marks: object = None  # block.marks.GroundMarks: the control marks (--gcp), or None
    check_marks: object = None  # the same: check points in gcp_list format, or None


def read_inputs(citymodel, output_path, *, input_path=None, database=None, gnss=None, gnss_crs=None,
                exif=None, initial_transform=None, preset="generalised", options_file=None,
                lod=2, model_crs=None, target_crs=None, precision=None,
                gnss_height_offset=None, gnss_bias=None, lever_arm=None, checkpoints=None,
                checkpoint_observations=None, sigma_generalisation=None, tolerance=None,
                variance_components=None, assignment=None, write_model=None, num_threads=None,
                terrain=None, terrain_sigma=None,
                workflow=None, location=None, location_radius=100.0, gcp=None,
                gcp_sigma=None) -> RefineInputs:
    """Options, city model, GNSS and check points as `main` takes them, and the reconstruction
    of `input_path` if given; fails on a taken `output_path` before any expensive work.
    `gcp`: a gcp_list.txt of control marks; `checkpoints` without `checkpoint_observations`: one
    of check marks; `gcp_sigma` (H, V m): their sigmas where the lines give none."""
    from .align.georegister import read_initial_transform
    from .citymodel.crs import user_crs
    from .files import atomic_directory

    options = _options_from_arguments(preset, options_file, precision, sigma_generalisation,
                                      tolerance, variance_components, assignment, workflow,
                                      terrain, terrain_sigma, gnss_bias, num_threads,
                                      gcp_sigma)
    if gnss_height_offset == "auto":
        if options.adjustment.gnss_offset == "none":
            options.adjustment.gnss_offset = "height"
        gnss_height_offset = None
    if write_model:  # writing the corrected model back means correcting it
        options.adjustment.correct_model = True
    if write_model is None:
        write_model = options.adjustment.correct_model
    cp_known = cp_observations = None
    if checkpoints is None and checkpoint_observations is not None:
        from .errors import InputError

        raise InputError("--checkpoint_observations needs --checkpoints ('id X Y Z' lines)")
    if checkpoint_observations is not None:
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
    reconstruction = read_reconstruction(input_path) if input_path is not None else None
    crs = user_crs(target_crs) if target_crs else peek_crs(citymodel, model_crs)
    observations = None
    if crs is not None:
        observations = read_gnss(database=database, gnss=gnss, gnss_crs=gnss_crs, exif=exif,
                                 target_crs=crs, default_sigma=options.adjustment.sigma_gnss)
    check_path = None if checkpoint_observations else checkpoints
    marks, check_marks = read_marks(gcp, check_path, crs, options)  # None without a CRS yet
    store = _read_model_near(citymodel, crs, model_crs, target_crs, lod, observations, marks,
                             location, location_radius)
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
    if crs is None:
        marks, check_marks = read_marks(gcp, check_path, store.crs, options)
    if check_marks is not None:  # also as plain check points (map evaluates those)
        cp_known, cp_observations = check_marks.checkpoints()
    inputs = {**({"input_path": str(input_path)} if input_path is not None else {}),
              **{k: str(v) for k, v in (("gcp", gcp), ("checkpoints", checkpoints)) if v},
              "citymodel": [str(p) for p in np.atleast_1d(citymodel)],
              "gnss_source": observations.source if observations is not None else None,
              "initial_transform": str(initial_transform) if initial_transform else None,
              "preset": preset, "options_file": str(options_file) if options_file else None}
    return RefineInputs(options, store, observations, transform, cp_known, cp_observations,
                        bool(write_model), inputs, reconstruction, marks, check_marks)


def _options_from_arguments(preset, options_file, precision, sigma_generalisation, tolerance,
                            variance_components, assignment, workflow, terrain, terrain_sigma,
                            gnss_bias, num_threads, gcp_sigma) -> RefineOptions:
    """The preset or options file, with the command line's overrides."""
    options = (RefineOptions.from_toml(options_file, preset) if options_file
               else RefineOptions.preset(preset))
    if precision is not None:  # --precision on/off/auto overrides the options file
        options.precision.covariances = precision
    if sigma_generalisation is not None:
        options.adjustment.sigma_generalisation = float(sigma_generalisation)
    if tolerance is not None:  # --tolerance overrides the options file
        options.mergedict({"precision": {"tolerance": float(tolerance)}}, source="--tolerance")
    if variance_components is not None:
        options.precision.variance_components = bool(variance_components)
    if assignment is not None:  # --assignment overrides the options file
        options.assignment.method = assignment
    if workflow is not None:  # --workflow overrides the options file
        options.mergedict({"workflow": {"mode": workflow}}, source="--workflow")
    if terrain is not None or terrain_sigma is not None:  # --terrain FILE ... | none
        from .citymodel.terrain import terrain_options

        terrain_options(options.terrain, terrain, terrain_sigma)
    if gnss_bias == "auto":
        options.adjustment.gnss_offset = "all"
    elif gnss_bias is not None:
        from .errors import InputError

        raise InputError(f"--gnss_bias takes auto, got {gnss_bias!r}")
    if num_threads is not None:  # threads of each Ceres solve (a batch worker uses one)
        options.adjustment.num_threads = int(num_threads)
    if gcp_sigma is not None:  # --gcp_sigma H V overrides the options file
        options.mergedict({"marks": dict(zip(("sigma_horizontal", "sigma_vertical"),
                                             map(float, gcp_sigma)))}, source="--gcp_sigma")
    return options


def _read_model_near(citymodel, crs, model_crs, target_crs, lod, observations, marks, location,
                     location_radius) -> PlaneStore:
    """The city model's buildings near the block: around the GNSS positions, else the location
    hint, else the control marks (of a directory of tiles only the tiles there are read)."""
    from .citymodel.crs import user_crs
    from .citymodel.read import read_city_model

    bbox = None
    if observations is not None:
        bbox = np.array([observations.positions.min(0) - GNSS_READ_MARGIN,
                         observations.positions.max(0) + GNSS_READ_MARGIN])
    elif location is not None:  # no GNSS: the model around the location hint
        reach = float(location_radius) + GNSS_READ_MARGIN
        bbox = np.array([[location[0] - reach, location[1] - reach, -1e5],
                         [location[0] + reach, location[1] + reach, 1e5]])
    if bbox is None and marks is not None:  # no GNSS: the model around the control marks
        bbox = marks_box(marks)
    if bbox is not None:  # of a directory of tiles, only those near the block are read
        from .citymodel.tiles import files_near

        citymodel = files_near(citymodel, bbox, crs,
                               assumed=user_crs(model_crs) if model_crs else None)
    try:
        store = read_city_model(citymodel, lod=lod, crs=model_crs, target_crs=target_crs,
                                bbox_crs=bbox)
    except NoOverlapError as error:
        if observations is None:
            raise NoOverlapError(
                f"the city model has no building within {reach:.0f} m of the location hint "
                f"({location[0]:.1f}, {location[1]:.1f}): {error.message}; check the hint's "
                "coordinates (model CRS) and the model tiles", error.path) from None
        raise NoOverlapError(
            "the city model does not overlap the GNSS positions "
            f"({observations.path or observations.source}, {GNSS_READ_MARGIN:.0f} m margin): "
            f"{error.message}; check the GNSS CRS and the model tiles", error.path) from None
    return store


def read_marks(gcp, checkpoints, crs, options: RefineOptions):
    """The control marks of `gcp` and the check marks of `checkpoints` (gcp_list.txt files, or
    None) in the city model's `crs`, with the sigmas of `options.marks` where a line states
    none; (None, None) while the CRS is not known (None)."""
    sigma = (options.marks.sigma_horizontal, options.marks.sigma_vertical)
    return tuple(read_gcp_list(path, crs, sigma) if path is not None and crs is not None
                 else None for path in (gcp, checkpoints))


def marks_box(marks) -> np.ndarray:
    """(2, 3) the box around the control marks in which city model tiles are read."""
    xyz = np.array([m.position for m in marks.marks])
    return np.array([xyz.min(0) - GNSS_READ_MARGIN, xyz.max(0) + GNSS_READ_MARGIN])


def write_outputs(result: RefineResult, output_path, read: RefineInputs, *, output_type="bin",
                  output_frame="crs", lod=2, model_crs=None, what="refined") -> None:
    """Write `result` into the new directory `output_path` (atomically) and print the summary
    lines; `what` names the block in them ("refined", "mapped")."""
    from .output.write import write_refined

    store = result.store
    write_refined(result, output_path, output_type=output_type, output_frame=output_frame,
                  inputs=read.inputs, write_model=read.write_model, model_lod=lod,
                  model_crs=model_crs)
    last = result.iterations[-1]
    # s0 of the final solve: the variance-component re-solve when there was one.
    s0 = (result.precision.variance.sigma0 if result.precision is not None
          else np.sqrt(last.final.sigma0_squared))
    if result.handed_back == "gnss_only":
        beyond = "" if result.quality.verdict == "failed" else " beyond GNSS"
        print(f"the city model could not help{beyond}: wrote the GNSS-only adjustment of "
              f"{result.reconstruction.num_reg_images()} images")
    elif result.quality.verdict == "failed":
        print(f"the city model could not help, and without GNSS there is no other result: the "
              f"{what} block is written, but do not trust it")
    else:
        print(f"{what} {result.reconstruction.num_reg_images()} images, "
              f"{result.reconstruction.num_points3D()} points; {last.num_assigned} tie points "
              f"on {last.num_faces} planes; s0 {s0:.3f}")
    print(result.quality.line())
    if result.gnss_offset is not None:
        print(offset_line(result.gnss_offset))
    if result.observability:
        print(f"datum fixed by: {datum_line(result.observability)}")
    if result.model_correction is not None:
        summary = result.model_correction.todict()
        print(f"model correction: {summary['num_corrected_faces']} faces corrected, "
              f"{summary['num_corrected_vertices']} vertices moved, "
              f"{summary['num_significant_vertices']} significantly; model_changes.csv"
              + (", corrected_model" if read.write_model else ""))
    print(f"output: {output_path} (COLMAP model in {store.crs.label}"
          f"{'' if output_frame == 'crs' else ' minus origin'}, report.md, assignments.ply)")


def write_failed_report(output_path, inputs: dict, error) -> None:
    """`output_path`/report.json of a refine that ended before any result (a model-only
    georegistration that is ambiguous or that the planes cannot hold): the inputs, the
    search's findings, the verdict "failed"."""
    import json

    from .files import atomic_directory

    report = {"inputs": inputs, "georegistration": error.report,
              "quality": {"verdict": "failed", "reasons": [error.message],
                          "metrics": {"location_score_ratio": error.report.get("score_ratio")}}}
    with atomic_directory(output_path) as directory:
        (Path(directory) / "report.json").write_text(json.dumps(report, indent=2))
    print(f"output: {output_path} (report.json only: no result)")


def main(input_path, citymodel, output_path, *, output_type="bin", output_frame="crs",
         progress=True, lod=2, model_crs=None, sequence=False, **kwargs) -> RefineResult:
    """`colmap-citymodel refine`: read everything, refine, write `output_path` atomically.
    The other keyword arguments are `read_inputs`'s:
    `checkpoints` / `checkpoint_observations`: files (evaluate's formats) of check points that
    are evaluated at the end (Delta, sigma; report.json `checkpoints`).
    `gnss_height_offset`: metres added to the GNSS heights, or "auto" (estimated from the
    model, AdjustmentOptions.gnss_offset "height"); `gnss_bias` "auto": a 3D bias ("all").
    `write_model`: correct the model and write it back in its own format (default: with the
    correct_model preset). `workflow`: "global" or "sliding_window" (overrides the options
    file's `[workflow] mode`). `location` (x, y) and `location_radius`: without GNSS, the
    block is found on the model near the hint (align.locate); when two places fit it about
    equally well, or its planes cannot hold it, only report.json is written and
    ModelOnlyFailure raised (exit 3). `sequence`: the images are video frames named in
    capture order; frames whose registered pose jumps from their neighbours' are reported
    (precision.sequence; report.json quality.metrics.sequence and warnings). An `input_path`
    that holds COLMAP's numbered models
    (sparse/0, sparse/1, ...) instead of one: each part is refined on its own into
    `output_path`/<part> (`refine_parts`)."""
    parts = model_parts(input_path)
    if parts:
        return refine_parts(parts, citymodel, output_path, output_type=output_type,
                            output_frame=output_frame, progress=progress, lod=lod,
                            model_crs=model_crs, sequence=sequence, **kwargs)
    read = read_inputs(citymodel, output_path, input_path=input_path, lod=lod,
                       model_crs=model_crs, **kwargs)
    from .align.locate import ModelOnlyFailure

    try:
        result = refine(read.reconstruction, read.store, read.observations, read.options,
                        initial_transform=read.initial_transform, progress=progress,
                        checkpoints=read.checkpoints,
                        checkpoint_observations=read.checkpoint_observations,
                        location=kwargs.get("location"),
                        location_radius=kwargs.get("location_radius", 100.0),
                        marks=read.marks, check_marks=read.check_marks)
    except ModelOnlyFailure as error:  # no result: the report says why
        write_failed_report(output_path, read.inputs, error)
        raise
    if sequence:
        add_sequence_check(result)
    write_outputs(result, output_path, read, output_type=output_type,
                  output_frame=output_frame, lod=lod, model_crs=model_crs)
    return result


def add_sequence_check(result: RefineResult) -> None:
    """The neighbouring-frame check of the returned block into its quality figures, a warning
    per frame that jumps."""
    from .precision.sequence import sequence_check

    check = sequence_check(result.reconstruction)
    if result.quality is not None and isinstance(result.quality.metrics, dict):
        result.quality.metrics["sequence"] = check
    for camera in check["cameras"].values():
        result.warnings += [f"sequence: frame {j['image']} lies {j['off_path_m']:.2f} m off "
                            f"its neighbours' path, {j['turn_deg']:.1f} deg from their view"
                            for j in camera["jumps"]]


def model_parts(input_path) -> list[Path]:
    """COLMAP's numbered models in `input_path` (a mapper's sparse/ with 0, 1, ...: parts of
    the block that share no images) when it holds no model itself; else none."""
    path = Path(input_path)
    if not path.is_dir() or any((path / f"cameras.{e}").exists() for e in ("bin", "txt")):
        return []
    return sorted((p for p in path.iterdir() if p.is_dir() and p.name.isdigit()
                   and any((p / f"cameras.{e}").exists() for e in ("bin", "txt"))),
                  key=lambda p: int(p.name))


def refine_parts(parts: list[Path], citymodel, output_path, **kwargs) -> RefineResult:
    """Refine each part of a model on its own (`main`) into `output_path`/<part>: with GNSS
    each is registered to its own positions, without it each is found on the model near the
    same location hint. Returns the result of the first part whose verdict is the worst;
    raises ModelOnlyFailure when no part has a result."""
    from .align.locate import ModelOnlyFailure
    from .files import check_new_directory

    check_new_directory(output_path)
    results, failures = [], []
    for part in parts:
        logger.info("model part %s of %d", part.name, len(parts))
        try:
            results.append(main(part, citymodel, Path(output_path) / part.name, **kwargs))
        except ModelOnlyFailure as error:  # its report.json is written; the others go on
            print(f"part {part.name}: {error}")
            failures.append(error)
    if not results:
        raise ModelOnlyFailure(f"none of the {len(parts)} model parts could be registered",
                               {"parts": [f.report for f in failures]})
    rank = {"ok": 0, "weak": 1, "failed": 2}
    worst = max(results, key=lambda r: rank.get(r.quality.verdict, 2))
    if failures and worst.quality.verdict != "failed":
        worst.quality.verdict = "failed"  # a part without a result fails the whole
        worst.quality.reasons.append(f"{len(failures)} of {len(parts)} model parts failed")
    return worst
