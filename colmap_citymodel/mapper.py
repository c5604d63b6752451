"""`colmap-citymodel map`: COLMAP's incremental mapping with the city model in its global
bundle adjustments, then refine's final adjustment, quality gate and outputs.

The loop is COLMAP's `IncrementalPipeline::ReconstructSubModel` step for step, driven through
pycolmap's `IncrementalMapper` (initial pair, `register_next_image`, `triangulate_image`,
`iterative_local_refinement`, and a global refinement whenever the pipeline's
`check_run_global_refinement` says so). Registration, triangulation, local bundle adjustments
and filtering stay COLMAP's. The global refinements differ once the block can be placed on the
model:

0. the initial image pair is COLMAP's; with `MapperOptions.start_at_gnss` it is sought among
   the images with GNSS first, so that the block grows out of its GNSS part (off by default:
   see the option);
1. while fewer than `MapperOptions.min_gnss_images` registered images have GNSS, a global
   refinement is COLMAP's (`iterative_global_refinement`, which also normalises the block);
2. at the first global refinement with that many, the block is georegistered: the 7-parameter
   fit to the registered images' GNSS (align.block_to_model.georegister, into the model's local
   frame) and refine's coarse search onto the model surfaces (workflow.coarse_start). COLMAP
   never normalises the block again;
3. from then on each global refinement is: COLMAP's track completion, merging and
   retriangulation, then the hybrid adjustment of the whole block with the model
   (adjust.loop: assignment from the current estimate, hybrid solves, at most
   `MapperOptions.hybrid_iterations` iterations; GNSS priors of the registered images with
   GNSS, the offset held), then COLMAP's track merging and point filtering.

Scale and position where GNSS stops (GNSS only at the start of a sequence): as in the sliding
window, the images already adjusted hold the new ones. COLMAP registers each new image against
the tie points of the adjusted block and its local bundle adjustments keep the images outside
the local window fixed, so a new image enters where the block puts it (the sliding window's
prediction step); each hybrid adjustment then holds the whole block by its tie points on the
planes and the GNSS of the registered images, and the loop keeps the block's scale from its
state before the adjustment where the planes cannot give it (`gnss_only`/`scale_sigma` of
adjust.loop). This does not hold a block georegistered early from few GNSS positions: started
among the GNSS images (`start_at_gnss`) with GNSS only at the start, it can settle at a wrong
scale; with COLMAP's own initial pair the model enters late and the result matches a refine
of the mapped block (docs/defaults.md, `start_at_gnss`).

Only one model is built (COLMAP's `multiple_models` does not apply): the largest connected
block is what the model can hold; images that cannot be registered to it are reported. As in
COLMAP's pipeline, a model smaller than `min_model_size` images (or 0.8 of them) is dropped
for the next initial pair, and without a model the initial pair's constraints are relaxed
(inliers, then triangulation angle halved, twice each, each time with a new mapper); only
when no pair grows a larger model is the first small one kept. After
mapping, `workflow.refine` runs on the mapped block as on any COLMAP model (started from the
mapper's georegistration), with the same report and outputs.

When the database holds no keypoints, COLMAP's feature extraction (`pycolmap.extract_features`)
and matching (`pycolmap.match_exhaustive`/`match_sequential`/`match_spatial`) run first.
"""

from __future__ import annotations

import copy
import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from .adjust.loop import adjustment_loop
from .align.block_to_model import georegister
from .align.coarse import SurfaceDistance
from .align.objective import BlockObjective
from .block.priors import GNSSPriors, priors_of_registered_images, scale_sigma_from_gnss
from .block.reconstruction import tie_points
from .citymodel.store import PlaneStore
from .errors import CityModelError, DatumError, GeoregistrationError, GNSSError, InputError
from .options import MapperOptions, RefineOptions
from .output.result import RefineResult
from .workflow import coarse_start, read_inputs, refine, write_outputs

logger = logging.getLogger(__name__)

MATCHERS = ("exhaustive", "sequential", "spatial")


