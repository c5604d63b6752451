"""The ground as control: refine with the scenario's DTM, with the terrain from the buildings'
feet alone (no DTM), and without terrain, against the GNSS-only block; camera-centre RMS per
axis against the simulated truth, the verdict, what fixed U and the terrain's residuals.

Cases (each with a DTM of two tiles, a height offset each (sigma 0.10 m) and 0.15 m noise per
post, in dtm/ of its workspace; GNSS 3/3/5 m white noise plus a 4 m bias; the "original"
model):

- drive (workspaces/robust_drive.toml): a forward-looking vehicle camera 2 m above a Berlin
  street with kerbs and a 2 % cross slope;
- grid (workspaces/nadir_grid.toml): a UAV mapping flight, a nadir camera 70 m above the
  ground on five strips 30 m apart over the eastern blocks of the same tile, about half its
  tie points on the ground.

Writes benchmarks/results/terrain.md and terrain.json.

    .venv/bin/python benchmarks/bench_terrain.py [--case drive|grid] [--modes dtm feet none]
        [--model corrected]
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from scenarios import (GENERATED, RESULTS, ROOT, build_from_toml, centre_errors, code_version,
                       inputs, truth_centres)

#: case -> (its scenario file in workspaces/, its workspace under workspaces/generated/)
CASES = {"drive": ("robust_drive.toml", "robust/drive"),
         "grid": ("nadir_grid.toml", "terrain/grid")}

#: What each case is, above its table.
ABOUT = {"drive": "A forward-looking vehicle camera 2 m above a street with kerbs and a 2 % "
                  "cross slope, facades on one side (40 key frames over 280 m).",
         "grid": "A UAV mapping flight: a nadir camera 70 m above the ground, five strips "
                 "30 m apart over 19 buildings (76 images)."}

#: A tie point within this height (m) of the true ground counts as a ground point.
GROUND_BAND = 0.5

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
    out["ground_share"] = ground_share(result.refined or result.reconstruction, result.origin,
                                       workspace)
    return out


def ground_share(rec, origin: np.ndarray, workspace: Path) -> float | None:
    """The share of the tie points of `rec` (local frame) within GROUND_BAND of the true
    ground (truth/ground.tif)."""
    import rasterio

    path = workspace / "truth" / "ground.tif"
    if not path.exists() or not len(rec.points3D):
        return None
    xyz = np.array([p.xyz for p in rec.points3D.values()]) + origin
    with rasterio.open(path) as src:
        ground = src.read(1, masked=True)
        rows, cols = rasterio.transform.rowcol(src.transform, xyz[:, 0], xyz[:, 1])
    rows, cols = np.asarray(rows), np.asarray(cols)
    inside = (rows >= 0) & (rows < ground.shape[0]) & (cols >= 0) & (cols < ground.shape[1])
    z = np.full(len(xyz), np.nan)
    z[inside] = np.ma.filled(ground[rows[inside], cols[inside]].astype(float), np.nan)
    return float(np.mean(np.abs(xyz[:, 2] - z) < GROUND_BAND))


def table(case: str, results: dict) -> str:
    share = next((r.get("ground_share") for r in results.values()
                  if r.get("ground_share") is not None), None)
    lines = [f"### {case}", ""]
    about = ABOUT.get(case.split(" ")[0])
    if about:
        lines += [about, ""]
    if share is not None:
        lines += [f"Tie points within {GROUND_BAND:g} m of the true ground: {share:.0%}.", ""]
    lines += ["| terrain | RMS E | RMS N | RMS U | RMS 3D | U fixed by | ground points | "
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
    parser.add_argument("--case", default="drive", choices=list(CASES))
    parser.add_argument("--modes", nargs="+", default=list(MODES), choices=list(MODES))
    parser.add_argument("--model", default=None, choices=["corrected", "detailed"],
                        help="another variant of the case's model than the given one "
                             "(systematic plane errors, feet included)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING)
    toml, generated = CASES[args.case]
    workspace, _ = build_from_toml(ROOT / "workspaces" / toml, GENERATED / generated)
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
        "bench_terrain.py --case drive\n    .venv/bin/python benchmarks/bench_terrain.py "
        "--case drive --model corrected\n    .venv/bin/python benchmarks/bench_terrain.py "
        "--case grid\n\nEach case: the \"original\" model (0.2 m / 0.5 deg plane errors, the "
        "buildings' ground heights included), GNSS 3/3/5 m white noise plus a 4 m bias, a DTM "
        "of two tiles (0.10 m offset sigma per tile, 0.15 m noise per post). Camera centres (estimated - simulated truth, m) over the "
        "registered images; U fixed by: adjust.observability's source of the height; ground "
        "points: tie points on the terrain faces after the last solve, terrain RMS their "
        "distance from it.\n\n" + text + "\n")
    return text


if __name__ == "__main__":
    main()
