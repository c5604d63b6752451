"""Model correction after refine's adjustment (AdjustmentOptions.correct_model).

The loop brings the block onto the model as given (sigma_VT 0.01 m everywhere). Then the
images correct the faces they see well (adjust.model_correction): assign the tie points to the
current model at the loop's last threshold, solve a `CorrectionProblem` (the corrected faces'
vertices released), eliminate f_dTP beyond 3 sigma and solve again with the original weights,
repeat until the RMS of the normalised residuals settles or `correction_iterations` are done.

By default the block's poses and intrinsics stay as the adjustment left them; the tie points
assigned to a plane are re-estimated with the corrected planes (their image observations and
f_dTP) on a copy of the block, so that they are not held where the adjustment to the given
planes pulled them, and the refined block is handed back unchanged. The tie points are the
control the planes are fitted to, as Unger corrected the generalised model with a reference
block's tie points as control points (5.2.2); a corrected plane is then as good as they are,
and the check points stay those of the adjustment. `correction_moves_block` estimates block
and model together instead (Unger 6.7.3: sigma_VT released in the global adjustment); where
the images have systematic errors the block then bends back and the corrected planes follow
it. The measurements on the simulated sequences are in docs/defaults.md
(`correction_moves_block`) and on the model correction benchmark page.

The sigmas of the corrected vertices come from the joint problem (block and model unknown,
the model's datum held by the datum condition) at the final state: how well the images and
the rest of the model determine each corrected vertex, the block's own uncertainty included.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..align.coarse import SurfaceDistance
from ..align.objective import BlockObjective
from ..assign.assignment import Assignment
from ..assign.schedule import assign
from ..block.priors import GNSSPriors
from ..block.reconstruction import tie_points
from ..citymodel.store import PlaneStore
from ..options import AdjustmentOptions, RefineOptions
from .model_correction import CorrectionSelection
from .problem import BaselinePriors, HybridProblem
from .record import IterationRecord
from .steps import RoofObservers, model_after_solve

logger = logging.getLogger(__name__)


def every_point_alike(options: AdjustmentOptions) -> AdjustmentOptions:
    """`options`, or where they estimate the faces' offsets and tilts a copy that weighs every
    tie point alike: a model correction frees the vertices of the faces the images see and
    estimates their errors there, not as offsets and tilts beside them."""
    if options.face_weighting != "offsets":
        return options
    return dataclasses.replace(options, face_weighting="per_point")


class CorrectionProblem(HybridProblem):
    """A hybrid problem in which the images correct the faces they see well
    (adjust.model_correction), every tie point alike (`every_point_alike`); `hold_block()`
    makes the block's unknowns constant."""

    releases_model = True
    block_held = False
    points_free = 0  # tie points left unknown in a held block

    def __init__(self, reconstruction, store, assignment, gnss, options: AdjustmentOptions,
                 **kwargs):
        super().__init__(reconstruction, store, assignment, gnss, every_point_alike(options),
                         **kwargs)

    def hold_block(self, free_assigned_points: bool = False) -> None:
        """Poses, intrinsics and tie points constant: only the model moves. With
        `free_assigned_points` the tie points assigned to a plane stay unknowns (each with its
        image observations and its f_dTP): the poses still fix the block, but the points are
        no longer held where the adjustment to the given planes pulled them."""
        rec, ceres = self.reconstruction, self.problem
        blocks = [rec.frame(f).rig_from_world.params
                  for f in {rec.image(i).frame_id for i in rec.reg_image_ids()}]
        blocks += [camera.params for camera in rec.cameras.values()]
        free = set(self.point_ids.tolist()) if free_assigned_points else set()
        blocks += [rec.point3D(i).xyz for i in rec.point3D_ids() if i not in free]
        for rig in rec.rigs.values():
            blocks += [sensor.params for sensor in rig.non_ref_sensors.values()]
        for block in blocks:
            if ceres.has_parameter_block(block):
                ceres.set_parameter_block_constant(block)
        self.block_held = True
        self.points_free = len(free)

    def num_unknowns(self) -> int:
        if not self.block_held:
            return super().num_unknowns()
        return 3 * len(self.blocks.faces) + 3 * len(self.blocks.vertex_ids) \
            + 3 * self.points_free


@dataclass
class CorrectionResult:
    reconstruction: pycolmap.Reconstruction  # the block (the input object if it was held)
    current: PlaneStore  # the corrected model state
    assignment: Assignment | None
    selection: CorrectionSelection | None  # what the last solve corrected
    covariance_problem: HybridProblem | None  # the joint problem for the vertices' sigmas
    last: HybridProblem | None = None  # the last solve when it moved the block, else None
    iterations: list[IterationRecord] = field(default_factory=list)
    undone: str | None = None  # why the correction was undone


