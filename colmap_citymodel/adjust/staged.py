"""The faces' errors as unknowns, started where every tie point alike has brought the block.

With `AdjustmentOptions.face_weighting` "offsets" each face's offset and tilts are unknowns
with priors (adjust.problem). Far from the model (the first, wide assignment thresholds) many
tie points sit on faces that are not theirs, and faces free to move by their generalisation
error follow them: the block's scale and position wander off with the wrong points (a drive
along one row of facades grew by 8.7 % in its first solve). Every point alike, on faces held
where the model has them, is the robust way there. So the loop runs twice:

1. every tie point alike (`face_weighting` "per_point") from the start, as Unger's loop,
   until one solve moves no camera by more than a tenth of the faces' sigma (the second loop
   moves the block on by up to that sigma: settling it further buys nothing);
2. from its result, at its last threshold and without the similarity rounds, with the faces'
   errors as unknowns, until that loop converges.

Where the first loop diverged, or its block fails the quality gate (`placed`, given by the
workflow: a model that does not fit, an ambiguous placement), the block is not on the model,
and the faces' effects refine a placement, they do not establish one: the second is not run.
How far the second loop moved the block from the first one's (`LoopResult.weighting_move`) is
how much the block depends on weighting the faces as units or every point alike; the stated
sigmas hold at least that (adjust.observability.weighting_observability).
The second loop starts on the model, at the assignment's final threshold: a scale change
there is what the faces' positions say, not wrong points pulling, so it does not hold the
block's scale at the GNSS-only one for a large change (it still holds it where the planes do
not fix the scale at all).
"""

from __future__ import annotations

import copy
import logging
from collections.abc import Callable
from dataclasses import replace

from ..block.reconstruction import camera_centres
from .correction_loop import every_point_alike
from .faces import sigma_face_in_use
from .loop import LoopResult, adjustment_loop
from .record import mean_move

logger = logging.getLogger(__name__)


def staged_adjustment_loop(rec, store, priors, options, objective, all_ids, *,
                           placed: Callable[[LoopResult, object], str | None] | None = None,
                           **kwargs) -> LoopResult:
    """adjust.loop.adjustment_loop, in two stages with `face_weighting` "offsets" (module
    docstring); `kwargs` go to both loops. `placed(first, options)`: why the first loop's
    block is not placed on the model (its quality gate failed), None if it is."""
    if options.adjustment.face_weighting != "offsets":
        return adjustment_loop(rec, store, priors, options, objective, all_ids, **kwargs)
    alike = copy.deepcopy(options)
    alike.adjustment = every_point_alike(alike.adjustment)
    # Its block is where the second loop starts, which moves it on by up to the faces' sigma:
    # settled to a tenth of that (convergence_sigma_share) is settled enough.
    alike.workflow.convergence_camera_shift = max(
        options.workflow.convergence_camera_shift,
        options.workflow.convergence_sigma_share * sigma_face_in_use(options.adjustment))
    first = adjustment_loop(rec, store, priors, alike, objective, all_ids, **kwargs,
                            places_next=True)
    why = (f"the loop with every tie point alike diverged ({first.diverged})"
           if first.diverged is not None else placed(first, alike) if placed else None)
    if why:
        logger.info("the faces' errors are not estimated: %s", why)
        return first
    effects = copy.deepcopy(options)
    effects.assignment.max_threshold = first.threshold
    effects.assignment.indirect_max_threshold = first.threshold
    effects.workflow.alignment_rounds = 0
    logger.info("the faces' errors as unknowns, from the block every tie point alike placed "
                "(threshold %.2f m)", first.threshold)
    # Its last iterate is its result: the block objective measures the tie points against the
    # given planes, which the faces' estimated offsets move them off on purpose, so the loop's
    # first iterate, nearest the first loop's block, tends to look best.
    placed_alike = camera_centres(first.reconstruction)  # the second loop moves this block
    second = adjustment_loop(first.reconstruction, store, priors, effects, objective, all_ids,
                             **kwargs, hold_runaway_scale=False, best_when_unsettled=False)
    return replace(_joined(first, second), weighting_move=mean_move(
        placed_alike, camera_centres(second.reconstruction)))


def _joined(first: LoopResult, second: LoopResult) -> LoopResult:
    """The second loop's result with the first loop's iterations before its own (numbered on,
    phase "faces"), the two moves, the first loop's observability, both warnings and seconds."""
    offset = len(first.iterations)
    iterations = first.iterations + [replace(record, iteration=record.iteration + offset,
                                             phase="faces") for record in second.iterations]
    seconds = dict(first.seconds)
    for key, value in second.seconds.items():
        seconds[key] = seconds.get(key, 0.0) + value
    return replace(second, iterations=iterations, move=second.move * first.move,
                   observability_before=first.observability_before,
                   warnings=first.warnings + second.warnings, seconds=seconds)
