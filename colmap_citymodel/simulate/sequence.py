"""Simulated UAV flights through city models, mapped by COLMAP (Unger chapter 5): one sequence
from a scenario file (scenario.py), and the scenario variants derived from it.

`colmap-citymodel simulate SCENARIO.toml --output_path WORKSPACE [--seed N]` builds a COLMAP
workspace whose drift is COLMAP's own:

1. Scene (scene.py): the given LOD2 model (a real CityGML/CityJSON file or a procedural
   street) and the true scene = model + generalisation effects (facade relief, recessed doors,
   balconies, roof overhangs, roof furniture, trees, cars, terrain) as a triangle mesh.
2. Flight (flight.py): key frames >= 1 m apart along a loop around the buildings (their footprints buffered
   by the facade distance), 5-15 m from the facades with a height profile, the camera looking
   sideways at the facades and tilted down (DJI Zenmuse X3 class: 4096 x 2160 px, f = 2400 px);
   or looking forward along the path; or along a given polyline of waypoints (a vehicle drive,
   a straight strip); or an orbit: one full circle around a centre, looking inward and down.
3. Observations (observations.py): points sampled on the true surfaces, visibility by ray casting (open3d) against
   the true mesh with distance and incidence limits, tracks broken by large viewpoint changes,
   detection losses and gaps, tracks of >= 3 views, 1 px image noise, unmatched keypoints and a
   few percent wrong matches. Optionally an unmodelled systematic image error: the true lens has
   radial distortion `flight.radial_k1` while the database camera states
   `flight.calibrated_radial_k1` (fixed in COLMAP). Without it, COLMAP's block is nearly perfect
   (2 mm camera-centre RMS after a similarity fit over 100 m); with k1 = 0.0007-0.001 (1.5-2 px
   in the image corners) it bends like Unger's real blocks (cm over 100 m, decimetres to a metre
   over 400 m after a Helmert fit). Check points: targets on facades and roofs, observed with 1 px
   noise, kept out of the SfM data.
4. GNSS (observations.py): true projection centres + white noise (default 3, 3, 5 m, the stated a priori sigma)
   + a slowly varying bias (Gaussian-filtered noise along the path) + optionally a constant bias
   of a given magnitude in a direction drawn from the seed. The benchmark sequences use
   Unger-like filtered GNSS instead: 0.3-0.5 m white noise, a 1 m bias, stated sigma 3, 3, 5 m.
5. COLMAP (mapping.py): database (camera, rig, frames, images, keypoints, matches, pose priors), geometric
   verification by COLMAP itself (`pycolmap.verify_matches`), then COLMAP's incremental mapper ->
   `sparse/0`. The interior orientation is known and kept fixed (as in Unger 5.3).
6. Images (render/, with `--render`): the key frames rendered from the true scene with procedural
   textures, sun, sky and shadows, the true lens distortion, exposure and sensor noise, as JPEGs
   with EXIF GPS and DJI XMP from the simulated GNSS (of every key frame, as gnss_all.txt), and
   check-point targets painted on the surfaces with their image positions in
   `images/gcp_list.txt`: a folder of photographs to run from, with the truth beside it.

Frames. `truth/` and everything "local" use the model CRS minus `truth/origin.txt` (the store's
origin: the model's lower bbox corner rounded down to metres). `checkpoints.txt`, `gnss.txt` and
the database pose priors (coordinate system CARTESIAN) are in the model CRS itself, full
coordinates: COLMAP stores prior positions as float64, so UTM-sized numbers lose nothing there,
but consumers should subtract the origin before adjusting. The same targets as ground marks in
OpenDroneMap's format (block.marks): `gcp_list.txt` holds `CheckPointOptions.control` of them
spread along the flight as control marks, `checkpoints_gcp_list.txt` the others as check marks
(from the truth, with the targets' pixel noise).

Sequences and scenarios. Everything that defines the images and their observations (scene,
flight, noise, seed, mapping) is a *sequence*; a scenario only chooses the given model variant
and the GNSS availability (Unger Table 6). With `cache_path`, a sequence is built and mapped once
(directory `<cache_path>/<name>-<hash>`) and every scenario of it is derived by copying, so all
scenarios of a sequence share the same images, observations, GNSS noise and `sparse/0`.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .flight import plan_flight
from .mapping import run_mapping, truth_reconstruction, write_database
from .buildings import building_changes, given_polygons, given_store
from .observations import gnss_gross_errors, simulate_checkpoints, simulate_gnss, \
    simulate_observations
from .scenario import STAGE_DETAILED, SimulationOptions, load_scenario, sequence_key
from .scene import GroundModel, build_true_scene, detailed_polygons, perturb_planes, perturb_polygons, procedural_store

logger = logging.getLogger(__name__)



# ----------------------------------------------------------------------------------------------
# options


# ----------------------------------------------------------------------------------------------
# flight


# ----------------------------------------------------------------------------------------------
# observations


# ----------------------------------------------------------------------------------------------
# check points and GNSS


# ----------------------------------------------------------------------------------------------
# COLMAP


# ----------------------------------------------------------------------------------------------
# the sequence and the scenario workspace


def _fmt(x: float) -> str:
    return repr(float(x))


def _write_lines(path: Path, header: str, lines) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(header)
        for line in lines:
            fh.write(line)
            fh.write("\n")


def write_mark_lists(out: Path, cps, names: list[str], xyz_crs: np.ndarray, crs_label: str,
                     control: int) -> None:
    """`gcp_list.txt` (`control` of the targets, spread along the flight) and
    `checkpoints_gcp_list.txt` (the others) in OpenDroneMap's format."""
    from ..block.marks import write_gcp_list

    count = len(cps.ids)
    chosen = set(np.unique(np.round(np.linspace(0, count - 1, min(control, count))).astype(int))
                 .tolist()) if control > 0 and count else set()
    rows = {True: [], False: []}
    for f, i, (u, v) in zip(cps.obs_frame, cps.obs_id, cps.obs_uv):
        k = int(i) - int(cps.ids[0]) if count else 0
        rows[k in chosen].append((xyz_crs[k], names[f], u, v, f"CP{int(i)}"))
    for name, kind in (("gcp_list.txt", True), ("checkpoints_gcp_list.txt", False)):
        if rows[kind]:  # a file without marks would be refused
            write_gcp_list(out / name, crs_label, rows[kind])


