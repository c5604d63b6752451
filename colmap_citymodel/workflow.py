"""The refine step (`colmap_citymodel.refine`): global workflow of Unger Table 3 with direct
assignment (a). A sliding-window workflow (Unger 3.3.2) will sit beside it.

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
from typing import TYPE_CHECKING

import numpy as np
import pycolmap
from tqdm import tqdm

from .assign_planes import Assignment, assign, filter_faces, next_threshold
from .errors import DatumError, GeoregistrationError, GNSSError, NoOverlapError
from .hybrid_adjustment import GNSSPriors, HybridProblem, SolveReport
from .options import RefineOptions
from .plane_store import PlaneStore

if TYPE_CHECKING:
    from .evaluate import CheckpointEvaluation
    from .precision import PrecisionResult, VarianceComponents

logger = logging.getLogger("colmap_citymodel.workflow")

# Two plane normals closer than this (either sign) count as the same orientation for the datum.
SAME_ORIENTATION_DEG = 10.0
# A direction whose weight in sum(n n^T) is below this fraction of the largest is "weak".
WEAK_DIRECTION_RATIO = 0.05
# Tie points this close to a model face count as "on the model" when searching the roll of a
# straight flight line.
SEARCH_DISTANCE = 1.0


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


def georegister(rec: pycolmap.Reconstruction, store: PlaneStore, gnss, initial_transform
                ) -> tuple[pycolmap.Sim3d, GNSSPriors | None, float | None]:
    """Bring the reconstruction into the store's local frame; return the applied similarity."""
    from .georegister import estimate_georegistration
    from .read_gnss import match_to_reconstruction

    priors = None
    rms = None
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
        sim3, rms = result.sim3, result.rms
        logger.info("georegistration to %d GNSS positions: scale %.4f, RMS %.2f m, %d inliers",
                    len(priors), sim3.scale, rms, int(np.count_nonzero(result.inlier_mask)))
    else:
        raise GeoregistrationError(
            "no GNSS positions and no initial transform: give --database/--gnss/--exif or "
            "--initial_transform")
    rec.transform(sim3)
    return sim3, priors, rms


def _lateral_spread(centres: np.ndarray) -> float:
    """Standard deviation (m) of the camera centres across their main direction."""
    singular = np.linalg.svd(centres - centres.mean(0), compute_uv=False)
    return float(singular[1] / np.sqrt(len(centres)))


def roll_about_flight_line(rec: pycolmap.Reconstruction, store: PlaneStore,
                           step_deg: float = 1.0, max_points: int = 5000) -> pycolmap.Sim3d:
    """The rotation about the flight line that best puts the tie points on the model.

    A flight along one street leaves the 7-parameter fit to GNSS almost free to rotate about
    the flight line (the centres deviate from a line by less than the GNSS noise), and
    side-looking images carry no roll cue either (that rotation is their tilt). The model does:
    among the rotations about the line through the centres' centroid, take the one that puts
    the most tie points within `SEARCH_DISTANCE` of a model face (a subsample of points, a
    `step_deg` grid, then a finer grid around the best). Returns it as a Sim3d (identity when
    no angle is clearly better than none).
    """
    centres = camera_centres(rec)
    centroid = centres.mean(0)
    direction = np.linalg.svd(centres - centroid)[2][0]
    _, points = tie_points(rec)
    rng = np.random.default_rng(0)
    if len(points) > max_points:
        points = points[rng.choice(len(points), max_points, replace=False)]
    points = points - centroid

    def rotation(theta: float) -> np.ndarray:
        return np.asarray(pycolmap.Rotation3d(direction * theta).matrix())

    def score(theta: float) -> int:
        moved = points @ rotation(theta).T + centroid
        faces, _ = store.closest_faces(moved, max_distance=SEARCH_DISTANCE, margin=0.5)
        return int(np.count_nonzero(faces >= 0))

    coarse = np.radians(np.arange(-180.0, 180.0, step_deg))
    scores = np.array([score(t) for t in coarse])
    best = coarse[int(np.argmax(scores))]
    fine = best + np.radians(np.linspace(-step_deg, step_deg, 11))
    fine_scores = np.array([score(t) for t in fine])
    theta = float(fine[int(np.argmax(fine_scores))])
    if fine_scores.max() <= 1.2 * score(0.0):
        return pycolmap.Sim3d()
    matrix = rotation(theta)
    logger.info("flight line nearly straight: rotated the block by %.1f deg about it to fit the "
                "model (%d of %d sampled tie points near a face, %d before)",
                np.degrees(theta), fine_scores.max(), len(points), score(0.0))
    return pycolmap.Sim3d(1.0, pycolmap.Rotation3d(matrix), centroid - matrix @ centroid)


