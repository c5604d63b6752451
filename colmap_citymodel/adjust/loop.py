"""Steps 3-4 of the global workflow, repeated: assign the tie points to the model planes, solve
the hybrid adjustment (robust on f_dTP where needed), until the RMS of the normalised residuals
settles, two solves in a row move no camera by more than a few millimetres, a solve that moved
them that little is followed by an assignment that keeps its planes and nearly all of its points,
an assignment repeats an earlier one (a cycle), the planes alternate between two sets with small
moves (the best of them is kept), the block objective worsens, or the iterations run out.

Assignments are recomputed from the current estimate every iteration; vertex-plane relations
never change; the threshold never grows (no flip-flop between two assignments); an f_dTP
eliminated as an outlier is not assigned to its face again. The first assignment is followed by
similarity rounds that move the whole block onto its planes. A solve that changes the scale
further than GNSS allows holds the scale from then on, and is undone first if it changed the
scale by far more (a collapse onto a few planes); a height that the planes leave to GNSS is
held where the first assignment and its similarity rounds put it (workflow.hold_gnss_height);
a solve that moves the block away from the model ends the loop at the best iterate.

The non-robust problem of one iteration is kept for the next where the set of planes and the
priors stay (HybridProblem.reassign exchanges the f_dTP blocks of the tie points that changed
plane); an assignment equal to the one the last solve used ends the loop without a solve.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import pycolmap
from tqdm import tqdm

from ..align.objective import BlockObjective
from ..assign.assignment import Assignment, Observers
from ..assign.direct import centred_surfaces
from ..assign.schedule import (assign, initial_threshold, next_threshold, resolve_method,
                               without_roof_points_seen_from_below)
from ..block.priors import GNSSPriors
from ..block.reconstruction import TiePointReader, camera_centres, observer_centres
from ..citymodel.ground_faces import terrain_mask
from ..citymodel.store import PlaneStore
from ..errors import DatumError
from ..options import AdjustmentOptions, AssignmentOptions, RefineOptions
from .datum import check_datum
from .faces import (estimate_sigma_face, face_offsets, outlier_factors, sigma_face_in_use,
                    snooped_faces)
from .observability import assigned_observability, left_to_gnss, offset_refusal
from .problem import LEVEL_FREE, BaselinePriors, HybridProblem, PosePriors
from .record import IterationRecord, cameras_settled, remaining_move
from .scale import (SCALE_RUNAWAY_SIGMAS, SCALE_UNDO_SIGMAS, baseline_priors, level_prior,
                    scale_change, shift_runaway)
from .steps import RoofObservers, align_block_to_planes, model_after_solve

logger = logging.getLogger(__name__)

#: The shifts held where the first assignment put the block when the planes leave them to GNSS:
#: the height only. Vertical walls never fix it; E or N can seem free at the first assignment,
#: metres from the model, and be fixed by the walls once the height is known; held, they
#: would keep the block from its walls.
HEIGHT = np.array([False, False, True])


@dataclass
class LoopResult:
    """Where the loop ended: the block (the best iterate), the model state, the assignment and
    the last solved problem."""

    reconstruction: pycolmap.Reconstruction
    current: PlaneStore  # the model after the last solve (adjusted vertices, refitted planes)
    assignment: Assignment
    last: HybridProblem
    iterations: list[IterationRecord]
    move: pycolmap.Sim3d  # what the similarity rounds after the first assignment applied
    observability_before: dict  # of the first assignment
    diverged: str | None  # why the loop stopped early, if the objective worsened
    warnings: list[str] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    # What a model correction after the loop continues with: the last assignment threshold,
    # the baseline priors that hold the scale (if any), the tie points' sampling weights.
    threshold: float = 0.0
    baselines: BaselinePriors | None = None
    weights: np.ndarray | None = None
    # Out of iterations: the largest camera move of the last iteration (m) and how far the
    # loop would still move the block (m, E N U; record.remaining_move); None if it stopped.
    unsettled_shift: float | None = None
    unsettled_move: np.ndarray | None = None
    # The rule that ended the loop: "rms", "camera_shift", "assignment_change",
    # "same_assignment", "cycle", "alternating_planes" or "diverged"; None when the iterations
    # ran out.
    stopped_by: str | None = None


def adjustment_loop(rec: pycolmap.Reconstruction, store: PlaneStore, priors: GNSSPriors | None,
                    options: RefineOptions, objective: BlockObjective, all_ids: np.ndarray, *,
                    exclude_point_ids: set[int] | None = None,
                    gnss_only: pycolmap.Reconstruction | None = None,
                    scale_sigma: float | None = None, progress: bool = True,
                    pose_priors: PosePriors | None = None,
                    hold_runaway_scale: bool = True,
                    best_when_unsettled: bool = True) -> LoopResult:
    """Run steps 3-4 on `rec` (modified in place; the result may hold the best iterate's copy
    instead). `store` is the model as given (its vertices are observed); `gnss_only` and
    `scale_sigma` let the loop hold the block's scale where the planes cannot give it, and,
    with `hold_runaway_scale`, from a solve on that changes it further than GNSS allows.
    `pose_priors`: frames held near given poses in every solve (a sliding window's images
    kept from the window before). `best_when_unsettled`: a loop that runs out of iterations,
    or swings between two sets of planes, returns its best iterate by the block objective;
    False: its last (the faces' loop, whose estimated offsets move the points off the given
    planes the objective measures them against)."""
    o_a, o_adj, o_w = options.assignment, options.adjustment, options.workflow
    current = store
    threshold = initial_threshold(o_a)
    weights = None
    if o_a.weighted_sampling:
        from ..assign.indirect import point_quality_weights

        weights = point_quality_weights(rec, all_ids)
    assignment: Assignment | None = None
    iterations: list[IterationRecord] = []
    observability_before: dict = {}
    warnings: list[str] = []
    seconds = {"assignment": 0.0, "hybrid_solves": 0.0}
    total_move = pycolmap.Sim3d()
    baselines = None
    level = None  # scale.level_prior: the height held where the first assignment put it
    runaway = np.zeros(3, bool)  # axes held since a solve ran away along them (shift_runaway)
    previous_rms = None
    last = None
    best = None  # (objective, iteration, reconstruction copy, assignment, current)
    diverged = None
    seen: dict[bytes, int] = {}  # assignment (faces of all points, threshold) -> iteration
    keep_best = False  # out of iterations: the best iterate, not the last, is the result
    unsettled_shift = None  # out of iterations: how far the last one still moved the cameras
    unsettled_move = None  # and how far it would still move the block (record.remaining_move)
    stopped_by = None
    face_factors: dict[int, float] = {}  # faces the adjustment weighs less (adjust.faces)
    dropped_faces: dict[int, float] = {}  # faces no tie point goes to (adjust.faces), their z
    # The sigma of the faces' offsets (m): given, or estimated from them after each solve.
    sigma_face = sigma_face_in_use(o_adj)
    # The last non-robust problem, kept for the next iteration (options.workflow.reuse_problem).
    reusable: HybridProblem | None = None
    solved: Assignment | None = None  # the assignment of the last solve (original weights)
    face_sets: list[bytes] = []  # the planes of each kept iteration
    eliminated_from = None  # the face each tie point was last eliminated from (-1: none)
    roof_observers = RoofObservers(store, o_a)  # the tie points keep their order in the loop
    read_tie_points = TiePointReader(exclude_point_ids)
    value = None  # the block objective after the last kept iteration
    bar = tqdm(range(o_w.max_iterations), desc="refine", unit="it", disable=not progress)
    for iteration in bar:
        t0 = time.perf_counter()
        point_ids, points = read_tie_points(rec)
        surfaces = current  # where the tie points are looked for
        if assignment is not None:
            if o_a.window == "centred" and resolve_method(o_a, threshold) == "direct":
                surfaces = centred_surfaces(points, point_ids, current, threshold, o_a)
            # The tie point set does not change inside the loop: same ids in the same order.
            # The threshold never grows again: no flip-flop between two assignments.
            threshold = min(threshold, next_threshold(assignment, points, surfaces, o_a,
                                                      window_sigma(o_adj, sigma_face)))
        observers = roof_observers(rec, point_ids)
        # Roofs keep only the points seen from above once the block is on the model: while
        # the first assignment and the similarity rounds bring it there from metres away,
        # parapets and eaves near a roof's plane hold its height (from a street they are
        # often the only points near a roof).
        kept_faces = assignment.faces if assignment is not None else None
        assignment = assign(points, point_ids, surfaces, threshold, o_a, weights,
                            observers if iterations else None, kept_faces)
        if eliminated_from is None:  # the tie points keep their order inside the loop
            eliminated_from = np.full(len(point_ids), -1, np.int64)
        if o_w.keep_eliminated:
            assignment = _without_eliminated(assignment, eliminated_from, points, o_a,
                                             kept_faces)
        if iterations and o_adj.face_test_alpha is not None:
            assignment = without_contradicted_faces(assignment, points, current, options,
                                                    sigma_face, dropped_faces, kept_faces,
                                                    iteration)
        assignment.face_factors = dict(face_factors)
        assignment.face_sigma = sigma_face
        assignment.dropped_faces = dict(dropped_faces)
        signature = _signature(assignment)
        if (o_w.reuse_problem and solved is not None and signature == _signature(solved)
                and last is not None):
            # The assignment the last solve used: solving it again would start at its
            # solution. The loop has converged.
            logger.info("iteration %d assigned as iteration %d, whose solution a solve would "
                        "repeat: the loop has converged", iteration, iterations[-1].iteration)
            seconds["assignment"] += time.perf_counter() - t0
            stopped_by = "same_assignment"
            break
        if (o_w.convergence_assignment_change is not None and solved is not None
                and last is not None and len(iterations) >= 2
                and iterations[-1].camera_shift < o_w.convergence_camera_shift):
            changed = assignment_change(solved.face_index, assignment.face_index)
            if changed is not None and changed <= o_w.convergence_assignment_change:
                # The last solve barely moved the cameras and this assignment keeps its
                # planes and nearly all of its points: a solve would start close to its own
                # solution and move them less again.
                logger.info("iteration %d assigned %.2f %% of the tie points otherwise than the "
                            "solve of iteration %d, which moved no camera by more than %.4f m: "
                            "the loop has converged", iteration, 100 * changed,
                            iterations[-1].iteration, iterations[-1].camera_shift)
                seconds["assignment"] += time.perf_counter() - t0
                stopped_by = "assignment_change"
                break
        repeats = seen.get(signature)
        seen.setdefault(signature, iteration)
        if iteration == 0 and assignment.num_assigned:
            # Initial values: move the block as a whole onto its planes first, so that the
            # adjustment is left with the block's deformation. As in ICP: fit, assign again,
            # fit again; a round that does not lower the block objective is undone.
            t_align = time.perf_counter()
            total_move, points, assignment = align_block_to_planes(
                rec, point_ids, points, assignment, current, priors, threshold, options,
                objective=objective, scale_sigma=scale_sigma, weights=weights)
            if observers is not None:  # the cameras moved with the block
                observers = Observers(observers.rows, total_move * observers.centres)
                assignment = without_roof_points_seen_from_below(assignment, points, current,
                                                                 observers, o_a)
            seconds["initial_alignment"] = time.perf_counter() - t_align
            t0 += seconds["initial_alignment"]
        seconds["assignment"] += time.perf_counter() - t0
        if iteration == 0:
            observability_before = assigned_observability(points, assignment, current, priors,
                                                          rec, options)
            # A sliding window's frames held from the window before keep the orientation count.
            warnings += check_datum(store, assignment, priors is not None,
                                    observability_before if pose_priors is None else None)
            if priors is not None and priors.estimates_offset and not priors.bias_is_random:
                refusal = offset_refusal(observability_before, priors.offset_axes)
                if refusal:
                    raise DatumError(
                        f"{offset_name(priors)} cannot be estimated from this model: {refusal}. "
                        "Give the offset in metres (--gnss_height_offset METRES) or GNSS in the "
                        "model's height system", store.source)
            if gnss_only is not None and priors is not None and pose_priors is None:
                # Where the coarse search and the similarity rounds put the block: GNSS at
                # full weight with every plane near it, roofs' edges seen from below too.
                level = level_prior(rec, priors, left_to_gnss(observability_before) & HEIGHT
                                    & o_w.hold_gnss_height, gnss_only)
                hold_scale = bool(scale_sigma) and observability_before.get(
                    "scale", {}).get("source") not in ("planes", "both")
                baselines = baseline_priors(gnss_only, priors, scale_sigma,
                                            hold_scale=hold_scale, level=level)
        elif assignment.num_assigned == 0 and priors is None and not pose_priors:
            raise DatumError("no tie point could be assigned to a model plane and there is no "
                             "GNSS: the datum is undefined", store.source)
        if iteration > 0 and level is not None and not runaway.any():
            # A height that the planes have come to fix (the first assignment, metres from the
            # model, saw other planes) is theirs from now on: released, never held again.
            if not np.any(left_to_gnss(assigned_observability(
                    points, assignment, current, priors, rec, options)) & HEIGHT):
                logger.info("iteration %d: the planes now fix U: no longer held", iteration)
                level = None
                baselines = baseline_priors(gnss_only, priors, scale_sigma,
                                            hold_scale=baselines.holds_scale, level=level)
                reusable = None  # the next problem has other priors

        t1 = time.perf_counter()
        centres_before = camera_centres(rec).reshape(-1, 3)
        # The block objective where this iteration's solves start (the last one's end).
        value_before = objective(rec) if value is None else value
        # Until the scale is held, keep the state before the solves: a solve that changes the
        # scale further than GNSS allows is undone and repeated with the scale held.
        before_solve = (pycolmap.Reconstruction(rec), current, assignment, _offset(priors)) \
            if gnss_only is not None and not (baselines is not None and baselines.holds_scale) \
            and scale_sigma and hold_runaway_scale else None
        # Until every axis is held, a solve that moves the block away from GNSS further than
        # GNSS allows (scale.shift_runaway) is undone and repeated with that axis held.
        guard_shift = (gnss_only is not None and priors is not None and pose_priors is None
                       and not runaway.all())
        before_shift = before_solve if before_solve is not None or not guard_shift else (
            pycolmap.Reconstruction(rec), current, assignment, _offset(priors))
        observed_before = observer_centres(rec, priors.image_ids) if guard_shift else None
        robust_report = None
        outliers = np.zeros(0, np.int64)
        # Only iterations that were kept count: one undone (its scale) is solved again as it was.
        if iterations and not (len(iterations) == 1 and o_w.robust_second_iteration):
            # Förstner-Wrobel only where needed: with the original weights first; robust
            # weighting and elimination follow only if some |v| / sigma exceeds the threshold.
            final = _final_problem(reusable, rec, store, assignment, priors, o_adj, current,
                                   baselines, pose_priors)
            final_report = final.solve()
            normalised = final.residuals["dTP"]
            needs_robust = bool(np.any(np.abs(normalised) > o_adj.elimination_threshold))
        else:
            needs_robust = True
        if needs_robust:
            robust = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                                   robust_planes=True, current=current, baselines=baselines,
                                   pose_priors=pose_priors)
            robust_report = robust.solve()
            normalised = robust.residuals["dTP"]
            outliers = robust.point_ids[np.abs(normalised) > o_adj.elimination_threshold]
            eliminated = np.isin(assignment.point_ids, outliers)
            if iterations:  # in the first, the block still moves by decimetres
                eliminated_from[eliminated] = assignment.face_index[eliminated]
            assignment = assignment.eliminate(eliminated, points, o_a, kept_faces)
            if (o_w.keep_eliminated and not o_w.solve_again_after_elimination
                    and iteration + 1 < o_w.max_iterations
                    and objective(rec) <= value_before + o_w.divergence_tolerance):
                # The next iteration's solve, which leaves these f_dTP out, is the one with
                # the original weights; it starts where the robust one ended. Not when the
                # robust solve moved the block off the model (its objective rose by more than
                # divergence_tolerance, as a diverging iteration's does): a wrong start had
                # assigned points to planes they are not on, and the solve with the original
                # weights must come at once, before the next assignment starts from there.
                final, final_report = robust, robust_report
            else:
                final = _final_problem(reusable if iteration > 0 else None, rec, store,
                                       assignment, priors, o_adj,
                                       model_after_solve(current, robust), baselines,
                                       pose_priors)
                final_report = final.solve()
        seconds["hybrid_solves"] += time.perf_counter() - t1
        current = model_after_solve(current, final)
        last = final
        if o_adj.face_weighting in ("face", "offsets") and o_adj.sigma_face is None:
            found = face_offsets(final, o_adj, sigma_face)
            model_faces = ~terrain_mask(store)[found.faces]
            estimated = estimate_sigma_face(found, o_adj, model_faces)
            sigma_face = estimated if estimated is not None else sigma_face
            logger.info("iteration %d: the faces' offsets spread by %.3f m (%s, %d faces)",
                        iteration, sigma_face, "estimated" if estimated is not None else "kept",
                        np.count_nonzero(model_faces))
        face_factors = outlier_factors(final, o_adj, sigma_face)
        if face_factors:
            logger.info("iteration %d: %d faces weighed less, their mean offsets beyond the "
                        "generalisation error (sigma x %s)", iteration, len(face_factors),
                        ", ".join(f"{v:.2f}" for v in face_factors.values()))
        robust_only = final.robust_planes  # the iteration ended on its robust solve
        if not robust_only:
            reusable = final if o_w.reuse_problem else None
        solved = None if robust_only else assignment
        if before_solve is not None:
            change = scale_change(gnss_only, rec, priors.image_ids)
            sigmas = abs(np.log1p(change)) / scale_sigma
            if SCALE_RUNAWAY_SIGMAS < sigmas <= SCALE_UNDO_SIGMAS:
                logger.warning("iteration %d changed the block's scale by %.2f %% (%.1f GNSS "
                               "sigma): the scale is held from now on", iteration,
                               100 * change, sigmas)
                baselines = baseline_priors(gnss_only, priors, scale_sigma, level=level)
                reusable = None  # the next problem has the baseline priors
            elif sigmas > SCALE_UNDO_SIGMAS:
                logger.warning("iteration %d changed the block's scale by %.2f %% (%.1f GNSS "
                               "sigma): undone, the scale is held from now on", iteration,
                               100 * change, sigmas)
                rec, current, assignment, offset = before_solve
                _restore_offset(priors, offset)
                baselines = baseline_priors(gnss_only, priors, scale_sigma, level=level)
                last = reusable = solved = None  # `rec` is the copy from before the solve
                continue
        if guard_shift:
            observed = observer_centres(rec, priors.image_ids)
            axes = shift_runaway(observed_before, observed, priors,
                                 o_adj.gnss_bias_share) & ~runaway
            if axes.any():
                names = "/".join(a for a, on in zip("ENU", axes) if on)
                logger.warning("iteration %d moved the block by %s m along %s, away from GNSS "
                               "further than it allows: undone, %s held from now on", iteration,
                               np.round(np.nanmean(observed - observed_before,
                                                   axis=0)[axes], 1).tolist(), names, names)
                rec, current, assignment, offset = before_shift
                _restore_offset(priors, offset)
                runaway |= axes
                held = np.zeros(3, bool) if level is None else level[2] < LEVEL_FREE
                level = level_prior(rec, priors, held | runaway, gnss_only)
                baselines = baseline_priors(gnss_only, priors, scale_sigma, level=level,
                                            hold_scale=baselines is not None
                                            and baselines.holds_scale)
                last = reusable = solved = None  # `rec` is the copy from before the solve
                continue

        rms = final_report.rms_total
        change = abs(previous_rms - rms) / rms if previous_rms else float("inf")
        centres_after = camera_centres(rec).reshape(-1, 3)
        same = centres_after.shape == centres_before.shape
        moved = float(np.max(np.linalg.norm(centres_after - centres_before, axis=1),
                             initial=0.0)) if same else float("inf")
        block_move = (tuple(float(v) for v in np.mean(centres_after - centres_before, axis=0))
                      if same and len(centres_after) else None)
        iterations.append(IterationRecord(iteration, threshold, assignment.num_assigned,
                                          assignment.num_faces,
                                          dict(assignment.rejected_faces), len(outliers),
                                          robust_report, final_report, change,
                                          camera_shift=moved, block_move=block_move))
        face_sets.append(assignment.faces.tobytes())
        bar.set_postfix(points=assignment.num_assigned, planes=assignment.num_faces,
                        rms=f"{rms:.4f}")
        value = objective(rec)
        logger.info("iteration %d: threshold %.2f m, %d points on %d planes, %d f_dTP "
                    "eliminated, RMS %.4f (relative change %.1e), cameras moved <= %.4f m, "
                    "dTP RMS %.3f m, s0 %.3f, objective %.4f", iteration, threshold,
                    assignment.num_assigned, assignment.num_faces, len(outliers), rms, change,
                    moved,
                    final_report.rms["dTP"] * o_adj.sigma_dtp,
                    np.sqrt(final_report.sigma0_squared), value)
        previous_rms = rms
        if best is None or value <= best[0]:
            best = (value, iteration, None, assignment, current, _offset(priors))
        elif value > best[0] + o_w.divergence_tolerance:
            # The hybrid solve moved the block away from the model: go back to the best
            # iterate and stop.
            diverged = (f"objective {value:.3f} in iteration {iteration} against "
                        f"{best[0]:.3f} in iteration {best[1]}")
            logger.warning("refine diverged (%s); the best iterate is kept", diverged)
            stopped_by = "diverged"
            break
        if best[1] == iteration:
            best = (value, iteration, pycolmap.Reconstruction(rec), assignment, current,
                    _offset(priors))
        if robust_only:  # no stopping rule before a solve with the original weights
            continue
        if change < o_w.convergence_rms_change:
            stopped_by = "rms"
            break
        if cameras_settled(iterations, o_w.convergence_camera_shift):
            logger.info("iterations %d and %d moved no camera by more than %.4f m: the loop "
                        "has converged", iteration - 1, iteration, o_w.convergence_camera_shift)
            stopped_by = "camera_shift"
            break
        if repeats is not None:
            # The same assignment as an earlier iteration: solving it again reaches the same
            # state, so the loop would only cycle between assignments until max_iterations.
            logger.info("iteration %d assigned as iteration %d did: the loop has converged",
                        iteration, repeats)
            stopped_by = "cycle"
            break
        if (alternating(face_sets) and max(it.camera_shift for it in iterations[-3:])
                < o_w.alternating_planes_shift):
            # A face at the limits of the assignment (its points just at the minimum count)
            # comes and goes, the block moving a little back and forth with it: the loop
            # would swing like that until the iterations run out.
            warnings.append(
                f"the assignment alternated between {iterations[-1].num_faces} and "
                f"{iterations[-2].num_faces} planes in iterations {iterations[-4].iteration}-"
                f"{iteration}, moving no camera by more than "
                f"{max(it.camera_shift for it in iterations[-3:]):.3f} m; "
                + (f"iteration {best[1]}, the best by the block objective ({best[0]:.4f}), "
                   "is the result" if best_when_unsettled else "the last is the result"))
            logger.info(warnings[-1])
            # The best iterate, unless it is this one (the block is where it should stay).
            keep_best = best_when_unsettled and best[1] != iteration
            stopped_by = "alternating_planes"
            break
    else:
        # Out of iterations without settling (a slow creep of the block along what the planes
        # leave free): the best iterate by the block objective is the result, not the last
        # (unless `best_when_unsettled` is off).
        unsettled_shift = iterations[-1].camera_shift if iterations else None
        unsettled_move = remaining_move(iterations)
        if not best_when_unsettled and iterations:
            warnings.append(f"the assignment loop did not converge in {o_w.max_iterations} "
                            f"iterations (the last moved the cameras by up to "
                            f"{unsettled_shift:.3f} m); the last iterate is the result")
            logger.info(warnings[-1])
        elif best is not None and best[2] is not None and last is not None \
                and best[1] != iterations[-1].iteration:
            warnings.append(f"the assignment loop did not converge in {o_w.max_iterations} "
                            f"iterations; iteration {best[1]}, the best by the block objective "
                            f"({best[0]:.4f}), is the result")
            logger.info(warnings[-1])
            keep_best = True
    bar.close()
    if (diverged is not None or keep_best) and best is not None and best[2] is not None:
        _, _, rec, assignment, current, offset = best
        _restore_offset(priors, offset)
        last = None
    if last is not None and last.robust_planes:
        last = None
    if last is None:  # back to the best iterate, the last iteration undone or robust only
        last = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                             robust_planes=False, current=current, baselines=baselines,
                             pose_priors=pose_priors)
        report = last.solve()
        current = model_after_solve(current, last)
        if not iterations:
            iterations.append(IterationRecord(len(iterations), threshold,
                                              assignment.num_assigned, assignment.num_faces,
                                              dict(assignment.rejected_faces), 0, None, report,
                                              float("inf")))
    return LoopResult(reconstruction=rec, current=current, assignment=assignment, last=last,
                      iterations=iterations, move=total_move,
                      observability_before=observability_before, diverged=diverged,
                      warnings=warnings, seconds=seconds, threshold=threshold,
                      baselines=baselines, weights=weights, unsettled_shift=unsettled_shift,
                      unsettled_move=unsettled_move,
                      stopped_by=stopped_by)


def without_contradicted_faces(assignment: Assignment, points: np.ndarray, current: PlaneStore,
                               options: RefineOptions, sigma_face: float,
                               dropped_faces: dict[int, float], kept_faces: np.ndarray | None,
                               iteration: int) -> Assignment:
    """`assignment` without the points of the faces the face test drops (adjust.faces.
    snooped_faces), those of earlier iterations included; `dropped_faces` ({face: z}) grows by
    the new ones: a face once dropped takes no points for the rest of the run."""
    o_adj = options.adjustment
    dropped_faces.update(snooped_faces(
        points, assignment.without(np.isin(assignment.face_index, list(dropped_faces))),
        current, o_adj.sigma_dtp, sigma_face, o_adj.face_test_alpha,
        candidates=~terrain_mask(current)))
    off = np.isin(assignment.face_index, list(dropped_faces))
    if not np.any(off):
        return assignment
    logger.info("iteration %d: %d faces dropped (%s): the other faces place their points "
                "beyond the generalisation error", iteration, len(dropped_faces),
                ", ".join(f"{f}: z {z:.1f}" for f, z in dropped_faces.items()))
    return assignment.eliminate(off, points, options.assignment, kept_faces)


def _final_problem(reusable: HybridProblem | None, rec: pycolmap.Reconstruction,
                   store: PlaneStore, assignment: Assignment, priors: GNSSPriors | None,
                   options, current: PlaneStore, baselines: BaselinePriors | None,
                   pose_priors: PosePriors | None) -> HybridProblem:
    """The non-robust hybrid problem of `assignment`: `reusable` with its f_dTP blocks
    exchanged where it can be (same planes and priors), else a new one."""
    if reusable is not None and reusable.reconstruction is rec and reusable.reassign(
            assignment, current, baselines=baselines, pose_priors=pose_priors):
        logger.debug("hybrid problem kept: %d f_dTP blocks exchanged", reusable.exchanged)
        return reusable
    return HybridProblem(rec, store, assignment, priors, options, robust_images=False,
                         robust_planes=False, current=current, baselines=baselines,
                         pose_priors=pose_priors)


def _without_eliminated(assignment: Assignment, eliminated_from: np.ndarray,
                        points: np.ndarray, options: AssignmentOptions,
                        kept_faces: np.ndarray | None = None) -> Assignment:
    """`assignment` without the tie points given again to a face they were eliminated from."""
    again = (assignment.face_index >= 0) & (assignment.face_index == eliminated_from)
    return assignment.eliminate(again, points, options, kept_faces) if again.any() \
        else assignment


def alternating(face_sets: list[bytes]) -> bool:
    """The last four iterations' sets of planes alternate between two: A, B, A, B."""
    return (len(face_sets) >= 4 and face_sets[-1] == face_sets[-3]
            and face_sets[-2] == face_sets[-4] and face_sets[-1] != face_sets[-2])