def _load_store(options: SimulationOptions):
    if options.scene.source == "procedural":
        return procedural_store(options.scene.procedural, options.seed)
    from ..citymodel.read import read_city_model

    bbox = None
    if options.scene.bbox_crs is not None:
        b = np.asarray(options.scene.bbox_crs, dtype=np.float64)
        bbox = b.reshape(2, -1)
    return read_city_model(options.scene.source, lod=options.scene.lod, crs=options.scene.crs,
                           target_crs=options.scene.target_crs, bbox_crs=bbox)


@dataclass
class SimulatedSequence:
    """What a sequence simulates before anything is written (local coordinates)."""

    store: Any  # the given model (PlaneStore)
    ground: GroundModel
    flight: Any  # flight.Flight
    scene: Any  # scene.TrueScene
    raycaster: Any = None  # open3d RaycastingScene of the true scene
    observations: Any = None  # observations.Observations (tie points)
    checkpoints: Any = None  # observations.CheckPoints
    gnss_crs: np.ndarray | None = None  # (N,3) GNSS positions in the model CRS
    changes: Any = None  # buildings.BuildingChanges: the given model's missing and extra ones


def plan_sequence(options: SimulationOptions) -> SimulatedSequence:
    """The sequence's given model, terrain, flight and true scene (no observations yet)."""
    seed = options.seed
    store = _load_store(options)
    ground = GroundModel(store, options.details)
    flight = plan_flight(store, options.flight, seed, ground)
    logger.info("%d key frames along %.0f m of path", len(flight.names), flight.arc[-1])
    roi = options.observations.max_distance + 5.0
    scene = build_true_scene(store, options.details, seed, roi_centres=flight.centres,
                             roi_radius=roi, ground=ground, avoid_points=flight.centres)
    logger.info("true scene: %d triangles, %d clutter objects", len(scene.triangles),
                scene.num_clutter_objects)
    changes = building_changes(store, flight.centres, flight.rotations[:, 2],
                               options.observations.max_distance, options.model_errors, seed,
                               ground)
    return SimulatedSequence(store, ground, flight, scene, changes=changes)


