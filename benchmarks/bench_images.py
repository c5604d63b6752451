"""From photographs to a georeferenced model: rendered flights through COLMAP's own features,
against the same flights with simulated tie points.

Blocks (`workspaces/render_*.toml`, simulated and rendered with `simulate --render` into
workspaces/generated/render/<family>, git-ignored): a UAV orbit around the Berlin tile
3920_5820's corner building (orbit), a vehicle drive along the Berlin block 3910_5819's street
front (drive), two nadir strips over its eastern blocks (nadir), and the demo's procedural
street, 60 images (street). Each workspace holds both inputs of one flight: the rendered JPEGs
(EXIF GPS, DJI XMP, check-point targets painted on the surfaces) and COLMAP's map of the
simulated tie points (`sparse/0`).

Per block:

- images: the run from the image folder. `--mapper run` (the default): the `run` command
  (colmap_citymodel.pipeline.run.main: the calibrated camera, one camera for the flight, the
  DTM tiles as terrain, its own matcher and mapping with the model). `colmap`: COLMAP's SIFT
  (pycolmap.extract_features, the calibrated camera given as SIMPLE_RADIAL), matching (spatial
  from the EXIF GNSS for the orbit and nadir blocks, sequential for the drive and the street),
  COLMAP's incremental mapping (intrinsics held), then refine with GNSS from the EXIF and the
  workspace's DTM tiles as terrain. `map`: the same features and matches, then `map`
  (mapper.map_block: the model in the mapper's global adjustments) and its final refine.
  `pipeline` in the JSON says which ran.
- tie points: refine on the workspace's `sparse/0` (scenarios.refine_with_quality, as the
  robustness benchmark runs it).
- check points: RMS 3D (m) of the triangulated check points against the truth
  (scenarios.checkpoint_errors, the simulator's `checkpoint_observations.txt`) for the GNSS-only
  adjustment of the image run, the image run and the tie-point run; `within` whether the image
  run is within 1.5 x + 0.05 m of the tie-point figure or not "ok".

    .venv/bin/python benchmarks/bench_images.py [--families orbit drive nadir street]
        [--mapper run|colmap|map] [--tables_only]

writes benchmarks/results/images.md and images.json (`{"blocks": [{"name", "family",
"images", "registered", "gnss_only_checkpoints_3d", "checkpoints_3d",
"tie_points_checkpoints_3d", "verdict", "seconds", ...}]}`; a run with --families replaces its
own blocks only).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from scenarios import GENERATED, RESULTS, build_from_toml, checkpoint_errors, code_version, \
    refine_with_quality  # noqa: E402

#: family -> (scenario file, matcher of the image run)
FAMILIES = {"orbit": ("render_orbit.toml", "spatial"),
            "drive": ("render_drive.toml", "sequential"),
            "nadir": ("render_nadir.toml", "spatial"),
            "street": ("render_street.toml", "sequential")}
#: Neighbours each image is matched with: the next N in name order (sequential), the N nearest
#: by GNSS position (spatial).
SEQUENTIAL_OVERLAP, SPATIAL_NEIGHBOURS = 12, 14
#: The done-when rule: the image run within this factor and margin (m) of the tie-point run.
FACTOR, MARGIN = 1.5, 0.05


# ----------------------------------------------------------------------------------------------
# the run from the image folder


def _camera(workspace: Path) -> tuple[str, str]:
    """The calibrated camera as COLMAP's SIMPLE_RADIAL parameters (the scenario's flight)."""
    sim = json.loads((workspace / "simulation.json").read_text())["options"]["flight"]
    params = [sim["focal_length"], sim["image_width"] / 2, sim["image_height"] / 2,
              sim.get("calibrated_radial_k1", 0.0)]
    return "SIMPLE_RADIAL", ",".join(repr(float(p)) for p in params)


def _refine_options(workspace: Path):
    from colmap_citymodel.options import RefineOptions

    options = RefineOptions.preset("generalised")
    options.precision.covariances = "off"
    dtm = sorted((workspace / "dtm").glob("*.tif"))
    if dtm:
        options.terrain.files = tuple(str(p) for p in dtm)
    return options


def run_images(workspace: Path, out: Path, matcher: str, mapper: str) -> dict:
    """The run from `workspace`/images: the `run` command (`mapper` "run"), else its steps
    here."""
    if mapper == "run":
        return run_command(workspace, out)
    return run_steps(workspace, out, matcher, mapper)


def run_command(workspace: Path, out: Path) -> dict:
    """colmap_citymodel.pipeline.run.main on the image folder (the `run` command's Python
    face) with the calibrated camera, one camera for the flight, the workspace's DTM tiles as
    terrain, and its own choice of matcher; a new run directory (no step reused)."""
    import shutil

    from colmap_citymodel.pipeline.run import main as run_main

    model, params = _camera(workspace)
    dtm = [str(p) for p in sorted((workspace / "dtm").glob("*.tif"))]
    if out.exists():
        shutil.rmtree(out)
    start = time.perf_counter(), time.process_time()
    run = run_main(workspace / "images", workspace / "given_model.gml", out,
                   camera_mode="single", camera_model=model, camera_params=params,
                   terrain=dtm or None, progress=False)
    seconds = time.perf_counter() - start[0], time.process_time() - start[1]
    steps = {"matching" if step.name == "matches" else step.name: step.seconds
             for step in run.steps}
    return {"pipeline": "run", "result": run.result, "seconds": seconds[0],
            "features_per_image": _features_per_image(out / "database.db"),
            "cpu_seconds": seconds[1], "step_seconds": steps,
            "matcher": run.matcher.todict().get("matcher") if run.matcher else None,
            "registered": int(run.result.reconstruction.num_reg_images())
            if run.result is not None else 0}


def run_steps(workspace: Path, out: Path, matcher: str, mapper: str) -> dict:
    """The run's steps: COLMAP's SIFT and matching, then COLMAP's incremental mapping and
    refine (`mapper` "colmap"), or `map` with the model inside and its final refine ("map");
    GNSS from the images' EXIF. COLMAP's own block (mapper "colmap") is also measured against
    the truth after a similarity transform (its shape)."""
    import shutil

    from colmap_citymodel.block.gnss import read_gnss_exif
    from colmap_citymodel.citymodel.read import read_city_model

    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    store = read_city_model(workspace / "given_model.gml")
    gnss = read_gnss_exif(workspace / "images", store.crs)
    steps: dict[str, list[float]] = {}
    database = _features_and_matches(workspace, out, matcher, gnss, store, steps)
    row: dict = {"pipeline": f"pycolmap+{'refine' if mapper == 'colmap' else 'map'}",
                 "features_per_image": _features_per_image(database)}
    options = _refine_options(workspace)
    clock = (time.perf_counter(), time.process_time())
    if mapper == "colmap":
        rec, row["models"] = _colmap_mapping(workspace, out, database)
        clock = _lap(steps, "mapping", clock)
        row["registered"] = int(rec.num_reg_images()) if rec is not None else 0
        row["colmap_centres_rms_after_similarity"] = _shape(rec, workspace)
        result = _refine(rec, store, gnss, options)
    else:
        from colmap_citymodel.mapper import MapperOptions, map_block, refine_mapped

        mapped = map_block(database, store, gnss, options, MapperOptions(), _pipeline(),
                           image_path=workspace / "images", progress=False)
        clock = _lap(steps, "mapping", clock)
        row["registered"] = int(mapped.reconstruction.num_reg_images())
        result = refine_mapped(mapped, store, gnss, options, progress=False)
    _lap(steps, "refine", clock)
    if result is not None:
        result.reconstruction.write(str(_fresh(out / "refined")))
    row.update(result=result, seconds=sum(v[0] for v in steps.values()),
               step_seconds={k: v[0] for k, v in steps.items()},
               step_cpu_seconds={k: v[1] for k, v in steps.items()})
    return row


def _fresh(path: Path) -> Path:
    path.mkdir(parents=True, exist_ok=True)
    return path


def _pipeline():
    """COLMAP's incremental mapping with the calibrated camera held."""
    from colmap_citymodel.mapper import pipeline_options

    return pipeline_options({"ba_refine_focal_length": False,
                             "ba_refine_principal_point": False,
                             "ba_refine_extra_params": False,
                             "mapper": {"abs_pose_refine_focal_length": False,
                                        "abs_pose_refine_extra_params": False}})


