"""Model correction after the assign/adjust loop (AdjustmentOptions.correct_model).

The loop brings the block onto the model as given (sigma_VT 0.01 m everywhere); then the
faces the images see well are corrected (adjust.model_correction): assign the tie points to
the current (corrected) model at the loop's last threshold, solve with their vertices released
(robust on f_dTP, eliminate, solve again with the original weights), repeat until the RMS of
the normalised residuals settles or `correction_iterations` are done. Correcting only after
the loop follows Unger 6.7.3: releasing sigma_VT for the global adjustment only ("globalOnly")
gave lower check point errors than releasing it from the start, where model errors, drift and
block deformation mix. A correction that moves the block away from the model (block objective
worse, against the corrected model, by more than `divergence_tolerance` than the loop's
block against the given one) is undone.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..align.coarse import SurfaceDistance
from ..align.objective import BlockObjective
from ..assign.assignment import Assignment, filter_faces
from ..assign.schedule import assign
from ..block.priors import GNSSPriors
from ..block.reconstruction import tie_points
from ..citymodel.store import PlaneStore
from ..options import RefineOptions
from .problem import BaselinePriors, HybridProblem
from .record import IterationRecord
from .steps import model_after_solve

logger = logging.getLogger(__name__)


@dataclass
class CorrectionResult:
    reconstruction: pycolmap.Reconstruction
    current: PlaneStore
    assignment: Assignment
    last: HybridProblem | None  # None: the correction was undone (the loop's state stands)
    iterations: list[IterationRecord] = field(default_factory=list)
    undone: str | None = None  # why the correction was undone


def correction_loop(rec: pycolmap.Reconstruction, store: PlaneStore, current: PlaneStore,
                    priors: GNSSPriors | None, options: RefineOptions, objective: BlockObjective,
                    threshold: float, *, exclude_point_ids: set[int] | None = None,
                    baselines: BaselinePriors | None = None, weights: np.ndarray | None = None,
                    first_iteration: int = 0) -> CorrectionResult:
    """Correct the model from the block `rec` (modified in place unless undone; the result's
    reconstruction is the one to use). `store`: the model as given (f_VT observes it);
    `current`: the loop's model state; `threshold`: the loop's last assignment threshold."""
    o_a, o_adj, o_w = options.assignment, options.adjustment, options.workflow
    saved = (pycolmap.Reconstruction(rec), current)
    before = objective(rec)
    records: list[IterationRecord] = []
    previous_rms = None
    last = assignment = None
    for k in range(o_adj.correction_iterations):
        point_ids, points = tie_points(rec, exclude_point_ids)
        assignment = assign(points, point_ids, current, threshold, o_a, weights)
        if not assignment.num_assigned:
            break
        rejected = dict(assignment.rejected_faces)
        robust = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                               robust_planes=True, current=current, baselines=baselines)
        robust_report = robust.solve()
        outliers = robust.point_ids[np.abs(robust.residuals["dTP"])
                                    > o_adj.elimination_threshold]
        assignment = assignment.without(np.isin(assignment.point_ids, outliers))
        assignment.face_index = filter_faces(points, assignment.face_index, o_a, rejected)
        assignment.distance[assignment.face_index < 0] = np.nan
        assignment.rejected_faces = rejected
        last = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                             robust_planes=False, current=model_after_solve(current, robust),
                             baselines=baselines)
        report = last.solve()
        current = model_after_solve(current, last)
        rms = report.rms_total
        change = abs(previous_rms - rms) / rms if previous_rms else float("inf")
        previous_rms = rms
        records.append(IterationRecord(first_iteration + k, threshold, assignment.num_assigned,
                                       assignment.num_faces, rejected, len(outliers),
                                       robust_report, report, change, phase="correction"))
        selection = last.blocks.correction
        logger.info("model correction %d: %d faces corrected (%d vertices released, %d faces "
                    "keep their planes beside them), %d points on %d planes, dTP RMS %.3f m, "
                    "RMS %.4f (relative change %.1e)", k, len(selection.faces),
                    len(selection.released), len(selection.held), assignment.num_assigned,
                    assignment.num_faces, report.rms["dTP"] * o_adj.sigma_dtp, rms, change)
        if change < o_w.convergence_rms_change:
            break
    if last is None:
        return CorrectionResult(saved[0], saved[1], assignment, None, records,
                                "no tie point could be assigned")
    # The block objective against the corrected model: the tie points near the model they
    # were adjusted to, and GNSS.
    after = BlockObjective(SurfaceDistance(current, o_a.excluded_classes), objective.priors,
                           objective.ids, objective.radius)(rec)
    if after > before + o_w.divergence_tolerance:
        reason = (f"the corrected model moved the block away from it (objective {before:.3f} "
                  f"-> {after:.3f})")
        logger.warning("model correction undone: %s", reason)
        return CorrectionResult(saved[0], saved[1], assignment, None, records, reason)
    return CorrectionResult(rec, current, assignment, last, records)
