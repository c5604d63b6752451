"""Writing the refine result: a georeferenced COLMAP model and the files people look at.

Everything goes into a temporary directory beside `output_path` that is renamed into place at
the end, so a failed run leaves nothing half-written and never touches the inputs.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np
import pycolmap

from ..adjust.record import cameras_settled
from ..citymodel.ground_faces import terrain_mask
from ..errors import InputError
from ..files import atomic_directory, write_point_ply
from ..precision.figures import html_page
from ..precision.report import write_precision_outputs
from .result import RefineResult

logger = logging.getLogger(__name__)

UNASSIGNED_GREY = (160, 160, 160)
TERRAIN_BROWN = (150, 105, 60)


def face_colours(num_faces: int) -> np.ndarray:
    """A fixed, well-spread colour per face index (same colours in every run)."""
    golden = 0.618033988749895
    hue = (np.arange(num_faces) * golden) % 1.0
    import colorsys

    return (np.array([colorsys.hsv_to_rgb(h, 0.75, 0.95) for h in hue]).reshape(-1, 3)
            * 255).astype(np.uint8)


def write_assignments_ply(result: RefineResult, path: Path, offset: np.ndarray) -> None:
    a = result.assignment
    xyz = np.array([result.reconstruction.point3D(int(i)).xyz for i in a.point_ids]).reshape(-1, 3)
    colours = np.tile(np.array(UNASSIGNED_GREY, np.uint8), (len(xyz), 1))
    palette = face_colours(len(result.store.faces))
    colours[a.assigned] = palette[a.face_index[a.assigned]]
    ground = a.assigned & terrain_mask(result.store)[np.maximum(a.face_index, 0)]
    colours[ground] = TERRAIN_BROWN  # ground tie points on the terrain faces
    write_point_ply(path, xyz + offset, colours,
                    {"face": a.face_index.astype(np.float32),
                     "distance": np.nan_to_num(a.distance, nan=-1.0).astype(np.float32)})


def sim3_dict(sim3: pycolmap.Sim3d) -> dict:
    return {"scale": float(sim3.scale),
            "rotation_xyzw": [float(v) for v in sim3.rotation.quat],
            "translation": [float(v) for v in sim3.translation],
            "matrix": np.asarray(sim3.matrix()).tolist()}


def georeference_dict(result: RefineResult, output_frame: str) -> dict:
    crs = result.store.crs
    origin = result.origin
    to_crs = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), origin) * result.input_to_local
    return {
        "crs": {"label": crs.label, "horizontal_epsg": crs.horizontal_epsg,
                "vertical_epsg": crs.vertical_epsg, "wkt": crs.wkt},
        "origin": [float(v) for v in origin],
        "output_frame": output_frame,
        "note": ("model coordinates are CRS coordinates" if output_frame == "crs" else
                 "model coordinates are CRS coordinates minus origin"),
        "result": result.handed_back,
        "result_note": ("the refined block" if result.handed_back == "refined" else
                        f"the GNSS-only adjustment (verdict {result.quality.verdict}: "
                        + "; ".join(result.quality.reasons) + ")"),
        "input_to_local_sim3": sim3_dict(result.input_to_local),
        "input_to_crs_sim3": sim3_dict(to_crs),
        "options": result.options.todict(),
    }


def plane_table(result: RefineResult) -> list[dict]:
    faces = result.store.faces
    rows = []
    for face, d in sorted(result.plane_residuals().items()):
        rows.append({"face": face, "gml_id": faces[face].gml_id,
                     "semantic": faces[face].semantic, "building_id": faces[face].building_id,
                     "num_points": int(len(d)), "mean_m": float(np.mean(d)),
                     "std_m": float(np.std(d)), "rms_m": float(np.sqrt(np.mean(d ** 2)))})
    return rows


#: Why a face near the block took no tie points though a camera could have seen it.
HIDDEN_REASON = "inside the city's volume: solid on both sides (a wall shared with another solid)"


def face_table(result: RefineResult) -> list[dict]:
    """report.json `faces`: each face that held tie points, as one observation of its offset:
    its points, their mean signed distance from the adjusted plane (`offset_m`), the sigma of
    that offset in the adjustment (`sigma_m`: sqrt(sigma_face^2 + sigma_dtp^2 / points), times
    the face's outlier factor), and "kept" or "downweighted" (adjust.faces); then the faces the
    face test dropped and the faces near the block that lie inside the city's volume, "dropped"
    (adjust.faces.snooped_faces, citymodel.visibility)."""
    from ..adjust.faces import FACE_HUBER_K, sigma_face_in_use
    from ..citymodel.visibility import visibility

    o = result.options.adjustment
    store, factors = result.store, result.assignment.face_factors
    sigma_face = sigma_face_in_use(o, result.assignment.face_sigma)
    rows = []
    for face, d in sorted(result.plane_residuals().items()):
        factor = factors.get(face, 1.0)
        sigma = float(np.sqrt(sigma_face ** 2 + o.sigma_dtp ** 2 / len(d)) * factor)
        row = {"face": face, "id": store.faces[face].gml_id, "points": int(len(d)),
               "offset_m": float(np.mean(d)), "sigma_m": sigma,
               "status": "downweighted" if factor > 1 else "kept"}
        if factor > 1:
            row["why"] = (f"its points' mean offset lies {factor ** 2 * FACE_HUBER_K:.1f} sigma "
                          "from the model, beyond its generalisation error")
        rows.append(row)
    for face, z in sorted(result.assignment.dropped_faces.items()):
        rows.append({"face": int(face), "id": store.faces[int(face)].gml_id, "points": 0,
                     "status": "dropped",
                     "why": f"the other faces place its points {z:.1f} sigma from it, beyond "
                            "its generalisation error (face test, alpha "
                            f"{o.face_test_alpha:g})"})
    vis = visibility(store)
    for face in np.flatnonzero(vis.hidden):
        rows.append({"face": int(face), "id": store.faces[int(face)].gml_id, "points": 0,
                     "status": "dropped", "why": HIDDEN_REASON})
    return rows


def report_dict(result: RefineResult, inputs: dict | None = None) -> dict:
    last = result.iterations[-1] if result.iterations else None
    return {
        "inputs": inputs or {},
        "georegistration": {"rms_m": result.georegistration_rms,
                            "sim3": sim3_dict(result.input_to_local),
                            **(result.georegistration or {})},
        "step2": {**(result.step2.todict() if result.step2 else {}),
                  "eliminated_image_observations": result.step2_eliminated},
        "iterations": [it.todict() for it in result.iterations],
        "converged": bool(last and (
            result.loop_stopped_by not in (None, "diverged")
            or last.relative_change < result.options.workflow.convergence_rms_change
            or cameras_settled(result.iterations,
                               result.options.workflow.convergence_camera_shift))),
        "stopped_by": result.loop_stopped_by,
        "sigma0": float(np.sqrt(last.final.sigma0_squared)) if last else None,
        "num_images": result.reconstruction.num_reg_images(),
        "num_points3D": result.reconstruction.num_points3D(),
        "num_assigned_points": result.assignment.num_assigned,
        "num_planes": result.assignment.num_faces,
        "planes": plane_table(result),
        "faces": face_table(result),
        "warnings": result.warnings,
        "seconds": result.seconds,
        "result": result.handed_back,
        "quality": result.quality.todict() if result.quality is not None else None,
        "observability": result.observability,
        "observability_before": result.observability_before,
        "datum_cues": result.datum_cues,
        "coarse_alignment": result.coarse_alignment,
        "gnss_height_offset": result.gnss_offset,
        "workflow": result.options.workflow.mode,
        "sliding_window": result.sliding_window,
        "terrain": result.terrain,
        "intrinsics": result.intrinsics,
        "control_marks": result.control_marks,
    }


def terrain_lines(terrain: dict | None) -> list[str]:
    """report.md's line on the terrain the ground tie points were held to."""
    if not terrain or terrain.get("source") in (None, "none"):
        return []
    residuals = terrain.get("residuals") or {}
    rms = residuals.get("rms_m")
    line = (f"Terrain: {terrain['source']} ({', '.join(terrain.get('tiles', [])[:4])}"
            f"{', ...' if len(terrain.get('tiles', [])) > 4 else ''}), "
            f"{terrain.get('num_faces', 0)} cells of {terrain.get('cell_m', 0):g} m, "
            f"{residuals.get('num_points', 0)} ground tie points"
            + (f", RMS {rms:.3f} m from it" if rms is not None else "") + ".")
    return [line, ""] + [f"- {w}" for w in terrain.get("warnings", [])] + (
        [""] if terrain.get("warnings") else [])


def control_marks_lines(record: dict | None) -> list[str]:
    """report.md's table of the ground control marks: each mark's images, where the block's
    rays put it against its surveyed position, its test, and whether it was used."""
    if not record:
        return []
    lines = ["## Control marks", "",
             "| mark | images | block minus survey E / N / U (m) | test | used |",
             "|---|---|---|---|---|"]
    for name, row in record["marks"].items():
        test = row.get("test") or {}
        offset = test.get("offset_m")
        lines.append(f"| {name} | {row['num_images']} | "
                     + (" / ".join(f"{v:+.3f}" for v in offset) if offset else "-") + " | "
                     + (f"{test['statistic']:.1f}" if "statistic" in test else "-") + " | "
                     + ("yes" if row["used"] else "no") + " |")
    lines.append("")
    lines += [f"- {name}: {row['reason']}" for name, row in record["marks"].items()
              if row.get("reason")]
    return lines + [""]


def _number(value, fmt: str = "{:.4f}") -> str:
    return "-" if value is None else fmt.format(value)


def report_markdown(report: dict) -> str:
    lines = ["# colmap-citymodel refine report", ""]
    quality = report.get("quality")
    if quality:
        lines += [f"**Verdict: {quality['verdict']}**"
                  + (" (the files hold the GNSS-only result)" if report["result"] == "gnss_only"
                     else ""), ""] + [f"- {r}" for r in quality["reasons"]] + [""]
    if report.get("observability"):
        # With ground control marks, their own sigma as one more column.
        marks = any("sigma_gcp" in row for row in report["observability"].values())
        keys = ("sigma", "sigma_planes", "sigma_gnss") + (("sigma_gcp",) if marks else ())
        lines += ["## What fixes the datum", "",
                  "| parameter | fixed by | sigma | sigma planes only | sigma GNSS only |"
                  + (" sigma marks only |" if marks else ""),
                  "|---|---|---|---|---|" + ("---|" if marks else "")]
        for name, row in report["observability"].items():
            unit = "deg" if name.startswith("rotation") else "" if name == "scale" else "m"
            cells = [f"{row[k]:.4g} {unit}".strip() if row.get(k) is not None else "free"
                     for k in keys]
            lines.append(f"| {name} | {row['source']} | " + " | ".join(cells) + " |")
        lines += ["", "Scale sigmas are relative; each plane counts with its generalisation "
                  "error, not once per tie point.", ""]
    if report.get("datum_cues"):
        lines += ["Georegistration cues: " + ", ".join(f"{k} from {v}" for k, v in
                                                       report["datum_cues"].items()) + ".", ""]
    coarse = report.get("coarse_alignment")
    if coarse:
        t = coarse["translation"]
        lines += [f"Coarse alignment: shift {', '.join(f'{v:+.2f}' for v in t['shift_m'])} m, "
                  f"tie points near the model {100 * t['near_share_before']:.0f} % -> "
                  f"{100 * t['near_share_after']:.0f} %"
                  + (f", turned about the vertical {coarse['heading_deg']:+.1f} deg"
                     if coarse.get("heading_deg") is not None else "")
                  + (f", roll about the flight line {coarse['roll_deg']:+.1f} deg"
                     if coarse["roll_deg"] is not None else "") + ".", ""]
    lines += terrain_lines(report.get("terrain"))
    lines += control_marks_lines(report.get("control_marks"))
    intrinsics = report.get("intrinsics")
    if intrinsics:
        lines += [f"Interior orientation: {'refined' if intrinsics['refined'] else 'held'} "
                  f"(step 2 with focal length and distortion free: chi-square "
                  f"{intrinsics['chi2_drop']:.1f} lower on {intrinsics['dof']} parameters, "
                  f"p = {intrinsics['p_value']:.2g}).", ""]
    offset = report.get("gnss_height_offset")
    if offset:
        sigma = f" +- {offset['sigma_m']:.2f}" if offset["sigma_m"] is not None else ""
        lines += [f"GNSS height offset (model minus GNSS, estimated from the model planes): "
                  f"{offset['value_m']:+.2f}{sigma} m, relative to {offset['relative_to']}"
                  + (f"; horizontal bias E, N {offset['bias_enu_m'][0]:+.2f}, "
                     f"{offset['bias_enu_m'][1]:+.2f} m" if "bias_enu_m" in offset else "")
                  + ".", ""]
    windows = report.get("sliding_window")
    if windows:
        lines += ["## Sliding window", "",
                  f"{windows['num_windows']} windows of {windows['window_size']} images in "
                  f"{windows['order']} order, {windows['window_new']} new per window, the "
                  f"oldest kept images at {windows['window_held_images']} camera stations held "
                  "by pose priors; then the global adjustment below.", "",
                  "| window | images | first | last | new | held | GNSS | points | planes | "
                  "RMS | s |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for w in windows["windows"]:
            lines.append(f"| {w['index']} | {w['num_images']} | {w['first_image']} | "
                         f"{w['last_image']} | {w['num_new']} | {w['num_held']} | "
                         f"{w['num_gnss']} | {w['num_assigned']} | {w['num_planes']} | "
                         f"{_number(w['rms'])} | {w['seconds']:.1f} |"
                         + (f" {w['note']}" if w["note"] else ""))
        lines.append("")
    geo = report["georegistration"]
    if geo["rms_m"] is not None:
        lines.append(f"Georegistration to GNSS: RMS {geo['rms_m']:.2f} m, "
                     f"scale {geo['sim3']['scale']:.5f}.")
    if geo.get("method") == "model only":
        lines.append(f"Georegistration from the model alone: {geo['hypotheses_2d']} placements "
                     f"searched, best share {geo['best_score']:.2f}, distinct runner-up "
                     f"{geo['runner_up_score']:.2f} (ratio {geo['score_ratio']:.2f}), "
                     f"{geo['hint_distance_m']:.1f} m from the location hint, "
                     f"{geo['seconds']:.1f} s.")
    s2 = report["step2"]
    if s2:
        lines.append(f"Step 2 (BA without model): image RMS {s2['rms']['image']:.3f} px "
                     f"(normalised), {s2['eliminated_image_observations']} image observations "
                     "eliminated.")
    lines += ["", "## Iterations (steps 3-4)", "",
              "| it | threshold m | points | planes | eliminated dTP | RMS image | RMS gnss "
              "| RMS dTP | RMS dVT | RMS VT | s0 | rel. change |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for it in report["iterations"]:
        rms = it["solve"]["rms"]
        label = {"correction": f"{it['iteration']} (model correction)",
                 "faces": f"{it['iteration']} (faces' errors)"}.get(it.get("phase"),
                                                                     it["iteration"])
        lines.append(
            f"| {label} | {it['threshold']:.3f} | {it['num_assigned_points']} | "
            f"{it['num_planes']} | {it['num_eliminated_dTP']} | " + " | ".join(
                f"{rms[g]:.4f}" for g in ("image", "gnss", "dTP", "dVT", "VT"))
            + f" | {it['solve']['sigma0']:.4f} | {it['relative_change']:.2e} |")
    lines += ["", "RMS values are of residuals normalised by their a priori sigma.", "",
              "## Planes (residuals of assigned tie points, m)", "",
              "| face | gml:id | class | points | mean | std |", "|---|---|---|---|---|---|"]
    for row in report["planes"]:
        lines.append(f"| {row['face']} | {row['gml_id']} | {row['semantic']} | "
                     f"{row['num_points']} | {row['mean_m']:+.3f} | {row['std_m']:.3f} |")
    if report["warnings"]:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in report["warnings"]]
    lines += ["", "## Time (s)", ""] + [f"- {k}: {v:.2f}" for k, v in report["seconds"].items()]
    return "\n".join(lines) + "\n"


def write_model_correction(result: RefineResult, directory: Path, *, write_model: bool,
                           lod: int = 2, model_crs: str | None = None) -> dict:
    """model_changes.csv / .ply and, with `write_model`, the corrected model in the format it
    was read in (output.corrected_model); returns the report's `model_correction` entry."""
    correction = result.model_correction
    if correction is None:
        if not result.options.adjustment.correct_model:
            note = "Model correction was not asked for (--preset correct_model)."
        elif result.handed_back == "gnss_only":
            note = "The model was not corrected: the GNSS-only result was handed back."
        else:
            note = "The model was not corrected: the correction was undone (see the warnings)."
        return {"note": note}
    from .corrected_model import write_corrected_model
    from .model_changes import write_changes_csv, write_changes_ply

    summary = correction.todict()
    summary["faces"] = correction.face_rows(result.store)
    summary["num_csv_rows"] = write_changes_csv(correction, result.store,
                                                directory / "model_changes.csv")
    write_changes_ply(correction, result.store, directory / "model_changes.ply")
    summary["written"] = []
    if write_model:
        written, warnings = write_corrected_model(correction, result.store, directory, lod=lod,
                                                  model_crs=model_crs)
        summary["written"] = written
        summary["warnings"] = warnings
        for w in warnings:
            logger.warning("corrected model: %s", w)
    return summary


def write_refined(result: RefineResult, output_path: str | Path, *, output_type: str = "bin",
                  output_frame: str = "crs", inputs: dict | None = None,
                  write_model: bool = False, model_lod: int = 2,
                  model_crs: str | None = None) -> Path:
    """Write the refined model and its report into the new directory `output_path`;
    `write_model`: also the corrected city model (corrected_model.gml / .city.json, or a
    directory of tiles) read with `model_lod` and `model_crs`."""
    if output_type not in ("bin", "txt"):
        raise InputError(f"unknown output type {output_type!r}; use bin or txt")
    if output_frame not in ("crs", "local"):
        raise InputError(f"unknown output frame {output_frame!r}; use crs or local")
    output_path = Path(output_path)
    offset = result.origin if output_frame == "crs" else np.zeros(3)
    with atomic_directory(output_path) as tmp:
        rec = result.reconstruction_in_crs() if output_frame == "crs" else result.reconstruction
        if output_type == "bin":
            rec.write_binary(str(tmp))
        else:
            rec.write_text(str(tmp))
        (tmp / "georeference.json").write_text(
            json.dumps(georeference_dict(result, output_frame), indent=2))
        write_assignments_ply(result, tmp / "assignments.ply", offset)
        try:
            from ..citymodel.mesh import write_mesh

            write_mesh(result.adjusted_store, tmp / "model_mesh.ply", frame=output_frame)
        except ImportError:  # pragma: no cover - mesh export is optional for the result
            logger.warning("model mesh not written: the mesh export is unavailable")
        report = report_dict(result, inputs)
        report["model_correction"] = write_model_correction(
            result, tmp, write_model=write_model, lod=model_lod, model_crs=model_crs)
        # Adds sigma0_by_group, global_test, precision to `report`; CSV, PLY, plots.
        precision_md, plots = write_precision_outputs(result, tmp, report, offset)
        from .model_changes import correction_section

        correction_md = (correction_section(report["model_correction"])
                         if result.options.adjustment.correct_model else "")
        summary = report_markdown(report) + correction_md + precision_md
        (tmp / "report.json").write_text(json.dumps(report, indent=2, default=_json_default))
        (tmp / "report.md").write_text(summary)
        page = html_page("colmap-citymodel refine report", plots, summary)
        (tmp / "report.html").write_text(with_view3d(page, result))
    logger.info("wrote the refined model and report to %s", output_path)
    return output_path


def with_view3d(page: str, result: RefineResult) -> str:
    """report.html's page with the interactive 3D view (output.view3d) after its heading."""
    from .view3d import insert_section, view_section

    t_view = time.perf_counter()
    section, facts = view_section(result, face_colours(len(result.store.faces)))
    logger.info("report.html: 3D view of %d of %d tie points, %d model faces (%.1f s)",
                facts["num_drawn"], facts["num_points"], facts["num_faces"],
                time.perf_counter() - t_view)
    return insert_section(page, section)


def _json_default(value):
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)