def simulate_sequence(options: SimulationOptions, *, progress: bool = True,
                      tie_points: bool = True) -> SimulatedSequence:
    """plan_sequence, then what the cameras observe: tie points (unless `tie_points` is
    False), check points and GNSS."""
    seed = options.seed
    sim = plan_sequence(options)
    sim.raycaster = sim.scene.raycasting_scene()
    if tie_points:
        sim.observations = simulate_observations(sim.flight, sim.scene, sim.raycaster,
                                                 options.observations, seed, progress)
    sim.checkpoints = simulate_checkpoints(sim.flight, sim.scene, sim.raycaster,
                                           options.observations, options.checkpoints, seed)
    sim.gnss_crs = simulate_gnss(sim.flight, options.gnss, seed) + sim.store.origin
    return sim


def build_sequence(options: SimulationOptions, out: Path, *, progress: bool = True) -> dict:
    """Everything shared by the scenarios of a sequence, written into `out` (a new directory):
    models/, truth/, database.db with all GNSS priors, gnss_all.txt, check points, sparse/;
    with options.render.enabled also images/ (render.images.render_flight)."""
    t_start = time.perf_counter()
    out.mkdir(parents=True)
    sim = simulate_sequence(options, progress=progress)
    t_built = time.perf_counter()
    num_detailed = _write_models(sim, options, out / "models")
    _write_truth(sim, out / "truth")
    _write_checkpoints_and_gnss(sim, options, out)
    write_database(out / "database.db", sim.flight, sim.observations, sim.gnss_crs,
                   options.gnss.sigma)
    stats = _sequence_stats(sim, options, num_detailed)
    stats["build_seconds"] = t_built - t_start
    stats.update(run_mapping(out, sim.flight, sim.observations, options.mapping, options.seed))
    if options.render.enabled:
        stats["render"] = render_sequence(sim, options, out, progress=progress)
    stats["total_seconds"] = time.perf_counter() - t_start
    stats["options"] = options.sequence_dict()
    (out / "simulation.json").write_text(json.dumps(stats, indent=2, default=str))
    logger.info(
        "sequence %s: %d key frames, %d tie points, %d observations; COLMAP registered %s/%d "
        "images in %s model(s), %.0f s in total", options.name, stats["num_key_frames"],
        stats["num_tie_points"], stats["num_image_observations"],
        stats.get("num_registered_images"), stats["num_key_frames"], stats.get("num_models"),
        stats["total_seconds"])
    return stats


def render_sequence(sim: SimulatedSequence, options: SimulationOptions, out: Path, *,
                    progress: bool = True, threads: int = 0) -> dict:
    """The sequence's key frames rendered into `out`/images/ (render.images.render_flight):
    JPEGs with EXIF GPS and DJI XMP from the simulated GNSS, gcp_list.txt of the targets at
    the check points."""
    import shapely

    from .render.images import render_flight
    from .scene import building_footprints

    footprints = shapely.unary_union(list(building_footprints(sim.store).values()))
    takeoff = float(sim.ground(sim.flight.centres[:1, :2])[0])
    return render_flight(out, flight=sim.flight, scene=sim.scene, footprints=footprints,
                         sidewalk_width=options.details.sidewalk_width, takeoff_height=takeoff,
                         crs=sim.store.crs, origin=sim.store.origin, gnss_crs=sim.gnss_crs,
                         gnss_sigma=options.gnss.sigma, checkpoints=sim.checkpoints,
                         options=options.render, seed=options.seed, progress=progress,
                         threads=threads)


