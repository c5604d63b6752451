"""The refine step (`colmap_citymodel.refine`): global workflow of Unger Table 3 with any
assignment method (direct (a) by default; (b), (c), auto). A sliding-window workflow (Unger
3.3.2) will sit beside it.

1. SfM (COLMAP, done before) + 7-parameter similarity to GNSS (or a given initial transform;
   along a straight line the cameras' upright orientation fixes the roll);
2. bundle adjustment with GNSS priors and no model, robust on image observations; image
   observations with normalised residual > 3 eliminated. This is the GNSS-only result that
   the quality gate compares with and hands back when the model cannot help;
   then coarse alignment: the block's shift (and roll about a straight line) against the
   model surfaces within a few GNSS sigma (coarse_alignment);
3. assign tie points to model planes (the first time followed by similarity rounds that must
   lower the block objective);
4. hybrid bundle adjustment, robust on f_dTP; fictitious observations with normalised residual
   > 3 eliminated and the adjustment repeated with the original weights.
Steps 3-4 repeat (assignments recomputed from the current estimate every iteration; vertex-plane
relations never change; the threshold never grows) until the relative change of the RMS of
normalised residuals < 1e-5 or 10 iterations, or until the block objective worsens (the best
iterate is kept). The scale is held from the GNSS-only block where the planes cannot give it.
At the end: observability of the datum and the quality verdict (quality.py).

Everything happens in the plane store's local frame (model CRS minus `store.origin`).
`refine()` works on pycolmap objects in memory and never modifies its inputs; `main()` is the
CLI's entry: read inputs, refine, write outputs atomically.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pycolmap
from tqdm import tqdm

from .assign_planes import (Assignment, assign, filter_faces, initial_threshold,
                            next_threshold)
from .errors import DatumError, GeoregistrationError, GNSSError, NoOverlapError
from .hybrid_adjustment import BaselinePriors, GNSSPriors, HybridProblem, SolveReport
from .options import RefineOptions
from .plane_store import PlaneStore

if TYPE_CHECKING:
    from .evaluate import CheckpointEvaluation
    from .precision import PrecisionResult, VarianceComponents
    from .quality import QualityReport

logger = logging.getLogger("colmap_citymodel.workflow")

# Two plane normals closer than this (either sign) count as the same orientation for the datum.
SAME_ORIENTATION_DEG = 10.0
# A direction whose weight in sum(n n^T) is below this fraction of the largest is "weak".
WEAK_DIRECTION_RATIO = 0.05


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

    def todict(self) -> dict:
        return {
            "iteration": self.iteration, "threshold": self.threshold,
            "num_assigned_points": self.num_assigned, "num_planes": self.num_faces,
            "rejected_planes": self.rejected_faces, "num_eliminated_dTP": self.num_eliminated,
            "robust_solve": self.robust.todict() if self.robust else None,
            "solve": self.final.todict(),
            "rms_normalised": self.final.rms_total, "relative_change": self.relative_change,
        }


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
    precision: "PrecisionResult | None" = None  # precision.py: s0, global test, covariances
    variance_components: "VarianceComponents | None" = None  # PrecisionOptions.variance_components
    checkpoints: "CheckpointEvaluation | None" = None  # Delta (and sigma) of given check points
    # The GNSS-only adjustment of the same block (local frame); None without GNSS.
    gnss_only: pycolmap.Reconstruction | None = None
    quality: "QualityReport | None" = None  # the verdict; "failed": `reconstruction` is gnss_only
    observability: dict = field(default_factory=dict)  # quality.observability, after the solve
    observability_before: dict = field(default_factory=dict)  # the same at the first assignment
    refined: pycolmap.Reconstruction | None = None  # the refined block, even when not handed back
    datum_cues: dict = field(default_factory=dict)  # which input fixed each datum parameter
    coarse_alignment: dict | None = None  # what the coarse search found (coarse_alignment)

    @property
    def handed_back(self) -> str:
        """"refined", or "gnss_only" when the quality gate failed."""
        return ("gnss_only" if self.quality is not None and self.quality.verdict == "failed"
                and self.gnss_only is not None else "refined")

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


def tie_points(rec: pycolmap.Reconstruction, exclude: set[int] | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    ids = np.array([i for i in rec.point3D_ids() if not exclude or i not in exclude], np.int64)
    xyz = np.array([rec.point3D(int(i)).xyz for i in ids]).reshape(-1, 3)
    return ids, xyz


def camera_centres(rec: pycolmap.Reconstruction) -> np.ndarray:
    return np.array([rec.image(i).projection_center() for i in rec.reg_image_ids()])


def check_datum(store: PlaneStore, assignment: Assignment, has_gnss: bool) -> list[str]:
    """Unger 3.2.3: at least four planes of different orientation fix the 7 datum parameters;
    GNSS adds a weak datum. Raise without GNSS and too few orientations; warn about weak
    directions (e.g. only parallel facades leave the translation along the street free)."""
    normals = store.normals[assignment.faces]
    orientations: list[np.ndarray] = []
    cos_same = np.cos(np.radians(SAME_ORIENTATION_DEG))
    for n in normals:
        if all(abs(n @ o) < cos_same for o in orientations):
            orientations.append(n)
    if len(orientations) < 4 and not has_gnss:
        raise DatumError(
            f"only {len(orientations)} model plane orientation(s) received tie points "
            f"({len(normals)} planes); at least 4 different orientations are needed to fix the "
            "datum without GNSS: give GNSS positions or a model that covers more of the scene")
    warnings = []
    if len(normals):
        scatter = normals.T @ normals
        eigenvalues, eigenvectors = np.linalg.eigh(scatter)
        for value, direction in zip(eigenvalues, eigenvectors.T):
            if value < WEAK_DIRECTION_RATIO * eigenvalues[-1]:
                warnings.append(
                    f"the assigned planes hardly constrain the translation along {describe(direction)}"
                    + ("; only GNSS fixes it" if has_gnss else ""))
    for w in warnings:
        logger.warning(w)
    return warnings


def describe(direction: np.ndarray) -> str:
    """A direction in words: vertical, or a horizontal azimuth in the CRS (clockwise from north)."""
    if abs(direction[2]) > 0.9:
        return "the vertical"
    azimuth = np.degrees(np.arctan2(direction[0], direction[1])) % 180.0
    return f"the horizontal direction of azimuth {azimuth:.0f} deg"


def crop_to_reconstruction(store: PlaneStore, rec: pycolmap.Reconstruction, margin: float
                           ) -> PlaneStore:
    """Keep the model faces near the georegistered reconstruction; none: NoOverlapError."""
    _, points = tie_points(rec)
    xyz = np.vstack([points, camera_centres(rec)])
    lower = np.percentile(xyz, 1, axis=0) - margin
    upper = np.percentile(xyz, 99, axis=0) + margin
    # Heights are not trusted yet (GNSS heights may be ellipsoidal): crop in plan only.
    lower[2], upper[2] = -1e9, 1e9
    cropped = store.subset_bbox(lower, upper)
    if len(cropped.faces) == 0:
        raise NoOverlapError(
            "the city model does not overlap the georegistered reconstruction: model bbox "
            f"{_fmt_box(store.bbox_crs)} vs reconstruction bbox "
            f"{_fmt_box(np.array([lower, upper]) + store.origin)} (model CRS); check the CRS "
            "of the GNSS positions or the initial transform, and the model", store.source)
    return cropped


def _fmt_box(box: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.1f}" for v in np.asarray(box).ravel()) + "]"


def step2_bundle_adjustment(rec: pycolmap.Reconstruction, gnss: GNSSPriors | None,
                            options: RefineOptions) -> tuple[SolveReport, int]:
    """BA with GNSS priors and no model, robust on image observations; then eliminate image
    observations with normalised residual > 3 (and points with too small intersection angle)."""
    o = options.adjustment
    problem = HybridProblem(rec, None, None, gnss, o, robust_images=True, robust_planes=False)
    report = problem.solve()
    eliminated = pycolmap.ObservationManager(rec).filter_all_points3D(
        o.elimination_threshold * o.sigma_image, o.min_triangulation_angle)
    logger.info("step 2 (BA without model): %d Ceres iterations, %.1f s, image RMS %.3f px, "
                "%d image observations eliminated", report.ceres_iterations, report.seconds,
                report.rms["image"] * o.sigma_image, eliminated)
    return report, int(eliminated)


def georegister(rec: pycolmap.Reconstruction, store: PlaneStore, gnss, initial_transform,
                details: dict | None = None
                ) -> tuple[pycolmap.Sim3d, GNSSPriors | None, float | None]:
    """Bring the reconstruction into the store's local frame; return the applied similarity.
    `details`, when given, receives which cue fixed each datum parameter ("cues")."""
    from .georegister import estimate_georegistration
    from .read_gnss import match_to_reconstruction

    priors = None
    rms = None
    cues = {"translation": "initial transform", "scale": "initial transform",
            "rotation": "initial transform"}
    if gnss is not None:
        if getattr(gnss, "vertical_applied", None) is False:
            raise GNSSError(
                f"the GNSS heights ({gnss.source}) could not be converted to the model's height "
                f"system {store.crs.label} (PROJ lacks the geoid grid; see the warning above): "
                "install the grid, or give the heights already converted, or "
                "--gnss_height_offset METRES (model height minus GNSS height, e.g. about -47 "
                "for ellipsoidal heights in Germany)")
        image_ids, positions, sigmas = match_to_reconstruction(gnss, rec, store.origin)
        lever_arm = getattr(gnss, "lever_arm", None)
        priors = GNSSPriors(np.asarray(image_ids), np.asarray(positions), np.asarray(sigmas),
                            None if lever_arm is None else np.asarray(lever_arm, float))
    if initial_transform is not None:
        # The given transform maps the input frame to model CRS coordinates.
        to_local = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), -store.origin)
        sim3 = to_local * initial_transform
    elif priors is not None:
        result = estimate_georegistration(rec, priors.positions, priors.image_ids,
                                          sigmas=priors.sigmas)
        sim3, rms, cues = result.sim3, result.rms, result.cues
        logger.info("georegistration to %d GNSS positions: scale %.4f, RMS %.2f m, %d inliers",
                    len(priors), sim3.scale, rms, int(np.count_nonzero(result.inlier_mask)))
    else:
        raise GeoregistrationError(
            "no GNSS positions and no initial transform: give --database/--gnss/--exif or "
            "--initial_transform")
    rec.transform(sim3)
    if details is not None:
        details["cues"] = dict(cues)
    return sim3, priors, rms


def camera_up_and_view(rec: pycolmap.Reconstruction, image_ids=None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Image "up" (-y axis) and viewing direction (z axis) of the cameras (default: every
    registered one) in the world frame."""
    ids = rec.reg_image_ids() if image_ids is None else image_ids
    rows = np.array([np.asarray(rec.image(int(i)).cam_from_world().rotation.matrix())
                     for i in ids])
    return -rows[:, 1], rows[:, 2]