@dataclass
class GlobalAdjustmentRecord:
    """One global refinement during mapping."""

    num_images: int  # registered images
    kind: str  # "colmap" or "hybrid"
    num_gnss: int = 0
    rms: float | None = None  # RMS of the normalised residuals of the last hybrid solve
    num_assigned: int = 0
    num_planes: int = 0
    iterations: int = 0
    seconds: float = 0.0
    note: str | None = None

    def todict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class MappedBlock:
    """What mapping produced: the block (the model's local frame once georegistered)."""

    reconstruction: pycolmap.Reconstruction
    georegistered_at: int | None  # registered images when the block was georegistered
    num_database_images: int
    adjustments: list[GlobalAdjustmentRecord] = field(default_factory=list)
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)

    @property
    def georegistered(self) -> bool:
        return self.georegistered_at is not None

    @property
    def num_hybrid(self) -> int:
        return sum(a.kind == "hybrid" for a in self.adjustments)

    def todict(self) -> dict:
        return {"num_database_images": self.num_database_images,
                "num_registered_images": int(self.reconstruction.num_reg_images()),
                "georegistered_at_images": self.georegistered_at,
                "num_global_adjustments": len(self.adjustments),
                "num_hybrid_adjustments": self.num_hybrid, "seconds": self.seconds,
                "global_adjustments": [a.todict() for a in self.adjustments]}


# -- COLMAP options from KEY=VALUE strings -----------------------------------------------------

def parse_option_values(items: list[str] | None, what: str) -> dict:
    """["a=1", "mapper.b=x"] -> {"a": 1, "mapper": {"b": "x"}}; values as TOML scalars
    (numbers, true/false), anything else a string."""
    import tomllib

    out: dict = {}
    for item in items or []:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise InputError(f"{what}: expected KEY=VALUE, got {item!r}")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        node = out
        parts = key.strip().split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def merged_options(options, values: dict, what: str):
    """pycolmap's option object `options` with `values` merged in; what pycolmap rejects is an
    InputError naming `what` (the command line's option)."""
    if values:
        try:
            options.mergedict(values)
        except Exception as error:  # pycolmap rejects unknown keys and wrong types
            raise InputError(f"{what}: {error}") from None
    return options


def pipeline_options(values: dict | None = None, *, num_threads: int | None = None,
                     seed: int | None = None) -> pycolmap.IncrementalPipelineOptions:
    """COLMAP's incremental pipeline options (`colmap mapper --Mapper.*`), updated by `values`."""
    o = pycolmap.IncrementalPipelineOptions()
    o.multiple_models = False
    if num_threads is not None:
        o.num_threads = int(num_threads)
    if seed is not None:
        o.random_seed = int(seed)
    return merged_options(o, values or {}, "--mapper_options")


# -- features and matches ----------------------------------------------------------------------

def database_state(database_path: Path) -> tuple[int, int, int]:
    """(images, images with keypoints, verified image pairs) of the database."""
    with pycolmap.Database.open(str(database_path)) as db:
        images = db.read_all_images()
        with_keypoints = sum(db.exists_keypoints(i.image_id) and
                             db.num_keypoints_for_image(i.image_id) > 0 for i in images)
        return len(images), int(with_keypoints), int(db.num_verified_image_pairs())


