"""Batch throughput: 12 simulated workspaces against a tiled Berlin model, on 1 and 2 workers of
the local process pool and on a Dask LocalCluster of 2 workers.

City model (benchmarks/cache/batch/tiles/, built once): the real Berlin LoD2 tile 3910_5819
(CityGML 2.0, EPSG:25833, dl-de/by-2.0; tests/data/citygml/berlin) split into 250 m columns
(each building whole in the column of its centroid: `3910_5819_x<easting>.gml`), so that blocks
lie on tile borders, plus the tiles 3920_5820 and the two Moabit files as they are: 7 tiles,
of which a workspace reads the ones within workflow.GNSS_READ_MARGIN (250 m) of its GNSS.

Workspaces (benchmarks/cache/batch/workspaces/, built once by the simulator and mapped by
COLMAP; scenario files in benchmarks/cache/batch/scenarios/): UAV loops along the facades
(sideways, 30 key frames) and orbits (36-40 key frames) over parts of 3910_5819 and
3920_5820, three of them across a column border; GNSS with stated sigma 3/3/5 m, white noise
2/2/3 m and a constant bias of 3 m. The batch refines each from its database's pose priors.

A round runs the whole batch from scratch with each engine in turn (1 worker, 2 workers, Dask
LocalCluster of 2; each refine on the cores over the workers as threads, the batch's default;
`--engines ... 1t` adds one worker held to one thread) into benchmarks/cache/batch/runs/ (the
wall time of batch.run.main, pool or cluster start included); the tile index is cached before the first run. Speedups are taken
within a round, whose runs follow each other under similar load. The machine is shared: the
tables give the load average and the CPU time the batch got (its processes' user + system
seconds over the wall time = the cores it had on average).

    .venv/bin/python benchmarks/bench_batch.py [--repeat N] [--engines 1 2 dask2 1t]
        [--build-only] [--report-only] [--fresh] [--cache DIR]

Adds its rounds to benchmarks/results/batch.json and writes benchmarks/results/batch.md from
all recorded rounds.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import shutil
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BERLIN = ROOT / "tests" / "data" / "citygml" / "berlin"
CACHE = ROOT / "benchmarks" / "cache" / "batch"
TILES, WORKSPACES, SCENARIOS, RUNS = (CACHE / d for d in ("tiles", "workspaces", "scenarios",
                                                          "runs"))


def use_cache(directory: Path) -> None:
    """Build and run in `directory` instead of benchmarks/cache/batch."""
    global CACHE, TILES, WORKSPACES, SCENARIOS, RUNS
    CACHE = Path(directory).resolve()
    TILES, WORKSPACES, SCENARIOS, RUNS = (CACHE / d for d in ("tiles", "workspaces",
                                                              "scenarios", "runs"))
RESULT = ROOT / "benchmarks" / "results" / "batch.md"
RUNS_JSON = RESULT.with_suffix(".json")
COLUMN = 250.0  # m, width of the columns 3910_5819 is split into

SOURCE_WEST = BERLIN / "3910_5819.gml"
SOURCE_NORTH = BERLIN / "3920_5820.gml"

#: Loops between tall buildings and narrow courts: higher, further from the facades, denser.
HIGHER = {"flight_height": 20.0, "facade_distance": 12.0, "distance_amplitude": 1.0,
          "spacing": 1.6, "observations": {"points_per_m2": 2.0}}
#: name -> (source, cut [x0, y0, x1, y1] EPSG:25833, flight). Loops follow the footprints of
#: the cut from the point nearest `start`; orbits circle `centre` (world coordinates here,
#: local in the scenario file).
SITES = {
    "west_row": (SOURCE_WEST, [390990, 5818950, 391160, 5819060],
                 {"mode": "sideways", "start": [391000, 5818990]}),
    "west_border": (SOURCE_WEST, [391170, 5818950, 391290, 5819060],
                    {"mode": "sideways", "start": [391180, 5818990]}),
    "mid_cluster": (SOURCE_WEST, [391410, 5818990, 391500, 5819080],
                    {"mode": "sideways", "start": [391420, 5818995]}),
    "mid_orbit": (SOURCE_WEST, [391400, 5818980, 391560, 5819100],
                  {"mode": "orbit", "centre": [391478, 5819045], "radius": 45.0}),
    "court_west": (SOURCE_WEST, [391520, 5818960, 391640, 5819100],
                   {"mode": "sideways", "start": [391525, 5818975], **HIGHER}),
    "court_north": (SOURCE_WEST, [391600, 5819040, 391700, 5819110],
                    {"mode": "sideways", "start": [391640, 5819110], **HIGHER}),
    "court_border": (SOURCE_WEST, [391690, 5818990, 391820, 5819100],
                     {"mode": "sideways", "start": [391700, 5819000]}),
    "east_cluster": (SOURCE_WEST, [391820, 5818990, 391900, 5819100],
                     {"mode": "sideways", "start": [391825, 5818995]}),
    "east_border": (SOURCE_WEST, [391900, 5819010, 392010, 5819140],
                    {"mode": "sideways", "start": [391990, 5819020], **HIGHER}),
    "east_orbit": (SOURCE_WEST, [391860, 5819020, 391990, 5819140],
                   {"mode": "orbit", "centre": [391925, 5819080], "radius": 60.0,
                    "num_key_frames": 40, "flight_height": 40.0, "pitch_deg": 45.0,
                    "observations": {"points_per_m2": 2.0}}),
    "north_corner": (SOURCE_NORTH, [392180, 5820040, 392330, 5820140],
                     {"mode": "orbit", "centre": [392261, 5820085], "radius": 40.0}),
    "north_court": (SOURCE_NORTH, [392020, 5820180, 392130, 5820300],
                    {"mode": "orbit", "centre": [392072, 5820245], "radius": 50.0,
                     "num_key_frames": 40, "observations": {"points_per_m2": 2.0}}),
}
#: engine -> (figure, workers, scheduler, threads per refine: None = the batch's default,
#: the cores over the workers). "1t" is one worker held to one thread: the refines one after
#: the other as single-threaded code, what two workers can at best halve.
ENGINES = {"1": ("seconds_1_worker", 1, None, None), "2": ("seconds_2_workers", 2, None, None),
           "dask2": ("seconds_dask_2_workers", 2, "local", None),
           "1t": ("seconds_1_worker_1_thread", 1, None, 1)}


# -- inputs -----------------------------------------------------------------------------------

def build_tiles() -> Path:
    """3910_5819 in 250 m columns, plus the other Berlin tiles as they are."""
    from colmap_citymodel.citymodel.raw_model import RawCityModel
    from colmap_citymodel.citymodel.read_citygml import read_citygml
    from colmap_citymodel.citymodel.write_citygml import write_citygml

    if TILES.is_dir() and any(TILES.glob("*.gml")):
        return TILES
    tmp = TILES.with_name(".tiles.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    raw = read_citygml(SOURCE_WEST)
    polygons = list(raw.polygon_table())
    centre: dict[str, list] = {}
    for p in polygons:
        centre.setdefault(p.building_id, []).append(p.exterior)
    column = {b: int(np.floor(np.vstack(r)[:, 0].mean() / COLUMN) * COLUMN)
              for b, r in centre.items()}
    for x in sorted(set(column.values())):
        part = [p for p in polygons if column[p.building_id] == x]
        ids = sorted({p.building_id for p in part})
        write_citygml(tmp / f"3910_5819_x{x}.gml", RawCityModel(
            source=str(SOURCE_WEST), format="CityGML", version="2.0", crs=raw.crs,
            polygons=part, building_ids=ids, part_ids=sorted({p.part_id for p in part
                                                              if p.part_id})))
    for name in ("3920_5820.gml", "Berlin_Moabit_1Bldg_v2.gml", "Berlin_Moabit_1Bldg_v3.gml"):
        shutil.copy(BERLIN / name, tmp / name)
    os.replace(tmp, TILES)
    return TILES


def _toml(value) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return repr(float(value)) if isinstance(value, float) else str(value)


def scenario_text(name: str, seed: int) -> str:
    """The simulator's scenario file of one site (local coordinates from the cut's origin)."""
    from colmap_citymodel.citymodel.read import read_city_model

    source, cut, flight = SITES[name]
    origin = read_city_model(source, bbox_crs=np.array(cut, float).reshape(2, 2)).origin[:2]
    lines = [f"# bench_batch site {name}", f'name = "batch_{name}"', f"seed = {seed}", "",
             "[scene]", f'source = "{source}"', f"bbox_crs = {list(map(float, cut))}", "",
             "[flight]"]
    flight = dict(flight)
    mode = flight.pop("mode")
    observations = flight.pop("observations", {})
    if mode == "orbit":
        values = {"mode": "orbit", "orbit_centre": (np.asarray(flight.pop("centre"), float)
                                                    - origin).round(1).tolist(),
                  "orbit_radius": flight.pop("radius"), "num_key_frames": 36,
                  "flight_height": 30.0, "height_amplitude": 1.0, "pitch_deg": 40.0}
    else:
        values = {"mode": "sideways", "start_xy": (np.asarray(flight.pop("start"), float)
                                                   - origin).round(1).tolist(),
                  "num_key_frames": 30, "spacing": 2.0, "flight_height": 14.0,
                  "pitch_deg": 25.0}
    values.update(flight)
    lines += [f"{k} = {_toml(v)}" for k, v in values.items()]
    observations = {"points_per_m2": 1.0, "max_distance": 60.0, **observations}
    lines += ["", "[observations]"] + [f"{k} = {_toml(v)}" for k, v in observations.items()]
    lines += ["", "[checkpoints]", "count = 10", "", "[gnss]", "sigma = [3.0, 3.0, 5.0]",
              "white_sigma = [2.0, 2.0, 3.0]", "bias_sigma = [0.0, 0.0, 0.0]",
              "bias_magnitude = 3.0", "", "[scenario]", f'name = "{name}"',
              'model = "corrected"', 'gnss = "all"', ""]
    return "\n".join(lines)


def build_workspaces() -> None:
    """The 12 workspaces (built once)."""
    from colmap_citymodel.simulate import sequence as simulate

    SCENARIOS.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(SITES):
        out = WORKSPACES / name
        if not (out / "sparse" / "0").is_dir():
            toml = SCENARIOS / f"{name}.toml"
            toml.write_text(scenario_text(name, 100 + k))
            started = time.perf_counter()
            simulate.main(toml, out, overwrite=out.exists(), progress=False)
            print(f"built {name} in {time.perf_counter() - started:.0f} s", flush=True)


def workspace_sizes() -> dict[str, tuple[int, int]]:
    """{name: (key frames, registered images of sparse/0)}."""
    import pycolmap

    sizes = {}
    for name in SITES:
        rec = pycolmap.Reconstruction(str(WORKSPACES / name / "sparse" / "0"))
        frames = len([ln for ln in (WORKSPACES / name / "gnss_all.txt").read_text().splitlines()
                      if ln.strip() and not ln.startswith("#")])
        sizes[name] = (frames, rec.num_reg_images())
    return sizes


# -- runs -------------------------------------------------------------------------------------

def _spin(n: int) -> int:
    """A CPU-bound chunk of pure Python (the control)."""
    total = 0
    for k in range(n):
        total += k * k % 7
    return total


def control_speedup(chunks: int = 12, n: int = 4_000_000) -> dict:
    """What the machine gives two processes right now: the same 12 CPU-bound chunks on a
    spawned pool of 1 and of 2 (pool start excluded); its speedup is the ceiling any batch
    could reach under the current load."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    seconds = {}
    for workers in (1, 2):
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            list(pool.map(_spin, [1000] * workers))  # started and warm
            started = time.perf_counter()
            list(pool.map(_spin, [n] * chunks))
            seconds[workers] = time.perf_counter() - started
    print(f"control: 1 process {seconds[1]:.1f} s, 2 processes {seconds[2]:.1f} s, "
          f"speedup {seconds[1] / seconds[2]:.2f}", flush=True)
    return {"control_1": seconds[1], "control_2": seconds[2]}


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run(engine: str, label: str, round_id: str) -> dict:
    from colmap_citymodel.batch.run import main as batch_main

    key, workers, scheduler, threads = ENGINES[engine]
    out = RUNS / label
    shutil.rmtree(out, ignore_errors=True)
    load_before = os.getloadavg()[0]
    cpu_before = children_cpu()
    started = time.perf_counter()
    rows = batch_main(WORKSPACES, TILES, out, workers=workers, threads=threads,
                      scheduler=scheduler, progress=False)
    seconds = time.perf_counter() - started
    cpu = children_cpu() - cpu_before
    load_after = os.getloadavg()[0]
    print(f"{key} = {seconds:.1f}  (load {load_before:.1f} -> {load_after:.1f}, "
          f"batch CPU {cpu:.0f} s = {cpu / seconds:.2f} cores)", flush=True)
    return {"round": round_id, "engine": engine, "key": key, "seconds": seconds, "cpu": cpu,
            "load_before": load_before, "load_after": load_after,
            "started": time.strftime("%Y-%m-%d %H:%M", time.localtime(time.time() - seconds)),
            "rows": rows}