def scale_sigma_from_gnss(priors: GNSSPriors) -> float:
    """Relative sigma of the block's scale that its GNSS positions determine."""
    spread = priors.positions - priors.positions.mean(0)
    return float(np.median(priors.sigmas) / np.sqrt(max(np.sum(spread ** 2), 1e-12)))


class BlockObjective:
    """One figure that every start-up move and loop iteration must lower: minus the share of a
    fixed subset of tie points near the model surfaces, plus the mean squared normalised GNSS
    residual weighted as in the translation search (a one-sigma shift of the whole block
    costs as much as 1 % of the tie points on the model)."""

    def __init__(self, surface, priors: GNSSPriors | None, point_ids: np.ndarray,
                 radius: float):
        from .coarse_alignment import MAX_SEARCH_POINTS, SHIFT_PENALTY

        rng = np.random.default_rng(1)
        self.ids = (point_ids if len(point_ids) <= 2 * MAX_SEARCH_POINTS else
                    rng.choice(point_ids, 2 * MAX_SEARCH_POINTS, replace=False))
        self.surface, self.priors, self.radius = surface, priors, radius
        self.penalty = SHIFT_PENALTY

    def points(self, rec: pycolmap.Reconstruction) -> np.ndarray:
        return np.array([rec.point3D(int(i)).xyz for i in self.ids if rec.exists_point3D(int(i))]
                        ).reshape(-1, 3)

    def __call__(self, rec: pycolmap.Reconstruction, moved: pycolmap.Sim3d | None = None
                 ) -> float:
        from .coarse_alignment import near_share

        points, antennas = self.points(rec), None
        if self.priors is not None:
            antennas = self.priors.observed_points(rec)
        if moved is not None:
            matrix = np.asarray(moved.matrix())
            points = points @ matrix[:, :3].T + matrix[:, 3]
            if antennas is not None:
                antennas = antennas @ matrix[:, :3].T + matrix[:, 3]
        value = -near_share(self.surface(points), self.radius)
        if antennas is not None:
            v = (antennas - self.priors.positions) / self.priors.sigmas
            value += self.penalty * float(np.mean(np.sum(v ** 2, axis=1)))
        return value