def refine(reconstruction: pycolmap.Reconstruction, city_model: PlaneStore, gnss=None,
           options: RefineOptions | None = None, *, initial_transform: pycolmap.Sim3d | None = None,
           exclude_point_ids: set[int] | None = None, progress: bool = True,
           checkpoints: dict | None = None, checkpoint_observations: list | None = None
           ) -> RefineResult:
    """Georeference `reconstruction` and adjust it together with `city_model`.

    `gnss` is a `read_gnss.GNSSObservations` (model CRS) or None; `initial_transform` maps the
    input frame to model CRS coordinates (used instead of a GNSS similarity when given).
    `exclude_point_ids` are never assigned to planes (e.g. check points in the model).
    The input reconstruction is not modified; the result holds a refined copy.
    `checkpoints` ({id: XYZ} model CRS) and `checkpoint_observations` ([(image, id, x, y)],
    evaluate.read_*) are only evaluated at the end (Delta, and sigma when covariances are on).
    """
    options = options or RefineOptions()
    timer = {"start": time.perf_counter()}
    rec = pycolmap.Reconstruction(reconstruction)
    sim3, priors, geo_rms = georegister(rec, city_model, gnss, initial_transform)
    store = crop_to_reconstruction(city_model, rec, options.workflow.overlap_margin)
    logger.info("model: %d faces, %d vertices near the reconstruction", len(store.faces),
                len(store.vertices))
    timer["georegistration"] = time.perf_counter() - timer["start"]

    warnings: list[str] = []
    report2, eliminated2 = step2_bundle_adjustment(rec, priors, options)
    if priors is not None and initial_transform is None and \
            _lateral_spread(camera_centres(rec)) < float(np.median(priors.sigmas[:, :2])):
        # After step 2: GNSS alone has moved the block freely about the flight line there.
        roll = roll_about_flight_line(rec, store)
        rec.transform(roll)
        sim3 = roll * sim3
    timer["step2"] = time.perf_counter() - timer["start"] - timer["georegistration"]

    o_a, o_adj, o_w = options.assignment, options.adjustment, options.workflow
    current = store
    threshold = o_a.max_threshold
    assignment: Assignment | None = None
    iterations: list[IterationRecord] = []
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
        if iteration == 0 and assignment.num_assigned:
            # Initial values: move the block as a whole onto its planes first, so that the
            # adjustment is left with the block's deformation. As in ICP: fit, assign again,
            # fit again. Where GNSS is missing or drifts (Scn4), the block's far end starts
            # metres off and its first assignments are partly wrong; each round gets more
            # right (long Scn4: camera centres 5.5 m -> 4.7, 2.6, 1.1, 0.7 ... 0.58 m).
            t_align = time.perf_counter()
            move, points, assignment = align_block_to_planes(
                rec, point_ids, points, assignment, current, priors, threshold, options)
            sim3 = move * sim3
            timer["initial_alignment"] = time.perf_counter() - t_align
            t0 += timer["initial_alignment"]
        assign_seconds += time.perf_counter() - t0
        if iteration == 0:
            warnings += check_datum(store, assignment, priors is not None)
        elif assignment.num_assigned == 0 and priors is None:
            raise DatumError("no tie point could be assigned to a model plane and there is no "
                             "GNSS: the datum is undefined", store.source)

        t1 = time.perf_counter()
        robust_report = None
        outliers = np.zeros(0, np.int64)
        rejected = dict(assignment.rejected_faces)
        if iteration > 0:
            # Förstner-Wrobel only where needed: with the original weights first; robust
            # weighting and elimination follow only if some |v| / sigma exceeds the threshold.
            final = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                                  robust_planes=False, current=current)
            final_report = final.solve()
            normalised = final.residuals["dTP"]
            needs_robust = bool(np.any(np.abs(normalised) > o_adj.elimination_threshold))
        else:
            needs_robust = True
        if needs_robust:
            robust = HybridProblem(rec, store, assignment, priors, o_adj, robust_images=False,
                                   robust_planes=True, current=current)
            robust_report = robust.solve()
            normalised = robust.residuals["dTP"]
            outliers = robust.point_ids[np.abs(normalised) > o_adj.elimination_threshold]
            assignment = assignment.without(np.isin(assignment.point_ids, outliers))
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
                    "eliminated, RMS %.4f (relative change %.1e), dTP RMS %.3f m, s0 %.3f",
                    iteration, threshold, assignment.num_assigned, assignment.num_faces,
                    len(outliers), rms, change,
                    final_report.rms["dTP"] * o_adj.sigma_dtp,
                    np.sqrt(final_report.sigma0_squared))
        previous_rms = rms
        if change < o_w.convergence_rms_change:
            break
    bar.close()

    from .precision import final_solve_in_refine, precision_after_refine

    vce = None
    if last.blocks.faces.size:  # VCE and/or estimated generalisation offsets, if asked
        last, vce = final_solve_in_refine(rec, store, assignment, priors, options, current,
                                          last)
        current = _current_from(current, last)
    precision = precision_after_refine(last, options.precision, checkpoint_observations)
    evaluation = None
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
        variance_components=vce, checkpoints=evaluation)


