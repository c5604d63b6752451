"""Calibration of refine's stated datum precision and of its quality verdict.

refine reports per block a verdict ("ok", "weak", "failed") and, per direction E, N, U, the
sigma of the block's position (report.json `observability`, with its source "planes", "gnss" or
"both"). This benchmark measures whether those sigmas cover the true errors: it draws simulated
blocks at random (reproducible for a `--seed`), builds each with the simulator
(`workspaces/generated/calibration/<name>`, git-ignored), runs refine with the defaults the
scenario benchmarks use (`scenarios.refine_with_quality`), and compares the camera-centre errors
against the simulated truth (RMS per axis and 3D) with the stated sigmas:

- z per axis = RMS camera-centre error / stated sigma, both of the block refine returns (the
  GNSS-only one after "failed", with the sigmas it states for it); 3D: error_3d against
  sigma_3d = sqrt(sigma_E^2 + sigma_N^2 + sigma_U^2); the refined block's error beside them;
- the verdict, and whether refine handed back the GNSS-only block;
- "wrong model" blocks: the model given to refine shifted horizontally by 10-40 m, which
  refine should answer with "failed" (and the GNSS-only block).

Blocks: flight geometries on real tiles (Berlin 3910_5819: a UAV strip and a vehicle drive
along its street front; Berlin 3920_5820: an orbit around its corner building; the tum2twin
Munich buildings: a UAV loop and a vehicle drive around them) and on the procedural street
(a UAV loop and a vehicle drive); the given model `detailed`, `corrected` or `original`; GNSS
with white noise of 0.3-3 m, a slowly varying bias of 0-1.5 m and a constant bias of 0-6 m in
a random direction (stated sigma 3, 3, 5 m throughout). The geometries are cycled in a seeded
random order so that any run covers them all; everything else is drawn per block.

    .venv/bin/python benchmarks/bench_calibration.py [--quick] [--seed 1] [--blocks 40]

writes benchmarks/results/calibration.md and calibration.json (`--quick`: 10 blocks). A block
whose simulation or mapping fails ("not built") or whose refine raises ("error") is recorded
as such and left out of the summary. `--tables_only` rewrites calibration.md from the json.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from colmap_citymodel.options import PrecisionOptions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from scenarios import GENERATED, RESULTS, ROOT, build_from_toml, centre_errors, code_version, \
    inputs, model_variant, toml_value, truth_centres  # noqa: E402

DATA = ROOT / "tests" / "data" / "citygml"
BERLIN_BLOCK = DATA / "berlin" / "3910_5819.gml"
BERLIN_CORNER = DATA / "berlin" / "3920_5820.gml"
MUNICH = DATA / "tum2twin"
#: The western 400 m of the Berlin block (its street front runs along local y ~ -1 .. 21).
BERLIN_BBOX = [390950.0, 5818900.0, 391350.0, 5819100.0]
MODELS = ("detailed", "corrected", "original")
AXES = ("E", "N", "U")
#: Stated GNSS sigma (m) of every block; the actual noise is drawn per block.
GNSS_SIGMA = [3.0, 3.0, 5.0]
QUICK_BLOCKS, DEFAULT_BLOCKS = 10, 40
#: Summary thresholds: z within this is "covered"; beyond the other an outlier.
Z_COVERED, Z_OUTLIER = 2.0, 3.5
#: A block this close to the truth (3D camera-centre RMS, m) deserves "ok".
GOOD_ERROR = 0.10
#: refine's default position tolerance (m).
TOLERANCE = PrecisionOptions().tolerance


# ----------------------------------------------------------------------------------------------
# block geometries: each returns (tile label, scene table, flight table, observations table)

def _street_line(rng: np.random.Generator, distance: float, frames: int, spacing: float):
    """Waypoints parallel to the Berlin block's street front, `distance` m south of it, long
    enough for `frames` key frames, starting at a random point along the street."""
    slope = 21.8 / 280.0
    length = frames * spacing * 1.25 + 10.0
    x0 = float(rng.uniform(-10.0, max(-10.0, 270.0 - length)))
    x1 = min(x0 + length + 20.0, 280.0)
    y = lambda x: -1.0 - distance + slope * (x + 10.0)  # noqa: E731
    return [[round(x0, 1), round(y(x0), 2)], [round(x1, 1), round(y(x1), 2)]]


def berlin_strip(rng):
    frames = int(rng.integers(35, 61))
    flight = {"mode": "sideways", "waypoints": _street_line(rng, rng.uniform(12, 22), frames, 2.0),
              "look": "left", "num_key_frames": frames, "spacing": 2.0, "spacing_jitter": 0.3,
              "distance_amplitude": 0.0, "flight_height": round(rng.uniform(15, 30), 1),
              "height_amplitude": 0.0, "pitch_deg": round(rng.uniform(25, 45), 1)}
    return ("Berlin 3910_5819", {"source": str(BERLIN_BLOCK), "bbox_crs": BERLIN_BBOX}, flight,
            {"points_per_m2": 2.0, "max_distance": 60.0})


def _drive(flight: dict, rng) -> dict:
    """A forward-looking vehicle camera 2 m above the road, turned towards the facades."""
    return {**flight, "mode": "forward", "look": "left", "spacing": 2.0, "spacing_jitter": 0.4,
            "distance_amplitude": 0.0, "flight_height": 2.0, "height_amplitude": 0.0,
            "pitch_deg": 2.0, "yaw_offset_deg": round(rng.uniform(20, 30), 1),
            "attitude_sigma_deg": [0.5, 0.3, 0.3], "image_width": 2464, "image_height": 2056,
            "focal_length": 2400.0}


def berlin_drive(rng):
    frames = int(rng.integers(30, 51))
    flight = _drive({"waypoints": _street_line(rng, rng.uniform(7, 10), frames, 2.0),
                     "num_key_frames": frames}, rng)
    return ("Berlin 3910_5819", {"source": str(BERLIN_BLOCK), "bbox_crs": BERLIN_BBOX}, flight,
            {"points_per_m2": 8.0, "max_distance": 50.0})


def berlin_orbit(rng):
    centre = [round(221.0 + rng.uniform(-3, 3), 1), round(30.0 + rng.uniform(-3, 3), 1)]
    flight = {"mode": "orbit", "orbit_centre": centre,
              "orbit_radius": round(rng.uniform(38, 50), 1),
              "num_key_frames": int(rng.integers(60, 101)),
              "flight_height": round(rng.uniform(25, 40), 1), "height_amplitude": 1.0,
              "pitch_deg": round(rng.uniform(35, 45), 1)}
    return ("Berlin 3920_5820", {"source": str(BERLIN_CORNER)}, flight,
            {"points_per_m2": 1.0, "max_distance": 75.0})


def munich_loop(rng):
    flight = {"mode": "sideways", "num_key_frames": int(rng.integers(40, 71)), "spacing": 2.0,
              "facade_distance": round(rng.uniform(10, 15), 1),
              "flight_height": round(rng.uniform(15, 25), 1),
              "pitch_deg": round(rng.uniform(20, 35), 1)}
    return ("Munich tum2twin", {"source": str(MUNICH)}, flight,
            {"points_per_m2": 1.5, "max_distance": 60.0})


def munich_drive(rng):
    flight = _drive({"num_key_frames": int(rng.integers(30, 51)),
                     "facade_distance": round(rng.uniform(8, 11), 1)}, rng)
    return ("Munich tum2twin", {"source": str(MUNICH)}, flight,
            {"points_per_m2": 8.0, "max_distance": 50.0})


def street_loop(rng):
    flight = {"num_key_frames": int(rng.integers(20, 61)), "spacing": 1.5,
              "flight_height": round(rng.uniform(12, 20), 1),
              "pitch_deg": round(rng.uniform(25, 35), 1)}
    return ("procedural street", {"source": "procedural", "procedural": {"num_buildings": 8}},
            flight, {"points_per_m2": 1.0})


def street_drive(rng):
    flight = _drive({"num_key_frames": int(rng.integers(30, 51)),
                     "facade_distance": round(rng.uniform(7, 10), 1)}, rng)
    return ("procedural street", {"source": "procedural", "procedural": {"num_buildings": 8}},
            flight, {"points_per_m2": 8.0, "max_distance": 50.0})


GEOMETRIES = {"berlin_strip": berlin_strip, "berlin_drive": berlin_drive,
              "berlin_orbit": berlin_orbit, "munich_loop": munich_loop,
              "munich_drive": munich_drive, "street_loop": street_loop,
              "street_drive": street_drive}


# ----------------------------------------------------------------------------------------------
# drawing blocks and writing their scenario files

def draw_blocks(count: int, seed: int) -> list[dict]:
    """`count` block specifications: geometries cycled in a random order, the rest drawn."""
    rng = np.random.default_rng(seed)
    names = list(GEOMETRIES)
    order = [names[i] for _ in range(math.ceil(count / len(names)))
             for i in rng.permutation(len(names))][:count]
    num_wrong = max(2, round(0.15 * count))
    wrong = set(rng.choice(count, size=num_wrong, replace=False).tolist())
    blocks = []
    for i, geometry in enumerate(order):
        tile, scene, flight, observations = GEOMETRIES[geometry](rng)
        white = float(rng.uniform(0.3, 3.0))
        drift = float(rng.uniform(0.0, 1.5))
        gnss = {"sigma": GNSS_SIGMA, "white_sigma": [round(white, 2)] * 2 + [round(1.5 * white, 2)],
                "bias_sigma": [round(drift, 2)] * 2 + [round(1.5 * drift, 2)],
                "bias_magnitude": round(float(rng.uniform(0.0, 6.0)), 2)}
        model = str(rng.choice(MODELS))
        shift = None
        if i in wrong:
            angle, size = rng.uniform(0, 2 * np.pi), rng.uniform(10.0, 40.0)
            shift = [round(size * math.cos(angle), 2), round(size * math.sin(angle), 2), 0.0]
        blocks.append({"name": f"s{seed}-{i:02d}-{geometry}", "geometry": geometry, "tile": tile,
                       "model": model, "wrong_model": shift is not None, "model_shift": shift,
                       "sim_seed": int(rng.integers(1, 1_000_000)), "gnss": gnss,
                       "toml": {"scene": scene, "flight": flight, "observations": observations}})
    return blocks


def scenario_toml(block: dict) -> str:
    """The block's simulator scenario file (colmap_citymodel.simulate.scenario)."""
    tables = {**block["toml"], "checkpoints": {"count": 15}, "gnss": block["gnss"],
              "scenario": {"name": block["geometry"], "model": block["model"], "gnss": "all"}}
    lines = [f"name = {json.dumps(block['name'])}", f"seed = {block['sim_seed']}"]
    for table, values in tables.items():
        lines += ["", f"[{table}]"]
        lines += [f"{key} = {toml_value(value)}" for key, value in values.items()]
    return "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------------------------
