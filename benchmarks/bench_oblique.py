"""The simulated oblique aerial block through the documented command sequence, and Mulder's
Table 5.2 (median a posteriori sigmas of tie points and projection centres for nadir, oblique and
both).

Steps (each a `colmap-citymodel` command, run in this process and timed):

1. `simulate-oblique` over a real Berlin LoD2 tile (five heads, GNSS/IMU noise);
2. `import-eo` -> rig, frames and pose priors in the database, the known-pose model;
3. pair lists: `pairs` (footprints on the city model), exhaustive (every pair), and spatial
   (what `colmap spatial_matcher` chooses with its defaults: each image's 50 nearest images
   by position, horizontally, within 100 m);
4. per pair list, on its own copy of the database: `simulate-matching` (the simulated
   descriptor matches of the listed pairs, then COLMAP's geometric verification, timed) and
   `triangulate` (COLMAP's point triangulator with the imported poses);
5. `refine` of the footprint-pairs block with the city model and import-eo's gnss.txt (its
   verdict is recorded; with "failed" refine writes the GNSS-only adjustment, exit status 3,
   and the chain goes on with that); the same refine with `--terrain none` beside it, for the
   terrain table (what the ground tie points on the terrain from the buildings' feet give);
6. `precision --subset nadir --subset oblique --subset both` on the refined block with the
   same GNSS, written to benchmarks/results/oblique.md (+ .json).

Camera centres of both refines and of the GNSS/IMU poses as imported (import-eo's known-pose
model, the block a user has without refine) against the simulation's true centres: RMS per
axis and 3D, in the terrain table.

    .venv/bin/python benchmarks/bench_oblique.py [--work DIR] [--seed 1]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from scenarios import centre_errors, truth_centres  # noqa: E402  (not a package)

RESULTS = ROOT / "benchmarks" / "results"
CITY = ROOT / "tests" / "data" / "citygml" / "berlin" / "3910_5819.gml"
CRS = "EPSG:25833"
SUBSETS = ["nadir=N/*", "oblique=F/*,B/*,L/*,R/*", "both=*"]
#: Mulder Table 5.2: median sigma X, Y, Z (cm) of tie points, nadir / oblique / both.
MULDER = {"nadir": (2.9, 2.9, 9.5), "oblique": (3.3, 3.0, 11.6), "both": (1.3, 1.3, 4.7)}


def cli(*argv, allowed=(0,)) -> float:
    from colmap_citymodel.cli import main

    t0 = time.perf_counter()
    status = main([str(a) for a in argv]) or 0
    if status not in allowed:
        raise SystemExit(f"command failed ({status}): {' '.join(map(str, argv))}")
    return time.perf_counter() - t0


def spatial_pairs(model: Path, path: Path, neighbours: int = 50, distance: float = 100.0) -> int:
    """COLMAP's spatial matcher defaults on the imported positions (ignore_z)."""
    import pycolmap
    from scipy.spatial import cKDTree

    rec = pycolmap.Reconstruction(str(model))
    names = sorted(i.name for i in rec.images.values())
    by_name = {i.name: i for i in rec.images.values()}
    xy = np.array([by_name[n].projection_center()[:2] for n in names])
    dist, idx = cKDTree(xy).query(xy, k=min(neighbours + 1, len(names)),
                                  distance_upper_bound=distance)
    pairs = set()
    for i in range(len(names)):
        for d, j in zip(dist[i], idx[i]):
            if np.isfinite(d) and j != i and j < len(names):
                pairs.add((min(i, j), max(i, j)))
    path.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in sorted(pairs)))
    return len(pairs)


def exhaustive_pairs(model: Path, path: Path) -> int:
    import pycolmap

    names = sorted(i.name for i in pycolmap.Reconstruction(str(model)).images.values())
    lines = [f"{a} {b}\n" for k, a in enumerate(names) for b in names[k + 1:]]
    path.write_text("".join(lines))
    return len(lines)


