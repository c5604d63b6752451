"""`colmap-citymodel run`: a folder of photographs, a city model and an output directory in; a
refined, georeferenced COLMAP model with refine's report out.

Steps (each logged with its time, recorded in `run.json`, and reused by a later run in the
same output directory):

1. inputs: the images' EXIF and XMP (`images.csv`: position, sigma, RTK status, attitude,
   camera), the city model and the GNSS in its CRS (workflow.read_inputs; GNSS from the
   images unless `--gnss FILE`);
2. features: COLMAP's SIFT of the images `database.db` lacks (pipeline.features);
3. matches: the run's GNSS as the database's pose priors, then COLMAP's matching of the pairs
   the chosen matcher gives and the database lacks (pipeline.matching);
4. mapping: COLMAP's incremental mapping with the city model in its global bundle adjustments
   (mapper.map_block) into `sparse/0`, in the model CRS once georegistered (`mapping.json`
   says which frame); reused while the database holds the same images;
5. refine: refine on the mapped block (workflow.refine) into `refined/` (report.md/.json/.html
   and refine's other outputs); an earlier `refined/` is replaced once the new one is written;
6. the report: `run.json` with the steps, the matcher and why, the GNSS sources, and how far
   the refined cameras look from the drone's gimbal attitude where the images carry one.

Output directory: `database.db`, `images.csv`, `sparse/0/`, `mapping.json`, `refined/`,
`run.json`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..errors import InputError
from ..mapper import map_block, merged_options, parse_option_values, pipeline_options
from ..options import MapperOptions
from ..workflow import (RefineInputs, add_sequence_check, read_inputs, refine,
                        write_failed_report, write_outputs)
from .features import extract, images_with_features, reader_options
from .images import CAMERA_MODES, ImageFolder, read_image_folder, write_images_csv
from .matching import MatcherChoice, choose_matcher, match, sync_pose_priors
from .options import RunOptions
from .state import RunState, Step, write_text_atomic

logger = logging.getLogger(__name__)

DATABASE_NAME = "database.db"
MAPPING_NAME = "mapping.json"
REFINED_NAME = "refined"
#: Where an earlier run's `refined/` waits while a new refine runs (deleted once it succeeded).
PREVIOUS_REFINED_NAME = "refined.previous"
#: The steps after which `stop_after` can end a run.
STOP_AFTER = ("features", "matches", "mapping")


@dataclass
class RunResult:
    """What `run` did: its steps, the matcher, the mapping, refine's result (None when a
    model-only georegistration failed before one)."""

    output_path: Path
    steps: list[Step]
    images: dict
    matcher: MatcherChoice | None = None
    mapping: dict = field(default_factory=dict)
    result: object = None  # output.result.RefineResult
    attitude: dict | None = None

    @property
    def verdict(self) -> str | None:
        """refine's verdict; None for a run stopped before refine."""
        return self.result.quality.verdict if self.result is not None else None

    def todict(self) -> dict:
        out = {"output_path": str(self.output_path), "images": self.images,
               "steps": [s.todict() for s in self.steps],
               "matcher": self.matcher.todict() if self.matcher else None,
               "mapping": {k: v for k, v in self.mapping.items()
                           if k not in ("database_names", "options", "global_adjustments")},
               "attitude": self.attitude, "verdict": self.verdict}
        if self.result is not None:
            out["registered_images"] = int(self.result.reconstruction.num_reg_images())
            out["report"] = str(self.output_path / REFINED_NAME / "report.json")
        return out


def colmap_options(cls, items: list[str] | None, what: str, num_threads: int | None = None):
    """pycolmap's option object `cls` with the KEY=VALUE strings `items` merged in."""
    options = cls()
    if num_threads is not None:
        options.num_threads = int(num_threads)
    return merged_options(options, parse_option_values(items, what), what)


