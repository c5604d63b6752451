"""Real street drive: COLMAP SfM of vehicle images, official LoD2 buildings, precise trajectory.

What it does, on a local copy of the data (it downloads nothing):

1. COLMAP (pycolmap, CPU) on the images: SIFT (at most ``--max_image_size`` px), exhaustive
   matching, incremental mapping allowing forward motion for the initial pair (the default
   ``init_max_forward_motion`` 0.95 rejects every pair of a forward-looking drive). Skipped when
   ``WORK/sparse/0`` exists (``--redo_sfm`` repeats it).
2. Pairs the trajectory rows with the images (row i = i-th image by name) and checks it: the
   7-parameter fit of the SfM camera centres to the rows, shifted by -2..2 rows, must be best
   without shift.
3. Reference camera centres: the trajectory rows, optionally + a lever arm in the vehicle
   frame (forward along the trajectory tangent, left, up; ``--lever_arm``, default none).
   Writes GNSS text files (``image_name E N H [sE sN sH]``, EPSG:25832+7837) for the cases:
   - ``precise``: the reference centres with sigma ``--precise_sigma`` (default 5 cm);
   - ``degraded``: the reference + a constant bias (``--bias``) + white noise (``--noise``,
     seed ``--seed``), sigma ``--gnss_sigma`` or refine's default (3, 3, 5 m): a simulated
     code GNSS;
   - ``noisy``: the reference + the same noise without bias.
4. For each case: GNSS-only (the 7-parameter similarity of the SfM centres to that GNSS, equal
   weights) and ``colmap-citymodel refine`` (subprocess, output ``WORK/refined_<case><tag>``;
   exit 3 = the quality gate failed and the GNSS-only adjustment was written), both compared
   with the reference centres: 3D RMS, and mean / standard deviation along track, across
   track (left), up.
5. Writes ``WORK/summary<tag>.json`` (with the colmap-citymodel commit, refine's messages and
   quality verdict) and prints a Markdown table.

Data: "LoD3ForLocalization" (Antonia Bieringer, TUM, bachelor's thesis 2023,
https://github.com/AntoniaBie/LoD3ForLocalization, commit db990ec). From it:
- ``data/Images/Route_3/307t_2021_031121_2965*_9.jpg``: 16 images, 2464 x 2056 px, of camera 9
  (forward-looking, f = 8.2199 mm / 3.45 um = 2382.6 px, ``main.py``) of a mobile mapping
  vehicle of 3D Mapping Solutions GmbH (MoFa project), driving east-south-east along the south
  side of the TUM main campus in Munich, 2 images a second (names: GPS seconds of week); the
  file "1_do not remove.jpg" is not one of them, leave it out;
- ``data/GNSS/9_Route3.txt``: 16 rows ``E N H`` (ETRS89 / UTM 32N, heights in the DHHN like the
  model: 516.9 m, 2 m above the model's ground at 514.8-515.0 m) of the vehicle's
  post-processed trajectory at the image times (row i = i-th image by name; the older
  ``GNSS_cam9_*`` files of the repository name camera 9). The SfM centres fit these rows with a
  7-parameter similarity to 2.5 mm RMS; moved by the offset that the repository's
  ``DataPrep.py`` adds for its "virtual camera" (dx 2.3104, dy -0.7484, dz 0.1080 m, taken as
  forward, left, up) they fit to 22 mm, and any offset along track worsens the fit (5 m: 45 mm).
  So the rows are taken as the projection centres of camera 9 (``--lever_arm 0 0 0``, the
  default) and serve as the precise reference, not as code GNSS.
The repository has no licence file (all rights reserved by default); the images and trajectory
are the thesis author's / 3D Mapping Solutions' test data. Use them locally for evaluation only,
never commit or redistribute them.

City model: the official Bavarian LoD2 buildings of tum2twin (https://github.com/tum-gis/tum2twin,
``citygml-lod2-datasets/DEBY_LOD2_*.gml``, LDBV Bayern open data, CC BY 4.0, EPSG:25832 +
DHHN2016), two of which (DEBY_LOD2_4906970, _4906972) line the left side of the street. The
official tiles 690_5334 / 690_5336 (geodaten.bayern.de opengeodata, CC BY 4.0) hold the
buildings on the right side too.

Layout of DATASET (a directory outside this repository):
    DATASET/images/307t_*.jpg     the 16 images
    DATASET/9_Route3.txt          the trajectory rows
    DATASET/citygml/*.gml         the LoD2 files (or give --citymodel)

Obtain it: ``git clone https://github.com/AntoniaBie/LoD3ForLocalization`` and
``git clone https://github.com/tum-gis/tum2twin``; copy ``data/Images/Route_3/307t_*.jpg`` to
DATASET/images, ``data/GNSS/9_Route3.txt`` to DATASET, ``citygml-lod2-datasets/*.gml`` to
DATASET/citygml.

Run: ``.venv/bin/python benchmarks/real_sequence.py DATASET [--work DIR]`` (about a minute on
two cores after the SfM, which takes about two).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

GNSS_CRS = "EPSG:25832+7837"
FOCAL_PX = 0.0082198514 / 3.45e-6  # camera 9, main.py of the data's repository
LEVER_ARM = (0.0, 0.0, 0.0)  # forward, left, up (m); see the module docstring
CASES = ("precise", "degraded", "noisy")


# --------------------------------------------------------------------------------------------
# SfM


def run_sfm(images: Path, work: Path, max_image_size: int, redo: bool) -> Path:
    """COLMAP on `images`; returns the directory of the largest model."""
    import pycolmap

    sparse = work / "sparse"
    if redo:
        shutil.rmtree(sparse, ignore_errors=True)
        (work / "database.db").unlink(missing_ok=True)
    if not (sparse / "0").is_dir():
        work.mkdir(parents=True, exist_ok=True)
        database = work / "database.db"
        database.unlink(missing_ok=True)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "SIMPLE_RADIAL"
        # Focal length prior from the data's calibration; principal point at the centre.
        reader.camera_params = f"{FOCAL_PX:.1f},1232,1028,0"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = max_image_size
        extraction.num_threads = 2
        t0 = time.perf_counter()
        names = sorted(p.name for p in images.glob("307t_*.jpg"))
        pycolmap.extract_features(database, images, image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=extraction, device=pycolmap.Device.cpu)
        pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
        options = pycolmap.IncrementalPipelineOptions()
        options.mapper.init_max_forward_motion = 1.0  # a forward-looking drive
        options.mapper.init_min_tri_angle = 4.0
        options.num_threads = 2
        options.random_seed = 0
        shutil.rmtree(sparse, ignore_errors=True)
        sparse.mkdir()
        models = pycolmap.incremental_mapping(database, images, sparse, options=options)
        print(f"SfM: {len(models)} model(s) in {time.perf_counter() - t0:.0f} s")
        if not models:
            raise SystemExit("COLMAP built no model")
    models = sorted((d for d in sparse.iterdir() if d.is_dir()),
                    key=lambda d: -pycolmap.Reconstruction(d).num_reg_images())
    return models[0]


# --------------------------------------------------------------------------------------------
# Geometry


def similarity(src: np.ndarray, dst: np.ndarray):
    """Least-squares 7-parameter similarity dst ~ s R src + t (Umeyama); returns (s, R, t)."""
    ms, md = src.mean(0), dst.mean(0)
    u, d, vt = np.linalg.svd((dst - md).T @ (src - ms) / len(src))
    flip = np.eye(3)
    flip[2, 2] = np.sign(np.linalg.det(u @ vt))
    rotation = u @ flip @ vt
    scale = np.trace(np.diag(d) @ flip) / np.mean(np.sum((src - ms) ** 2, axis=1))
    return scale, rotation, md - scale * rotation @ ms


def apply(sim, points: np.ndarray) -> np.ndarray:
    scale, rotation, t = sim
    return scale * points @ rotation.T + t


def rms3d(diff: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(diff ** 2, axis=1))))


def vehicle_axes(trajectory: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit forward (trajectory tangent, horizontal) and left vectors per row."""
    tangent = np.gradient(trajectory[:, :2], axis=0)
    forward = tangent / np.linalg.norm(tangent, axis=1, keepdims=True)
    forward3 = np.column_stack([forward, np.zeros(len(forward))])
    left3 = np.column_stack([-forward[:, 1], forward[:, 0], np.zeros(len(forward))])
    return forward3, left3