def _features_and_matches(workspace: Path, out: Path, matcher: str, gnss, store,
                          steps: dict) -> Path:
    """COLMAP's SIFT (the calibrated camera given) and matching into out/database.db."""
    import pycolmap

    from colmap_citymodel.files import quiet_colmap

    images = workspace / "images"
    names = sorted(p.name for p in images.glob("*.jpg"))
    database = out / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model, reader.camera_params = _camera(workspace)
    clock = (time.perf_counter(), time.process_time())
    with quiet_colmap(out / "colmap.log"):
        pycolmap.extract_features(database, images, image_names=names, reader_options=reader,
                                  camera_mode=pycolmap.CameraMode.SINGLE)
    clock = _lap(steps, "features", clock)
    _write_priors(database, gnss, store)
    with quiet_colmap(out / "colmap.log"):
        _match(database, matcher)
    _lap(steps, "matching", clock)
    return database


def _colmap_mapping(workspace: Path, out: Path, database: Path):
    """COLMAP's incremental mapping; the model with the most registered images."""
    import pycolmap

    from colmap_citymodel.files import quiet_colmap

    with quiet_colmap(out / "colmap.log"):
        models = pycolmap.incremental_mapping(database, workspace / "images",
                                              _fresh(out / "sparse"), _pipeline())
    if not models:
        return None, 0
    return max(models.values(), key=lambda r: r.num_reg_images()), len(models)