def assignment_change(before: np.ndarray, after: np.ndarray) -> float | None:
    """Share of the tie points assigned in either of two assignments (face of each tie point,
    -1: none; same points in the same order) whose face differs; None if the set of faces
    differs (a face gained or lost moves the block in its own way)."""
    if not np.array_equal(np.unique(before[before >= 0]), np.unique(after[after >= 0])):
        return None
    either = (before >= 0) | (after >= 0)
    if not either.any():
        return 0.0
    return float(np.count_nonzero(before[either] != after[either]) / np.count_nonzero(either))


def _signature(assignment: Assignment) -> bytes:
    """What a solve depends on: the points' faces, the threshold and the faces' weights."""
    factors = sorted((f, round(v, 2)) for f, v in assignment.face_factors.items())
    return (assignment.face_index.tobytes() + np.float64(assignment.threshold).tobytes()
            + repr(factors).encode())


def window_sigma(options: AdjustmentOptions, sigma_face: float) -> float:
    """The sigma (m) of a tie point's distance from its face's given plane, in which the
    threshold's lower bound is counted (AssignmentOptions.min_threshold_sigmas): sigma_dtp
    where it stands for all of it (every point alike); with the faces' errors as unknowns or
    faces as units also their offset's sigma, by which a face's points stand off its plane
    together (else a face 2 of their sigmas off its plane loses the points beyond the window
    and looks nearer than it is)."""
    if options.face_weighting in ("face", "offsets"):
        return float(np.hypot(options.sigma_dtp, sigma_face))
    return float(options.sigma_dtp)


def offset_name(priors: GNSSPriors) -> str:
    """How the user asked for the GNSS offset, for messages."""
    if np.all(priors.offset_axes):
        return "the constant GNSS bias (--gnss_bias auto)"
    return "the GNSS height offset (--gnss_height_offset auto)"


def _offset(priors: GNSSPriors | None) -> np.ndarray | None:
    return None if priors is None else np.array(priors.offset, dtype=np.float64)


def _restore_offset(priors: GNSSPriors | None, offset: np.ndarray | None) -> None:
    """Back to the GNSS offset of an earlier state (solves write their estimate into it)."""
    if priors is not None and offset is not None:
        priors.offset = np.array(offset, dtype=np.float64)