def matching_variant(work: Path, name: str, pairs: Path) -> dict:
    from colmap_citymodel.block.triangulate import images_with_points
    from colmap_citymodel.simulate.oblique import simulate_matching
    import pycolmap

    database = work / f"database_{name}.db"
    shutil.copyfile(work / "ws" / "database.db", database)
    t0 = time.perf_counter()
    matching = simulate_matching(work / "ws", pairs, database)
    t_match = time.perf_counter() - t0
    out = work / f"sparse_{name}"
    t_tri = cli("triangulate", "--database", database, "--input_path", work / "eo" / "sparse",
                "--output_path", out)
    rec = pycolmap.Reconstruction(str(out))
    return {"pairs": matching.pairs, "matched_pairs": matching.matched_pairs,
            "verified_pairs": matching.verified_pairs, "inlier_matches": matching.inlier_matches,
            "verification_seconds": matching.seconds_verification,
            "matching_seconds": t_match, "triangulation_seconds": t_tri,
            "images": rec.num_images(), "images_with_20_points": images_with_points(rec, 20),
            "tie_points": rec.num_points3D(), "observations": rec.compute_num_observations(),
            "mean_track_length": rec.compute_mean_track_length()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("/tmp/bench_oblique"))
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--strips", type=int, default=3)
    parser.add_argument("--strip_length", type=float, default=600.0)
    parser.add_argument("--output", type=Path, default=RESULTS / "oblique.md")
    args = parser.parse_args(argv)
    work = args.work
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    ws = work / "ws"
    times = {}
    times["simulate"] = cli("simulate-oblique", "--citymodel", CITY, "--output_path", ws,
                            "--seed", args.seed, "--strips", args.strips, "--strip_length",
                            args.strip_length)
    times["import_eo"] = cli("import-eo", "--database", ws / "database.db", "--eo",
                             ws / "eo.txt", "--rig", ws / "rig.json", "--eo_crs", CRS,
                             "--output_path", work / "eo")
    times["pairs"] = cli("pairs", "--input_path", work / "eo" / "sparse", "--citymodel", CITY,
                         "--database", ws / "database.db", "--output", work / "pairs_footprint.txt")
    exhaustive_pairs(work / "eo" / "sparse", work / "pairs_exhaustive.txt")
    spatial_pairs(work / "eo" / "sparse", work / "pairs_spatial.txt")
    variants = {}
    for name in ("footprint", "spatial", "exhaustive"):
        variants[name] = matching_variant(work, name, work / f"pairs_{name}.txt")
        print(name, json.dumps(variants[name]), flush=True)
    times["refine"] = cli("refine", "--input_path", work / "sparse_footprint", "--citymodel",
                          CITY, "--gnss", work / "eo" / "gnss.txt", "--gnss_crs", CRS,
                          "--output_path", work / "refined", "--precision", "off",
                          "--no_progress", allowed=(0, 3))  # 3: GNSS-only result written
    times["refine_no_terrain"] = cli(
        "refine", "--input_path", work / "sparse_footprint", "--citymodel", CITY, "--gnss",
        work / "eo" / "gnss.txt", "--gnss_crs", CRS, "--output_path", work / "refined_none",
        "--precision", "off", "--no_progress", "--terrain", "none", allowed=(0, 3))
    subset_args = [a for s in SUBSETS for a in ("--subset", s)]
    times["precision"] = cli("precision", "--input_path", work / "refined", *subset_args,
                             "--gnss", work / "eo" / "gnss.txt", "--gnss_crs", CRS,
                             "--output_path", work / "precision", "--no_progress")
    report = json.loads((work / "precision" / "precision_subsets.json").read_text())
    refine_report = json.loads((work / "refined" / "report.json").read_text())
    simulation = json.loads((ws / "truth" / "simulation.json").read_text())
    truth = truth_centres(ws)
    centres = {"GNSS/IMU poses as imported": centre_rms(work / "eo" / "sparse", truth),
               "refine (terrain from the buildings' feet)": centre_rms(work / "refined", truth),
               "refine --terrain none": centre_rms(work / "refined_none", truth)}
    result = {"seed": args.seed, "simulation": simulation, "times_seconds": times,
              "camera_centres": centres,
              "matching": variants, "precision": report["subsets"],
              "refine_quality": refine_report.get("quality"),
              "terrain": {"default": terrain_summary(refine_report),
                          "none": terrain_summary(json.loads(
                              (work / "refined_none" / "report.json").read_text()))}}
    RESULTS.mkdir(exist_ok=True)
    args.output.with_suffix(".json").write_text(json.dumps(result, indent=2, default=str))
    args.output.write_text(markdown(result))
    print(markdown(result))
    return 0