def extract_and_match(database_path: Path, image_path: Path, *, matcher: str = "exhaustive",
                      camera_model: str | None = None, single_camera: bool = False,
                      extraction: dict | None = None, matching: dict | None = None) -> None:
    """COLMAP's SIFT extraction of the images under `image_path` into the database, then its
    matching and geometric verification (`matcher`: exhaustive, sequential or spatial)."""
    if matcher not in MATCHERS:
        raise InputError(f"--matcher takes {', '.join(MATCHERS)}, got {matcher!r}")
    if not image_path.is_dir():
        raise InputError(f"the database {database_path} holds no features and the image "
                         f"directory {image_path} does not exist: nothing to extract them from")
    reader = pycolmap.ImageReaderOptions()
    if camera_model:
        reader.camera_model = camera_model
    logger.info("feature extraction (COLMAP SIFT) of %s", image_path)
    pycolmap.extract_features(
        database_path, image_path, reader_options=reader,
        camera_mode=pycolmap.CameraMode.SINGLE if single_camera else pycolmap.CameraMode.AUTO,
        extraction_options=merged_options(pycolmap.FeatureExtractionOptions(),
                                          extraction or {}, "--extraction_options"))
    logger.info("%s matching (COLMAP)", matcher)
    match = {"exhaustive": pycolmap.match_exhaustive, "sequential": pycolmap.match_sequential,
             "spatial": pycolmap.match_spatial}[matcher]
    match(database_path, matching_options=merged_options(pycolmap.FeatureMatchingOptions(),
                                                         matching or {}, "--matching_options"))


# -- the global adjustment with the model ------------------------------------------------------

class ModelGlobalAdjustment:
    """Global refinements of the growing block: COLMAP's until the block is georegistered, then
    the hybrid adjustment with the model (module docstring, steps 1-3)."""

    def __init__(self, store: PlaneStore, gnss, options: RefineOptions,
                 mapper_options: MapperOptions):
        self.store, self.gnss, self.options = store, gnss, options
        self.mapper_options = mapper_options
        self.surface = SurfaceDistance(store, options.assignment.excluded_classes,
                                       options.adjustment.num_threads)
        self.georegistered_at: int | None = None
        self.offset = np.zeros(3)  # the GNSS offset found at georegistration, then held
        self.records: list[GlobalAdjustmentRecord] = []
        self.last_problem = None  # the last hybrid solve's problem (tests, diagnostics)
        self._gnss_names = set(gnss.image_names) if gnss is not None else set()

    @property
    def georegistered(self) -> bool:
        return self.georegistered_at is not None

    def num_gnss(self, rec: pycolmap.Reconstruction) -> int:
        return sum(rec.image(i).name in self._gnss_names for i in rec.reg_image_ids())

    def priors(self, rec: pycolmap.Reconstruction) -> GNSSPriors | None:
        if self.gnss is None:
            return None
        try:
            return priors_of_registered_images(self.gnss, rec, self.store.origin,
                                               offset=self.offset.copy())
        except GNSSError:
            return None

    def georegister(self, rec: pycolmap.Reconstruction) -> None:
        """Move `rec` (in place) into the model's local frame and onto the model."""
        details: dict = {}
        _, priors, rms = georegister(rec, self.store, self.gnss, None, details,
                                     self.options.adjustment.gnss_offset)
        ids, points = tie_points(rec)
        if self.options.workflow.coarse_search_sigmas > 0:
            objective = BlockObjective(self.surface, priors, ids, self.options.adjustment,
                                       self.options.workflow.divergence_alpha)
            coarse_start(rec, points, self.store, self.surface, priors, objective,
                         self.options, straight="roll_about_line" in details.get("cues", {}))
        if priors.estimates_offset:
            self.offset = np.array(priors.fit_offset(rec), dtype=np.float64)
        self.georegistered_at = int(rec.num_reg_images())
        logger.info("mapping: block georegistered at %d images (%d with GNSS, RMS %.2f m)",
                    self.georegistered_at, len(priors), rms or float("nan"))

    def __call__(self, mapper: pycolmap.IncrementalMapper,
                 pipeline: pycolmap.IncrementalPipelineOptions) -> GlobalAdjustmentRecord:
        rec = mapper.reconstruction
        mapper_opts = pipeline.get_mapper()
        t0 = time.perf_counter()
        num_gnss = self.num_gnss(rec)
        note = None
        if not self.georegistered and self.gnss is not None and \
                num_gnss >= self.mapper_options.min_gnss_images:
            work = pycolmap.Reconstruction(rec)  # the block stays as it is if this fails
            try:
                self.georegister(work)
            except GeoregistrationError as error:  # e.g. too short a baseline yet: later
                note = f"not georegistered yet: {error.message}"
                logger.info("mapping: %s", note)
            else:
                _copy_back(rec, work)
        record = GlobalAdjustmentRecord(num_images=int(rec.num_reg_images()),
                                        kind="hybrid" if self.georegistered else "colmap",
                                        num_gnss=num_gnss, note=note)
        if self.georegistered:
            try:
                with _quiet_stages():
                    self._hybrid(mapper, pipeline, record)
            except DatumError as error:  # no plane (and no GNSS) holds the block yet
                record.kind, record.note = "colmap", f"no hybrid adjustment: {error.message}"
                _colmap_refinement(mapper, pipeline, normalize=False)
        else:
            _colmap_refinement(mapper, pipeline, normalize=True)
        mapper.filter_frames(mapper_opts)
        record.seconds = time.perf_counter() - t0
        self.records.append(record)
        logger.info("mapping: global adjustment (%s) at %d images: %s", record.kind,
                    record.num_images, "-" if record.rms is None else
                    f"RMS {record.rms:.4f}, {record.num_assigned} points on "
                    f"{record.num_planes} planes")
        return record

    def _hybrid(self, mapper, pipeline, record: GlobalAdjustmentRecord) -> None:
        """COLMAP's track completion and retriangulation, the hybrid adjustment of the whole
        block with the model (on a copy, written back), COLMAP's merging and filtering."""
        rec = mapper.reconstruction
        tri = pipeline.get_triangulation()
        mapper.complete_and_merge_tracks(tri)
        mapper.retriangulate(tri)
        priors = self.priors(rec)
        options = copy.deepcopy(self.options)
        options.workflow.max_iterations = self.mapper_options.hybrid_iterations
        # Mapping's adjustments keep the growing block on the model; the faces' errors as
        # unknowns are left to refine's adjustment after it (adjust.staged).
        options.adjustment.face_weighting = "per_point"
        if self.records and self.records[-1].kind == "hybrid":
            options.workflow.alignment_rounds = 0  # the adjustment before placed the block
        work = pycolmap.Reconstruction(rec)
        ids, _ = tie_points(work)
        objective = BlockObjective(self.surface, priors, ids, options.adjustment,
                                   options.workflow.divergence_alpha)
        loop = adjustment_loop(work, self.store, priors, options, objective, ids,
                               gnss_only=pycolmap.Reconstruction(rec),
                               scale_sigma=scale_sigma_from_gnss(priors)
                               if priors is not None and len(priors) > 1 else None,
                               progress=False)
        _copy_back(rec, loop.reconstruction)
        self.last_problem = loop.last
        last = loop.iterations[-1]
        record.rms = float(last.final.rms_total)
        record.num_assigned = int(loop.assignment.num_assigned)
        record.num_planes = int(loop.assignment.num_faces)
        record.iterations = len(loop.iterations)
        mapper.complete_and_merge_tracks(tri)
        mapper.filter_points(pipeline.get_mapper())


