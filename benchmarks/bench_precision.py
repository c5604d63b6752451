"""Honest precision of check points: Delta/sigma per axis, classical vs aware.

On a simulated workspace with check points (default: the short sequence's Scn3, the original
generalised LOD2 model with systematic plane errors, GNSS everywhere; built by the simulator as
benchmarks/bench_refine.py does if missing), refine runs once per variant on the same
`sparse/0`, with the check points' image observations given to refine (never assigned to planes,
never control; their covariance is the marginal one of the adjustment, precision.py). Each run
reports sigma_CP under two stochastic models for the same estimate:

- classical: Unger's (independent f_dTP, sigma_dTP 0.2 m), s0^2 (A^T P A)^-1;
- generalisation_aware: plus per-plane offsets o_p ~ N(0, sigma_generalisation^2) shared by the
  plane's f_dTP (options.GENERALISATION_SIGMA = 0.2 m, Unger 5.3's "typical size of
  generalisation effects") and the plane's tilts (its vertices each off by that sigma),
  propagated as consider parameters.

Variants: `default` (refine's defaults: no a priori sigma_generalisation, the
generalisation-aware sigmas with the sigma the planes' mean residuals give), `plain` (Unger's
weights, sigma_generalisation 0.2 m a priori), `vce` (then iterated variance components of image and
f_dTP, the re-weighted solve is the result), `estimated` (experimental: the offsets estimated as
unknowns in a final re-solve; shows the scale bias that keeps this off).

Prints Unger's Tables 12/13 per variant and model (RMS of Delta = known - estimated per axis,
RMS of sigma_CP, ratio, before and after the 7-parameter Helmert transform; after Helmert also
against the sigma of the Helmert residuals) and writes benchmarks/results/precision.md (+ .json).

    .venv/bin/python benchmarks/bench_precision.py [--workspace DIR] [--variants plain vce ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
VARIANTS = ("default", "plain", "vce", "estimated")
DESCRIPTION = {
    "default": "refine's defaults (Unger's weights, no a priori sigma_generalisation): the "
               "generalisation-aware sigmas with the sigma the planes' mean f_dTP residuals "
               "give (moments, no re-solve)",
    "plain": "Unger's weights (sigma_image 1 px, sigma_dTP 0.2 m), sigma_generalisation 0.2 m",
    "vce": "iterated variance components of image and f_dTP after the loop (re-weighted "
           "solve); sigma_generalisation estimated from the planes' mean residuals",
    "estimated": "experimental: per-plane offsets estimated (prior 0.2 m) in a re-solve after "
                 "the loop",
}


def options_for(variant: str):
    from colmap_citymodel.options import GENERALISATION_SIGMA, RefineOptions

    options = RefineOptions()
    options.precision.covariances = "on"
    if variant != "default":
        options.adjustment.sigma_generalisation = GENERALISATION_SIGMA
    options.precision.variance_components = variant == "vce"
    options.adjustment.estimate_generalisation = variant == "estimated"
    return options


def run(workspace: Path, variant: str) -> dict:
    from colmap_citymodel.block.gnss import read_gnss
    from colmap_citymodel.block.reconstruction import read_reconstruction
    from colmap_citymodel.citymodel.read import read_city_model
    from colmap_citymodel.precision.checkpoints import read_checkpoint_observations, read_checkpoints
    from colmap_citymodel.workflow import refine

    store = read_city_model(workspace / "given_model.gml")
    gnss = read_gnss(database=workspace / "database.db", target_crs=store.crs)
    sfm = read_reconstruction(workspace / "sparse" / "0")
    checkpoints = read_checkpoints(workspace / "checkpoints.txt")
    observations = read_checkpoint_observations(workspace / "checkpoint_observations.txt")
    start = time.perf_counter()
    result = refine(sfm, store, gnss, options_for(variant), progress=False,
                    checkpoints=checkpoints, checkpoint_observations=observations)
    seconds = time.perf_counter() - start
    evaluation = result.checkpoints
    p = result.precision
    evaluated = evaluation.todict()
    evaluated.pop("points")  # per check point: in refine's checkpoint_precision.csv
    out = {"variant": variant, "description": DESCRIPTION[variant], "seconds": seconds,
           "evaluation": evaluated, "sigma0": p.variance.sigma0,
           "sigma0_by_group": p.variance.sigma0_by_group,
           "global_test": p.variance.test.todict() if p.variance.test else None,
           "median_point_sigma_m": p.summary().get("median_point_sigma_m"),
           "generalisation": p.summary().get("generalisation"),
           "generalisation_offsets": p.summary().get("generalisation_offsets")}
    if result.variance_components is not None:
        out["variance_components"] = result.variance_components.todict()
    return out


def markdown(workspace: Path, runs: list[dict], command: str) -> str:
    from colmap_citymodel.precision.checkpoints import format_delta_sigma

    shown = workspace.relative_to(ROOT) if workspace.is_relative_to(ROOT) else workspace
    lines = ["# Check point Delta/sigma: classical vs generalisation-aware stochastic model", "",
             "Produced by", "", f"    {command}", "",
             f"Workspace `{shown}`"
             " (simulated; check points observed in the images with 1 px noise, never assigned "
             "to planes, never control). Delta = known - estimated; sigma_CP = marginal a "
             "posteriori sigma of the check points (poses, planes, vertices and datum uncertain; "
             "check point image observations in the normal system), scaled by s0^2; the "
             "generalisation-aware sigma adds per-plane offsets (0.2 m a priori; with VCE the "
             "data's own value) and tilts (the planes' vertices each off by that much) "
             "propagated into the same estimate. RMS over the check points per axis. \"after Helmert\" uses the "
             "same sigma_CP (Unger Table 13); the extra row divides by the sigma of the Helmert "
             "residuals. Unger's ratios for Scn3a (short sequence): 6.8 / 18.9 / 8.9 before, "
             "3.7 / 4.3 / 1.1 after Helmert. Target for the generalisation-aware model: "
             "Delta/sigma in [0.5, 2] per axis.", ""]
    lines += ["## Summary", "",
              "| variant | stochastic model | RMS Delta 3D (m) | Delta/sigma X, Y, Z before "
              "Helmert | after Helmert vs sigma of the residuals |", "|---|---|---|---|---|"]
    for r in runs:
        for model, table in (r["evaluation"].get("delta_sigma_by_model") or {}).items():
            before = table["before_helmert"]
            after = table.get("after_helmert") or {}
            lines.append(
                f"| {r['variant']} | {model} | {r['evaluation']['rms_3d']:.3f} | "
                + " / ".join(f"{before[a]['ratio']:.2f}" for a in "XYZ") + " | "
                + (" / ".join(f"{after[a]['ratio_residual']:.2f}" for a in "XYZ")
                   if after and "ratio_residual" in after["X"] else "-") + " |")
    lines.append("")
    for r in runs:
        ev = r["evaluation"]
        lines += [f"## {r['variant']}: {r['description']}", "",
                  f"RMS Delta 3D {ev['rms_3d']:.3f} m, after Helmert "
                  f"{ev['rms_3d_after_helmert']:.3f} m; s0 {r['sigma0']:.3f} ("
                  + ", ".join(f"{g} {v:.3f}" for g, v in r["sigma0_by_group"].items()
                              if v is not None)
                  + f"); refine {r['seconds']:.0f} s.", ""]
        if r.get("variance_components"):
            vc = r["variance_components"]
            lines += ["Variance components: " + ", ".join(
                f"{g} {s:.4g}" for g, s in vc["sigmas"].items()) + f" (factors "
                + ", ".join(f"{g} {f:.3f}" for g, f in vc["factors"].items()
                            if abs(f - 1.0) > 1e-12)
                + f"; {len(vc['history'])} re-weighted solves, "
                f"{'converged' if vc['converged'] else 'not converged'}).", ""]
        g = r.get("generalisation") or {}
        if g.get("mode") == "consider":
            prior = g["sigma_prior_m"]
            lines += [f"Generalisation offsets per plane: a priori "
                      f"{'none' if prior is None else f'{prior:.3f} m'}, "
                      f"from the planes' mean residuals {g['sigma_estimated_m']:.3f} m; used "
                      f"{g['sigma_m']:.3f} m ({'estimated' if g['sigma_from_data'] else 'a priori'}"
                      ").", ""]
        if r.get("generalisation_offsets"):
            g = r["generalisation_offsets"]
            lines += [f"Generalisation offsets of {g['num_planes']} planes: RMS "
                      f"{g['rms_m']:.3f} m, max |o| {g['max_abs_m']:.3f} m, median sigma "
                      f"{g['median_sigma_m']:.3f} m.", ""]
        tables = ev.get("delta_sigma_by_model") or {}
        for model, table in tables.items():
            lines += [f"**{model}** stochastic model ({table['sigma_note']}):", "",
                      format_delta_sigma(table).rstrip(), ""]
        if not tables:
            lines += ["(no check point covariances)", ""]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--workspace", type=Path, help="a simulated workspace with check points")
    parser.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    parser.add_argument("--no_write", action="store_true", help="do not write results/precision.md")
    parser.add_argument("--output", type=Path, default=RESULTS / "precision.md",
                        help="markdown file to write (a .json beside it)")
    args = parser.parse_args()
    from colmap_citymodel import logger
    from colmap_citymodel.precision.checkpoints import format_delta_sigma

    logger.setLevel(logging.WARNING)
    if args.workspace is None:
        sys.path.insert(0, str(ROOT / "benchmarks"))
        from bench_refine import workspace_for

        args.workspace = workspace_for("short_scn3")
    workspace = args.workspace.resolve()
    runs = []
    for variant in args.variants:
        r = run(workspace, variant)
        runs.append(r)
        ev = r["evaluation"]
        print(f"== {variant}: {r['description']}")
        print(f"RMS Delta 3D {ev['rms_3d']:.3f} m (after Helmert {ev['rms_3d_after_helmert']:.3f}"
              f" m), s0 {r['sigma0']:.3f}, {r['seconds']:.0f} s")
        if r.get("variance_components"):
            print("variance components:", json.dumps(r["variance_components"]["sigmas"]))
        for model, table in (ev.get("delta_sigma_by_model") or {}).items():
            print(f"-- {model}")
            print(format_delta_sigma(table))
        sys.stdout.flush()
    command = ".venv/bin/python benchmarks/bench_precision.py " + " ".join(sys.argv[1:])
    if not args.no_write:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(markdown(workspace, runs, command.strip()))
        args.output.with_suffix(".json").write_text(json.dumps(runs, indent=1, default=float))
        print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