def main(image_path, citymodel, output_path, *, gnss=None, gnss_crs=None, matcher="auto",
         camera_mode="auto", camera_model=None, camera_params=None, extraction_options=None,
         matching_options=None, mapper_options=None, min_gnss_images=None,
         hybrid_iterations=None, start_at_gnss=False, num_threads=None, location=None,
         location_radius=100.0, sequence=False, progress=True, output_type="bin",
         output_frame="crs", lod=2, model_crs=None, stop_after: str | None = None,
         options: RunOptions | None = None, **kwargs) -> RunResult:
    """`colmap-citymodel run` (module docstring). `image_path`: the folder of photographs;
    `citymodel`: CityGML/CityJSON files, tile directories or archives; `output_path`: the run
    directory (created; a later run with the same one resumes). `gnss`/`gnss_crs`: a GNSS text
    file instead of the images' EXIF/XMP. `matcher`: "auto" (pipeline.matching), "exhaustive",
    "spatial" or "sequential". `camera_mode`: "auto" (a camera per camera body and image
    size), "single" or "per_image"; `camera_model`, `camera_params`: COLMAP's image reader.
    `extraction_options`, `matching_options`, `mapper_options`: KEY=VALUE strings for
    pycolmap's FeatureExtractionOptions, FeatureMatchingOptions, IncrementalPipelineOptions.
    `min_gnss_images`, `hybrid_iterations`, `start_at_gnss`: MapperOptions. `stop_after`:
    "features", "matches" or "mapping" ends the run after that step (a later run goes on from
    there). `location`, `location_radius`, `sequence` and the other keyword arguments:
    refine's (workflow.read_inputs, workflow.main)."""
    image_path, output_path = Path(image_path), Path(output_path)
    options = options or RunOptions()
    if stop_after not in (None, *STOP_AFTER):
        raise InputError(f"--stop_after takes {', '.join(STOP_AFTER)}, got {stop_after!r}")
    if camera_mode not in CAMERA_MODES:
        raise InputError(f"--camera_mode takes {', '.join(CAMERA_MODES)}, got {camera_mode!r}")
    reader_options(camera_model, camera_params)  # bad camera options fail before any work
    if not image_path.is_dir():
        raise InputError("image directory does not exist", image_path)
    extraction, matching, user_values, pipeline = _colmap_settings(
        extraction_options, matching_options, mapper_options, num_threads)
    mapper = _mapper_options(min_gnss_images, hybrid_iterations, start_at_gnss)
    state = RunState.open(output_path)
    state.info = {"image_path": str(image_path),
                  "citymodel": [str(p) for p in np.atleast_1d(citymodel)]}
    database = output_path / DATABASE_NAME
    with state.step("inputs") as step:
        folder, read = _inputs(image_path, citymodel, output_path, step, gnss=gnss,
                               gnss_crs=gnss_crs, location=location,
                               location_radius=location_radius, lod=lod, model_crs=model_crs,
                               num_threads=num_threads, progress=progress, **kwargs)
    run = RunResult(output_path, state.steps, folder.summary())
    try:
        rec = _colmap_steps(run, state, folder, read, database, stop_after, options, progress,
                            dict(camera_mode=camera_mode, camera_model=camera_model,
                                 camera_params=camera_params, extraction=extraction),
                            matcher, matching, mapper, pipeline, user_values)
        if stop_after is not None:
            _restore_previous(output_path)
            print(state.table())
            return run
        with state.step("refine") as step:
            run.result = _refine(rec, run.mapping, read, output_path, step, location=location,
                                 location_radius=location_radius, sequence=sequence,
                                 progress=progress, output_type=output_type,
                                 output_frame=output_frame, lod=lod, model_crs=model_crs)
    except BaseException:
        _restore_previous(output_path)  # no new result: the earlier one, as it was
        raise
    with state.step("report") as step:
        run.attitude = attitude_check(run.result.reconstruction, folder, read.store)
        step.details = {"attitude": run.attitude, "summary": _attitude_line(run.attitude)}
        state.info["result"] = {k: v for k, v in run.todict().items() if k != "steps"}
    print(state.table())
    return run