def components(diff: np.ndarray, forward: np.ndarray, left: np.ndarray) -> dict:
    """3D RMS and mean / std of differences along track, across track (left) and up."""
    along = np.sum(diff * forward, axis=1)
    across = np.sum(diff * left, axis=1)
    up = diff[:, 2]
    out = {"rms_3d_m": rms3d(diff)}
    for key, value in (("along", along), ("left", across), ("up", up)):
        out[f"mean_{key}_m"] = float(value.mean())
        out[f"std_{key}_m"] = float(value.std())
    return out


def write_gnss(path: Path, names, xyz: np.ndarray, sigma: float | None) -> None:
    with open(path, "w") as handle:
        handle.write(f"# image_name E N H{' sE sN sH' if sigma else ''} ({GNSS_CRS})\n")
        for name, p in zip(names, xyz):
            extra = f" {sigma} {sigma} {sigma}" if sigma else ""
            handle.write(f"{name} {p[0]:.4f} {p[1]:.4f} {p[2]:.4f}{extra}\n")


# --------------------------------------------------------------------------------------------
# refine


# Runs the command line interface of the colmap_citymodel package in a given directory (a
# snapshot of one commit, e.g. from `git archive`) instead of the installed (editable) one.
LAUNCHER = (
    "import sys; sys.meta_path = [f for f in sys.meta_path if 'editable' not in "
    "type(f).__module__]; sys.path.insert(0, sys.argv.pop(1)); "
    "from colmap_citymodel.cli import main; sys.exit(main())"
)


