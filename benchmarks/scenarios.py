"""Unger's scenarios on simulated flights: check point accuracy per method.

For each sequence (short ~90, long ~340 key frames) and scenario Scn1..Scn6
(`workspaces/{short,long}_scnN.toml`), the workspace is built by the simulator (each sequence is
mapped once by COLMAP; workspaces under workspaces/generated/, as workspaces/README.md builds them), then every method runs on copies of
the same `sparse/0` and is evaluated on the simulated check points:

- refine_a:  colmap-citymodel refine (global workflow, direct assignment (a));
- refine_b, refine_c, refine_auto: the same with assignment (b) "msac", (c) "roi_msac" and
             "auto";
- sliding_window: refine with `--workflow sliding_window` (windows of 100 images moved on by
             33, then the global adjustment; direct assignment); long sequence only (the short
             one is a single window);
- map:       colmap-citymodel map: COLMAP's incremental mapping of the workspace's database
             (its simulated matches) again, with the model in every global bundle adjustment
             once 10 registered images have GNSS, then refine's final adjustment (direct
             assignment);
- gnss_ba:   7-parameter fit to GNSS + bundle adjustment with GNSS priors (COLMAP's pose-prior BA);
- gnss_sim3: 7-parameter fit to GNSS only (what `colmap model_aligner` does);
- icp:       gnss_sim3, then rigid point-to-plane ICP of the tie points to the model (open3d), the
             approach the source argues cannot fix block deformation.
Scenarios without a model (Scn5, Scn6) run gnss_ba and gnss_sim3 only.

Prints one table per sequence like Unger's Tables 10/11 and writes
benchmarks/results/{short,long}.md and benchmarks/results/scenarios.json
({sequence: {scenario: {method: {rms_x, rms_y, rms_z, rms_3d, rms_3d_after_helmert, helmert,
seconds}}}}).

    .venv/bin/python benchmarks/scenarios.py [--sequences short long] [--scenarios Scn1 Scn3]

With --robustness it runs the blocks shaped unlike the procedural street instead
(`workspaces/robust_{drive,orbit,strip,short}.toml`: a vehicle drive, an orbit around one
building, one straight strip, a 20-image block; GNSS with a 4-5 m bias): per case refine and the
GNSS-only adjustment of the same block (camera centres against the simulated truth, per axis and
3D; check points), refine's quality verdict and the seconds. Writes the `robustness` section of
scenarios.json (the other sections are kept) and benchmarks/results/robustness.md.

    .venv/bin/python benchmarks/scenarios.py --robustness [--cases drive orbit strip short]

`--model_variants corrected detailed` adds, per case, refine against the other variants of the
case's model: the given one has systematic plane errors, so this separates the method's error
from the model's.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import time
from pathlib import Path

import numpy as np
import pycolmap

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
GENERATED = ROOT / "workspaces" / "generated"
SCENARIOS = ("Scn1", "Scn2", "Scn3", "Scn4", "Scn5", "Scn6")
METHODS = ("refine_a", "refine_b", "refine_c", "refine_auto", "sliding_window", "map", "gnss_ba",
           "gnss_sim3", "icp")
#: Methods that only run on these sequences.
ONLY_ON = {"sliding_window": ("long",)}
# Unger chapter 6 (method.md 8): RMS 3D of check points, m.
UNGER = {"short": {"Scn1": 0.10, "Scn2": 0.19, "Scn3": 0.25, "Scn5": "< 1"},
         "long": {"Scn2": 0.12, "Scn4": 0.31, "Scn5": "metres", "Scn6": "~5"}}


def toml_value(value) -> str:
    """One TOML value (bool, number, string, list, inline table) as scenario files write it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {toml_value(v)}" for k, v in value.items()) + " }"
    if isinstance(value, str):
        return json.dumps(value)
    return repr(float(value)) if isinstance(value, float) else str(int(value))


def update_json(path: Path, keys: list[str], value) -> dict:
    """Set path[keys[0]]...[keys[-1]] = value in the JSON file, read just before writing: other
    benchmarks (or other runs of this one) write their own parts of the same file meanwhile.
    Returns the whole updated content."""
    everything = json.loads(path.read_text()) if path.exists() else {}
    node = everything
    for key in keys[:-1]:
        node = node.setdefault(key, {})
    node[keys[-1]] = value
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.write_text(json.dumps(everything, indent=2))
    os.replace(tmp, path)
    return everything


def build_workspace(sequence: str, scenario: str) -> Path:
    from colmap_citymodel.simulate import sequence as simulate

    toml = ROOT / "workspaces" / f"{sequence}_{scenario.lower()}.toml"
    out = GENERATED / sequence / scenario
    if not (out / "sparse" / "0").is_dir():
        simulate.main(toml, out, cache_path=GENERATED / "cache", overwrite=out.exists())
    return out