def _refine(rec, store, gnss, options):
    from colmap_citymodel.workflow import refine

    return None if rec is None else refine(rec, store, gnss, options, progress=False)


def _shape(rec, workspace: Path) -> float | None:
    """RMS (m) of the block's camera centres from the truth after a similarity transform."""
    import pycolmap

    from scenarios import truth_centres

    if rec is None or rec.num_reg_images() < 3:
        return None
    truth = truth_centres(workspace)
    done = [im for im in rec.images.values() if im.has_pose]
    a = np.array([im.projection_center() for im in done])
    b = np.array([truth[im.name] for im in done])
    b = b - b.mean(axis=0)
    sim3 = pycolmap.estimate_sim3d(a, b).matrix()
    moved = a @ sim3[:, :3].T + sim3[:, 3]
    return float(np.sqrt(np.mean(np.sum((moved - b) ** 2, axis=1))))


def _lap(steps: dict, name: str, clock: tuple[float, float]) -> tuple[float, float]:
    now = (time.perf_counter(), time.process_time())
    steps[name] = [now[0] - clock[0], now[1] - clock[1]]
    return now


def _write_priors(database: Path, gnss, store) -> None:
    """The EXIF GNSS as the database's pose priors (model CRS minus the model's origin,
    CARTESIAN), for spatial matching."""
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        by_name = {im.name: im for im in db.read_all_images()}
        db.clear_pose_priors()
        for name, position, sigma in zip(gnss.image_names, gnss.positions, gnss.sigmas):
            if name not in by_name:
                continue
            prior = pycolmap.PosePrior(
                position=np.asarray(position, np.float64) - store.origin,
                position_covariance=np.diag(np.asarray(sigma, np.float64) ** 2),
                coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN)
            prior.corr_data_id = by_name[name].data_id
            db.write_pose_prior(prior)


def _match(database: Path, matcher: str) -> None:
    import pycolmap

    if matcher == "sequential":
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = SEQUENTIAL_OVERLAP
        pycolmap.match_sequential(database, pairing_options=pairing)
    else:
        pairing = pycolmap.SpatialPairingOptions()
        pairing.max_num_neighbors = SPATIAL_NEIGHBOURS
        pairing.ignore_z = False
        pycolmap.match_spatial(database, pairing_options=pairing)