def refine(reconstruction: pycolmap.Reconstruction, city_model: PlaneStore, gnss=None,
           options: RefineOptions | None = None, *, initial_transform: pycolmap.Sim3d | None = None,
           exclude_point_ids: set[int] | None = None, progress: bool = True,
           checkpoints: dict | None = None, checkpoint_observations: list | None = None
           ) -> RefineResult:
    """Georeference `reconstruction` and adjust it together with `city_model`.

    `gnss` is a `read_gnss.GNSSObservations` (model CRS) or None; `initial_transform` maps the
    input frame to model CRS coordinates (used instead of a GNSS similarity when given).
    `exclude_point_ids` are never assigned to planes (e.g. check points in the model).
    The input reconstruction is not modified; the result holds a refined copy, or, when the
    quality gate fails, the GNSS-only adjustment (`result.quality`, `result.gnss_only`).
    `checkpoints` ({id: XYZ} model CRS) and `checkpoint_observations` ([(image, id, x, y)],
    evaluate.read_*) are only evaluated at the end (Delta, and sigma when covariances are on).
    """
    from .coarse_alignment import SurfaceDistance, coarse_alignment

    options = options or RefineOptions()
    timer = {"start": time.perf_counter()}
    rec = pycolmap.Reconstruction(reconstruction)
    details: dict = {}
    sim3, priors, geo_rms = georegister(rec, city_model, gnss, initial_transform, details)
    store = crop_to_reconstruction(city_model, rec, options.workflow.overlap_margin)
    logger.info("model: %d faces, %d vertices near the reconstruction", len(store.faces),
                len(store.vertices))
    timer["georegistration"] = time.perf_counter() - timer["start"]

    warnings: list[str] = []
    report2, eliminated2 = step2_bundle_adjustment(rec, priors, options)
    gnss_only = gnss_only_sim3 = None
    if priors is not None:
        gnss_only, gnss_only_sim3 = pycolmap.Reconstruction(rec), sim3
    timer["step2"] = time.perf_counter() - timer["start"] - timer["georegistration"]

    o_a, o_adj, o_w = options.assignment, options.adjustment, options.workflow
    surface = SurfaceDistance(store, o_a.excluded_classes)
    all_ids, points = tie_points(rec, exclude_point_ids)
    objective = BlockObjective(surface, priors, all_ids, 2 * o_adj.sigma_dtp)
    scale_sigma = scale_sigma_from_gnss(priors) if priors is not None else None
    coarse = None
    if priors is not None and initial_transform is None and o_w.coarse_search_sigmas > 0:
        # The GNSS-only block is off the model by the GNSS error (metres, mostly a bias):
        # search the shift (and, along a straight line, the roll) that puts the tie points
        # on the model before any of them is assigned.
        t_coarse = time.perf_counter()
        # The images with GNSS fixed the georegistration; if they lie on a line, its rotation
        # about that line came from the cameras' upright orientation and is searched again.
        centres = np.array([rec.image(int(i)).projection_center() for i in priors.image_ids])
        straight = "roll_about_line" in details.get("cues", {})
        up, view = camera_up_and_view(rec, priors.image_ids)
        coarse = coarse_alignment(points, centres, up, view, store, surface,
                                  np.median(priors.sigmas, axis=0), straight,
                                  o_w.coarse_search_sigmas)
        if objective(rec, coarse.sim3) < objective(rec):
            rec.transform(coarse.sim3)
            sim3 = coarse.sim3 * sim3
        else:
            logger.info("coarse alignment kept the GNSS-only position (no better objective)")
        timer["coarse_alignment"] = time.perf_counter() - t_coarse

    current = store
    threshold = initial_threshold(o_a)
    weights = None
    if o_a.weighted_sampling:
        from .assign_msac import point_quality_weights

        weights = point_quality_weights(rec, all_ids)
    assignment: Assignment | None = None
    iterations: list[IterationRecord] = []
    observability_before: dict = {}
    baselines = None
    previous_rms = None
    solve_seconds = assign_seconds = 0.0
    last = None
    best = None  # (objective, iteration, reconstruction copy, assignment, current)
    diverged = None
    bar = tqdm(range(o_w.max_iterations), desc="refine", unit="it", disable=not progress)
    for iteration in bar:
        t0 = time.perf_counter()
        point_ids, points = tie_points(rec, exclude_point_ids)
        if assignment is not None:
            # The tie point set does not change inside the loop: same ids in the same order.
            # The threshold never grows again: no flip-flop between two assignments.
            threshold = min(threshold, next_threshold(assignment, points, current, o_a,
                                                      o_adj.sigma_dtp))
        assignment = assign(points, point_ids, current, threshold, o_a, weights)
        if iteration == 0 and assignment.num_assigned:
            # Initial values: move the block as a whole onto its planes first, so that the
            # adjustment is left with the block's deformation. As in ICP: fit, assign again,
            # fit again; a round that does not lower the block objective is undone.
            t_align = time.perf_counter()
            move, points, assignment = align_block_to_planes(
                rec, point_ids, points, assignment, current, priors, threshold, options,
                objective=objective, scale_sigma=scale_sigma, weights=weights)
            sim3 = move * sim3
            timer["initial_alignment"] = time.perf_counter() - t_align
            t0 += timer["initial_alignment"]
        assign_seconds += time.perf_counter() - t0
        if iteration == 0:
            warnings += check_datum(store, assignment, priors is not None)
            observability_before = assigned_observability(points, assignment, current, priors,
                                                          rec, options)
            if gnss_only is not None and scale_sigma and \
                    observability_before.get("scale", {}).get("source") not in ("planes", "both"):
                baselines = baseline_priors(gnss_only, priors, scale_sigma)
        elif assignment.num_assigned == 0 and priors is None:
            raise DatumError("no tie point could be assigned to a model plane and there is no "
                             "GNSS: the datum is undefined", store.source)

        t1 = time.perf_counter()
        # Until the scale is held, keep the state before the solves: a solve that changes the
        # scale further than GNSS allows is undone and repeated with the scale held.
        before_solve = (pycolmap.Reconstruction(rec), current, assignment) \
            if gnss_only is not None and baselines is None and scale_sigma else None
        robust_report = None
        outliers = np.zeros(0, np.int64)
        rejected = dict(assignment.rejected_faces)
        if iteration > 0:
            # Förstner-Wrobel only where needed: with the original weights first; robust
            # weighting and elimination follow only if some |v| / sigma exceeds the threshold.
            final = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                                  robust_planes=False, current=current, baselines=baselines)
            final_report = final.solve()
            normalised = final.residuals["dTP"]
            needs_robust = bool(np.any(np.abs(normalised) > o_adj.elimination_threshold))
        else:
            needs_robust = True
        if needs_robust:
            robust = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                                   robust_planes=True, current=current, baselines=baselines)
            robust_report = robust.solve()
            normalised = robust.residuals["dTP"]
            outliers = robust.point_ids[np.abs(normalised) > o_adj.elimination_threshold]
            assignment = assignment.without(np.isin(assignment.point_ids, outliers))
            assignment.face_index = filter_faces(points, assignment.face_index, o_a, rejected)
            assignment.distance[assignment.face_index < 0] = np.nan
            assignment.rejected_faces = rejected
            final = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                                  robust_planes=False, current=_current_from(current, robust),
                                  baselines=baselines)
            final_report = final.solve()
        solve_seconds += time.perf_counter() - t1
        current = _current_from(current, final)
        last = final
        if before_solve is not None:
            change = scale_change(gnss_only, rec, priors.image_ids)
            if abs(np.log1p(change)) > SCALE_RUNAWAY_SIGMAS * scale_sigma:
                logger.warning("iteration %d changed the block's scale by %.2f %% (%.1f GNSS "
                               "sigma): undone, the scale is held from now on", iteration,
                               100 * change, abs(np.log1p(change)) / scale_sigma)
                rec, current, assignment = before_solve
                baselines = baseline_priors(gnss_only, priors, scale_sigma)
                last = None
                continue

        rms = final_report.rms_total
        change = abs(previous_rms - rms) / rms if previous_rms else float("inf")
        iterations.append(IterationRecord(iteration, threshold, assignment.num_assigned,
                                          assignment.num_faces, rejected, len(outliers),
                                          robust_report, final_report, change))
        bar.set_postfix(points=assignment.num_assigned, planes=assignment.num_faces,
                        rms=f"{rms:.4f}")
        value = objective(rec)
        logger.info("iteration %d: threshold %.2f m, %d points on %d planes, %d f_dTP "
                    "eliminated, RMS %.4f (relative change %.1e), dTP RMS %.3f m, s0 %.3f, "
                    "objective %.4f", iteration, threshold, assignment.num_assigned,
                    assignment.num_faces, len(outliers), rms, change,
                    final_report.rms["dTP"] * o_adj.sigma_dtp,
                    np.sqrt(final_report.sigma0_squared), value)
        previous_rms = rms
        if best is None or value <= best[0]:
            best = (value, iteration, None, assignment, current)
        elif value > best[0] + o_w.divergence_tolerance:
            # The hybrid solve moved the block away from the model: go back to the best
            # iterate and stop.
            diverged = (f"objective {value:.3f} in iteration {iteration} against "
                        f"{best[0]:.3f} in iteration {best[1]}")
            logger.warning("refine diverged (%s); the best iterate is kept", diverged)
            break
        if best[1] == iteration:
            best = (value, iteration, pycolmap.Reconstruction(rec), assignment, current)
        if change < o_w.convergence_rms_change:
            break
    bar.close()
    if diverged is not None and best is not None and best[2] is not None:
        _, _, rec, assignment, current = best
        last = None
    if last is None:  # back to the best iterate, or the last iteration was undone
        last = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                             robust_planes=False, current=current, baselines=baselines)
        report = last.solve()
        current = _current_from(current, last)
        if not iterations:
            iterations.append(IterationRecord(len(iterations), threshold,
                                              assignment.num_assigned, assignment.num_faces,
                                              dict(assignment.rejected_faces), 0, None, report,
                                              float("inf")))

    from .precision import final_solve_in_refine, precision_after_refine

    vce = None
    if last.blocks.faces.size:  # VCE and/or estimated generalisation offsets, if asked
        last, vce = final_solve_in_refine(rec, store, assignment, priors, options, current,
                                          last)
        current = _current_from(current, last)
    point_ids, points = tie_points(rec, exclude_point_ids)
    observability = assigned_observability(points, assignment, current, priors, rec, options)
    quality = measure_quality(rec, gnss_only, surface, priors, assignment, last, observability,
                              points, options, diverged, scale_sigma)
    logger.info("datum fixed by: %s", datum_line(observability))
    logger.info(quality.line())
    precision = evaluation = None
    refined = rec
    if quality.verdict == "failed" and gnss_only is not None:
        # Never hand back a block worse than GNSS alone: the result is the GNSS-only one.
        rec, sim3 = gnss_only, gnss_only_sim3
    else:
        precision = precision_after_refine(last, options.precision, checkpoint_observations)
    if checkpoints is not None and checkpoint_observations is not None:
        from .evaluate import evaluate_with_precision

        evaluation = evaluate_with_precision(rec, checkpoints, checkpoint_observations,
                                             store.origin, precision)
    blocks = last.blocks
    timer.update(assignment=assign_seconds, hybrid_solves=solve_seconds,
                 total=time.perf_counter() - timer["start"])
    del timer["start"]
    return RefineResult(
        reconstruction=rec, store=store, adjusted_store=current, assignment=assignment,
        plane_faces=blocks.faces, plane_normals=blocks.normal_array,
        plane_offsets=blocks.offset_array, input_to_local=sim3, georegistration_rms=geo_rms,
        step2=report2, step2_eliminated=eliminated2, iterations=iterations, options=options,
        warnings=warnings, seconds=timer, gnss_priors=priors, precision=precision,
        variance_components=vce, checkpoints=evaluation, gnss_only=gnss_only,
        quality=quality, observability=observability,
        observability_before=observability_before, refined=refined,
        datum_cues=details.get("cues", {}),
        coarse_alignment=coarse.todict() if coarse is not None else None)