def model_variant(workspace: Path) -> str:
    """"detailed", "corrected", "original" or "none" (simulate's scenario.model)."""
    import tomllib

    scenario = tomllib.loads((workspace / "scenario.toml").read_text()).get("scenario", {})
    return scenario.get("model", "original")


def has_model(workspace: Path) -> bool:
    return model_variant(workspace) != "none"


def evaluate(rec: pycolmap.Reconstruction, workspace: Path, origin: np.ndarray) -> dict:
    from colmap_citymodel.precision.checkpoints import evaluate_checkpoints, read_checkpoint_observations, read_checkpoints

    evaluation = evaluate_checkpoints(rec, read_checkpoints(workspace / "checkpoints.txt"),
                                      read_checkpoint_observations(
                                          workspace / "checkpoint_observations.txt"),
                                      origin, frame="local")
    d = evaluation.todict()
    return {k: d[k] for k in ("rms_x", "rms_y", "rms_z", "rms_3d", "rms_3d_after_helmert",
                              "helmert", "num_checkpoints")}


def inputs(workspace: Path, model: str | None = None):
    """The workspace's reconstruction, city model and GNSS; `model` names another variant of
    the model (`models/<model>.gml`) than the scenario's given one."""
    from colmap_citymodel.block.gnss import read_gnss
    from colmap_citymodel.block.reconstruction import read_reconstruction
    from colmap_citymodel.citymodel.read import read_city_model

    given = (workspace / "given_model.gml" if model is None
             else workspace / "models" / f"{model}.gml")
    # Scenarios without a model still need its CRS and local frame (origin) for GNSS and check
    # points: take them from the sequence's corrected model, which no method then uses.
    store = read_city_model(given if given.exists() else workspace / "models" / "corrected.gml")
    gnss = read_gnss(database=workspace / "database.db", target_crs=store.crs)
    return read_reconstruction(workspace / "sparse" / "0"), store, gnss


def run_refine(workspace: Path, assignment: str = "direct", workflow: str = "global"):
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.workflow import refine

    rec, store, gnss = inputs(workspace)
    # Unger's settings for a detailed model (sigma_dTP 5 cm, 5 points per plane) in Scn1.
    options = RefineOptions.preset(
        "detailed" if model_variant(workspace) == "detailed" else "generalised")
    options.precision.covariances = "off"
    options.assignment.method = assignment
    options.workflow.mode = workflow
    result = refine(rec, store, gnss, options, progress=False)
    return result.reconstruction, store


def run_map(workspace: Path):
    """colmap-citymodel map on a copy of the workspace's database (its simulated matches; the
    interior orientation fixed as the simulator's COLMAP run keeps it), then refine's final
    adjustment on the mapped block; the same refine options as run_refine."""
    import shutil
    import tempfile

    from colmap_citymodel.mapper import map_block, pipeline_options, refine_mapped
    from colmap_citymodel.options import MapperOptions, RefineOptions
    from colmap_citymodel.simulate.scenario import load_scenario

    _, store, gnss = inputs(workspace)
    options = RefineOptions.preset(
        "detailed" if model_variant(workspace) == "detailed" else "generalised")
    options.precision.covariances = "off"
    simulation = load_scenario(
        ROOT / "workspaces" / f"{workspace.parent.name}_{workspace.name.lower()}.toml")
    fixed = not simulation.mapping.refine_intrinsics
    pipeline = pipeline_options({
        "ba_refine_focal_length": not fixed, "ba_refine_principal_point": False,
        "ba_refine_extra_params": not fixed,
        "mapper": {"abs_pose_refine_focal_length": not fixed,
                   "abs_pose_refine_extra_params": not fixed}},
        seed=simulation.mapping.random_seed if simulation.mapping.random_seed is not None
        else simulation.seed)
    with tempfile.TemporaryDirectory() as tmp:
        database = Path(tmp) / "database.db"
        shutil.copy(workspace / "database.db", database)
        mapped = map_block(database, store, gnss, options, MapperOptions(), pipeline,
                           progress=False)
    print(f"  map: {mapped.reconstruction.num_reg_images()} of {mapped.num_database_images} "
          f"images, {len(mapped.adjustments)} global adjustments ({mapped.num_hybrid} with the "
          f"model from {mapped.georegistered_at} images on), {mapped.seconds:.0f} s", flush=True)
    result = refine_mapped(mapped, store, gnss, options, progress=False)
    return result.reconstruction, store


def run_gnss(workspace: Path, with_ba: bool):
    from colmap_citymodel.adjust.steps import step2_bundle_adjustment
    from colmap_citymodel.align.block_to_model import georegister
    from colmap_citymodel.options import RefineOptions

    rec, store, gnss = inputs(workspace)
    _, priors, _ = georegister(rec, store, gnss, None)
    if with_ba:
        step2_bundle_adjustment(rec, priors, RefineOptions())
    return rec, store


