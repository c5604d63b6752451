"""The hybrid bundle adjustment: COLMAP's own bundle adjuster plus model residual blocks.

Unger 3.2 (method.md section 2). The problem is the `pyceres.Problem` of
`pycolmap.create_default_ceres_bundle_adjuster` (reprojection errors of all tie points in all
registered images), to which this module adds, through the C++ extension's cost functions:

- f_pos: GNSS projection centre priors on each frame's rig_from_world block (sigma 3, 3, 5 m);
  with a model and `GNSSPriors.offset_axes`, a constant offset of all GNSS positions is one
  more parameter block (1 value for the height, 3 for a bias) with its prior (group "offset");
- f_dTP: distance tie point -> assigned plane = 0 (sigma_dTP 0.2 m, robust in step 4);
- f_dVT: distance vertex -> each plane in the problem it belongs to = 0 (0.01 m);
- f_VT: direct observation of each vertex of those planes (0.01 m: the model is "almost fixed");
  in a problem that releases the model (`releases_model`, adjust.correction_loop's
  CorrectionProblem) the vertices of the faces the images see well get sigma_vt_corrected
  (0.5 m) and keep f_dVT to the given planes of their other faces, which enter as constant
  blocks (adjust.model_correction);
- optionally (generalisation_offsets=True and sigma_generalisation set) a generalisation
  offset o_p per plane in f_dTP, (n.X + d + o_p) / sigma_dTP, with the prior
  o_p ~ N(0, sigma_generalisation^2) (group "gen"). Experimental: see AdjustmentOptions.

Planes are unknowns with 3 degrees of freedom: a unit normal on a sphere manifold plus an
offset, so the signed distance of X is n . X + d. The gauge is left free: GNSS and the model
planes give the datum. Everything is in the plane store's local frame (CRS minus origin).

COLMAP's reprojection residuals are in pixels, weighted as if sigma_image were 1 px; so that the
weights stay right for another sigma_image, our cost functions get their sigmas divided by
sigma_image (the whole objective is then scaled by sigma_image^2, which moves no minimum), and
`group_residuals` divides every group by sigma_image.

Residual order in the problem is the order of addition, group by group (`GROUPS`), which lets
`group_residuals` split `evaluate_residuals` into the observation groups without bookkeeping
inside Ceres. f_dTP comes last: `reassign` removes and adds only the f_dTP blocks of tie points
whose plane changed, and Ceres fills a removed block's place with the last block, which is then
always another f_dTP block (the problem mirrors that order in `point_ids`).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field

import numpy as np
import pyceres
import pycolmap

from .._ext import load_core
from ..assign.assignment import Assignment
from ..block.priors import GNSSPriors
from ..block.reconstruction import position_in_rig
from ..citymodel.ground_faces import terrain_face_sigmas, terrain_mask
from ..citymodel.store import PlaneStore
from ..options import AdjustmentOptions
from .faces import sigma_face_in_use, tilt_axes, tilt_variances
from .marks import active_marks, add_control_marks
from .model_correction import CorrectionSelection, datum_condition, select_corrected_faces

logger = logging.getLogger(__name__)

#: Observation groups in the order their residuals enter the problem. "gen": the priors
#: o_p ~ N(0, sigma_generalisation^2) of the per-plane generalisation offsets (only with
#: AdjustmentOptions.sigma_generalisation; otherwise empty). "scale": baseline lengths that
#: hold the block's scale where the planes do not determine it (BaselinePriors; else empty).
#: "offset": the prior of the GNSS offset (GNSSPriors.offset_prior_sigma; else empty).
#: "pose": the poses of images held from the previous window of a sliding-window adjustment
#: (PosePriors; else empty). "gcp": ground control marks, their surveyed positions and image
#: measurements (adjust.marks; else empty). "dTP" is last so that its blocks can be exchanged
#: (`reassign`).
GROUPS = ("image", "gnss", "dVT", "VT", "gen", "scale", "offset", "pose", "gcp", "dTP")

#: `reassign` rebuilds nothing up to this many changed f_dTP blocks; beyond it the caller
#: builds a new problem (each removal scans Ceres's residual blocks: O(changes x residuals)).
MAX_REASSIGNED = 2000


@dataclass
class BaselinePriors:
    """What is held where the planes cannot fix it (adjust.scale): the GNSS-only block's scale,
    as distances between the projection centres of image pairs held at given lengths, and the
    block's height where the first assignment put it, as one image's projection centre held
    there."""

    image_pairs: np.ndarray  # (K, 2) image ids; K = 0: the scale is not held
    lengths: np.ndarray  # (K,) metres
    sigmas: np.ndarray  # (K,) metres
    level_image: int = -1  # -1: no level held
    level_position: np.ndarray | None = None  # (3,) its projection centre, local frame
    level_sigmas: np.ndarray | None = None  # (3,) metres; LEVEL_FREE on axes not held
    # How much tighter the priors are than GNSS's own sigma of what they hold (the scale, the
    # mean height): the solve needs them so, the covariances count them at GNSS's sigma
    # (`hold_relaxation`).
    tightening: float = 1.0
    level_tightening: float = 1.0

    def __len__(self) -> int:
        return len(self.lengths)

    @property
    def holds_scale(self) -> bool:
        return len(self.lengths) > 0

    @property
    def holds_level(self) -> bool:
        return self.level_image >= 0


#: The prior sigma (m) of BaselinePriors.level_sigmas on an axis that is not held.
LEVEL_FREE = 1e6


@dataclass
class PosePriors:
    """Poses of frames held near given values (a sliding window's images kept from the window
    before, adjust.sliding_window): each pose is observed through three points fixed to its
    rig, the projection centre and the points `lever` metres along the rig's x and y axes,
    each with the prior sigma `sigma_position`; `lever` = sigma_position / sigma_rotation
    makes a rotation of sigma_rotation (radians) move the axis points by one sigma. (The
    three points share the translation, so the position is held to about sigma_position /
    sqrt(3).)"""

    image_ids: np.ndarray  # (K,) one image of each held frame
    rig_from_world: list  # (K,) pycolmap.Rigid3d: the held poses
    sigma_position: float  # metres
    sigma_rotation: float  # radians

    def __len__(self) -> int:
        return len(self.image_ids)

    @property
    def lever(self) -> float:
        return self.sigma_position / self.sigma_rotation


@dataclass
class SolveReport:
    """Figures of one solve, all residuals normalised by their a priori sigma."""

    rms: dict[str, float]  # per group: RMS of normalised residuals (f_dTP: by sigma_dtp)
    count: dict[str, int]  # per group: number of scalar observations
    sum_squares: dict[str, float]  # as the problem weighs them (f_dTP: by their faces' sigmas)
    num_unknowns: int
    ceres_iterations: int
    seconds: float
    termination: str
    linear_solver: str = ""  # Ceres' linear solver used (SPARSE_SCHUR, ITERATIVE_SCHUR, ...)

    @property
    def num_observations(self) -> int:
        return sum(self.count.values())

    @property
    def redundancy(self) -> int:
        return self.num_observations - self.num_unknowns

    @property
    def sigma0_squared(self) -> float:
        r = self.redundancy
        return float(sum(self.sum_squares.values()) / r) if r > 0 else float("nan")

    @property
    def rms_total(self) -> float:
        n = self.num_observations
        return float(np.sqrt(sum(self.sum_squares.values()) / n)) if n else float("nan")

    def todict(self) -> dict:
        return {
            "rms": self.rms, "count": self.count, "num_unknowns": self.num_unknowns,
            "redundancy": self.redundancy, "sigma0": float(np.sqrt(self.sigma0_squared)),
            "ceres_iterations": self.ceres_iterations, "seconds": self.seconds,
            "termination": self.termination, "linear_solver": self.linear_solver,
        }


@dataclass
class PlaneBlocks:
    """The model unknowns in the problem: one normal (3) and offset (1) array per face and one
    array (3) per vertex. Ceres holds raw pointers to these arrays: keep this object alive."""

    faces: np.ndarray
    normals: list[np.ndarray] = field(default_factory=list)
    offsets: list[np.ndarray] = field(default_factory=list)
    vertex_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    vertices: list[np.ndarray] = field(default_factory=list)
    # Per face (1): its generalisation offset o_p; empty in the classical model.
    generalisation: list[np.ndarray] = field(default_factory=list)
    # Face slot -> index in `generalisation` (every slot, or with `face_weighting` "offsets"
    # the model's faces: terrain cells keep their units' weights instead).
    generalisation_slots: dict[int, int] = field(default_factory=dict)
    # Per face (3): the constant point on the plane (the face's vertex centroid) that its
    # offset refers to: the plane is n.(X - reference) + offset = 0 (see offset_array).
    references: list[np.ndarray] = field(default_factory=list)
    # Model correction (a problem with `releases_model`): which faces the solve corrects and
    # which vertices it releases; the given planes of the faces that keep them (constant
    # blocks, one normal and offset each, in the order of `correction.held`).
    correction: CorrectionSelection | None = None
    held_normals: list[np.ndarray] = field(default_factory=list)
    held_offsets: list[np.ndarray] = field(default_factory=list)

    @property
    def normal_array(self) -> np.ndarray:
        return np.array(self.normals).reshape(-1, 3)

    @property
    def offset_array(self) -> np.ndarray:
        """The planes' offsets d in the frame, n.X + d = 0 (the blocks hold them at their
        reference points)."""
        offsets = np.array(self.offsets).reshape(-1)
        if not len(offsets):
            return offsets
        return offsets - np.einsum("ij,ij->i", self.normal_array,
                                   np.array(self.references).reshape(-1, 3))

    @property
    def vertex_array(self) -> np.ndarray:
        return np.array(self.vertices).reshape(-1, 3)

    @property
    def generalisation_array(self) -> np.ndarray:
        """(F,) generalisation offsets o_p (m): the tie points' surface is n.X + d + o_p = 0
        (at the face's reference point, where its tilts do not move it)."""
        return np.array([g[0] for g in self.generalisation], dtype=np.float64)


IMAGE_LOSSES = {"huber": pycolmap.LossFunctionType.HUBER,
                "cauchy": pycolmap.LossFunctionType.CAUCHY}


def bundle_adjustment_options(options: AdjustmentOptions, robust_images: bool
                              ) -> pycolmap.BundleAdjustmentOptions:
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = options.refine_intrinsics
    ba.refine_extra_params = options.refine_intrinsics
    ba.refine_principal_point = False
    ba.refine_sensor_from_rig = False
    ba.print_summary = False
    if robust_images:
        ba.ceres.loss_function_type = IMAGE_LOSSES[options.image_loss]
        ba.ceres.loss_function_scale = options.image_loss_scale
    else:
        ba.ceres.loss_function_type = pycolmap.LossFunctionType.TRIVIAL
    ba.ceres.solver_options.max_num_iterations = options.max_solver_iterations
    sparse = max(int(options.max_images_direct_solver), 1)
    ba.ceres.max_num_images_direct_sparse_cpu_solver = sparse
    # COLMAP requires its dense limit (50) below the sparse one.
    ba.ceres.max_num_images_direct_dense_cpu_solver = min(
        ba.ceres.max_num_images_direct_dense_cpu_solver, sparse - 1)
    ba.ceres.solver_options.num_threads = options.num_threads
    # COLMAP stops on gradient_tolerance only; a relative cost tolerance ends the many
    # near-converged re-solves of the outer loop early without changing the optimum.
    ba.ceres.solver_options.function_tolerance = options.function_tolerance
    ba.ceres.solver_options.initial_trust_region_radius = options.initial_trust_region_radius
    return ba


#: A problem is reused for a new assignment only while no face's f_dTP sigma changes by more
#: than this share (with `face_weighting` "face" it follows the face's number of points).
REWEIGHT_TOLERANCE = 0.1


def slot_factors(assignment: Assignment, faces: np.ndarray) -> np.ndarray | None:
    """The assignment's outlier factor of each face of `faces` (None: none downweighted)."""
    if not assignment.face_factors:
        return None
    return np.array([assignment.face_factors.get(int(f), 1.0) for f in faces])


def face_sigmas(options: AdjustmentOptions, rows: np.ndarray, num_faces: int,
                factors: np.ndarray | None = None, sigma_face: float | None = None
                ) -> np.ndarray:
    """(num_faces,) the sigma (m) of each face's f_dTP: sigma_dtp, or with `face_weighting`
    "face" sqrt(sigma_dtp^2 + n sigma_face^2) times the face's outlier factor (`factors`, 1:
    none), n the face's points (`rows`: the face slot of each assigned point), so that a face's
    points together weigh as one observation of its offset, 1 / (sigma_face^2 + sigma_dtp^2 /
    n); sigma_face: `sigma_face`, else the option's, else DEFAULT_SIGMA_FACE."""
    sigma_face = sigma_face_in_use(options, sigma_face)
    sigmas = np.full(num_faces, float(options.sigma_dtp))
    if options.face_weighting == "face":
        counts = np.bincount(rows, minlength=num_faces)
        sigmas = np.sqrt(options.sigma_dtp ** 2 + counts * sigma_face ** 2)
        if factors is not None:
            sigmas = sigmas * factors
    return sigmas


def tie_sigmas(options: AdjustmentOptions, store: PlaneStore, faces: np.ndarray,
               point_faces: np.ndarray, assignment: Assignment) -> np.ndarray:
    """(len(faces),) the sigma (m) of each face's f_dTP: `face_sigmas` for the model's faces,
    terrain faces as one observation per terrain unit (citymodel.ground_faces); `point_faces`:
    the face of each assigned point."""
    rows = np.searchsorted(faces, point_faces)
    sigmas = face_sigmas(options, rows, len(faces), slot_factors(assignment, faces),
                         assignment.face_sigma)
    return terrain_face_sigmas(store, faces, rows, sigmas, options.sigma_dtp)


#: Generalisation effects per face with `face_weighting` "offsets": its offset (m) and its tilts
#: about its two principal axes (in sigmas of each, adjust.faces.tilt_axes).
EFFECTS = 3

#: Tie points of a face whose images give the frames that measure the block's scale there:
#: enough to find the face's far-apart observers, few enough to stay cheap on large faces.
FRAMES_SAMPLE_POINTS = 200

#: The shortest distance (m) between two frames that measures the block's scale for the
#: tie points' relief (`face_weighting` "offsets"): below it (a camera turning on the spot)
#: the distances stay in metres.
MIN_SCALE_BASE = 1.0

#: The f_dTP sigmas of one face's tie points that include its tilt error
#: (`AdjustmentOptions.face_tilt_weights`) are rounded to steps of this share, so that the
#: points of a face share a few cost functions: 2 % in sigma moves a weight by 4 %, well
#: within what the tilt's own sigma is known to.
TILT_SIGMA_STEP = 0.02


def tie_point_sigmas(options: AdjustmentOptions, store: PlaneStore, faces: np.ndarray,
                     point_faces: np.ndarray, points: np.ndarray, sigmas: np.ndarray,
                     sigma_face: float | None = None) -> np.ndarray:
    """(P,) the sigma (m) of each assigned point's f_dTP: its face's (`sigmas`, `tie_sigmas`),
    with `options.face_tilt_weights` grown by the model face's tilt error at the point
    (adjust.faces.tilt_variances, each vertex off by the faces' offset sigma): a face's
    variance v grows to v (1 + t / u), t the tilt variance at the point, u what v stands for
    per point (sigma_dtp^2; with `face_weighting` "face" sigma_face^2 + sigma_dtp^2 / n).
    Terrain faces keep their units' sigma. Rounded to TILT_SIGMA_STEP."""
    rows = np.searchsorted(faces, point_faces)
    base = np.asarray(sigmas, float)[rows]
    if not options.face_tilt_weights or not len(rows):
        return base
    sigma_face = sigma_face_in_use(options, sigma_face)
    tilt = tilt_variances(store, point_faces, points, sigma_face)
    tilt[terrain_mask(store)[point_faces]] = 0.0
    unit = np.full(len(faces), float(options.sigma_dtp) ** 2)
    if options.face_weighting == "face":
        counts = np.bincount(rows, minlength=len(faces))
        unit = sigma_face ** 2 + unit / np.maximum(counts, 1)
    grown = base * np.sqrt(1.0 + tilt / unit[rows])
    step = np.log1p(TILT_SIGMA_STEP)
    return base * np.exp(np.round(np.log(grown / base) / step) * step)


def _far_pair(ids: np.ndarray, centres: dict) -> tuple[int, int, float]:
    """Two of the frames `ids` (at least two) far apart: the one furthest from their centroid
    and the one furthest from it, and their distance (m)."""
    xyz = np.array([centres[int(f)] for f in ids])
    a = int(np.argmax(np.linalg.norm(xyz - xyz.mean(axis=0), axis=1)))
    b = int(np.argmax(np.linalg.norm(xyz - xyz[a], axis=1)))
    if a == b:
        b = (a + 1) % len(ids)
    return int(ids[a]), int(ids[b]), float(np.linalg.norm(xyz[a] - xyz[b]))


class HybridProblem:
    """One hybrid adjustment problem built from the current state; solve() updates in place.

    `reconstruction` is modified by solve(): poses, tie points (and intrinsics if enabled).
    The model unknowns are read back from `blocks`.
    """

    #: True in a problem that lets the images correct the faces they see well
    #: (adjust.correction_loop.CorrectionProblem); False: every vertex at sigma_VT.
    releases_model: bool = False

    def __init__(self, reconstruction: pycolmap.Reconstruction, store: PlaneStore | None,
                 assignment: Assignment | None, gnss: GNSSPriors | None,
                 options: AdjustmentOptions, *, robust_images: bool, robust_planes: bool,
                 current: PlaneStore | None = None, generalisation_offsets: bool = False,
                 baselines: BaselinePriors | None = None, pose_priors: PosePriors | None = None):
        """`store` is the model as observed (f_VT observes its vertices); `current` (same
        topology, default `store`) holds the current estimate used as initial values.
        `generalisation_offsets`: estimate a per-plane offset with the prior
        N(0, options.sigma_generalisation^2) (only if that is set; see AdjustmentOptions).
        `pose_priors`: frames held near given poses (a sliding window's datum from the window
        before)."""
        core = load_core()
        self.reconstruction = reconstruction
        self.options = options
        config = pycolmap.BundleAdjustmentConfig()
        for image_id in reconstruction.reg_image_ids():
            config.add_image(image_id)
        # GNSS and the model planes give the datum (checked before solving). With neither
        # (step 2 after an initial transform), fix it COLMAP's way to keep the problem regular.
        with_model = store is not None and assignment is not None and assignment.num_assigned
        held = pose_priors is not None and len(pose_priors) > 0
        marks = active_marks()  # ground control marks of the run (adjust.marks)
        held = held or (marks is not None and marks.holds_datum(reconstruction))
        self.gauge_fixed = gnss is None and not with_model and not held
        if self.gauge_fixed:
            config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
        self.adjuster = pycolmap.create_default_ceres_bundle_adjuster(
            bundle_adjustment_options(options, robust_images), config, reconstruction)
        self.problem: pyceres.Problem = self.adjuster.problem
        self.counts = {"image": self.problem.num_residuals()}
        self.robust_planes = robust_planes
        # Every f_dTP's loss follows this switch (Huber while robust_planes, none otherwise):
        # `reassign` turns the problem into its robust or its non-robust twin without a build.
        self._robust = core.RobustSwitch(robust_planes)
        self.baselines = baselines
        self.pose_priors = pose_priors
        self.point_ids = np.zeros(0, np.int64)
        self.point_faces = np.zeros(0, np.int64)  # the face of each f_dTP row
        self.face_sigmas = np.zeros(0)  # the sigma of each face's f_dTP (blocks.faces order)
        self._row_sigmas = np.zeros(0)  # the sigma of each f_dTP row (point_ids order)
        self.blocks = PlaneBlocks(faces=np.zeros(0, np.int64))
        self._generalisation_offsets = generalisation_offsets
        self.gnss = gnss
        # The model as this problem saw it (its faces' extents give their tilt errors in the
        # generalisation-aware precision); None without one.
        self.model = (current if current is not None else store) if with_model else None
        # The GNSS offset's unknown components (a view of nothing else: solve() copies it back
        # into gnss.offset); None when the offset is not estimated in this problem.
        self.gnss_offset: np.ndarray | None = None
        self._add_gnss(core, gnss, estimate_offset=bool(with_model) and gnss is not None
                       and gnss.estimates_offset)
        if with_model:
            self._add_model(core, store, current if current is not None else store, assignment,
                            robust_planes)
        else:
            self.counts.update(dTP=0, dVT=0, VT=0, gen=0)
        self._add_baselines(core, baselines)
        self._add_offset_prior(core, gnss)
        self._add_pose_priors(core, pose_priors)
        self.marks = add_control_marks(self, core)  # group "gcp"
        if with_model:
            self._add_tie_distances()

    def _add_pose_priors(self, core, priors: PosePriors | None) -> None:
        """Group "pose" (last): three rig points of each held frame at their held positions."""
        self.counts["pose"] = 0
        if priors is None:
            return
        rec = self.reconstruction
        sigma = np.full(3, priors.sigma_position / self.options.sigma_image)
        done: set[int] = set()
        for image_id, pose in zip(priors.image_ids, priors.rig_from_world):
            image = rec.image(int(image_id))
            block = rec.frame(image.frame_id).rig_from_world.params
            if image.frame_id in done or not self.problem.has_parameter_block(block):
                continue
            done.add(image.frame_id)
            centre = position_in_rig(rec, image)
            world_from_rig = pose.inverse()
            for axis in (None, 0, 1):
                in_rig = centre.copy()
                if axis is not None:
                    in_rig[axis] += priors.lever
                cost = core.ProjectionCenterPriorCost(np.asarray(world_from_rig * in_rig, float),
                                                      sigma, in_rig)
                self.problem.add_residual_block(cost, None, [block])
                self.counts["pose"] += 3

    def _add_baselines(self, core, baselines: BaselinePriors | None) -> None:
        """Group "scale": the holds of `baselines`; `hold_relaxation` has a factor per row
        that takes it back from its tightened sigma to the sigma of what it holds."""
        self.counts["scale"] = 0
        self.hold_relaxation = np.zeros(0)
        if baselines is None:
            return
        rec = self.reconstruction
        for (a, b), length, sigma in zip(baselines.image_pairs, baselines.lengths,
                                         baselines.sigmas):
            image_a, image_b = rec.image(int(a)), rec.image(int(b))
            block_a = rec.frame(image_a.frame_id).rig_from_world.params
            block_b = rec.frame(image_b.frame_id).rig_from_world.params
            if image_a.frame_id == image_b.frame_id or not (
                    self.problem.has_parameter_block(block_a)
                    and self.problem.has_parameter_block(block_b)):
                continue
            cost = core.BaselineLengthPriorCost(
                float(length), float(sigma) / self.options.sigma_image,
                position_in_rig(rec, image_a), position_in_rig(rec, image_b))
            self.problem.add_residual_block(cost, None, [block_a, block_b])
            self.counts["scale"] += 1
        relaxation = [np.full(self.counts["scale"], 1.0 / baselines.tightening)]
        if baselines.holds_level:
            image = rec.image(int(baselines.level_image))
            block = rec.frame(image.frame_id).rig_from_world.params
            if self.problem.has_parameter_block(block):
                cost = core.ProjectionCenterPriorCost(
                    np.asarray(baselines.level_position, float),
                    np.asarray(baselines.level_sigmas, float) / self.options.sigma_image,
                    position_in_rig(rec, image))
                self.problem.add_residual_block(cost, None, [block])
                self.counts["scale"] += 3
                relaxation.append(np.full(3, 1.0 / baselines.level_tightening))
        self.hold_relaxation = np.concatenate(relaxation)

    # -- building ---------------------------------------------------------------------------
    def _add_gnss(self, core, gnss: GNSSPriors | None, estimate_offset: bool) -> None:
        self.counts["gnss"] = 0
        if gnss is None:
            return
        rec = self.reconstruction
        axes = np.asarray(gnss.offset_axes, bool)
        if estimate_offset:
            directions = gnss.offset_directions()
            self.gnss_offset = np.ascontiguousarray(gnss.offset[axes], dtype=np.float64)
            self.problem.add_parameter_block(self.gnss_offset, len(self.gnss_offset))
            # The constant part of what GNSS observed: the positions with the offset's fixed
            # components (the unknown ones enter through the block).
            observed = gnss.positions + np.where(axes, 0.0, gnss.offset)
        else:
            observed = gnss.observed
        for image_id, position, sigma in zip(gnss.image_ids, observed, gnss.sigmas):
            image = rec.image(int(image_id))
            frame = rec.frame(image.frame_id)
            rig_from_world = frame.rig_from_world.params
            if not self.problem.has_parameter_block(rig_from_world):
                continue
            sigma = np.asarray(sigma, float) / self.options.sigma_image
            if self.gnss_offset is not None:
                cost = core.ProjectionCenterOffsetPriorCost(
                    np.asarray(position, float), sigma, gnss.observed_in_rig(rec, image),
                    directions)
                self.problem.add_residual_block(cost, None, [rig_from_world, self.gnss_offset])
            else:
                cost = core.ProjectionCenterPriorCost(np.asarray(position, float), sigma,
                                                      gnss.observed_in_rig(rec, image))
                self.problem.add_residual_block(cost, None, [rig_from_world])
            self.counts["gnss"] += 3

    def _add_offset_prior(self, core, gnss: GNSSPriors | None) -> None:
        """Group "offset" (last): the prior N(0, sigma^2) of each unknown offset component."""
        self.counts["offset"] = 0
        if self.gnss_offset is None or gnss.offset_prior_sigma is None \
                or not np.all(np.asarray(gnss.offset_prior_sigma) > 0):
            return
        axes = np.asarray(gnss.offset_axes, bool)
        sigma = (np.broadcast_to(np.asarray(gnss.offset_prior_sigma, float), (3,))[axes]
                 / self.options.sigma_image)
        if len(self.gnss_offset) == 1:
            cost = core.ScalarPriorCost(0.0, float(sigma[0]))
        else:
            cost = core.PointPositionPriorCost(np.zeros(3), sigma)
        self.problem.add_residual_block(cost, None, [self.gnss_offset])
        self.counts["offset"] = len(self.gnss_offset)

    def _add_model(self, core, store: PlaneStore, current: PlaneStore, assignment: Assignment,
                   robust_planes: bool) -> None:
        """The model's unknowns and observations: the planes, the generalisation offsets (if
        estimated), the f_dTP's weights (added last, `_add_tie_distances`), the vertices with
        their f_dVT and f_VT, the corrected model's datum condition and the offsets' priors."""
        faces = assignment.faces
        blocks, slot_of_face = self._add_planes(current, faces)
        with_offsets = self._add_generalisation_blocks(blocks, faces, store, assignment)
        self._prepare_tie_distances(core, store, current, assignment, blocks, slot_of_face,
                                    with_offsets)
        released = self._add_vertices(core, store, current, assignment, blocks, slot_of_face)
        if released and self.options.sigma_correction_datum is not None:
            self._add_correction_datum(core, store, blocks)
        # Group "gen" last: the priors of the generalisation offsets.
        if with_offsets:
            self._add_effect_priors(core, blocks)
        self.counts["gen"] = int(sum(len(b) for b in blocks.generalisation))
        self.blocks = blocks

    def _add_planes(self, current: PlaneStore, faces: np.ndarray
                    ) -> tuple[PlaneBlocks, dict[int, int]]:
        """Each face's normal (on the unit sphere) and offset as unknowns at `current`."""
        problem = self.problem
        blocks = PlaneBlocks(faces=faces)
        sphere = pyceres.SphereManifold(3)
        for f in faces:
            # Offsets refer to a point on the plane, so that normal and offset are
            # uncorrelated unknowns (see cpp_ext point_plane_distance.h).
            reference = current.vertices[current.face_vertex_ids(f)].mean(axis=0)
            blocks.references.append(reference)
            blocks.normals.append(np.array(current.normals[f], dtype=np.float64))
            blocks.offsets.append(np.array([current.offsets[f] + current.normals[f] @ reference],
                                           dtype=np.float64))
            problem.add_parameter_block(blocks.normals[-1], 3)
            problem.set_manifold(blocks.normals[-1], sphere)
            problem.add_parameter_block(blocks.offsets[-1], 1)
        return blocks, {int(f): k for k, f in enumerate(faces)}

    def _add_effect_priors(self, core, blocks: PlaneBlocks) -> None:
        """The priors of the faces' generalisation effects: N(0, sigma^2) of each offset and,
        with `face_weighting` "offsets", N(0, 1) of its two tilts (in their sigmas)."""
        if self.options.face_weighting == "offsets":
            prior = core.PointPositionPriorCost(
                np.zeros(EFFECTS), np.array([self._offset_sigma, 1.0, 1.0])
                / self.options.sigma_image)
        else:
            prior = core.ScalarPriorCost(0.0, self._offset_sigma / self.options.sigma_image)
        for block in blocks.generalisation:
            self.problem.add_residual_block(prior, None, [block])

    @property
    def offset_prior_sigma(self) -> float | None:
        """The prior sigma (m) of the faces' offsets estimated in this problem (None: none)."""
        return self._offset_sigma if len(self.blocks.generalisation) else None

    def _add_generalisation_blocks(self, blocks: PlaneBlocks, faces: np.ndarray,
                                   store: PlaneStore, assignment: Assignment) -> bool:
        """Generalisation-aware model: an offset unknown per plane, shared by its tie points
        (with `face_weighting` "offsets" on the model's faces, its prior sigma the faces'
        offset sigma; else only with `generalisation_offsets` and sigma_generalisation set,
        on every plane); True if added."""
        o = self.options
        if o.face_weighting == "offsets":
            self._offset_sigma = sigma_face_in_use(o, assignment.face_sigma)
            if len(self._frame_blocks()) < 2:
                return False
            for k in np.flatnonzero(~terrain_mask(store)[faces]):
                blocks.generalisation_slots[int(k)] = len(blocks.generalisation)
                blocks.generalisation.append(np.zeros(EFFECTS, dtype=np.float64))
                self.problem.add_parameter_block(blocks.generalisation[-1], EFFECTS)
            return bool(blocks.generalisation)
        self._offset_sigma = o.sigma_generalisation
        with_offsets = self._generalisation_offsets and o.sigma_generalisation is not None
        if with_offsets and not o.sigma_generalisation > 0:
            from ..errors import InputError

            raise InputError("adjustment.sigma_generalisation must be > 0 (or unset for the "
                             f"classical model), got {o.sigma_generalisation}")
        if with_offsets:
            for k in range(len(faces)):
                blocks.generalisation_slots[k] = k
                blocks.generalisation.append(np.zeros(1, dtype=np.float64))
                self.problem.add_parameter_block(blocks.generalisation[-1], 1)
        return with_offsets

    def _prepare_tie_distances(self, core, store: PlaneStore, current: PlaneStore,
                               assignment: Assignment, blocks: PlaneBlocks,
                               slot_of_face: dict[int, int], with_offsets: bool) -> None:
        """The f_dTP's points, faces and weights (added last, `_add_tie_distances`): one
        residual per assigned tie point, in the order of `point_ids`; one cost (its sigma)
        and loss per face and sigma (`_tie_cost`)."""
        o = self.options
        faces = assignment.faces
        assigned = assignment.assigned
        self.point_ids = np.asarray(assignment.point_ids[assigned], np.int64)
        self.point_faces = np.asarray(assignment.face_index[assigned], np.int64)
        self.face_sigmas = tie_sigmas(o, store, faces, self.point_faces, assignment)
        self._row_sigmas = self._point_sigmas(current, faces, self.point_ids, self.point_faces,
                                              self.face_sigmas, assignment)
        self._tilt_axes: dict[int, np.ndarray] = {}  # face slot -> (2, 3), "offsets"
        self._tie_factory = lambda sigma, reference, k: core.PointPlaneDistanceCost(sigma,
                                                                                    reference)
        self._offset_factory = lambda sigma, reference, k: core.PointPlaneOffsetDistanceCost(
            sigma, reference)
        if self.options.face_weighting == "offsets" and blocks.generalisation_slots:
            effects = core.PointPlaneEffectsDistanceCost
            faces_of = np.asarray(faces)
            self._face_frames = self._faces_far_frames(
                blocks.generalisation_slots, np.searchsorted(faces, self.point_faces))

            def factory(sigma, reference, k):
                axes = self._tilt_axes.setdefault(
                    k, tilt_axes(current, int(faces_of[k]), self._offset_sigma))
                base = self._face_frames[k][2]
                return effects(sigma, reference, axes, max(base, MIN_SCALE_BASE),
                               base >= MIN_SCALE_BASE)
            self._offset_factory = factory
        self._tie_costs: dict = {}
        self._with_offsets = with_offsets
        self._slot_of_face = slot_of_face
        self._references = blocks.references

    def _add_held_planes(self, core, store: PlaneStore, current: PlaneStore,
                         assignment: Assignment, blocks: PlaneBlocks
                         ) -> tuple[set[int], dict[int, int], list]:
        """Model correction: the vertices of the faces the images see well are released; a
        released vertex stays on the given (constant) plane of each of its faces that is not
        corrected. Returns the released vertices, each held face's slot and its f_dVT cost."""
        o = self.options
        problem = self.problem
        rec = self.reconstruction
        points = np.full((len(assignment.point_ids), 3), np.nan)
        points[assignment.assigned] = [rec.point3D(int(i)).xyz for i in self.point_ids]
        selection = select_corrected_faces(current, assignment, points, o)
        blocks.correction = selection
        held_slot: dict[int, int] = {}
        held_costs = []
        for k, f in enumerate(selection.held):
            held_slot[int(f)] = k
            reference = store.vertices[store.face_vertex_ids(f)].mean(axis=0)
            normal = np.array(store.normals[f], dtype=np.float64)
            blocks.held_normals.append(normal)
            blocks.held_offsets.append(np.array([store.offsets[f] + normal @ reference],
                                                dtype=np.float64))
            problem.add_parameter_block(blocks.held_normals[-1], 3)
            problem.add_parameter_block(blocks.held_offsets[-1], 1)
            problem.set_parameter_block_constant(blocks.held_normals[-1])
            problem.set_parameter_block_constant(blocks.held_offsets[-1])
            held_costs.append(core.PointPlaneDistanceCost(o.sigma_dvt / o.sigma_image,
                                                          reference))
        return set(selection.released.tolist()), held_slot, held_costs

    def _add_vertices(self, core, store: PlaneStore, current: PlaneStore,
                      assignment: Assignment, blocks: PlaneBlocks,
                      slot_of_face: dict[int, int]) -> set[int]:
        """The vertices of the planes in the problem, each with f_dVT to its planes (and to the
        held planes of a corrected model) and f_VT; returns the released vertices."""
        o = self.options
        problem = self.problem
        faces = assignment.faces
        vertex_ids = np.unique(np.concatenate([store.face_vertex_ids(f) for f in faces]))
        blocks.vertex_ids = vertex_ids
        indptr, indices = store.vertex_faces
        vertex_costs = [core.PointPlaneDistanceCost(o.sigma_dvt / o.sigma_image, r)
                        for r in blocks.references]
        released, held_slot, held_costs = (
            self._add_held_planes(core, store, current, assignment, blocks)
            if self.releases_model else (set(), {}, []))
        corrected = set() if blocks.correction is None else set(blocks.correction.faces.tolist())
        n_dvt = 0
        for v in vertex_ids:
            blocks.vertices.append(np.array(current.vertices[v], dtype=np.float64))
            for f in indices[indptr[v]:indptr[v + 1]]:
                k = slot_of_face.get(int(f))
                if k is not None:
                    problem.add_residual_block(vertex_costs[k], None,
                                               [blocks.vertices[-1], blocks.normals[k],
                                                blocks.offsets[k]])
                    n_dvt += 1
                if int(v) in released and int(f) not in corrected:
                    h = held_slot[int(f)]
                    problem.add_residual_block(held_costs[h], None,
                                               [blocks.vertices[-1], blocks.held_normals[h],
                                                blocks.held_offsets[h]])
                    n_dvt += 1
        self.counts["dVT"] = n_dvt
        sigma_vt = np.full(3, o.sigma_vt / o.sigma_image)
        sigma_released = np.full(3, o.sigma_vt_corrected / o.sigma_image)
        for v, vertex in zip(vertex_ids, blocks.vertices):
            problem.add_residual_block(
                core.PointPositionPriorCost(np.array(store.vertices[v], dtype=np.float64),
                                            sigma_released if int(v) in released else sigma_vt),
                None, [vertex])
        self.counts["VT"] = 3 * len(vertex_ids)
        return released

    def _add_correction_datum(self, core, store: PlaneStore, blocks: PlaneBlocks) -> None:
        """The corrected model keeps the given model's datum (one condition of up to 7 rows)."""
        o = self.options
        ids, matrix, reference = datum_condition(store, blocks.correction,
                                                 o.sigma_correction_datum / o.sigma_image)
        if len(matrix):
            slots = np.searchsorted(blocks.vertex_ids, ids)
            self.problem.add_residual_block(core.LinearPointsConditionCost(matrix, reference),
                                            None, [blocks.vertices[k] for k in slots])
            self.counts["VT"] += len(matrix)

    def _point_sigmas(self, model: PlaneStore, faces: np.ndarray, point_ids: np.ndarray,
                      point_faces: np.ndarray, sigmas: np.ndarray, assignment: Assignment
                      ) -> np.ndarray:
        """`tie_point_sigmas` of the tie points `point_ids` at their current positions."""
        o = self.options
        if o.face_tilt_weights and len(point_ids):
            rec = self.reconstruction
            points = np.array([rec.point3D(int(i)).xyz for i in point_ids])
        else:
            points = np.zeros((len(point_ids), 3))
        return tie_point_sigmas(o, model, faces, point_faces, points, sigmas,
                                assignment.face_sigma)

    def _tie_cost(self, k: int, sigma: float):
        """The cost and loss of an f_dTP on face slot `k` at `sigma` (m), made once."""
        key = (k, round(float(sigma), 9))
        if key not in self._tie_costs:
            o = self.options
            # The robust loss bends at the same distance (m) on every face; switched off it
            # leaves the residuals as they are (self._robust).
            loss = load_core().SwitchableHuberLoss(o.plane_loss_scale * o.sigma_dtp / sigma,
                                                   self._robust)
            factory = (self._offset_factory
                       if self._with_offsets and k in self.blocks.generalisation_slots
                       else self._tie_factory)
            self._tie_costs[key] = (factory(sigma / o.sigma_image, self._references[k], k),
                                    loss)
        return self._tie_costs[key]

    def _add_tie_blocks(self, point_ids, faces, sigmas) -> list:
        """One f_dTP block per tie point (its face, its sigma in m), in their order; the
        blocks' handles. The costs and each face's other parameter blocks are looked up once
        per face and sigma, not per point."""
        slots = [self._slot_of_face[int(f)] for f in faces]
        faces_blocks = {k: [self.blocks.normals[k], self.blocks.offsets[k]]
                        + self._effect_blocks(k) for k in set(slots)}
        costs = {}
        point3D, add = self.reconstruction.point3D, self.problem.add_residual_block
        out = []
        for point_id, k, sigma in zip(point_ids, slots, sigmas):
            key = (k, sigma)
            if key not in costs:
                costs[key] = self._tie_cost(k, float(sigma))
            cost, loss = costs[key]
            out.append(add(cost, loss, [point3D(int(point_id)).xyz] + faces_blocks[k]))
        return out

    def _effect_blocks(self, k: int) -> list:
        """The generalisation offset of face slot `k` (if it has one) and, with
        `face_weighting` "offsets", the two frames that give the block's scale."""
        blocks = self.blocks
        if not self._with_offsets:
            return []
        g = blocks.generalisation_slots.get(k)
        if g is None:
            return []
        frames = (list(self._face_frames[k][:2]) if self.options.face_weighting == "offsets"
                  else [])
        return [blocks.generalisation[g]] + frames

    def face_effect_shifts(self, point_ids: np.ndarray) -> np.ndarray:
        """(len(point_ids), 3) m: where the faces' estimated effects (`face_weighting`
        "offsets") put each tie point relative to its given face, undone: the move along the
        face's normal by its offset and tilts at the point; zero for points on no face with
        effects."""
        point_ids = np.asarray(point_ids, np.int64)
        out = np.zeros((len(point_ids), 3))
        blocks = self.blocks
        if self.options.face_weighting != "offsets" or not blocks.generalisation \
                or not len(self.point_ids):
            return out
        order = np.argsort(self.point_ids)
        found = np.searchsorted(self.point_ids, point_ids, sorter=order)
        found = np.minimum(found, len(order) - 1)
        rows = order[found]
        here = self.point_ids[rows] == point_ids
        slots = np.searchsorted(blocks.faces, self.point_faces[rows])
        effect_of = np.full(len(blocks.faces), -1)
        for k, g in blocks.generalisation_slots.items():
            effect_of[k] = g
        here &= effect_of[slots] >= 0
        if not here.any():
            return out
        slots = slots[here]
        effects = np.array(blocks.generalisation)[effect_of[slots]]
        rec = self.reconstruction
        xyz = np.array([rec.point3D(int(p)).xyz for p in point_ids[here]])
        lever = xyz - np.array(blocks.references)[slots]
        axes = np.array([self._tilt_axes.get(int(k), np.zeros((2, 3))) for k in slots])
        move = effects[:, 0] + np.einsum("pk,pkj,pj->p", effects[:, 1:], axes, lever)
        normals = np.array(blocks.normals)[slots]
        out[here] = normals / np.linalg.norm(normals, axis=1, keepdims=True) * move[:, None]
        return out

    def _effects_reweighted(self, assignment: Assignment) -> bool:
        """True where the faces' effects' prior sigma (`face_weighting` "offsets") would
        change by more than REWEIGHT_TOLERANCE for `assignment`."""
        if self.options.face_weighting != "offsets" or not self.blocks.generalisation:
            return False
        sigma = sigma_face_in_use(self.options, assignment.face_sigma)
        return abs(sigma / self._offset_sigma - 1.0) > REWEIGHT_TOLERANCE

    def _frame_blocks(self) -> dict[int, np.ndarray]:
        """{frame id: its rig_from_world block} of the frames in the problem."""
        rec = self.reconstruction
        out = {}
        for image_id in rec.reg_image_ids():
            frame = rec.frame(rec.image(image_id).frame_id)
            if self.problem.has_parameter_block(frame.rig_from_world.params):
                out[frame.frame_id] = frame.rig_from_world.params
        return out

    def _faces_far_frames(self, with_effects, slots: np.ndarray) -> dict[int, tuple]:
        """Per face slot with effects: (rig_from_world of two frames, their rig origins'
        distance m) of the two frames furthest apart among those that see the face's tie
        points (`with_effects`: those slots; `slots`: the slot of each assigned point): the
        block's scale where the face is, which the block's bending far away does not change.
        Faces seen from one frame only take the problem's two frames furthest apart."""
        rec = self.reconstruction
        blocks = self._frame_blocks()
        ids = np.fromiter(blocks, np.int64, len(blocks))
        centres = {int(f): rec.frame(int(f)).rig_from_world.inverse().translation for f in ids}
        whole = _far_pair(ids, centres)
        order = np.argsort(slots, kind="stable")
        starts = np.searchsorted(slots[order], np.arange(max(with_effects, default=-1) + 2))
        out = {}
        for k in with_effects:
            points = self.point_ids[order[starts[k]:starts[k + 1]]][:FRAMES_SAMPLE_POINTS]
            seen = {rec.image(el.image_id).frame_id for p in points
                    for el in rec.point3D(int(p)).track.elements}
            seen = np.array([f for f in seen if f in blocks], np.int64)
            a, b, length = _far_pair(seen, centres) if len(seen) >= 2 else whole
            out[k] = (blocks[a], blocks[b], length)
        return out

    def _add_tie_distances(self) -> None:
        """Group "dTP" (last): one block per assigned tie point, in the order of `point_ids`."""
        self._tie_blocks = self._add_tie_blocks(self.point_ids, self.point_faces,
                                                self._row_sigmas.tolist())
        self.counts["dTP"] = len(self.point_ids)

    def reassign(self, assignment: Assignment, current: PlaneStore, *,
                 robust_planes: bool = False, baselines: BaselinePriors | None = None,
                 pose_priors: PosePriors | None = None) -> bool:
        """Make this problem the one `HybridProblem(..., assignment, current=current)` would
        build, in place: the f_dTP blocks of the tie points whose plane changed are removed
        and added, their loss switched to `robust_planes`, the model unknowns are set to
        `current`; image, GNSS and model blocks stay. Poses and tie points are the
        reconstruction's own (already current). Returns False, changing nothing, where that is
        not possible: another set of planes or other priors, a problem that releases the
        model, or more than `MAX_REASSIGNED` changes (build a new problem then)."""
        if (self.releases_model or not self.counts.get("dTP") or not hasattr(self, "_tie_blocks")
                or baselines is not self.baselines
                or pose_priors is not self.pose_priors
                or not np.array_equal(assignment.faces, self.blocks.faces)
                or self._effects_reweighted(assignment)):
            return False
        assigned = assignment.assigned
        new_ids = np.asarray(assignment.point_ids[assigned], np.int64)
        new_faces = np.asarray(assignment.face_index[assigned], np.int64)
        sigmas = tie_sigmas(self.options, current, self.blocks.faces, new_faces, assignment)
        if np.any(np.abs(sigmas / self.face_sigmas - 1.0) > REWEIGHT_TOLERANCE):
            return False  # the faces' weights changed: their costs must be made anew
        # Blocks that stay: the same tie point on the same plane (point ids are unique).
        stays = np.zeros(len(self.point_ids), bool)
        match = np.zeros(len(self.point_ids), np.int64)
        if len(new_ids):
            order = np.argsort(new_ids, kind="stable")
            at = np.searchsorted(new_ids[order], self.point_ids)
            match = order[np.minimum(at, len(new_ids) - 1)]
            stays = (new_ids[match] == self.point_ids) & (new_faces[match] == self.point_faces)
        removed = np.flatnonzero(~stays)
        kept = np.zeros(len(new_ids), bool)
        kept[match[stays]] = True
        added = np.flatnonzero(~kept)
        if len(removed) + len(added) > MAX_REASSIGNED:
            return False
        ids, faces, blocks = list(self.point_ids), list(self.point_faces), self._tie_blocks
        row_sigmas = list(self._row_sigmas)
        # Ceres puts the last block where one is removed: mirror that, from the highest
        # position down, so that every position still refers to the block it held.
        for j in removed[::-1]:
            self.problem.remove_residual_block(blocks[j])
            ids[j], faces[j], blocks[j] = ids[-1], faces[-1], blocks[-1]
            row_sigmas[j] = row_sigmas[-1]
            ids.pop(), faces.pop(), blocks.pop(), row_sigmas.pop()
        added_sigmas = self._point_sigmas(current, self.blocks.faces, new_ids[added],
                                          new_faces[added], self.face_sigmas, assignment)
        blocks += self._add_tie_blocks(new_ids[added], new_faces[added],
                                       np.asarray(added_sigmas, float).tolist())
        ids += new_ids[added].tolist()
        faces += new_faces[added].tolist()
        row_sigmas += np.asarray(added_sigmas, float).tolist()
        self.point_ids = np.asarray(ids, np.int64)
        self.point_faces = np.asarray(faces, np.int64)
        self._row_sigmas = np.asarray(row_sigmas, float)
        self.counts["dTP"] = len(self.point_ids)
        self.exchanged = len(removed) + len(added)
        self.robust_planes = robust_planes
        self._robust.on = robust_planes
        self._set_model(current)
        return True

    def _set_model(self, current: PlaneStore) -> None:
        """The model unknowns from `current` (same topology), as a new problem starts them."""
        blocks = self.blocks
        for k, f in enumerate(blocks.faces):
            blocks.normals[k][:] = current.normals[f]
            blocks.offsets[k][:] = current.offsets[f] + current.normals[f] @ blocks.references[k]
        for vertex, v in zip(blocks.vertices, blocks.vertex_ids):
            vertex[:] = current.vertices[v]
        for offset in blocks.generalisation:
            offset[:] = 0.0

    # -- solving ----------------------------------------------------------------------------
    def num_unknowns(self) -> int:
        """Tangent-space dimension of the variable parameters (the u of n - u)."""
        rec = self.reconstruction
        frames = {rec.image(i).frame_id for i in rec.reg_image_ids()}
        u = 6 * len(frames) + 3 * rec.num_points3D()
        if self.options.refine_intrinsics:
            u += sum(len(c.params) - 2 for c in rec.cameras.values())  # principal point fixed
        u += 3 * len(self.blocks.faces) + 3 * len(self.blocks.vertex_ids)
        u += sum(len(block) for block in self.blocks.generalisation)
        u += 0 if self.gnss_offset is None else len(self.gnss_offset)
        u += 0 if self.marks is None else self.marks.num_unknowns
        return u - (7 if self.gauge_fixed else 0)  # one frame and one coordinate held

    def group_residuals(self) -> dict[str, np.ndarray]:
        """Normalised residuals per observation group as the problem weighs them (loss
        functions not applied; f_dTP by their faces' sigmas, `dtp_sigmas`)."""
        evaluate = pyceres.EvaluateOptions()
        evaluate.apply_loss_function = False
        # As many threads as the solves (Ceres evaluates on one by default). Most of the
        # 60-70 ms for the 375k residuals of a 90-image block is pyceres building their list.
        threads = self.options.num_threads
        evaluate.num_threads = threads if threads > 0 else (os.cpu_count() or 1)
        values = np.asarray(self.problem.evaluate_residuals(evaluate))
        out, start = {}, 0
        for group in GROUPS:
            n = self.counts[group]
            out[group] = values[start:start + n]
            start += n
        out = {group: r / self.options.sigma_image for group, r in out.items()}
        return out

    def dtp_sigmas(self) -> np.ndarray:
        """(dTP rows,) the sigma (m) each f_dTP row was weighted with."""
        if not len(self.point_faces):
            return np.zeros(0)
        return np.asarray(self._row_sigmas, float)

    def solve(self) -> SolveReport:
        import time

        start = time.perf_counter()
        summary = self.adjuster.solve()
        seconds = time.perf_counter() - start
        ceres_summary = getattr(summary, "ceres_summary", None)
        iterations = (ceres_summary.num_successful_steps + ceres_summary.num_unsuccessful_steps
                      if ceres_summary is not None else -1)
        if ceres_summary is not None:
            logger.debug("ceres: %s", ceres_summary.FullReport())
        if self.gnss_offset is not None:  # the estimate back into the priors
            axes = np.asarray(self.gnss.offset_axes, bool)
            offset = np.array(self.gnss.offset, dtype=np.float64)
            offset[axes] = self.gnss_offset
            self.gnss.offset = offset
        whitened = self.group_residuals()
        # At the solution, until the next solve; every f_dTP in units of sigma_dtp, whatever
        # weight its face gave it (outlier tests and reports read distances).
        residuals = dict(whitened)
        if len(residuals.get("dTP", ())):
            residuals["dTP"] = whitened["dTP"] * self.dtp_sigmas() / self.options.sigma_dtp
        self.residuals = residuals
        return SolveReport(
            rms={g: float(np.sqrt(np.mean(r ** 2))) if len(r) else float("nan")
                 for g, r in residuals.items()},
            count={g: len(r) for g, r in residuals.items()},
            sum_squares={g: float(np.sum(r ** 2)) for g, r in whitened.items()},
            num_unknowns=self.num_unknowns(),
            ceres_iterations=iterations,
            seconds=seconds,
            termination=str(getattr(summary, "termination_type", "")),
            linear_solver=(str(ceres_summary.linear_solver_type_used).split(".")[-1]
                           if ceres_summary is not None else ""),
        )