def _colmap_refinement(mapper: pycolmap.IncrementalMapper,
                       pipeline: pycolmap.IncrementalPipelineOptions, *, normalize: bool) -> None:
    """COLMAP's own global refinement; `normalize`: also rescale the block (only before it
    is georegistered: afterwards it is in the model's frame)."""
    mapper.iterative_global_refinement(
        pipeline.ba_global_max_refinements, pipeline.ba_global_max_refinement_change,
        pipeline.get_mapper(), pipeline.get_global_bundle_adjustment(),
        pipeline.get_triangulation(), normalize_reconstruction=normalize)


#: Stages whose per-iteration log lines the global adjustments during mapping keep quiet (one
#: line per global adjustment instead), unless debug logging is on.
QUIET_DURING_MAPPING = ("colmap_citymodel.adjust", "colmap_citymodel.assign",
                        "colmap_citymodel.align", "colmap_citymodel.block")


@contextmanager
def _quiet_stages():
    if logging.getLogger("colmap_citymodel").getEffectiveLevel() <= logging.DEBUG:
        yield
        return
    saved = [(lg, lg.level) for lg in map(logging.getLogger, QUIET_DURING_MAPPING)]
    for lg, _ in saved:
        lg.setLevel(logging.WARNING)
    try:
        yield
    finally:
        for lg, level in saved:
            lg.setLevel(level)