#: A solve that changes the block's scale from the GNSS-only one by more than this many GNSS
#: scale sigmas is undone and repeated with the scale held (BaselinePriors): GNSS puts the
#: true scale within three sigma, so further is the point-to-plane residuals shrinking.
SCALE_RUNAWAY_SIGMAS = 3.0


def scale_change(reference: pycolmap.Reconstruction, rec: pycolmap.Reconstruction,
                 image_ids) -> float:
    """Relative scale of the camera centres of `image_ids` in `rec` against `reference`
    (similarity fit) - 1."""
    ids = [int(i) for i in image_ids]
    a = np.array([reference.image(i).projection_center() for i in ids])
    b = np.array([rec.image(i).projection_center() for i in ids])
    similarity = pycolmap.estimate_sim3d(a, b)
    return float(similarity.scale) - 1.0 if similarity is not None else 0.0


#: Where the planes do not determine the scale, the baseline priors hold the GNSS-only
#: block's scale this many times tighter than GNSS's own scale sigma: point-to-plane residuals
#: shrink with the block (a similarity changes no reprojection error), and 16 GNSS priors do
#: not hold 2000 of them (a real drive past one facade row: -41 % with GNSS sigma 3 m).
BASELINE_TIGHTENING = 10.0


def baseline_priors(gnss_only: pycolmap.Reconstruction, priors: GNSSPriors,
                    scale_sigma: float) -> BaselinePriors:
    """Pairs of GNSS images half the block apart along its main axis, with their distances in
    the GNSS-only adjustment; together they hold its scale to scale_sigma / BASELINE_TIGHTENING."""
    ids = np.asarray(priors.image_ids)
    centres = np.array([gnss_only.image(int(i)).projection_center() for i in ids])
    axis = np.linalg.svd(centres - centres.mean(0))[2][0]
    order = ids[np.argsort((centres - centres.mean(0)) @ axis)]
    half = len(order) // 2
    pairs = np.column_stack([order[:half], order[len(order) - half:]])
    lengths = np.array([np.linalg.norm(gnss_only.image(int(a)).projection_center()
                                       - gnss_only.image(int(b)).projection_center())
                        for a, b in pairs])
    relative = scale_sigma / BASELINE_TIGHTENING * np.sqrt(max(len(pairs), 1))
    logger.info("the planes do not fix the block's scale: %d baseline priors hold the GNSS-only "
                "scale (sigma %.2g)", len(pairs), scale_sigma / BASELINE_TIGHTENING)
    return BaselinePriors(pairs, lengths, np.maximum(lengths * relative, 1e-6))