def _colmap_settings(extraction_options, matching_options, mapper_options, num_threads):
    """pycolmap's extraction and matching options, the user's mapper values and COLMAP's
    incremental pipeline options (InputError for a bad KEY=VALUE)."""
    extraction = colmap_options(pycolmap.FeatureExtractionOptions, extraction_options,
                                "--extraction_options", num_threads)
    matching = colmap_options(pycolmap.FeatureMatchingOptions, matching_options,
                              "--matching_options", num_threads)
    user_values = parse_option_values(mapper_options, "--mapper_options")
    return extraction, matching, user_values, pipeline_options(user_values,
                                                               num_threads=num_threads)


def _colmap_steps(run: RunResult, state: RunState, folder: ImageFolder, read: RefineInputs,
                  database: Path, stop_after, options: RunOptions, progress: bool,
                  cameras: dict, matcher: str, matching, mapper: MapperOptions, pipeline,
                  user_values: dict) -> pycolmap.Reconstruction | None:
    """Features, matches and mapping (up to `stop_after`); the mapped block, or None."""
    output_path = state.path.parent
    with state.step("features") as step:
        step.details = extract(folder, database, state, **cameras, options=options,
                               progress=progress)
        step.status = "reused" if step.details["extracted"] == 0 else "done"
    if stop_after == "features":
        return None
    with state.step("matches") as step:
        run.matcher = _match(folder, read, database, output_path, step, matcher, matching,
                             options, progress)
    if stop_after == "matches":
        return None
    with state.step("mapping") as step:
        rec, run.mapping = _mapping(database, output_path, folder, read, mapper, pipeline,
                                    step, progress, options, user_values)
    return rec


def _restore_previous(output_path: Path) -> None:
    """An earlier run's refined/ back in its place (a run that stops or fails before refine
    has written a new one)."""
    refined, previous = output_path / REFINED_NAME, output_path / PREVIOUS_REFINED_NAME
    if previous.exists() and not refined.exists():
        os.replace(previous, refined)


def _mapper_options(min_gnss_images, hybrid_iterations, start_at_gnss) -> MapperOptions:
    out = MapperOptions()
    if min_gnss_images is not None:
        out.min_gnss_images = int(min_gnss_images)
    if hybrid_iterations is not None:
        out.hybrid_iterations = int(hybrid_iterations)
    out.start_at_gnss = bool(start_at_gnss)
    return out


# -- 1. inputs ------------------------------------------------------------------------------------

def _inputs(image_path: Path, citymodel, output_path: Path, step: Step, *, gnss, gnss_crs,
            location, progress, **kwargs) -> tuple[ImageFolder, RefineInputs]:
    """The images' metadata (images.csv), the city model and the GNSS (workflow.read_inputs).
    An earlier run's refined/ is moved aside first (refine writes a new one)."""
    folder = read_image_folder(image_path, progress)
    write_images_csv(folder, output_path / "images.csv")
    located = folder.with_position()
    if gnss is None and not located and location is None:
        raise InputError(f"none of the {len(folder.names)} images has an EXIF/XMP GPS "
                         "position: give --gnss FILE, or --location X Y", image_path)
    refined, previous = output_path / REFINED_NAME, output_path / PREVIOUS_REFINED_NAME
    if refined.exists():
        shutil.rmtree(previous, ignore_errors=True)
        os.replace(refined, previous)
        logger.info("the earlier result %s waits in %s until refine has written a new one",
                    refined, previous)
    source = {"gnss": gnss, "gnss_crs": gnss_crs} if gnss is not None else (
        {"exif": image_path} if located else {})
    read = read_inputs(citymodel, refined, location=location, **source, **kwargs)
    read.inputs = {"image_path": str(image_path), "run_path": str(output_path), **read.inputs}
    summary = folder.summary()
    rtk = ", ".join(f"{n} {status}" for status, n in summary["rtk"].items())
    step.details = {"metadata": summary, "gnss_source": read.inputs.get("gnss_source"),
                    "model_crs": read.store.crs.label, "model_faces": int(read.store.num_faces),
                    "summary": f"{len(folder.names)} images, {len(located)} with a position"
                               + (f" (RTK: {rtk})" if rtk else "")
                               + f"; {read.store.num_buildings} buildings"}
    return folder, read


