"""Refine speed on a simulated flight mapped by COLMAP.

Default: the long sequence's Scn3 workspace (340 images, ~100k tie points, ~680k image
observations; built by `colmap-citymodel simulate workspaces/long_scn3.toml ...` if missing);
`--quick`: the short sequence's Scn3 (90 images, ~28k tie points), about 4x smaller.
Measured in one run, on copies of the same input:
- plain_solve_s: COLMAP's bundle adjustment of the input reconstruction as COLMAP ships it
  (`pycolmap.bundle_adjustment` with default BundleAdjustmentOptions = `colmap
  bundle_adjuster`), median of 3 runs: the baseline a user already pays for;
- hybrid_solve_s: one hybrid adjustment as refine's first iteration does it, set-up included:
  from the georegistered block, assign with refine's default method at its first threshold,
  move the block onto the planes (similarity), assign again, build the problem (COLMAP's
  problem + GNSS + f_dTP, f_dVT, f_VT), solve;
- assignment time per iteration and total refine time (refine() with its default options, as
  the CLI runs it); with
  `--quick` the median of 3 refines, each after one of COLMAP's adjustments (`--refine_runs`):
  this machine's speed drifts by 20 % from minute to minute, and alternating the two makes
  both see the same drift.
Also printed for transparency: a GNSS-prior BA of the georegistered block with refine's solver
settings (`plain_gnss_solve_s`): from COLMAP's converged output it stops after one step, so it
is a lower bound no adjustment that has to move the block can reach.
Prints the figures and, last, the lines `plain_solve_s`, `hybrid_solve_s`, `hybrid_solve_ratio`,
`assignment_fraction`, `refine_ratio` (targets: <= 1.2, <= 0.10, and <= 2.0 with `--quick`,
<= 1.0 at full size).

Then one refine per assignment method (the default, and `--methods`, default the others),
each printing `assignment_fraction_<method>` (target <= 0.10): refine's own assignment seconds
(`result.seconds["assignment"]`: reading the tie points, the threshold and the assign calls of
each iteration, not those inside the initial alignment rounds) over the refine's wall time.
Also per method: the seconds of every `assign` call of the refine (alignment rounds included,
`all_assign_fraction`), the final assignment's points and planes, camera centre and check
point RMS (3D, m), the verdict, and the process CPU seconds of the assign calls and of the
refine (all threads; steadier than wall time on a loaded machine). `--results FILE` writes
them as a markdown table; `--assignment_only` skips the plain/hybrid solve figures. The
machine's load moves every figure: compare fractions, and runs against a baseline measured
alongside.

`--profile N` (default 25; 0: none) runs one more refine with the default options under
cProfile and prints, after `refine_ratio`, where its time went: every iteration's solves (the
robust and the final one: seconds, Ceres iterations) and how far it moved the cameras, the
problems built and kept, and the N functions with the most time of their own and with the
most time in all; `--profile_out FILE` also writes them as markdown
(benchmarks/results/refine_profile_quick.md). The profiled refine runs slower than the timed
ones (cProfile's own cost): read its shares, not its seconds.

    .venv/bin/python benchmarks/bench_refine.py [--quick | --scenario long_scn3] [--workspace DIR]
        [--methods direct msac roi_msac] [--refine_runs N] [--assignment_only] [--results FILE]
        [--profile N] [--profile_out FILE]
"""

from __future__ import annotations

import argparse
import logging
import subprocess
import time
from pathlib import Path

import numpy as np
import pycolmap

from colmap_citymodel import logger
from colmap_citymodel.adjust.problem import HybridProblem
from colmap_citymodel.adjust.steps import align_block_to_planes
from colmap_citymodel.align.block_to_model import crop_to_reconstruction, georegister
from colmap_citymodel.assign.schedule import assign, initial_threshold
from colmap_citymodel.block.reconstruction import tie_points
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.simulate.synthetic import centre_errors
from colmap_citymodel.workflow import refine


def workspace_for(scenario: str) -> Path:
    """The simulated workspace of `workspaces/<scenario>.toml` (e.g. long_scn3), built into
    workspaces/generated/<sequence>/<ScnN> (sequence mapped once, in generated/cache) if
    missing."""
    from colmap_citymodel.simulate import sequence as simulate

    root = Path(__file__).resolve().parents[1] / "workspaces"
    sequence, scn = scenario.split("_")
    out = root / "generated" / sequence / scn.capitalize()
    if not (out / "sparse" / "0").is_dir():
        simulate.main(root / f"{scenario}.toml", out,
                      cache_path=root / "generated" / "cache", overwrite=out.exists())
    return out