def _write_models(sim: SimulatedSequence, options: SimulationOptions, models: Path) -> int:
    """models/: corrected.gml (the given model), original.gml (with systematic plane errors),
    detailed.gml (the true scene's building polygons). Returns the detailed polygons' count."""
    from ..citymodel.raw_model import RawCityModel
    from ..citymodel.write_citygml import raw_from_store, write_citygml

    store, seed, origin = sim.store, options.seed, sim.store.origin
    models.mkdir()
    changes = sim.changes
    given = given_store(store, changes)
    write_citygml(models / "corrected.gml", raw_from_store(given), name="corrected (as given)")
    original = perturb_planes(given, options.model_errors, seed)
    write_citygml(models / "original.gml", raw_from_store(original),
                  name="original (systematic plane errors)")
    det = detailed_polygons(sim.scene, options.model_errors.detailed_min_area)
    if changes:
        det = given_polygons(det, changes, origin)
    det = perturb_polygons(det, options.model_errors.detailed_shift_sigma,
                           options.model_errors.detailed_rotation_sigma_deg, seed, STAGE_DETAILED)
    for i, p in enumerate(det):
        p.exterior = p.exterior + origin
        p.holes = [h + origin for h in p.holes]
        p.gml_id = f"detailed_{i}"
    srs = raw_from_store(store).crs
    write_citygml(models / "detailed.gml",
                  RawCityModel("simulate", "CityGML", "2.0", srs, det,
                               sorted({p.building_id for p in det}), []),
                  name="detailed (true scene planes)")
    return len(det)


def _write_truth(sim: SimulatedSequence, truth: Path) -> None:
    """truth/: true poses and tie points, origin.txt, the true mesh, its labels, the ground;
    the true LOD2 model where the given one lacks or adds buildings."""
    from ..citymodel.write_citygml import raw_from_store, write_citygml

    origin = sim.store.origin
    truth.mkdir()
    truth_reconstruction(sim.flight, sim.observations).write_text(str(truth))
    (truth / "origin.txt").write_text(
        "# origin X Y Z: local = model CRS - origin\n"
        f"{_fmt(origin[0])} {_fmt(origin[1])} {_fmt(origin[2])}\n"
        f"# crs: {sim.store.crs.label}\n")
    if sim.changes:  # the given model is not the truth's: keep the true LOD2 model beside it
        write_citygml(truth / "true_model.gml", raw_from_store(sim.store),
                      name="the true scene's LOD2 model")
    sim.scene.to_trimesh().export(truth / "true_scene.ply")
    np.save(truth / "true_scene_labels.npy", sim.scene.labels)
    _write_true_ground(sim.scene, origin, sim.store.crs, truth / "ground.tif")


def _write_checkpoints_and_gnss(sim: SimulatedSequence, options: SimulationOptions,
                                out: Path) -> None:
    """checkpoints.txt, checkpoint_observations.txt and gnss_all.txt (model CRS)."""
    cps, flight, label = sim.checkpoints, sim.flight, sim.store.crs.label
    cp_crs = cps.xyz + sim.store.origin
    _write_lines(out / "checkpoints.txt", f"# id X Y Z ({label})\n",
                 (f"{i} {_fmt(x)} {_fmt(y)} {_fmt(z)}" for i, (x, y, z) in zip(cps.ids, cp_crs)))
    _write_lines(out / "checkpoint_observations.txt",
                 "# image_name id x y (pixels, COLMAP convention)\n",
                 (f"{flight.names[f]} {i} {_fmt(u)} {_fmt(v)}"
                  for f, i, (u, v) in zip(cps.obs_frame, cps.obs_id, cps.obs_uv)))
    write_mark_lists(out, cps, flight.names, cp_crs, label,
                     options.checkpoints.control)
    sig = options.gnss.sigma
    _write_lines(out / "gnss_all.txt", f"# image_name X Y Z sX sY sZ ({label})\n",
                 (f"{n} {_fmt(p[0])} {_fmt(p[1])} {_fmt(p[2])} {sig[0]} {sig[1]} {sig[2]}"
                  for n, p in zip(flight.names, sim.gnss_crs)))


