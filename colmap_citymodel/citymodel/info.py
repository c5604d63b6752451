"""`model-info`: read a city model like every other stage does and summarise what the store holds."""

from __future__ import annotations

import json
from pathlib import Path

from .read import city_model_files, read_city_model
from .visibility import visibility


def _fmt_range(lo: float, hi: float) -> str:
    return f"[{lo:.3f}, {hi:.3f}]"


def format_summary(info: dict) -> str:
    """The human-readable summary printed by `model-info`."""
    crs = info["crs"]
    crs_text = crs["label"]
    if crs.get("srs_name") and crs["srs_name"] != crs["label"]:
        crs_text += f"  (srsName {crs['srs_name']})"
    if crs["horizontal_epsg"] is None:
        crs_text += "\n" + crs["wkt"]
    classes = ", ".join(f"{k} {v}" for k, v in info["faces_by_class"].items())
    (x0, y0, z0), (x1, y1, z1) = info["bbox"]
    lines = [
        f"source      {', '.join(info['files'])}",
        f"format      {info['format']} {info['version']}",
        f"CRS         {crs_text}",
        f"buildings   {info['num_buildings']} ({info['num_parts']} building parts)",
        f"faces       {info['num_faces']}: {classes}",
        f"holes       {info.get('num_holes', 0)} in {info.get('faces_with_holes', 0)} faces",
        f"vertices    {info['num_vertices']}",
        f"bbox        x {_fmt_range(x0, x1)}  y {_fmt_range(y0, y1)}  z {_fmt_range(z0, z1)}",
        f"hidden      {info.get('hidden_faces', 0)} faces inside the city's volume, "
        f"{info.get('partly_hidden_faces', 0)} partly (no tie point is put there)",
        f"dropped     {info['num_dropped_degenerate']} degenerate faces",
        f"non-planar  {info['num_nonplanar']} faces flagged "
        f"(max RMS out of plane {info['max_rms_out_of_plane']:.4f} m)",
    ]
    if info["warnings"]:
        lines.append(f"warnings    {len(info['warnings'])}")
        lines += [f"  - {w}" for w in info["warnings"]]
    return "\n".join(lines)


def main(
    paths: str | Path | list,
    *,
    lod: int = 2,
    crs: str | None = None,
    target_crs: str | None = None,
    as_json: bool = False,
) -> dict:
    """Read the model at `paths` and print its summary (one JSON object with `as_json`).

    Returns the summary dict (keys include version, crs, num_buildings, num_faces, num_vertices,
    faces_by_class, bbox, warnings)."""
    files = city_model_files(paths)
    store = read_city_model(files, lod=lod, crs=crs, target_crs=target_crs)
    info = store.summary()
    info.update(visibility(store).summary())
    info["files"] = [str(f) for f in files]
    info["lod"] = lod
    if as_json:
        print(json.dumps(info))
    else:
        print(format_summary(info))
    return info
