"""The refine step: global workflow of Unger Table 3 with direct assignment (a).

1. SfM (COLMAP, done before) + 7-parameter similarity to GNSS (or a given initial transform);
2. bundle adjustment with GNSS priors and no model, robust on image observations; image
   observations with normalised residual > 3 eliminated;
3. assign tie points to model planes;
4. hybrid bundle adjustment, robust on f_dTP; fictitious observations with normalised residual
   > 3 eliminated and the adjustment repeated with the original weights.
Steps 3-4 repeat (assignments recomputed from the current estimate every iteration; vertex-plane
relations never change) until the relative change of the RMS of normalised residuals < 1e-5
or 10 iterations.

Everything happens in the plane store's local frame (model CRS minus `store.origin`).
`refine()` works on pycolmap objects in memory and never modifies its inputs; `main()` is the
CLI's entry: read inputs, refine, write outputs atomically.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from .assign_planes import Assignment, assign, filter_faces, next_threshold
from .errors import DatumError, GeoregistrationError, NoOverlapError
from .hybrid_adjustment import GNSSPriors, HybridProblem, SolveReport
from .options import RefineOptions
from .plane_store import PlaneStore

logger = logging.getLogger("colmap_citymodel.refine")

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
    robust: SolveReport
    final: SolveReport
    relative_change: float

    def todict(self) -> dict:
        return {
            "iteration": self.iteration, "threshold": self.threshold,
            "num_assigned_points": self.num_assigned, "num_planes": self.num_faces,
            "rejected_planes": self.rejected_faces, "num_eliminated_dTP": self.num_eliminated,
            "robust_solve": self.robust.todict(), "solve": self.final.todict(),
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
    cropped = store.subset_bbox(lower, upper)
    if len(cropped.faces) == 0:
        raise NoOverlapError(
            "the city model does not overlap the georegistered reconstruction: model bbox "
            f"{_fmt_box(store.bbox_crs)} vs reconstruction bbox "
            f"{_fmt_box(np.array([lower, upper]) + store.origin)} (model CRS); check the CRS "
            "of the GNSS positions and the model", store.source)
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


def georegister(rec: pycolmap.Reconstruction, store: PlaneStore, gnss, initial_transform
                ) -> tuple[pycolmap.Sim3d, GNSSPriors | None, float | None]:
    """Bring the reconstruction into the store's local frame; return the applied similarity."""
    from .georegister import estimate_georegistration
    from .read_gnss import match_to_reconstruction

    priors = None
    rms = None
    if gnss is not None:
        image_ids, positions, sigmas = match_to_reconstruction(gnss, rec, store.origin)
        priors = GNSSPriors(np.asarray(image_ids), np.asarray(positions), np.asarray(sigmas))
    if initial_transform is not None:
        # The given transform maps the input frame to model CRS coordinates.
        to_local = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), -store.origin)
        sim3 = to_local * initial_transform
    elif priors is not None:
        result = estimate_georegistration(rec, priors.positions, priors.image_ids)
        sim3, rms = result.sim3, result.rms
        logger.info("georegistration to %d GNSS positions: scale %.4f, RMS %.2f m, %d inliers",
                    len(priors), sim3.scale, rms, int(np.count_nonzero(result.inlier_mask)))
    else:
        raise GeoregistrationError(
            "no GNSS positions and no initial transform: give --database/--gnss/--exif or "
            "--initial_transform")
    rec.transform(sim3)
    return sim3, priors, rms