def _sequence_stats(sim: SimulatedSequence, options: SimulationOptions,
                    num_detailed: int) -> dict[str, Any]:
    store, flight, scene = sim.store, sim.flight, sim.scene
    obs, cps = sim.observations, sim.checkpoints
    stats = {
        "sequence": options.name,
        "seed": options.seed,
        "sequence_key": sequence_key(options),
        "crs": store.crs.label,
        "origin": [float(v) for v in store.origin],
        "num_key_frames": len(flight.names),
        "path_length_m": float(flight.arc[-1]),
        "image_size": [flight.width, flight.height],
        "focal_length_px": flight.focal,
        "num_model_faces": store.num_faces,
        "num_buildings": store.num_buildings,
        "num_true_triangles": int(len(scene.triangles)),
        "num_clutter_objects": scene.num_clutter_objects,
        "num_detailed_polygons": num_detailed,
        "num_candidate_points": obs.num_candidates,
        "num_visible_observations": obs.num_visible,
        "num_tie_points": int(len(obs.track_xyz)),
        "num_image_observations": int(len(obs.obs_track)),
        "mean_track_length_true": float(len(obs.obs_track) / max(len(obs.track_xyz), 1)),
        "num_keypoints": int(sum(len(k) for k in obs.keypoints)),
        "num_matched_pairs": len(obs.pairs),
        "num_matches": int(sum(len(m) for m in obs.pairs.values())),
        "num_outlier_matches": int(obs.num_outlier_matches),
        "num_checkpoints": int(len(cps.ids)),
        "num_checkpoint_observations": int(len(cps.obs_id)),
    }
    if sim.changes:
        stats["model_buildings"] = sim.changes.todict()
    gross = gnss_gross_errors(flight, options.gnss, options.seed)[1]
    if gross:
        stats["gnss_gross_errors"] = gross
    return stats


README = """# Simulated COLMAP workspace: {name}

Made by `colmap-citymodel simulate` (colmap_citymodel/simulate/), seed {seed},
sequence {sequence} (key {key}). Scenario: given model `{model}`, GNSS `{gnss}`.

| file | content |
|---|---|
| `database.db` | COLMAP database: camera (SIMPLE_PINHOLE, fixed), rig, frames, images, keypoints, matches incl. wrong ones, two-view geometries (COLMAP's own verification), pose priors (GNSS, model CRS, CARTESIAN, covariance diag(sigma^2)) for the images with GNSS in this scenario |
| `sparse/0` | COLMAP's incremental mapper result (arbitrary frame); `sparse/1..` only if COLMAP split the block |
| `truth/` | true poses and tie points (COLMAP text model) in the LOCAL frame = model CRS - `truth/origin.txt`; `true_scene.ply` the true mesh (same frame), `true_scene_labels.npy` its triangle labels (0 wall, 1 roof, 2 detail, 3 clutter, 4 ground); `true_model.gml` the true LOD2 model when the given one lacks or adds buildings (model_errors) |
| `given_model.gml` | the building model of this scenario (CityGML 2.0, model CRS), turned and moved when the scenario asks (model_turn_deg, model_shift); absent when the scenario has none |
| `models/` | all variants: `corrected.gml` (the LOD2 model as given: only generalisation effects), `original.gml` (plus systematic plane errors), `detailed.gml` (the true building planes, LOD3-like, stored as LOD2 surfaces) |
| `checkpoints.txt` | `id X Y Z` true check point coordinates (model CRS) |
| `checkpoint_observations.txt` | `image_name id x y` image observations of check points (1 px noise); not in the database |
| `gcp_list.txt` | some of the same targets as control marks, OpenDroneMap's format (`refine --gcp`) |
| `checkpoints_gcp_list.txt` | the other targets as check marks, the same format (`refine --checkpoints`, `evaluate --checkpoints`) |
| `gnss.txt` | `image_name X Y Z sX sY sZ` GNSS available in this scenario (model CRS) |
| `gnss_all.txt` | GNSS of every key frame (same noise realisation) |
| `scenario.toml` | the scenario file (`sequence.toml`: the sequence file it names) |
| `simulation.json` | options, sizes, timings |
| `colmap.log` | COLMAP's log |
{images}
Sizes: {frames} key frames, {tps} tie points, {obs} image observations, {cps} check points;
COLMAP registered {reg} of {frames} images ({models} model(s)).
"""


