"""The precision outputs people look at: per-image CSV, tie point sigmas as PLY scalars, plots
and a self-contained HTML report next to `report.json`.

- `image_precision.csv`: per image X0, Y0, Z0 (CRS or local, as the model output) and omega,
  phi, kappa with their a posteriori sigmas (scaled by s0^2);
- `image_covariance.csv`: per image the full 6 x 6 covariance of X0, Y0, Z0 (m) and omega, phi,
  kappa (rad), its 21 upper-triangle entries c00 c01 ... c55 (read by `dense-quality`);
- `point_precision.ply`: tie points coloured by their 3D sigma, scalar fields sigma_x/y/z
  (marginal) and sigma_x/y/z_conditional (poses, planes, vertices held fixed), num_images;
- `report.html` with embedded PNGs (also written to `plots/`): residual histograms per plane
  (Unger Fig. 17), a plan-view tie point sigma map (Mulder Fig. 5.5), image sigmas along the
  flight, and with check points (refine --checkpoints) their error arrows (Unger Fig. 22),
  |Delta| vs sigma and the Delta/sigma tables (Unger Tables 12/13);
- with check points: report.json `checkpoints` (checkpoints.CheckpointEvaluation.todict: RMS,
  Helmert, per point Delta and sigma, `delta_sigma_by_model` with per-axis RMS of Delta, RMS of
  sigma and their ratio before and after Helmert), `checkpoint_precision.csv` and
  `checkpoint_precision.json` (the joint covariances, read by `colmap-citymodel evaluate`);
- with sigma_generalisation: the generalisation-aware sigmas beside the classical ones
  (`*_aware` columns / scalar fields).

Plots use matplotlib's object API with the Agg canvas (no display, no pyplot state).
"""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np

from .estimate import PrecisionResult
from .figures import new_figure, png_bytes

logger = logging.getLogger(__name__)

#: At most this many planes get their own residual histogram (the ones with most points).
MAX_PLANE_HISTOGRAMS = 11

CSV_COLUMNS = ("image_id", "name", "X0", "Y0", "Z0", "omega_deg", "phi_deg", "kappa_deg",
               "sigma_X0_m", "sigma_Y0_m", "sigma_Z0_m", "sigma_omega_deg", "sigma_phi_deg",
               "sigma_kappa_deg", "num_points3D")
#: Appended with sigma_generalisation: the generalisation-aware sigmas of the centres.
AWARE_CSV_COLUMNS = ("sigma_X0_aware_m", "sigma_Y0_aware_m", "sigma_Z0_aware_m")
CHECKPOINT_CSV_COLUMNS = ("id", "X", "Y", "Z", "dX", "dY", "dZ", "views")


# -- files ---------------------------------------------------------------------------------------

def write_image_csv(path: Path, precision: PrecisionResult, offset: np.ndarray) -> None:
    sigma = precision.image_sigmas
    aware = precision.aware_sigmas("image_cov")
    if aware is not None:
        aware = aware[:, :3]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CSV_COLUMNS + (AWARE_CSV_COLUMNS if aware is not None else ()))
        for k, image_id in enumerate(precision.image_ids):
            centre = precision.centres[k] + offset
            writer.writerow([int(image_id), precision.image_names[k]]
                            + [f"{v:.4f}" for v in centre]
                            + [f"{v:.6f}" for v in precision.angles_deg[k]]
                            + [f"{v:.5f}" for v in sigma[k, :3]]
                            + [f"{v:.6f}" for v in sigma[k, 3:]]
                            + [int(precision.image_num_observations[k])]
                            + ([f"{v:.5f}" for v in aware[k]] if aware is not None else []))


def write_image_covariance_csv(path: Path, precision: PrecisionResult) -> None:
    upper = np.triu_indices(6)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["image_id", "name"] + [f"c{i}{j}" for i, j in zip(*upper)])
        for k, image_id in enumerate(precision.image_ids):
            writer.writerow([int(image_id), precision.image_names[k]]
                            + [f"{v:.6e}" for v in precision.image_cov[k][upper]])