def refine(reconstruction: pycolmap.Reconstruction, city_model: PlaneStore, gnss=None,
           options: RefineOptions | None = None, *, initial_transform: pycolmap.Sim3d | None = None,
           exclude_point_ids: set[int] | None = None, progress: bool = True) -> RefineResult:
    """Georeference `reconstruction` and adjust it together with `city_model`.

    `gnss` is a `read_gnss.GNSSObservations` (model CRS) or None; `initial_transform` maps the
    input frame to model CRS coordinates (used instead of a GNSS similarity when given).
    `exclude_point_ids` are never assigned to planes (e.g. check points in the model).
    The input reconstruction is not modified; the result holds a refined copy.
    """
    options = options or RefineOptions()
    timer = {"start": time.perf_counter()}
    rec = pycolmap.Reconstruction(reconstruction)
    sim3, priors, geo_rms = georegister(rec, city_model, gnss, initial_transform)
    store = crop_to_reconstruction(city_model, rec, options.workflow.overlap_margin)
    logger.info("model: %d faces, %d vertices near the reconstruction", len(store.faces),
                len(store.vertices))
    timer["georegistration"] = time.perf_counter() - timer["start"]

    report2, eliminated2 = step2_bundle_adjustment(rec, priors, options)
    timer["step2"] = time.perf_counter() - timer["start"] - timer["georegistration"]

    o_a, o_adj, o_w = options.assignment, options.adjustment, options.workflow
    current = store
    threshold = o_a.max_threshold
    assignment: Assignment | None = None
    iterations: list[IterationRecord] = []
    warnings: list[str] = []
    previous_rms = None
    solve_seconds = assign_seconds = 0.0
    last = None
    bar = tqdm(range(o_w.max_iterations), desc="refine", unit="it", disable=not progress)
    for iteration in bar:
        t0 = time.perf_counter()
        point_ids, points = tie_points(rec, exclude_point_ids)
        if assignment is not None:
            # The tie point set does not change inside the loop: same ids in the same order.
            threshold = next_threshold(assignment, points, current, o_a, o_adj.sigma_dtp)
        assignment = assign(points, point_ids, current, threshold, o_a)
        assign_seconds += time.perf_counter() - t0
        if iteration == 0:
            warnings += check_datum(store, assignment, priors is not None)
        elif assignment.num_assigned == 0 and priors is None:
            raise DatumError("no tie point could be assigned to a model plane and there is no "
                             "GNSS: the datum is undefined", store.source)

        t1 = time.perf_counter()
        robust = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                               robust_planes=True, current=current)
        robust_report = robust.solve()
        normalised = robust.group_residuals()["dTP"]
        outliers = robust.point_ids[np.abs(normalised) > o_adj.elimination_threshold]
        assignment = assignment.without(np.isin(assignment.point_ids, outliers))
        rejected = dict(assignment.rejected_faces)
        assignment.face_index = filter_faces(points, assignment.face_index, o_a, rejected)
        assignment.distance[assignment.face_index < 0] = np.nan
        assignment.rejected_faces = rejected
        final = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                              robust_planes=False, current=_current_from(current, robust))
        final_report = final.solve()
        solve_seconds += time.perf_counter() - t1
        current = _current_from(current, final)
        last = final

        rms = final_report.rms_total
        change = abs(previous_rms - rms) / rms if previous_rms else float("inf")
        iterations.append(IterationRecord(iteration, threshold, assignment.num_assigned,
                                          assignment.num_faces, rejected, len(outliers),
                                          robust_report, final_report, change))
        bar.set_postfix(points=assignment.num_assigned, planes=assignment.num_faces,
                        rms=f"{rms:.4f}")
        logger.info("iteration %d: threshold %.2f m, %d points on %d planes, %d f_dTP "
                    "eliminated, RMS %.4f, dTP RMS %.3f m, s0 %.3f", iteration, threshold,
                    assignment.num_assigned, assignment.num_faces, len(outliers), rms,
                    final_report.rms["dTP"] * o_adj.sigma_dtp,
                    np.sqrt(final_report.sigma0_squared))
        previous_rms = rms
        if change < o_w.convergence_rms_change:
            break
    bar.close()

    blocks = last.blocks
    timer.update(assignment=assign_seconds, hybrid_solves=solve_seconds,
                 total=time.perf_counter() - timer["start"])
    del timer["start"]
    return RefineResult(
        reconstruction=rec, store=store, adjusted_store=current, assignment=assignment,
        plane_faces=blocks.faces, plane_normals=blocks.normal_array,
        plane_offsets=blocks.offset_array, input_to_local=sim3, georegistration_rms=geo_rms,
        step2=report2, step2_eliminated=eliminated2, iterations=iterations, options=options,
        warnings=warnings, seconds=timer)


def _current_from(current: PlaneStore, problem: HybridProblem) -> PlaneStore:
    """The model state after a solve: adjusted vertices, planes refitted to them."""
    blocks = problem.blocks
    if len(blocks.vertex_ids) == 0:
        return current
    vertices = current.vertices.copy()
    vertices[blocks.vertex_ids] = blocks.vertex_array
    return current.with_vertices(vertices)