def run_refine(model: Path, citymodel: Path, gnss: Path, out: Path, extra: list[str],
               package_dir: Path | None = None) -> dict:
    """colmap-citymodel refine as a user runs it; returns exit code, messages and report."""
    shutil.rmtree(out, ignore_errors=True)
    exe = Path(sys.executable).with_name("colmap-citymodel")
    if package_dir is not None:
        program = [sys.executable, "-c", LAUNCHER, str(package_dir)]
    else:
        program = [str(exe) if exe.exists() else "colmap-citymodel"]
    command = [*program, "refine", "--no_progress",
               "--input_path", str(model), "--citymodel", str(citymodel),
               "--output_path", str(out), "--gnss", str(gnss), "--gnss_crs", GNSS_CRS, *extra]
    t0 = time.perf_counter()
    result = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    (out.parent / f"{out.name}.log").write_text(result.stdout + result.stderr)
    info = {"command": " ".join(command), "returncode": result.returncode, "seconds": seconds,
            "warnings": [line for line in result.stderr.splitlines() if "WARNING" in line],
            "last_lines": (result.stdout + result.stderr).strip().splitlines()[-3:]}
    report = out / "report.json"
    if result.returncode in (0, 3) and report.is_file():
        data = json.loads(report.read_text())
        info.update(
            georegistration_rms_m=data.get("georegistration", {}).get("rms_m"),
            num_assigned_points=data.get("num_assigned_points"),
            num_planes=data.get("num_planes"), sigma0=data.get("sigma0"),
            sigma0_by_group=data.get("sigma0_by_group")
            or data.get("precision", {}).get("sigma0_by_group"),
            converged=data.get("converged"), report_warnings=data.get("warnings"),
            result=data.get("result"), quality=data.get("quality"),
            coarse_alignment=data.get("coarse_alignment"))
    return info


def centres(model: Path, names) -> np.ndarray:
    import pycolmap

    rec = pycolmap.Reconstruction(model)
    by_name = {im.name: im.projection_center() for im in rec.images.values() if im.has_pose}
    return np.array([by_name.get(n, [np.nan] * 3) for n in names], dtype=np.float64)


