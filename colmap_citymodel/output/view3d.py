"""The interactive 3D view in report.html: the block on the city model, in the browser.

One plotly figure (WebGL, plotly.js embedded in the page, so it opens offline):

- the city model faces near the block as triangles, per class (walls, roofs, ground, other):
  faces without tie points pale and half transparent, faces that took tie points opaque in a
  stronger shade of their class; the face outlines as thin lines;
- the tie points of the assignment, at most `MAX_POINTS` of them (a fixed random subset, the
  same points in both blocks): assigned points in the colour of their face (the palette of
  assignments.ply), unassigned points grey; a second colouring by the signed distance of each
  assigned point to the plane of its face;
- the cameras as small frusta with a line along their track;
- fixed axis ranges in true proportions around the block, seen from the cameras' side;
- buttons that show the GNSS-only block (step 2, before the model took part), the refined one,
  or both, and buttons for the colouring.

Coordinates are in the plane store's local frame (model CRS minus `store.origin`), so that the
browser's 32-bit floats keep centimetres; the caption gives the origin. After plotly has drawn,
the page sets `window.viewReady = true` and `document.body.dataset.traces` (traces in the
figure), `dataset.drawn` (objects in the WebGL scene) and `dataset.readyMs` (milliseconds from
the start of loading).
"""

from __future__ import annotations

import base64
import html

import numpy as np
import pycolmap

from ..citymodel.mesh import triangulate_face
from ..citymodel.store import PlaneStore
from .result import RefineResult

#: Most tie points drawn per block (a fixed random subset beyond that).
MAX_POINTS = 30_000
#: Most model faces drawn (those nearest the block's centre beyond that).
MAX_FACES = 20_000
#: Metres around the cameras and tie points within which model faces are drawn.
FACE_MARGIN = 15.0
#: The anchor of the view in report.html (the batch index links to it).
ANCHOR = "view-3d"
PLOT_ID = "view3d-plot"

#: (name, classes, colour of faces without tie points, colour of faces with tie points).
CLASS_GROUPS = (
    ("walls", ("WallSurface",), "#ececec", "#b4bccb"),
    ("roofs", ("RoofSurface",), "#f3e0d9", "#d7a595"),
    ("ground", ("GroundSurface",), "#ebe3cf", "#c4b27f"),
    ("other", None, "#dde8f3", "#9fbfdc"),
)
UNASSIGNED = "#a0a0a0"
#: Signed distance to the face: blue behind it, near-black on it, red in front of it (pale
#: faces behind the points stay readable, unlike a scale that is white in the middle).
RESIDUAL_COLOURS = [[0.0, "#2166ac"], [0.5, "#202020"], [1.0, "#d6301d"]]
BLOCK_STYLE = {"gnss_only": ("GNSS-only", "#e6550d"), "refined": ("refined", "#08306b")}

#: Sets the page's ready flag once plotly's newPlot promise has resolved.
READY_SCRIPT = """
var gd = document.getElementById('{plot_id}');
var scene = gd._fullLayout.scene && gd._fullLayout.scene._scene;
document.body.dataset.traces = String(gd.data.length);
document.body.dataset.drawn = String(scene && scene.glplot ? scene.glplot.objects.length : 0);
document.body.dataset.readyMs = String(Math.round(performance.now()));
window.viewReady = true;
"""


def _hex(rgb) -> str:
    return "#%02x%02x%02x" % tuple(int(v) for v in rgb)


