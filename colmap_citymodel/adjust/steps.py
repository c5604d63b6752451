"""The adjustments of the refine loop other than the hybrid solve itself: the bundle adjustment
with GNSS and no model, the similarity rounds onto the assigned planes, and the model state
after a solve."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from ..align.georegister import transform_points
from ..align.objective import BlockObjective
from ..assign.assignment import Assignment, Observers
from ..assign.schedule import assign
from ..block.priors import GNSSPriors
from ..block.reconstruction import observations, observer_centres
from ..citymodel.store import PlaneStore
from ..options import AssignmentOptions, RefineOptions
from .problem import HybridProblem, SolveReport

logger = logging.getLogger(__name__)


class RoofObservers:
    """Where the tie points are seen from, for the roof test of the assignment
    (`AssignmentOptions.roofs_seen_from_above`): the observations are listed once, the camera
    centres read anew at each call. None when the test is off or the model has no roof."""

    def __init__(self, store: PlaneStore, options: AssignmentOptions):
        self.enabled = options.roofs_seen_from_above and bool(
            np.any(store.faces.semantic.mask("RoofSurface")))
        self._index: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self, rec: pycolmap.Reconstruction, point_ids: np.ndarray
                 ) -> Observers | None:
        """`point_ids`: the same tie points, in the same order, at every call."""
        if not self.enabled:
            return None
        if self._index is None:
            self._index = observations(rec, point_ids)
        rows, image_ids = self._index
        return Observers(rows, observer_centres(rec, image_ids))


def step2_bundle_adjustment(rec: pycolmap.Reconstruction, gnss: GNSSPriors | None,
                            options: RefineOptions) -> tuple[SolveReport, int]:
    """BA with GNSS priors and no model; image observations with normalised residual > 3 (and
    points with too small intersection angle) eliminated, then, with the original weights
    (`AdjustmentOptions.image_loss` "none"), the adjustment repeated without them; with a
    robust image loss the robust solve comes first and is not repeated."""
    o = options.adjustment
    robust = o.image_loss != "none"
    report = HybridProblem(rec, None, None, gnss, o, robust_images=robust,
                           robust_planes=False).solve()
    eliminated = pycolmap.ObservationManager(rec).filter_all_points3D(
        o.elimination_threshold * o.sigma_image, o.min_triangulation_angle)
    if not robust and eliminated:
        first = report
        report = HybridProblem(rec, None, None, gnss, o, robust_images=False,
                               robust_planes=False).solve()
        report.ceres_iterations += first.ceres_iterations
        report.seconds += first.seconds
    logger.info("step 2 (BA without model): %d Ceres iterations, %.1f s, image RMS %.3f px, "
                "%d image observations eliminated", report.ceres_iterations, report.seconds,
                report.rms["image"] * o.sigma_image, eliminated)
    return report, int(eliminated)


#: Solver iterations of the interior-orientation test's solve. A partial solve lowers the
#: chi-square by less than a converged one, so the test only gets more conservative; where it
#: finds them off, the solve is then converged. A few iterations already show a lens a pixel
#: off far beyond any usual significance level; where the interior orientation is right, the
#: test costs those iterations only.
INTRINSICS_TEST_ITERATIONS = 5


@dataclass
class IntrinsicsTest:
    """Step 2's test of the cameras' interior orientation: how much the chi-square of the
    bundle adjustment without the model drops when each camera's focal length and distortion
    are free (in units of its variance factor), on how many degrees of freedom, its p-value,
    and whether they are refined from then on."""

    drop: float
    dof: int
    p_value: float
    refined: bool
    # The block solved with them free, kept only when `refined` (refine continues with it).
    freed: pycolmap.Reconstruction | None = field(default=None, repr=False)

    def todict(self) -> dict:
        return {"chi2_drop": self.drop, "dof": self.dof, "p_value": self.p_value,
                "refined": self.refined}


def check_intrinsics(rec: pycolmap.Reconstruction, gnss: GNSSPriors | None,
                    options: RefineOptions, held: SolveReport) -> IntrinsicsTest | None:
    """After step 2 with the interior orientation held (`held` its report): solve a copy
    again with each camera's focal length and distortion free; where the chi-square drops by
    more than chance allows at `intrinsics_test_alpha` (a likelihood-ratio test, the drop over
    the freed solve's variance factor against chi-square with as many degrees of freedom as
    parameters freed; `INTRINSICS_TEST_ITERATIONS` solver iterations), that solve is
    converged and refine continues from it (`IntrinsicsTest.freed`). None: no test (refined
    anyway, or off)."""
    o = options.adjustment
    if o.refine_intrinsics or o.intrinsics_test_alpha is None:
        return None
    trial = pycolmap.Reconstruction(rec)
    freed = HybridProblem(trial, None, None, gnss, replace(
        o, refine_intrinsics=True,
        max_solver_iterations=min(o.max_solver_iterations, INTRINSICS_TEST_ITERATIONS)),
        robust_images=False, robust_planes=False).solve()
    dof = freed.num_unknowns - held.num_unknowns
    drop = (sum(held.sum_squares.values()) - sum(freed.sum_squares.values())) \
        / freed.sigma0_squared
    p_value = float(chi2.sf(max(drop, 0.0), dof)) if dof > 0 and np.isfinite(drop) else 1.0
    refined = p_value < o.intrinsics_test_alpha
    if refined:  # the later hybrid solves start from a converged block, as step 2's do
        HybridProblem(trial, None, None, gnss, replace(o, refine_intrinsics=True),
                      robust_images=False, robust_planes=False).solve()
    logger.info("interior orientation: chi-square %.1f lower with focal length and distortion "
                "free (%d parameters, p = %.2g): %s", drop, dof, p_value,
                "refined from here on" if refined else "held as given")
    return IntrinsicsTest(float(drop), int(dof), p_value, bool(refined),
                          trial if refined else None)


#: Fractions of an alignment round's similarity tried, in this order, when the whole of it
#: raises the block objective.
STEP_FRACTIONS = (0.5, 0.25, 0.125)


def align_block_to_planes(rec: pycolmap.Reconstruction, point_ids: np.ndarray,
                          points: np.ndarray, assignment: Assignment, store: PlaneStore,
                          priors: GNSSPriors | None, threshold: float, options: RefineOptions,
                          *, objective: BlockObjective | None = None,
                          scale_sigma: float | None = None, weights: np.ndarray | None = None
                          ) -> tuple[pycolmap.Sim3d, np.ndarray, Assignment]:
    """Refine's initial alignment rounds: fit a similarity to the assigned planes, move `rec`
    by it, assign again at `threshold`, until a fit moves the tie points by less than
    `alignment_tolerance` on average. With an `objective`, a round whose similarity does not
    lower it tries `STEP_FRACTIONS` of that similarity; when none lowers it the round is
    undone and ends the rounds. Returns the total similarity and the moved `points` (same ids)
    with their last assignment."""
    total = pycolmap.Sim3d()
    value = objective(rec) if objective is not None else None
    for _ in range(options.workflow.alignment_rounds):
        move, moved = align_to_planes(rec, points, assignment, store, priors, options.adjustment,
                                      scale_sigma)
        if objective is not None:
            new_value = objective(rec, move)
            for fraction in STEP_FRACTIONS:
                if new_value < value:
                    break
                # The fit's optimum can overshoot (at the first, wide threshold part of the
                # assignments are wrong): a shorter step towards it may still help.
                shorter = partial_similarity(move, fraction, points.mean(0))
                shorter_value = objective(rec, shorter)
                if shorter_value < value:
                    logger.info("alignment round: objective %.4f -> %.4f for the whole move, "
                                "%.4f for %.3g of it", value, new_value, shorter_value, fraction)
                    move, new_value = shorter, shorter_value
                    moved = transform_points(move, points)
            if new_value >= value:
                logger.info("alignment round undone: objective %.4f -> %.4f", value, new_value)
                break
            value = new_value
        rec.transform(move)
        total = move * total
        mean_shift = float(np.linalg.norm(moved - points, axis=1).mean())
        points = moved
        assignment = assign(points, point_ids, store, threshold, options.assignment, weights)
        if mean_shift < options.workflow.alignment_tolerance or not assignment.num_assigned:
            break
    return total, points, assignment


def partial_similarity(move: pycolmap.Sim3d, fraction: float, centre: np.ndarray
                       ) -> pycolmap.Sim3d:
    """`fraction` of the similarity `move` (scale, rotation angle and the shift of `centre`
    each scaled), as a step towards it."""
    rotation = Rotation.from_matrix(np.asarray(move.rotation.matrix()))
    partial = Rotation.from_rotvec(rotation.as_rotvec() * fraction).as_matrix()
    scale = move.scale ** fraction
    target = centre + fraction * (transform_points(move, centre[None])[0] - centre)
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(partial), target - scale * partial @ centre)


def align_to_planes(rec: pycolmap.Reconstruction, points: np.ndarray, assignment: Assignment,
                    store: PlaneStore, priors: GNSSPriors | None, options,
                    scale_sigma: float | None = None) -> tuple[pycolmap.Sim3d, np.ndarray]:
    """The similarity that best puts the assigned tie points on their planes (and the block on
    GNSS, with the adjustment's weights; see initial_alignment), and all `points` moved by it.
    `scale_sigma`: how far (relative) GNSS lets the scale change."""
    from ..align.initial_alignment import similarity_to_planes
    from ..errormodel.model import gnss_model

    assigned = assignment.assigned
    faces = assignment.face_index[assigned]
    gnss = {}
    if priors is not None:  # GNSS's positions as read, its bias an error of its model
        antennas = priors.observed_points(rec)
        gnss = dict(antennas=antennas, gnss=priors.positions,
                    gnss_model=gnss_model(priors, antennas, options))
    result = similarity_to_planes(points[assigned], store.normals[faces], store.offsets[faces],
                                  options.sigma_dtp, options.plane_loss_scale,
                                  scale_sigma=scale_sigma, **gnss)
    moved = transform_points(result.sim3, points)
    logger.info("block moved onto the planes of its %d assigned tie points by a similarity "
                "(%d iterations): mean shift %.2f m, scale %.5f, inlier distance RMS %.3f -> "
                "%.3f m", int(assigned.sum()), result.iterations,
                float(np.linalg.norm(moved - points, axis=1).mean()), result.sim3.scale,
                result.rms_before, result.rms_after)
    return result.sim3, moved


def model_after_solve(current: PlaneStore, problem: HybridProblem) -> PlaneStore:
    """The model state after a solve: adjusted vertices, planes refitted to them."""
    blocks = problem.blocks
    if len(blocks.vertex_ids) == 0:
        return current
    vertices = current.vertices.copy()
    vertices[blocks.vertex_ids] = blocks.vertex_array
    return current.with_vertices(vertices)
