"""Held-out generalisation benchmark: refine on blocks drawn at random, none of them tuned on.

At least 200 simulated blocks (`generalisation_blocks.draw_blocks`, seeded): seven geometry
families (a forward-looking and a side-looking vehicle drive, a UAV orbit round one building
and round a group of buildings, a nadir mapping grid, an oblique ring 60-120 m out, a short
hand-held video) on every real tile of tests/data (Berlin x 2, NRW, Munich, Tokyo PLATEAU
reprojected to EPSG:6677, Delft 3DBAG, The Hague, Rotterdam; CityGML and CityJSON) and the
procedural street; the given model "detailed", "corrected", "original" or "harsh" (larger face
errors), the true scene with parapets, overhangs, roof furniture, balconies, trees and cars,
sometimes a building missing from the model or a box in it that the true scene lacks; GNSS
white, with a constant bias, with a slowly varying bias, with outliers and a step, RTK-grade,
or none (a location hint 10-50 m off instead); about 18 % wrong models (shifted 10-40 m,
turned 3-20 deg, or the neighbouring street) that still overlap the block; half the blocks
with a DTM. Each block's split, "dev" (tune on it) or "held_out" (report only), is a hash of
its simulation seed.

Each block is built by the simulator (workspaces/generated/generalisation/<name>, git-ignored;
built once, reused by later runs) and refined as a user would: the CLI in a subprocess,
`<python> -m colmap_citymodel refine --input_path sparse/0 --citymodel given_model.gml
--database database.db --output_path ... [--terrain dtm/*.tif] [--location X Y]` with refine's
defaults, plus the check points (evaluated at the end, never used). Read back: the exit code,
report.json (verdict, reasons, observability sigma and source per E, N, U) and the written
model, whose camera centres are compared with the truth. The GNSS-only block is this
checkout's GNSS-only adjustment (benchmarks/scenarios.py `gnss_only_block`: a similarity to
GNSS, then the bundle adjustment with GNSS priors) of the same workspace.

    .venv/bin/python benchmarks/bench_generalisation.py [--split dev|held_out|all] [--quick]
        [--blocks N] [--seed S] [--jobs N] [--names NAME ...] [--code DIR] [--python PATH]
        [--precision auto|on|off] [--results DIR] [--tables_only] [--rerun]

writes generalisation.md and generalisation.json in --results (default benchmarks/results)
after every block. A block already measured there with the same code version and the same
description is skipped (an interrupted run resumes); `--rerun` or `--names` measure again.
`--code DIR` measures the refine of another checkout (its .venv/bin/python unless --python
names one) on the same blocks, built by this checkout's simulator; give it its own --results.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import generalisation_blocks as blocks_mod  # noqa: E402
from generalisation_blocks import ROOT, SPLITS, draw_blocks  # noqa: E402
from generalisation_summary import summarise, write_markdown  # noqa: E402
from scenarios import toml_value  # noqa: E402

GENERATED = ROOT / "workspaces" / "generated" / "generalisation"
RESULTS = ROOT / "benchmarks" / "results"
DEFAULT_BLOCKS, QUICK_PER_SPLIT = 200, 10
AXES = ("E", "N", "U")
#: A refine that runs longer than this (s) is stopped and recorded as "timeout".
REFINE_TIMEOUT = 1800
#: A true building counts as seen when this many true tie points lie on it.
MIN_POINTS_SEEN = 20
#: Metres around a footprint within which a tie point lies on the building (walls, balconies).
SEEN_BUFFER = 1.0
#: Check points per block (evaluated by refine at the end, never control).
CHECKPOINTS = 15


# ----------------------------------------------------------------------------------------------
# the block's scenario file and workspace

def scenario_table(block: dict) -> dict:
    """The simulator's [scenario] table: model level, GNSS, DTM, wrong datum."""
    table = {"name": block["family"], "model": "original" if block["model"] == "harsh"
             else block["model"], "gnss": "none" if block["gnss_model"] == "none" else "all",
             "dtm": bool(block["terrain"])}
    wrong = block.get("wrong") or {}
    for key in ("model_shift", "model_turn_deg", "model_turn_centre"):
        if key in wrong:
            table[key] = wrong[key]
    return table