# one block: build, refine, measure

def refine_block(workspace: Path, shift: list[float] | None):
    """refine() with the defaults of scenarios.refine_with_quality, against the workspace's
    given model, moved by `shift` (m) when given."""
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.workflow import refine

    rec, store, gnss = inputs(workspace)
    if shift is not None:
        store = store.with_vertices(store.vertices + np.asarray(shift, dtype=np.float64))
    options = RefineOptions.preset(
        "detailed" if model_variant(workspace) == "detailed" else "generalised")
    options.precision.covariances = "off"
    return refine(rec, store, gnss, options, progress=False)


def _ratio(a: float, b: float) -> float | None:
    """a / b, None when b is not a positive finite number."""
    return float(a / b) if np.isfinite(b) and b > 0 else None


def _axes(errors: dict) -> list[float]:
    return [errors["rms_x"], errors["rms_y"], errors["rms_z"]]


#: The verdict's figures kept per block (quality.metrics), for reading the tests' margins.
METRICS = ("fit", "gnss_test", "placement", "gnss_alone", "one_plane", "position_sigma_m",
           "near_share", "near_share_gnss_only", "assigned_share", "shift_enu_m")


def measure(block: dict, workspace: Path) -> dict:
    """Refine the built block; errors, stated sigmas, z, verdict. The errors and z are those of
    the block refine returns (the GNSS-only one after "failed") against the sigmas it states
    for it; the refined block's errors beside them."""
    start = time.perf_counter()
    result = refine_block(workspace, block["model_shift"])
    seconds = time.perf_counter() - start
    truth = truth_centres(workspace)
    refined = centre_errors(result.refined, result.origin, truth)
    returned = centre_errors(result.reconstruction, result.origin, truth)
    obs = result.observability or {}
    sigma = [float(obs.get(a, {}).get("sigma") or float("nan")) for a in AXES]
    error = _axes(returned)
    metrics = result.quality.metrics if result.quality else {}
    row = {"verdict": str(result.quality.verdict) if result.quality else "n/a",
           "reasons": [str(r) for r in getattr(result.quality, "reasons", [])],
           "handed_back_gnss_only": result.handed_back == "gnss_only",
           "error_3d": returned["rms_3d"], "sigma_3d": float(np.sqrt(np.sum(np.square(sigma)))),
           "error": error, "sigma": sigma, "z": [_ratio(e, s) for e, s in zip(error, sigma)],
           "source": [obs.get(a, {}).get("source", "-") for a in AXES],
           "refined_error_3d": refined["rms_3d"], "refined_error": _axes(refined),
           "num_images": returned["num_images"], "num_true_images": returned["num_true_images"],
           "metrics": {k: metrics.get(k) for k in METRICS}, "seconds": seconds}
    if result.gnss_only is not None:
        row["gnss_only_error_3d"] = centre_errors(result.gnss_only, result.origin,
                                                  truth)["rms_3d"]
    return row