def sample_indices(n: int, max_points: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most `max_points` of `n` items (all of them when n is small)."""
    if n <= max_points:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, max_points, replace=False))


def point_positions(rec: pycolmap.Reconstruction, point_ids: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (P, 3), present (P,) bool): the points of `rec` by id (nan where it has none)."""
    xyz = np.full((len(point_ids), 3), np.nan)
    present = np.zeros(len(point_ids), bool)
    for k, pid in enumerate(point_ids):
        pid = int(pid)
        if rec.exists_point3D(pid):
            xyz[k] = rec.point3D(pid).xyz
            present[k] = True
    return xyz, present


def camera_centres(rec: pycolmap.Reconstruction) -> tuple[list, np.ndarray]:
    """(images ordered by name, their centres (N, 3))."""
    images = sorted((rec.image(i) for i in rec.reg_image_ids()), key=lambda im: im.name)
    centres = np.array([im.projection_center() for im in images]).reshape(-1, 3)
    return images, centres


def frustum_size(centres: np.ndarray) -> float:
    """Depth (m) of the drawn frusta: 0.4 times the median step between neighbouring cameras
    of the track, at least 0.3 m, at most 1/80 of the block's extent."""
    if len(centres) < 2:
        return 1.0
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    steps = steps[steps > 1e-6]
    extent = float(np.linalg.norm(np.ptp(centres, axis=0)))
    size = 0.4 * float(np.median(steps)) if len(steps) else 1.0
    return float(np.clip(size, 0.3, max(0.3, extent / 80.0)))


def frusta_lines(rec: pycolmap.Reconstruction, images: list, size: float) -> np.ndarray:
    """(K, 3) polyline vertices, nan rows between pieces: each camera's centre to its image
    corners at depth `size` and the image rectangle."""
    pieces = []
    nan = np.full((1, 3), np.nan)
    corners_px = {}
    for image in images:
        camera = rec.camera(image.camera_id)
        if image.camera_id not in corners_px:
            w, h = float(camera.width), float(camera.height)
            normalised = np.asarray(camera.cam_from_img(
                np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])))
            corners_px[image.camera_id] = np.c_[normalised, np.ones(4)]
        rotation = np.asarray(image.cam_from_world().rotation.matrix())
        centre = np.asarray(image.projection_center())
        corners = centre + size * (corners_px[image.camera_id] @ rotation)
        for c in corners:
            pieces += [centre[None], c[None], nan]
        pieces += [corners, corners[:1], nan]
    return np.vstack(pieces) if pieces else np.zeros((0, 3))


def track_line(centres: np.ndarray) -> np.ndarray:
    """The camera centres in name order, broken (nan) where a step is more than 10 times the
    median step (another sequence)."""
    if len(centres) < 2:
        return centres
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    limit = 10.0 * max(float(np.median(steps)), 1e-3)
    rows = [centres[:1]]
    for step, centre in zip(steps, centres[1:]):
        if step > limit:
            rows.append(np.full((1, 3), np.nan))
        rows.append(centre[None])
    return np.vstack(rows)


def faces_near(store: PlaneStore, lo: np.ndarray, hi: np.ndarray, max_faces: int) -> np.ndarray:
    """Indices of the faces whose bounding box meets the box [lo, hi] (local frame), at most
    `max_faces` of them (those with centroids nearest the box's centre)."""
    if store.num_faces == 0:
        return np.zeros(0, np.int64)
    faces = store.faces
    ring_face = np.repeat(np.arange(store.num_faces), np.diff(faces.face_ring))
    entry_ring = np.repeat(np.arange(len(faces.ring_ptr) - 1), np.diff(faces.ring_ptr))
    entry_face = ring_face[entry_ring]
    xyz = store.vertices[faces.ring_vertex]
    fmin = np.full((store.num_faces, 3), np.inf)
    fmax = np.full((store.num_faces, 3), -np.inf)
    np.minimum.at(fmin, entry_face, xyz)
    np.maximum.at(fmax, entry_face, xyz)
    near = np.flatnonzero(np.all((fmax >= lo) & (fmin <= hi), axis=1))
    if len(near) > max_faces:
        distance = np.linalg.norm(store.centroids[near] - 0.5 * (lo + hi), axis=1)
        near = np.sort(near[np.argsort(distance)[:max_faces]])
    return near


def _class_of(store: PlaneStore, faces: np.ndarray) -> np.ndarray:
    """Per face of `faces`, the index of its group in CLASS_GROUPS."""
    semantic = np.asarray(store.faces.semantic.categories, dtype=object)[
        store.faces.semantic.codes[faces]] if len(faces) else np.zeros(0, object)
    group = np.full(len(faces), len(CLASS_GROUPS) - 1)
    for g, (_, classes, _, _) in enumerate(CLASS_GROUPS[:-1]):
        group[np.isin(semantic, classes)] = g
    return group