def datum_line(observability_dict: dict) -> str:
    """'E planes (0.09 m), ..., U gnss (0.79 m), ...' for the log and the console."""
    parts = []
    for name, row in observability_dict.items():
        unit = " deg" if name.startswith("rotation") else "" if name == "scale" else " m"
        sigma = f" ({row['sigma']:.3g}{unit})" if row["sigma"] is not None else ""
        parts.append(f"{name} {row['source']}{sigma}")
    return ", ".join(parts)


def assigned_observability(points: np.ndarray, assignment: Assignment, store: PlaneStore,
                           priors: GNSSPriors | None, rec: pycolmap.Reconstruction,
                           options: RefineOptions) -> dict:
    """quality.observability for the assigned tie points and the GNSS of `rec`."""
    from .options import GENERALISATION_SIGMA
    from .quality import observability

    assigned = assignment.assigned
    faces = assignment.face_index[assigned]
    sigma_gen = options.adjustment.sigma_generalisation or GENERALISATION_SIGMA
    return observability(points[assigned], store.normals[faces], faces,
                         priors.observed_points(rec) if priors is not None else None,
                         priors.sigmas if priors is not None else None,
                         options.adjustment.sigma_dtp, sigma_gen)


def measure_quality(rec: pycolmap.Reconstruction, gnss_only: pycolmap.Reconstruction | None,
                    surface, priors: GNSSPriors | None, assignment: Assignment, last,
                    observability_dict: dict, points: np.ndarray, options: RefineOptions,
                    diverged: str | None, scale_sigma: float | None):
    """The figures of the quality gate (quality.quality_verdict) and the verdict; `points`
    are the refined tie points that could be assigned (check points left out)."""
    from .quality import (QualityThresholds, gnss_scatter, planes_fix, quality_verdict,
                          rests_on_one_plane)

    thresholds = QualityThresholds()
    metrics: dict = {
        "assigned_share": assignment.num_assigned / max(len(points), 1),
        "num_assigned_points": assignment.num_assigned, "num_planes": assignment.num_faces,
        "near_share": float(np.mean(surface(points) < thresholds.near_distance))
        if len(points) else 0.0,
        "near_share_gnss_only": None, "diverged": diverged,
        "planes_fix": planes_fix(observability_dict),
        "one_plane": rests_on_one_plane(observability_dict),
    }
    shift_sigmas = [observability_dict.get(k, {}).get("sigma") for k in ("E", "N", "U")]
    if all(v is not None for v in shift_sigmas):
        metrics["position_sigma_m"] = float(np.linalg.norm(shift_sigmas))
    normalised = last.residuals.get("dTP", np.zeros(0))
    if len(normalised):
        dtp = float(np.sqrt(np.mean(normalised ** 2)))
        metrics["dtp_rms_sigmas"] = float(dtp)
        metrics["dtp_rms_m"] = float(dtp) * options.adjustment.sigma_dtp
    from .coarse_alignment import wall_points

    walls = wall_points(points) if len(points) else np.zeros((0, 3))
    metrics["num_wall_points"] = len(walls)
    if len(walls) >= options.assignment.min_points_per_plane:
        metrics["wall_near_share"] = float(np.mean(surface(walls) < thresholds.near_distance))
    if gnss_only is not None and priors is not None:
        _, before = tie_points(gnss_only)
        metrics["near_share_gnss_only"] = (float(np.mean(surface(before)
                                                         < thresholds.near_distance))
                                           if len(before) else 0.0)
        # Where GNSS observed: elsewhere (GNSS for part of the block) the GNSS-only result is
        # an extrapolation that the model is there to correct.
        ids = [int(i) for i in priors.image_ids]
        a = np.array([gnss_only.image(i).projection_center() for i in ids])
        b = np.array([rec.image(i).projection_center() for i in ids])
        sigma = np.median(priors.sigmas, axis=0)
        mean_shift = (b - a).mean(0)
        metrics["shift_m"] = float(np.linalg.norm(mean_shift))
        metrics["shift_enu_m"] = mean_shift.tolist()
        metrics["shift_sigmas"] = float(np.linalg.norm(mean_shift / sigma))
        if scale_sigma:
            change = scale_change(gnss_only, rec, ids)
            metrics["scale_change"] = change
            metrics["scale_change_sigmas"] = abs(np.log1p(change)) / scale_sigma
        before_scatter = gnss_scatter(priors.observed_points(gnss_only), priors.positions,
                                      priors.sigmas)
        after_scatter = gnss_scatter(priors.observed_points(rec), priors.positions,
                                     priors.sigmas)
        metrics["gnss_scatter"] = after_scatter
        metrics["gnss_scatter_ratio"] = after_scatter / max(before_scatter, 1e-9)
    return quality_verdict(metrics, thresholds)