IMAGES_ROW = ("| `images/` | the key frames rendered (JPEG, EXIF GPS and DJI XMP from the GNSS of "
              "every key frame as in `gnss_all.txt`; `gcp_list.txt`: the check-point targets' "
              "image positions, OpenDroneMap's format); `render.json` their statistics |\n")


def _write_true_ground(scene, origin: np.ndarray, crs, path: Path) -> None:
    """truth/ground.tif: the true scene's ground at 1 m posts (model CRS), which a scenario's
    DTM (`scenario.dtm`) is made from."""
    from .dtm import true_ground_grid, write_grid
    from .scene import LABEL_GROUND

    ground = scene.triangles[scene.labels == LABEL_GROUND]
    if not len(ground) or crs.horizontal_epsg is None:
        return
    x0, y_top, heights = true_ground_grid(ground)
    write_grid(path, x0 + origin[0], y_top + origin[1], 1.0, heights + origin[2],
               f"EPSG:{crs.horizontal_epsg}")


def move_given_model(workspace: Path, scenario) -> None:
    """given_model.gml turned by scenario.model_turn_deg about the vertical through
    scenario.model_turn_centre (local xy; default: the true camera centres' mean), then moved
    by scenario.model_shift (ScenarioOptions)."""
    import pycolmap

    from ..citymodel.read import read_city_model
    from ..citymodel.write_citygml import raw_from_store, write_citygml

    path = workspace / "given_model.gml"
    origin = np.array([float(v) for v in (workspace / "truth" / "origin.txt").read_text()
                       .splitlines()[1].split()[:3]])
    if scenario.model_turn_centre is not None:
        centre = np.asarray(scenario.model_turn_centre, dtype=np.float64)
    else:
        truth = pycolmap.Reconstruction(str(workspace / "truth"))
        centre = np.mean([im.projection_center()[:2] for im in truth.images.values()], axis=0)
    store = read_city_model(path)
    xyz = store.to_crs(store.vertices) - origin  # the truth's local frame
    a = np.radians(scenario.model_turn_deg)
    turn = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    xyz[:, :2] = (xyz[:, :2] - centre) @ turn.T + centre
    xyz += np.asarray(scenario.model_shift, dtype=np.float64)
    moved = store.with_vertices(store.to_local(xyz + origin))
    write_citygml(path, raw_from_store(moved), name="given model, moved (a wrong datum)")