def scenario_toml(block: dict) -> str:
    """The block's simulator scenario file (colmap_citymodel.simulate.scenario)."""
    tables = dict(block["toml"])
    scene = dict(tables["scene"])
    if scene["source"] != "procedural":
        scene["source"] = str(ROOT / scene["source"])
    tables.update(scene=scene, checkpoints={"count": CHECKPOINTS},
                  mapping={"num_threads": 1}, scenario=scenario_table(block))
    lines = [f"name = {json.dumps(block['name'])}", f"seed = {block['sim_seed']}"]
    for table, values in tables.items():
        lines += ["", f"[{table}]"]
        lines += [f"{key} = {toml_value(value)}" for key, value in values.items()
                  if value is not None and not isinstance(value, dict)]
        for key, value in values.items():
            if isinstance(value, dict):
                lines += ["", f"[{table}.{key}]"]
                lines += [f"{k} = {toml_value(v)}" for k, v in value.items()]
    return "\n".join(lines) + "\n"


def block_hash(block: dict) -> str:
    """A hash of everything that defines the block and how refine is run on it."""
    return hashlib.sha256(json.dumps(block, sort_keys=True).encode()).hexdigest()[:12]


def build(block: dict) -> tuple[Path, dict, float]:
    """The block's workspace (built once; rebuilt when its scenario file changed), its
    simulation.json and the CPU seconds its build took (recorded in build_cpu.txt)."""
    import dataclasses

    from colmap_citymodel.simulate import sequence as simulate
    from colmap_citymodel.simulate.scenario import load_scenario, sequence_key

    GENERATED.mkdir(parents=True, exist_ok=True)
    toml = GENERATED / f"{block['name']}.toml"
    toml.write_text(scenario_toml(block))
    options = load_scenario(toml)
    out = GENERATED / block["name"]
    stats = out / "simulation.json"
    made = json.loads(stats.read_text()) if stats.exists() else {}
    scenario = json.loads(json.dumps(dataclasses.asdict(options.scenario)))
    if not ((out / "sparse" / "0").is_dir() and made.get("sequence_key") == sequence_key(options)
            and made.get("scenario") == scenario and (out / "build_cpu.txt").exists()):
        cpu = time.process_time()  # all threads of this process: the simulator and COLMAP
        simulate.main(toml, out, overwrite=out.exists(), progress=False)
        (out / "build_cpu.txt").write_text(f"{time.process_time() - cpu:.2f}\n")
    return out, json.loads(stats.read_text()), float((out / "build_cpu.txt").read_text())


# ----------------------------------------------------------------------------------------------
# running refine as a user would