def align_block_to_planes(rec: pycolmap.Reconstruction, point_ids: np.ndarray,
                          points: np.ndarray, assignment: Assignment, store: PlaneStore,
                          priors: GNSSPriors | None, threshold: float, options: RefineOptions,
                          *, objective: BlockObjective | None = None,
                          scale_sigma: float | None = None, weights: np.ndarray | None = None
                          ) -> tuple[pycolmap.Sim3d, np.ndarray, Assignment]:
    """Refine's initial alignment rounds: fit a similarity to the assigned planes, move `rec`
    by it, assign again at `threshold`, until a fit moves the tie points by less than
    `alignment_tolerance` on average. With an `objective`, a round that does not lower it is
    undone and ends the rounds. Returns the total similarity and the moved `points` (same ids)
    with their last assignment."""
    total = pycolmap.Sim3d()
    value = objective(rec) if objective is not None else None
    for _ in range(options.workflow.alignment_rounds):
        move, moved = align_to_planes(rec, points, assignment, store, priors, options.adjustment,
                                      scale_sigma)
        if objective is not None:
            new_value = objective(rec, move)
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


def align_to_planes(rec: pycolmap.Reconstruction, points: np.ndarray, assignment: Assignment,
                    store: PlaneStore, priors: GNSSPriors | None, options,
                    scale_sigma: float | None = None) -> tuple[pycolmap.Sim3d, np.ndarray]:
    """The similarity that best puts the assigned tie points on their planes (and the block on
    GNSS, with the adjustment's weights; see initial_alignment), and all `points` moved by it.
    `scale_sigma`: how far (relative) GNSS lets the scale change."""
    from .initial_alignment import similarity_to_planes

    assigned = assignment.assigned
    faces = assignment.face_index[assigned]
    gnss = {}
    if priors is not None:
        gnss = dict(antennas=priors.observed_points(rec), gnss=priors.positions,
                    gnss_sigmas=priors.sigmas)
    result = similarity_to_planes(points[assigned], store.normals[faces], store.offsets[faces],
                                  options.sigma_dtp, options.plane_loss_scale,
                                  scale_sigma=scale_sigma, **gnss)
    matrix = np.asarray(result.sim3.matrix())
    moved = points @ matrix[:, :3].T + matrix[:, 3]
    logger.info("block moved onto the planes of its %d assigned tie points by a similarity "
                "(%d iterations): mean shift %.2f m, scale %.5f, inlier distance RMS %.3f -> "
                "%.3f m", int(assigned.sum()), result.iterations,
                float(np.linalg.norm(moved - points, axis=1).mean()), result.sim3.scale,
                result.rms_before, result.rms_after)
    return result.sim3, moved


