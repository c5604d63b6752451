"""The ground as control on the robustness drive: refine with the scenario's DTM, with the
terrain from the buildings' feet alone (no DTM), and without terrain, against the GNSS-only
block; camera-centre RMS per axis against the simulated truth, the verdict, what fixed U and
the terrain's residuals.

The drive (workspaces/robust_drive.toml): a forward-looking vehicle camera 2 m above a Berlin
street with kerbs and a 2 % cross slope, GNSS 3/3/5 m white noise plus a 4 m bias; its DTM
(dtm/ of the workspace) has two tiles with a height offset each (sigma 0.10 m) and 0.15 m
noise per post. Writes benchmarks/results/terrain.md and terrain.json.

    .venv/bin/python benchmarks/bench_terrain.py [--case drive] [--modes dtm feet none]
        [--model corrected]
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from scenarios import (RESULTS, ROOT, build_robust_workspace, centre_errors, code_version,
                       inputs, truth_centres)

MODES = {"dtm": "the scenario's DTM", "feet": "the buildings' feet (no DTM)",
         "none": "no terrain (--terrain none)"}


def run(workspace: Path, mode: str, model: str | None = None) -> dict:
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.workflow import refine

    rec, store, gnss = inputs(workspace, model)
    options = RefineOptions()
    options.precision.covariances = "off"
    options.assignment.method = "direct"
    if mode == "dtm":
        options.terrain.files = tuple(str(p) for p in sorted((workspace / "dtm").glob("*.tif")))
    elif mode == "none":
        options.terrain.source = "none"
    start = time.perf_counter()
    result = refine(rec, store, gnss, options, progress=False)
    seconds = time.perf_counter() - start
    truth = truth_centres(workspace)
    out = {"seconds": seconds, "verdict": result.quality.verdict,
           "reasons": [str(r) for r in result.quality.reasons],
           "cameras": centre_errors(result.refined or result.reconstruction, result.origin,
                                    truth),
           "observability": json.loads(json.dumps(result.observability, default=str)),
           "terrain": json.loads(json.dumps(result.terrain, default=float))}
    if result.gnss_only is not None:
        out["gnss_only"] = centre_errors(result.gnss_only, result.origin, truth)
    return out


def table(case: str, results: dict) -> str:
    lines = [f"### {case}", "",
             "| terrain | RMS E | RMS N | RMS U | RMS 3D | U fixed by | ground points | "
             "terrain RMS (m) | verdict | s |", "|---|---|---|---|---|---|---|---|---|---|"]
    gnss_only = next((r["gnss_only"] for r in results.values() if "gnss_only" in r), None)
    if gnss_only is not None:
        lines.append(f"| GNSS only | {gnss_only['rms_x']:.3f} | {gnss_only['rms_y']:.3f} | "
                     f"{gnss_only['rms_z']:.3f} | {gnss_only['rms_3d']:.3f} | gnss | - | - | - "
                     "| - |")
    for mode, r in results.items():
        c = r["cameras"]
        row = r["observability"].get("U") or {}
        u = row.get("source", "-") + (" (terrain)" if row.get("terrain") else "")
        res = (r["terrain"].get("residuals") or {})
        rms = res.get("rms_m")
        lines.append(f"| {MODES[mode]} | {c['rms_x']:.3f} | {c['rms_y']:.3f} | {c['rms_z']:.3f} "
                     f"| {c['rms_3d']:.3f} | {u} | {res.get('num_points', 0)} | "
                     f"{'-' if rms is None else f'{rms:.3f}'} | {r['verdict']} | "
                     f"{r['seconds']:.0f} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", default="drive")
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    parser.add_argument("--model", default=None, choices=["corrected", "detailed"],
                        help="another variant of the case's model than the given one "
                             "(systematic plane errors, feet included)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    workspace, _ = build_robust_workspace(args.case)
    results = {}
    for mode in args.modes:
        print(f"{args.case} / {mode} ...", flush=True)
        results[mode] = run(workspace, mode, args.model)
        c = results[mode]["cameras"]
        print(f"  RMS E/N/U {c['rms_x']:.3f} {c['rms_y']:.3f} {c['rms_z']:.3f} m, "
              f"{results[mode]['verdict']}", flush=True)
    path = RESULTS / "terrain.json"
    everything = json.loads(path.read_text()) if path.exists() else {}
    key = args.case + (f" ({args.model} model)" if args.model else "")
    everything[key] = {"code": code_version(), "workspace":
                             str(workspace.relative_to(ROOT)), "modes": results}
    path.write_text(json.dumps(everything, indent=2))
    print(write_markdown(everything))


def write_markdown(everything: dict) -> str:
    """benchmarks/results/terrain.md from terrain.json's content; returns the tables."""
    text = "\n\n".join(table(case, v["modes"]) + f"\n\nCode: {v['code']}."
                       for case, v in everything.items())
    (RESULTS / "terrain.md").write_text(
        "# The ground as control\n\nProduced by\n\n    .venv/bin/python benchmarks/"
        "bench_terrain.py\n\nCamera centres (estimated - simulated truth, m) over the "
        "registered images; U fixed by: adjust.observability's source of the height; ground "
        "points: tie points on the terrain faces after the last solve, terrain RMS their "
        "distance from it.\n\n" + text + "\n")
    return text


if __name__ == "__main__":
    main()
