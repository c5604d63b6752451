"""Command line interface. It only parses arguments and calls each stage's typed `main`, so the
CLI and the Python API cannot drift. Domain errors become one line and exit code 2 here; a
refine whose quality gate fails exits 3."""

from __future__ import annotations

import argparse
import math
import sys

from . import logger
from .errors import CityModelError


def _add_model_info(subparsers) -> None:
    p = subparsers.add_parser("model-info", help="summarise a CityGML/CityJSON building model")
    p.add_argument("path", nargs="+", help="CityGML/CityJSON file(s) or a directory of tiles")
    p.add_argument("--lod", type=int, default=2, help="level of detail to read (1, 2 or 3)")
    p.add_argument("--crs", default=None, help="CRS to assume when the file names none (EPSG:N)")
    p.add_argument("--target_crs", default=None, help="projected CRS to reproject to (EPSG:N)")
    p.add_argument("--json", action="store_true", help="print one JSON object")

    def run(args):
        from .citymodel.info import main

        main(args.path, lod=args.lod, crs=args.crs, target_crs=args.target_crs, as_json=args.json)

    p.set_defaults(func=run)


def _add_evaluate(subparsers) -> None:
    p = subparsers.add_parser("evaluate", help="check point errors of a COLMAP model")
    p.add_argument("--input_path", required=True, help="COLMAP model directory to evaluate")
    p.add_argument("--checkpoints", required=True,
                   help="OpenDroneMap's gcp_list.txt of check marks (any CRS: converted into "
                        "the model's), or with --observations a text file 'id X Y Z' (model "
                        "CRS)")
    p.add_argument("--observations", default=None,
                   help="text file 'image_name id x y' (px) of --checkpoints in the 'id X Y Z' "
                        "format")
    p.add_argument("--crs", default=None,
                   help="the model's CRS (EPSG:N) for gcp_list check marks, where no "
                        "georeference.json beside the model records it")
    p.add_argument("--gcp_sigma", type=float, nargs=2, metavar=("H", "V"), default=(0.02, 0.03),
                   help="sigmas (m) of the check marks' surveyed positions where their lines "
                        "give none (default 0.02 0.03)")
    p.add_argument("--origin_file", default=None,
                   help="georeference.json (or 'X Y Z') when the model is in the local frame")
    p.add_argument("--frame", choices=["auto", "crs", "local"], default="auto",
                   help="frame of the model's coordinates (auto: decide from the data)")
    p.add_argument("--truth_path", default=None, help="truth COLMAP model (default: ../truth)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--output_path", default=None,
                   help="new directory for report.html, the plots and evaluation.json")
    p.add_argument("--checkpoint_precision", default=None,
                   help="check point covariances (refine's checkpoint_precision.json; default: "
                        "the one in --input_path) for the Delta/sigma table")

    def run(args):
        from .precision.checkpoints import main

        if args.output_path:  # a taken output directory fails before the evaluation
            from .files import check_new_directory

            check_new_directory(args.output_path)
        out = main(args.input_path, args.checkpoints, args.observations,
                   origin_file=args.origin_file, frame=args.frame, as_json=args.json,
                   truth_path=args.truth_path, precision_file=args.checkpoint_precision,
                   crs=args.crs, sigma=args.gcp_sigma)
        if args.output_path:
            from .precision.plots import write_evaluate_outputs

            write_evaluate_outputs(args.output_path, out, args.checkpoints
                                   if args.observations else out.get("known"))

    p.set_defaults(func=run)


