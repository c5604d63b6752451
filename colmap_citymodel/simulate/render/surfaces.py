"""What the renderer knows of each triangle of the true scene (its part, object, plane frame and
face rectangle) and of each ray hit (position, normals, texture coordinates, pixel footprint).

Texture coordinates are metres in the plane of the hit triangle: s along the plane's horizontal
axis u, t along v = n x u (up a wall, up the slope of a roof), both measured from the local
origin, so that coplanar triangles (a wall cut around its windows) carry one continuous
texture. A face's rectangle (the bounds of its polygon in s, t) places window frames, door
panels and car windows on their faces.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..scene import TrueScene


def plane_axes(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) per unit normal (N,3): u horizontal (along x for horizontal planes), v = n x u;
    scene.plane_basis for many normals at once."""
    n = np.asarray(normals, dtype=np.float64)
    u = np.stack([-n[:, 1], n[:, 0], np.zeros(len(n))], axis=1)  # z x n
    flat = np.linalg.norm(u, axis=1) < 1e-6
    u[flat] = np.array([1.0, 0.0, 0.0]) - n[flat, :1] * n[flat]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(n, u)


@dataclass
class SceneTables:
    """Per triangle of the true scene (T rows)."""

    normals: np.ndarray  # (T,3) float32, as the triangle is wound
    u: np.ndarray  # (T,3) float32
    v: np.ndarray  # (T,3) float32
    rect: np.ndarray  # (T,4) float32: umin, vmin, umax, vmax of the triangle's face (s, t)
    parts: np.ndarray  # (T,) int8 scene.PART_*
    labels: np.ndarray  # (T,) int8 scene.LABEL_*
    objects: np.ndarray  # (T,) int32, -1 for the terrain
    faces: np.ndarray  # (T,) int32

    @classmethod
    def of(cls, scene: TrueScene) -> SceneTables:
        tri = scene.triangles
        normals = scene.normals
        u, v = plane_axes(normals)
        s = np.einsum("tkc,tc->tk", tri, u)  # (T,3) per vertex
        t = np.einsum("tkc,tc->tk", tri, v)
        faces = scene.faces if scene.faces is not None else np.arange(len(tri), dtype=np.int32)
        nf = int(faces.max()) + 1 if len(faces) else 0
        lo_s = np.full(nf, np.inf)
        lo_t = np.full(nf, np.inf)
        hi_s = np.full(nf, -np.inf)
        hi_t = np.full(nf, -np.inf)
        np.minimum.at(lo_s, faces, s.min(1))
        np.minimum.at(lo_t, faces, t.min(1))
        np.maximum.at(hi_s, faces, s.max(1))
        np.maximum.at(hi_t, faces, t.max(1))
        rect = np.stack([lo_s[faces], lo_t[faces], hi_s[faces], hi_t[faces]], axis=1)
        parts = scene.parts if scene.parts is not None else scene.labels.astype(np.int8)
        objects = (scene.objects if scene.objects is not None
                   else np.full(len(tri), -1, np.int32))
        return cls(normals.astype(np.float32), u.astype(np.float32), v.astype(np.float32),
                   rect.astype(np.float32), parts, scene.labels, objects, faces)


@dataclass
class Hits:
    """The surface at the first hit of each ray (N rays that hit)."""

    p: np.ndarray  # (N,3) float32 hit points, local
    view: np.ndarray  # (N,3) float32 unit ray directions
    distance: np.ndarray  # (N,) float32 metres along the ray
    tri: np.ndarray  # (N,) triangle ids
    normal: np.ndarray  # (N,3) the triangle's normal turned towards the camera
    s: np.ndarray  # (N,) texture coordinates (m)
    t: np.ndarray
    rect: np.ndarray  # (N,4) the face's rectangle in (s, t)
    part: np.ndarray  # (N,) scene.PART_*
    label: np.ndarray  # (N,) scene.LABEL_*
    obj: np.ndarray  # (N,) object number, -1: terrain
    face: np.ndarray  # (N,) face number
    footprint: np.ndarray  # (N,) metres of surface one pixel covers (geometric mean of its sides)

    @classmethod
    def of(cls, tables: SceneTables, origins: np.ndarray, dirs: np.ndarray,
           distance: np.ndarray, tri: np.ndarray, pixel_angle: float) -> Hits:
        p = origins + dirs * distance[:, None]
        n = tables.normals[tri]
        cos = np.einsum("ij,ij->i", n, dirs)
        n *= np.where(cos > 0, np.float32(-1.0), np.float32(1.0))[:, None]
        # a pixel's footprint is pixel_angle x distance across the view and that over |cos|
        # along it: their geometric mean keeps detail on surfaces seen at grazing angles
        # (roads from a car) that the larger side would blur away
        footprint = distance * np.float32(pixel_angle) / np.sqrt(np.maximum(np.abs(cos), 0.05))
        s = np.einsum("ij,ij->i", p, tables.u[tri])
        t = np.einsum("ij,ij->i", p, tables.v[tri])
        return cls(p, dirs, distance, tri, n, s, t, tables.rect[tri], tables.parts[tri],
                   tables.labels[tri], tables.objects[tri], tables.faces[tri], footprint)

    def __len__(self) -> int:
        return len(self.tri)

    def local(self, i: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Position within the face's rectangle of the hits `i`: (a, b) from its lower-left
        corner (m) and its width and height (m)."""
        r = self.rect[i]
        return self.s[i] - r[:, 0], self.t[i] - r[:, 1], r[:, 2] - r[:, 0], r[:, 3] - r[:, 1]