def _copy_back(rec: pycolmap.Reconstruction, adjusted: pycolmap.Reconstruction) -> None:
    """The adjusted poses, tie points and intrinsics into the mapper's own reconstruction
    (which must stay the same object: the mapper holds it)."""
    for fid in rec.reg_frame_ids():
        rec.frame(fid).rig_from_world = adjusted.frame(fid).rig_from_world
    for point_id in rec.point3D_ids():
        if adjusted.exists_point3D(point_id):
            rec.point3D(point_id).xyz = adjusted.point3D(point_id).xyz
    for camera_id, camera in adjusted.cameras.items():
        rec.camera(camera_id).params = camera.params


# -- the incremental loop ----------------------------------------------------------------------

#: As COLMAP: after this many failed trials of a young model, another initial pair is tried.
MIN_NUM_INITIAL_REG_TRIALS = 30


def map_block(database_path, store: PlaneStore, gnss, options: RefineOptions | None = None,
              mapper_options: MapperOptions | None = None,
              pipeline: pycolmap.IncrementalPipelineOptions | None = None, *,
              image_path=None, progress: bool = True,
              global_adjustment: ModelGlobalAdjustment | None = None) -> MappedBlock:
    """Map the database's images incrementally with `store` in the global adjustments (module
    docstring). `gnss`: block.gnss.GNSSObservations in the store's CRS, or None (then every
    global adjustment stays COLMAP's). The result is in the store's local frame when the block
    was georegistered."""
    options = options or RefineOptions()
    mapper_options = mapper_options or MapperOptions()
    pipeline = pipeline or pipeline_options()
    start = time.perf_counter()
    if image_path is not None and Path(image_path).is_dir():
        pipeline.image_path = str(image_path)
    else:
        pipeline.extract_colors = False
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(level, 1)  # COLMAP's per-image log lines
    try:
        with pycolmap.Database.open(str(database_path)) as db:
            cache = pycolmap.DatabaseCache.create(db, pycolmap.DatabaseCacheOptions(
                min_num_matches=pipeline.min_num_matches,
                ignore_watermarks=pipeline.ignore_watermarks,
                image_names=set(pipeline.image_names)))
    finally:
        pycolmap.logging.minloglevel = level
    num_images = cache.num_images()
    if num_images < 2:
        raise InputError(f"the database {database_path} holds {num_images} image(s) with "
                         "matches: nothing to map")
    adjust = global_adjustment or ModelGlobalAdjustment(store, gnss, options, mapper_options)
    controller = pycolmap.IncrementalPipeline(pipeline, cache, pycolmap.ReconstructionManager())
    mapper_opts = pipeline.get_mapper()
    tri = pipeline.get_triangulation()
    bar = tqdm(total=num_images, desc="map", unit="img", disable=not progress)

    def show(rec: pycolmap.Reconstruction, record: GlobalAdjustmentRecord | None = None
             ) -> None:
        bar.n = int(rec.num_reg_images())
        if record is not None:
            bar.set_postfix(rms="-" if record.rms is None else f"{record.rms:.4f}",
                            planes=record.num_planes, assigned=record.num_assigned,
                            ba=record.kind)
        bar.refresh()

    warnings: list[str] = []
    seeds: list[int] = []
    if gnss is not None and mapper_options.start_at_gnss and pipeline.init_image_id1 == -1:
        graph = cache.correspondence_graph
        names = set(gnss.image_names)
        seeds = sorted((i for i, image in cache.images.items() if image.name in names),
                       key=lambda i: -graph.num_correspondences_for_image(i))
    pycolmap.logging.minloglevel = max(level, 1)

    # COLMAP's smallest model worth keeping among several (IncrementalPipeline): a model that
    # stops short of it is dropped for the next initial pair; only when every pair and each
    # relaxation below gives a smaller one is the first such model kept.
    min_size = max(2, min(pipeline.min_model_size, int(0.8 * num_images)))

    def attempt(size: int) -> pycolmap.Reconstruction | None:
        # a new mapper each time, as COLMAP's: it tries each initial pair and image only so
        # often (init_max_reg_trials), and a relaxed search must see them all again
        return _trials(pycolmap.IncrementalMapper(cache), mapper_opts, pipeline, controller,
                       adjust, tri, show, seeds, min_size=size,
                       reset=lambda: adjust.__init__(store, gnss, options, mapper_options))

    try:
        rec = _relaxed(attempt, mapper_opts, min_size)
    finally:
        pycolmap.logging.minloglevel = level
        bar.close()
    if rec is None or rec.num_reg_images() == 0:
        raise CityModelError(f"COLMAP found no initial image pair in {database_path}: "
                             "too few verified matches to map")
    missing = num_images - int(rec.num_reg_images())
    if missing:
        warnings.append(f"{missing} of {num_images} images not registered")
        logger.warning("mapping: %d of %d images not registered", missing, num_images)
    if not adjust.georegistered:
        warnings.append(f"the block was never georegistered during mapping (fewer than "
                        f"{mapper_options.min_gnss_images} registered images with GNSS): "
                        "COLMAP's global adjustments only")
    return MappedBlock(rec, adjust.georegistered_at, num_images, adjust.records,
                       time.perf_counter() - start, warnings)


