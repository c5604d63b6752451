"""Georegistration without GNSS: simulated blocks registered from the city model alone.

Each block is refined twice: with its simulated GNSS (the scenario benchmarks' defaults,
`scenarios.refine_with_quality`), and without any GNSS from a location hint 40 m from the
true block centre (mean camera centre) in a random direction (seeded per block), no heading,
radius 100 m (`refine(..., location=hint)`, align.locate). Per block: the camera-centre RMS
against the simulated truth of both, the no-GNSS verdict (a search that fails, ambiguous or
finding nothing, is "failed" too), the search's best and runner-up scores, and the seconds of
the model-only registration against those of the whole refine with GNSS, and the frames
the neighbouring-frame check (`refine --sequence`, precision.sequence) reports as jumping in
the no-GNSS result (the simulated images are video frames named in capture order).

A run succeeds when it ends within max(0.30 m, 1.3 x the GNSS refine's error) of the truth;
every other run should end "failed"; a run "ok" or "weak" beyond 1 m is a wrong result.

Blocks: the robustness blocks (workspaces/robust_{drive,orbit,strip,short}.toml, Berlin
3910_5819 / 3920_5820 and the procedural street), the demo street
(colmap_citymodel/simulate/demo.toml) with 5 scene seeds, and a UAV loop on three other real
tiles of tests/data (Munich tum2twin, Rotterdam, The Hague). Workspaces are built once under
workspaces/generated/ (git-ignored).

    .venv/bin/python benchmarks/bench_no_gnss.py [--cases drive orbit ...] [--results DIR]

writes benchmarks/results/no_gnss.md and no_gnss.json (or DIR's).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scenarios import GENERATED, RESULTS, ROOT, build_from_toml, build_robust_workspace, \
    centre_errors, code_version, inputs, model_variant, refine_with_quality, \
    truth_centres  # noqa: E402

HINT_DISTANCE, RADIUS = 40.0, 100.0
GOOD_ABSOLUTE, GOOD_RELATIVE, WRONG = 0.30, 1.3, 1.0
DEMO_SEEDS = (1, 2, 3, 4, 5)
DATA = ROOT / "tests" / "data"
#: UAV loops around the buildings of real tiles (the simulator's "sideways" flight).
TILES = {
    "munich": {"source": str(DATA / "citygml" / "tum2twin")},
    "rotterdam": {"source": str(DATA / "cityjson" / "rotterdam_subset.json"),
                  "crs": "EPSG:7415"},
    "hague": {"source": str(DATA / "cityjson" / "DH_01_subs.city.json"), "crs": "EPSG:7415"},
}
CASES = (["drive", "orbit", "strip", "short"] + [f"demo{s}" for s in DEMO_SEEDS]
         + list(TILES))


def tile_toml(name: str, scene: dict) -> str:
    lines = [f'name = "no_gnss_{name}"', "seed = 5", "", "[scene]"]
    lines += [f"{k} = {json.dumps(v)}" for k, v in scene.items()]
    lines += ["", "[flight]", 'mode = "sideways"', "num_key_frames = 50", "spacing = 2.0",
              "facade_distance = 12.0", "flight_height = 20.0", "pitch_deg = 30.0", "",
              "[observations]", "points_per_m2 = 1.5", "max_distance = 60.0", "",
              "[checkpoints]", "count = 15", "", "[gnss]", "sigma = [3.0, 3.0, 5.0]",
              "white_sigma = [2.0, 2.0, 3.0]", "bias_sigma = [0.5, 0.5, 0.75]",
              "bias_magnitude = 3.0", "", "[scenario]", 'name = "loop"', 'model = "original"',
              'gnss = "all"']
    return "\n".join(lines) + "\n"


def workspace_of(case: str) -> Path:
    if case in ("drive", "orbit", "strip", "short"):
        return build_robust_workspace(case)[0]
    out = GENERATED / "no_gnss"
    out.mkdir(parents=True, exist_ok=True)
    if case.startswith("demo"):
        seed = int(case[4:])
        return build_from_toml(ROOT / "colmap_citymodel" / "simulate" / "demo.toml",
                               out / f"demo-seed{seed}", seed=seed)[0]
    toml = out / f"{case}.toml"
    toml.write_text(tile_toml(case, TILES[case]))
    return build_from_toml(toml, out / case)[0]


def hint_of(case: str, truth: dict) -> np.ndarray:
    centre = np.mean(np.array(list(truth.values())), axis=0)[:2]
    angle = np.random.default_rng(zlib.crc32(case.encode())).uniform(0.0, 2 * np.pi)
    return centre + HINT_DISTANCE * np.array([np.cos(angle), np.sin(angle)])


def without_gnss(workspace: Path, hint: np.ndarray) -> dict:
    from colmap_citymodel.align.locate import ModelOnlyFailure
    from colmap_citymodel.errors import CityModelError, GeoregistrationError
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.precision.sequence import sequence_check
    from colmap_citymodel.workflow import refine

    rec, store, _ = inputs(workspace)
    options = RefineOptions.preset(
        "detailed" if model_variant(workspace) == "detailed" else "generalised")
    options.precision.covariances = "off"
    dtm = sorted((workspace / "dtm").glob("*.tif"))  # as refine_with_quality: the scenario's DTM
    if dtm:
        options.terrain.files = tuple(str(p) for p in dtm)
    start = time.perf_counter()
    out: dict = {"hint": hint.tolist()}
    try:
        result = refine(rec, store, None, options, location=hint, location_radius=RADIUS,
                        progress=False)
    except ModelOnlyFailure as error:  # ambiguous, or planes that cannot hold the block
        out.update(verdict="failed", failure=error.message, georegistration=error.report)
    except GeoregistrationError as error:
        out.update(verdict="failed", failure="not found: " + error.message)
    except CityModelError as error:  # e.g. planes that cannot fix the datum without GNSS
        out.update(verdict="failed", failure=f"{type(error).__name__}: {error.message}")
    else:
        out.update(verdict=result.quality.verdict, reasons=list(result.quality.reasons),
                   georegistration=result.georegistration,
                   cameras=centre_errors(result.reconstruction, store.origin,
                                         truth_centres(workspace)),
                   sequence_jumps=sequence_check(result.reconstruction)["jumps"],
                   placement_ratio=((result.quality.metrics or {}).get("placement")
                                    or {}).get("ratio"))
    out["seconds"] = time.perf_counter() - start
    return out


def run_case(case: str) -> dict:
    workspace = workspace_of(case)
    truth = truth_centres(workspace)
    gnss = refine_with_quality(workspace, assignment=None)
    row = {"case": case, "workspace": str(workspace.relative_to(ROOT)),
           "num_images": len(truth), "gnss_verdict": gnss["verdict"],
           "gnss_seconds": gnss["seconds"],
           "gnss_cameras": centre_errors(gnss["refined"], gnss["origin"], truth)
           if gnss["refined"] is not None else None}
    row["no_gnss"] = without_gnss(workspace, hint_of(case, truth))
    row["outcome"] = outcome(row)
    row["code"] = code_version()
    return row


def outcome(row: dict) -> str:
    """"registered" (within the target), "failed" (said so), "missed" (not failed, off the
    target but within 1 m) or "wrong" (ok/weak beyond 1 m)."""
    run = row["no_gnss"]
    if run["verdict"] == "failed":
        return "failed"
    error = run["cameras"]["rms_3d"]
    gnss_error = (row["gnss_cameras"] or {}).get("rms_3d", 0.0)
    if error <= max(GOOD_ABSOLUTE, GOOD_RELATIVE * gnss_error):
        return "registered"
    return "wrong" if error > WRONG else "missed"


def _f(value, fmt="{:.3f}") -> str:
    return "-" if value is None else fmt.format(value)


def write_results(rows: list[dict], command: str, results: Path = RESULTS) -> None:
    (results / "no_gnss.json").write_text(json.dumps(rows, indent=1, default=float))
    lines = ["# Georegistration without GNSS", "", "Produced by", "", f"    {command}", "",
             f"Code measured: {', '.join(sorted({r['code'] for r in rows}))}. Hint "
             f"{HINT_DISTANCE:g} m from the true block centre in a random direction, radius "
             f"{RADIUS:g} m, no heading. Error: camera-centre RMS 3D (m) against the simulated "
             "truth. Target: within max(0.30 m, 1.3 x the GNSS refine's error); otherwise "
             "\"failed\". best, runner-up, ratio: the search's scores; placement ratio: the "
             "verdict's ambiguity test (best over the best distinct placement, on the model's "
             "faces); jumps: frames the sequence check reports. reg s: the model-only "
             "search; refine s: the whole refine with GNSS.",
             "", "| block | images | GNSS refine error | verdict | no-GNSS error | verdict | "
             "best | runner-up | ratio | placement ratio | jumps | hint distance | reg s | "
             "refine s (GNSS) | outcome |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        run, geo = r["no_gnss"], r["no_gnss"].get("georegistration") or {}
        lines.append(
            f"| {r['case']} | {r['num_images']} | "
            f"{_f((r['gnss_cameras'] or {}).get('rms_3d'))} | {r['gnss_verdict']} | "
            f"{_f((run.get('cameras') or {}).get('rms_3d'))} | {run['verdict']} | "
            f"{_f(geo.get('best_score'), '{:.2f}')} | {_f(geo.get('runner_up_score'), '{:.2f}')} | "
            f"{_f(geo.get('score_ratio'), '{:.2f}')} | "
            f"{_f(run.get('placement_ratio'), '{:.2f}')} | "
            f"{_f(None if 'sequence_jumps' not in run else len(run['sequence_jumps']), '{}')} | "
            f"{_f(geo.get('hint_distance_m'), '{:.1f}')} | "
            f"{_f(geo.get('seconds'), '{:.1f}')} | {r['gnss_seconds']:.1f} | {r['outcome']} |")
    counts = {k: sum(r["outcome"] == k for r in rows)
              for k in ("registered", "failed", "missed", "wrong")}
    lines += ["", f"Outcomes of {len(rows)} blocks: " + ", ".join(
        f"{k} {v}" for k, v in counts.items()) + "."]
    failures = [f"- {r['case']}: {r['no_gnss']['failure']}" for r in rows
                if r["no_gnss"].get("failure")]
    if failures:
        lines += ["", "Searches that failed:", ""] + failures
    (results / "no_gnss.md").write_text("\n".join(lines) + "\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=CASES, choices=CASES)
    parser.add_argument("--results", type=Path, default=RESULTS,
                        help="folder for no_gnss.md/.json (default benchmarks/results)")
    args = parser.parse_args()
    logging.getLogger("colmap_citymodel").setLevel(logging.WARNING)
    # Rows accumulate in no_gnss.json: `--cases` reruns some of them.
    command = ".venv/bin/python benchmarks/bench_no_gnss.py [--cases CASE ...]"
    args.results.mkdir(parents=True, exist_ok=True)
    path = args.results / "no_gnss.json"
    previous = {r["case"]: r for r in json.loads(path.read_text())} if path.exists() else {}
    for case in args.cases:
        print(f"{case}: ...", flush=True)
        row = run_case(case)
        previous[case] = row
        run = row["no_gnss"]
        print(f"{case}: GNSS {_f((row['gnss_cameras'] or {}).get('rms_3d'))} m, no GNSS "
              f"{_f((run.get('cameras') or {}).get('rms_3d'))} m {run['verdict']} "
              f"({row['outcome']}), {run['seconds']:.0f} s vs {row['gnss_seconds']:.0f} s",
              flush=True)
        write_results([previous[c] for c in CASES if c in previous], command, args.results)


if __name__ == "__main__":
    main()
