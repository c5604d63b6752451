"""The record of a model correction for people: what moved, by how much, and how sure.

- `model_changes.csv`: one row per corrected vertex and face it belongs to (the building id,
  the face's gml:id and class, the vertex's given coordinates in the model CRS, its shift
  E/N/U, the sigma of the corrected vertex along the shift and per axis, the test
  |shift| / sigma and whether it exceeds the threshold); faces that kept their plane beside
  corrected ones are listed with role "kept_plane" (their shared vertices slide within them);
- `model_changes.ply`: the corrected model as a mesh, each face coloured by the largest shift of
  its vertices (grey: unchanged; blue to red up to `COLOUR_FULL_SCALE` m), with per-triangle
  `face_id` and `shift` (m);
- `correction_section`: the summary for report.md.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..adjust.model_correction import ModelCorrection
from ..citymodel.mesh import store_to_trimesh
from ..citymodel.store import PlaneStore

#: Shift (m) that gets the full red of the colour scale.
COLOUR_FULL_SCALE = 0.5
UNCHANGED_GREY = (170, 170, 170)

CSV_COLUMNS = ("building_id", "face_id", "semantic", "role", "vertex", "E", "N", "U",
               "shift_E", "shift_N", "shift_U", "shift_m", "sigma_m", "sigma_E", "sigma_N",
               "sigma_U", "test", "significant")


def change_rows(correction: ModelCorrection, store: PlaneStore) -> list[dict]:
    """The CSV rows (model CRS coordinates, metres)."""
    indptr, owners = store.vertex_faces
    corrected = set(correction.faces.tolist())
    sigma, axes, test = correction.sigma, correction.sigma_axes, correction.test
    significant = correction.significant
    rows = []
    for k, v in enumerate(correction.vertex_ids.tolist()):
        given = correction.given[k] + store.origin
        shift = correction.shift[k]
        for f in owners[indptr[v]:indptr[v + 1]].tolist():
            face = store.faces[f]
            rows.append({
                "building_id": face.building_id, "face_id": face.gml_id,
                "semantic": face.semantic,
                "role": "corrected" if f in corrected else "kept_plane", "vertex": v,
                "E": f"{given[0]:.4f}", "N": f"{given[1]:.4f}", "U": f"{given[2]:.4f}",
                "shift_E": f"{shift[0]:+.4f}", "shift_N": f"{shift[1]:+.4f}",
                "shift_U": f"{shift[2]:+.4f}", "shift_m": f"{np.linalg.norm(shift):.4f}",
                "sigma_m": _number(sigma[k]), "sigma_E": _number(axes[k, 0]),
                "sigma_N": _number(axes[k, 1]), "sigma_U": _number(axes[k, 2]),
                "test": _number(test[k], 2), "significant": str(bool(significant[k])).lower(),
            })
    return rows


def _number(value: float, decimals: int = 4) -> str:
    return f"{value:.{decimals}f}" if np.isfinite(value) else ""


def write_changes_csv(correction: ModelCorrection, store: PlaneStore, path: Path) -> int:
    rows = change_rows(correction, store)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    return len(rows)


def shift_colours(shift: np.ndarray) -> np.ndarray:
    """(F, 3) uint8: grey where nothing moved, blue (small) to red (COLOUR_FULL_SCALE)."""
    t = np.clip(np.asarray(shift, float) / COLOUR_FULL_SCALE, 0.0, 1.0)
    rgb = np.column_stack([255 * t, 80 * (1 - np.abs(2 * t - 1)), 255 * (1 - t)])
    rgb[shift <= 0] = UNCHANGED_GREY
    return rgb.astype(np.uint8)


def write_changes_ply(correction: ModelCorrection, given: PlaneStore, path: Path,
                      frame: str = "crs") -> None:
    """The corrected model, faces coloured by their largest vertex shift (binary PLY, float64
    vertices; per triangle its store face and that shift)."""
    corrected = correction.corrected_store(given)
    face_shift = correction.face_shifts(given)
    mesh, triangle_face = store_to_trimesh(corrected, frame=frame, split_faces=True)
    vertices = np.asarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int32)
    # split_faces: each mesh vertex belongs to one face; colour it by that face's shift
    vertex_face = np.zeros(len(vertices), np.int64)
    vertex_face[faces.ravel()] = np.repeat(triangle_face, 3)
    rgb = shift_colours(face_shift)[vertex_face]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        "comment colmap-citymodel corrected building model, faces coloured by their shift\n"
        f"element vertex {len(vertices)}\nproperty double x\nproperty double y\n"
        "property double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
        "property int face_id\nproperty float shift\nend_header\n")
    vrec = np.empty(len(vertices), np.dtype([("xyz", "<f8", 3), ("rgb", "u1", 3)]))
    vrec["xyz"], vrec["rgb"] = vertices, rgb
    frec = np.empty(len(faces), np.dtype([("n", "u1"), ("idx", "<i4", 3), ("face_id", "<i4"),
                                          ("shift", "<f4")]))
    frec["n"], frec["idx"], frec["face_id"] = 3, faces, triangle_face
    frec["shift"] = face_shift[triangle_face]
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())


def correction_section(summary: dict) -> str:
    """report.md: what the images corrected in the model."""
    lines = ["", "## Model correction", ""]
    if summary.get("written") is None and summary.get("num_corrected_faces") is None:
        return "\n".join(lines + [summary.get("note", "The model was not corrected."), ""])
    lines += [
        f"{summary['num_corrected_faces']} faces corrected (each with its plane determined by "
        f"its tie points to {summary.get('max_plane_sigma_m') or 0:g} m a posteriori sigma at "
        f"every vertex), {summary['num_held_faces']} faces beside them kept their planes; "
        f"{summary['num_corrected_vertices']} vertices moved, "
        f"{summary['num_significant_vertices']} of them significantly "
        f"(|shift| / sigma > {summary['significance_threshold']:g}).", ""]
    if summary.get("shift_rms_m") is not None:
        median_sigma = summary.get("median_sigma_m")
        lines += [f"Shifts: RMS {summary['shift_rms_m']:.3f} m, largest "
                  f"{summary['shift_max_m']:.3f} m; median sigma of a corrected vertex "
                  + (f"{median_sigma:.3f} m" if median_sigma is not None else "not computed")
                  + f" ({summary['covariance_note']}).", ""]
    not_corrected = summary.get("assigned_faces_not_corrected") or {}
    if not_corrected:
        lines += ["Faces with tie points that were not corrected: " + ", ".join(
            f"{n} ({reason.replace('_', ' ')})" for reason, n in not_corrected.items()) + ".", ""]
    written = summary.get("written") or []
    if written:
        lines += ["| file written | from | coordinates moved | vertices |", "|---|---|---|---|"]
        for w in written:
            lines.append(f"| {w['target']} | {w['source']} | {w['num_moved']} | "
                         f"{w['num_vertices_moved']} |")
        lines.append("")
    lines += ["Per vertex: `model_changes.csv`; the corrected faces coloured by their shift: "
              "`model_changes.ply`.", ""]
    return "\n".join(lines)