# -- 3. matches -----------------------------------------------------------------------------------

def _match(folder: ImageFolder, read: RefineInputs, database: Path, output_path: Path,
           step: Step, matcher: str, matching, options: RunOptions, progress: bool
           ) -> MatcherChoice:
    """The run's GNSS into the database's pose priors, the matcher's choice, the matching."""
    names = sorted(images_with_features(database))
    gnss_xy: dict[str, np.ndarray] = {}
    if read.observations is not None:
        written = sync_pose_priors(database, read.observations)
        logger.info("matches: %d GNSS positions written as the database's pose priors "
                    "(model CRS)", written)
        positions = dict(zip(read.observations.image_names, read.observations.positions))
        gnss_xy = {n: positions[n][:2] for n in names if n in positions}
    choice = choose_matcher(names, gnss_xy, options.matching, matcher)
    logger.info("matches: %s matcher (%s)", choice.matcher, choice.reason)
    step.details = match(database, choice, output_path, matching=matching, options=options,
                         progress=progress)
    step.status = "reused" if step.details["matched"] == 0 else "done"
    return choice


# -- 4. mapping -----------------------------------------------------------------------------------

def _names_key(names: list[str]) -> str:
    return hashlib.sha1("\n".join(sorted(names)).encode()).hexdigest()


def _mapping(database: Path, output_path: Path, folder: ImageFolder, read: RefineInputs,
             mapper: MapperOptions, pipeline, step: Step, progress: bool,
             options: RunOptions, user_values: dict) -> tuple[pycolmap.Reconstruction, dict]:
    """The mapped block of `sparse/0` when an earlier run mapped the same database images in
    the same model CRS with the same options, else COLMAP's incremental mapping with the
    model (`_map`), written to `sparse/0` (model CRS once georegistered) and `mapping.json`."""
    names = sorted(images_with_features(database))
    sparse, record_path = output_path / "sparse" / "0", output_path / MAPPING_NAME
    record = _read_record(record_path)
    setup = _names_key([json.dumps(pipeline.todict(), sort_keys=True, default=str),
                        json.dumps(mapper.__dict__, sort_keys=True)])
    if (record.get("database_names") == _names_key(names) and record.get("crs") ==
            read.store.crs.label and record.get("options") == setup
            and (sparse / "images.bin").exists()):
        step.status = "reused"
        step.details = {"summary": f"{record['num_registered_images']} of "
                                   f"{record['num_database_images']} images (earlier run)"}
        return pycolmap.Reconstruction(sparse), record
    mapped, attempts = _map(database, folder, read, mapper, pipeline, progress, options,
                            user_values)
    rec = mapped.reconstruction
    if mapped.georegistered:  # the store's local frame -> model CRS coordinates
        rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), read.store.origin))
    _write_model(rec, output_path / "sparse")
    record = {**mapped.todict(), "frame": "crs" if mapped.georegistered else "colmap",
              "crs": read.store.crs.label, "database_names": _names_key(names),
              "options": setup, "attempts": attempts, "warnings": list(mapped.warnings)}
    write_text_atomic(record_path, json.dumps(record, indent=2))
    step.details = {k: record[k] for k in ("num_database_images", "num_registered_images",
                                           "georegistered_at_images", "num_hybrid_adjustments",
                                           "attempts")}
    step.details["summary"] = (f"{record['num_registered_images']} of "
                               f"{record['num_database_images']} images registered, "
                               f"{mapped.num_hybrid} global adjustments with the model")
    return rec, record