def derive_scenario(seq_dir: Path, options: SimulationOptions, out: Path) -> dict:
    """A scenario workspace from a built sequence: copies, then restricts GNSS priors and picks
    the given model."""
    import pycolmap

    shutil.copytree(seq_dir, out)
    stats = json.loads((out / "simulation.json").read_text())
    sc = options.scenario
    names, lines = [], []
    for line in (out / "gnss_all.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        names.append(line.split()[0])
        lines.append(line)
    n = len(names)
    available = np.zeros(n, dtype=bool)
    if sc.gnss == "all":
        available[:] = True
    elif sc.gnss == "first":
        available[: max(sc.gnss_first_n, 0)] = True
    if sc.gnss != "none":
        hdr = (out / "gnss_all.txt").read_text().splitlines()[0] + "\n"
        _write_lines(out / "gnss.txt", hdr, (l for l, a in zip(lines, available) if a))
    db = pycolmap.Database.open(str(out / "database.db"))
    try:
        priors = db.read_all_pose_priors()
        keep_ids = {k + 1 for k in np.flatnonzero(available)}
        db.clear_pose_priors()
        for p in priors:
            if p.corr_data_id.id in keep_ids:
                p.pose_prior_id = pycolmap.INVALID_POSE_PRIOR_ID
                db.write_pose_prior(p)
    finally:
        db.close()
    if sc.model != "none":
        shutil.copy2(out / "models" / f"{sc.model}.gml", out / "given_model.gml")
        if any(sc.model_shift) or sc.model_turn_deg:
            move_given_model(out, sc)
    if sc.dtm:
        from .dtm import dtm_from_truth

        if not (out / "truth" / "ground.tif").exists():
            raise InputError("scenario.dtm needs the sequence's truth/ground.tif (a sequence "
                             "with ground in a CRS with an EPSG code)", seq_dir)
        dtm_from_truth(out / "truth" / "ground.tif", out / "dtm", tiles=sc.dtm_tiles,
                       offset_sigma=sc.dtm_offset_sigma, noise_sigma=sc.dtm_noise,
                       seed=options.seed)
    for i, src in enumerate(options.source_files):
        dst = "scenario.toml" if i == len(options.source_files) - 1 else "sequence.toml"
        shutil.copy2(src, out / dst)
    stats["scenario"] = dataclasses.asdict(sc)
    stats["num_gnss"] = int(available.sum())
    (out / "simulation.json").write_text(json.dumps(stats, indent=2, default=str))
    (out / "README.md").write_text(README.format(
        name=sc.name or options.name, seed=options.seed, sequence=options.name,
        key=stats["sequence_key"], model=sc.model, gnss=sc.gnss if sc.gnss != "first" else
        f"first {sc.gnss_first_n} key frames", frames=stats["num_key_frames"],
        tps=stats["num_tie_points"], obs=stats["num_image_observations"],
        cps=stats["num_checkpoints"], reg=stats.get("num_registered_images", "-"),
        models=stats.get("num_models", "-"), images=IMAGES_ROW if "render" in stats else ""))
    return stats


def _place_sequence(built: Path, seq_dir: Path) -> None:
    """The built sequence into the cache as `seq_dir`, by one rename. Where another run of the
    same sequence (the same key: equal) has placed it meanwhile, that one stays and this is
    dropped: a run deriving scenarios from it never sees it removed. A leftover without
    simulation.json (not a finished build) is replaced."""
    if seq_dir.exists() and not (seq_dir / "simulation.json").exists():
        shutil.rmtree(seq_dir)
    try:
        os.replace(built, seq_dir)
    except OSError:
        if not (seq_dir / "simulation.json").exists():
            raise
        logger.info("sequence %s was built meanwhile by another run; using it", seq_dir)


def main(scenario_path: str | Path, output_path: str | Path, *, seed: int | None = None,
         cache_path: str | Path | None = None, overwrite: bool = False,
         progress: bool = True, render: bool = False) -> Path:
    """Build the scenario's workspace at `output_path` (see the module docstring); returns it.

    cache_path: directory of built sequences (`<name>-<hash>`), reused by later scenarios of the
    same sequence; None builds the sequence afresh. render: also render the key frames into
    images/ (as the scenario's `render.enabled`). The workspace appears atomically."""
    options = load_scenario(scenario_path)
    if seed is not None:
        options.seed = int(seed)
    if render:
        options.render.enabled = True
    out = Path(output_path).resolve()
    if out.exists():
        if not overwrite:
            raise InputError("output workspace exists (use --overwrite to replace it)", out)
    out.parent.mkdir(parents=True, exist_ok=True)
    key = sequence_key(options)
    tmp_root = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        if cache_path is not None:
            cache = Path(cache_path).resolve()
            cache.mkdir(parents=True, exist_ok=True)
            seq_dir = cache / f"{options.name}-{key}"
            if not (seq_dir / "simulation.json").exists():
                seq_tmp = Path(tempfile.mkdtemp(prefix=f".{seq_dir.name}.", dir=cache))
                try:
                    build_sequence(options, seq_tmp / "seq", progress=progress)
                    _place_sequence(seq_tmp / "seq", seq_dir)
                finally:
                    shutil.rmtree(seq_tmp, ignore_errors=True)
            else:
                logger.info("reusing sequence %s", seq_dir)
        else:
            seq_dir = tmp_root / "sequence"
            build_sequence(options, seq_dir, progress=progress)
        derive_scenario(seq_dir, options, tmp_root / "workspace")
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp_root / "workspace", out)
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
    logger.info("wrote %s", out)
    return out