def _current_from(current: PlaneStore, problem: HybridProblem) -> PlaneStore:
    """The model state after a solve: adjusted vertices, planes refitted to them."""
    blocks = problem.blocks
    if len(blocks.vertex_ids) == 0:
        return current
    vertices = current.vertices.copy()
    vertices[blocks.vertex_ids] = blocks.vertex_array
    return current.with_vertices(vertices)


# -- CLI entry: read inputs, refine, write outputs ------------------------------------------------

#: Metres around the GNSS positions in which city model buildings are read.
GNSS_READ_MARGIN = 250.0


def peek_crs(citymodel, assumed: str | None = None):
    """The CRS of the first city model file from its first srsName / referenceSystem, read
    from the file's head only (so GNSS can bound what is read of a large model); None when
    the head names none (the model is then read whole first)."""
    import re

    from .crs import resolve_crs, user_crs
    from .read_city_model import city_model_files

    files = city_model_files(citymodel)
    with open(files[0], "rb") as f:
        head = f.read(1 << 20).decode("utf-8", errors="ignore")
    found = re.search(r'srsName="([^"]+)"', head) or \
        re.search(r'"referenceSystem"\s*:\s*"([^"]+)"', head)
    if found:
        info = resolve_crs(found.group(1), path=files[0])
        return info if info.is_projected else None
    return user_crs(assumed) if assumed else None


def read_reconstruction(path: str | Path) -> pycolmap.Reconstruction:
    from .errors import InputError
    from .read_colmap import read_model

    path = Path(path)
    if not path.is_dir():
        raise InputError("COLMAP model directory does not exist", path)
    if not any((path / f"cameras.{ext}").exists() for ext in ("bin", "txt")):
        raise InputError("not a COLMAP model directory (no cameras.bin or cameras.txt)", path)
    rec = read_model(path)  # checks the files first: damage gets a message naming the file
    if rec.num_reg_images() < 3:
        raise InputError(f"the model has only {rec.num_reg_images()} registered images", path)
    return rec