def _map(database: Path, folder: ImageFolder, read: RefineInputs, mapper: MapperOptions,
         pipeline, progress: bool, options: RunOptions, user_values: dict):
    """mapper.map_block; while it registers less than `options.remap_below` of the images,
    again with another random seed, every other time with the small-parallax settings
    (RunOptions), the largest block kept. Returns (MappedBlock, [{settings, random_seed,
    registered} of each attempt])."""
    seed = pipeline.random_seed
    colmap = {group: {key: getattr(getattr(pipeline, group), key) for key in values}
              for group, values in options.small_parallax().items()}
    small = {group: {key: value for key, value in values.items()
                     if key not in user_values.get(group, {})}
             for group, values in options.small_parallax().items()}
    attempts, best = [], None
    try:
        for k in range(1 + options.remap_attempts):
            settings = small if k % 2 else colmap
            _set_pipeline(pipeline, settings)
            pipeline.random_seed = seed if k == 0 else max(seed, 0) + k
            if k:
                logger.info("mapping: %d of %d images registered; mapping again with %s "
                            "settings, random seed %d (RunOptions.remap_attempts)",
                            best.reconstruction.num_reg_images(), best.num_database_images,
                            "small-parallax" if k % 2 else "COLMAP's", pipeline.random_seed)
            mapped = map_block(database, read.store, read.observations, read.options, mapper,
                               pipeline, image_path=folder.path, progress=progress)
            registered = int(mapped.reconstruction.num_reg_images())
            attempts.append({"settings": "small_parallax" if k % 2 else "colmap",
                             "random_seed": pipeline.random_seed, "registered": registered})
            if best is None or registered > best.reconstruction.num_reg_images():
                best = mapped
            if registered >= options.remap_below * mapped.num_database_images:
                break
    finally:
        _set_pipeline(pipeline, colmap)
        pipeline.random_seed = seed
    return best, attempts


def _set_pipeline(pipeline, values: dict) -> None:
    for group, settings in values.items():
        for key, value in settings.items():
            setattr(getattr(pipeline, group), key, value)