def typed(values, dtype: str = "f4") -> dict:
    """A numeric array as plotly.js's typed-array spec (little-endian bytes in base64): a
    quarter of the size of JSON numbers, and decoded without parsing."""
    array = np.ascontiguousarray(values, dtype=np.dtype(dtype).newbyteorder("<"))
    return {"dtype": dtype, "bdata": base64.b64encode(array.tobytes()).decode("ascii")}


def xyz_arrays(xyz: np.ndarray) -> dict:
    xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    return {"x": typed(xyz[:, 0]), "y": typed(xyz[:, 1]), "z": typed(xyz[:, 2])}


def mesh_traces(store: PlaneStore, faces: np.ndarray, used: set[int]) -> list[dict]:
    """Mesh3d traces of `faces`: per class group, faces without tie points and faces with."""
    group = _class_of(store, faces)
    triangles = {int(f): triangulate_face(store, int(f)) for f in faces}
    traces = []
    for g, (name, _, plain, strong) in enumerate(CLASS_GROUPS):
        for with_points in (False, True):
            chosen = [int(f) for f, k in zip(faces, group)
                      if k == g and (int(f) in used) == with_points]
            tri = [triangles[f] for f in chosen if len(triangles[f])]
            if not tri:
                continue
            ids, inverse = np.unique(np.concatenate(tri), return_inverse=True)
            ijk = inverse.reshape(-1, 3)
            label = f"{name} with tie points" if with_points else name
            traces.append({
                "type": "mesh3d", **xyz_arrays(store.vertices[ids]),
                "i": typed(ijk[:, 0], "i4"), "j": typed(ijk[:, 1], "i4"),
                "k": typed(ijk[:, 2], "i4"), "color": strong if with_points else plain,
                "opacity": 1.0 if with_points else 0.55, "flatshading": True,
                "lighting": {"ambient": 0.85, "diffuse": 0.35, "specular": 0.05},
                "name": f"{label} ({len(chosen)})", "showlegend": True, "hoverinfo": "name",
                "legendgroup": "model"})
    return traces


def outline_trace(store: PlaneStore, faces: np.ndarray) -> dict:
    """The faces' rings as one line trace (nan between rings)."""
    fl = store.faces
    rows = []
    nan = np.full((1, 3), np.nan)
    for f in faces:
        for r in range(fl.face_ring[f], fl.face_ring[f + 1]):
            ring = fl.ring_vertex[fl.ring_ptr[r]:fl.ring_ptr[r + 1]]
            rows += [store.vertices[ring], store.vertices[ring[:1]], nan]
    return {"type": "scatter3d", **xyz_arrays(np.vstack(rows) if rows else np.zeros((0, 3))),
            "mode": "lines", "line": {"color": "#525252", "width": 1},
            "name": "face outlines", "hoverinfo": "skip", "legendgroup": "model"}