def read_gnss(*, database=None, gnss=None, gnss_crs=None, exif=None, target_crs,
              default_sigma=(3.0, 3.0, 5.0)):
    """GNSS from exactly one source: COLMAP database pose priors, a text file or EXIF."""
    from .errors import InputError
    from . import read_gnss as rg

    given = [name for name, value in (("--database", database), ("--gnss", gnss),
                                      ("--exif", exif)) if value]
    if len(given) > 1:
        raise InputError(f"give one GNSS source, not {' and '.join(given)}")
    if database:
        return rg.read_gnss_database(database, target_crs, default_sigma)
    if gnss:
        if not gnss_crs:
            raise InputError("--gnss needs --gnss_crs (e.g. EPSG:4979 or EPSG:25832+7837)", gnss)
        return rg.read_gnss_text(gnss, gnss_crs, target_crs, default_sigma)
    if exif:
        return rg.read_gnss_exif(exif, target_crs, default_sigma)
    return None


def main(input_path, citymodel, output_path, *, database=None, gnss=None, gnss_crs=None,
         exif=None, initial_transform=None, preset="generalised", options_file=None,
         lod=2, model_crs=None, target_crs=None, output_type="bin", output_frame="crs",
         progress=True, precision=None, gnss_height_offset=None, lever_arm=None,
         checkpoints=None, checkpoint_observations=None, sigma_generalisation=None,
         variance_components=None, assignment=None) -> RefineResult:
    """`colmap-citymodel refine`: read everything, refine, write `output_path` atomically.
    `checkpoints` / `checkpoint_observations`: files (evaluate's formats) of check points that
    are evaluated at the end (Delta, sigma; report.json `checkpoints`)."""
    from .crs import user_crs
    from .georegister import read_initial_transform
    from .read_city_model import read_city_model
    from .write_output import atomic_directory, write_refined

    options = (RefineOptions.from_toml(options_file, preset) if options_file
               else RefineOptions.preset(preset))
    if precision is not None:  # --precision on/off/auto overrides the options file
        options.precision.covariances = precision
    if sigma_generalisation is not None:
        options.adjustment.sigma_generalisation = float(sigma_generalisation)
    if variance_components is not None:
        options.precision.variance_components = bool(variance_components)
    if assignment is not None:  # --assignment overrides the options file
        options.assignment.method = assignment
    cp_known = cp_observations = None
    if (checkpoints is None) != (checkpoint_observations is None):
        from .errors import InputError

        raise InputError("give --checkpoints and --checkpoint_observations together")
    if checkpoints is not None:
        from .evaluate import read_checkpoint_observations, read_checkpoints

        cp_known = read_checkpoints(checkpoints)
        cp_observations = read_checkpoint_observations(checkpoint_observations)
    # Fail on a taken output directory before the expensive work.
    with atomic_directory(output_path):
        pass
    Path(output_path).rmdir()
    reconstruction = read_reconstruction(input_path)
    crs = user_crs(target_crs) if target_crs else peek_crs(citymodel, model_crs)
    observations = None
    if crs is not None:
        observations = read_gnss(database=database, gnss=gnss, gnss_crs=gnss_crs, exif=exif,
                                 target_crs=crs, default_sigma=options.adjustment.sigma_gnss)
    bbox = None
    if observations is not None:
        bbox = np.array([observations.positions.min(0) - GNSS_READ_MARGIN,
                         observations.positions.max(0) + GNSS_READ_MARGIN])
    try:
        store = read_city_model(citymodel, lod=lod, crs=model_crs, target_crs=target_crs,
                                bbox_crs=bbox)
    except NoOverlapError as error:
        raise NoOverlapError(
            f"the city model does not overlap the GNSS positions ({observations.source}, "
            f"{GNSS_READ_MARGIN:.0f} m margin): {error.message}; check the GNSS CRS and the "
            "model tiles", error.path) from None
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
    result = refine(reconstruction, store, observations, options,
                    initial_transform=transform, progress=progress, checkpoints=cp_known,
                    checkpoint_observations=cp_observations)
    inputs = {"input_path": str(input_path), "citymodel": [str(p) for p in np.atleast_1d(citymodel)],
              "gnss_source": observations.source if observations is not None else None,
              "initial_transform": str(initial_transform) if initial_transform else None,
              "preset": preset, "options_file": str(options_file) if options_file else None}
    write_refined(result, output_path, output_type=output_type, output_frame=output_frame,
                  inputs=inputs)
    last = result.iterations[-1]
    # s0 of the final solve: the variance-component re-solve when there was one.
    s0 = (result.precision.variance.sigma0 if result.precision is not None
          else np.sqrt(last.final.sigma0_squared))
    if result.handed_back == "gnss_only":
        print(f"the city model could not help: wrote the GNSS-only adjustment of "
              f"{result.reconstruction.num_reg_images()} images")
    elif result.quality.verdict == "failed":
        print("the city model could not help, and without GNSS there is no other result: the "
              "refined block is written, but do not trust it")
    else:
        print(f"refined {result.reconstruction.num_reg_images()} images, "
              f"{result.reconstruction.num_points3D()} points; {last.num_assigned} tie points "
              f"on {last.num_faces} planes; s0 {s0:.3f}")
    print(result.quality.line())
    if result.observability:
        print(f"datum fixed by: {datum_line(result.observability)}")
    print(f"output: {output_path} (COLMAP model in {store.crs.label}"
          f"{'' if output_frame == 'crs' else ' minus origin'}, report.md, assignments.ply)")
    return result