def align_block_to_planes(rec: pycolmap.Reconstruction, point_ids: np.ndarray,
                          points: np.ndarray, assignment: Assignment, store: PlaneStore,
                          priors: GNSSPriors | None, threshold: float, options: RefineOptions
                          ) -> tuple[pycolmap.Sim3d, np.ndarray, Assignment]:
    """Refine's initial alignment rounds: fit a similarity to the assigned planes, move `rec`
    by it, assign again at `threshold`, until a fit moves the tie points by less than
    `alignment_tolerance` on average. Returns the total similarity and the moved `points`
    (same ids) with their last assignment."""
    total = pycolmap.Sim3d()
    for _ in range(options.workflow.alignment_rounds):
        move, moved = align_to_planes(rec, points, assignment, store, priors, options.adjustment)
        rec.transform(move)
        total = move * total
        mean_shift = float(np.linalg.norm(moved - points, axis=1).mean())
        points = moved
        assignment = assign(points, point_ids, store, threshold, options.assignment)
        if mean_shift < options.workflow.alignment_tolerance or not assignment.num_assigned:
            break
    return total, points, assignment


def align_to_planes(rec: pycolmap.Reconstruction, points: np.ndarray, assignment: Assignment,
                    store: PlaneStore, priors: GNSSPriors | None, options
                    ) -> tuple[pycolmap.Sim3d, np.ndarray]:
    """The similarity that best puts the assigned tie points on their planes (and the block on
    GNSS, with the adjustment's weights; see initial_alignment), and all `points` moved by it."""
    from .initial_alignment import similarity_to_planes

    assigned = assignment.assigned
    faces = assignment.face_index[assigned]
    gnss = {}
    if priors is not None:
        gnss = dict(antennas=priors.observed_points(rec), gnss=priors.positions,
                    gnss_sigmas=priors.sigmas)
    result = similarity_to_planes(points[assigned], store.normals[faces], store.offsets[faces],
                                  options.sigma_dtp, options.plane_loss_scale, **gnss)
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

    path = Path(path)
    if not path.is_dir():
        raise InputError("COLMAP model directory does not exist", path)
    if not any((path / f"cameras.{ext}").exists() for ext in ("bin", "txt")):
        raise InputError("not a COLMAP model directory (no cameras.bin or cameras.txt)", path)
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as error:  # pycolmap raises plain RuntimeErrors for broken files
        raise InputError(f"cannot read the COLMAP model: {error}", path) from None
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
         variance_components=None) -> RefineResult:
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
    print(f"refined {result.reconstruction.num_reg_images()} images, "
          f"{result.reconstruction.num_points3D()} points; {last.num_assigned} tie points on "
          f"{last.num_faces} planes; s0 {s0:.3f}")
    print(f"output: {output_path} (COLMAP model in {store.crs.label}"
          f"{'' if output_frame == 'crs' else ' minus origin'}, report.md, assignments.ply)")
    return result
