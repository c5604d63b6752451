"""`colmap-citymodel demo`: the whole job on a built-in workspace with known truth.

1. simulate the packaged scenario `simulate/demo.toml` (a procedural street, COLMAP's own incremental mapper);
2. the baseline a user has without a city model: 7-parameter fit to GNSS + bundle adjustment
   with GNSS priors (what COLMAP's pose-prior BA does);
3. `refine` with the given LOD2 model (systematic errors like a real generalised model);
4. check point evaluation of both against the known targets, read as check marks from the
   simulator's `checkpoints_gcp_list.txt` (OpenDroneMap's format, as a user's surveyed check
   points would come); a summary table with the ASPRS accuracy figures.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pycolmap

from . import logger
from .errors import InputError

DEMO_SCENARIO = Path(__file__).resolve().parent / "simulate" / "demo.toml"
MARKER = ".colmap_citymodel_demo"


def write_baseline(workspace: Path, out: Path) -> Path:
    """GNSS-only baseline: similarity to GNSS, then BA with GNSS priors, written in CRS."""
    from .adjust.steps import step2_bundle_adjustment
    from .align.block_to_model import georegister
    from .block.gnss import read_gnss
    from .block.reconstruction import read_reconstruction
    from .citymodel.read import read_city_model
    from .files import atomic_directory
    from .options import RefineOptions

    store = read_city_model(workspace / "given_model.gml")
    gnss = read_gnss(database=workspace / "database.db", target_crs=store.crs)
    rec = read_reconstruction(workspace / "sparse" / "0")
    _, priors, _ = georegister(rec, store, gnss, None)
    step2_bundle_adjustment(rec, priors, RefineOptions())
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), store.origin))
    with atomic_directory(out) as tmp:
        rec.write_binary(str(tmp))
        (tmp / "georeference.json").write_text(json.dumps(
            {"origin": [float(v) for v in store.origin], "output_frame": "crs",
             "crs": {"label": store.crs.label, "wkt": store.crs.wkt},
             "note": "GNSS-only baseline: Sim3 to GNSS + bundle adjustment with GNSS priors"},
            indent=2))
    return out


def main(output_path: str | Path, *, scenario: str | Path | None = None,
         progress: bool = True) -> dict:
    from .precision import checkpoints as evaluate
    from .simulate import sequence as simulate
    from .workflow import main as refine_main

    scenario = Path(scenario) if scenario else DEMO_SCENARIO
    if not scenario.is_file():
        raise InputError("demo scenario not found", scenario)
    out = Path(output_path)
    if out.exists() and any(out.iterdir()):
        if not (out / MARKER).exists():
            raise InputError("output path exists and is not a previous demo output; give a new "
                             "directory", out)
        shutil.rmtree(out)  # a previous demo run of ours: replace it
    out.mkdir(parents=True, exist_ok=True)
    (out / MARKER).write_text("written by colmap-citymodel demo\n")

    logger.info("1/4 simulating the demo flight (COLMAP mapper) into %s", out / "workspace")
    workspace = simulate.main(scenario, out / "workspace", progress=progress)
    logger.info("2/4 GNSS-only baseline")
    baseline = write_baseline(workspace, out / "gnss_only")
    logger.info("3/4 refine with the city model")
    refined = refine_main(workspace / "sparse" / "0", workspace / "given_model.gml", out / "refined",
                          database=workspace / "database.db", progress=progress,
                          checkpoints=workspace / "checkpoints_gcp_list.txt")
    logger.info("4/4 check points")
    results = {}
    for name, model in (("gnss_only", baseline), ("refined", out / "refined")):
        evaluation = evaluate.main(model, workspace / "checkpoints_gcp_list.txt", as_json=False)
        results[name] = evaluation["evaluated"]
    results["refined"]["verdict"] = refined.quality.verdict
    lines = ["# colmap-citymodel demo", "",
             "Check point errors (known - estimated), m:", "",
             "| method | RMS X | RMS Y | RMS Z | RMS 3D | RMS 3D after Helmert |",
             "|---|---|---|---|---|---|"]
    for name, r in results.items():
        lines.append(f"| {name} | {r['rms_x']:.3f} | {r['rms_y']:.3f} | {r['rms_z']:.3f} | "
                     f"{r['rms_3d']:.3f} | {r['rms_3d_after_helmert']:.3f} |")
    lines += ["", "ASPRS Positional Accuracy Standards, Edition 2 (with the check marks' stated "
              "survey sigmas, 0.02 / 0.03 m), m; the test of each block on the check marks:", "",
              "| method | RMSE_H | RMSE_V | horizontal 95 % | vertical 95 % | check test |",
              "|---|---|---|---|---|---|"]
    for name, r in results.items():
        a, t = r["asprs"], r["test"]
        lines.append(f"| {name} | {a['rmse_h_m']:.3f} | {a['rmse_v_m']:.3f} | "
                     f"{a['horizontal_accuracy_95_m']:.3f} | {a['vertical_accuracy_95_m']:.3f} | "
                     f"{'passed' if t['passed'] else 'failed'} ({t['sigmas']}) |")
    lines += ["", f"Refine's verdict: {refined.quality.verdict}"
              + (f" ({'; '.join(refined.quality.reasons)})" if refined.quality.reasons else "")]
    table = "\n".join(lines) + "\n"
    (out / "summary.md").write_text(table)
    (out / "summary.json").write_text(json.dumps(results, indent=2))
    print()
    print(table)
    print(f"outputs in {out.resolve()}:")
    print(f"  workspace/   simulated COLMAP workspace (database.db, sparse/0, given_model.gml, truth/)")
    print(f"  gnss_only/   GNSS-only bundle adjustment (COLMAP model in the model CRS)")
    print(f"  refined/     refined COLMAP model in the model CRS, report.md, report.html "
          f"(with a 3D view), assignments.ply, model_mesh.ply")
    print(f"  summary.md   the table above")
    return {k: float(v["rms_3d"]) for k, v in results.items()}


if __name__ == "__main__":  # pragma: no cover
    main("demo_output")
