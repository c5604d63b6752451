"""Surfaces no camera sees: faces, and parts of faces, that lie inside the city's volume.

A wall between two parts of a building, the wall two adjacent buildings share and the lower part
of a tall wall that a lower neighbour stands against have solid on both sides. No tie point lies
on them, yet they are model planes like any facade: a block placed on them sits metres behind the
surface its images saw. A point X of face f is hidden when X + h n_f and X - h n_f both lie
inside a building (h = `PROBE_DEPTH`, n_f the face's unit normal, either orientation).

Inside a building: an upward ray from the point crosses the roofs and ground surfaces of the
model an odd number of times (LOD2 roofs cover their building's footprint; walls are parallel to
the ray and are not counted). Three rays, offset by millimetres, vote, so that a ray along an
edge shared by two roof triangles does not decide alone.

`visibility(store)` samples every face on a grid and keeps, per face, the share of its area that
is hidden; assignment, the coarse search and the block objective take no point on a hidden face,
and none on the hidden part of a partly hidden one (`Visibility.hidden_at`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from .store import PlaneStore

logger = logging.getLogger(__name__)

#: Metres probed on both sides of a face. Solid within this distance on both sides means no
#: camera can stand in front of the surface: a gap this narrow between two buildings is no
#: street. Larger than a LOD2 model's typical generalisation (0.2 m), so that two walls of
#: neighbours that miss each other by that much still count as one shared wall.
PROBE_DEPTH = 0.5

#: Spacing (m) of the sample points on a face; a large face is sampled more coarsely, so
#: that no face takes more than `MAX_SAMPLES` points.
SAMPLE_SPACING = 1.0
MAX_SAMPLES = 400


#: Classes whose triangles bound a building from above and below: the surfaces an upward ray
#: crosses when it leaves or enters a building.
CAPPING_CLASSES = ("RoofSurface", "GroundSurface", "OuterCeilingSurface", "OuterFloorSurface",
                   "ClosureSurface")

#: Classes that are never sampled: they take no tie points in any case.
UNSEEN_CLASSES = ("GroundSurface", "ClosureSurface")

_JITTER = np.array([[0.0013, 0.0007], [-0.0011, 0.0017], [0.0019, -0.0009]])


def class_mask(store: PlaneStore, classes) -> np.ndarray:
    """(F,) bool: faces whose semantic class is one of `classes`."""
    mask = np.zeros(store.num_faces, bool)
    for name in classes:
        mask |= store.faces.semantic.mask(name)
    return mask


class CityVolume:
    """Inside test for the buildings of a store (local frame): upward-ray parity against its
    roofs and ground surfaces."""

    def __init__(self, store: PlaneStore):
        import open3d as o3d

        from .mesh import triangulate_face

        capping = class_mask(store, CAPPING_CLASSES)
        triangles = [triangulate_face(store, int(f)) for f in np.flatnonzero(capping)]
        triangles = (np.concatenate(triangles) if triangles else np.zeros((0, 3), np.int64))
        self.num_triangles = len(triangles)
        self._scene = o3d.t.geometry.RaycastingScene()
        if len(triangles):
            self._scene.add_triangles(
                o3d.core.Tensor(np.ascontiguousarray(store.vertices, np.float32)),
                o3d.core.Tensor(np.ascontiguousarray(triangles, np.uint32)))

    def inside(self, points: np.ndarray) -> np.ndarray:
        """(P,) bool: the points that lie inside a building."""
        import open3d as o3d

        points = np.asarray(points, np.float64).reshape(-1, 3)
        if not len(points) or not self.num_triangles:
            return np.zeros(len(points), bool)
        votes = np.zeros(len(points), np.int64)
        for dx, dy in _JITTER:
            rays = np.zeros((len(points), 6), np.float32)
            rays[:, :3] = points + (dx, dy, 0.0)
            rays[:, 5] = 1.0
            counts = self._scene.count_intersections(o3d.core.Tensor(rays)).numpy()
            votes += counts % 2
        return votes >= 2


@dataclass
class Visibility:
    """Which faces of a store, and which parts of them, a camera can see."""

    hidden_share: np.ndarray  # (F,) share of the face's sample points that are hidden
    volume: CityVolume
    # Partly hidden faces: face -> the hidden part as a polygon in the face's 2D frame
    # (the union of the grid cells of its hidden sample points).
    hidden_parts: dict = field(default_factory=dict)

    @property
    def hidden(self) -> np.ndarray:
        """(F,) bool: faces hidden as a whole (no sample point of theirs is visible)."""
        return self.hidden_share >= 1.0

    @property
    def partial(self) -> np.ndarray:
        """(F,) bool: faces with a hidden part and a visible rest."""
        return (self.hidden_share > 0) & ~self.hidden

    def hidden_at(self, points: np.ndarray, faces: np.ndarray, normals: np.ndarray
                  ) -> np.ndarray:
        """(P,) bool: is the surface of `faces[i]` hidden where `points[i]` lies on it?
        `points` are on (or near) the faces' planes; `normals` their faces' unit normals."""
        points = np.asarray(points, np.float64).reshape(-1, 3)
        faces = np.asarray(faces, np.int64)
        out = self.hidden[faces].copy()
        probe = np.flatnonzero(self.partial[faces])
        if len(probe):
            out[probe] = both_sides_inside(self.volume, points[probe], normals[probe])
        return out

    def summary(self) -> dict:
        return {"hidden_faces": int(np.count_nonzero(self.hidden)),
                "partly_hidden_faces": int(np.count_nonzero(self.partial))}


def both_sides_inside(volume: CityVolume, points: np.ndarray, normals: np.ndarray
                      ) -> np.ndarray:
    """(P,) bool: points with a building on both sides of their surface (`PROBE_DEPTH`)."""
    offset = PROBE_DEPTH * np.asarray(normals, np.float64)
    return volume.inside(points + offset) & volume.inside(points - offset)


def face_samples(store: PlaneStore, faces: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Grid points inside each face's polygon: (points (S, 3) local frame, face of each,
    their (u, v) in the face's 2D frame (S, 2), the grid spacing of each face (F,))."""
    edges = store._edges2d()
    points, owners, uvs = [], [], []
    steps = np.zeros(store.num_faces)
    for f in faces:
        lo_u, hi_u = edges["lo_u"][f], edges["hi_u"][f]
        lo_v, hi_v = edges["lo_v"][f], edges["hi_v"][f]
        extent = max(hi_u - lo_u, 1e-9) * max(hi_v - lo_v, 1e-9)
        step = steps[f] = max(SAMPLE_SPACING, float(np.sqrt(extent / MAX_SAMPLES)))
        u = np.arange(lo_u + step / 2, hi_u, step)
        v = np.arange(lo_v + step / 2, hi_v, step)
        if not len(u) or not len(v):
            u, v = np.array([(lo_u + hi_u) / 2]), np.array([(lo_v + hi_v) / 2])
        uu, vv = (a.ravel() for a in np.meshgrid(u, v))
        inside = store._inside_pairs(np.full(len(uu), f, np.int64), uu, vv, 0.0)
        if not inside.any():  # a sliver narrower than the grid: its centroid stands for it
            uu, vv = np.zeros(1), np.zeros(1)
        else:
            uu, vv = uu[inside], vv[inside]
        R, c = store.rotations[f], store.centroids[f]
        points.append(c + np.outer(uu, R[:, 0]) + np.outer(vv, R[:, 1]))
        owners.append(np.full(len(uu), f, np.int64))
        uvs.append(np.stack([uu, vv], axis=1))
    if not points:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 2)), steps
    return np.concatenate(points), np.concatenate(owners), np.concatenate(uvs), steps