def run_block(block: dict, tmp: Path) -> dict:
    """Build and measure one block; a failure of either is recorded, not raised."""
    row = {k: block[k] for k in ("name", "geometry", "tile", "model", "wrong_model",
                                 "model_shift", "sim_seed", "gnss")}
    toml = tmp / f"{block['name']}.toml"
    toml.write_text(scenario_toml(block))
    start = time.perf_counter()
    try:
        workspace, sim = build_from_toml(toml, GENERATED / "calibration" / block["name"],
                                         seed=block["sim_seed"])
        row["num_key_frames"] = sim.get("num_key_frames")
        row["num_registered_images"] = sim.get("num_registered_images")
    except Exception as error:  # a block the simulator cannot build or map is a result too
        row.update(verdict="not built", failure=f"{type(error).__name__}: {error}")
        row["seconds"] = time.perf_counter() - start
        return row
    row["build_seconds"] = time.perf_counter() - start
    try:
        row.update(measure(block, workspace))
    except Exception as error:  # noqa: BLE001  (a refine that raises is a result too)
        row.update(verdict="error", failure=f"{type(error).__name__}: {error}",
                   seconds=time.perf_counter() - start - row["build_seconds"])
    return row


# ----------------------------------------------------------------------------------------------
# summary and output

def _rms(values) -> float | None:
    values = [v for v in values if v is not None and np.isfinite(v)]
    return float(np.sqrt(np.mean(np.square(values)))) if values else None


