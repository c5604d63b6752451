"""Steps 3-4 of the global workflow, repeated: assign the tie points to the model planes, solve
the hybrid adjustment (robust on f_dTP where needed), until the RMS of the normalised residuals
settles, two solves in a row move no camera by more than a tenth of the block's stated sigma
(at least a few millimetres: settle_tolerance), a solve that moved them that little is followed
by an assignment that keeps its planes and nearly all of its points, an assignment repeats an
earlier one (a cycle), the planes alternate between two sets with small moves (the best of them
is kept), the block objective worsens, or the iterations run out.

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
plane, and switches their loss for the next iteration's robust solve); an assignment equal to
the one the last solve used ends the loop without a solve.
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
from .record import IterationRecord, cameras_settled, mean_move, remaining_move
from .scale import (SCALE_RUNAWAY_SIGMAS, SCALE_UNDO_SIGMAS, baseline_priors, level_prior,
                    scale_change, shift_runaway)
from .steps import RoofObservers, align_block_to_planes, model_after_solve

logger = logging.getLogger(__name__)

#: A loop diverges only where its block left the best iterate by more than this many of its
#: position's stated 3D sigma (and its placement score fell significantly): 2, the reach of a
#: 95 % region.
DIVERGENCE_SIGMAS = 2.0
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
    # With the faces' errors as unknowns (adjust.staged): the block's mean move (m, E N U) from
    # where the loop with every tie point alike placed it; None without that second loop.
    weighting_move: np.ndarray | None = None
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
                    best_when_unsettled: bool = True, places_next: bool = False) -> LoopResult:
    """Run steps 3-4 on `rec` (modified in place; the result may hold the best iterate's copy
    instead). `store` is the model as given (its vertices are observed); `gnss_only` and
    `scale_sigma` let the loop hold the block's scale where the planes cannot give it, and,
    with `hold_runaway_scale`, from a solve on that changes it further than GNSS allows.
    `pose_priors`: frames held near given poses in every solve (a sliding window's images
    kept from the window before). `best_when_unsettled`: a loop that runs out of iterations,
    or swings between two sets of planes, returns its best iterate by the block objective;
    False: its last (the faces' loop, whose estimated offsets move the points off the given
    planes the objective measures them against). `places_next`: the block is where another
    loop starts (adjust.staged), so one settled iteration ends it, a robust one too (its
    result is solved with the original weights once more)."""
    loop = _Loop(rec, store, priors, options, objective, all_ids, exclude_point_ids,
                 gnss_only, scale_sigma, pose_priors, hold_runaway_scale, best_when_unsettled,
                 places_next)
    bar = tqdm(range(options.workflow.max_iterations), desc="refine", unit="it",
               disable=not progress)
    for iteration in bar:
        if loop.assign(iteration):
            break
        loop.hold_datum(iteration)
        loop.solve(iteration)
        if loop.undone(iteration):
            continue
        loop.record(iteration, bar)
        if loop.stops(iteration):
            break
    else:
        loop.out_of_iterations()
    bar.close()
    return loop.result()


class _Loop:
    """One adjustment_loop's state and its steps, in the order each iteration runs them:
    assign (stopping where the assignment shows the loop has converged), hold the datum
    (the first iteration's checks and priors), solve, undo a solve that ran away, record,
    the stopping rules; after the last iteration, the result."""

    def __init__(self, rec, store, priors, options, objective, all_ids, exclude_point_ids,
                 gnss_only, scale_sigma, pose_priors, hold_runaway_scale, best_when_unsettled,
                 places_next):
        self.rec, self.store, self.priors, self.options = rec, store, priors, options
        self.objective, self.gnss_only, self.scale_sigma = objective, gnss_only, scale_sigma
        self.pose_priors, self.hold_runaway_scale = pose_priors, hold_runaway_scale
        self.best_when_unsettled, self.places_next = best_when_unsettled, places_next
        self.o_a, self.o_adj, self.o_w = options.assignment, options.adjustment, options.workflow
        self.current = store
        self.threshold = initial_threshold(self.o_a)
        self.weights = None
        if self.o_a.weighted_sampling:
            from ..assign.indirect import point_quality_weights

            self.weights = point_quality_weights(rec, all_ids)
        self.assignment: Assignment | None = None
        self.iterations: list[IterationRecord] = []
        self.observability_before: dict = {}
        self.warnings: list[str] = []
        self.seconds = {"assignment": 0.0, "hybrid_solves": 0.0}
        self.total_move = pycolmap.Sim3d()
        self.baselines = None
        self.level = None  # scale.level_prior: the height held where the first assignment put it
        self.runaway = np.zeros(3, bool)  # axes held since a solve ran away (shift_runaway)
        self.previous_rms = None
        self.last = None
        self.best = None  # (objective, iteration, reconstruction copy, assignment, current,
        #                    GNSS offset)
        self.diverged = None
        self.seen: dict[bytes, int] = {}  # assignment (faces of all points) -> iteration
        self.repeats = None  # the earlier iteration this one's assignment repeats
        self.keep_best = False  # the best iterate, not the last, is the result
        self.unsettled_shift = None  # out of iterations: the last one's largest camera move
        self.unsettled_move = None  # and how far it would still move the block (remaining_move)
        self.stopped_by = None
        self.face_factors: dict[int, float] = {}  # faces the adjustment weighs less (faces)
        self.dropped_faces: dict[int, float] = {}  # faces no tie point goes to, their z
        # The sigma of the faces' offsets (m): given, or estimated from them after each solve.
        self.sigma_face = sigma_face_in_use(self.o_adj)
        # The last non-robust problem, kept for the next iteration (workflow.reuse_problem).
        self.reusable: HybridProblem | None = None
        self.solved: Assignment | None = None  # the assignment of the last solve
        self.face_sets: list[bytes] = []  # the planes of each kept iteration
        self.eliminated_from = None  # the face each tie point was last eliminated from (-1)
        self.roof_observers = RoofObservers(store, self.o_a)  # tie points keep their order
        self.read_tie_points = TiePointReader(exclude_point_ids)
        self.value = None  # the block objective after the last kept iteration
        self.lowest = None  # the lowest block objective of the kept iterations
        # The largest camera move (m) of a settled iteration (settle_tolerance, from the first
        # assignment's stated sigma on).
        self.settle = self.o_w.convergence_camera_shift

    # -- assign ----------------------------------------------------------------------------

    def assign(self, iteration: int) -> bool:
        """This iteration's assignment (in the first, with the similarity rounds that move the
        block onto its planes); True where it shows that the loop has converged."""
        t0 = time.perf_counter()
        self._assign_points(iteration)
        if self._converged_before_solve(iteration):
            self.seconds["assignment"] += time.perf_counter() - t0
            return True
        self.repeats = self.seen.get(self.signature)
        self.seen.setdefault(self.signature, iteration)
        if iteration == 0 and self.assignment.num_assigned:
            t0 += self._align_block()
        self.seconds["assignment"] += time.perf_counter() - t0
        return False

    def _assign_points(self, iteration: int) -> None:
        """The tie points to faces, at the threshold the last assignment's distances give."""
        o_a, o_adj = self.o_a, self.o_adj
        self.point_ids, self.points = self.read_tie_points(self.rec)
        surfaces = self.current  # where the tie points are looked for
        if self.assignment is not None:
            if o_a.window == "centred" and resolve_method(o_a, self.threshold) == "direct":
                surfaces = centred_surfaces(self.points, self.point_ids, self.current,
                                            self.threshold, o_a)
            # The tie point set does not change inside the loop: same ids in the same order.
            # The threshold never grows again: no flip-flop between two assignments.
            self.threshold = min(self.threshold, next_threshold(
                self.assignment, self.points, surfaces, o_a,
                window_sigma(o_adj, self.sigma_face)))
        self.observers = self.roof_observers(self.rec, self.point_ids)
        # Roofs keep only the points seen from above once the block is on the model: while
        # the first assignment and the similarity rounds bring it there from metres away,
        # parapets and eaves near a roof's plane hold its height (from a street they are
        # often the only points near a roof).
        self.kept_faces = self.assignment.faces if self.assignment is not None else None
        assignment = assign(self.points, self.point_ids, surfaces, self.threshold, o_a,
                            self.weights, self.observers if self.iterations else None,
                            self.kept_faces)
        if self.eliminated_from is None:  # the tie points keep their order inside the loop
            self.eliminated_from = np.full(len(self.point_ids), -1, np.int64)
        if self.o_w.keep_eliminated:
            assignment = _without_eliminated(assignment, self.eliminated_from, self.points,
                                             o_a, self.kept_faces)
        if self.iterations and o_adj.face_test_alpha is not None:
            assignment = without_contradicted_faces(assignment, self.points, self.current,
                                                    self.options, self.sigma_face,
                                                    self.dropped_faces, self.kept_faces,
                                                    iteration)
        assignment.face_factors = dict(self.face_factors)
        assignment.face_sigma = self.sigma_face
        assignment.dropped_faces = dict(self.dropped_faces)
        self.assignment = assignment
        self.signature = _signature(assignment)

    def _converged_before_solve(self, iteration: int) -> bool:
        """The assignment the last solve used, or one that keeps its planes and nearly all of
        its points after a solve that barely moved the cameras: a solve would start at (or
        close to) its own solution."""
        o_w, solved, iterations = self.o_w, self.solved, self.iterations
        if (o_w.reuse_problem and solved is not None and self.signature == _signature(solved)
                and self.last is not None):
            logger.info("iteration %d assigned as iteration %d, whose solution a solve would "
                        "repeat: the loop has converged", iteration, iterations[-1].iteration)
            self.stopped_by = "same_assignment"
            return True
        if (o_w.convergence_assignment_change is not None and solved is not None
                and self.last is not None and len(iterations) >= 2
                and iterations[-1].camera_shift < self.settle):
            changed = assignment_change(solved.face_index, self.assignment.face_index)
            if changed is not None and changed <= o_w.convergence_assignment_change:
                # The last solve barely moved the cameras and this assignment keeps its
                # planes and nearly all of its points: a solve would start close to its own
                # solution and move them less again.
                logger.info("iteration %d assigned %.2f %% of the tie points otherwise than the "
                            "solve of iteration %d, which moved no camera by more than %.4f m: "
                            "the loop has converged", iteration, 100 * changed,
                            iterations[-1].iteration, iterations[-1].camera_shift)
                self.stopped_by = "assignment_change"
                return True
        return False

    def _align_block(self) -> float:
        """Initial values: move the block as a whole onto its planes first, so that the
        adjustment is left with the block's deformation. As in ICP: fit, assign again, fit
        again; a round that does not lower the block objective is undone. Its seconds."""
        t_align = time.perf_counter()
        self.total_move, self.points, self.assignment = align_block_to_planes(
            self.rec, self.point_ids, self.points, self.assignment, self.current, self.priors,
            self.threshold, self.options, objective=self.objective,
            scale_sigma=self.scale_sigma, weights=self.weights)
        if self.observers is not None:  # the cameras moved with the block
            self.observers = Observers(self.observers.rows,
                                       self.total_move * self.observers.centres)
            self.assignment = without_roof_points_seen_from_below(
                self.assignment, self.points, self.current, self.observers, self.o_a)
        self.seconds["initial_alignment"] = time.perf_counter() - t_align
        return self.seconds["initial_alignment"]

    # -- datum -----------------------------------------------------------------------------

    def hold_datum(self, iteration: int) -> None:
        """The first iteration: the datum's checks, the GNSS offset's, and the priors that hold
        the height and scale the planes leave to GNSS; later ones: a height the planes have
        come to fix is released."""
        if iteration == 0:
            self._first_datum()
        elif (self.assignment.num_assigned == 0 and self.priors is None
              and not self.pose_priors):
            raise DatumError("no tie point could be assigned to a model plane and there is no "
                             "GNSS: the datum is undefined", self.store.source)
        if iteration > 0 and self.level is not None and not self.runaway.any():
            # A height that the planes have come to fix (the first assignment, metres from the
            # model, saw other planes) is theirs from now on: released, never held again.
            if not np.any(left_to_gnss(assigned_observability(
                    self.points, self.assignment, self.current, self.priors, self.rec,
                    self.options)) & HEIGHT):
                logger.info("iteration %d: the planes now fix U: no longer held", iteration)
                self.level = None
                self.baselines = baseline_priors(self.gnss_only, self.priors, self.scale_sigma,
                                                 hold_scale=self.baselines.holds_scale,
                                                 level=self.level)
                self.reusable = None  # the next problem has other priors

    def _first_datum(self) -> None:
        """The first assignment's observability, the datum's and the GNSS offset's checks,
        and the priors that hold what the planes leave to GNSS (height, scale)."""
        priors, options = self.priors, self.options
        self.observability_before = assigned_observability(
            self.points, self.assignment, self.current, priors, self.rec, options)
        self.settle = settle_tolerance(self.observability_before, self.o_w)
        # A sliding window's frames held from the window before keep the orientation count.
        self.warnings += check_datum(self.store, self.assignment, priors is not None,
                                     self.observability_before if self.pose_priors is None
                                     else None)
        if priors is not None and priors.estimates_offset and not priors.bias_is_random:
            refusal = offset_refusal(self.observability_before, priors.offset_axes)
            if refusal:
                raise DatumError(
                    f"{offset_name(priors)} cannot be estimated from this model: {refusal}. "
                    "Give the offset in metres (--gnss_height_offset METRES) or GNSS in the "
                    "model's height system", self.store.source)
        if self.gnss_only is not None and priors is not None and self.pose_priors is None:
            # Where the coarse search and the similarity rounds put the block: GNSS at full
            # weight with every plane near it, roofs' edges seen from below too.
            self.level = level_prior(self.rec, priors,
                                     left_to_gnss(self.observability_before) & HEIGHT
                                     & self.o_w.hold_gnss_height, self.gnss_only)
            hold_scale = bool(self.scale_sigma) and self.observability_before.get(
                "scale", {}).get("source") not in ("planes", "both")
            self.baselines = baseline_priors(self.gnss_only, priors, self.scale_sigma,
                                             hold_scale=hold_scale, level=self.level)

    # -- solve -----------------------------------------------------------------------------

    def solve(self, iteration: int) -> None:
        """The hybrid solves of this iteration (Förstner-Wrobel where needed), the state kept
        to undo them, the faces' offset sigma and weights from their solution."""
        t1 = time.perf_counter()
        rec, o_w = self.rec, self.o_w
        self.centres_before = camera_centres(rec).reshape(-1, 3)
        # The block objective where this iteration's solves start (the last one's end).
        self.value_before = self.objective(rec) if self.value is None else self.value
        # Until the scale is held, keep the state before the solves: a solve that changes the
        # scale further than GNSS allows is undone and repeated with the scale held.
        self.before_solve = (
            (pycolmap.Reconstruction(rec), self.current, self.assignment, _offset(self.priors))
            if self.gnss_only is not None
            and not (self.baselines is not None and self.baselines.holds_scale)
            and self.scale_sigma and self.hold_runaway_scale else None)
        # Until every axis is held, a solve that moves the block away from GNSS further than
        # GNSS allows (scale.shift_runaway) is undone and repeated with that axis held.
        self.guard_shift = (self.gnss_only is not None and self.priors is not None
                            and self.pose_priors is None and not self.runaway.all())
        self.before_shift = (
            self.before_solve if self.before_solve is not None or not self.guard_shift
            else (pycolmap.Reconstruction(rec), self.current, self.assignment,
                  _offset(self.priors)))
        self.observed_before = (observer_centres(rec, self.priors.image_ids)
                                if self.guard_shift else None)
        final, self.final_report, self.robust_report, self.outliers = self._solves(iteration)
        self.seconds["hybrid_solves"] += time.perf_counter() - t1
        self.current = model_after_solve(self.current, final)
        self.last = final
        self._faces_after_solve(final, iteration)
        self.robust_only = final.robust_planes  # the iteration ended on its robust solve
        if not self.robust_only:
            self.reusable = final if o_w.reuse_problem else None
        self.solved = None if self.robust_only else self.assignment

    def _solves(self, iteration: int):
        """(final problem, its report, the robust solve's report or None, eliminated ids)."""
        rec, store, priors, o_adj, o_w = self.rec, self.store, self.priors, self.o_adj, self.o_w
        robust_report = None
        outliers = np.zeros(0, np.int64)
        # Only iterations that were kept count: one undone (its scale) is solved again as it was.
        if self.iterations and not (len(self.iterations) == 1 and o_w.robust_second_iteration):
            # Förstner-Wrobel only where needed: with the original weights first; robust
            # weighting and elimination follow only if some |v| / sigma exceeds the threshold.
            final = _final_problem(self.reusable, rec, store, self.assignment, priors, o_adj,
                                   self.current, self.baselines, self.pose_priors)
            final_report = final.solve()
            normalised = final.residuals["dTP"]
            needs_robust = bool(np.any(np.abs(normalised) > o_adj.elimination_threshold))
        else:
            needs_robust = True
        if not needs_robust:
            return final, final_report, robust_report, outliers
        robust = _final_problem(self.reusable, rec, store, self.assignment, priors, o_adj,
                                self.current, self.baselines, self.pose_priors,
                                robust_planes=True)
        robust_report = robust.solve()
        normalised = robust.residuals["dTP"]
        outliers = robust.point_ids[np.abs(normalised) > o_adj.elimination_threshold]
        eliminated = np.isin(self.assignment.point_ids, outliers)
        if self.iterations:  # in the first, the block still moves by decimetres
            self.eliminated_from[eliminated] = self.assignment.face_index[eliminated]
        self.assignment = self.assignment.eliminate(eliminated, self.points, self.o_a,
                                                    self.kept_faces)
        if (o_w.keep_eliminated and not o_w.solve_again_after_elimination
                and iteration + 1 < o_w.max_iterations
                and self.objective(rec) <= self.value_before + self.objective.tolerance):
            # The next iteration's solve, which leaves these f_dTP out, is the one with the
            # original weights; it starts where the robust one ended. Not when the robust
            # solve moved the block off the model (its objective rose by more than
            # the objective's tolerance, as a diverging iteration's does): a wrong start had
            # assigned points to planes they are not on, and the solve with the original
            # weights must come at once, before the next assignment starts from there.
            return robust, robust_report, robust_report, outliers
        final = _final_problem(self.reusable if iteration > 0 else None, rec, store,
                               self.assignment, priors, o_adj,
                               model_after_solve(self.current, robust), self.baselines,
                               self.pose_priors)
        return final, final.solve(), robust_report, outliers

    def _faces_after_solve(self, final: HybridProblem, iteration: int) -> None:
        """The faces' offset sigma estimated from their offsets at the solution (where it is
        not given), and the faces to weigh less."""
        o_adj = self.o_adj
        if o_adj.face_weighting in ("face", "offsets") and o_adj.sigma_face is None:
            found = face_offsets(final, o_adj, self.sigma_face)
            model_faces = ~terrain_mask(self.store)[found.faces]
            estimated = estimate_sigma_face(found, o_adj, model_faces)
            self.sigma_face = estimated if estimated is not None else self.sigma_face
            logger.info("iteration %d: the faces' offsets spread by %.3f m (%s, %d faces)",
                        iteration, self.sigma_face,
                        "estimated" if estimated is not None else "kept",
                        np.count_nonzero(model_faces))
        self.face_factors = outlier_factors(final, o_adj, self.sigma_face)
        if self.face_factors:
            logger.info("iteration %d: %d faces weighed less, their mean offsets beyond the "
                        "generalisation error (sigma x %s)", iteration, len(self.face_factors),
                        ", ".join(f"{v:.2f}" for v in self.face_factors.values()))

    # -- undo ------------------------------------------------------------------------------

    def undone(self, iteration: int) -> bool:
        """Whether this iteration's solve was undone: it changed the block's scale, or moved
        it away from GNSS, further than GNSS allows; that scale or axis is held from now on."""
        return self._scale_ran_away(iteration) or self._shift_ran_away(iteration)

    def _scale_ran_away(self, iteration: int) -> bool:
        """The solve changed the scale beyond what GNSS allows: held from now on, and the
        solve undone (True) where the change was far beyond it."""
        if self.before_solve is None:
            return False
        gnss_only, priors, scale_sigma = self.gnss_only, self.priors, self.scale_sigma
        change = scale_change(gnss_only, self.rec, priors.image_ids)
        sigmas = abs(np.log1p(change)) / scale_sigma
        if SCALE_RUNAWAY_SIGMAS < sigmas <= SCALE_UNDO_SIGMAS:
            logger.warning("iteration %d changed the block's scale by %.2f %% (%.1f GNSS "
                           "sigma): the scale is held from now on", iteration, 100 * change,
                           sigmas)
            self.baselines = baseline_priors(gnss_only, priors, scale_sigma, level=self.level)
            self.reusable = None  # the next problem has the baseline priors
        elif sigmas > SCALE_UNDO_SIGMAS:
            logger.warning("iteration %d changed the block's scale by %.2f %% (%.1f GNSS "
                           "sigma): undone, the scale is held from now on", iteration,
                           100 * change, sigmas)
            self.rec, self.current, self.assignment, offset = self.before_solve
            _restore_offset(priors, offset)
            self.baselines = baseline_priors(gnss_only, priors, scale_sigma, level=self.level)
            self.last = self.reusable = self.solved = None  # `rec`: the copy from before
            return True
        return False

    def _shift_ran_away(self, iteration: int) -> bool:
        """The solve moved the block away from GNSS along an axis further than GNSS allows:
        undone (True), that axis held from now on."""
        if not self.guard_shift:
            return False
        priors = self.priors
        observed = observer_centres(self.rec, priors.image_ids)
        axes = shift_runaway(self.observed_before, observed, priors,
                             self.o_adj.gnss_bias_share) & ~self.runaway
        if not axes.any():
            return False
        names = "/".join(a for a, on in zip("ENU", axes) if on)
        logger.warning("iteration %d moved the block by %s m along %s, away from GNSS "
                       "further than it allows: undone, %s held from now on", iteration,
                       np.round(np.nanmean(observed - self.observed_before,
                                           axis=0)[axes], 1).tolist(), names, names)
        self.rec, self.current, self.assignment, offset = self.before_shift
        _restore_offset(priors, offset)
        self.runaway |= axes
        held = np.zeros(3, bool) if self.level is None else self.level[2] < LEVEL_FREE
        self.level = level_prior(self.rec, priors, held | self.runaway, self.gnss_only)
        self.baselines = baseline_priors(self.gnss_only, priors, self.scale_sigma,
                                         level=self.level,
                                         hold_scale=self.baselines is not None
                                         and self.baselines.holds_scale)
        self.last = self.reusable = self.solved = None  # `rec`: the copy from before the solve
        return True

    # -- record and stop -------------------------------------------------------------------

    def record(self, iteration: int, bar) -> None:
        """The iteration's record (report.json `iterations`), its log line and objective."""
        final_report, assignment = self.final_report, self.assignment
        rms = final_report.rms_total
        change = abs(self.previous_rms - rms) / rms if self.previous_rms else float("inf")
        centres_after = camera_centres(self.rec).reshape(-1, 3)
        same = centres_after.shape == self.centres_before.shape
        moved = float(np.max(np.linalg.norm(centres_after - self.centres_before, axis=1),
                             initial=0.0)) if same else float("inf")
        move = mean_move(self.centres_before, centres_after)
        block_move = tuple(float(v) for v in move) if move is not None else None
        self.iterations.append(IterationRecord(
            iteration, self.threshold, assignment.num_assigned, assignment.num_faces,
            dict(assignment.rejected_faces), len(self.outliers), self.robust_report,
            final_report, change, camera_shift=moved, block_move=block_move))
        self.face_sets.append(assignment.faces.tobytes())
        bar.set_postfix(points=assignment.num_assigned, planes=assignment.num_faces,
                        rms=f"{rms:.4f}")
        self.value = self.objective(self.rec)
        logger.info("iteration %d: threshold %.2f m, %d points on %d planes, %d f_dTP "
                    "eliminated, RMS %.4f (relative change %.1e), cameras moved <= %.4f m, "
                    "dTP RMS %.3f m, s0 %.3f, objective %.4f", iteration, self.threshold,
                    assignment.num_assigned, assignment.num_faces, len(self.outliers), rms,
                    change, moved, final_report.rms["dTP"] * self.o_adj.sigma_dtp,
                    np.sqrt(final_report.sigma0_squared), self.value)
        self.previous_rms = rms
        self.change = change

    def stops(self, iteration: int) -> bool:
        """The stopping rules after a kept iteration: diverged (the block objective
        significantly worse than the lowest seen, and the block moved away from the best
        iterate: `_away_from`), the RMS settled, the cameras settled, a cycle, or alternating
        sets of planes. The best iterate is the latest whose objective is not significantly
        worse than the lowest."""
        o_w, value, best = self.o_w, self.value, self.best
        self.lowest = value if self.lowest is None else min(self.lowest, value)
        if best is None or value <= self.lowest + self.objective.tolerance:
            # Not significantly worse than the best seen: the later iterate is the best one
            # (the score and the solves weigh the tie points a little differently).
            self.best = best = (value, iteration, None, self.assignment, self.current,
                                _offset(self.priors))
        elif self._away_from(best):
            # The hybrid solve moved the block away from the model: go back to the best
            # iterate and stop.
            self.diverged = (f"objective {value:.3f} in iteration {iteration} against "
                             f"{best[0]:.3f} in iteration {best[1]}")
            logger.warning("refine diverged (%s); the best iterate is kept", self.diverged)
            self.stopped_by = "diverged"
            return True
        if best[1] == iteration:
            self.best = (value, iteration, pycolmap.Reconstruction(self.rec), self.assignment,
                         self.current, _offset(self.priors))
        if (self.places_next and len(self.iterations) > 1
                and self.iterations[-1].camera_shift < self.settle):
            logger.info("iteration %d moved no camera by more than %.4f m: the block is placed "
                        "for the loop that follows", iteration, self.settle)
            self.stopped_by = "camera_shift"
            return True
        if self.robust_only:  # no stopping rule before a solve with the original weights
            return False
        if self.change < o_w.convergence_rms_change:
            self.stopped_by = "rms"
            return True
        if cameras_settled(self.iterations, self.settle):
            logger.info("iterations %d and %d moved no camera by more than %.4f m: the loop "
                        "has converged", iteration - 1, iteration, self.settle)
            self.stopped_by = "camera_shift"
            return True
        if self.repeats is not None:
            # The same assignment as an earlier iteration: solving it again reaches the same
            # state, so the loop would only cycle between assignments until max_iterations.
            logger.info("iteration %d assigned as iteration %d did: the loop has converged",
                        iteration, self.repeats)
            self.stopped_by = "cycle"
            return True
        return self._alternates(iteration)

    def _away_from(self, best) -> bool:
        """Whether the block has moved from the `best` iterate by more than DIVERGENCE_SIGMAS
        of its position's stated 3D sigma at the first assignment: a significantly worse
        placement score within that reach is the score and the solves weighing the same
        tie points a little differently, not a block leaving the model."""
        if best[2] is None:
            return True
        sigmas = [self.observability_before.get(a, {}).get("sigma") for a in ("E", "N", "U")]
        if any(v is None for v in sigmas):
            return True
        move = mean_move(camera_centres(best[2]).reshape(-1, 3),
                         camera_centres(self.rec).reshape(-1, 3))
        return move is None or float(np.linalg.norm(move)) > DIVERGENCE_SIGMAS * float(
            np.linalg.norm(sigmas))

    def _alternates(self, iteration: int) -> bool:
        """The planes alternated between two sets with small moves: the loop stops (True)."""
        iterations, best = self.iterations, self.best
        if not (alternating(self.face_sets) and max(it.camera_shift for it in iterations[-3:])
                < self.o_w.alternating_planes_shift):
            return False
        # A face at the limits of the assignment (its points just at the minimum count) comes
        # and goes, the block moving a little back and forth with it: the loop would swing
        # like that until the iterations run out.
        self.warnings.append(
            f"the assignment alternated between {iterations[-1].num_faces} and "
            f"{iterations[-2].num_faces} planes in iterations {iterations[-4].iteration}-"
            f"{iteration}, moving no camera by more than "
            f"{max(it.camera_shift for it in iterations[-3:]):.3f} m; "
            + (f"iteration {best[1]}, the best by the block objective ({best[0]:.4f}), "
               "is the result" if self.best_when_unsettled else "the last is the result"))
        logger.info(self.warnings[-1])
        # The best iterate, unless it is this one (the block is where it should stay).
        self.keep_best = self.best_when_unsettled and best[1] != iteration
        self.stopped_by = "alternating_planes"
        return True

    def out_of_iterations(self) -> None:
        """Out of iterations without settling (a slow creep of the block along what the planes
        leave free): the best iterate by the block objective is the result, not the last
        (unless `best_when_unsettled` is off); how far the loop would still have moved the
        block is kept for the stated sigmas."""
        iterations, best, o_w = self.iterations, self.best, self.o_w
        self.unsettled_shift = iterations[-1].camera_shift if iterations else None
        self.unsettled_move = remaining_move(iterations)
        if not self.best_when_unsettled and iterations:
            self.warnings.append(f"the assignment loop did not converge in {o_w.max_iterations} "
                                 f"iterations (the last moved the cameras by up to "
                                 f"{self.unsettled_shift:.3f} m); the last iterate is the result")
            logger.info(self.warnings[-1])
        elif best is not None and best[2] is not None and self.last is not None \
                and best[1] != iterations[-1].iteration:
            self.warnings.append(f"the assignment loop did not converge in {o_w.max_iterations} "
                                 f"iterations; iteration {best[1]}, the best by the block "
                                 f"objective ({best[0]:.4f}), is the result")
            logger.info(self.warnings[-1])
            self.keep_best = True

    # -- result ----------------------------------------------------------------------------

    def result(self) -> LoopResult:
        """The kept iterate (the best one where the loop diverged or keeps its best) with a
        non-robust solved problem."""
        best, priors = self.best, self.priors
        if (self.diverged is not None or self.keep_best) and best is not None \
                and best[2] is not None:
            _, _, self.rec, self.assignment, self.current, offset = best
            _restore_offset(priors, offset)
            self.last = None
        if self.last is not None and self.last.robust_planes:
            self.last = None
        if self.last is None:  # back to the best iterate, the last iteration undone or robust
            self.last = HybridProblem(self.rec, self.store, self.assignment, priors, self.o_adj,
                                      robust_images=False, robust_planes=False,
                                      current=self.current, baselines=self.baselines,
                                      pose_priors=self.pose_priors)
            report = self.last.solve()
            self.current = model_after_solve(self.current, self.last)
            if not self.iterations:
                a = self.assignment
                self.iterations.append(IterationRecord(len(self.iterations), self.threshold,
                                                       a.num_assigned, a.num_faces,
                                                       dict(a.rejected_faces), 0, None, report,
                                                       float("inf")))
        return LoopResult(reconstruction=self.rec, current=self.current,
                          assignment=self.assignment, last=self.last,
                          iterations=self.iterations, move=self.total_move,
                          observability_before=self.observability_before,
                          diverged=self.diverged, warnings=self.warnings,
                          seconds=self.seconds, threshold=self.threshold,
                          baselines=self.baselines, weights=self.weights,
                          unsettled_shift=self.unsettled_shift,
                          unsettled_move=self.unsettled_move, stopped_by=self.stopped_by)