# --------------------------------------------------------------------------------------------


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, help="directory with images/, 9_Route3.txt")
    parser.add_argument("--work", type=Path, help="results (default DATASET/work)")
    parser.add_argument("--citymodel", type=Path, help="LoD2 file or directory "
                        "(default DATASET/citygml)")
    parser.add_argument("--max_image_size", type=int, default=1600)
    parser.add_argument("--redo_sfm", action="store_true")
    parser.add_argument("--lever_arm", type=float, nargs=3, default=LEVER_ARM,
                        metavar=("FORWARD", "LEFT", "UP"),
                        help="camera minus trajectory point in the vehicle frame, metres")
    parser.add_argument("--bias", type=float, nargs=3, default=(1.5, -2.0, 3.0),
                        metavar=("E", "N", "H"), help="bias of the degraded GNSS, metres")
    parser.add_argument("--noise", type=float, nargs=3, default=(0.5, 0.5, 1.0),
                        metavar=("E", "N", "H"), help="white noise of the simulated GNSS, m")
    parser.add_argument("--precise_sigma", type=float, default=0.05)
    parser.add_argument("--gnss_sigma", type=float, default=None,
                        help="sigma (m) written for the degraded and noisy GNSS (default none: "
                        "refine's default 3, 3, 5 m)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--refine_args", default="", help="extra refine arguments, one string")
    parser.add_argument("--package_dir", type=Path, help="run refine from the colmap_citymodel "
                        "package in this directory (e.g. a `git archive` of one commit plus the "
                        "built _core extension) instead of the installed one")
    parser.add_argument("--tag", default="", help="suffix of the refine output directories and "
                        "of summary.json (to keep runs with other --refine_args)")
    args = parser.parse_args(argv)

    dataset = args.dataset.resolve()
    work = (args.work or dataset / "work").resolve()
    citymodel = (args.citymodel or dataset / "citygml").resolve()
    images = dataset / "images"
    work.mkdir(parents=True, exist_ok=True)

    import pycolmap

    model = run_sfm(images, work, args.max_image_size, args.redo_sfm)
    rec = pycolmap.Reconstruction(model)
    names = sorted(im.name for im in rec.images.values())
    all_names = sorted(p.name for p in images.glob("307t_*.jpg"))
    trajectory = np.loadtxt(dataset / "9_Route3.txt")
    if len(trajectory) != len(all_names):
        raise SystemExit(f"{len(trajectory)} trajectory rows for {len(all_names)} images")
    row = {n: i for i, n in enumerate(all_names)}
    rows = np.array([row[n] for n in names])
    sfm = centres(model, names)
    repo = Path(__file__).resolve().parents[1]
    version = subprocess.run(["git", "-C", str(repo), "describe", "--always", "--dirty"],
                             capture_output=True, text=True).stdout.strip()
    if args.package_dir is not None:
        version = f"package {args.package_dir.resolve()}"
    summary: dict = {
        "colmap_citymodel_commit": version or "unknown",
        "dataset": str(dataset), "model": str(model), "citymodel": str(citymodel),
        "images": len(all_names), "registered": rec.num_reg_images(),
        "points3D": rec.num_points3D(),
        "mean_reprojection_error_px": rec.compute_mean_reprojection_error(),
        "camera": str(rec.cameras[next(iter(rec.cameras))].params.tolist()),
    }
    print(f"colmap-citymodel {summary['colmap_citymodel_commit']}")
    print(f"SfM: {summary['registered']} of {summary['images']} images, "
          f"{summary['points3D']} points, {summary['mean_reprojection_error_px']:.3f} px")

    # Trajectory row i <-> i-th image: the fit must be best without shift.
    shift_rms = {}
    for shift in range(-2, 3):
        ok = (rows + shift >= 0) & (rows + shift < len(trajectory))
        target = trajectory[rows[ok] + shift]
        shift_rms[shift] = rms3d(target - apply(similarity(sfm[ok], target), sfm[ok]))
    summary["trajectory_fit_rms_by_row_shift_m"] = shift_rms
    print("7-parameter fit SfM -> trajectory, RMS by row shift:",
          ", ".join(f"{k:+d}: {v:.3f} m" for k, v in shift_rms.items()))
    if min(shift_rms, key=shift_rms.get) != 0:
        print("WARNING: the trajectory rows fit better shifted: check the pairing")

    forward, left = vehicle_axes(trajectory)
    lever = np.asarray(args.lever_arm, dtype=np.float64)
    reference = trajectory + lever[0] * forward + lever[1] * left + np.array([0, 0, lever[2]])
    summary["lever_arm_forward_left_up_m"] = lever.tolist()
    write_gnss(work / "reference_centres.txt", all_names, reference, None)
    ref = reference[rows]
    fwd, lft = forward[rows], left[rows]

    rng = np.random.default_rng(args.seed)
    noise = rng.normal(size=reference.shape) * np.asarray(args.noise)
    bias = np.asarray(args.bias, dtype=np.float64)
    gnss = {
        "precise": (reference, args.precise_sigma),
        "degraded": (reference + bias + noise, args.gnss_sigma),
        "noisy": (reference + noise, args.gnss_sigma),
    }
    extra = args.refine_args.split()
    summary["cases"] = {}
    for case in args.cases:
        positions, sigma = gnss[case]
        path = work / f"gnss_{case}{args.tag}.txt"
        write_gnss(path, all_names, positions, sigma)
        entry: dict = {"gnss_file": str(path), "gnss_sigma": sigma or "default (3, 3, 5)",
                       "gnss_vs_reference": components(positions[rows] - ref, fwd, lft)}
        only = apply(similarity(sfm, positions[rows]), sfm)
        entry["gnss_only_vs_reference"] = components(only - ref, fwd, lft)
        info = run_refine(model, citymodel, path, work / f"refined_{case}{args.tag}", extra,
                          args.package_dir)
        entry["refine"] = info
        if info["returncode"] in (0, 3):  # 3: quality gate failed, GNSS-only result written
            refined = centres(work / f"refined_{case}{args.tag}", names)
            entry["refined_vs_reference"] = components(refined - ref, fwd, lft)
            # Convention-free: the refined camera in the vehicle frame of the trajectory.
            offset = components(refined - trajectory[rows], fwd, lft)
            entry["refined_minus_trajectory_vehicle_frame"] = offset
        summary["cases"][case] = entry

    (work / f"summary{args.tag}.json").write_text(json.dumps(summary, indent=2, default=str))
    print()
    print("| case | solution | 3D RMS m | mean along / left / up m | std along / left / up m |")
    print("|---|---|---|---|---|")
    for case, entry in summary["cases"].items():
        for key, label in (("gnss_vs_reference", "GNSS input"),
                           ("gnss_only_vs_reference", "GNSS-only 7-par."),
                           ("refined_vs_reference", "refined")):
            c = entry.get(key)
            if c is None:
                print(f"| {case} | {label} | refine failed (exit "
                      f"{entry['refine']['returncode']}) | | |")
                continue
            if key == "refined_vs_reference" and entry["refine"]["returncode"] == 3:
                label = "refine output = GNSS-only (exit 3)"
            print(f"| {case} | {label} | {c['rms_3d_m']:.3f} | {c['mean_along_m']:+.2f} / "
                  f"{c['mean_left_m']:+.2f} / {c['mean_up_m']:+.2f} | {c['std_along_m']:.2f} / "
                  f"{c['std_left_m']:.2f} / {c['std_up_m']:.2f} |")
    for case, entry in summary["cases"].items():
        r = entry["refine"]
        if r["returncode"] in (0, 3):
            geo = r.get("georegistration_rms_m")
            print(f"{case}: refine exit {r['returncode']}, georegistration RMS "
                  f"{geo if geo is None else round(geo, 3)} m, {r.get('num_assigned_points')} "
                  f"tie points on {r.get('num_planes')} planes, s0 {r.get('sigma0')}")
            quality = r.get("quality") or {}
            if quality:
                reasons = "; ".join(quality.get("reasons", []))
                print(f"  quality {quality.get('verdict')}: {reasons}")
            o = entry["refined_minus_trajectory_vehicle_frame"]
            print(f"  output camera - trajectory (vehicle frame): along {o['mean_along_m']:+.3f}"
                  f" +- {o['std_along_m']:.3f}, left {o['mean_left_m']:+.3f} +- "
                  f"{o['std_left_m']:.3f}, up {o['mean_up_m']:+.3f} +- {o['std_up_m']:.3f} m")
        else:
            print(f"{case}: refine exit {r['returncode']}: {r['last_lines']}")
    print(f"summary: {work / f'summary{args.tag}.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