def summarise(rows: list[dict]) -> dict:
    measured = [r for r in rows if "z" in r]
    right = [r for r in measured if not r["wrong_model"]]
    wrong = [r for r in measured if r["wrong_model"]]
    z = [v for r in right for v in r["z"] if v is not None]
    by_source = {}
    for source in ("planes", "both", "gnss"):
        zs = [v for r in right for v, s in zip(r["z"], r["source"])
              if s == source and v is not None]
        if zs:
            by_source[source] = {"count": len(zs), "rms_z": _rms(zs),
                                 "share_z_le_2": sum(v <= Z_COVERED for v in zs) / len(zs),
                                 "max_z": float(max(zs))}
    good = [r for r in right if r.get("refined_error_3d", r["error_3d"]) <= GOOD_ERROR]
    return {
        "blocks": len(rows), "measured": len(measured), "right_model": len(right),
        "not_built_or_failed": [r["name"] for r in rows if "z" not in r],
        "rms_z": _rms(z), "share_z_le_2": sum(v <= Z_COVERED for v in z) / len(z) if z else None,
        "count_z_gt_3_5": sum(v > Z_OUTLIER for v in z), "max_z": float(max(z)) if z else None,
        "z_by_source": by_source,
        "verdicts": {v: sum(r["verdict"] == v for r in right) for v in ("ok", "weak", "failed")},
        "handed_back_gnss_only": sum(r["handed_back_gnss_only"] for r in measured),
        "wrong_model": len(wrong),
        "wrong_model_not_failed": [r["name"] for r in wrong if r["verdict"] != "failed"],
        "ok_error_over_2_sigma": [r["name"] for r in right if r["verdict"] == "ok"
                                  and r["error_3d"] > 2.0 * r["sigma_3d"]],
        "ok_sigma_over_tolerance": [r["name"] for r in right if r["verdict"] == "ok"
                                    and r["sigma_3d"] > TOLERANCE],
        "within_0_10_m": len(good),
        "within_0_10_m_ok": sum(r["verdict"] == "ok" for r in good),
        "within_0_10_m_not_ok": [r["name"] for r in good if r["verdict"] != "ok"],
        "within_0_10_m_not_ok_not_gnss_alone": [
            r["name"] for r in good if r["verdict"] != "ok"
            and not (r.get("metrics") or {}).get("gnss_alone")],
        "returned_worse_than_gnss_only": [
            r["name"] for r in measured if not r["handed_back_gnss_only"]
            and r["error_3d"] > r.get("gnss_only_error_3d", float("inf"))],
    }