#: At most this many images with GNSS are tried as the first image of the initial pair.
MAX_GNSS_SEEDS = 20
#: As COLMAP's IncrementalPipeline: how often the initial pair's constraints are relaxed (each
#: time the inliers, then the triangulation angle halved) when no model could be started.
NUM_INIT_RELAXATIONS = 2


def _relaxed(attempt, mapper_opts, min_size: int) -> pycolmap.Reconstruction | None:
    """`attempt(min_size)`, and as COLMAP's IncrementalPipeline, without a model, again with
    the initial pair's inliers, then its triangulation angle halved (twice each); at last
    `attempt(2)`: a model smaller than `min_size` rather than none."""
    rec = attempt(min_size)
    for name in ("init_min_num_inliers", "init_min_tri_angle") * NUM_INIT_RELAXATIONS:
        if rec is not None:
            return rec
        value = getattr(mapper_opts, name)
        setattr(mapper_opts, name, value // 2 if isinstance(value, int) else value / 2)
        logger.info("mapping: no model of %d images yet; COLMAP's relaxed initial pair: "
                    "init_min_num_inliers %d, init_min_tri_angle %.1f deg", min_size,
                    mapper_opts.init_min_num_inliers, mapper_opts.init_min_tri_angle)
        rec = attempt(min_size)
    return attempt(2) if rec is None and min_size > 2 else rec


def _trials(mapper, mapper_opts, pipeline, controller, adjust, tri, show, seeds, *,
            reset, min_size: int = 2) -> pycolmap.Reconstruction | None:
    """COLMAP's trials of initial pairs until one grows into a model of at least `min_size`
    images (`reset`: a fresh global adjustment after a model that stopped short of it; the
    mapper tries each initial pair once). Returns the model, or None."""
    for _ in range(pipeline.init_num_trials):
        rec = pycolmap.Reconstruction()
        mapper.begin_reconstruction(rec)
        status = _initialize(mapper, mapper_opts, pipeline, rec, seeds)
        if status != "ok":
            mapper.end_reconstruction(True)
            if status == "no_pair":
                return None
            continue  # a bad pair: COLMAP's next initial pair
        show(rec, adjust.records[-1] if adjust.records else None)
        status = _grow(mapper, mapper_opts, pipeline, controller, rec, adjust, tri, show,
                       min_size)
        if status == "bad_model":
            mapper.end_reconstruction(True)
            reset()
            continue
        mapper.end_reconstruction(False)
        return rec
    return None


def _initialize(mapper, mapper_opts, pipeline, rec, seeds: list[int]) -> str:
    """COLMAP's initial pair: find (first with one of the `seeds` images), register,
    triangulate, global BA (COLMAP's), filter. Returns "ok", "no_pair" (none left to try) or
    "bad_pair"."""
    found = None
    for seed in seeds[:MAX_GNSS_SEEDS]:
        found = mapper.find_initial_image_pair(mapper_opts, seed, -1)
        if found is not None:
            break
    if found is None:
        found = mapper.find_initial_image_pair(mapper_opts, pipeline.init_image_id1,
                                               pipeline.init_image_id2)
    if found is None:
        return "no_pair"
    (id1, id2), cam2_from_cam1 = found
    mapper.register_initial_image_pair(mapper_opts, id1, id2, cam2_from_cam1)
    for image_id in (id1, id2):
        _triangulate_frame(mapper, pipeline.get_triangulation(), rec, image_id)
    mapper.adjust_global_bundle(mapper_opts, pipeline.get_global_bundle_adjustment())
    rec.normalize()
    mapper.filter_points(mapper_opts)
    mapper.filter_frames(mapper_opts)
    return "ok" if rec.num_reg_frames() > 0 and rec.num_points3D() > 0 else "bad_pair"


def _triangulate_frame(mapper, tri, rec, image_id: int) -> None:
    for data_id in rec.image(image_id).frame.data_ids:
        if data_id.sensor_id.type == pycolmap.SensorType.CAMERA:
            mapper.triangulate_image(tri, data_id.id)


def _grow(mapper, mapper_opts, pipeline, controller, rec, adjust, tri, show,
          min_size: int = 2) -> str:
    """COLMAP's ReconstructSubModel after the initial pair, with `adjust` as the global
    refinement. Returns "ok", or "bad_model" when a young model stops growing."""
    ba_prev_frames, ba_prev_points = rec.num_reg_frames(), rec.num_points3D()
    success = previous_success = True
    while success or previous_success:
        previous_success, success = success, False
        next_images = mapper.find_next_images(mapper_opts, False)
        if not next_images:
            break
        image_id = None
        for trial, candidate in enumerate(next_images):
            if mapper.register_next_image(mapper_opts, candidate):
                success, image_id = True, candidate
                break
            if trial >= MIN_NUM_INITIAL_REG_TRIALS and \
                    rec.num_reg_frames() < pipeline.min_model_size:
                break
        if success:
            _triangulate_frame(mapper, tri, rec, image_id)
            mapper.iterative_local_refinement(
                pipeline.ba_local_max_refinements, pipeline.ba_local_max_refinement_change,
                mapper_opts, pipeline.get_local_bundle_adjustment(), tri, image_id)
            record = None
            if controller.check_run_global_refinement(rec, ba_prev_frames, ba_prev_points):
                record = adjust(mapper, pipeline)
                ba_prev_frames, ba_prev_points = rec.num_reg_frames(), rec.num_points3D()
            show(rec, record)
        elif previous_success:
            show(rec, adjust(mapper, pipeline))
    if rec.num_reg_frames() < min_size:
        return "bad_model"
    if rec.num_reg_frames() != ba_prev_frames or rec.num_points3D() != ba_prev_points:
        show(rec, adjust(mapper, pipeline))
    return "ok"


def refine_mapped(mapped: MappedBlock, store: PlaneStore, gnss, options: RefineOptions, *,
                  initial_transform: pycolmap.Sim3d | None = None, **kwargs) -> RefineResult:
    """refine's final adjustment, quality gate and precision on the mapped block. A block
    georegistered during mapping is already in the model's local frame and on the model:
    refine starts there (its georegistration is that frame's shift to the CRS, no GNSS fit and
    no coarse search again). The other keyword arguments are workflow.refine's."""
    if mapped.georegistered and initial_transform is None:
        initial_transform = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), store.origin)
    result = refine(mapped.reconstruction, store, gnss, options,
                    initial_transform=initial_transform, **kwargs)
    result.warnings += mapped.warnings
    return result