def code_version() -> str:
    """HEAD of the checkout the package is imported from, "+ uncommitted changes" if its
    sources or this benchmark differ from it."""
    import colmap_citymodel

    package = Path(colmap_citymodel.__file__).resolve().parent

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(package), *args], capture_output=True, text=True,
                              check=True).stdout.strip()

    try:
        commit = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", ".", "../cpp_ext",
                    "../benchmarks/bench_refine.py")
    except (OSError, subprocess.CalledProcessError):
        return f"package at {package} (not a git checkout)"
    return commit + (" + uncommitted changes" if dirty else "")


class AssignTimer:
    """Wraps `assign` where the refine loop and the alignment rounds call it: the wall and the
    process CPU seconds of every call."""

    def __init__(self):
        from colmap_citymodel.adjust import loop, steps

        self.modules, self.inner = (loop, steps), loop.assign
        self.seconds = self.cpu_seconds = 0.0
        for module in self.modules:
            module.assign = self

    def restore(self) -> None:
        for module in self.modules:
            module.assign = self.inner

    def __call__(self, *args, **kwargs):
        t, c = time.perf_counter(), time.process_time()
        try:
            return self.inner(*args, **kwargs)
        finally:
            self.seconds += time.perf_counter() - t
            self.cpu_seconds += time.process_time() - c


def checkpoint_rms(rec: pycolmap.Reconstruction, workspace: Path, origin: np.ndarray) -> float:
    """RMS 3D (m) of the simulated check points triangulated in `rec` (local frame)."""
    from colmap_citymodel.precision.checkpoints import (
        evaluate_checkpoints,
        read_checkpoint_observations,
        read_checkpoints,
    )

    if not (workspace / "checkpoints.txt").exists():
        return float("nan")
    try:
        return float(evaluate_checkpoints(
            rec, read_checkpoints(workspace / "checkpoints.txt"),
            read_checkpoint_observations(workspace / "checkpoint_observations.txt"),
            origin, frame="local").rms_3d)
    except Exception as error:  # too few triangulated check points is a result too
        print(f"check points: {type(error).__name__}: {error}")
        return float("nan")


def timed_refine(method: str, sfm, store, gnss, truth, workspace: Path) -> dict:
    """One refine with assignment `method` (covariances off): its figures."""
    options = RefineOptions()
    options.precision.covariances = "off"  # timed separately (precision.py)
    options.assignment.method = method
    timer = AssignTimer()
    try:
        t, c = time.perf_counter(), time.process_time()
        result = refine(sfm, store, gnss, options, progress=False)
        seconds, cpu_seconds = time.perf_counter() - t, time.process_time() - c
    finally:
        timer.restore()
    rec = result.reconstruction_in_crs()
    return {
        "method": method, "refine_s": seconds, "assignment_s": result.seconds["assignment"],
        "all_assign_s": timer.seconds, "iterations": len(result.iterations),
        "fraction": result.seconds["assignment"] / seconds,
        "all_assign_fraction": timer.seconds / seconds,
        # CPU seconds of the process (all its threads): less sensitive to the machine's load
        "all_assign_cpu_s": timer.cpu_seconds, "refine_cpu_s": cpu_seconds,
        "points": result.assignment.num_assigned, "planes": result.assignment.num_faces,
        "camera_rms": float(np.sqrt(np.mean(centre_errors(rec, truth) ** 2))),
        "checkpoint_rms": checkpoint_rms(result.reconstruction, workspace, result.origin),
        "verdict": result.quality.verdict if result.quality is not None else "n/a",
        "seconds": result.seconds,
    }


def method_line(r: dict) -> str:
    return (f"assignment_fraction_{r['method']} {r['fraction']:.4f} "
            f"(refine {r['refine_s']:.1f} s, {r['iterations']} iterations, assignment "
            f"{r['assignment_s']:.1f} s, all assign calls {r['all_assign_s']:.1f} s = "
            f"{r['all_assign_fraction']:.4f}, CPU {r['all_assign_cpu_s']:.1f} of "
            f"{r['refine_cpu_s']:.1f} s, {r['points']} points on {r['planes']} planes, "
            f"camera centres {r['camera_rms']:.3f} m, check points {r['checkpoint_rms']:.3f} m, "
            f"verdict {r['verdict']})")