def round_figures(runs: list[dict]) -> dict:
    """The figures of one round (the engines run one after the other, under similar load)."""
    s = {r["engine"]: r["seconds"] for r in runs}
    figures = {ENGINES[e][0]: v for e, v in s.items()}
    if "1" in s and "2" in s:
        figures["speedup_2_workers"] = s["1"] / s["2"]
    if "1" in s and "dask2" in s:
        figures["speedup_dask_2_workers"] = s["1"] / s["dask2"]
    if "2" in s and "dask2" in s:
        figures["dask_overhead_vs_pool"] = s["dask2"] / s["2"] - 1.0
    if "1t" in s and "1" in s:
        figures["threads_speedup_1_worker"] = s["1t"] / s["1"]
    if "1t" in s and "2" in s:
        figures["speedup_2_workers_over_1_thread"] = s["1t"] / s["2"]
    control = [r for r in runs if "control_1" in r]
    if control:
        figures["control_speedup_2_processes"] = (control[0]["control_1"]
                                                  / control[0]["control_2"])
        if "speedup_2_workers" in figures:
            figures["speedup_2_workers_of_control"] = (figures["speedup_2_workers"]
                                                       / figures["control_speedup_2_processes"])
    return figures


def _autogroup() -> str:
    try:
        return Path("/proc/sys/kernel/sched_autogroup_enabled").read_text().strip()
    except OSError:
        return "unknown"