def sigma_colours(values: np.ndarray) -> np.ndarray:
    """uint8 RGB of a viridis ramp between the 2nd and 98th percentile of `values`."""
    from matplotlib import colormaps

    if not len(values):
        return np.zeros((0, 3), np.uint8)
    lo, hi = np.percentile(values, [2, 98])
    t = np.clip((values - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return (colormaps["viridis"](t)[:, :3] * 255).astype(np.uint8)


def write_point_ply(path: Path, precision: PrecisionResult, offset: np.ndarray,
                    num_images: np.ndarray | None = None) -> None:
    from ..files import write_point_ply as write_ply

    sigma = precision.point_sigmas
    conditional = precision.point_sigmas_conditional
    scalars = {f"sigma_{a}": sigma[:, i].astype(np.float32) for i, a in enumerate("xyz")}
    scalars.update({f"sigma_{a}_conditional": conditional[:, i].astype(np.float32)
                    for i, a in enumerate("xyz")})
    scalars["sigma_3d"] = np.linalg.norm(sigma, axis=1).astype(np.float32)
    aware = precision.aware_sigmas("point_cov")
    if aware is not None:
        scalars.update({f"sigma_{a}_aware": aware[:, i].astype(np.float32)
                        for i, a in enumerate("xyz")})
    if num_images is not None:
        scalars["num_images"] = num_images.astype(np.float32)
    write_ply(path, precision.points + offset, sigma_colours(scalars["sigma_3d"]), scalars)


# -- plots ---------------------------------------------------------------------------------------


def plot_plane_histograms(residuals: dict[int, np.ndarray], labels: dict[int, str] | None = None
                          ) -> bytes | None:
    """Histograms of tie point -> plane distances per plane, like Unger Fig. 17."""
    if not residuals:
        return None
    labels = labels or {}
    order = sorted(residuals, key=lambda f: -len(residuals[f]))[:MAX_PLANE_HISTOGRAMS]
    panels = [("all planes", np.concatenate(list(residuals.values())))] + [
        (labels.get(f, f"face {f}"), residuals[f]) for f in order]
    columns = 4
    rows = int(np.ceil(len(panels) / columns))
    figure = new_figure(3.2 * columns, 2.4 * rows)
    everything = panels[0][1]
    limit = max(float(np.percentile(np.abs(everything), 99)), 1e-3)
    bins = np.linspace(-limit, limit, 31)
    for k, (title, d) in enumerate(panels):
        ax = figure.add_subplot(rows, columns, k + 1)
        ax.hist(np.clip(d, -limit, limit), bins=bins, color="C0" if k else "C1")
        ax.axvline(0.0, color="k", lw=0.6)
        ax.set_title(f"{title}\nn {len(d)}, mean {np.mean(d):+.3f}, std {np.std(d):.3f} m",
                     fontsize=8)
        ax.tick_params(labelsize=7)
        if k >= len(panels) - columns:
            ax.set_xlabel("distance to plane (m)", fontsize=8)
    return png_bytes(figure)


def plot_point_sigma_map(precision: PrecisionResult, offset: np.ndarray) -> bytes | None:
    """Plan view of the tie points coloured by sigma X, Y, Z (Mulder Fig. 5.5), with cameras;
    the generalisation-aware sigmas where refine gives them."""
    if not len(precision.point_ids):
        return None
    figure = new_figure(15, 4.6)
    xy = precision.points[:, :2] - precision.points[:, :2].mean(0)
    centres = precision.centres[:, :2] - precision.points[:, :2].mean(0)
    aware_sigmas = precision.aware_sigmas("point_cov")
    aware = aware_sigmas is not None
    sigma = (aware_sigmas if aware else precision.point_sigmas) * 100.0
    for i, axis in enumerate("XYZ"):
        ax = figure.add_subplot(1, 3, i + 1)
        hi = float(np.percentile(sigma[:, i], 98))
        scatter = ax.scatter(xy[:, 0], xy[:, 1], c=sigma[:, i], s=3, cmap="viridis", vmin=0,
                             vmax=max(hi, 1e-6))
        if len(centres):
            ax.plot(centres[:, 0], centres[:, 1], "r.", ms=3, label="cameras")
        ax.set_aspect("equal")
        ax.set_title(f"tie point sigma {axis} (cm{', aware' if aware else ''}), "
                     f"median {np.median(sigma[:, i]):.2f}", fontsize=9)
        ax.set_xlabel("X - mean (m)", fontsize=8)
        ax.set_ylabel("Y - mean (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        figure.colorbar(scatter, ax=ax, shrink=0.8)
    return png_bytes(figure)


def plot_image_sigmas(precision: PrecisionResult) -> bytes | None:
    """Sigma of X0, Y0, Z0 and omega, phi, kappa per image, in image order; with the
    generalisation-aware model, its centre sigmas solid and the classical ones dashed."""
    if not len(precision.image_ids):
        return None
    order = np.argsort(precision.image_names)
    sigma = precision.image_sigmas[order]
    aware = precision.aware_sigmas("image_cov")
    if aware is not None:
        aware = aware[order]
    figure = new_figure(12, 4)
    ax = figure.add_subplot(1, 2, 1)
    for i, axis in enumerate(("X0", "Y0", "Z0")):
        if aware is None:
            ax.plot(sigma[:, i] * 100.0, ".-", ms=3, lw=0.6, label=axis)
            continue
        line, = ax.plot(aware[:, i] * 100.0, ".-", ms=3, lw=0.8, label=f"{axis}")
        ax.plot(sigma[:, i] * 100.0, "--", lw=0.6, color=line.get_color(),
                label=f"{axis} classical")
    ax.set_ylabel("sigma (cm)")
    ax.set_xlabel("image (sorted by name)")
    ax.legend(fontsize=8)
    ax.set_title("projection centres" + (" (solid: with the model's generalisation error; "
                                         "dashed: classical)" if aware is not None else ""),
                 fontsize=9)
    ax = figure.add_subplot(1, 2, 2)
    for i, axis in enumerate(("omega", "phi", "kappa")):
        ax.plot(sigma[:, 3 + i] * 3600.0, ".-", ms=3, lw=0.6, label=axis)
    ax.set_ylabel("sigma (arc seconds)")
    ax.set_xlabel("image (sorted by name)")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.set_title("rotations", fontsize=9)
    return png_bytes(figure)


# -- report text ---------------------------------------------------------------------------------

def precision_report_dict(precision: PrecisionResult) -> dict:
    """The keys report.json gains: sigma0, sigma0_by_group, global_test, precision."""
    summary = precision.summary()
    return {"sigma0": summary["sigma0"], "sigma0_by_group": summary["sigma0_by_group"],
            "global_test": summary["global_test"], "precision": summary}


def _fmt(value, spec: str = ".4f") -> str:
    return "-" if value is None else format(value, spec)


def precision_markdown(report: dict) -> str:
    p = report.get("precision")
    if not p:
        return ""
    lines = ["", "## A posteriori precision", "",
             f"s0 = {p['sigma0']:.4f} (redundancy {p['redundancy']:.1f}, group redundancies "
             f"from {p['redundancy_method'].replace('_', ' ')}).", "",
             "| group | observations | redundancy | v'Pv | s0 |", "|---|---|---|---|---|"]
    for g, s0 in p["sigma0_by_group"].items():
        lines.append(f"| {g} | {p['count_by_group'][g]} | {p['redundancy_by_group'][g]:.1f} | "
                     f"{p['vtpv_by_group'][g]:.2f} | {_fmt(s0)} |")
    t = p.get("global_test")
    if t:
        lines += ["", f"Global test (two-sided chi-square, alpha {t['alpha']}): T = "
                  f"{t['statistic']:.1f}, r = {t['redundancy']:.1f}, acceptance interval "
                  f"[{t['acceptance_interval'][0]:.1f}, {t['acceptance_interval'][1]:.1f}], "
                  f"p = {t['p_value']:.3g}: **{'accepted' if t['accepted'] else 'rejected'}**."]
    if p.get("covariances"):
        m, mp, mc = p["median_image_sigma"], p["median_point_sigma_m"], \
            p["median_point_sigma_conditional_m"]
        lines += ["", "Median a posteriori sigmas (scaled by s0^2):", "",
                  f"- projection centres X0/Y0/Z0: {m['X0_m'] * 100:.2f} / {m['Y0_m'] * 100:.2f}"
                  f" / {m['Z0_m'] * 100:.2f} cm; omega/phi/kappa: {m['omega_deg'] * 3600:.1f} / "
                  f"{m['phi_deg'] * 3600:.1f} / {m['kappa_deg'] * 3600:.1f} arc seconds",
                  f"- tie points X/Y/Z (marginal): {mp['X'] * 100:.2f} / {mp['Y'] * 100:.2f} / "
                  f"{mp['Z'] * 100:.2f} cm",
                  f"- tie points X/Y/Z (conditional on poses, planes, vertices): "
                  f"{mc['X'] * 100:.2f} / {mc['Y'] * 100:.2f} / {mc['Z'] * 100:.2f} cm",
                  "", "Per image: `image_precision.csv`; per tie point: `point_precision.ply`; "
                  "plots: `report.html`."]
        g = p.get("generalisation") or {}
        if g.get("mode") == "consider":
            gi, gp = g.get("median_image_sigma_m"), g.get("median_point_sigma_m")
            source = ("estimated from the planes' mean f_dTP residuals" if g.get("sigma_from_data")
                      else f"a priori; the planes' mean f_dTP residuals say "
                           f"{g.get('sigma_estimated_m') or 0.0:.3f} m")
            lines += ["", f"Generalisation-aware (per-plane offsets of {g['sigma_m']:.3f} m, "
                      f"{source}, and the tilts of planes whose vertices are that far off, "
                      "shared by each plane's f_dTP and propagated into the estimate; the "
                      "`*_aware` columns and fields):"]
            if gi:
                lines.append(f"- projection centres X0/Y0/Z0: {gi['X0'] * 100:.2f} / "
                             f"{gi['Y0'] * 100:.2f} / {gi['Z0'] * 100:.2f} cm")
            if gp:
                lines.append(f"- tie points X/Y/Z: {gp['X'] * 100:.2f} / {gp['Y'] * 100:.2f} / "
                             f"{gp['Z'] * 100:.2f} cm")
    else:
        lines += ["", "Covariances were not computed (precision.covariances / --precision)."]
    return "\n".join(lines) + "\n"


# -- check points ---------------------------------------------------------------------------------

def write_checkpoint_csv(path: Path, evaluation) -> None:
    """Per check point: estimated coordinates (model CRS), Delta = known - estimated, views and
    the sigmas of each stochastic model."""
    models = list(evaluation.covariances)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(CHECKPOINT_CSV_COLUMNS + tuple(
            f"sigma_{a}_{m}_m" for m in models for a in "XYZ"))
        sigmas = {m: evaluation.sigmas_of(m) for m in models}
        for k, pid in enumerate(evaluation.ids):
            writer.writerow([pid] + [f"{v:.4f}" for v in evaluation.estimated[k]]
                            + [f"{v:.4f}" for v in evaluation.errors[k]]
                            + [int(evaluation.num_views.get(pid, 0))]
                            + [f"{v:.5f}" for m in models for v in sigmas[m][k]])


def checkpoint_markdown(report: dict) -> str:
    """The report.md section of the check points: RMS, Helmert, Delta/sigma per model."""
    from .accuracy import accuracy_markdown
    from .checkpoints import format_delta_sigma

    c = report.get("checkpoints")
    if not c:
        return ""
    lines = ["", "## Check points", "",
             f"{c['num_checkpoints']} check points (never assigned to planes, never control), "
             f"{len(c.get('missing', []))} not triangulated. RMS of Delta = known - estimated: "
             f"X {c['rms_x']:.3f}, Y {c['rms_y']:.3f}, Z {c['rms_z']:.3f}, 3D {c['rms_3d']:.3f} m; "
             f"after the Helmert transform {c['rms_3d_after_helmert']:.3f} m."]
    for model, table in (c.get("delta_sigma_by_model") or {}).items():
        if table:
            lines += ["", format_delta_sigma(
                table, f"Delta/sigma, {model.replace('_', ' ')} stochastic model (Unger Tables "
                       f"12/13; {table.get('sigma_note', '')}):").rstrip()]
    if not c.get("delta_sigma_by_model"):
        lines += ["", "No check point sigma (covariances were not computed)."]
    lines += ["", "Per check point: `checkpoint_precision.csv`."]
    lines += [accuracy_markdown(c).rstrip()] if c.get("marks") else []
    vc = report.get("variance_components")
    if vc:
        lines += ["", "Variance components (iterated, re-weighted final solve): " + ", ".join(
            f"{g} {v:.4g}" for g, v in vc["sigmas"].items()) + (
            "" if vc["converged"] else " (not converged)") + "."]
    return "\n".join(lines) + "\n"


def checkpoint_plots(evaluation) -> dict[str, bytes]:
    """Error arrows (Unger Fig. 22) and |Delta| vs sigma of refine's check points, drawn by
    precision.plots when it is available."""
    try:
        from .plots import plot_checkpoint_errors, plot_delta_vs_sigma
    except ImportError:  # pragma: no cover - plots are optional for the report
        return {}
    plots = {}
    if len(evaluation.ids) >= 1:
        plots["check point errors (Unger Fig. 22)"] = plot_checkpoint_errors(
            evaluation.known[:, :2], evaluation.errors, ids=list(evaluation.ids),
            title="check point errors")
    model = evaluation.primary_model
    sigmas = evaluation.sigmas_of(model) if model else None
    if sigmas is not None and np.isfinite(sigmas).all(1).any():
        have = np.isfinite(sigmas).all(1)
        plots[f"|Delta| vs sigma, {model.replace('_', ' ')} (Unger Table 12)"] = \
            plot_delta_vs_sigma(evaluation.errors[have], sigmas[have],
                                title=f"|Delta| vs sigma, {model.replace('_', ' ')}")
    return plots


# -- refine's outputs ----------------------------------------------------------------------------

def refine_plots(result, offset: np.ndarray) -> dict[str, bytes]:
    plots: dict[str, bytes | None] = {}
    faces = result.store.faces
    labels = {f: f"{faces[f].semantic} {faces[f].building_id}" for f in result.plane_faces}
    plots["residuals per plane (Unger Fig. 17)"] = plot_plane_histograms(
        result.plane_residuals(), labels)
    precision = result.precision
    if precision is not None and precision.has_covariances:
        plots["tie point sigma map (Mulder Fig. 5.5)"] = plot_point_sigma_map(precision, offset)
        plots["image sigmas"] = plot_image_sigmas(precision)
    evaluation = getattr(result, "checkpoints", None)
    if evaluation is not None and len(evaluation.ids):
        plots.update(checkpoint_plots(evaluation))
    return {k: v for k, v in plots.items() if v is not None}


def write_precision_outputs(result, directory: Path, report: dict, offset: np.ndarray
                            ) -> tuple[str, dict[str, bytes]]:
    """Add the precision keys to `report`, write the CSV, the PLY and the plots into
    `directory`; return the markdown section and the plots (name -> PNG) for the page."""
    precision: PrecisionResult | None = result.precision
    if precision is not None:
        report.update(precision_report_dict(precision))
        if precision.has_covariances:
            write_image_csv(directory / "image_precision.csv", precision, offset)
            write_image_covariance_csv(directory / "image_covariance.csv", precision)
            rec = result.reconstruction
            num_images = np.array([rec.point3D(int(i)).track.length()
                                   for i in precision.point_ids])
            write_point_ply(directory / "point_precision.ply", precision, offset, num_images)
    if getattr(result, "variance_components", None) is not None:
        report["variance_components"] = result.variance_components.todict()
    evaluation = getattr(result, "checkpoints", None)
    if evaluation is not None:
        from .checkpoints import CHECKPOINT_PRECISION_FILE, write_checkpoint_precision

        report["checkpoints"] = evaluation.todict()
        write_checkpoint_csv(directory / "checkpoint_precision.csv", evaluation)
        if evaluation.covariances:
            write_checkpoint_precision(directory / CHECKPOINT_PRECISION_FILE, evaluation)
    plots = refine_plots(result, offset)
    if plots:
        (directory / "plots").mkdir(exist_ok=True)
        for k, (name, png) in enumerate(plots.items()):
            slug = "".join(c if c.isalnum() else "_" for c in name.split(" (")[0]).strip("_")
            (directory / "plots" / f"{k}_{slug}.png").write_bytes(png)
    return precision_markdown(report) + checkpoint_markdown(report), plots