def results_table(rows: list[dict]) -> str:
    lines = ["| method | assignment s | all assign calls s | refine s | fraction | "
             "all-calls fraction | all assign calls CPU s | refine CPU s | iterations | "
             "assigned points | planes | camera centre RMS m | check point RMS m | verdict |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['method']} | {r['assignment_s']:.1f} | {r['all_assign_s']:.1f} | "
                     f"{r['refine_s']:.1f} | {r['fraction']:.3f} | "
                     f"{r['all_assign_fraction']:.3f} | {r['all_assign_cpu_s']:.1f} | "
                     f"{r['refine_cpu_s']:.1f} | {r['iterations']} | {r['points']} | "
                     f"{r['planes']} | {r['camera_rms']:.3f} | {r['checkpoint_rms']:.3f} | "
                     f"{r['verdict']} |")
    return "\n".join(lines) + "\n"


#: refine's own assignment method, the one refine_ratio times.
DEFAULT_METHOD = RefineOptions().assignment.method


def solve_figures(sfm, store, gnss, truth, workspace: Path, refine_runs: int = 1) -> dict:
    """The plain and hybrid solve figures and refine with its default options (its row: the run
    with the median time). With `refine_runs` > 1 the refines alternate with COLMAP's
    adjustments (COLMAP, refine, COLMAP, refine, ...): a machine whose speed drifts slows both
    alike."""
    refine_options = RefineOptions()
    refine_options.precision.covariances = "off"  # timed separately (precision.py)

    plain_seconds, refines = [], []
    for k in range(max(3, refine_runs)):
        if k < 3:
            plain_rec = pycolmap.Reconstruction(sfm)
            t = time.perf_counter()
            pycolmap.bundle_adjustment(plain_rec, pycolmap.BundleAdjustmentOptions())
            plain_seconds.append(time.perf_counter() - t)
        if k < refine_runs - 1:
            refines.append(timed_refine(DEFAULT_METHOD, sfm, store, gnss, truth, workspace))
    plain_s = float(np.median(plain_seconds))

    start = pycolmap.Reconstruction(sfm)
    _, priors, _ = georegister(start, store, gnss, None)
    store_near = crop_to_reconstruction(store, start, refine_options.workflow.overlap_margin)
    gnss_rec = pycolmap.Reconstruction(start)
    gnss_problem = HybridProblem(gnss_rec, None, None, priors, refine_options.adjustment,
                                 robust_images=False, robust_planes=False)
    gnss_report = gnss_problem.solve()

    hybrid_rec = pycolmap.Reconstruction(start)
    t = time.perf_counter()
    ids, xyz = tie_points(hybrid_rec)
    first_threshold = initial_threshold(refine_options.assignment)
    assignment = assign(xyz, ids, store_near, first_threshold, refine_options.assignment)
    first_assignment_s = time.perf_counter() - t
    t = time.perf_counter()
    _, xyz, assignment = align_block_to_planes(  # as refine's iteration 0
        hybrid_rec, ids, xyz, assignment, store_near, priors, first_threshold, refine_options)
    hybrid = HybridProblem(hybrid_rec, store_near, assignment, priors,
                           refine_options.adjustment, robust_images=False, robust_planes=False)
    hybrid_report = hybrid.solve()
    hybrid_s = time.perf_counter() - t

    refines.append(timed_refine(DEFAULT_METHOD, sfm, store, gnss, truth, workspace))
    times = [r["refine_s"] for r in refines]
    median = refines[int(np.argsort(times)[len(times) // 2])]  # the median run (upper median)
    refine_s, iterations, error = median["refine_s"], median["iterations"], median["camera_rms"]

    print(f"plain COLMAP bundle adjustment (defaults): "
          f"{', '.join(f'{v:.2f}' for v in plain_seconds)} s")
    print(f"plain GNSS-prior solve of the georegistered block (refine's settings): "
          f"{gnss_report.ceres_iterations} Ceres iterations, {gnss_report.seconds:.3f} s, "
          f"{gnss_report.count['image']} image residuals")
    print(f"hybrid solve: {hybrid_report.ceres_iterations} Ceres iterations "
          f"({hybrid_report.seconds:.3f} s of {hybrid_s:.3f} s with alignment and set-up), "
          f"{assignment.num_assigned} points on {assignment.num_faces} planes "
          f"(assignment {first_assignment_s:.3f} s)")
    if len(refines) > 1:
        print(f"refines (alternating with COLMAP's adjustments): "
              f"{', '.join(f'{v:.1f}' for v in times)} s, the median run below")
    print(f"refine ({DEFAULT_METHOD} assignment): {iterations} iterations, {refine_s:.1f} s "
          f"({', '.join(f'{k} {v:.1f}' for k, v in median['seconds'].items())}), "
          f"camera centre RMS vs truth {error:.3f} m")
    print(f"assignment_s_per_iteration {median['assignment_s'] / iterations:.3f}")
    print(f"plain_gnss_solve_s {gnss_report.seconds:.3f}")
    print(f"refine_ratio_vs_plain_gnss_solve {refine_s / gnss_report.seconds:.3f}")
    print(f"plain_solve_s {plain_s:.3f}")
    print(f"hybrid_solve_s {hybrid_s:.3f}")
    print(f"hybrid_solve_ratio {hybrid_s / plain_s:.3f}")
    print(f"assignment_fraction {median['fraction']:.4f}")
    print(f"refine_ratio {refine_s / plain_s:.3f}")
    median["plain_s"] = plain_s
    return median


class SolveSpy:
    """Counts the hybrid problems built and kept (HybridProblem.__init__ and .reassign) and the
    CPU seconds of each build, while installed."""

    def __init__(self):
        self.builds, self.kept, self.refused = [], 0, 0
        self.init, self.reassign = HybridProblem.__init__, HybridProblem.reassign
        spy = self

        def init(problem, *args, **kwargs):
            start = time.process_time()
            spy.init(problem, *args, **kwargs)
            spy.builds.append(time.process_time() - start)

        def reassign(problem, *args, **kwargs):
            kept = spy.reassign(problem, *args, **kwargs)
            spy.kept += bool(kept)
            spy.refused += not kept
            return kept

        HybridProblem.__init__, HybridProblem.reassign = init, reassign

    def restore(self) -> None:
        HybridProblem.__init__, HybridProblem.reassign = self.init, self.reassign


def iteration_lines(result) -> list[str]:
    """One line per loop iteration: its solves, how far it moved the cameras, what it changed."""
    lines = []
    for it in result.iterations:
        robust = (f"robust {it.robust.seconds:.2f} s / {it.robust.ceres_iterations} it"
                  if it.robust is not None and it.robust is not it.final else
                  "robust only" if it.robust is not None else "no robust solve")
        lines.append(f"| {it.iteration} | {it.phase} | {it.threshold:.2f} | {it.num_assigned} | "
                     f"{it.num_faces} | {it.num_eliminated} | {robust} | "
                     f"{it.final.seconds:.2f} s / {it.final.ceres_iterations} it | "
                     f"{it.camera_shift * 1000:.1f} | {it.relative_change:.1e} |")
    return lines


def profile_refine(sfm, store, gnss, top: int) -> str:
    """One refine with the default options (covariances off) under cProfile: a markdown
    summary of its iterations, its problems and its top functions."""
    import cProfile
    import io
    import pstats

    options = RefineOptions()
    options.precision.covariances = "off"
    spy = SolveSpy()
    profiler = cProfile.Profile()
    wall, cpu = time.perf_counter(), time.process_time()
    try:
        profiler.enable()
        result = refine(sfm, store, gnss, options, progress=False)
        profiler.disable()
    finally:
        spy.restore()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    stages = ", ".join(f"{k} {v:.1f}" for k, v in result.seconds.items())
    out = [f"profiled refine: {wall:.1f} s wall, {cpu:.1f} s CPU ({stages}); "
           f"{len(spy.builds)} hybrid problems built ({sum(spy.builds):.1f} s CPU), "
           f"{spy.kept} kept by reassign, {spy.refused} reassigns refused", "",
           "| iteration | loop | threshold m | points | planes | eliminated | robust solve | "
           "final solve | largest camera move mm | RMS change |",
           "|---|---|---|---|---|---|---|---|---|---|", *iteration_lines(result), ""]
    for order in ("tottime", "cumulative"):
        text = io.StringIO()
        pstats.Stats(profiler, stream=text).sort_stats(order).print_stats(top)
        body = text.getvalue()
        body = body[body.index("ncalls"):] if "ncalls" in body else body
        out += [f"top {top} by {order}:", "", "```", body.rstrip(), "```", ""]
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--quick", action="store_true",
                        help="short_scn3: the short sequence (~4x smaller)")
    parser.add_argument("--scenario", default="long_scn3",
                        help="workspaces/<scenario>.toml (default long_scn3, the full size)")
    parser.add_argument("--workspace", type=Path, help="a simulated workspace to use instead")
    parser.add_argument("--methods", nargs="*",
                        default=[m for m in ("direct", "msac", "roi_msac", "auto")
                                 if m != DEFAULT_METHOD],
                        help="assignment methods to time besides refine's default "
                             f"({DEFAULT_METHOD}), each in a full refine "
                             "(assignment_fraction_<method>)")
    parser.add_argument("--refine_runs", type=int,
                        help="refines with the default options for refine_ratio, alternating with "
                             "COLMAP's three adjustments; the median counts (default 3 with "
                             "--quick, else 1)")
    parser.add_argument("--assignment_only", action="store_true",
                        help="only the refines per assignment method (no plain/hybrid solves)")
    parser.add_argument("--results", type=Path,
                        help="write the per-method figures to this markdown file")
    parser.add_argument("--profile", type=int, default=25, metavar="N",
                        help="after the timed refines, one refine under cProfile: its "
                             "iterations and its N top functions (0: none)")
    parser.add_argument("--profile_out", type=Path,
                        help="write the profile's summary to this markdown file")
    args = parser.parse_args()
    logger.setLevel(logging.WARNING)
    scenario = "short_scn3" if args.quick else args.scenario
    workspace = args.workspace or workspace_for(scenario)
    from colmap_citymodel.block.gnss import read_gnss
    from colmap_citymodel.block.reconstruction import read_reconstruction
    from colmap_citymodel.citymodel.read import read_city_model

    store = read_city_model(workspace / "given_model.gml")
    gnss = read_gnss(database=workspace / "database.db", target_crs=store.crs)
    sfm = read_reconstruction(workspace / "sparse" / "0")
    print(f"workspace {workspace}: {sfm.num_reg_images()} images, {sfm.num_points3D()} tie "
          f"points, {sfm.compute_num_observations()} image observations, "
          f"{len(store.faces)} model faces")
    # Compare in model CRS: truth/ is local to the sequence's origin, the result to the store's.
    truth = pycolmap.Reconstruction(str(workspace / "truth"))
    truth_origin = np.loadtxt(workspace / "truth" / "origin.txt", comments="#")
    truth.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), truth_origin))
    version = code_version()
    print(f"code {version}")
    rows = []
    if not args.assignment_only:
        runs = args.refine_runs if args.refine_runs is not None else (3 if args.quick else 1)
        rows.append(solve_figures(sfm, store, gnss, truth, workspace, max(1, runs)))
        print(method_line(rows[0]))
    else:
        rows.append(timed_refine(DEFAULT_METHOD, sfm, store, gnss, truth, workspace))
        print(method_line(rows[0]))
    for method in args.methods:
        rows.append(timed_refine(method, sfm, store, gnss, truth, workspace))
        print(method_line(rows[-1]))
    table = results_table(rows)
    print(table)
    if args.profile > 0:
        summary = profile_refine(sfm, store, gnss, args.profile)
        ratio = (f"refine_ratio {rows[0]['refine_s'] / rows[0]['plain_s']:.3f} (refine "
                 f"{rows[0]['refine_s']:.1f} s, COLMAP's bundle adjustment "
                 f"{rows[0]['plain_s']:.1f} s)" if "plain_s" in rows[0] else "")
        print(ratio + "\n" + summary)
        if args.profile_out is not None:
            args.profile_out.parent.mkdir(parents=True, exist_ok=True)
            args.profile_out.write_text(
                f"# Profile of refine on `{workspace.name}`\n\ncode {version}; {ratio}\n\n"
                + summary + "\n")
            print(f"wrote {args.profile_out}")
    if args.results is not None:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        args.results.write_text(
            f"workspace `{workspace}` ({sfm.num_reg_images()} images, {sfm.num_points3D()} tie "
            f"points), code {version}\n\n" + table)
        print(f"wrote {args.results}")


if __name__ == "__main__":
    main()