def settle_tolerance(observability_dict: dict, o_w) -> float:
    """The largest camera move (m) of an iteration that counts as settled: `o_w.
    convergence_sigma_share` of the smallest stated shift sigma (E, N, U) of
    `observability_dict`, at least `o_w.convergence_camera_shift` (WorkflowOptions)."""
    sigmas = [observability_dict.get(name, {}).get("sigma") for name in ("E", "N", "U")]
    sigmas = [s for s in sigmas if s is not None and np.isfinite(s)]
    share = o_w.convergence_sigma_share * min(sigmas) if sigmas else 0.0
    return max(o_w.convergence_camera_shift, share)


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
                   pose_priors: PosePriors | None, robust_planes: bool = False
                   ) -> HybridProblem:
    """The hybrid problem of `assignment` (non-robust, or robust on f_dTP): `reusable` with
    its f_dTP blocks exchanged and their loss switched where it can be (same planes and
    priors), else a new one."""
    if reusable is not None and reusable.reconstruction is rec and reusable.reassign(
            assignment, current, robust_planes=robust_planes, baselines=baselines,
            pose_priors=pose_priors):
        logger.debug("hybrid problem kept: %d f_dTP blocks exchanged", reusable.exchanged)
        return reusable
    return HybridProblem(rec, store, assignment, priors, options, robust_images=False,
                         robust_planes=robust_planes, current=current, baselines=baselines,
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
