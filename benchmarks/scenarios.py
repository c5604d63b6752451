"""Unger's scenarios on simulated flights: check point accuracy per method (issue 4, part 4).

For each sequence (short ~90, long ~340 key frames) and scenario Scn1..Scn6
(`workspaces/{short,long}_scnN.toml`), the workspace is built by the simulator (each sequence is
mapped once by COLMAP; workspaces under workspaces/generated/, as workspaces/README.md builds them), then every method runs on copies of
the same `sparse/0` and is evaluated on the simulated check points:

- refine_a:  colmap-citymodel refine (global workflow, direct assignment (a));
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
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np
import pycolmap

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
GENERATED = ROOT / "workspaces" / "generated"
SCENARIOS = ("Scn1", "Scn2", "Scn3", "Scn4", "Scn5", "Scn6")
METHODS = ("refine_a", "gnss_ba", "gnss_sim3", "icp")
# Unger chapter 6 (method.md 8): RMS 3D of check points, m.
UNGER = {"short": {"Scn1": 0.10, "Scn2": 0.19, "Scn3": 0.25, "Scn5": "< 1"},
         "long": {"Scn2": 0.12, "Scn4": 0.31, "Scn5": "metres", "Scn6": "~5"}}


def build_workspace(sequence: str, scenario: str) -> Path:
    from colmap_citymodel import simulate

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
    from colmap_citymodel.evaluate import (evaluate_checkpoints, read_checkpoint_observations,
                                           read_checkpoints)

    evaluation = evaluate_checkpoints(rec, read_checkpoints(workspace / "checkpoints.txt"),
                                      read_checkpoint_observations(
                                          workspace / "checkpoint_observations.txt"),
                                      origin, frame="local")
    d = evaluation.todict()
    return {k: d[k] for k in ("rms_x", "rms_y", "rms_z", "rms_3d", "rms_3d_after_helmert",
                              "helmert", "num_checkpoints")}


def inputs(workspace: Path):
    from colmap_citymodel.read_city_model import read_city_model
    from colmap_citymodel.workflow import read_gnss, read_reconstruction

    given = workspace / "given_model.gml"
    # Scenarios without a model still need its CRS and local frame (origin) for GNSS and check
    # points: take them from the sequence's corrected model, which no method then uses.
    store = read_city_model(given if given.exists() else workspace / "models" / "corrected.gml")
    gnss = read_gnss(database=workspace / "database.db", target_crs=store.crs)
    return read_reconstruction(workspace / "sparse" / "0"), store, gnss


def run_refine(workspace: Path):
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.workflow import refine

    rec, store, gnss = inputs(workspace)
    # Unger's settings for a detailed model (sigma_dTP 5 cm, 5 points per plane) in Scn1.
    options = RefineOptions.preset(
        "detailed" if model_variant(workspace) == "detailed" else "generalised")
    options.precision.covariances = "off"
    result = refine(rec, store, gnss, options, progress=False)
    return result.reconstruction, store


def run_gnss(workspace: Path, with_ba: bool):
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.workflow import georegister, step2_bundle_adjustment

    rec, store, gnss = inputs(workspace)
    _, priors, _ = georegister(rec, store, gnss, None)
    if with_ba:
        step2_bundle_adjustment(rec, priors, RefineOptions())
    return rec, store


def run_icp(workspace: Path):
    """Sim3 to GNSS, then rigid point-to-plane ICP of the tie points to the model surface."""
    import open3d as o3d

    from colmap_citymodel.export_mesh import store_to_trimesh
    from colmap_citymodel.workflow import tie_points

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


RUNNERS = {"refine_a": run_refine, "gnss_ba": lambda w: run_gnss(w, True),
           "gnss_sim3": lambda w: run_gnss(w, False), "icp": run_icp}


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
    parser.add_argument("--methods", nargs="+", default=list(METHODS))
    parser.add_argument("--tables_only", action="store_true",
                        help="only rewrite the tables from results/scenarios.json")
    args = parser.parse_args()
    import colmap_citymodel  # noqa: F401  (sets up the package logger first)

    logging.getLogger("colmap_citymodel").setLevel(logging.WARNING)
    RESULTS.mkdir(parents=True, exist_ok=True)
    json_path = RESULTS / "scenarios.json"
    everything = json.loads(json_path.read_text()) if json_path.exists() else {}
    for sequence in args.sequences:
        results = everything.setdefault(sequence, {})
        for scenario in [] if args.tables_only else args.scenarios:
            start = time.perf_counter()
            workspace = build_workspace(sequence, scenario)
            print(f"{sequence} {scenario}: workspace ready in {time.perf_counter() - start:.0f} s",
                  flush=True)
            model = has_model(workspace)
            for method in args.methods:
                if not model and method in ("refine_a", "icp"):
                    continue
                start = time.perf_counter()
                try:
                    rec, store = RUNNERS[method](workspace)
                    r = evaluate(rec, workspace, store.origin)
                except Exception as error:  # a failed method is a result too
                    r = {"error": f"{type(error).__name__}: {error}"}
                r["seconds"] = time.perf_counter() - start
                results.setdefault(scenario, {})[method] = r
                print(f"  {method}: " + (f"RMS 3D {r['rms_3d']:.3f} m, after Helmert "
                                         f"{r['rms_3d_after_helmert']:.3f} m" if "rms_3d" in r
                                         else r["error"]) + f" ({r['seconds']:.0f} s)", flush=True)
                json_path.write_text(json.dumps(everything, indent=2))
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