def compute_visibility(store: PlaneStore) -> Visibility:
    """The hidden share of every face of `store` (see the module docstring)."""
    volume = CityVolume(store)
    share = np.zeros(store.num_faces)
    sampled = np.flatnonzero(~class_mask(store, UNSEEN_CLASSES))
    parts = {}
    if len(sampled) and volume.num_triangles:
        points, owner, uv, steps = face_samples(store, sampled)
        hidden = both_sides_inside(volume, points, store.normals[owner])
        share = (np.bincount(owner, weights=hidden, minlength=store.num_faces)
                 / np.maximum(np.bincount(owner, minlength=store.num_faces), 1))
        partial = (share > 0) & (share < 1.0)
        for f in np.flatnonzero(partial):
            cells = uv[(owner == f) & hidden]
            parts[int(f)] = cell_union(cells, steps[f])
    result = Visibility(share, volume, parts)
    logger.debug("visibility: %d faces hidden, %d partly", *result.summary().values())
    return result


def cell_union(centres: np.ndarray, step: float):
    """The union of the square grid cells (side `step`) around `centres` (K, 2), as a shapely
    geometry with the cells' staircase along straight edges merged."""
    import shapely

    half = step / 2.0
    boxes = shapely.box(centres[:, 0] - half, centres[:, 1] - half,
                        centres[:, 0] + half, centres[:, 1] + half)
    return shapely.union_all(boxes).simplify(step * 0.01)


