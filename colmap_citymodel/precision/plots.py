"""Plots and an HTML report of a check point evaluation (method.md 7; Unger 5.1.3, 6.3).

- `plot_checkpoint_errors`: the horizontal check point errors as arrows in plan view, coloured
  by the height error, with a scale arrow (Unger Fig. 22);
- `plot_delta_vs_sigma`: |Delta| against the a posteriori sigma per axis, with the 1:1 line and
  the band 0.5 <= |Delta| / sigma <= 2 (points above it: sigma over-optimistic, Unger Table 12);
- `write_evaluation_report`: a new directory with `evaluation.json`, the PNGs and a
  self-contained `report.html` (PNGs embedded as base64, as refine's report).

The evaluation is the dict `precision.checkpoints.main` returns ({"evaluated": ..., "truth": ...}); a check
point's sigma is its `points[id]["sigma"]` (present only when the adjustment's covariance was
available), so every sigma plot is skipped without it. Plots use matplotlib's object API with
the Agg canvas, through precision.figures' `new_figure` / `png_bytes`.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from .figures import html_page, new_figure, png_bytes

logger = logging.getLogger(__name__)

#: The longest error arrow is drawn this fraction of the plot extent long.
ARROW_FRACTION = 0.12
#: |Delta| / sigma inside this band counts as consistent (a factor of two either way).
RATIO_BAND = (0.5, 2.0)
AXES = ("X", "Y", "Z")


def _round_length(value: float) -> float:
    """1, 2 or 5 x 10^k nearest below `value` (length of the scale arrow)."""
    if not np.isfinite(value) or value <= 0:
        return 1.0
    exponent = np.floor(np.log10(value))
    for step in (5.0, 2.0, 1.0):
        if step * 10 ** exponent <= value:
            return float(step * 10 ** exponent)
    return float(10 ** exponent)


def plot_checkpoint_errors(known_xy, errors_xyz, *, ids=None,
                           title: str = "check point errors") -> bytes:
    """Arrows from each check point's known position along its horizontal error (known minus
    estimated, exaggerated), coloured by the Z error; a scale arrow gives the exaggeration."""
    known_xy = np.asarray(known_xy, dtype=np.float64).reshape(-1, 2)
    errors = np.asarray(errors_xyz, dtype=np.float64).reshape(-1, 3)
    if len(known_xy) != len(errors) or not len(errors):
        raise ValueError("plot_checkpoint_errors needs one error per known position")
    from matplotlib.colors import Normalize

    centre = known_xy.mean(0)
    xy = known_xy - centre
    extent = max(float(np.ptp(xy[:, 0])), float(np.ptp(xy[:, 1])), 1.0)
    horizontal = np.linalg.norm(errors[:, :2], axis=1)
    longest = max(float(horizontal.max()), 1e-6)
    exaggeration = ARROW_FRACTION * extent / longest
    key = _round_length(longest)
    z_limit = max(float(np.abs(errors[:, 2]).max()), 1e-6)

    pad = 0.08 * extent + ARROW_FRACTION * extent
    x_range = (xy[:, 0].min() - pad, xy[:, 0].max() + pad)
    y_range = (xy[:, 1].min() - pad, xy[:, 1].max() + pad)
    # The figure follows the points' extent (a strip along a street is wide and low).
    aspect = (x_range[1] - x_range[0]) / (y_range[1] - y_range[0])
    width = 10.0
    height = float(np.clip(0.78 * width / aspect + 1.6, 3.8, 10.0))
    figure = new_figure(width, height)
    figure.subplots_adjust(left=0.08, right=0.95, bottom=1.0 / height, top=1 - 0.75 / height)
    ax = figure.add_subplot(1, 1, 1)
    arrows = ax.quiver(xy[:, 0], xy[:, 1], errors[:, 0], errors[:, 1], errors[:, 2],
                       cmap="coolwarm", norm=Normalize(-z_limit, z_limit), angles="xy",
                       scale_units="xy", scale=1.0 / exaggeration, width=0.003, zorder=3)
    ax.scatter(xy[:, 0], xy[:, 1], s=8, c="k", zorder=4)
    if ids is not None:
        for (x, y), label in zip(xy, ids):
            ax.annotate(str(label), (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.quiverkey(arrows, 0.04, 0.06, key, f"{key:g} m (arrows x{exaggeration:.0f})",
                 labelpos="E", coordinates="axes", fontproperties={"size": 8}, color="k")
    ax.set_xlim(*x_range)
    ax.set_ylim(*y_range)
    ax.set_aspect("equal")
    ax.set_xlabel(f"X - {centre[0]:.0f} (m)", fontsize=8)
    ax.set_ylabel(f"Y - {centre[1]:.0f} (m)", fontsize=8)
    ax.tick_params(labelsize=7)
    rms = np.sqrt(np.mean(errors ** 2, axis=0))
    ax.set_title(f"{title}\n{len(errors)} points, RMS X {rms[0]:.3f}, Y {rms[1]:.3f}, "
                 f"Z {rms[2]:.3f} m", fontsize=9)
    bar = figure.colorbar(arrows, ax=ax, shrink=0.8)
    bar.set_label("Z error, known - estimated (m)", fontsize=8)
    return png_bytes(figure)


def plot_delta_vs_sigma(delta_xyz, sigma_xyz, *, title: str = "|Delta| vs sigma") -> bytes:
    """Per axis |Delta| over sigma (log-log) with the 1:1 line and the [0.5, 2] band; the
    panel title gives RMS |Delta| / RMS sigma (Unger Table 12) and the share inside the band."""
    delta = np.abs(np.asarray(delta_xyz, dtype=np.float64).reshape(-1, 3))
    sigma = np.asarray(sigma_xyz, dtype=np.float64).reshape(-1, 3)
    if len(delta) != len(sigma):
        raise ValueError("plot_delta_vs_sigma needs one sigma per Delta")
    usable = np.isfinite(sigma).all(1) & (sigma > 0).all(1) & np.isfinite(delta).all(1)
    if not usable.any():
        raise ValueError("plot_delta_vs_sigma needs at least one finite, positive sigma")
    delta, sigma = delta[usable], sigma[usable]
    # |Delta| near zero is common (|N(0, sigma)|): the axes start a little below the smallest
    # sigma or the 10th percentile of |Delta|, smaller |Delta| are drawn on the lower edge.
    hi = max(float(sigma.max()), float(delta.max()), 1e-12) * 2
    lo = max(min(float(sigma.min()), float(np.percentile(delta, 10))) / 3, 1e-6 * hi)
    floor = lo * 1.05
    line = np.array([lo, hi])
    figure = new_figure(14, 4.8)
    figure.subplots_adjust(left=0.06, right=0.98, bottom=0.13, top=0.82, wspace=0.3)
    for k, axis in enumerate(AXES):
        ax = figure.add_subplot(1, 3, k + 1)
        ax.fill_between(line, RATIO_BAND[0] * line, RATIO_BAND[1] * line, color="0.88",
                        label=f"{RATIO_BAND[0]:g} <= |Delta|/sigma <= {RATIO_BAND[1]:g}")
        ax.plot(line, line, "k-", lw=0.8, label="|Delta| = sigma")
        ax.scatter(sigma[:, k], np.maximum(delta[:, k], floor), s=14, c="C3", zorder=3)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_aspect("equal")
        ratio = np.sqrt(np.mean(delta[:, k] ** 2)) / np.sqrt(np.mean(sigma[:, k] ** 2))
        inside = np.mean((delta[:, k] >= RATIO_BAND[0] * sigma[:, k])
                         & (delta[:, k] <= RATIO_BAND[1] * sigma[:, k]))
        ax.set_title(f"{axis}: RMS|Delta| / RMS sigma = {ratio:.2f}, {100 * inside:.0f}% in band",
                     fontsize=9)
        ax.set_xlabel(f"sigma {axis} (m)", fontsize=8)
        ax.set_ylabel(f"|Delta {axis}| (m)", fontsize=8)
        ax.tick_params(labelsize=7)
        if k == 0:
            ax.legend(fontsize=7, loc="upper left")
    figure.suptitle(f"{title} ({len(delta)} check points)", fontsize=10)
    return png_bytes(figure)


# -- the evaluation dict -------------------------------------------------------------------------

def _point_arrays(block: dict) -> tuple[list[str], np.ndarray, np.ndarray | None]:
    """ids, errors (N, 3) and sigmas (N, 3) or None from one evaluation block."""
    points = block.get("points") or {}
    ids = list(points)
    errors = np.array([points[i]["error"] for i in ids], dtype=np.float64).reshape(-1, 3)
    sigmas = None
    if ids and all("sigma" in points[i] for i in ids):
        sigmas = np.array([[np.nan if v is None else v for v in points[i]["sigma"]]
                           for i in ids], dtype=np.float64).reshape(-1, 3)
        if not np.isfinite(sigmas).all(1).any():
            sigmas = None
    return ids, errors, sigmas


def evaluation_plots(evaluation: dict, known: dict | None = None) -> dict[str, bytes]:
    """The plots of an `precision.checkpoints.main` result: error arrows of the evaluated model (and of the
    truth poses, if evaluated) when the known coordinates are given, |Delta| vs sigma when the
    check points have sigmas. `known`: id -> (3,) known coordinates (checkpoints.read_checkpoints)."""
    plots: dict[str, bytes] = {}
    blocks = [("evaluated", "evaluated model")]
    if evaluation.get("truth"):
        blocks.append(("truth", "truth poses"))
    for key, label in blocks:
        ids, errors, sigmas = _point_arrays(evaluation[key])
        if not ids:
            continue
        if known is not None and all(i in known for i in ids):
            xy = np.array([np.asarray(known[i], float)[:2] for i in ids])
            plots[f"check point errors, {label} (Unger Fig. 22)"] = plot_checkpoint_errors(
                xy, errors, ids=ids, title=f"check point errors, {label}")
        if sigmas is not None:
            plots[f"|Delta| vs sigma, {label} (Unger Table 12)"] = plot_delta_vs_sigma(
                errors, sigmas, title=f"|Delta| vs a posteriori sigma, {label}")
    return plots


def evaluation_markdown(evaluation: dict) -> str:
    """RMS, Helmert, the Delta/sigma table (if any) and the per point errors as Markdown."""
    from .checkpoints import format_delta_sigma

    lines = ["# Check point evaluation", ""]
    for key, label in (("evaluated", "Evaluated model"), ("truth", "Truth poses")):
        block = evaluation.get(key)
        if not block:
            continue
        lines += [f"## {label}", "",
                  f"{block['num_checkpoints']} check points ({block.get('frame', '?')} frame), "
                  f"{len(block.get('missing', []))} not triangulated.", "",
                  "| RMS X (m) | RMS Y (m) | RMS Z (m) | RMS 3D (m) | RMS 3D after Helmert (m) |",
                  "|---|---|---|---|---|",
                  f"| {block['rms_x']:.3f} | {block['rms_y']:.3f} | {block['rms_z']:.3f} | "
                  f"{block['rms_3d']:.3f} | {block['rms_3d_after_helmert']:.3f} |"]
        h = block.get("helmert")
        if h:
            lines += ["", f"Helmert: t = ({h['tx']:.3f}, {h['ty']:.3f}, {h['tz']:.3f}) m, "
                      f"omega {h['omega_deg']:.4f}, phi {h['phi_deg']:.4f}, kappa "
                      f"{h['kappa_deg']:.4f} deg, scale {h['scale_ppm']:.1f} ppm."]
        if block.get("delta_sigma"):
            table = block["delta_sigma"]
            lines += ["", format_delta_sigma(
                table, f"Delta/sigma ({table.get('sigma_note') or 'sigma from the adjustment'}):"
            ).rstrip()]
        ids, errors, sigmas = _point_arrays(block)
        points = block["points"]
        lines += ["", "| id | dX (m) | dY (m) | dZ (m) | views | rms px |"
                  + (" sigma X | sigma Y | sigma Z |" if sigmas is not None else ""),
                  "|---|---|---|---|---|---|" + ("---|---|---|" if sigmas is not None else "")]
        for k, pid in enumerate(ids):
            rms_px = points[pid].get("rms_px", float("nan"))
            row = (f"| {pid} | " + " | ".join(f"{v:+.3f}" for v in errors[k])
                   + f" | {points[pid].get('views', '')} | {rms_px:.2f} |")
            if sigmas is not None:
                row += " " + " | ".join(f"{v:.4f}" for v in sigmas[k]) + " |"
            lines.append(row)
        lines.append("")
    return "\n".join(lines)


def evaluation_html(evaluation: dict, plots: dict[str, bytes],
                    title: str = "colmap-citymodel check point evaluation") -> str:
    """A self-contained page: the PNGs inline (base64) and the Markdown summary."""
    return html_page(title, plots, evaluation_markdown(evaluation))


def plot_file_name(index: int, name: str) -> str:
    slug = "".join(c if c.isalnum() else "_" for c in name.split(" (")[0]).strip("_")
    while "__" in slug:
        slug = slug.replace("__", "_")
    return f"{index}_{slug}.png"


def write_evaluation_report(directory, evaluation: dict, plots: dict[str, bytes]) -> Path:
    """New directory `directory` (atomic): evaluation.json, evaluation.md, the PNGs under
    plots/ and report.html with the same PNGs embedded."""
    from ..files import atomic_directory

    directory = Path(directory)
    with atomic_directory(directory) as tmp:
        (tmp / "evaluation.json").write_text(json.dumps(evaluation, indent=2, default=_json))
        (tmp / "evaluation.md").write_text(evaluation_markdown(evaluation))
        if plots:
            (tmp / "plots").mkdir()
            for k, (name, png) in enumerate(plots.items()):
                (tmp / "plots" / plot_file_name(k, name)).write_bytes(png)
        (tmp / "report.html").write_text(evaluation_html(evaluation, plots))
    logger.info("wrote the check point report to %s", directory)
    return directory


def write_evaluate_outputs(output_path, evaluation: dict, checkpoints=None) -> Path:
    """What `colmap-citymodel evaluate --output_path` writes: the plots of `evaluation` (the
    known coordinates for the arrow plots from the `checkpoints` file, if given) and the
    report (`write_evaluation_report`)."""
    known = checkpoints if isinstance(checkpoints, dict) else None
    if checkpoints is not None and known is None:
        from .checkpoints import read_checkpoints

        known = read_checkpoints(checkpoints)
    return write_evaluation_report(output_path, evaluation, evaluation_plots(evaluation, known))


def _json(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)