def correction_loop(rec: pycolmap.Reconstruction, store: PlaneStore, current: PlaneStore,
                    priors: GNSSPriors | None, options: RefineOptions, threshold: float, *,
                    exclude_point_ids: set[int] | None = None,
                    baselines: BaselinePriors | None = None, weights: np.ndarray | None = None,
                    objective: BlockObjective | None = None,
                    first_iteration: int = 0) -> CorrectionResult:
    """Correct the model from the block `rec`. `store`: the model as given (f_VT observes
    it); `current`: the model state after the adjustment; `threshold`: its last assignment
    threshold. With `correction_moves_block`, `rec` is adjusted in place (a correction whose
    block objective, against the corrected model, is worse than `objective`'s against the
    given one by more than its tolerance (a significant likelihood ratio) is undone: the
    result then holds a copy of the block as it was)."""
    o_a, o_adj, o_w = options.assignment, options.adjustment, options.workflow
    moves_block = o_adj.correction_moves_block
    # With the block held the model's datum comes from the block: no datum condition.
    o_solve = o_adj if moves_block else dataclasses.replace(o_adj, sigma_correction_datum=None)
    saved = (pycolmap.Reconstruction(rec), current) if moves_block else None
    before = objective(rec) if moves_block and objective is not None else None
    # A held block is solved on a copy: the poses stay, the assigned tie points move with the
    # corrected planes there, and the refined block handed back is the adjustment's own.
    work = rec if moves_block else pycolmap.Reconstruction(rec)
    records: list[IterationRecord] = []
    previous_rms = None
    last = assignment = None
    roof_observers = RoofObservers(store, o_a)
    for k in range(o_adj.correction_iterations):
        point_ids, points = tie_points(work, exclude_point_ids)
        assignment = assign(points, point_ids, current, threshold, o_a, weights,
                            roof_observers(work, point_ids))
        if not assignment.num_assigned:
            break
        robust = CorrectionProblem(work, store, assignment, priors, o_solve, robust_images=False,
                                   robust_planes=True, current=current, baselines=baselines)
        if not moves_block:
            robust.hold_block(free_assigned_points=True)
        robust_report = robust.solve()
        outliers = robust.point_ids[np.abs(robust.residuals["dTP"])
                                    > o_adj.elimination_threshold]
        assignment = assignment.eliminate(np.isin(assignment.point_ids, outliers), points, o_a)
        last = CorrectionProblem(work, store, assignment, priors, o_solve, robust_images=False,
                                 robust_planes=False, current=model_after_solve(current, robust),
                                 baselines=baselines)
        if not moves_block:
            last.hold_block(free_assigned_points=True)
        report = last.solve()
        current = model_after_solve(current, last)
        rms = report.rms_total
        change = abs(previous_rms - rms) / rms if previous_rms else float("inf")
        previous_rms = rms
        records.append(IterationRecord(first_iteration + k, threshold, assignment.num_assigned,
                                       assignment.num_faces, dict(assignment.rejected_faces),
                                       len(outliers),
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
        return CorrectionResult(rec if saved is None else saved[0],
                                current if saved is None else saved[1], assignment, None, None,
                                iterations=records, undone="no tie point could be assigned")
    if moves_block:
        undone = _moved_away(rec, current, objective, before, options)
        if undone is not None:
            return CorrectionResult(saved[0], saved[1], assignment, None, None,
                                    iterations=records, undone=undone)
        return CorrectionResult(rec, current, assignment, last.blocks.correction, last, last,
                                records)
    # The sigmas: the joint problem at the final state (not solved again).
    joint = CorrectionProblem(work, store, assignment, priors, o_adj, robust_images=False,
                              robust_planes=False, current=current, baselines=baselines)
    return CorrectionResult(rec, current, assignment, last.blocks.correction, joint, None,
                            records)


def _moved_away(rec: pycolmap.Reconstruction, current: PlaneStore, objective, before,
                options: RefineOptions) -> str | None:
    """Why the correction that moved the block is undone: its block objective against the
    corrected model (the tie points near the model they were adjusted to, and GNSS) is worse
    than `before` (against the given one) by more than the objective's tolerance; None when it
    is not, or without an objective."""
    if before is None:
        return None
    after = BlockObjective(SurfaceDistance(current, options.assignment.excluded_classes,
                                           options.adjustment.num_threads),
                           objective.priors, objective.ids, objective.options,
                           options.workflow.divergence_alpha)(rec)
    if after <= before + objective.tolerance:
        return None
    reason = (f"the corrected model moved the block away from it (objective {before:.3f} -> "
              f"{after:.3f})")
    logger.warning("model correction undone: %s", reason)
    return reason