def model_frame(model: Path):
    """A COLMAP model and the origin of its frame in the model CRS: a refine output
    (georeference.json beside it: CRS, or local with its origin) or import-eo's known-pose
    model (origin.json one level up)."""
    import pycolmap

    origin = np.zeros(3)
    georeference = model / "georeference.json"
    if georeference.exists():
        g = json.loads(georeference.read_text())
        origin = np.zeros(3) if g["output_frame"] == "crs" else np.asarray(g["origin"])
    elif (model.parent / "origin.json").exists():
        origin = np.asarray(json.loads((model.parent / "origin.json").read_text())["origin"])
    return pycolmap.Reconstruction(str(model)), origin


def centre_rms(model: Path, truth: dict[str, np.ndarray]) -> dict:
    """RMS (m) of the model's projection centres against `truth` (model CRS), per axis and 3D
    (scenarios.centre_errors)."""
    e = centre_errors(*model_frame(model), truth)
    return {"images": e["num_images"], "E": e["rms_x"], "N": e["rms_y"], "U": e["rms_z"],
            "3d": e["rms_3d"]}


def terrain_summary(report: dict) -> dict:
    """What a refine's report.json says about the terrain and the ground tie points."""
    terrain = report.get("terrain") or {}
    residuals = terrain.get("residuals") or {}
    u = (report.get("observability") or {}).get("U") or {}
    quality = report.get("quality") or {}
    return {"source": terrain.get("source", "none"), "cell_m": terrain.get("cell_m"),
            "num_faces": terrain.get("num_faces"), "units": len(residuals.get("units") or {}),
            "ground_points": residuals.get("num_points", 0), "rms_m": residuals.get("rms_m"),
            "assigned": report.get("num_assigned_points"), "points": report.get("num_points3D"),
            "u_source": u.get("source", "-") + (" (terrain)" if u.get("terrain") else ""),
            "u_sigma_m": u.get("sigma"), "verdict": quality.get("verdict"),
            "reasons": quality.get("reasons") or []}


def terrain_table(terrain: dict) -> list[str]:
    """The terrain table: refine as run (the terrain from the buildings' feet) and with
    `--terrain none`."""
    lines = ["## Terrain", "", "refine with its default terrain (the buildings' feet: no DTM "
             "given) and with `--terrain none`:", "",
             "| terrain | cells (m) | terrain faces | units | tie points on the terrain | "
             "their RMS distance (m) | assigned / all tie points | U fixed by | sigma U (m) | "
             "verdict |", "|---|---|---|---|---|---|---|---|---|---|"]
    for name, t in terrain.items():
        rms = "-" if t["rms_m"] is None else f"{t['rms_m']:.3f}"
        sigma = "-" if t["u_sigma_m"] is None else f"{t['u_sigma_m']:.3f}"
        lines.append(f"| {t['source'] if name == 'default' else '--terrain none'} | "
                     f"{t['cell_m'] or '-'} | {t['num_faces'] or 0} | {t['units']} | "
                     f"{t['ground_points']} | {rms} | {t['assigned']} / {t['points']} | "
                     f"{t['u_source']} | {sigma} | {t['verdict']} |")
    return lines + [""]


