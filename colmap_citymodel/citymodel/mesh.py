"""The plane store as a triangle mesh: for viewing beside a COLMAP model (PLY/OBJ) and for ray
casting in the flight simulator.

Each face (exterior ring + holes) is triangulated with earcut (mapbox_earcut) in the face's own
2D frame (columns 0, 1 of its R), so tilted faces and holes triangulate like flat polygons;
triangles are wound counter-clockwise around the face normal (outward). Earcut's bridges to
holes can produce zero-area triangles; they are kept so the mesh stays closed (they have no
normal and are never hit by a ray).

PLY is written by a small writer here with float64 (`double`) vertex coordinates: trimesh's PLY
exporter writes float32, which in a CRS frame (6-7 digit coordinates) would round vertices to
several centimetres. OBJ goes through trimesh with 8 decimals.
"""

from __future__ import annotations

import logging
import os
import tempfile
from pathlib import Path

import mapbox_earcut
import numpy as np
import trimesh

from ..errors import InputError
from .store import PlaneStore

logger = logging.getLogger(__name__)

SEMANTIC_COLOURS: dict[str, tuple[int, int, int]] = {
    "WallSurface": (200, 200, 200),
    "RoofSurface": (200, 60, 40),
    "GroundSurface": (110, 80, 50),
    "ClosureSurface": (120, 170, 220),
    "OuterCeilingSurface": (230, 190, 90),
    "OuterFloorSurface": (150, 120, 90),
    "Window": (90, 170, 230),
    "Door": (140, 90, 60),
}
DEFAULT_COLOUR = (255, 0, 255)  # unknown class: magenta, easy to spot


def triangulate_face(store: PlaneStore, f: int) -> np.ndarray:
    """(T, 3) store-vertex indices of the triangles of face f, wound around its normal."""
    face = store.faces[f]
    rings = [face.exterior, *face.holes]
    ids = np.concatenate(rings)
    R, c = store.rotations[f], store.centroids[f]
    uv = (store.vertices[ids] - c) @ R[:, :2]
    ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
    tri = mapbox_earcut.triangulate_float64(np.ascontiguousarray(uv), ends).reshape(-1, 3)
    if len(tri) == 0:
        return np.zeros((0, 3), np.int64)
    a, b, cc = uv[tri[:, 0]], uv[tri[:, 1]], uv[tri[:, 2]]
    signed = (b[:, 0] - a[:, 0]) * (cc[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (cc[:, 0] - a[:, 0])
    tri = np.where((signed < 0)[:, None], tri[:, ::-1], tri)  # det(R)=+1: ccw in uv = outward
    return ids[tri].astype(np.int64)


def store_to_trimesh(
    store: PlaneStore, frame: str = "local", split_faces: bool = False
) -> tuple[trimesh.Trimesh, np.ndarray]:
    """(mesh, triangle_face): the store as a trimesh and, per triangle, the store face index.

    frame "local" (store coordinates) or "crs" (origin added; float64 in memory).
    split_faces False: the mesh shares the store's vertices (vertex i of the mesh is store vertex
    i), for ray casting. True: every face gets its own vertex copies so that vertex colours can
    follow the semantic class (export). Triangle colours by class are set either way.
    """
    if frame not in ("local", "crs"):
        raise ValueError(f"frame must be 'local' or 'crs', not {frame!r}")
    tris, owner = [], []
    for f in range(store.num_faces):
        t = triangulate_face(store, f)
        tris.append(t)
        owner.append(np.full(len(t), f, np.int64))
    triangles = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    triangle_face = np.concatenate(owner) if owner else np.zeros(0, np.int64)
    vertices = store.vertices + (store.origin if frame == "crs" else 0.0)
    face_rgb = np.array(
        [SEMANTIC_COLOURS.get(f.semantic, DEFAULT_COLOUR) for f in store.faces], np.uint8
    ).reshape(-1, 3)
    tri_rgba = np.c_[face_rgb[triangle_face], np.full(len(triangle_face), 255, np.uint8)]
    if split_faces:
        # one vertex copy per (face, vertex) pair
        key = triangle_face[:, None] * (len(vertices) + 1) + triangles
        uniq, inv = np.unique(key.ravel(), return_inverse=True)
        vid = uniq % (len(vertices) + 1)
        vface = uniq // (len(vertices) + 1)
        mesh = trimesh.Trimesh(
            vertices=vertices[vid], faces=inv.reshape(-1, 3), process=False,
            vertex_colors=np.c_[face_rgb[vface], np.full(len(vid), 255, np.uint8)],
        )
        mesh.visual.face_colors = tri_rgba
    else:
        mesh = trimesh.Trimesh(
            vertices=vertices, faces=triangles, face_colors=tri_rgba, process=False
        )
    return mesh, triangle_face


def _write_ply_f64(mesh: trimesh.Trimesh, triangle_face: np.ndarray, path: Path) -> None:
    """Binary little-endian PLY: double x,y,z + uchar rgb per vertex; faces with int face_id."""
    V = np.asarray(mesh.vertices, np.float64)
    rgb = np.asarray(mesh.visual.vertex_colors, np.uint8)[:, :3]
    F = np.asarray(mesh.faces, np.int32)
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment colmap-citymodel building model\n"
        f"element vertex {len(V)}\nproperty double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        f"element face {len(F)}\nproperty list uchar int vertex_indices\n"
        "property int face_id\nend_header\n"
    )
    vdt = np.dtype([("xyz", "<f8", 3), ("rgb", "u1", 3)])
    vrec = np.empty(len(V), vdt)
    vrec["xyz"], vrec["rgb"] = V, rgb
    fdt = np.dtype([("n", "u1"), ("idx", "<i4", 3), ("face_id", "<i4")])
    frec = np.empty(len(F), fdt)
    frec["n"], frec["idx"], frec["face_id"] = 3, F, triangle_face
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())


def write_mesh(store: PlaneStore, path: str | Path, frame: str = "local") -> Path:
    """Write the store as a mesh: `.ply` (binary, float64 vertices, per-vertex class colours,
    per-triangle store face id) or `.obj` (trimesh, vertex colours, 8 decimals). Written to a
    temporary file beside `path` and renamed, so a failed write leaves nothing behind."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".obj"):
        raise InputError("mesh file must end in .ply or .obj", path)
    mesh, triangle_face = store_to_trimesh(store, frame=frame, split_faces=True)
    fd, tmp_name = tempfile.mkstemp(suffix=suffix, prefix=".tmp_", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        if suffix == ".ply":
            _write_ply_f64(mesh, triangle_face, tmp)
        else:
            text = trimesh.exchange.obj.export_obj(
                mesh, include_normals=False, include_color=True, digits=8
            )
            tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    logger.info(
        "wrote %s: %d triangles of %d faces (%s frame)", path, len(mesh.faces),
        store.num_faces, frame,
    )
    return path