def run_icp(workspace: Path):
    """Sim3 to GNSS, then rigid point-to-plane ICP of the tie points to the model surface."""
    import open3d as o3d

    from colmap_citymodel.block.reconstruction import tie_points
    from colmap_citymodel.citymodel.mesh import store_to_trimesh

    rec, store = run_gnss(workspace, with_ba=False)
    mesh, triangle_face = store_to_trimesh(store)
    keep = np.array([store.faces[f].semantic not in ("GroundSurface", "ClosureSurface")
                     for f in triangle_face])
    mesh.update_faces(keep)
    samples, triangles = mesh.sample(200_000, return_index=True)
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(samples))
    target.normals = o3d.utility.Vector3dVector(mesh.face_normals[triangles])
    _, xyz = tie_points(rec)
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    estimation = o3d.pipelines.registration.TransformationEstimationPointToPlane(
        o3d.pipelines.registration.TukeyLoss(k=0.5))
    transform = np.eye(4)
    for distance in (2.0, 1.0, 0.5):  # coarse to fine correspondence distances
        transform = o3d.pipelines.registration.registration_icp(
            source, target, distance, transform, estimation,
            o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=50)).transformation
    rec.transform(pycolmap.Sim3d(transform[:3, :4]))
    return rec, store


# ----------------------------------------------------------------------------------------------
# robustness: blocks shaped unlike the procedural street

ROBUST_CASES = ("drive", "orbit", "strip", "short")
# a run counts as at the truth when its camera centres are within this (RMS 3D, m)
TRUTH_TOLERANCE = 0.25


def code_version() -> str:
    """The commit of the colmap_citymodel package that runs (its git checkout's HEAD), with
    "+ uncommitted changes" when its sources differ from that commit."""
    import subprocess

    import colmap_citymodel

    package = Path(colmap_citymodel.__file__).resolve().parent

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(package), *args], capture_output=True, text=True,
                              check=True).stdout.strip()

    try:
        commit = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", ".", "../cpp_ext")
    except (OSError, subprocess.CalledProcessError):
        return f"package at {package} (not a git checkout)"
    return commit + (" + uncommitted changes" if dirty else "")


def build_robust_workspace(case: str, *, seed: int | None = None) -> tuple[Path, dict]:
    """workspaces/robust_<case>.toml -> workspaces/generated/robust/<case>[-seed<N>] (built
    once, again when the toml no longer matches its sequence key; the sequence cached in
    workspaces/generated/cache). Returns the workspace and its simulation.json (sizes,
    registered images, build seconds)."""
    return build_from_toml(ROOT / "workspaces" / f"robust_{case}.toml",
                           GENERATED / "robust" / (case if seed is None else f"{case}-seed{seed}"),
                           seed=seed)


def build_from_toml(toml: Path, out: Path, *, seed: int | None = None) -> tuple[Path, dict]:
    from colmap_citymodel.simulate import sequence as simulate
    from colmap_citymodel.simulate.scenario import load_scenario, sequence_key

    options = load_scenario(toml)
    if seed is not None:
        options.seed = seed
    stats = out / "simulation.json"
    made = json.loads(stats.read_text()) if stats.exists() else {}
    if not ((out / "sparse" / "0").is_dir() and made.get("sequence_key") == sequence_key(options)
            and made.get("scenario") == json.loads(json.dumps(
                dataclasses.asdict(options.scenario)))):
        simulate.main(toml, out, seed=seed, cache_path=GENERATED / "cache",
                      overwrite=out.exists(), progress=False)
    return out, json.loads(stats.read_text())