def _read_record(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def _write_model(rec: pycolmap.Reconstruction, sparse: Path) -> None:
    """`rec` into `sparse`/0, replacing what was there only once it is written whole."""
    scratch = Path(tempfile.mkdtemp(prefix=".sparse.", dir=sparse.parent))
    try:
        (scratch / "0").mkdir()
        rec.write(scratch / "0")
        if sparse.exists():
            shutil.rmtree(sparse)
        os.replace(scratch, sparse)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


# -- 5. refine ------------------------------------------------------------------------------------

def _refine(rec: pycolmap.Reconstruction, mapping: dict, read: RefineInputs, output_path: Path,
            step: Step, *, location, location_radius, sequence, progress, output_type,
            output_frame, lod, model_crs):
    """refine on the mapped block into refined/; the earlier result, moved aside by the inputs
    step, is deleted once this one is there. With GNSS, refine georegisters the whole block
    itself (`start_transform`); without, it starts where mapping placed it on the model."""
    from ..align.locate import ModelOnlyFailure

    refined = output_path / REFINED_NAME
    initial = start_transform(mapping, read)
    try:
        result = refine(rec, read.store, read.observations, read.options,
                        initial_transform=initial, progress=progress,
                        checkpoints=read.checkpoints,
                        checkpoint_observations=read.checkpoint_observations,
                        location=location, location_radius=location_radius)
    except ModelOnlyFailure as error:  # no result: the report says why
        write_failed_report(refined, read.inputs, error)
        shutil.rmtree(output_path / PREVIOUS_REFINED_NAME, ignore_errors=True)
        raise
    result.warnings += mapping.get("warnings", [])
    if sequence:
        add_sequence_check(result)
    write_outputs(result, refined, read, output_type=output_type, output_frame=output_frame,
                  lod=lod, model_crs=model_crs, what="mapped")
    shutil.rmtree(output_path / PREVIOUS_REFINED_NAME, ignore_errors=True)
    step.details = {"verdict": result.quality.verdict, "reasons": list(result.quality.reasons),
                    "result": result.handed_back,
                    "summary": f"quality {result.quality.verdict}"}
    return result


def start_transform(mapping: dict, read: RefineInputs) -> pycolmap.Sim3d | None:
    """refine's `initial_transform` for the mapped block: None (refine fits the block to GNSS
    itself) where there is GNSS, also where mapping georegistered the block: mapping did so at
    its first images with GNSS (MapperOptions.min_gnss_images), where a short, nearly straight
    track leaves the rotation about it to the few tie points seen by then (a street's mapped
    block rolled by 19 deg there), while refine's fit takes every image and, along a straight
    track, the roll from all the walls and the ground (align.georegister). Without GNSS: the
    identity where mapping placed the block on the model (model CRS). A block mapping left in
    COLMAP's frame: the user's transform, if any."""
    if mapping.get("frame") != "crs":
        return read.initial_transform
    return None if read.observations is not None else pycolmap.Sim3d()


# -- 6. the report --------------------------------------------------------------------------------

def attitude_check(rec: pycolmap.Reconstruction, folder: ImageFolder, store) -> dict | None:
    """How far the viewing direction of each registered camera of `rec` (the store's local
    frame) lies from the one its gimbal attitude gives (block.image_metadata.attitude_view;
    true north turned to grid north at the block): the median, 90th percentile and largest
    angle in degrees, and the five largest.
    None when no registered image carries a gimbal attitude."""
    from ..block.image_metadata import attitude_view

    gimbal = {m.name: m.gimbal for m in folder.metadata if m.gimbal is not None}
    images = [rec.image(i) for i in rec.reg_image_ids() if rec.image(i).name in gimbal]
    if not images:
        return None
    centres = np.array([image.projection_center() for image in images])  # local frame
    turn = _grid_north_turn(centres.mean(0) + store.origin, store.crs)
    angles = {}
    for image in images:
        yaw, pitch, _ = gimbal[image.name]
        expected = attitude_view(yaw + turn, pitch)
        view = image.cam_from_world().rotation.matrix().T @ np.array([0.0, 0.0, 1.0])
        angles[image.name] = float(np.degrees(np.arccos(np.clip(view @ expected, -1, 1))))
    values = np.array(list(angles.values()))
    worst = sorted(angles.items(), key=lambda kv: -kv[1])[:5]
    return {"images": len(values), "median_deg": round(float(np.median(values)), 2),
            "p90_deg": round(float(np.percentile(values, 90)), 2),
            "max_deg": round(float(values.max()), 2), "grid_north_turn_deg": round(turn, 3),
            "largest": [{"image": n, "deg": round(a, 2)} for n, a in worst]}


def _grid_north_turn(xyz: np.ndarray, crs) -> float:
    """Degrees to add to a true azimuth at `xyz` (model CRS) to get the grid azimuth."""
    from pyproj import CRS, Transformer

    from ..block.gnss import _pyproj_crs

    crs = _pyproj_crs(crs)
    horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
    to_geo = Transformer.from_crs(horizontal, CRS.from_epsg(4326), always_xy=True)
    to_grid = Transformer.from_crs(CRS.from_epsg(4326), horizontal, always_xy=True)
    lon, lat = to_geo.transform(xyz[0], xyz[1])
    east, north = to_grid.transform(lon, lat + 1e-4)
    return float(np.degrees(np.arctan2(east - xyz[0], north - xyz[1])))


def _attitude_line(attitude: dict | None) -> str:
    if attitude is None:
        return "no gimbal attitude in the images"
    return (f"cameras {attitude['median_deg']:.1f} deg (median), {attitude['max_deg']:.1f} deg "
            f"(largest) from their gimbal attitude, {attitude['images']} images")
