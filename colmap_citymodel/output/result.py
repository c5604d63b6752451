"""The record that refine returns: the adjusted block, the model state, the assignment, the
iterations, and what the precision and quality stages found. The output stage writes it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..adjust.model_correction import ModelCorrection
from ..adjust.problem import SolveReport
from ..adjust.record import IterationRecord
from ..assign.assignment import Assignment
from ..block.priors import GNSSPriors
from ..citymodel.store import PlaneStore
from ..options import RefineOptions
from ..precision.checkpoints import CheckpointEvaluation
from ..precision.estimate import PrecisionResult
from ..precision.quality import QualityReport
from ..precision.variance_components import VarianceComponents


@dataclass
class RefineResult:
    """What refine() returns. `reconstruction` is in the store's local frame."""

    reconstruction: pycolmap.Reconstruction
    store: PlaneStore  # the model as given (cropped to the reconstruction)
    adjusted_store: PlaneStore  # same topology with adjusted vertices
    assignment: Assignment
    plane_faces: np.ndarray  # faces that were unknowns in the last solve
    plane_normals: np.ndarray  # their adjusted normals (local frame)
    plane_offsets: np.ndarray
    input_to_local: pycolmap.Sim3d  # the initial similarity applied to the input
    georegistration_rms: float | None
    step2: SolveReport | None
    step2_eliminated: int
    iterations: list[IterationRecord]
    options: RefineOptions
    warnings: list[str] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    gnss_priors: GNSSPriors | None = None  # the GNSS priors of the last solve (local frame)
    precision: PrecisionResult | None = None  # precision.py: s0, global test, covariances
    variance_components: VarianceComponents | None = None  # PrecisionOptions.variance_components
    checkpoints: CheckpointEvaluation | None = None  # Delta (and sigma) of given check points
    # The GNSS-only adjustment of the same block (local frame); None without GNSS.
    gnss_only: pycolmap.Reconstruction | None = None
    quality: QualityReport | None = None  # the verdict; "failed": `reconstruction` is gnss_only
    observability: dict = field(default_factory=dict)  # quality.observability, after the solve
    observability_before: dict = field(default_factory=dict)  # the same at the first assignment
    refined: pycolmap.Reconstruction | None = None  # the refined block, even when not handed back
    datum_cues: dict = field(default_factory=dict)  # which input fixed each datum parameter
    # The terrain the ground tie points were held to (citymodel.ground_faces.block_terrain:
    # source, tiles, cells, warnings; "residuals" per terrain unit after the last solve).
    terrain: dict = field(default_factory=dict)
    # Step 2's test of the interior orientation (adjust.steps.IntrinsicsTest.todict) or None.
    intrinsics: dict | None = None
    # The ground control marks (adjust.marks.marks_record: each mark's use, test and blunder
    # reason), None without them.
    control_marks: dict | None = None
    coarse_alignment: dict | None = None  # what the coarse search found (align.coarse)
    # The estimated constant GNSS offset (--gnss_height_offset auto, --gnss_bias auto) with its
    # sigma, start value, prior and the geoid the heights came through; None when not estimated.
    gnss_offset: dict | None = None
    # What the images corrected in the model (AdjustmentOptions.correct_model), else None.
    model_correction: ModelCorrection | None = None
    # The windows of the sliding-window workflow (adjust.sliding_window), else None.
    sliding_window: dict | None = None
    # The rule that ended the assign/adjust loop (adjust.loop.LoopResult.stopped_by): None when
    # its iterations ran out or when it did not run.
    loop_stopped_by: str | None = None
    # The model-only georegistration's search (align.locate: method, hypotheses, best and
    # runner-up scores, the hint's distance, seconds); None when GNSS or a transform gave it.
    georegistration: dict | None = None

    @property
    def handed_back(self) -> str:
        """"refined", or "gnss_only" when the GNSS-only block is the result (the quality gate
        failed, or the model fixes nothing of the datum that GNSS does not fix better)."""
        return ("gnss_only" if self.gnss_only is not None
                and self.reconstruction is self.gnss_only else "refined")

    @property
    def origin(self) -> np.ndarray:
        return self.store.origin

    def reconstruction_in_crs(self) -> pycolmap.Reconstruction:
        """A copy of the refined reconstruction in model CRS coordinates (origin added)."""
        rec = pycolmap.Reconstruction(self.reconstruction)
        rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), self.origin))
        return rec

    def plane_residuals(self) -> dict[int, np.ndarray]:
        """Signed distances (m) of the assigned tie points to their adjusted planes, per face."""
        slot = {int(f): k for k, f in enumerate(self.plane_faces)}
        out: dict[int, list[float]] = {}
        a = self.assignment
        for point_id, face in zip(a.point_ids[a.assigned], a.face_index[a.assigned]):
            k = slot.get(int(face))
            if k is None:
                continue
            xyz = self.reconstruction.point3D(int(point_id)).xyz
            out.setdefault(int(face), []).append(float(self.plane_normals[k] @ xyz
                                                       + self.plane_offsets[k]))
        return {f: np.array(v) for f, v in out.items()}