def _n(value, fmt: str = "{:.3f}") -> str:
    return "-" if value is None or not np.isfinite(value) else fmt.format(value)


def _triple(values, fmt: str = "{:.2f}") -> str:
    return " / ".join(_n(v, fmt) for v in values)


def block_table(rows: list[dict]) -> list[str]:
    lines = ["| block | tile | model | GNSS white / bias (m) | verdict | error 3D | sigma 3D "
             "| error E / N / U | sigma E / N / U | z E / N / U | fixed by | GNSS-only 3D "
             "| refined 3D | images | s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        model = r["model"] + (" shifted %.0f m" % np.hypot(*r["model_shift"][:2])
                              if r["wrong_model"] else "")
        gnss = f"{r['gnss']['white_sigma'][0]:.1f} / {r['gnss']['bias_magnitude']:.1f}"
        if "z" not in r:
            lines.append(f"| {r['name']} | {r['tile']} | {model} | {gnss} | {r['verdict']}: "
                         f"{r.get('failure', '')} |||||||||| {r['seconds']:.0f} |")
            continue
        verdict = r["verdict"] + (" (GNSS-only handed back)" if r["handed_back_gnss_only"]
                                  else "")
        lines.append(
            f"| {r['name']} | {r['tile']} | {model} | {gnss} | {verdict} | "
            f"{_n(r['error_3d'])} | {_n(r['sigma_3d'])} | {_triple(r['error'], '{:.3f}')} | "
            f"{_triple(r['sigma'], '{:.3f}')} | {_triple(r['z'])} | {'/'.join(r['source'])} | "
            f"{_n(r.get('gnss_only_error_3d'))} | {_n(r.get('refined_error_3d'))} | "
            f"{r.get('num_registered_images', '-')} of "
            f"{r.get('num_key_frames', '-')} | {r['seconds']:.0f} |")
    return lines


def summary_lines(s: dict) -> list[str]:
    lines = [f"- measured blocks: {s['measured']} of {s['blocks']} ({s['right_model']} with the "
             f"right model); not built or failed: {', '.join(s['not_built_or_failed']) or 'none'}",
             f"- right model, all z (3 per block): RMS z {_n(s['rms_z'], '{:.2f}')}, share z <= 2 "
             f"{_n(s['share_z_le_2'], '{:.0%}')}, z > 3.5: {s['count_z_gt_3_5']}, max z "
             f"{_n(s['max_z'], '{:.2f}')}"]
    for source, b in s["z_by_source"].items():
        lines.append(f"  - directions fixed by {source}: {b['count']} z, RMS "
                     f"{b['rms_z']:.2f}, share <= 2 {b['share_z_le_2']:.0%}, max {b['max_z']:.2f}")
    v = s["verdicts"]
    lines += [f"- verdicts (right model): ok {v['ok']}, weak {v['weak']}, failed {v['failed']}; "
              f"GNSS-only block handed back (all blocks): {s['handed_back_gnss_only']}",
              f"- wrong-model blocks not \"failed\": {len(s['wrong_model_not_failed'])} of "
              f"{s['wrong_model']} ({', '.join(s['wrong_model_not_failed']) or '-'})",
              f"- \"ok\" with 3D error > 2 x stated 3D sigma: {len(s['ok_error_over_2_sigma'])} "
              f"({', '.join(s['ok_error_over_2_sigma']) or '-'})",
              f"- \"ok\" with stated 3D sigma > the tolerance {TOLERANCE:g} m: "
              f"{len(s.get('ok_sigma_over_tolerance', []))}",
              f"- refined block within {GOOD_ERROR:.2f} m (3D): {s['within_0_10_m']}, of them "
              f"\"ok\" {s['within_0_10_m_ok']}, not \"ok\": "
              f"{', '.join(s['within_0_10_m_not_ok']) or '-'}; of those, not \"ok\" although "
              f"no direction rests on GNSS alone: "
              f"{', '.join(s.get('within_0_10_m_not_ok_not_gnss_alone', [])) or '-'}",
              f"- refined block handed back although further from the truth than the GNSS-only "
              f"block: {len(s['returned_worse_than_gnss_only'])} "
              f"({', '.join(s['returned_worse_than_gnss_only']) or '-'})"]
    return lines