def _features_per_image(database: Path) -> float:
    import pycolmap

    with pycolmap.Database.open(str(database)) as db:
        counts = [db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()]
    return float(np.mean(counts)) if counts else 0.0


# ----------------------------------------------------------------------------------------------
# one block


def _cp3d(rec, workspace: Path, origin) -> float | None:
    if rec is None:
        return None
    errors = checkpoint_errors(rec, workspace, np.asarray(origin))
    return errors.get("rms_3d")


def run_block(family: str, mapper: str) -> dict:
    toml, matcher = FAMILIES[family]
    start = time.perf_counter()
    workspace, sim = build_from_toml(ROOT / "workspaces" / toml, GENERATED / "render" / family)
    render = sim.get("render", {})
    name = f"render_{family}" + ("_map" if mapper == "map" else "")
    row = {"name": name, "family": family, "images": sim["num_key_frames"],
           "build_seconds": time.perf_counter() - start, "matcher": matcher,
           "render_seconds_per_image": render.get("seconds_per_image"),
           "render_cpu_seconds_per_image": render.get("cpu_seconds_per_image")}
    ties = refine_with_quality(workspace)
    row["tie_points_checkpoints_3d"] = _cp3d(ties["refined"], workspace, ties["origin"])
    row["tie_points_gnss_only_checkpoints_3d"] = _cp3d(ties["gnss_only"], workspace,
                                                       ties["gnss_only_origin"])
    row["tie_points_verdict"] = ties["verdict"]
    row["tie_points_registered"] = sim.get("num_registered_images")
    try:
        run = run_images(workspace, workspace / f"run_{mapper}", matcher, mapper)
    except Exception as error:  # noqa: BLE001  (a run that raises is a result too)
        row.update(registered=0, verdict="error", failure=f"{type(error).__name__}: {error}",
                   checkpoints_3d=None, gnss_only_checkpoints_3d=None, seconds=None)
        return row
    result = run.pop("result")
    row.update(run)
    quality = getattr(result, "quality", None)
    row["verdict"] = str(quality.verdict) if quality is not None else "n/a"
    row["reasons"] = [str(r) for r in getattr(quality, "reasons", [])] if quality else []
    row["checkpoints_3d"] = _cp3d(getattr(result, "reconstruction", None), workspace,
                                  getattr(result, "origin", None))
    row["gnss_only_checkpoints_3d"] = _cp3d(getattr(result, "gnss_only", None), workspace,
                                            getattr(result, "origin", None))
    tie, cp = row["tie_points_checkpoints_3d"], row["checkpoints_3d"]
    row["within"] = bool(row["verdict"] != "ok" or (
        cp is not None and tie is not None and cp <= FACTOR * tie + MARGIN))
    return row


# ----------------------------------------------------------------------------------------------
# output


def _n(value, fmt: str = "{:.3f}") -> str:
    return "-" if value is None else fmt.format(value)


def write_results(rows: list[dict], command: str, code: str, results: Path) -> None:
    results.mkdir(parents=True, exist_ok=True)
    path = results / "images.json"
    old = json.loads(path.read_text()).get("blocks", []) if path.exists() else []
    names = {r["name"] for r in rows}
    blocks = [r for r in old if r["name"] not in names] + rows
    order = list(FAMILIES)
    blocks.sort(key=lambda r: order.index(r["family"]) if r["family"] in order else 99)
    path.write_text(json.dumps({"blocks": blocks, "command": command, "code": code},
                               indent=2, default=float))
    write_markdown(blocks, command, code, results)


