"""One iteration of the refine loop as the report shows it."""

from __future__ import annotations

from dataclasses import dataclass

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


    def todict(self) -> dict:
        return {
            "iteration": self.iteration, "threshold": self.threshold,
            "num_assigned_points": self.num_assigned, "num_planes": self.num_faces,
            "rejected_planes": self.rejected_faces, "num_eliminated_dTP": self.num_eliminated,
            "robust_solve": self.robust.todict() if self.robust else None,
            "solve": self.final.todict(),
            "rms_normalised": self.final.rms_total, "relative_change": self.relative_change,
            "phase": self.phase, "camera_shift_m": self.camera_shift,
            # The iteration ended on its robust solve; the next one solved with the original
            # weights (WorkflowOptions.solve_again_after_elimination).
            "robust_only": self.robust is not None and self.final is self.robust,
        }


def cameras_settled(iterations: list[IterationRecord], tolerance: float) -> bool:
    """Two iterations in a row, after the first, moved no camera by more than `tolerance` (m):
    one small move alone can be a pause in a slow swing of the block."""
    return len(iterations) > 2 and max(it.camera_shift for it in iterations[-2:]) < tolerance