def truth_centres(workspace: Path) -> dict[str, np.ndarray]:
    """True projection centres by image name, model CRS (truth/ is local to truth/origin.txt)."""
    truth = pycolmap.Reconstruction(str(workspace / "truth"))
    lines = [line for line in (workspace / "truth" / "origin.txt").read_text().splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    origin = np.array([float(v) for v in lines[0].split()[:3]])
    return {im.name: im.projection_center() + origin for im in truth.images.values()}


def centre_errors(rec: pycolmap.Reconstruction, origin: np.ndarray, truth: dict) -> dict:
    """RMS of (estimated - true) camera centres of `rec` (local frame: model CRS - origin) per
    axis and 3D, over its registered images; also how many of the true images it has."""
    names = [image.name for image in rec.images.values()
             if image.has_pose and image.name in truth]
    if not names:
        return {"num_images": 0, "num_true_images": len(truth)}
    by_name = {image.name: image for image in rec.images.values()}
    estimated = np.array([by_name[name].projection_center() for name in names])
    true_local = np.array([truth[name] for name in names]) - origin
    d = estimated - true_local
    rms = np.sqrt(np.mean(d ** 2, axis=0))
    # The block's shape alone: what remains after the 7-parameter fit onto the true centres.
    from colmap_citymodel.precision.checkpoints import helmert_transform

    try:
        shape = helmert_transform(true_local, estimated).rms_3d
    except ValueError:  # fewer than 3 images, or all on one line
        shape = float("nan")
    return {"rms_x": float(rms[0]), "rms_y": float(rms[1]), "rms_z": float(rms[2]),
            "rms_3d": float(np.sqrt(np.sum(rms ** 2))), "rms_3d_after_helmert": shape,
            "mean_error": [float(v) for v in d.mean(axis=0)],
            "num_images": len(names), "num_true_images": len(truth)}


def checkpoint_errors(rec: pycolmap.Reconstruction, workspace: Path, origin: np.ndarray) -> dict:
    """Check point RMS (evaluate()) or, without usable check points, the reason."""
    if not (workspace / "checkpoints.txt").exists():
        return {}
    try:
        r = evaluate(rec, workspace, origin)
    except Exception as error:  # too few triangulated check points is a result too
        return {"error": f"{type(error).__name__}: {error}"}
    return {k: r[k] for k in ("rms_x", "rms_y", "rms_z", "rms_3d", "num_checkpoints")}


def refine_with_quality(workspace: Path, gnss=None, assignment: str | None = None,
                        model: str | None = None, gnss_bias: str | None = None) -> dict:
    """refine() on the workspace (GNSS from its database unless given; `assignment`: the
    method, None for refine's default; `gnss_bias` "auto": as refine --gnss_bias auto, the
    GNSS's constant bias estimated): the refined and the
    GNSS-only reconstruction (local frame), their origin, the verdict and its reasons. A refine
    that raises gives verdict "error" and no refined reconstruction. Without a GNSS-only result
    from refine, the GNSS-only block is the 7-parameter fit to GNSS plus the bundle adjustment
    with GNSS priors (run_gnss)."""
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.workflow import refine

    rec, store, gnss_db = inputs(workspace, model)
    gnss = gnss_db if gnss is None else gnss
    variant = model or model_variant(workspace)
    options = RefineOptions.preset("detailed" if variant == "detailed" else "generalised")
    options.precision.covariances = "off"
    if assignment is not None:
        options.assignment.method = assignment
    if gnss_bias == "auto":
        options.adjustment.gnss_offset = "all"
    dtm = sorted((workspace / "dtm").glob("*.tif"))  # a scenario with `dtm = true`
    if dtm:
        options.terrain.files = tuple(str(p) for p in dtm)
    out: dict = {"origin": store.origin, "refined": None, "gnss_only": None,
                 "verdict": "n/a", "reasons": [], "quality_metrics": None, "observability": None}
    start = time.perf_counter()
    try:
        result = refine(rec, store, gnss, options, progress=False)
    except Exception as error:
        out["verdict"] = "error"
        out["reasons"] = [f"{type(error).__name__}: {error}"]
        result = None
    out["seconds"] = time.perf_counter() - start
    if result is not None:
        out["refined"] = result.reconstruction
        out["origin"] = np.asarray(getattr(result, "origin", store.origin))
        out["gnss_only"] = getattr(result, "gnss_only", None)
        quality = getattr(result, "quality", None)
        if quality is not None:
            out["verdict"] = str(getattr(quality, "verdict", "n/a"))
            out["reasons"] = [str(r) for r in getattr(quality, "reasons", [])]
            out["quality_metrics"] = json.loads(json.dumps(getattr(quality, "metrics", None),
                                                           default=float))
        observability = getattr(result, "observability", None)
        if observability is not None:
            out["observability"] = json.loads(json.dumps(observability, default=str))
    if out["gnss_only"] is None:
        start = time.perf_counter()
        out["gnss_only"], gnss_store = gnss_only_block(workspace, gnss)
        out["gnss_only_origin"] = gnss_store.origin
        out["gnss_only_seconds"] = time.perf_counter() - start
    else:
        out["gnss_only_origin"] = out["origin"]
    return out


def gnss_only_block(workspace: Path, gnss=None):
    """The GNSS-only adjustment: 7-parameter fit to GNSS, bundle adjustment with GNSS priors."""
    from colmap_citymodel.adjust.steps import step2_bundle_adjustment
    from colmap_citymodel.align.block_to_model import georegister
    from colmap_citymodel.options import RefineOptions

    rec, store, gnss_db = inputs(workspace)
    _, priors, _ = georegister(rec, store, gnss_db if gnss is None else gnss, None)
    step2_bundle_adjustment(rec, priors, RefineOptions())
    return rec, store


#: The other assignment methods as robustness rows: benchmark name -> AssignmentOptions.method.
ASSIGNMENT_METHODS = {"refine_b": "msac", "refine_c": "roi_msac", "refine_auto": "auto"}


def robustness_method(case: str, method: str) -> dict:
    """Refine of a robustness case with another assignment method: camera centre and check
    point errors of its result (the GNSS-only block when it failed), verdict, seconds."""
    workspace, _ = build_robust_workspace(case)
    run = refine_with_quality(workspace, assignment=ASSIGNMENT_METHODS[method])
    rec = run["refined"]
    return {"verdict": run["verdict"], "reasons": run["reasons"], "seconds": run["seconds"],
            "cameras": centre_errors(rec, run["origin"], truth_centres(workspace))
            if rec is not None else None,
            "checkpoints": checkpoint_errors(rec, workspace, run["origin"])
            if rec is not None else None, "code": code_version()}


#: Other variants of a robustness case's model (models/ of its workspace): `corrected` has the
#: generalisation effects of a published LOD2 model only, `detailed` the true building planes;
#: the given `original` adds systematic plane errors (0.2 m shift, 0.5 deg tilt per face).
MODEL_VARIANTS = ("corrected", "detailed")


def robustness_model(case: str, variant: str) -> dict:
    """Refine of a robustness case against another variant of its model: camera centre errors
    per axis, verdict, what fixes E/N/U, seconds. Separates the method's error from the given
    model's."""
    workspace, _ = build_robust_workspace(case)
    run = refine_with_quality(workspace, assignment="direct", model=variant)
    rec = run["refined"]
    return {"verdict": run["verdict"], "reasons": run["reasons"], "seconds": run["seconds"],
            "observability": run["observability"],
            "cameras": centre_errors(rec, run["origin"], truth_centres(workspace))
            if rec is not None else None, "code": code_version()}


def robustness_case(case: str) -> dict:
    start = time.perf_counter()
    workspace, sim = build_robust_workspace(case)
    build = time.perf_counter() - start
    truth = truth_centres(workspace)
    run = refine_with_quality(workspace, assignment="direct")
    r: dict = {"workspace": str(workspace.relative_to(ROOT)),
               "num_key_frames": sim["num_key_frames"],
               "num_registered_images": sim.get("num_registered_images"),
               "num_models": sim.get("num_models"),
               "build_seconds": sim.get("total_seconds"), "ready_seconds": build,
               "verdict": run["verdict"], "reasons": run["reasons"],
               "quality_metrics": run["quality_metrics"], "observability": run["observability"],
               "seconds": run["seconds"]}
    for key, rec, origin in (("refine", run["refined"], run["origin"]),
                             ("gnss_only", run["gnss_only"], run["gnss_only_origin"])):
        if rec is None:
            r[key] = None
            continue
        r[key] = {"cameras": centre_errors(rec, origin, truth),
                  "checkpoints": checkpoint_errors(rec, workspace, origin)}
    if "gnss_only_seconds" in run:
        r["gnss_only_seconds"] = run["gnss_only_seconds"]
    return r


def _f(d: dict | None, *keys, fmt: str = "{:.3f}") -> str:
    for k in keys:
        if not isinstance(d, dict) or k not in d:
            return "-"
        d = d[k]
    return fmt.format(d) if isinstance(d, (int, float)) else str(d)


#: A direction the planes constrain must end this many times closer to the truth than the
#: GNSS-only block (and within TRUTH_TOLERANCE); a direction they leave to GNSS (or to a single
#: plane, which observability names) must end no further from it than the GNSS-only block.
CONSTRAINED_GAIN = 10.0


def direction_check(cameras: dict | None, gnss_only: dict | None,
                    observability: dict | None) -> dict:
    """Per direction E, N, U (the local frame's X, Y, Z): what fixes it (observability), the
    refined and GNSS-only camera-centre RMS, their ratio and whether the direction meets its
    criterion: constrained by planes ('planes' or 'both', more than one plane) -> refined
    <= TRUTH_TOLERANCE and >= CONSTRAINED_GAIN times better than GNSS only; otherwise (GNSS,
    one plane, none) -> refined no worse than GNSS only."""
    out = {}
    for axis, key in (("E", "rms_x"), ("N", "rms_y"), ("U", "rms_z")):
        obs = (observability or {}).get(axis, {})
        source = obs.get("source", "-")
        constrained = source in ("planes", "both") and not obs.get("one_plane", False)
        refined = (cameras or {}).get(key)
        gnss = (gnss_only or {}).get(key)
        if refined is None or gnss is None:
            out[axis] = {"source": source, "constrained": constrained, "meets": None}
            continue
        gain = gnss / refined if refined > 0 else float("inf")
        meets = (refined <= TRUTH_TOLERANCE and gain >= CONSTRAINED_GAIN) if constrained \
            else refined <= gnss
        out[axis] = {"source": source + (" (one plane)" if obs.get("one_plane") else ""),
                     "constrained": constrained, "refined": refined, "gnss_only": gnss,
                     "gain": gain, "meets": bool(meets)}
    return out


def _direction_cell(d: dict) -> str:
    if d.get("meets") is None:
        return "-"
    rule = "planes" if d["constrained"] else "free"
    return (f"{d['refined']:.3f} / {d['gnss_only']:.3f} = {d['gain']:.1f}x, {d['source']}, "
            f"{rule}: {'yes' if d['meets'] else 'no'}")


def direction_table(results: dict) -> list[str]:
    """The per-direction criterion for every case and model variant (direction_check)."""
    lines = ["", f"Per direction: refined / GNSS-only camera-centre RMS (m) = gain, what fixes "
             f"it, and whether it meets its criterion (a direction the planes fix, by more than "
             f"one plane: <= {TRUTH_TOLERANCE} m and >= {CONSTRAINED_GAIN:.0f}x better than GNSS "
             f"only; a direction left to GNSS or to one plane: no worse than GNSS only). The "
             f"GNSS-only block is the same for every model variant.", "",
             "| case | model | E | N | U | all |", "|---|---|---|---|---|---|"]
    met = []
    for case, r in results.items():
        gnss = (r.get("gnss_only") or {}).get("cameras")
        rows = [("original", (r.get("refine") or {}).get("cameras"), r.get("observability"))]
        rows += [(v, m.get("cameras"), m.get("observability"))
                 for v, m in (r.get("models") or {}).items()]
        for variant, cams, obs in rows:
            check = direction_check(cams, gnss, obs)
            meets = [d["meets"] for d in check.values()]
            everything = None if None in meets else all(meets)
            if everything:
                met.append(f"{case} ({variant})")
            lines.append(f"| {case} | {variant} | " + " | ".join(
                _direction_cell(check[a]) for a in ("E", "N", "U")) +
                f" | {'-' if everything is None else ('yes' if everything else 'no')} |")
    lines += ["", f"Cases and models that meet it in every direction: "
              f"{', '.join(met) if met else 'none'}.", "",
              "How much of the error the given model's own plane errors leave to any method "
              "that takes its planes as given (the true block fitted onto them), and whether a "
              "direction's target lies below that: `model_floor.md` "
              "(`benchmarks/model_floor.py`)."]
    return lines


def robustness_table(results: dict) -> str:
    lines = ["| case | images (registered) | method | cam RMS X | Y | Z | 3D | cam 3D after "
             "Helmert | CP RMS 3D | verdict | s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for case, r in results.items():
        images = f"{r['num_key_frames']} ({r['num_registered_images']})"
        for key, label in (("gnss_only", "GNSS only"), ("refine", "refine")):
            m = r.get(key)
            cams = m["cameras"] if m else None
            cps = m["checkpoints"] if m else None
            verdict = r["verdict"] if key == "refine" else ""
            secs = r["seconds"] if key == "refine" else r.get("gnss_only_seconds")
            lines.append(
                f"| {case} | {images} | {label} | {_f(cams, 'rms_x')} | {_f(cams, 'rms_y')} | "
                f"{_f(cams, 'rms_z')} | {_f(cams, 'rms_3d')} | {_f(cams, 'rms_3d_after_helmert')} "
                f"| {_f(cps, 'rms_3d')} | {verdict} "
                f"| {'' if secs is None else f'{secs:.0f}'} |")
    wrong_ok = [case for case, r in results.items() if r["verdict"] == "ok" and (
        r.get("refine") is None or r["refine"]["cameras"].get("rms_3d", np.inf) > TRUTH_TOLERANCE)]
    lines += ["", f"Cases whose refined camera centres end further than {TRUTH_TOLERANCE} m "
              f"(RMS 3D) from the truth with verdict ok: "
              f"{', '.join(wrong_ok) if wrong_ok else 'none'}."]
    lines += ["", "Workspaces (simulate: build + COLMAP mapping, seconds when they were built):",
              "", "| case | key frames | registered | COLMAP models | build s |",
              "|---|---|---|---|---|"]
    for case, r in results.items():
        lines.append(f"| {case} | {r['num_key_frames']} | {r['num_registered_images']} | "
                     f"{r['num_models']} | {_f(r, 'build_seconds', fmt='{:.0f}')} |")
    methods = {case: r["methods"] for case, r in results.items() if r.get("methods")}
    if methods:
        lines += ["", "Other assignment methods (refine_a above is direct assignment): camera "
                  "centre RMS 3D (m) and verdict", "",
                  "| case | " + " | ".join(ASSIGNMENT_METHODS) + " |",
                  "|---|" + "---|" * len(ASSIGNMENT_METHODS)]
        for case, by_method in methods.items():
            cells = [f"{_f(by_method.get(m), 'cameras', 'rms_3d')} "
                     f"({by_method[m]['verdict']})" if m in by_method else "-"
                     for m in ASSIGNMENT_METHODS]
            lines.append(f"| {case} | " + " | ".join(cells) + " |")
    models = {case: r["models"] for case, r in results.items() if r.get("models")}
    if models:
        lines += ["", "The same blocks against other variants of their model (the given one is "
                  "`original`: the LOD2 model with systematic plane errors of 0.2 m and 0.5 deg "
                  "per face; `corrected`: generalisation effects only; `detailed`: the true "
                  "building planes): camera centre RMS per axis and 3D (m), what fixes E / N / U, "
                  "verdict", "", "| case | model | X | Y | Z | 3D | E / N / U from | verdict |",
                  "|---|---|---|---|---|---|---|---|"]
        for case, by_model in models.items():
            given = results[case]
            rows = [("original", {"cameras": (given.get("refine") or {}).get("cameras"),
                                  "observability": given.get("observability"),
                                  "verdict": given["verdict"]})]
            rows += [(v, by_model[v]) for v in MODEL_VARIANTS if v in by_model]
            for variant, m in rows:
                cams = m.get("cameras")
                obs = m.get("observability") or {}
                fixed = " / ".join(obs.get(k, {}).get("source", "-") for k in ("E", "N", "U"))
                lines.append(f"| {case} | {variant} | {_f(cams, 'rms_x')} | {_f(cams, 'rms_y')} "
                             f"| {_f(cams, 'rms_z')} | {_f(cams, 'rms_3d')} | {fixed} | "
                             f"{m['verdict']} |")
    lines += direction_table(results)
    reasons = [(case, r["reasons"]) for case, r in results.items() if r["reasons"]]
    if reasons:
        lines += ["", "Reasons given with the verdicts:", ""]
        lines += [f"- {case}: " + "; ".join(rs) for case, rs in reasons]
    return "\n".join(lines) + "\n"


def _code_versions(results: dict) -> str:
    versions = sorted({r.get("code", "not recorded") for r in results.values()})
    return ", ".join(versions) if versions else "-"


def run_robustness(cases: list[str], json_path: Path, methods: list[str] = (),
                   models: list[str] = ()) -> None:
    everything = json.loads(json_path.read_text()) if json_path.exists() else {}
    for case in cases:
        print(f"robustness {case}: ...", flush=True)
        if "refine_a" in methods or not methods:
            r = robustness_case(case)
            r["code"] = code_version()
            r["methods"] = everything.get("robustness", {}).get(case, {}).get("methods", {})
            r["models"] = everything.get("robustness", {}).get(case, {}).get("models", {})
            print(f"  verdict {r['verdict']}; camera RMS 3D refine "
                  f"{_f(r['refine'], 'cameras', 'rms_3d')} m, GNSS only "
                  f"{_f(r['gnss_only'], 'cameras', 'rms_3d')} m ({r['seconds']:.0f} s)",
                  flush=True)
            everything = update_json(json_path, ["robustness", case], r)
        for method in [m for m in methods if m in ASSIGNMENT_METHODS]:
            m = robustness_method(case, method)
            print(f"  {method}: verdict {m['verdict']}; camera RMS 3D "
                  f"{_f(m, 'cameras', 'rms_3d')} m ({m['seconds']:.0f} s)", flush=True)
            everything = update_json(json_path, ["robustness", case, "methods", method], m)
        for variant in models:
            m = robustness_model(case, variant)
            print(f"  model {variant}: verdict {m['verdict']}; camera RMS 3D "
                  f"{_f(m, 'cameras', 'rms_3d')} m ({m['seconds']:.0f} s)", flush=True)
            everything = update_json(json_path, ["robustness", case, "models", variant], m)
    results = {c: everything["robustness"][c] for c in ROBUST_CASES
               if c in everything.get("robustness", {})}
    text = robustness_table(results)
    (RESULTS / "robustness.md").write_text(
        "# Robustness: blocks shaped unlike the procedural street\n\nProduced by (results "
        "accumulate in scenarios.json, section `robustness`)\n\n    .venv/bin/python "
        "benchmarks/scenarios.py --robustness\n\nCases (workspaces/robust_*.toml, "
        "workspaces/README.md): `drive` a forward-looking vehicle camera at 2 m along one side of "
        "a street (Berlin 3910_5819), `orbit` a UAV circle around one building (Berlin "
        "3920_5820), `strip` one straight UAV strip (Berlin 3910_5819), `short` 20 images of "
        "the procedural street. GNSS: white noise 3/3/5 m plus a constant bias of 4 m (drive, "
        "orbit) or 5 m (strip, short), stated sigma 3/3/5 m. cam RMS: camera centres (estimated "
        "- simulated truth, m) over the registered images; cam 3D after Helmert: the same "
        "after a 7-parameter fit onto the true centres, the block's shape error alone; CP RMS "
        "3D: check points "
        "triangulated in the result. GNSS only: the GNSS-only adjustment of the same block "
        "(refine's own when it returns one, else a 7-parameter fit to GNSS plus bundle "
        "adjustment with GNSS priors). verdict: refine's quality verdict (n/a: this refine "
        "has none); s: seconds of refine (for GNSS only: of that separate adjustment).\n\n"
        f"Code measured: {_code_versions(results)}.\n\n" + text)
    print(text)


RUNNERS = {"refine_a": run_refine, "refine_b": lambda w: run_refine(w, "msac"),
           "refine_c": lambda w: run_refine(w, "roi_msac"),
           "refine_auto": lambda w: run_refine(w, "auto"),
           "sliding_window": lambda w: run_refine(w, workflow="sliding_window"),
           "map": run_map,
           "gnss_ba": lambda w: run_gnss(w, True), "gnss_sim3": lambda w: run_gnss(w, False),
           "icp": run_icp}


def table(sequence: str, results: dict) -> str:
    lines = [f"## {sequence} sequence", "",
             "| scenario | method | RMS X | RMS Y | RMS Z | RMS 3D | RMS 3D after Helmert "
             "| Helmert t (m) | rot (deg) | scale (ppm) | s | Unger RMS 3D |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for scenario, methods in results.items():
        for method, r in methods.items():
            if "error" in r:
                lines.append(f"| {scenario} | {method} | failed: {r['error']} |||||||||")
                continue
            h = r["helmert"] or {}
            t = ", ".join(f"{h.get(k, float('nan')):.2f}" for k in ("tx", "ty", "tz"))
            rot = ", ".join(f"{h.get(k, float('nan')):.3f}"
                            for k in ("omega_deg", "phi_deg", "kappa_deg"))
            unger = UNGER.get(sequence, {}).get(scenario, "") if method == "refine_a" else ""
            lines.append(
                f"| {scenario} | {method} | {r['rms_x']:.3f} | {r['rms_y']:.3f} | "
                f"{r['rms_z']:.3f} | {r['rms_3d']:.3f} | {r['rms_3d_after_helmert']:.3f} | {t} | "
                f"{rot} | {h.get('scale_ppm', float('nan')):.0f} | {r['seconds']:.0f} | {unger} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sequences", nargs="+", default=["short", "long"])
    parser.add_argument("--scenarios", nargs="+", default=list(SCENARIOS))
    parser.add_argument("--methods", nargs="+", default=None,
                        help=f"methods (default: all, {', '.join(METHODS)}; with --robustness: "
                             "refine_a)")
    parser.add_argument("--tables_only", action="store_true",
                        help="only rewrite the tables from results/scenarios.json")
    parser.add_argument("--robustness", action="store_true",
                        help="run the robustness cases (workspaces/robust_*.toml) instead")
    parser.add_argument("--cases", nargs="+", default=list(ROBUST_CASES),
                        choices=ROBUST_CASES, help="robustness cases to run")
    parser.add_argument("--model_variants", nargs="*", default=[], choices=MODEL_VARIANTS,
                        help="with --robustness: also refine each case against these variants "
                             "of its model")
    args = parser.parse_args()
    import colmap_citymodel  # noqa: F401  (sets up the package logger first)

    logging.getLogger("colmap_citymodel").setLevel(logging.WARNING)
    RESULTS.mkdir(parents=True, exist_ok=True)
    json_path = RESULTS / "scenarios.json"
    if args.robustness:
        # Robustness rows: refine_a (direct) unless --methods names others.
        run_robustness([] if args.tables_only else args.cases, json_path,
                       [m for m in args.methods or ["refine_a"] if m.startswith("refine")],
                       args.model_variants)
        return
    everything = json.loads(json_path.read_text()) if json_path.exists() else {}
    for sequence in args.sequences:
        results = everything.setdefault(sequence, {})
        for scenario in [] if args.tables_only else args.scenarios:
            start = time.perf_counter()
            workspace = build_workspace(sequence, scenario)
            print(f"{sequence} {scenario}: workspace ready in {time.perf_counter() - start:.0f} s",
                  flush=True)
            model = has_model(workspace)
            for method in args.methods or METHODS:
                if not model and (method.startswith("refine") or method in (
                        "icp", "sliding_window", "map")):
                    continue
                if sequence not in ONLY_ON.get(method, (sequence,)):
                    continue
                start = time.perf_counter()
                try:
                    rec, store = RUNNERS[method](workspace)
                    r = evaluate(rec, workspace, store.origin)
                except Exception as error:  # a failed method is a result too
                    r = {"error": f"{type(error).__name__}: {error}"}
                r["seconds"] = time.perf_counter() - start
                results = update_json(json_path, [sequence, scenario, method], r)[sequence]
                print(f"  {method}: " + (f"RMS 3D {r['rms_3d']:.3f} m, after Helmert "
                                         f"{r['rms_3d_after_helmert']:.3f} m" if "rms_3d" in r
                                         else r["error"]) + f" ({r['seconds']:.0f} s)", flush=True)
        results = dict(sorted(results.items()))
        text = table(sequence, results)
        command = f"    .venv/bin/python benchmarks/scenarios.py --sequences {sequence}"
        (RESULTS / f"{sequence}.md").write_text(
            f"# Check point accuracy, {sequence} sequence\n\nProduced by (results accumulate in "
            f"scenarios.json; a run with --scenarios updates those rows)\n\n{command}\n\n"
            "RMS of check point errors (known - estimated) in metres; Helmert: the 7-parameter "
            "transform from estimated to known check points (rotation centre at their "
            "centroid); Unger: his RMS 3D for the refine in the same scenario (method.md 8).\n\n"
            + text)
        print(text)


if __name__ == "__main__":
    main()
