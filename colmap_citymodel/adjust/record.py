"""One iteration of the refine loop as the report shows it, and what a loop's iterations tell
about its convergence."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .problem import SolveReport


@dataclass
class IterationRecord:
    iteration: int
    threshold: float
    num_assigned: int
    num_faces: int
    rejected_faces: dict[str, int]
    num_eliminated: int
    robust: SolveReport | None  # None: no |v| / sigma above the threshold, no robust solve
    final: SolveReport
    relative_change: float
    phase: str = "loop"  # "loop": steps 3-4; "faces": their second loop with the faces' errors
    # as unknowns (adjust.staged); "correction": with the model corrected
    camera_shift: float = float("nan")  # largest camera centre change of this iteration (m)
    block_move: tuple[float, float, float] | None = None  # mean camera centre change (m, E N U)


    def todict(self) -> dict:
        return {
            "iteration": self.iteration, "threshold": self.threshold,
            "num_assigned_points": self.num_assigned, "num_planes": self.num_faces,
            "rejected_planes": self.rejected_faces, "num_eliminated_dTP": self.num_eliminated,
            "robust_solve": self.robust.todict() if self.robust else None,
            "solve": self.final.todict(),
            "rms_normalised": self.final.rms_total, "relative_change": self.relative_change,
            "phase": self.phase, "camera_shift_m": self.camera_shift,
            "block_move_m": list(self.block_move) if self.block_move is not None else None,
            # The iteration ended on its robust solve; the next one solved with the original
            # weights (WorkflowOptions.solve_again_after_elimination).
            "robust_only": self.robust is not None and self.final is self.robust,
        }


def cameras_settled(iterations: list[IterationRecord], tolerance: float) -> bool:
    """Two iterations in a row, after the first, moved no camera by more than `tolerance` (m):
    one small move alone can be a pause in a slow swing of the block."""
    return len(iterations) > 2 and max(it.camera_shift for it in iterations[-2:]) < tolerance


def mean_move(before: np.ndarray, after: np.ndarray) -> np.ndarray | None:
    """(3,) the cameras' mean move (m) between two `camera_centres` of one block; None where
    the registered images differ or there are none."""
    if before.shape != after.shape or not len(after):
        return None
    return np.mean(after - before, axis=0)


#: Steps of a creep (moves along an axis with one sign) that its rate is estimated from: two
#: ratios of successive steps, the fewest that tell a slowing creep from a noisy one.
MIN_CREEP_STEPS = 3


def remaining_move(iterations: list[IterationRecord]) -> np.ndarray | None:
    """(3,) how far (m, E N U) the block would still move if the loop went on, from its last
    iterations' mean moves: a loop that converges linearly with rate r (each step r times the
    one before) has |s| r / (1 - r) left after step s. Along an axis the last steps of one sign
    (at least MIN_CREEP_STEPS) give r (a least-squares line through their log sizes); r >= 1,
    a creep that does not slow, leaves inf. Steps that change sign swing round where the loop
    settles: the last step is what is left. None without the iterations' moves."""
    moves = [it.block_move for it in iterations if it.block_move is not None]
    if not moves:
        return None
    moves = np.asarray(moves, float)
    out = np.abs(moves[-1])
    for axis in range(3):
        steps = moves[:, axis]
        last = steps[-1]
        run = 1
        while run < len(steps) and steps[-run - 1] * last > 0:
            run += 1
        if last == 0.0 or run < MIN_CREEP_STEPS:
            continue
        sizes = np.log(np.abs(steps[-run:]))
        rate = float(np.exp(np.polyfit(np.arange(run), sizes, 1)[0]))
        out[axis] = abs(last) * rate / (1.0 - rate) if rate < 1.0 else np.inf
    return out