def truth_of(workspace: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The truth's origin and the true camera centres (model CRS) by image name."""
    import pycolmap

    lines = [line for line in (workspace / "truth" / "origin.txt").read_text().splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    origin = np.array([float(v) for v in lines[0].split()[:3]])
    truth = pycolmap.Reconstruction(str(workspace / "truth"))
    return origin, {im.name: im.projection_center() + origin for im in truth.images.values()}


def location_hint(block: dict, centres: dict[str, np.ndarray]) -> list[float]:
    """The block's location hint (model CRS): its distance and direction from the true block
    centre (the mean camera centre) as drawn."""
    centre = np.mean(np.array(list(centres.values())), axis=0)[:2]
    a = math.radians(block["hint"]["angle_deg"])
    return (centre + block["hint"]["distance_m"] * np.array([math.cos(a), math.sin(a)])).tolist()


def refine_command(block: dict, workspace: Path, out: Path, python: str, hint,
                   precision: str) -> list[str]:
    cmd = [python, "-m", "colmap_citymodel", "refine", "--input_path",
           str(workspace / "sparse" / "0"), "--citymodel", str(workspace / "given_model.gml"),
           "--output_path", str(out), "--no_progress",
           "--checkpoints", str(workspace / "checkpoints.txt"),
           "--checkpoint_observations", str(workspace / "checkpoint_observations.txt")]
    if block["gnss_model"] != "none":
        cmd += ["--database", str(workspace / "database.db")]
    else:
        cmd += ["--location", f"{hint[0]:.3f}", f"{hint[1]:.3f}"]
    if block["terrain"]:
        cmd += ["--terrain", *[str(p) for p in sorted((workspace / "dtm").glob("*.tif"))]]
    if precision != "auto":
        cmd += ["--precision", precision]
    return cmd


def run_refine(cmd: list[str], code_dir: Path, out: Path) -> dict:
    """The CLI in a subprocess in `code_dir`: exit code, seconds, the end of its output."""
    if out.exists():
        shutil.rmtree(out)
    start, cpu = time.perf_counter(), _children_cpu()
    try:
        done = subprocess.run(cmd, cwd=code_dir, capture_output=True, text=True,
                              timeout=REFINE_TIMEOUT)
    except subprocess.TimeoutExpired:
        return {"exit": None, "seconds": time.perf_counter() - start, "timeout": True}
    tail = (done.stdout + done.stderr).strip().splitlines()[-12:]
    return {"exit": done.returncode, "seconds": time.perf_counter() - start,
            "cpu_seconds": _children_cpu() - cpu, "log_tail": tail}


def _children_cpu() -> float:
    """CPU seconds (user + system) of this process's finished children."""
    import resource

    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


# ----------------------------------------------------------------------------------------------
# measuring

def centre_errors(rec, truth: dict[str, np.ndarray], origin: np.ndarray) -> dict | None:
    """RMS per axis and 3D of (estimated - true) camera centres of `rec` (model CRS; origin
    subtracted from both before differencing) over its registered images."""
    names = [im.name for im in rec.images.values() if im.has_pose and im.name in truth]
    if not names:
        return None
    by_name = {im.name: im for im in rec.images.values()}
    d = np.array([by_name[n].projection_center() - origin for n in names]) - np.array(
        [truth[n] - origin for n in names])
    rms = np.sqrt(np.mean(d ** 2, axis=0))
    return {"error": rms.tolist(), "error_3d": float(np.sqrt(np.sum(rms ** 2))),
            "mean_error": d.mean(axis=0).tolist(), "images": len(names)}


def gnss_only_errors(workspace: Path, truth: dict, origin: np.ndarray) -> dict | None:
    """The GNSS-only block's camera-centre errors (scenarios.gnss_only_block), cached in the
    workspace per code version of this checkout."""
    from scenarios import code_version, gnss_only_block

    cache = workspace / "gnss_only.json"
    code = code_version()
    saved = json.loads(cache.read_text()) if cache.exists() else {}
    if saved.get("code") != code:
        rec, store = gnss_only_block(workspace)
        rec.transform(_translation(store.origin))
        saved = {"code": code, "errors": centre_errors(rec, truth, origin)}
        cache.write_text(json.dumps(saved))
    return saved["errors"]


def _translation(offset: np.ndarray):
    import pycolmap

    return pycolmap.Sim3d(np.c_[np.eye(3), np.asarray(offset, dtype=np.float64)])


def buildings_seen(workspace: Path, origin: np.ndarray) -> int:
    """True buildings with at least MIN_POINTS_SEEN true tie points on them (within
    SEEN_BUFFER m of the footprint, above its feet)."""
    import pycolmap
    import shapely

    from colmap_citymodel.citymodel.read import read_city_model
    from colmap_citymodel.simulate.scene import building_footprints

    path = workspace / "truth" / "true_model.gml"
    store = read_city_model(path if path.exists() else workspace / "models" / "corrected.gml")
    points = np.array([p.xyz for p in pycolmap.Reconstruction(
        str(workspace / "truth")).points3D.values()]) + origin - store.origin
    feet = {}
    for face in store.faces:
        z = store.vertices[face.exterior][:, 2].min()
        feet[face.building_id] = min(z, feet.get(face.building_id, np.inf))
    seen = 0
    for bid, footprint in building_footprints(store).items():
        inside = shapely.contains_xy(footprint.buffer(SEEN_BUFFER), points[:, 0], points[:, 1])
        seen += int(np.sum(inside & (points[:, 2] > feet[bid] + 0.5)) >= MIN_POINTS_SEEN)
    return seen


def read_report(out: Path) -> dict:
    """What report.json says: verdict, reasons, sigma and source per axis, and a few figures
    that help to read a failure."""
    path = out / "report.json"
    if not path.exists():
        return {}
    report = json.loads(path.read_text())
    quality = report.get("quality") or {}
    obs = report.get("observability") or {}
    sigma = [(obs.get(a) or {}).get("sigma") for a in AXES]
    sigma = [float(s) if s is not None else None for s in sigma]
    row = {"verdict": quality.get("verdict", "n/a"), "reasons": quality.get("reasons", []),
           "result": report.get("result"), "sigma": sigma,
           "source": [(obs.get(a) or {}).get("source", "-") for a in AXES],
           "sigma_3d": (float(np.sqrt(np.sum(np.square(sigma))))
                        if all(s is not None for s in sigma) else None)}
    coarse = (report.get("coarse_alignment") or {}).get("translation") or {}
    row["coarse_shift_m"] = coarse.get("shift_m")
    geo = report.get("georegistration") or {}
    if geo.get("method") == "model only" or "score_ratio" in geo:
        row["location"] = {k: geo.get(k) for k in ("best_score", "runner_up_score",
                                                   "score_ratio", "hint_distance_m")}
    cps = report.get("checkpoints") or {}
    if isinstance(cps, dict) and cps.get("rms_3d") is not None:
        row["checkpoints_rms_3d"] = cps["rms_3d"]
    row["stopped_by"] = report.get("stopped_by")
    return row


def measure(block: dict, workspace: Path, out: Path, ran: dict) -> dict:
    """The row of a refined block: verdict, errors of the written model, stated sigmas, z."""
    import pycolmap

    origin, truth = truth_of(workspace)
    row = read_report(out)
    if ran.get("timeout"):
        row["verdict"] = "timeout"
    elif ran["exit"] == 2:  # refine refused its input with a message
        row["verdict"] = "refused"
        row["failure"] = next((line for line in reversed(ran.get("log_tail") or [])
                               if line.startswith("error:")), None)
    elif ran["exit"] not in (0, 3):
        row["verdict"] = "error"
    elif not row:
        row["verdict"] = "failed" if ran["exit"] == 3 else "error"
    written = (out / "images.bin").exists() or (out / "images.txt").exists()
    errors = centre_errors(pycolmap.Reconstruction(str(out)), truth, origin) if written else None
    row.update(errors or {"error": None, "error_3d": None, "images": 0})
    sigma = row.get("sigma") or [None] * 3
    row["z"] = [e / s if errors and s else None for e, s in zip(row["error"] or [None] * 3,
                                                               sigma)]
    row["true_images"] = len(truth)
    if block["gnss_model"] != "none":
        try:
            gnss = gnss_only_errors(workspace, truth, origin)
        except Exception as error:  # noqa: BLE001  (GNSS alone may not place the block)
            gnss = None
            row["gnss_only_failure"] = f"{type(error).__name__}: {error}"
        row["gnss_only_error_3d"] = gnss["error_3d"] if gnss else None
        row["gnss_only_error"] = gnss["error"] if gnss else None
    row["buildings_seen"] = buildings_seen(workspace, origin)
    return row


# ----------------------------------------------------------------------------------------------
# one block: build, refine, measure (in a worker process)

KEPT = ("name", "split", "family", "city", "tile", "format", "gnss_model", "model",
        "wrong_model", "wrong", "terrain", "hint", "sim_seed")


def run_block(block: dict, code_dir: str, python: str, code: str, precision: str) -> dict:
    """Build, refine and measure one block; a failure of any step is recorded, not raised."""
    import colmap_citymodel  # noqa: F401  (sets up the package logger, quietened here)

    logging.getLogger("colmap_citymodel").setLevel(logging.ERROR)
    row = {k: block[k] for k in KEPT}
    row.update(code=code, block_hash=block_hash(block), exit=None)
    start = time.perf_counter()
    try:
        workspace, sim, build_cpu = build(block)
    except Exception as error:  # noqa: BLE001  (a block the simulator cannot build is a result)
        row.update(verdict="not built", failure=f"{type(error).__name__}: {error}",
                   build_seconds=time.perf_counter() - start)
        return row
    row["build_seconds"] = time.perf_counter() - start
    row["build_cpu_seconds"] = build_cpu
    row["simulation"] = {k: sim.get(k) for k in ("num_key_frames", "num_registered_images",
                                                 "num_models", "num_tie_points",
                                                 "model_buildings", "gnss_gross_errors")}
    hint = None
    if block["gnss_model"] == "none":
        hint = location_hint(block, truth_of(workspace)[1])
        row["hint_xy"] = hint
    out = workspace / f"refine-{code.split()[0]}"
    cmd = refine_command(block, workspace, out, python, hint, precision)
    ran = run_refine(cmd, Path(code_dir), out)
    row.update(exit=ran["exit"], seconds=ran["seconds"], cpu_seconds=ran.get("cpu_seconds"),
               command=" ".join(cmd[1:]))
    try:
        row.update(measure(block, workspace, out, ran))
    except Exception as error:  # noqa: BLE001  (an unreadable output is a result too)
        row.update(verdict="error", failure=f"measuring: {type(error).__name__}: {error}")
    if row["verdict"] in ("error", "timeout", "refused"):
        row["log_tail"] = ran.get("log_tail")
    return row


# ----------------------------------------------------------------------------------------------
# the run: selection, resume, pool, results after every block

def code_version_of(code_dir: Path) -> str:
    """The last commit of the checkout whose refine runs that changed its package or its
    extension (commits of benchmarks, tests or docs leave the version), "+ uncommitted
    changes" when those sources differ from it."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(code_dir), *args], capture_output=True,
                              text=True, check=True).stdout.strip()

    try:
        commit = git("log", "-1", "--format=%h", "--", "colmap_citymodel", "cpp_ext")
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", "colmap_citymodel",
                    "cpp_ext")
    except (OSError, subprocess.CalledProcessError):
        return f"checkout at {code_dir} (not a git checkout)"
    return commit + (" + uncommitted changes" if dirty else "")


def select(args) -> list[dict]:
    """The blocks of this run, in drawing order (dev first)."""
    count = args.blocks or (2 * QUICK_PER_SPLIT if args.quick else DEFAULT_BLOCKS)
    drawn = draw_blocks(count, args.seed)
    if args.names:
        unknown = set(args.names) - {b["name"] for b in drawn}
        if unknown:
            sys.exit(f"unknown block names (drawn with --seed {args.seed} --blocks {count}): "
                     f"{', '.join(sorted(unknown))}")
        return [b for b in drawn if b["name"] in set(args.names)]
    splits = SPLITS if args.split == "all" else (args.split,)
    return [b for b in drawn if b["split"] in splits]


def load_rows(path: Path) -> dict[str, dict]:
    return {r["name"]: r for r in json.loads(path.read_text())["blocks"]} if path.exists() \
        else {}


def write_results(rows: dict[str, dict], results: Path, command: str, seed: int) -> dict:
    """generalisation.json and .md in `results` (written atomically); returns the summary."""
    ordered = sorted(rows.values(), key=lambda r: (SPLITS.index(r["split"]), r["name"]))
    summary = {s: summarise([r for r in ordered if r["split"] == s]) for s in SPLITS
               if any(r["split"] == s for r in ordered)}
    content = {"blocks": ordered, "summary": summary, "command": command, "seed": seed,
               "codes": sorted({r["code"] for r in ordered}),
               "skipped_combinations": blocks_mod.skipped_combinations()}
    results.mkdir(parents=True, exist_ok=True)
    tmp = results / f".generalisation.json.{os.getpid()}"
    tmp.write_text(json.dumps(content, indent=1, default=float))
    os.replace(tmp, results / "generalisation.json")
    write_markdown(content, results / "generalisation.md")
    return summary


def progress_line(row: dict, done: int, total: int) -> str:
    error = row.get("error_3d")
    gnss = row.get("gnss_only_error_3d")
    return (f"[{done}/{total}] {row['name']}: {row['verdict']} (exit {row['exit']}), error 3D "
            f"{'-' if error is None else f'{error:.3f}'} m, GNSS-only "
            f"{'-' if gnss is None else f'{gnss:.3f}'} m, build "
            f"{row.get('build_seconds', 0):.0f} s, refine {row.get('seconds') or 0:.0f} s"
            + (f" ({row['failure']})" if row.get("failure") else ""))


def run(args, command: str) -> None:
    code_dir = Path(args.code).resolve()
    python = args.python or str(code_dir / ".venv" / "bin" / "python")
    code = code_version_of(code_dir)
    path = args.results / "generalisation.json"
    rows = load_rows(path)
    todo = [b for b in select(args) if args.rerun or args.names
            or rows.get(b["name"], {}).get("code") != code
            or rows.get(b["name"], {}).get("block_hash") != block_hash(b)]
    print(f"{len(todo)} block(s) to measure with {python} (code {code}), {args.jobs} job(s)",
          flush=True)
    with ProcessPoolExecutor(max_workers=args.jobs, mp_context=get_context("spawn")) as pool:
        futures = [pool.submit(run_block, b, str(code_dir), python, code, args.precision)
                   for b in todo]
        for done, future in enumerate(as_completed(futures), 1):
            row = future.result()
            rows[row["name"]] = row
            print(progress_line(row, done, len(todo)), flush=True)
            write_results(rows, args.results, command, args.seed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--split", default="dev", choices=["dev", "held_out", "all"],
                        help="which blocks (default dev; held_out only to report)")
    parser.add_argument("--quick", action="store_true",
                        help=f"the first {QUICK_PER_SPLIT} blocks of each split")
    parser.add_argument("--blocks", type=int, default=None,
                        help=f"blocks drawn, half per split (default {DEFAULT_BLOCKS})")
    parser.add_argument("--seed", type=int, default=1, help="draws the blocks (default 1)")
    parser.add_argument("--jobs", type=int, default=2, help="blocks at once (default 2)")
    parser.add_argument("--names", nargs="+", default=None, help="measure these blocks again")
    parser.add_argument("--rerun", action="store_true",
                        help="measure again blocks already measured with this code")
    parser.add_argument("--code", default=str(ROOT),
                        help="checkout whose refine is measured (default this one)")
    parser.add_argument("--python", default=None,
                        help="its Python (default CODE/.venv/bin/python)")
    parser.add_argument("--precision", default="auto", choices=["auto", "on", "off"],
                        help="refine's --precision (default auto: refine's own default)")
    parser.add_argument("--results", type=Path, default=RESULTS,
                        help="folder of generalisation.md/.json (default benchmarks/results)")
    parser.add_argument("--tables_only", action="store_true",
                        help="only rewrite the tables from generalisation.json")
    args = parser.parse_args()
    path = args.results / "generalisation.json"
    if args.tables_only:
        if not path.exists():
            sys.exit(f"{path}: not found (run the benchmark first)")
        saved = json.loads(path.read_text())
        write_results(load_rows(path), args.results, saved["command"], saved["seed"])
        return
    import colmap_citymodel  # noqa: F401  (sets up the package logger, quietened here)

    logging.getLogger("colmap_citymodel").setLevel(logging.WARNING)
    command = " ".join([".venv/bin/python benchmarks/bench_generalisation.py", *sys.argv[1:]])
    run(args, command)
    summary = json.loads(path.read_text())["summary"] if path.exists() else {}
    from generalisation_summary import summary_lines

    for split, s in summary.items():
        print(f"\n{split}:\n" + "\n".join(summary_lines(s)))


if __name__ == "__main__":
    main()