def visibility(store: PlaneStore) -> Visibility:
    """`compute_visibility(store)`, computed once per store."""
    cached = store._cache.get("visibility")
    if cached is None:
        cached = store._cache["visibility"] = compute_visibility(store)
    return cached


def visible_triangles(store: PlaneStore, excluded_classes=UNSEEN_CLASSES
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The surfaces tie points can lie on as triangles: (vertices (V, 3), triangles (T, 3),
    face of each triangle). Hidden faces are left out; of a partly hidden face only its
    visible part is kept (its polygon less the hidden grid cells)."""
    from .mesh import triangulate_face

    vis = visibility(store)
    excluded = class_mask(store, excluded_classes) | vis.hidden
    vertices = [np.asarray(store.vertices, np.float64)]
    triangles, owners = [], []
    base = len(store.vertices)
    for f in np.flatnonzero(~excluded):
        if int(f) in vis.hidden_parts:
            v, t = visible_part_triangles(store, int(f), vis.hidden_parts[int(f)])
            t = t + base
            vertices.append(v)
            base += len(v)
        else:
            t = triangulate_face(store, int(f))
        triangles.append(t)
        owners.append(np.full(len(t), f, np.int64))
    if not triangles:
        return vertices[0], np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    return (np.concatenate(vertices), np.concatenate(triangles).astype(np.int64),
            np.concatenate(owners))


def visible_part_triangles(store: PlaneStore, f: int, hidden_part
                           ) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) local frame, triangles (T, 3) into them): face `f` less `hidden_part`
    (a polygon in its 2D frame), triangulated with earcut."""
    import mapbox_earcut
    import shapely

    face = store.faces[f]
    R, c = store.rotations[f], store.centroids[f]

    def uv(ring):
        return (store.vertices[ring] - c) @ R[:, :2]

    polygon = shapely.Polygon(uv(face.exterior), [uv(h) for h in face.holes]).buffer(0)
    visible = polygon.difference(hidden_part)
    vertices, triangles, base = [], [], 0
    for piece in getattr(visible, "geoms", [visible]):
        if not isinstance(piece, shapely.Polygon) or piece.is_empty or piece.area <= 0:
            continue
        rings = [np.asarray(piece.exterior.coords)[:-1]]
        rings += [np.asarray(r.coords)[:-1] for r in piece.interiors]
        points = np.concatenate(rings)
        ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
        tri = mapbox_earcut.triangulate_float64(np.ascontiguousarray(points), ends)
        vertices.append(c + points @ R[:, :2].T)
        triangles.append(tri.reshape(-1, 3).astype(np.int64) + base)
        base += len(points)
    if not vertices:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(vertices), np.concatenate(triangles)