def point_residuals(result: RefineResult, xyz: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Signed distance (m) of each point to the plane of its face: the adjusted plane where the
    face was an unknown of the last solve, the face's own plane otherwise (nan: no face)."""
    store = result.adjusted_store
    normals = np.array(store.normals).reshape(-1, 3)
    offsets = np.array(store.offsets).reshape(-1)
    if len(result.plane_faces):
        normals[result.plane_faces] = result.plane_normals
        offsets[result.plane_faces] = result.plane_offsets
    out = np.full(len(xyz), np.nan)
    ok = face >= 0
    out[ok] = np.einsum("ij,ij->i", normals[face[ok]], xyz[ok]) + offsets[face[ok]]
    return out


def face_colourscale(palette: np.ndarray, faces: np.ndarray) -> tuple[list, float]:
    """(plotly colourscale, cmax) that gives marker colour value f the palette colour of face
    f, for each f of `faces` (piecewise constant around each of them; cmin is 0)."""
    cmax = float(max(len(palette) - 1, 1))
    scale = []
    for f in np.unique(faces):
        colour = _hex(palette[f])
        lo, hi = max(f - 0.4, 0.0) / cmax, min(f + 0.4, cmax) / cmax
        scale += [[lo, colour], [hi, colour]]
    if not scale:
        return [[0.0, UNASSIGNED], [1.0, UNASSIGNED]], cmax
    scale[0][0], scale[-1][0] = 0.0, 1.0
    return scale, cmax


def block_traces(key: str, rec: pycolmap.Reconstruction, xyz: np.ndarray, present: np.ndarray,
                 face: np.ndarray, images: list, centres: np.ndarray, frustum: float,
                 visible: bool, colours: dict) -> list[dict]:
    """A block's traces: unassigned tie points, tie points on faces (coloured by face), the
    cameras (frusta and track)."""
    label, colour = BLOCK_STYLE[key]
    unassigned = present & (face < 0)
    assigned = present & (face >= 0)
    lines = np.vstack([frusta_lines(rec, images, frustum), np.full((1, 3), np.nan),
                       track_line(centres)])
    return [
        {"type": "scatter3d", **xyz_arrays(xyz[unassigned]), "mode": "markers",
         "visible": visible, "marker": {"size": 1.5, "color": UNASSIGNED}, "hoverinfo": "skip",
         "name": f"{label}: unassigned tie points ({int(unassigned.sum())})"},
        {"type": "scatter3d", **xyz_arrays(xyz[assigned]), "mode": "markers",
         "visible": visible,
         "marker": {"size": 2, "color": typed(face[assigned]), **colours["face"],
                    "showscale": False,
                    "colorbar": {"title": {"text": "distance to<br>its face (m)"}, "len": 0.5}},
         "customdata": typed(face[assigned], "i4"),
         "hovertemplate": "face %{customdata}<extra></extra>",
         "name": f"{label}: tie points on faces ({int(assigned.sum())})"},
        {"type": "scatter3d", **xyz_arrays(lines), "mode": "lines", "visible": visible,
         "line": {"color": colour, "width": 2}, "hoverinfo": "skip",
         "name": f"{label}: cameras ({len(images)})"},
    ]


#: The longest mark error is drawn this long (m), at most MAX_EXAGGERATION times its length.
ERROR_DRAWN = 2.0
MAX_EXAGGERATION = 100.0
MARK_COLOURS = {"check": "#6a3d9a", "control": "#1a9850", "left out": "#d73027"}


def mark_traces(result: RefineResult) -> list[dict]:
    """The ground marks: check marks at their surveyed positions with their error vectors
    (where the block puts them), control marks with where the block's rays put them; vectors
    exaggerated alike so that the longest is ERROR_DRAWN m (the legend gives the factor)."""
    groups = []  # (kind, surveyed (N, 3) local, errors (N, 3), names)
    evaluation = result.checkpoints
    if evaluation is not None and len(evaluation.ids):
        used = [(evaluation.accuracy or {}).get("marks", {}).get(n, {}).get("used", True)
                for n in evaluation.ids]
        known = np.asarray(evaluation.known) - result.origin
        errors = -np.asarray(evaluation.errors)
        for kind, keep in (("check", np.array(used)), ("left out", ~np.array(used))):
            if keep.any():
                groups.append((kind, known[keep], errors[keep],
                               [n for n, k in zip(evaluation.ids, keep) if k]))
    marks = (result.control_marks or {}).get("marks", {})
    for kind, wanted in (("control", True), ("left out", False)):
        rows = [(n, r) for n, r in marks.items() if r["used"] is wanted]
        if rows:
            groups.append((kind, np.array([r["surveyed_local_m"] for _, r in rows]),
                           np.array([(r.get("test") or {}).get("offset_m", [0.0] * 3)
                                     for _, r in rows]), [n for n, _ in rows]))
    if not groups:
        return []
    longest = max(float(np.max(np.linalg.norm(g[2], axis=1), initial=0.0)) for g in groups)
    factor = min(MAX_EXAGGERATION, ERROR_DRAWN / longest) if longest > 0 else 1.0
    traces = []
    for kind, surveyed, errors, names in groups:
        colour = MARK_COLOURS[kind]
        label = "check marks" if kind == "check" else ("control marks" if kind == "control"
                                                       else "marks left out")
        tips = surveyed + factor * errors
        lines = np.stack([surveyed, tips, np.full_like(surveyed, np.nan)], axis=1)
        traces += [
            {"type": "scatter3d", **xyz_arrays(surveyed), "mode": "markers",
             "marker": {"size": 5, "color": colour, "symbol": "diamond"}, "text": names,
             "hovertemplate": "%{text}<extra></extra>",
             "name": f"{label} ({len(names)})"},
            {"type": "scatter3d", **xyz_arrays(lines.reshape(-1, 3)), "mode": "lines",
             "line": {"color": colour, "width": 4}, "hoverinfo": "skip",
             "name": f"{label}: error x {factor:.0f}"}]
    return traces


def restyle_marker(values: dict, num_traces: int) -> dict:
    """Marker attributes as restyle arguments: a list value (a colourscale) is given once per
    trace, as restyle reads a list as one value per trace."""
    return {f"marker.{k}": [v] * num_traces if isinstance(v, list) else v
            for k, v in values.items()}


def build_figure(result: RefineResult, palette: np.ndarray, *, max_points: int = MAX_POINTS,
                 max_faces: int = MAX_FACES, seed: int = 0) -> tuple[dict, dict]:
    """(plotly figure as a dict of data and layout, facts about it: numbers drawn, the traces
    of each block, the residual colour range). `palette`: (F, 3) uint8 colour of each store
    face (assignments.ply's)."""
    a = result.assignment
    refined = rec_of(result, "refined")
    blocks = [(key, rec) for key, rec in (("gnss_only", result.gnss_only), ("refined", refined))
              if rec is not None]
    shown = result.handed_back if result.handed_back in dict(blocks) else blocks[-1][0]
    pick = sample_indices(len(a.point_ids), max_points, seed)
    point_ids, face = a.point_ids[pick], a.face_index[pick]

    geometry = {}
    for key, rec in blocks:
        xyz, present = point_positions(rec, point_ids)
        images, centres = camera_centres(rec)
        geometry[key] = (xyz, present, images, centres, point_residuals(result, xyz, face))
    lo, hi = block_box([g[0][g[1]] for g in geometry.values()],
                       [g[3] for g in geometry.values()])
    store = result.adjusted_store
    faces = faces_near(store, lo - FACE_MARGIN, hi + FACE_MARGIN, max_faces)
    used = {int(f) for f in np.unique(face[face >= 0])}
    traces = mesh_traces(store, faces, used) + [outline_trace(store, faces)] \
        + mark_traces(result)  # shown with every block
    num_model = len(traces)

    scale = residual_scale(geometry)
    face_scale, cmax = face_colourscale(palette, face[face >= 0])
    colours = {"face": {"colorscale": face_scale, "cmin": 0.0, "cmax": cmax},
               "residual": {"colorscale": RESIDUAL_COLOURS, "cmin": -scale, "cmax": scale}}

    frustum = frustum_size(geometry[shown][3]) if blocks else 1.0
    per_block: dict[str, list[int]] = {}
    for key, rec in blocks:
        xyz, present, images, centres, _ = geometry[key]
        per_block[key] = list(range(len(traces), len(traces) + 3))
        traces += block_traces(key, rec, xyz, present, face, images, centres, frustum,
                               key == shown, colours)

    buttons, active = block_buttons([k for k, _ in blocks], per_block, num_model, len(traces),
                                    shown)
    colour_buttons = colour_by_buttons([k for k, _ in blocks], geometry, face, per_block,
                                       colours)
    num_points = len(a.point_ids)
    title = (f"{len(pick):,} of {num_points:,} tie points drawn"
             + (" (a random subset)" if len(pick) < num_points else "")
             + f", {len(faces):,} model faces, local frame (m)")
    layout = {
        "title": {"text": title, "x": 0.01, "font": {"size": 14}},
        "height": 720, "margin": {"l": 0, "r": 0, "t": 40, "b": 0},
        "legend": {"x": 1.0, "xanchor": "right", "y": 0.92,
                   "bgcolor": "rgba(255,255,255,0.7)", "font": {"size": 11}},
        "scene": {**scene_box(store, faces, lo, hi),
                  "camera": scene_camera(geometry[shown][3] if blocks else np.zeros((0, 3)),
                                         geometry[shown][0][geometry[shown][1]] if blocks
                                         else np.zeros((0, 3)))},
        "updatemenus": [
            {"type": "buttons", "direction": "right", "buttons": buttons, "active": active,
             "x": 0.0, "xanchor": "left", "y": 1.0, "yanchor": "top", "pad": {"l": 8},
             "showactive": True},
            {"type": "buttons", "direction": "right", "buttons": colour_buttons, "active": 0,
             "x": 0.0, "xanchor": "left", "y": 0.95, "yanchor": "top", "pad": {"l": 8},
             "showactive": True},
        ]}
    facts = {"num_points": num_points, "num_drawn": int(len(pick)),
             "num_faces": int(len(faces)),
             "num_faces_with_points": len(used & set(faces.tolist())),
             "num_traces": len(traces), "num_model_traces": num_model, "blocks": per_block,
             "shown": shown, "residual_scale_m": scale,
             "num_drawn_visible": num_model + (len(per_block[shown]) if blocks else 0)}
    return {"data": traces, "layout": layout}, facts


def residual_scale(geometry: dict) -> float:
    """Full scale (m) of the distance colours: 3 x the refined block's RMS distance to its
    faces, within 0.1-2 m (0.5 without a refined block)."""
    if "refined" not in geometry:
        return 0.5
    r = geometry["refined"][4]
    r = r[geometry["refined"][1] & np.isfinite(r)]
    if not len(r):
        return 0.5
    return float(f"{np.clip(3.0 * np.sqrt(np.mean(r ** 2)), 0.1, 2.0):.2g}")


def block_buttons(keys: list[str], per_block: dict, num_model: int, num_traces: int,
                  shown: str) -> tuple[list[dict], int]:
    """The buttons that show one block (or both) with the model, and the active one."""
    buttons = []
    options = [[k] for k in keys] + ([list(keys)] if len(keys) > 1 else [])
    for chosen in options:
        visible = [True] * num_model + [False] * (num_traces - num_model)
        for k in chosen:
            for t in per_block[k]:
                visible[t] = True
        buttons.append({"label": "both blocks" if len(chosen) > 1
                        else f"{BLOCK_STYLE[chosen[0]][0]} block",
                        "method": "restyle", "args": [{"visible": visible}]})
    return buttons, (options.index([shown]) if keys else 0)


def colour_by_buttons(keys: list[str], geometry: dict, face: np.ndarray, per_block: dict,
                      colours: dict) -> list[dict]:
    """The buttons that colour every block's tie points by face or by distance to it."""
    coloured = [per_block[k][1] for k in keys]
    on_faces = [geometry[k][1] & (face >= 0) for k in keys]
    return [
        {"label": "colour by face", "method": "restyle",
         "args": [{"marker.color": [typed(face[m]) for m in on_faces],
                   **restyle_marker(colours["face"], len(coloured)),
                   "marker.showscale": False}, coloured]},
        {"label": "colour by distance to face", "method": "restyle",
         "args": [{"marker.color": [typed(geometry[k][4][m]) for k, m in zip(keys, on_faces)],
                   **restyle_marker(colours["residual"], len(coloured)),
                   "marker.showscale": True}, coloured]},
    ]


def block_box(points: list[np.ndarray], centres: list[np.ndarray]) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """(lo, hi) corners of the box around the cameras and the bulk of the tie points (their
    0.5 and 99.5 percentiles: a few stray points far off do not shrink the block)."""
    corners = [np.zeros((0, 3))] + [c for c in centres if len(c)]
    points = np.vstack([np.zeros((0, 3))] + list(points))
    if len(points):
        corners.append(np.percentile(points, [0.5, 99.5], axis=0))
    corners = np.vstack(corners)
    if not len(corners):
        return np.zeros(3), np.zeros(3)
    return corners.min(0), corners.max(0)


def scene_box(store: PlaneStore, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> dict:
    """Fixed axis ranges and true proportions for the scene: the block's box grown by the
    drawn faces and a margin. Fixed, so that switching blocks keeps the view; plotly's own
    "data" aspect mode scales the scene to its volume, which puts a long street's ends out of
    the picture."""
    if len(faces):
        vertices = store.vertices[np.unique(np.concatenate(
            [store.faces.ring_vertex[store.faces.ring_ptr[store.faces.face_ring[f]]:
                                     store.faces.ring_ptr[store.faces.face_ring[f + 1]]]
             for f in faces]))]
        lo, hi = np.minimum(lo, vertices.min(0)), np.maximum(hi, vertices.max(0))
    margin = 0.03 * max(float(np.max(hi - lo)), 1.0)
    lo, hi = lo - margin, hi + margin
    size = hi - lo
    ratio = size / size.max()
    axes = {}
    for name, title, a, b in zip("xyz", ("E", "N", "up"), lo, hi):
        axes[f"{name}axis"] = {"title": {"text": title}, "range": [float(a), float(b)],
                               "autorange": False}
    return {"aspectmode": "manual", **axes,
            "aspectratio": {k: float(v) for k, v in zip("xyz", ratio)}}


def rec_of(result: RefineResult, key: str) -> pycolmap.Reconstruction:
    if key == "gnss_only":
        return result.gnss_only
    return result.refined if result.refined is not None else result.reconstruction


def scene_camera(centres: np.ndarray, points: np.ndarray) -> dict:
    """plotly's scene camera: from above the cameras' side of the tie points (`points`),
    looking across the block's long axis and a little along it. (The eye is in units of the
    scene's extent when aspectmode is "data".)"""
    if len(centres) >= 2:
        horizontal = centres[:, :2] - centres[:, :2].mean(0)
        _, _, vt = np.linalg.svd(horizontal, full_matrices=False)
        along = vt[0]
    else:
        along = np.array([1.0, 0.0])
    across = np.array([-along[1], along[0]])
    if len(centres) and len(points):
        side = centres[:, :2].mean(0) - points[:, :2].mean(0)
        if side @ across < 0:
            across = -across
    elif across[1] > 0:  # from the south
        across = -across
    if along[0] > 0:  # and a little from the west
        along = -along
    eye = 0.7 * across + 0.28 * along
    return {"eye": {"x": float(eye[0]), "y": float(eye[1]), "z": 0.5},
            "up": {"x": 0, "y": 0, "z": 1}}


def view_section(result: RefineResult, palette: np.ndarray, *, max_points: int = MAX_POINTS,
                 max_faces: int = MAX_FACES) -> tuple[str, dict]:
    """(HTML section with the 3D view and its caption, facts of build_figure). plotly.js is
    embedded in the section: the page needs no network."""
    figure, facts = build_figure(result, palette, max_points=max_points, max_faces=max_faces)
    origin = result.origin
    crs = result.store.crs.label
    blocks = ("the GNSS-only block (the bundle adjustment with GNSS, before the model took "
              "part), the refined block, or both" if "gnss_only" in facts["blocks"] else
              "the refined block (there is no GNSS-only one without GNSS)")
    handed_back = (" The GNSS-only block is what was written (see the verdict), and it shows "
                   "first." if facts["shown"] == "gnss_only" else "")
    caption = (
        f"Coordinates in metres in the local frame: model CRS ({crs}) minus the origin E "
        f"{origin[0]:.3f}, N {origin[1]:.3f}, H {origin[2]:.3f}. Buttons at the top left: "
        f"{blocks}; tie points coloured by the face they were assigned to (grey: unassigned) "
        "or by their signed distance to that face's plane (+- "
        f"{facts['residual_scale_m']:g} m full scale). Faces that took tie points are drawn "
        "in stronger colours. Drag to turn, scroll to zoom, click a legend entry to hide it."
        + handed_back)
    import plotly.io

    # A plain dict with typed arrays, not validated (validation takes seconds on 30k points).
    div = plotly.io.to_html(figure, validate=False, full_html=False, include_plotlyjs=True,
                            div_id=PLOT_ID, post_script=READY_SCRIPT,
                            config={"displaylogo": False, "responsive": True})
    section = (f"<h2 id='{ANCHOR}'>3D view</h2>\n<p>{html.escape(caption)}</p>\n{div}\n")
    return section, facts


def insert_section(page: str, section: str) -> str:
    """`page` with `section` after its first heading (before </body> if it has none)."""
    at = page.find("</h1>")
    if at >= 0:
        at += len("</h1>")
        return page[:at] + "\n" + section + page[at:]
    at = page.rfind("</body>")
    return page[:at] + section + page[at:] if at >= 0 else page + section
