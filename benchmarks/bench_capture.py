"""Refine against GNSS bias: how far from the truth does a block end, and does the verdict know?

Two blocks: the demo street (colmap_citymodel/simulate/demo.toml, a UAV along a procedural street) and the
vehicle drive (workspaces/robust_drive.toml, a forward-looking camera at 2 m along one side of a
Berlin street). Each is simulated and mapped by COLMAP once (workspaces/generated/capture/demo,
workspaces/generated/robust/drive, the robustness benchmark's); every
run then gives refine the same block with a fresh GNSS realisation: the true projection centres
plus white noise 3/3/5 m plus a constant bias of 1, 2, 4, 8 or 12 m in a direction drawn from the
run's seed (simulate.simulate_gnss with GNSSOptions.bias_magnitude; stated sigma 3/3/5 m). The
seed draws both the white noise and the direction, so the levels of one seed share a direction.

Per run: camera-centre RMS (estimated - simulated truth) per axis and 3D of refine's result (its
default options, as a user runs it) and of
the GNSS-only adjustment of the same block, and refine's verdict. Summary per block and bias:
the share of runs whose result ends within 0.25 m (RMS 3D) of the truth, and the number of runs
that end further away with the verdict "ok" (a wrong result refine vouches for; must be 0).

Where the given model lets a block end: per block, refine with the true projection centres
as GNSS (no noise, no bias, stated sigma 3/3/5 m) on the given model and on the model's true
surfaces (the workspace's `corrected` model). Started there, refine ends at the optimum its
model offers near the truth: biased runs that land about as far off as that run land where the
model puts the block, not where the GNSS bias left it. Beside it the chance that a block ends
within the tolerance by refine's own stated position sigmas (E, N, U of the run started at the
truth): how often a block with a model of this quality lands within it over the model's error
realisations, where the benchmark draws only one.

Writes benchmarks/results/capture.md and the `capture` section of
benchmarks/results/scenarios.json (runs keyed block/bias/seed, the runs started at the truth
keyed block/model under `at_truth`; a run with --cases or --quick replaces only its own runs).

The drive's runs share one realisation of the given model's errors, and where refine can land
is that realisation's (the run started at the truth). `--realisations 1 3` adds the same runs on
the drive simulated at other seeds (`drive-seed1`, ...: other plane errors of the given model,
other SfM and DTM noise; the workspaces `benchmarks/model_floor.py --seeds` uses): how often
capture lands within the tolerance where the model lets a block land there, and where not.
A bias far beyond the GNSS's stated sigma (16 m against 3 m) looks exactly like a model whose
georeference is that far off; refine then refuses the move ("failed"). `--gnss_bias auto` runs
the same as refine --gnss_bias auto, a user's statement that the GNSS may carry such a bias.

    .venv/bin/python benchmarks/bench_capture.py [--quick] [--cases demo drive]
        [--levels 1 2 4 8 12] [--seeds 5] [--realisations N ...] [--gnss_bias auto]
        [--at_truth_only] [--tables_only]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from scenarios import (  # noqa: E402  (the benchmarks directory is not a package)
    GENERATED,
    RESULTS,
    TRUTH_TOLERANCE,
    build_from_toml,
    build_robust_workspace,
    centre_errors,
    code_version,
    inputs,
    refine_with_quality,
    truth_centres,
    update_json,
)

CASES = {"demo": "colmap_citymodel/simulate/demo.toml", "drive": "workspaces/robust_drive.toml"}
LEVELS = (1.0, 2.0, 4.0, 8.0, 12.0)
NUM_SEEDS = 5
QUICK_LEVELS = (2.0, 8.0)
QUICK_SEEDS = 2
WHITE_SIGMA = (3.0, 3.0, 5.0)
STATED_SIGMA = (3.0, 3.0, 5.0)


def build_block(case: str) -> tuple[Path, dict]:
    """The block's workspace: the robustness workspace of the same toml when there is one
    (workspaces/generated/robust/, "drive-seed3": the drive simulated at seed 3), else
    workspaces/generated/capture/<case>."""
    if "-seed" in case:
        name, seed = case.split("-seed")
        return build_robust_workspace(name, seed=int(seed))
    toml = Path(CASES[case])
    if toml.name.startswith("robust_"):
        return build_robust_workspace(toml.name.removeprefix("robust_").removesuffix(".toml"))
    return build_from_toml(ROOT / toml, GENERATED / "capture" / case)


def biased_gnss(gnss, truth: dict, level: float, seed: int):
    """`gnss` (the workspace's observations, model CRS) with positions redrawn: truth + white
    noise + a constant bias of `level` metres (simulate.simulate_gnss)."""
    from colmap_citymodel.simulate.flight import Flight
    from colmap_citymodel.simulate.scenario import GNSSOptions
    from colmap_citymodel.simulate.observations import simulate_gnss

    names = [n for n in gnss.image_names if n in truth]
    centres = np.array([truth[n] for n in names])
    origin = np.floor(centres.min(axis=0))  # keeps the noise arithmetic in small numbers
    local = centres - origin
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(local, axis=0), axis=1))]
    rotations = np.repeat(np.eye(3)[None], len(names), axis=0)
    flight = Flight(names, local, rotations, arc, 1, 1, 1.0)
    options = GNSSOptions(sigma=STATED_SIGMA, white_sigma=WHITE_SIGMA, bias_sigma=(0.0, 0.0, 0.0),
                          bias_magnitude=level)
    positions = simulate_gnss(flight, options, seed) + origin
    return dataclasses.replace(gnss, image_names=names, positions=positions,
                               sigmas=np.tile(np.asarray(STATED_SIGMA), (len(names), 1)))


def run_one(workspace: Path, truth: dict, gnss_db, level: float, seed: int,
            gnss_bias: str | None = None) -> dict:
    run = refine_with_quality(workspace, biased_gnss(gnss_db, truth, level, seed),
                              gnss_bias=gnss_bias)
    r = {"bias_m": level, "seed": seed, "verdict": run["verdict"], "reasons": run["reasons"],
         "quality_metrics": run["quality_metrics"], "seconds": run["seconds"],
         "refine": None if run["refined"] is None else centre_errors(run["refined"],
                                                                     run["origin"], truth),
         "gnss_only": centre_errors(run["gnss_only"], run["gnss_only_origin"], truth)}
    final = r["refine"] if r["refine"] is not None else r["gnss_only"]
    r["final_rms_3d"] = final.get("rms_3d", float("inf"))
    r["within_tolerance"] = bool(r["final_rms_3d"] <= TRUTH_TOLERANCE)
    return r


#: Samples of the Monte Carlo chance of a 3D error within the tolerance from three axis sigmas.
CHANCE_SAMPLES = 200_000


def chance_within(sigmas, tolerance: float = TRUTH_TOLERANCE) -> float:
    """P(|e| <= tolerance) for e ~ N(0, diag(sigmas^2)) (a generalised chi-square; Monte Carlo,
    fixed seed): the share of blocks that end within the tolerance when their error is what the
    stated sigmas say."""
    draws = np.random.default_rng(0).standard_normal((CHANCE_SAMPLES, 3)) * np.asarray(sigmas)
    return float(np.mean(np.sum(draws ** 2, axis=1) <= tolerance ** 2))


def run_at_truth(workspace: Path, truth: dict, gnss_db, model: str | None) -> dict:
    """Refine with the true projection centres as GNSS (no noise, no bias, stated sigma
    STATED_SIGMA) on the given model (`model` None) or another variant of it."""
    names = [n for n in gnss_db.image_names if n in truth]
    gnss = dataclasses.replace(gnss_db, image_names=names,
                               positions=np.array([truth[n] for n in names]),
                               sigmas=np.tile(np.asarray(STATED_SIGMA), (len(names), 1)))
    run = refine_with_quality(workspace, gnss, model=model)
    sigmas = (run["quality_metrics"] or {}).get("position_sigmas_m")
    return {"model": model or "given", "verdict": run["verdict"], "seconds": run["seconds"],
            "refine": None if run["refined"] is None
            else centre_errors(run["refined"], run["origin"], truth),
            "stated_sigmas_m": sigmas,
            "chance_within": None if sigmas is None else chance_within(sigmas)}


def summarise(runs: dict) -> dict:
    out: dict = {}
    for r in runs.values():
        s = out.setdefault(r["case"], {}).setdefault(f"{r['bias_m']:g}", {
            "runs": 0, "within": 0, "wrong_ok": 0, "verdicts": {}, "refine_rms_3d": [],
            "gnss_only_rms_3d": []})
        s["runs"] += 1
        s["within"] += r["within_tolerance"]
        s["wrong_ok"] += (not r["within_tolerance"]) and r["verdict"] == "ok"
        s["verdicts"][r["verdict"]] = s["verdicts"].get(r["verdict"], 0) + 1
        s["refine_rms_3d"].append(r["final_rms_3d"])
        s["gnss_only_rms_3d"].append(r["gnss_only"].get("rms_3d", float("nan")))
    for levels in out.values():
        for s in levels.values():
            s["share_within"] = s["within"] / s["runs"]
            for key in ("refine_rms_3d", "gnss_only_rms_3d"):
                s[f"median_{key}"] = float(np.median(s.pop(key)))
    return out


#: The bias range of the per-block summary (m): the biases up to this length.
BLOCK_SUMMARY_MAX_BIAS = 16.0


def block_lines(section: dict) -> list[str]:
    """capture.md's summary per block over its runs with biases up to BLOCK_SUMMARY_MAX_BIAS:
    the share within the tolerance, the runs refine refused ("failed", the GNSS-only block
    handed back), and where the block ends started at the truth (the floor its model's
    realisation sets)."""
    blocks: dict[str, list[dict]] = {}
    for r in section["runs"].values():
        if r["bias_m"] <= BLOCK_SUMMARY_MAX_BIAS:
            blocks.setdefault(r["case"], []).append(r)
    lines = ["## Per block", "",
             f"Runs with biases up to {BLOCK_SUMMARY_MAX_BIAS:g} m; `refused`: verdict "
             "\"failed\" (the GNSS-only block handed back); `at the truth`: the block's run "
             "started at the truth with its given model (below), where its model lets it land.",
             "", f"| block | runs | within {TRUTH_TOLERANCE} m | refused | within, of the runs "
             "not refused | > tolerance with verdict ok | at the truth (m) |",
             "|---|---|---|---|---|---|---|"]
    at_truth = section.get("at_truth") or {}
    for case in sorted(blocks):
        runs = blocks[case]
        within = sum(r["within_tolerance"] for r in runs)
        refused = sum(r["verdict"] == "failed" for r in runs)
        kept = [r for r in runs if r["verdict"] != "failed"]
        wrong = sum((not r["within_tolerance"]) and r["verdict"] == "ok" for r in runs)
        truth = (at_truth.get(f"{case.split(',')[0]}/given") or {}).get("refine") or {}
        lines.append(
            f"| {case} | {len(runs)} | {within} ({within / len(runs):.0%}) | {refused} | "
            f"{sum(r['within_tolerance'] for r in kept)} of {len(kept)} | {wrong} | "
            + (f"{truth['rms_3d']:.3f}" if "rms_3d" in truth else "-") + " |")
    return lines + [""]


def tables(section: dict) -> str:
    lines = block_lines(section) + ["## Summary", "",
             f"| block | bias (m) | runs | share within {TRUTH_TOLERANCE} m "
             f"| > {TRUTH_TOLERANCE} m with verdict ok | verdicts | median RMS 3D refine "
             "| median RMS 3D GNSS only |",
             "|---|---|---|---|---|---|---|---|"]
    for case, levels in section["summary"].items():
        for level in sorted(levels, key=float):
            s = levels[level]
            verdicts = ", ".join(f"{k} {v}" for k, v in sorted(s["verdicts"].items()))
            lines.append(f"| {case} | {level} | {s['runs']} | {s['share_within']:.0%} | "
                         f"{s['wrong_ok']} | {verdicts} | {s['median_refine_rms_3d']:.3f} | "
                         f"{s['median_gnss_only_rms_3d']:.3f} |")
    if section.get("at_truth"):
        lines += at_truth_table(section["at_truth"])
    total_wrong_ok = sum(s["wrong_ok"] for levels in section["summary"].values()
                         for s in levels.values())
    lines += ["", f"Runs further than {TRUTH_TOLERANCE} m from the truth with verdict ok: "
              f"**{total_wrong_ok}** (must be 0).", "", "## Runs", "",
              "| block | bias (m) | seed | refine RMS X | Y | Z | 3D "
              "| GNSS only RMS X | Y | Z | 3D | verdict | s |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def axes(m):
        if not m or "rms_3d" not in m:
            return "- | - | - | -"
        return " | ".join(f"{m[k]:.3f}" for k in ("rms_x", "rms_y", "rms_z", "rms_3d"))

    for key in sorted(section["runs"], key=lambda k: (k.split("/")[0], float(k.split("/")[1]),
                                                      int(k.split("/")[2]))):
        r = section["runs"][key]
        lines.append(f"| {r['case']} | {r['bias_m']:g} | {r['seed']} | {axes(r['refine'])} | "
                     f"{axes(r['gnss_only'])} | {r['verdict']} | {r['seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def at_truth_table(at_truth: dict) -> list[str]:
    lines = ["", "## Started at the truth", "",
             "GNSS = the true projection centres (no noise, no bias, stated sigma 3/3/5 m). "
             "`given`: the block's given model; `corrected`: the model's true surfaces. Stated "
             "sigmas: refine's own position sigmas E, N, U of that run; chance within: the "
             f"share of blocks within {TRUTH_TOLERANCE} m 3D when their error is what those "
             "sigmas say (over the model's error realisations; the runs above share one).", "",
             "| block | model | RMS E | N | U | 3D | verdict | stated sigmas E, N, U | "
             f"chance within {TRUTH_TOLERANCE} m |",
             "|---|---|---|---|---|---|---|---|---|"]
    for key in sorted(at_truth):
        r = at_truth[key]
        m = r["refine"] or {}
        errors = (" | ".join(f"{m[k]:.3f}" for k in ("rms_x", "rms_y", "rms_z", "rms_3d"))
                  if "rms_3d" in m else "- | - | - | -")
        sigmas = (", ".join(f"{v:.3f}" for v in r["stated_sigmas_m"])
                  if r.get("stated_sigmas_m") else "-")
        chance = f"{r['chance_within']:.0%}" if r.get("chance_within") is not None else "-"
        lines.append(f"| {key.split('/')[0]} | {r['model']} | {errors} | {r['verdict']} | "
                     f"{sigmas} | {chance} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", nargs="*", default=list(CASES), choices=list(CASES),
                        help="blocks (none with --realisations: only those)")
    parser.add_argument("--levels", nargs="+", type=float, default=None,
                        help=f"bias magnitudes in metres (default {LEVELS})")
    parser.add_argument("--seeds", type=int, default=None,
                        help=f"seeds per block and bias (default {NUM_SEEDS})")
    parser.add_argument("--quick", action="store_true",
                        help=f"biases {QUICK_LEVELS} m and {QUICK_SEEDS} seeds")
    parser.add_argument("--at_truth_only", action="store_true",
                        help="only the runs started at the truth (no GNSS bias runs)")
    parser.add_argument("--realisations", nargs="+", type=int, default=[],
                        help="also the drive simulated at these seeds (other realisations of "
                             "the given model's errors)")
    parser.add_argument("--gnss_bias", choices=["auto"], default=None,
                        help="the runs as refine --gnss_bias auto (the GNSS's constant bias "
                             "estimated where the planes fix the position), kept apart as "
                             "block \"<block>, --gnss_bias auto\"; no runs at the truth")
    parser.add_argument("--tables_only", action="store_true",
                        help="only rewrite capture.md from results/scenarios.json")
    args = parser.parse_args()
    levels = args.levels or (QUICK_LEVELS if args.quick else LEVELS)
    seeds = range(1, 1 + (args.seeds or (QUICK_SEEDS if args.quick else NUM_SEEDS)))
    import colmap_citymodel  # noqa: F401  (sets up the package logger first)

    logging.getLogger("colmap_citymodel").setLevel(logging.WARNING)
    RESULTS.mkdir(parents=True, exist_ok=True)
    json_path = RESULTS / "scenarios.json"
    command = " ".join(["    .venv/bin/python benchmarks/bench_capture.py", *sys.argv[1:]])
    cases = args.cases + [f"drive-seed{n}" for n in args.realisations]
    for case in [] if args.tables_only else cases:
        start = time.perf_counter()
        workspace, sim = build_block(case)
        print(f"{case}: workspace ready in {time.perf_counter() - start:.0f} s "
              f"({sim.get('num_registered_images')}/{sim['num_key_frames']} images registered)",
              flush=True)
        truth = truth_centres(workspace)
        _, _, gnss_db = inputs(workspace)
        label = case if args.gnss_bias is None else f"{case}, --gnss_bias {args.gnss_bias}"
        for model in () if args.gnss_bias else (None, "corrected"):
            r = run_at_truth(workspace, truth, gnss_db, model)
            r["code"] = code_version()
            print(f"  started at the truth, {r['model']} model: refine "
                  f"{(r['refine'] or {}).get('rms_3d', float('nan')):.3f} m, verdict "
                  f"{r['verdict']}", flush=True)
            update_json(json_path, ["capture", "at_truth", f"{case}/{r['model']}"], r)
        for level in [] if args.at_truth_only else levels:
            for seed in seeds:
                r = run_one(workspace, truth, gnss_db, float(level), seed, args.gnss_bias)
                r["case"] = label
                r["code"] = code_version()
                print(f"  bias {level:g} m seed {seed}: refine "
                      f"{r['final_rms_3d']:.3f} m, GNSS only "
                      f"{r['gnss_only'].get('rms_3d', float('nan')):.3f} m, verdict "
                      f"{r['verdict']} ({r['seconds']:.0f} s)", flush=True)
                # only this run's entry, then the summary of all: other benchmarks write their
                # own sections of the file meanwhile
                runs = update_json(json_path, ["capture", "runs", f"{label}/{level:g}/{seed}"],
                                   r)["capture"]["runs"]
                update_json(json_path, ["capture", "summary"], summarise(runs))
                update_json(json_path, ["capture", "settings"], {
                    "command": command, "white_sigma": WHITE_SIGMA, "stated_sigma": STATED_SIGMA,
                    "tolerance_m": TRUTH_TOLERANCE,
                    "blocks": dict(CASES)})
    everything = json.loads(json_path.read_text()) if json_path.exists() else {}
    section = everything.get("capture")
    if not section:
        print("no capture results yet")
        return
    text = tables(section)
    (RESULTS / "capture.md").write_text(
        "# Refine against GNSS bias (capture)\n\nProduced by (the last run; runs accumulate "
        "in scenarios.json, section `capture`)\n\n"
        + section.get("settings", {}).get("command", "    .venv/bin/python "
                                          "benchmarks/bench_capture.py") + "\n\nBlocks: "
        "`demo` (colmap_citymodel/simulate/demo.toml, UAV along a procedural street, 60 images) and `drive` "
        "(workspaces/robust_drive.toml, forward-looking vehicle camera, 40 images); "
        "`drive-seedN`: the same drive simulated at seed N (another realisation of the given "
        "model's plane errors, of the SfM and the DTM noise); `<block>, --gnss_bias auto`: the "
        "same runs with refine's `--gnss_bias auto` (the GNSS's constant bias estimated). "
        "Each mapped "
        "by COLMAP once. Per run: GNSS = truth + white noise 3/3/5 m + a constant bias of the "
        "given length in a direction drawn from the seed (stated sigma 3/3/5 m). RMS: camera "
        "centres, estimated - simulated truth (m). refine: refine's result with its default "
        "options (on verdict "
        "\"failed\" the GNSS-only block it returns); GNSS only: the GNSS-only adjustment of the "
        "same block. Within: result RMS 3D <= "
        f"{TRUTH_TOLERANCE} m. Code measured: "
        + ", ".join(sorted({r.get("code", "not recorded") for r in section["runs"].values()}))
        + ".\n\n" + text)
    print(text)


if __name__ == "__main__":
    main()