def write_markdown(blocks: list[dict], command: str, code: str, results: Path) -> None:
    lines = ["# Rendered images through COLMAP's own features", "", "Produced by", "",
             f"    {command}", "", f"Code measured: {code}.", "",
             "Per block: the flight rendered into JPEGs and run from the image folder "
             "(`pipeline`: `run`; `pycolmap+refine`: COLMAP's SIFT, matching and incremental "
             "mapping, then refine with GNSS from the EXIF; `pycolmap+map`: the same features "
             "and matches, then `map` with the model inside and its final refine), against "
             "refine on the same flight's simulated tie points (COLMAP's map of them). Check "
             "points: RMS 3D (m) against the truth; GNSS-only: the GNSS-only adjustment. "
             f"within: the image run within {FACTOR} x + {MARGIN} m of the tie-point run, or "
             "not \"ok\". s: seconds of the image run (features, matching, mapping, refine); "
             "render: seconds per image of rendering, wall / CPU (all threads).", "",
             "| block | images | registered | features / image | GNSS-only | images | tie "
             "points (GNSS-only) | verdict (tie points) | within | s | render | pipeline |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in blocks:
        verdict = f"{r.get('verdict')} ({r.get('tie_points_verdict', '-')})"
        if r.get("failure"):
            verdict += f": {r['failure']}"
        lines.append(
            f"| {r['name']} | {r['images']} | {r.get('registered', '-')} | "
            f"{_n(r.get('features_per_image'), '{:.0f}')} | "
            f"{_n(r.get('gnss_only_checkpoints_3d'))} | {_n(r.get('checkpoints_3d'))} | "
            f"{_n(r.get('tie_points_checkpoints_3d'))} "
            f"({_n(r.get('tie_points_gnss_only_checkpoints_3d'))}) | {verdict} | "
            f"{'yes' if r.get('within') else 'no'} | {_n(r.get('seconds'), '{:.0f}')} | "
            f"{_n(r.get('render_seconds_per_image'), '{:.1f}')} / "
            f"{_n(r.get('render_cpu_seconds_per_image'), '{:.1f}')} | "
            f"{r.get('pipeline', '-')} |")
    lines += ["", "Steps of the image runs, seconds wall / CPU (a 2-core machine shared with "
              "other jobs: wall times are inflated), and COLMAP's own block (before refine) "
              "against the truth after a similarity transform:", "",
              "| block | matcher | features | matching | mapping | refine | COLMAP's block "
              "shape (m) |", "|---|---|---|---|---|---|---|"]
    for r in blocks:
        wall, cpu = r.get("step_seconds") or {}, r.get("step_cpu_seconds") or {}
        cells = [(f"{wall[k]:.0f} / {cpu[k]:.0f}" if k in cpu else f"{wall[k]:.0f} / -")
                 if k in wall else "-" for k in ("features", "matching", "mapping", "refine")]
        lines.append(f"| {r['name']} | {r.get('matcher', '-')} | " + " | ".join(cells) +
                     f" | {_n(r.get('colmap_centres_rms_after_similarity'))} |")
    (results / "images.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--families", nargs="+", choices=list(FAMILIES),
                        default=list(FAMILIES), help="blocks to run (default: all)")
    parser.add_argument("--mapper", choices=("run", "colmap", "map"), default="run",
                        help="the image run: run: the `run` command; "
                             "colmap: COLMAP's incremental mapping, then refine; map: `map` "
                             "with the model inside, then its final refine")
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--tables_only", action="store_true",
                        help="only rewrite images.md from images.json")
    args = parser.parse_args()
    if args.tables_only:
        saved = json.loads((args.results / "images.json").read_text())
        write_markdown(saved["blocks"], saved["command"], saved["code"], args.results)
        return
    import colmap_citymodel  # noqa: F401  (sets up the package logger first)

    logging.getLogger("colmap_citymodel").setLevel(logging.ERROR)
    command = " ".join([".venv/bin/python benchmarks/bench_images.py", *sys.argv[1:]])
    code = code_version()
    rows = []
    for family in args.families:
        print(f"{family} ...", flush=True)
        row = run_block(family, args.mapper)
        rows.append(row)
        print(f"  {row.get('registered')} of {row['images']} registered; check points GNSS-only "
              f"{_n(row.get('gnss_only_checkpoints_3d'))}, images "
              f"{_n(row.get('checkpoints_3d'))}, tie points "
              f"{_n(row.get('tie_points_checkpoints_3d'))} m; {row.get('verdict')}", flush=True)
        write_results(rows, command, code, args.results)


if __name__ == "__main__":
    main()