# -- the command -------------------------------------------------------------------------------

def main(database_path, image_path, citymodel, output_path, *, output_type="bin",
         output_frame="crs", progress=True, lod=2, model_crs=None, mapper_options=None,
         min_gnss_images=None, hybrid_iterations=None, start_at_gnss=False,
         matcher="exhaustive",
         camera_model=None, single_camera=False, extraction_options=None,
         matching_options=None, database=None, **kwargs) -> tuple[RefineResult, MappedBlock]:
    """`colmap-citymodel map`: features and matches if the database has none, incremental
    mapping with the model, then refine's final adjustment and outputs (atomically into the new
    `output_path`). `mapper_options`, `extraction_options`, `matching_options`: KEY=VALUE
    strings for pycolmap's IncrementalPipelineOptions, FeatureExtractionOptions,
    FeatureMatchingOptions. GNSS comes from the database's pose priors unless `gnss`/`exif`
    name another source; the other keyword arguments are workflow.read_inputs's."""
    database_path = Path(database_path)
    image_path = Path(image_path)
    if not database_path.is_file():
        raise InputError(f"the database {database_path} does not exist")
    pipeline = pipeline_options(parse_option_values(mapper_options, "--mapper_options"),
                                num_threads=kwargs.get("num_threads"))
    extraction = parse_option_values(extraction_options, "--extraction_options")
    matching = parse_option_values(matching_options, "--matching_options")
    images, with_keypoints, pairs = database_state(database_path)
    if with_keypoints == 0 and not image_path.is_dir():  # before reading anything else
        raise InputError(f"the database {database_path} holds no features and the image "
                         f"directory {image_path} does not exist: nothing to extract them from")
    if kwargs.get("gnss") is None and kwargs.get("exif") is None:
        database = database if database is not None else database_path
    read = read_inputs(citymodel, output_path, lod=lod, model_crs=model_crs, database=database,
                       **kwargs)
    read.inputs = {"database_path": str(database_path), "image_path": str(image_path),
                   **read.inputs}
    if with_keypoints == 0:
        extract_and_match(database_path, image_path, matcher=matcher, camera_model=camera_model,
                          single_camera=single_camera, extraction=extraction, matching=matching)
    elif pairs == 0:
        logger.info("the database has keypoints but no verified pairs: %s matching", matcher)
        match = {"exhaustive": pycolmap.match_exhaustive,
                 "sequential": pycolmap.match_sequential,
                 "spatial": pycolmap.match_spatial}[matcher]
        match(database_path, matching_options=merged_options(
            pycolmap.FeatureMatchingOptions(), matching, "--matching_options"))
    mapper_opts = MapperOptions()
    if min_gnss_images is not None:
        mapper_opts.min_gnss_images = int(min_gnss_images)
    if hybrid_iterations is not None:
        mapper_opts.hybrid_iterations = int(hybrid_iterations)
    mapper_opts.start_at_gnss = bool(start_at_gnss)
    mapped = map_block(database_path, read.store, read.observations, read.options, mapper_opts,
                       pipeline, image_path=image_path, progress=progress)
    print(f"mapped {mapped.reconstruction.num_reg_images()} of {mapped.num_database_images} "
          f"images in {mapped.seconds:.0f} s: {len(mapped.adjustments)} global adjustments, "
          f"{mapped.num_hybrid} of them with the model"
          + (f" (from {mapped.georegistered_at} images on)" if mapped.georegistered else ""))
    result = refine_mapped(mapped, read.store, read.observations, read.options,
                           initial_transform=read.initial_transform, progress=progress,
                           checkpoints=read.checkpoints,
                           checkpoint_observations=read.checkpoint_observations)
    write_outputs(result, output_path, read, output_type=output_type,
                  output_frame=output_frame, lod=lod, model_crs=model_crs, what="mapped")
    return result, mapped