def report(runs: list[dict], sizes: dict) -> tuple[str, dict]:
    """batch.md from all recorded runs: per round and the median over the rounds."""
    rounds: dict[str, list[dict]] = {}
    for r in runs:
        rounds.setdefault(r["round"], []).append(r)
    per_round = {k: round_figures(v) for k, v in rounds.items()}
    keys = [k for k in ("seconds_1_worker", "seconds_2_workers", "seconds_dask_2_workers",
                        "seconds_1_worker_1_thread", "speedup_2_workers",
                        "speedup_dask_2_workers", "dask_overhead_vs_pool",
                        "control_speedup_2_processes", "speedup_2_workers_of_control",
                        "threads_speedup_1_worker", "speedup_2_workers_over_1_thread")
            if any(k in f for f in per_round.values())]
    figures = {k: statistics.median(f[k] for f in per_round.values() if k in f) for k in keys}
    n_tiles = len(list(TILES.glob("*.gml")))
    images = sorted(n for n, _ in sizes.values())
    registered = sorted(n for _, n in sizes.values())
    fmt = (lambda k, v: f"{v:.1f}" if k.startswith("seconds") else
           f"{100 * v:+.1f} %" if k == "dask_overhead_vs_pool" else f"{v:.2f}")
    lines = ["# Batch: 12 workspaces, process pool and Dask", "",
             "Produced by (each invocation adds its rounds to `batch.json`)", "",
             "    .venv/bin/python benchmarks/bench_batch.py [--repeat N]", "",
             f"Inputs: Berlin 3910_5819 in 250 m columns plus 3920_5820 and the two Moabit "
             f"files ({n_tiles} tiles); 12 simulated UAV blocks ({images[0]}-{images[-1]} key "
             f"frames, {registered[0]}-{registered[-1]} registered by COLMAP), three of them "
             "(west_border, mid_orbit, court_border) on a column border; refine's defaults; "
             "see the docstring of `benchmarks/bench_batch.py`. Each engine refines all 12 "
             "from scratch (wall time of the whole batch, pool or cluster start included).", "",
             f"Machine: {os.cpu_count()} cores, shared with other sessions. `load` is the "
             "1-minute load average before -> after a run; `cores` the CPU seconds of the "
             "batch's processes over its wall time, i.e. the cores it actually got. From "
             "round 5 on, each round starts with a control: 12 CPU-bound chunks of pure "
             "Python on a spawned pool of 1 and of 2 processes; its speedup "
             "(`control_speedup_2_processes`) is what the machine gave a second process at "
             "that time, and `speedup_2_workers_of_control` the batch's speedup as a share of "
             "it. The kernel shares the CPU between sessions, not processes "
             "(`/proc/sys/kernel/sched_autogroup_enabled` = "
             f"{_autogroup()}): while other sessions keep the cores busy, the processes of "
             "one session share that session's part, so a second worker gets nothing the "
             "first does not lose.", "",
             "Threads: up to round 6 one worker refined with the libraries' default threads "
             "and two workers with one thread each, except Open3D's pool (two threads in "
             "each worker). From round 7 on each refine runs on the cores over the workers "
             "(one worker: 2 threads, two workers: 1 each, Open3D included), the largest "
             "workspaces start first, and the LocalCluster's workers run without Dask's "
             "profiler and with glibc's default memory trimming. `1_worker_1_thread` (round "
             "7 on) is one worker held to one thread: `threads_speedup_1_worker` is what the "
             "threads of one refine gain, and `speedup_2_workers_over_1_thread` what two "
             "workers gain over refines run one after the other single-threaded; on 2 free "
             "cores `speedup_2_workers` can at best reach 2 / `threads_speedup_1_worker`. "
             "Round 7 ran on the workspaces built again from the same scenarios in a "
             "directory of its own (`--cache`); their figures differ from round 6's in the "
             "third digit.",
             "",
             "| figure | median over rounds | " + " | ".join(per_round) + " |",
             "|---|---|" + "---|" * len(per_round)]
    for key in keys:
        lines.append(f"| {key} | {fmt(key, figures[key])} | " + " | ".join(
            fmt(key, f[key]) if key in f else "" for f in per_round.values()) + " |")
    lines += ["", "Runs:", "",
              "| round | started | engine | seconds | load | batch CPU s | cores |",
              "|---|---|---|---|---|---|---|"]
    for r in runs:
        lines.append(f"| {r['round']} | {r.get('started', '')} | "
                     f"{r['key'].removeprefix('seconds_')} | {r['seconds']:.1f} | "
                     f"{r['load_before']:.1f} -> {r['load_after']:.1f} | {r['cpu']:.0f} | "
                     f"{r['cpu'] / r['seconds']:.2f} |")
    last = next(r for r in reversed(runs) if r.get("rows"))
    rows = {row["workspace"]: row for row in last["rows"]}
    lines += ["", f"Workspaces (summary of the last run, round {last['round']} "
              f"{last['key'].removeprefix('seconds_')}; seconds: the task's wall time):", "",
              "| workspace | key frames | registered | tiles read | verdict | s0 GNSS-only | "
              "s0 | near model GNSS-only | near model | shift (m) | seconds | error |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    from colmap_citymodel.batch.summary import cell

    for name in SITES:
        row = rows.get(name, {})
        frames, registered = sizes[name]
        tiles = ", ".join(t.removeprefix("3910_5819_").removesuffix(".gml")
                          for t in row.get("tile_files", []))
        lines.append("| " + " | ".join([
            name, str(frames), str(registered), tiles, cell(row, "verdict"),
            cell(row, "s0_gnss_only"), cell(row, "s0"), cell(row, "near_model_gnss_only"),
            cell(row, "near_model"), cell(row, "shift_m"), cell(row, "seconds"),
            cell(row, "error")]) + " |")
    lines += ["", "Tiles read: `x<easting>` = the 3910_5819 column starting at that easting. "
              "near model: tie points within 0.5 m of the model; shift: mean camera shift of "
              "the refined block from the GNSS-only adjustment.", ""]
    return "\n".join(lines), figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeat", type=int, default=1, help="rounds (each runs every engine)")
    parser.add_argument("--engines", nargs="+", default=["1", "2", "dask2"],
                        choices=list(ENGINES))
    parser.add_argument("--build-only", action="store_true")
    parser.add_argument("--report-only", action="store_true",
                        help="rewrite batch.md from batch.json")
    parser.add_argument("--fresh", action="store_true", help="forget the recorded rounds")
    parser.add_argument("--cache", type=Path, default=CACHE,
                        help="where the tiles, workspaces and runs are built (default: "
                             "benchmarks/cache/batch)")
    args = parser.parse_args()
    use_cache(args.cache)
    from colmap_citymodel import logger

    logger.setLevel(logging.WARNING)
    build_tiles()
    build_workspaces()
    sizes = workspace_sizes()
    from colmap_citymodel.citymodel.tiles import build_tile_index

    build_tile_index(TILES)  # the index is cached next to the tiles before any timed run
    if args.build_only:
        return
    runs = [] if args.fresh or not RUNS_JSON.exists() else \
        json.loads(RUNS_JSON.read_text())["runs"]
    if not args.report_only:
        first = 1 + max((int(r["round"]) for r in runs), default=0)
        for k in range(args.repeat):
            control = control_speedup()
            for engine in args.engines:
                runs.append({**run(engine, f"{engine}_{k}", str(first + k)), **control})
                RUNS_JSON.write_text(json.dumps({"runs": runs}, indent=1))
    text, figures = report(runs, sizes)
    for key, value in figures.items():
        print(f"{key} = {value:.3f}")
    RESULT.write_text(text)
    print(f"wrote {RESULT}")


if __name__ == "__main__":
    sys.exit(main())