def centre_table(centres: dict) -> list[str]:
    lines = ["Camera centres against the simulation's truth (RMS, m; a refine that fails hands "
             "back its GNSS-only adjustment):", "",
             "| block | images | E | N | U | 3D |", "|---|---|---|---|---|---|"]
    for name, c in centres.items():
        lines.append(f"| {name} | {c['images']} | {c['E']:.3f} | {c['N']:.3f} | {c['U']:.3f} | "
                     f"{c['3d']:.3f} |")
    return lines + [""]


def markdown(result: dict) -> str:
    sim = result["simulation"]
    o = sim["options"]
    lines = ["# Oblique aerial block (simulated)", "",
             f"`benchmarks/bench_oblique.py --seed {result['seed']}`: {sim['exposures']} "
             f"exposures x {sim['heads']} heads = {sim['images']} images in {o['strips']} "
             f"strips ({o['strip_length']:.0f} m, exposures every {o['exposure_spacing']:.0f} "
             f"m, strips {o['strip_spacing']:.0f} m apart) {o['flying_height']:.0f} m above "
             "the Berlin LoD2 tile 3910_5819 (35 buildings) with generalisation effects; "
             f"PINHOLE {o['width']} x {o['height']} px, f = {o['focal']:.0f} px for every head, "
             "obliques tilted 45 deg; EO noise "
             f"{o['eo_sigma'][0]}/{o['eo_sigma'][1]}/{o['eo_sigma'][2]} m and "
             f"{o['attitude_sigma_deg']} deg; {o['pixel_noise']} px keypoint noise; matches "
             f"only between views less than {o['max_match_angle_deg']:.0f} deg apart.", "",
             "## Pair selection", "",
             "| pairs | pairs | matched (>= 15) | verified | inlier matches | verification s "
             "| images with >= 20 tie points | tie points | observations | track length |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, v in result["matching"].items():
        lines.append(f"| {name} | {v['pairs']} | {v['matched_pairs']} | {v['verified_pairs']} | "
                     f"{v['inlier_matches']} | {v['verification_seconds']:.1f} | "
                     f"{v['images_with_20_points']} / {v['images']} | {v['tie_points']} | "
                     f"{v['observations']} | {v['mean_track_length']:.2f} |")
    q = result.get("refine_quality") or {}
    lines += ["", f"refine: verdict {q.get('verdict')}"
              + (f" ({'; '.join(q.get('reasons', []))})" if q.get("reasons") else "") + ".", ""]
    if result.get("terrain"):
        lines += terrain_table(result["terrain"])
    if result.get("camera_centres"):
        lines += centre_table(result["camera_centres"])
    lines += ["", "## Median a posteriori sigmas per subset (Mulder Table 5.2)", "",
              "Tie points and projection centres, cm (GNSS datum: import-eo's gnss.txt, "
              "sigma 5/5/10 cm per image):", "",
              "| subset | images | tie points | tie X | tie Y | tie Z | centre X0 | centre Y0 | "
              "centre Z0 | Mulder tie X / Y / Z |", "|---|---|---|---|---|---|---|---|---|---|"]
    for s in result["precision"]:
        p, c = s["median_point_sigma"], s["median_centre_sigma"]
        m = MULDER.get(s["name"])
        lines.append(f"| {s['name']} | {s['num_images']} | {s['num_points3D']} | "
                     f"{100 * p['X']:.2f} | {100 * p['Y']:.2f} | {100 * p['Z']:.2f} | "
                     f"{100 * c['X0']:.2f} | {100 * c['Y0']:.2f} | {100 * c['Z0']:.2f} | "
                     + (f"{m[0]} / {m[1]} / {m[2]}" if m else "") + " |")
    t = result["times_seconds"]
    lines += ["", "Seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in t.items()) + ".", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