def _add_simulate(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate", help="simulate a UAV flight through a city model and map it with COLMAP")
    p.add_argument("scenario", help="scenario TOML (see workspaces/*.toml)")
    p.add_argument("--output_path", required=True, help="workspace directory to create")
    p.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    p.add_argument("--cache_path", default=None,
                   help="directory of built sequences, reused by scenarios of the same sequence")
    p.add_argument("--overwrite", action="store_true", help="replace an existing workspace")
    p.add_argument("--render", action="store_true",
                   help="also render the key frames into images/ (JPEG with EXIF GPS and DJI "
                        "XMP from the simulated GNSS, check-point targets painted on the "
                        "surfaces, their image positions in images/gcp_list.txt); the "
                        "scenario's [render] table sets light, textures and sensor")

    def run(args):
        from .simulate.sequence import main

        main(args.scenario, args.output_path, seed=args.seed, cache_path=args.cache_path,
             overwrite=args.overwrite, render=args.render)

    p.set_defaults(func=run)


def _offset_value(text: str) -> float | str:
    """--gnss_height_offset: metres, or "auto"."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected metres or auto, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected finite metres or auto, got {text!r}")
    return value


def _add_gnss_arguments(p, *, database: bool, initial_transform: bool, exif: bool,
                        title: str | None) -> None:
    gnss = p.add_argument_group(title or (
        "GNSS (one source)" + (" or an initial transform" if initial_transform else
                              "; default: the database's pose priors")))
    if database:
        gnss.add_argument("--database", help="COLMAP database with pose priors")
    gnss.add_argument("--gnss", help="text file: image_name X Y Z [sX sY sZ]")
    gnss.add_argument("--gnss_crs", help="CRS of --gnss, e.g. EPSG:4979 or EPSG:25832+7837")
    if exif:
        gnss.add_argument("--exif", help="directory of the images with EXIF GPS (or a "
                                         "drone's XMP)")
    gnss.add_argument("--gnss_height_offset", type=_offset_value, default=None,
                      metavar="METRES|auto",
                      help="metres added to GNSS heights (model height minus GNSS height), or "
                           "auto: a constant offset estimated from the model's roofs and eaves "
                           "(GNSS heights in another height system: ellipsoidal, EGM96 from "
                           "the flight controller, above take-off)")
    gnss.add_argument("--gnss_bias", choices=["auto"], default=None,
                      help="auto: a constant 3D GNSS bias estimated from the model (needs "
                           "planes that fix all three directions; includes the height offset)")
    gnss.add_argument("--lever_arm", type=float, nargs=3, metavar=("X", "Y", "Z"),
                      help="GNSS antenna in the camera (rig) frame, metres: x right, y down, "
                           "z along the view")
    if initial_transform:
        gnss.add_argument("--initial_transform",
                          help="4x4 matrix or Sim3 JSON from the input frame to model CRS")


def _add_citymodel_arguments(p, *, database: bool, initial_transform: bool,
                             exif: bool = True,
                             output_help: str = "new directory for the results",
                             gnss_title: str | None = None) -> None:
    """The city model, GNSS, stochastic model, output and check point options that refine,
    map and run share (workflow.read_inputs / write_outputs)."""
    p.add_argument("--citymodel", required=True, nargs="+",
                   help="CityGML/CityJSON file(s) or a directory of tiles (also *.gz, *.zip)")
    p.add_argument("--output_path", required=True, help=output_help)
    _add_gnss_arguments(p, database=database, initial_transform=initial_transform, exif=exif,
                        title=gnss_title)
    p.add_argument("--preset", default="generalised",
                   choices=["generalised", "detailed", "correct_model"],
                   help="stochastic model preset (detailed: sigma_dTP 0.05 m, 5 points/plane, "
                        "every tie point alike instead of the faces' errors as unknowns; "
                        "correct_model: the images correct the model, see --write_model)")
    p.add_argument("--write_model", action="store_true", default=None,
                   help="correct the city model where the images see it well and write it back "
                        "in its own format and version (corrected_model.gml / .city.json, "
                        "tiles into corrected_model/) with model_changes.csv/.ply; on by "
                        "default with --preset correct_model")
    p.add_argument("--options", dest="options_file", help="TOML file overriding options")
    p.add_argument("--assignment", choices=["direct", "msac", "roi_msac", "auto"], default=None,
                   help="tie point to plane assignment: auto (default: roi_msac while the "
                        "threshold is above 1 m, then direct), direct (a: each tie point to its "
                        "closest plane), msac (b: planes extracted from the cloud), roi_msac "
                        "(c: one plane searched near each model plane)")
    p.add_argument("--workflow", choices=["global", "sliding_window"], default=None,
                   help="global (default): the whole block at once; sliding_window: windows "
                        "of 100 images in name order moved on by 33, each adjusted with the "
                        "model, then the global adjustment ([workflow] options)")
    p.add_argument("--terrain", nargs="+", default=None, metavar="FILE|none",
                   help="DTM rasters (GeoTIFF/COG tiles, any CRS; heights in the model's "
                        "height system) that hold the ground tie points (road, pavement); "
                        "default: the model's TIN relief, else the buildings' feet; none: no "
                        "terrain (docs/terrain.md)")
    p.add_argument("--terrain_sigma", type=float, default=None, metavar="M",
                   help="the DTM's stated height accuracy (m, default 0.15), one offset per "
                        "tile")
    p.add_argument("--lod", type=int, default=2, help="level of detail of the model to use")
    p.add_argument("--crs", dest="model_crs", help="CRS of a model file that names none")
    p.add_argument("--target_crs", help="projected CRS to reproject a geographic model to")
    p.add_argument("--output_type", choices=["bin", "txt"], default="bin")
    p.add_argument("--output_frame", choices=["crs", "local"], default="crs",
                   help="crs: model CRS coordinates; local: CRS minus the recorded origin")
    p.add_argument("--no_progress", action="store_true", help="no progress bars")
    p.add_argument("--precision", choices=["auto", "on", "off"], default=None,
                   help="a posteriori covariances of images and tie points (default auto: on "
                        "below 2,500 images; s0 and the global test are always reported)")
    quality = p.add_argument_group("check points and honest precision")
    quality.add_argument("--checkpoints", metavar="FILE",
                         help="check points, evaluated at the end (never control): "
                              "OpenDroneMap's gcp_list.txt (a CRS line, then 'geo_x geo_y "
                              "geo_z im_x im_y image_name [name] [sigma_h sigma_v]'; "
                              "docs/control-points.md), or with --checkpoint_observations "
                              "'id X Y Z' lines (model CRS)")
    quality.add_argument("--checkpoint_observations",
                         help="image observations 'image_name id x y' (pixels) of "
                              "--checkpoints in the 'id X Y Z' format")
    quality.add_argument("--sigma_generalisation", type=float, default=None, metavar="M",
                         help="per-plane generalisation error (m; Unger's typical size 0.2): "
                              "report generalisation-aware sigmas beside the classical ones")
    quality.add_argument("--tolerance", type=float, default=None, metavar="METRES",
                         help="position tolerance of the verdict (m, default 0.25): a "
                              "result that its stated sigmas do not place within it with 95 "
                              "%% probability is 'weak'")
    quality.add_argument("--variance_components", action="store_true", default=None,
                         help="iterated variance components of image and f_dTP, then a "
                              "re-weighted final solve")


def _citymodel_kwargs(args) -> dict:
    """workflow.read_inputs / write_outputs keyword arguments of the shared options."""
    out = dict(citymodel=args.citymodel, output_path=args.output_path, gnss=args.gnss,
               gnss_crs=args.gnss_crs, preset=args.preset,
               options_file=args.options_file, lod=args.lod, model_crs=args.model_crs,
               target_crs=args.target_crs, output_type=args.output_type,
               output_frame=args.output_frame, progress=not args.no_progress,
               precision=args.precision, gnss_height_offset=args.gnss_height_offset,
               gnss_bias=args.gnss_bias, lever_arm=args.lever_arm,
               checkpoints=args.checkpoints,
               checkpoint_observations=args.checkpoint_observations,
               sigma_generalisation=args.sigma_generalisation, tolerance=args.tolerance,
               variance_components=args.variance_components, assignment=args.assignment,
               write_model=args.write_model, workflow=args.workflow, terrain=args.terrain,
               terrain_sigma=args.terrain_sigma)
    for name in ("database", "initial_transform", "exif"):
        if hasattr(args, name):
            out[name] = getattr(args, name)
    return out


def _add_refine(subparsers) -> None:
    p = subparsers.add_parser(
        "refine", help="georeference and refine a COLMAP model with a city building model",
        epilog="exit status: 0 refined (quality ok or weak: see the quality line and "
               "report.json), 2 bad input, 3 the quality gate failed: the model could not help "
               "and the output holds the GNSS-only adjustment (or, for a block registered "
               "from the model alone that fits two places about equally well or whose planes "
               "cannot hold it, report.json alone)")
    p.add_argument("--input_path", required=True,
                   help="COLMAP model directory (sparse/0), or sparse/ with several parts: "
                        "each is refined on its own into OUTPUT_PATH/<part>")
    _add_citymodel_arguments(p, database=True, initial_transform=True)
    hint = p.add_argument_group("no GNSS: register from the model alone (docs/no-gnss.md)")
    hint.add_argument("--location", type=float, nargs=2, metavar=("X", "Y"), default=None,
                      help="rough position of the block (model CRS): without GNSS, or with "
                           "GNSS whose stated sigma exceeds 20 m, the block is found on the "
                           "model near it and refined with the model as the only datum")
    hint.add_argument("--location_radius", type=float, default=100.0, metavar="M",
                      help="metres around --location within which the block's centre is "
                           "searched (default 100)")
    marks = p.add_argument_group("ground control marks (docs/control-points.md)")
    marks.add_argument("--gcp", metavar="FILE",
                       help="OpenDroneMap's gcp_list.txt: marks surveyed on the ground and "
                            "measured in the images, in the adjustment with their sigmas; "
                            "alone (no GNSS) they georeference the block")
    marks.add_argument("--gcp_sigma", type=float, nargs=2, metavar=("H", "V"), default=None,
                       help="sigmas (m) of the marks' surveyed positions and heights where "
                            "their lines give none (default 0.02 0.03); also those of "
                            "--checkpoints in gcp_list format")
    p.add_argument("--sequence", action="store_true",
                   help="the images are video frames named in capture order: after refine, "
                        "frames whose pose jumps from their neighbours' are reported "
                        "(report.json quality.metrics.sequence)")

    def run(args):
        from .workflow import main

        _location_checked(args)
        result = main(args.input_path, **_citymodel_kwargs(args), location=args.location,
                      location_radius=args.location_radius, sequence=args.sequence,
                      gcp=args.gcp, gcp_sigma=args.gcp_sigma)
        # The quality gate failed: the output holds the GNSS-only result (if there was GNSS).
        return 3 if result.quality.verdict == "failed" else 0

    p.set_defaults(func=run)


def _add_map(subparsers) -> None:
    p = subparsers.add_parser(
        "map", help="COLMAP's incremental mapping with the city model in its global bundle "
                    "adjustments, then refine's final adjustment and outputs",
        epilog="exit status as refine: 0 mapped (quality ok or weak), 2 bad input, 3 the "
               "quality gate failed (the output holds the GNSS-only adjustment)")
    p.add_argument("--database_path", required=True,
                   help="COLMAP database; without keypoints, COLMAP's feature extraction and "
                        "matching run first")
    p.add_argument("--image_path", required=True,
                   help="image directory (features are extracted from it when the database "
                        "has none; colours of the points)")
    _add_citymodel_arguments(p, database=False, initial_transform=False)
    m = p.add_argument_group("mapping (COLMAP's options as in colmap mapper)")
    m.add_argument("--mapper_options", nargs="+", metavar="KEY=VALUE",
                   help="pycolmap IncrementalPipelineOptions, e.g. ba_global_frames_ratio=1.2 "
                        "min_num_matches=30 mapper.init_min_num_inliers=50 "
                        "ba_refine_focal_length=false")
    m.add_argument("--min_gnss_images", type=int, default=None, metavar="N",
                   help="registered images with GNSS before the block is georegistered and the "
                        "global adjustments take the model (default 10)")
    m.add_argument("--hybrid_iterations", type=int, default=None, metavar="N",
                   help="assign + hybrid adjustment iterations per global adjustment while "
                        "mapping (default 3; the final refine runs its own)")
    m.add_argument("--start_at_gnss", action="store_true",
                   help="seek COLMAP's initial pair among the images with GNSS first (the model "
                        "then enters early; experimental: see the README)")
    m.add_argument("--num_threads", type=int, default=None, help="threads (COLMAP, Ceres)")
    f = p.add_argument_group("features and matches (only when the database has none)")
    f.add_argument("--matcher", choices=["exhaustive", "sequential", "spatial"],
                   default="exhaustive", help="COLMAP matcher (default exhaustive)")
    f.add_argument("--camera_model", default=None,
                   help="COLMAP camera model of the images (default SIMPLE_RADIAL)")
    f.add_argument("--single_camera", action="store_true",
                   help="one camera for all images")
    f.add_argument("--extraction_options", nargs="+", metavar="KEY=VALUE",
                   help="pycolmap FeatureExtractionOptions, e.g. sift.max_num_features=4096")
    f.add_argument("--matching_options", nargs="+", metavar="KEY=VALUE",
                   help="pycolmap FeatureMatchingOptions, e.g. use_gpu=false")

    def run(args):
        from .mapper import main

        result, _ = main(args.database_path, args.image_path, **_citymodel_kwargs(args),
                         mapper_options=args.mapper_options,
                         min_gnss_images=args.min_gnss_images,
                         hybrid_iterations=args.hybrid_iterations,
                         start_at_gnss=args.start_at_gnss,
                         num_threads=args.num_threads, matcher=args.matcher,
                         camera_model=args.camera_model, single_camera=args.single_camera,
                         extraction_options=args.extraction_options,
                         matching_options=args.matching_options)
        return 3 if result.quality.verdict == "failed" else 0

    p.set_defaults(func=run)


def _location_checked(args) -> None:
    if args.location is not None and not (
            all(math.isfinite(v) for v in args.location)
            and math.isfinite(args.location_radius) and args.location_radius > 0):
        raise CityModelError("--location needs finite X Y and --location_radius a "
                             "positive number of metres")


def _add_run(subparsers) -> None:
    p = subparsers.add_parser(
        "run", help="from a folder of photographs: COLMAP's features, matching and mapping "
                    "with the city model inside, refine and its report",
        epilog="the output directory holds database.db, images.csv (EXIF/XMP of every image), "
               "sparse/0 and mapping.json (the mapped block), refined/ (refine's outputs and "
               "report) and run.json (the steps and their times); run again with the same "
               "--output_path to resume: features, matches and the mapped block are reused. "
               "Exit status as refine: 0 ok or weak, 2 bad input, 3 the quality gate failed")
    p.add_argument("--image_path", required=True,
                   help="folder of the photographs (subfolders too; names relative to it)")
    _add_citymodel_arguments(
        p, database=False, initial_transform=False, exif=False,
        output_help="run directory: created, or an earlier run's to resume",
        gnss_title="GNSS (default: the images' EXIF GPS and a drone's XMP, with RTK sigmas)")
    hint = p.add_argument_group("no GNSS: register from the model alone (docs/no-gnss.md)")
    hint.add_argument("--location", type=float, nargs=2, metavar=("X", "Y"), default=None,
                      help="rough position of the block (model CRS), for images without GNSS")
    hint.add_argument("--location_radius", type=float, default=100.0, metavar="M",
                      help="metres around --location within which the block is searched")
    p.add_argument("--sequence", action="store_true",
                   help="the images are video frames in name order: frames whose pose jumps "
                        "from their neighbours' are reported")
    c = p.add_argument_group("cameras (COLMAP's image reader)")
    c.add_argument("--camera_model", default=None,
                   help="COLMAP camera model, e.g. SIMPLE_RADIAL (default), OPENCV")
    c.add_argument("--camera_params", default=None, metavar="P1,P2,...",
                   help="the camera model's parameters, e.g. f,cx,cy,k (pixels); default: "
                        "from EXIF")
    c.add_argument("--camera_mode", choices=["auto", "single", "per_image"], default="auto",
                   help="auto (default): one camera per camera body and image size (EXIF "
                        "make, model, serial number, focal length); single: one for all; "
                        "per_image: one each")
    c.add_argument("--single_camera", dest="camera_mode", action="store_const",
                   const="single", help="one camera for all images (--camera_mode single)")
    f = p.add_argument_group("features and matching (COLMAP, CPU)")
    f.add_argument("--matcher", choices=["auto", "exhaustive", "spatial", "sequential"],
                   default="auto",
                   help="auto (default): exhaustive up to 30 images, spatial with GNSS for "
                        "every image, sequential for video frames, else exhaustive; the "
                        "choice and its reason are logged and in run.json")
    f.add_argument("--extraction_options", nargs="+", metavar="KEY=VALUE",
                   help="pycolmap FeatureExtractionOptions, e.g. max_image_size=1600 "
                        "sift.max_num_features=4096")
    f.add_argument("--matching_options", nargs="+", metavar="KEY=VALUE",
                   help="pycolmap FeatureMatchingOptions, e.g. sift.max_ratio=0.8")
    m = p.add_argument_group("mapping (as map)")
    m.add_argument("--mapper_options", nargs="+", metavar="KEY=VALUE",
                   help="pycolmap IncrementalPipelineOptions, e.g. min_num_matches=30")
    m.add_argument("--min_gnss_images", type=int, default=None, metavar="N",
                   help="registered images with GNSS before the model enters mapping "
                        "(default 10)")
    m.add_argument("--hybrid_iterations", type=int, default=None, metavar="N",
                   help="assign + hybrid adjustment iterations per global adjustment while "
                        "mapping (default 3)")
    m.add_argument("--num_threads", type=int, default=None,
                   help="threads (COLMAP, Ceres; default: all cores)")
    p.add_argument("--stop_after", choices=["features", "matches", "mapping"], default=None,
                   help="end the run after this step (run again without it to go on)")

    def run(args):
        from .pipeline.run import main

        _location_checked(args)
        kwargs = _citymodel_kwargs(args)
        image_path, output_path = args.image_path, kwargs.pop("output_path")
        citymodel = kwargs.pop("citymodel")
        result = main(image_path, citymodel, output_path, **kwargs, matcher=args.matcher,
                      camera_mode=args.camera_mode, camera_model=args.camera_model,
                      camera_params=args.camera_params,
                      extraction_options=args.extraction_options,
                      matching_options=args.matching_options,
                      mapper_options=args.mapper_options,
                      min_gnss_images=args.min_gnss_images,
                      hybrid_iterations=args.hybrid_iterations, num_threads=args.num_threads,
                      location=args.location, location_radius=args.location_radius,
                      sequence=args.sequence, stop_after=args.stop_after)
        return 3 if args.stop_after is None and result.verdict == "failed" else 0

    p.set_defaults(func=run)


def _add_demo(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="simulate a flight, refine it with the city model, evaluate check points")
    p.add_argument("--output_path", default="demo_output", help="directory for all outputs")
    p.add_argument("--scenario", default=None, help="scenario TOML (default: the packaged demo street, colmap_citymodel/simulate/demo.toml)")
    p.add_argument("--no_progress", action="store_true")

    def run(args):
        from .demo import main

        main(args.output_path, scenario=args.scenario, progress=not args.no_progress)

    p.set_defaults(func=run)


def _add_precision(subparsers) -> None:
    p = subparsers.add_parser(
        "precision", help="a posteriori sigmas of tie points and cameras per image subset "
                          "(Mulder Table 5.2)")
    p.add_argument("--input_path", required=True, help="COLMAP model directory (sparse/0)")
    p.add_argument("--subset", dest="subsets", action="append", required=True,
                   metavar="NAME=GLOB[,GLOB...]",
                   help="named image subset by image-name globs, e.g. nadir='nadir/*', "
                        "both='*'; repeat for each subset")
    p.add_argument("--output_path", default=None,
                   help="new directory for JSON, Markdown table, sigma maps and histograms")
    gnss = p.add_argument_group("GNSS datum (optional; without it the gauge is fixed by two "
                                "images, as COLMAP's BA does)")
    gnss.add_argument("--database", help="COLMAP database with pose priors")
    gnss.add_argument("--gnss", help="text file: image_name X Y Z [sX sY sZ]")
    gnss.add_argument("--gnss_crs", help="CRS of --gnss, e.g. EPSG:25832 or EPSG:4979")
    gnss.add_argument("--target_crs", help="projected CRS for geographic GNSS (default: UTM)")
    p.add_argument("--datum", choices=["solve", "inner"], default="solve",
                   help="sigmas in the table: solve = in the solve's gauge (GNSS or fixed); "
                        "inner = S-transformed to the inner constraints of the tie points")
    p.add_argument("--max_images", type=int, default=None,
                   help="largest subset whose covariances are computed (default 500)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--no_progress", action="store_true", help="no progress bars")

    def run(args):
        from .precision.subsets import main

        main(args.input_path, args.subsets, output_path=args.output_path,
             database=args.database, gnss=args.gnss, gnss_crs=args.gnss_crs,
             target_crs=args.target_crs, datum=args.datum, max_images=args.max_images,
             as_json=args.json, progress=not args.no_progress)

    p.set_defaults(func=run)


def _add_batch(subparsers) -> None:
    p = subparsers.add_parser(
        "batch", help="refine many COLMAP workspaces against a city model (process pool or "
                      "Dask cluster)",
        epilog="each workspace is refined into OUTPUT_PATH/<workspace>/ (log: "
               "<workspace>.log); summary.csv/.json/.html list them all. A rerun skips the "
               "finished ones. Exit status: 0 every workspace has a result, 1 some failed "
               "(see the summary), 2 bad input")
    p.add_argument("--workspaces", required=True, nargs="+",
                   help="workspace directories (sparse/<n>/ plus database.db, gnss.txt or "
                        "images/), directories to search for them, or text files listing "
                        "them one a line")
    p.add_argument("--citymodel", required=True, nargs="+",
                   help="CityGML/CityJSON files or directories of tiles (only the tiles near "
                        "a workspace's GNSS are read)")
    p.add_argument("--output_path", required=True, help="directory for the results")
    p.add_argument("--workers", type=int, default=None,
                   help="workspaces refined at once: worker processes of the local pool or "
                        "of --scheduler local (default: the number of cores)")
    p.add_argument("--threads", type=int, default=None,
                   help="threads of each refine (Ceres, OpenMP/OpenBLAS, Open3D; default: "
                        "the cores over --workers, so that the workers do not oversubscribe "
                        "the cores: on 2 cores 1 worker runs 2 threads, 2 workers 1 each; "
                        "1 on a remote --scheduler)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="run on Dask: 'local' starts a LocalCluster of --workers processes, "
                        "tcp://HOST:PORT uses a running scheduler (default: a local process "
                        "pool)")
    p.add_argument("--force", action="store_true",
                   help="refine the workspaces finished by an earlier run again")
    p.add_argument("--no_progress", action="store_true", help="no progress bar")
    p.add_argument("--gnss_crs", help="CRS of the workspaces' gnss.txt files, e.g. EPSG:4979")
    p.add_argument("--gnss_height_offset", type=_offset_value, default=None,
                   help="metres added to GNSS heights, or auto (as refine)")
    p.add_argument("--gnss_bias", choices=["auto"], default=None,
                   help="estimate a constant 3D GNSS bias (as refine)")
    p.add_argument("--lever_arm", type=float, nargs=3, metavar=("X", "Y", "Z"),
                   help="GNSS antenna in the camera frame, metres (as refine)")
    p.add_argument("--preset", default=None, choices=["generalised", "detailed", "correct_model"],
                   help="stochastic model preset (as refine)")
    p.add_argument("--options", dest="options_file", help="TOML file overriding options")
    p.add_argument("--assignment", choices=["direct", "msac", "roi_msac", "auto"], default=None)
    p.add_argument("--lod", type=int, default=None, help="level of detail of the model to use")
    p.add_argument("--crs", dest="model_crs", help="CRS of model files that name none")
    p.add_argument("--target_crs", help="projected CRS to reproject geographic tiles to")
    p.add_argument("--output_type", choices=["bin", "txt"], default=None)
    p.add_argument("--output_frame", choices=["crs", "local"], default=None)
    p.add_argument("--precision", choices=["auto", "on", "off"], default=None)
    p.add_argument("--sigma_generalisation", type=float, default=None, metavar="M")
    p.add_argument("--variance_components", action="store_true", default=None)
    p.add_argument("--write_model", action="store_true", default=None,
                   help="correct the model and write it into each workspace's output (as refine)")

    def run(args):
        from .batch.run import main

        rows = main(args.workspaces, args.citymodel, args.output_path, workers=args.workers,
                    threads=args.threads, scheduler=args.scheduler, force=args.force,
                    gnss_crs=args.gnss_crs,
                    progress=not args.no_progress, preset=args.preset,
                    options_file=args.options_file, assignment=args.assignment, lod=args.lod,
                    model_crs=args.model_crs, target_crs=args.target_crs,
                    output_type=args.output_type, output_frame=args.output_frame,
                    precision=args.precision, sigma_generalisation=args.sigma_generalisation,
                    variance_components=args.variance_components,
                    gnss_height_offset=args.gnss_height_offset, gnss_bias=args.gnss_bias,
                    lever_arm=args.lever_arm, write_model=args.write_model)
        return 1 if any(r.get("status") == "error" for r in rows) else 0

    p.set_defaults(func=run)


def _add_import_eo(subparsers) -> None:
    p = subparsers.add_parser(
        "import-eo", help="GNSS/IMU exterior orientations of a multi-head camera into a COLMAP "
                          "database (rig, frames, pose priors) and a known-pose model",
        epilog="attitude conventions, frames and files: README 'Oblique aerial blocks'")
    p.add_argument("--database", required=True, help="COLMAP database (changed in place)")
    p.add_argument("--eo", required=True,
                   help="text file: exposure X Y Z A1 A2 A3 [sX sY sZ], angles in degrees")
    p.add_argument("--rig", required=True,
                   help="rig JSON: heads with image_name template, lever_arm, boresight, camera")
    p.add_argument("--eo_crs", required=True, help="CRS of the EO positions, e.g. EPSG:25832")
    p.add_argument("--model_crs", default=None,
                   help="projected CRS of the city model (default: --eo_crs)")
    p.add_argument("--attitude", choices=["opk", "rpy"], default="opk",
                   help="opk: photogrammetric omega, phi, kappa of the body's camera axes; "
                        "rpy: roll, pitch, yaw (heading) of an IMU body x forward, y right, "
                        "z down")
    p.add_argument("--output_path", required=True,
                   help="new directory: sparse/ (the known-pose model), origin.json, gnss.txt")

    def run(args):
        from .block.import_eo import main

        result = main(args.database, args.eo, args.rig, args.eo_crs, args.output_path,
                      model_crs=args.model_crs, attitude=args.attitude)
        print(result.summary())

    p.set_defaults(func=run)


def _add_pairs(subparsers) -> None:
    p = subparsers.add_parser(
        "pairs", help="image pairs to match in a known-pose block, from overlapping footprints "
                      "on the city model and terrain",
        epilog="the output is a pair list for `colmap matches_importer --match_type pairs`")
    p.add_argument("--input_path", required=True,
                   help="COLMAP model with poses (import-eo's OUTPUT/sparse)")
    p.add_argument("--output", required=True, help="pair list to write (image_name1 image_name2)")
    p.add_argument("--citymodel", nargs="+", default=None,
                   help="CityGML/CityJSON file(s) or a directory of tiles: rays stop on it")
    p.add_argument("--terrain_height", type=float, default=None, metavar="H",
                   help="terrain height in the model CRS (default with --citymodel: its lowest "
                        "vertex)")
    p.add_argument("--database", default=None,
                   help="COLMAP database whose images the pairs must name (checked)")
    p.add_argument("--origin_file", default=None,
                   help="origin.json of the model's local frame (default: beside --input_path)")
    p.add_argument("--min_overlap", type=float, default=None,
                   help="smallest overlap, share of the smaller footprint (default 0.2)")
    p.add_argument("--lod", type=int, default=2, help="level of detail of the city model")
    p.add_argument("--crs", dest="model_crs", default=None,
                   help="CRS of a city model file that names none")

    def run(args):
        from .block.pairs import PairOptions, main

        options = PairOptions()
        if args.min_overlap is not None:
            options.min_overlap = args.min_overlap
        result = main(args.input_path, args.output, citymodel=args.citymodel,
                      terrain_height=args.terrain_height, database=args.database,
                      origin_file=args.origin_file, lod=args.lod, model_crs=args.model_crs,
                      options=options)
        print(result.summary())

    p.set_defaults(func=run)


def _add_dense_quality(subparsers) -> None:
    p = subparsers.add_parser(
        "dense-quality", help="sigma of every dense point from the refined cameras' "
                              "covariances (PLY scalar fields); weighted vs unweighted planes")
    p.add_argument("--input_path", required=True,
                   help="refined COLMAP model (poses and tie points; the PLY's frame)")
    p.add_argument("--ply", required=True, help="dense point cloud (e.g. COLMAP's fused.ply)")
    p.add_argument("--image_covariance", required=True,
                   help="refine's image_covariance.csv (full 6x6) or image_precision.csv "
                        "(sigmas only)")
    p.add_argument("--output", required=True, help="PLY to write with the sigma fields")
    p.add_argument("--tie_point_precision", default=None,
                   help="refine's point_precision.ply: adds sigma_3d_count (Mulder's "
                        "polynomial of the tie point sigma per number of views)")
    p.add_argument("--sigma_image", type=float, default=None,
                   help="pixels, a dense point's matching noise (default 1.0; 0: cameras only)")
    p.add_argument("--visibility_radius", type=float, default=None,
                   help="tie points within this distance decide who sees a point (default 5)")
    p.add_argument("--planes", action="store_true",
                   help="also extract planes with and without the sigmas as weights "
                        "(fields plane_weighted, plane_unweighted)")
    p.add_argument("--inlier_distance", type=float, default=None,
                   help="plane inlier distance with --planes (default 0.1)")

    def run(args):
        from .precision.dense import DenseOptions, PlaneOptions, main

        options = DenseOptions()
        if args.sigma_image is not None:
            options.sigma_image = args.sigma_image
        if args.visibility_radius is not None:
            options.visibility_radius = args.visibility_radius
        planes = None
        if args.planes:
            planes = PlaneOptions()
            if args.inlier_distance is not None:
                planes.inlier_distance = args.inlier_distance
        result = main(args.input_path, args.ply, args.image_covariance, args.output,
                      tie_point_precision=args.tie_point_precision, options=options,
                      planes=planes)
        print(result.summary())

    p.set_defaults(func=run)


def _add_triangulate(subparsers) -> None:
    p = subparsers.add_parser(
        "triangulate", help="tie points of a known-pose block from the database's verified "
                            "matches (COLMAP's point triangulator, poses held)")
    p.add_argument("--database", required=True, help="COLMAP database with verified matches")
    p.add_argument("--input_path", required=True,
                   help="COLMAP model with the poses (import-eo's OUTPUT/sparse)")
    p.add_argument("--output_path", required=True, help="directory for the triangulated model")

    def run(args):
        from .block.triangulate import main

        print(main(args.database, args.input_path, args.output_path).summary())

    p.set_defaults(func=run)


def _add_simulate_oblique(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate-oblique", help="simulate a five-head oblique aerial block over a city model "
                                 "(database with keypoints, eo.txt, rig.json, truth)")
    p.add_argument("--citymodel", required=True, help="CityGML/CityJSON file of the buildings")
    p.add_argument("--output_path", required=True, help="workspace directory to create")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--strips", type=int, default=None, help="parallel strips (default 3)")
    p.add_argument("--strip_length", type=float, default=None, help="metres (default 600)")
    p.add_argument("--centre", type=float, nargs=2, default=None, metavar=("X", "Y"),
                   help="block centre in the model CRS (default: the model's bbox centre)")

    def run(args):
        from .simulate.oblique import ObliqueOptions, simulate_oblique_block

        options = ObliqueOptions(citymodel=args.citymodel, seed=args.seed,
                                 centre=None if args.centre is None else tuple(args.centre))
        if args.strips is not None:
            options.strips = args.strips
        if args.strip_length is not None:
            options.strip_length = args.strip_length
        stats = simulate_oblique_block(options, args.output_path)
        print(f"simulate-oblique: {stats['exposures']} exposures x {stats['heads']} heads, "
              f"{stats['observations']} observations; workspace {args.output_path}")

    p.set_defaults(func=run)


def _add_simulate_matching(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate-matching", help="in a simulate-oblique workspace: matches of the listed "
                                  "pairs from the truth, then COLMAP's geometric verification")
    p.add_argument("--workspace", required=True, help="simulate-oblique workspace")
    p.add_argument("--pairs", required=True, help="pair list (image_name1 image_name2)")
    p.add_argument("--database", default=None, help="database (default WORKSPACE/database.db)")

    def run(args):
        from .simulate.oblique import simulate_matching

        r = simulate_matching(args.workspace, args.pairs, args.database)
        print(f"simulate-matching: {r.matched_pairs} of {r.pairs} pairs matched "
              f"({r.matches} matches); COLMAP verified {r.verified_pairs} pairs, "
              f"{r.inlier_matches} inlier matches in {r.seconds_verification:.1f} s")

    p.set_defaults(func=run)


SUBCOMMANDS = [_add_model_info, _add_run, _add_refine, _add_map, _add_demo, _add_evaluate,
               _add_simulate, _add_precision, _add_batch, _add_import_eo, _add_pairs,
               _add_triangulate, _add_dense_quality, _add_simulate_oblique,
               _add_simulate_matching]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="colmap-citymodel",
        description="Georeference and refine COLMAP reconstructions with a city building model.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    subparsers = parser.add_subparsers(dest="command", required=True)
    for add in SUBCOMMANDS:
        add(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.verbose:
        logger.setLevel("DEBUG")
    try:
        status = args.func(args)
    except CityModelError as error:
        print(f"error: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return status if isinstance(status, int) else 0


if __name__ == "__main__":
    sys.exit(main())