def write_results(rows: list[dict], command: str, code: str, quick: bool,
                  results: Path) -> dict:
    """calibration.json and calibration.md in `results`; returns the summary."""
    summary = summarise(rows)
    results.mkdir(parents=True, exist_ok=True)
    (results / "calibration.json").write_text(json.dumps(
        {"run": "quick" if quick else "full", "blocks": rows, "summary": summary,
         "command": command, "code": code}, indent=2, default=float))
    write_markdown(rows, summary, command, code, quick, results)
    return summary


def write_markdown(rows: list[dict], summary: dict, command: str, code: str, quick: bool,
                   results: Path) -> None:
    title = "# Calibration of refine's stated sigmas and verdict" + (
        f" (quick run, {len(rows)} blocks)" if quick else f" ({len(rows)} blocks)")
    text = "\n".join([
        title, "", "Produced by", "", f"    {command}", "", f"Code measured: {code}.", "",
        "Per block: camera-centre RMS error (m) of the block refine returns (the GNSS-only "
        "one after \"failed\") against the simulated truth per axis E / N / U and 3D; the "
        "stated sigma per axis from report.json `observability` (for the returned block) "
        "and sigma 3D = root of the sum of the three variances; z = error / sigma; fixed by: the observability source per axis; verdict: refine's; GNSS-only "
        "3D: the GNSS-only block's error; refined 3D: the refined block's (returned unless "
        "\"failed\"); GNSS: white noise sigma (horizontal; vertical x1.5) "
        "and the constant bias. Stated GNSS sigma 3 / 3 / 5 m throughout. Wrong-model blocks: "
        "the model given to refine shifted horizontally. images: registered by COLMAP of the "
        "key frames. s: seconds of refine.", "",
        "## Summary", "", *summary_lines(summary), "", "## Blocks", "", *block_table(rows), ""])
    (results / "calibration.md").write_text(text)


def run(count: int, seed: int, command: str, quick: bool, results: Path) -> list[dict]:
    """Draw, build and measure the blocks; the results rewritten after each block."""
    import colmap_citymodel.workflow  # noqa: F401  (the code measured is the code imported now)

    code = code_version()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, block in enumerate(draw_blocks(count, seed)):
            print(f"[{i + 1}/{count}] {block['name']} ({block['tile']}, {block['model']}"
                  f"{', wrong model' if block['wrong_model'] else ''}) ...", flush=True)
            row = run_block(block, Path(tmp))
            rows.append(row)
            print("  " + (f"{row['verdict']}: error 3D {row['error_3d']:.3f} m, sigma 3D "
                          f"{row['sigma_3d']:.3f} m, z {_triple(row['z'])}" if "z" in row
                          else f"{row['verdict']}: {row.get('failure')}") +
                  f" ({row.get('build_seconds', 0):.0f} s build, {row['seconds']:.0f} s)",
                  flush=True)
            write_results(rows, command, code, quick, results)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seed", type=int, default=1, help="draws the blocks (default 1)")
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_BLOCKS} blocks")
    parser.add_argument("--blocks", type=int, default=None,
                        help=f"number of blocks (default {DEFAULT_BLOCKS}; --quick "
                             f"{QUICK_BLOCKS})")
    parser.add_argument("--results", type=Path, default=RESULTS,
                        help="folder for calibration.md/.json (default benchmarks/results)")
    parser.add_argument("--tables_only", action="store_true",
                        help="only rewrite calibration.md from calibration.json")
    args = parser.parse_args()
    if args.tables_only:
        path = args.results / "calibration.json"
        if not path.exists():
            sys.exit(f"{path}: not found (run the benchmark first)")
        saved = json.loads(path.read_text())
        write_markdown(saved["blocks"], summarise(saved["blocks"]), saved["command"],
                       saved["code"], saved.get("run") == "quick", args.results)
        return
    count = args.blocks or (QUICK_BLOCKS if args.quick else DEFAULT_BLOCKS)
    import colmap_citymodel  # noqa: F401  (sets up the package logger first)

    logging.getLogger("colmap_citymodel").setLevel(logging.ERROR)
    command = " ".join([".venv/bin/python benchmarks/bench_calibration.py", *sys.argv[1:]])
    rows = run(count, args.seed, command, args.quick, args.results)
    print("\n".join(summary_lines(summarise(rows))))


if __name__ == "__main__":
    main()
