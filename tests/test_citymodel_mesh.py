"""Mesh export of the plane store: triangulation with holes, areas, winding, face map, PLY/OBJ
round trips with full float64 precision in the CRS frame."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from colmap_citymodel.citymodel.mesh import SEMANTIC_COLOURS, store_to_trimesh, write_mesh
from colmap_citymodel.citymodel.read_cityjson import read_cityjson
from colmap_citymodel.citymodel.build import build_store, store_from_polygons
from colmap_citymodel.errors import InputError
from data_paths import CITYJSON

CUBE_V = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    float,
)
CUBE_F = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
CUBE_SEM = ["GroundSurface", "RoofSurface"] + ["WallSurface"] * 4


def rot(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def first_hits(mesh, origins, directions):
    """Moeller-Trumbore, brute force: index of the first triangle hit per ray (-1 none)."""
    T = mesh.triangles
    e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    out = []
    for o, d in zip(origins, directions):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = o - T[:, 0]
            u = np.einsum("ij,ij->i", s, p) / det
            q = np.cross(s, e1)
            v = (q @ d) / det
            t = np.einsum("ij,ij->i", e2, q) / det
        ok = (np.abs(det) > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        out.append(int(np.flatnonzero(ok)[np.argmin(t[ok])]) if ok.any() else -1)
    return np.array(out)


def tilted_scene():
    """A concave L-shaped face with two holes and a pentagon, tilted, at CRS magnitudes."""
    R = rot([0.3, 1, 0.2], 0.9)
    L = np.array([[0, 0], [10, 0], [10, 4], [4, 4], [4, 10], [0, 10]], float)
    h1 = np.array([[1, 1], [1, 3], [3, 3], [3, 1]], float)  # clockwise (hole)
    h2 = np.array([[6, 1], [6, 2], [8, 2], [8, 1]], float)
    pent = np.array([[20, 0], [24, 0], [25, 3], [22, 5], [19, 3]], float)
    off = np.array([690123.25, 5334567.75, 512.5])

    def to3(a):
        return np.c_[a, np.zeros(len(a))] @ R.T + off

    store = store_from_polygons(
        [to3(L), to3(pent)], holes=[[to3(h1), to3(h2)], []],
        semantics=["RoofSurface", "WallSurface"],
    )
    return store, (100 - 36) - 4 - 2  # L-shape minus the two holes


def test_triangle_areas_sum_to_face_areas_with_holes():
    store, area_l = tilted_scene()
    assert store.areas[0] == pytest.approx(area_l)
    mesh, tri_face = store_to_trimesh(store)
    per_face = np.bincount(tri_face, mesh.area_faces, store.num_faces)
    np.testing.assert_allclose(per_face, store.areas, rtol=1e-9)
    # every triangle winds around its face's outward normal (earcut's hole bridges may add
    # zero-area triangles; they keep the mesh closed and have no normal)
    ok = mesh.area_faces > 1e-9
    assert ok.sum() >= len(ok) - 2
    np.testing.assert_allclose(mesh.face_normals[ok], store.normals[tri_face[ok]], atol=1e-9)
    # triangles inside the holes: none (centroids of triangles are not in a hole)
    c = mesh.triangles_center[tri_face == 0]
    assert np.all(store.contains_projection(0, c, margin=0.0))
    # the ray-casting mesh shares the store's vertices
    np.testing.assert_array_equal(mesh.vertices, store.vertices)


def test_cube_mesh_is_watertight_outward_and_face_map_works_for_rays():
    store = store_from_polygons([CUBE_V[f] for f in CUBE_F], semantics=CUBE_SEM,
                                origin=np.zeros(3))
    mesh, tri_face = store_to_trimesh(store)
    assert len(mesh.faces) == 12 and mesh.is_watertight
    assert mesh.volume == pytest.approx(1.0)  # positive volume: outward winding
    # a ray from above hits the roof; the map names the roof face
    hit = first_hits(
        mesh, np.array([[0.3, 0.6, 5.0], [5.0, 0.5, 0.5]]), np.array([[0, 0, -1.0], [-1.0, 0, 0]])
    )
    assert store.faces[tri_face[hit[0]]].semantic == "RoofSurface"
    assert np.allclose(store.normals[tri_face[hit[1]]], [1, 0, 0])
    # split mesh: colours follow the class
    split, tf = store_to_trimesh(store, split_faces=True)
    assert len(split.vertices) == 24
    roof_v = split.faces[tf == 1].ravel()
    assert np.all(split.visual.vertex_colors[roof_v, :3] == SEMANTIC_COLOURS["RoofSurface"])


def test_ply_and_obj_round_trip_float64_in_crs_frame(tmp_path):
    store, _ = tilted_scene()
    crs_vertices = store.to_crs(store.vertices)
    ply = write_mesh(store, tmp_path / "m.ply", frame="crs")
    loaded = trimesh.load(ply, process=False)
    assert loaded.vertices.dtype == np.float64
    # every written vertex is exactly a store vertex in CRS coordinates (no float32 rounding)
    d = np.abs(loaded.vertices[:, None, :] - crs_vertices[None]).max(2).min(1)
    assert d.max() == 0.0
    assert loaded.area == pytest.approx(store.areas.sum(), rel=1e-9)
    obj = write_mesh(store, tmp_path / "m.obj", frame="crs")
    lo = trimesh.load(obj, process=False)
    d = np.abs(lo.vertices[:, None, :] - crs_vertices[None]).max(2).min(1)
    assert d.max() < 1e-7
    assert lo.area == pytest.approx(store.areas.sum(), rel=1e-6)
    local = trimesh.load(write_mesh(store, tmp_path / "l.ply"), process=False)
    assert np.abs(local.vertices).max() < 100
    assert sorted(p.name for p in tmp_path.iterdir()) == ["l.ply", "m.obj", "m.ply"]
    with pytest.raises(InputError):
        write_mesh(store, tmp_path / "m.stl")


def test_real_model_mesh_areas_and_closed_solids(tmp_path):
    store = build_store(read_cityjson(CITYJSON / "3dbag_b2.city.json"))
    mesh, tri_face = store_to_trimesh(store)
    per_face = np.bincount(tri_face, mesh.area_faces, store.num_faces)
    # faces are planar to 0.3 mm here: triangle areas match the projected (Newell) areas
    np.testing.assert_allclose(per_face, store.areas, rtol=1e-3)
    assert np.all(np.bincount(tri_face, minlength=store.num_faces) >= 1)
    assert mesh.is_watertight and mesh.volume > 0
    out = write_mesh(store, tmp_path / "bag.ply", frame="crs")
    assert trimesh.load(out, process=False).area == pytest.approx(mesh.area, rel=1e-9)
