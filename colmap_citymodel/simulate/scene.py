"""Scenes of the UAV simulator (Unger 5.1.1, 5.2.2): the given LOD2 model, its error
variants, and the *true* scene that the simulated camera sees.

- The given model is a PlaneStore: a real CityGML/CityJSON file read by `read_city_model`, or a
  procedural street (a row of box buildings with gable, hip or flat roofs along a street).
- The true scene is that model plus generalisation effects a LOD2 model does not have (Unger
  Fig. 10): facade relief (pilasters +0.1 m, window recesses -0.12 m), entrances and garage doors
  0.5-1 m behind the wall, balconies 1 m out with balustrades, roof overhangs on sloped roofs,
  parapets on flat roofs, roof furniture (chimneys, boxes), optionally dormers, clutter in front
  of facades (trees, cars, optionally street furniture) and the terrain. It is a triangle mesh
  (for sampling points, ray casting and rendering; each triangle knows its part: window, reveal,
  door, chimney, crown, car, ...; its object: a building or one clutter object; and the planar
  face it was cut from) plus the planar polygons of the buildings (the *detailed* model,
  LOD3-like, for Scn1).
- Model variants: "corrected" = the LOD2 model as given (its planes are the true scene's main
  planes, only generalisation effects differ), "original" = the same topology with systematic
  plane errors (per face a shift N(0, 0.2 m) along the normal and a tilt N(0, 0.5 deg); every
  vertex then moves to the least-squares intersection of its (perturbed) planes, so shared
  vertices stay shared and faces stay nearly planar), "detailed" = the true building polygons.

All coordinates here are local (CRS minus `store.origin`), float64.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import mapbox_earcut
import numpy as np
import shapely
from shapely.geometry import Polygon, box
from shapely.geometry.polygon import orient

from ..citymodel.raw_model import RawPolygon
from ..citymodel.store import PlaneStore
from ..citymodel.build import store_from_polygons

logger = logging.getLogger(__name__)

# triangle labels of the true mesh
LABEL_WALL, LABEL_ROOF, LABEL_DETAIL, LABEL_CLUTTER, LABEL_GROUND = 0, 1, 2, 3, 4
LABEL_NAMES = ("wall", "roof", "detail", "clutter", "ground")

# What each triangle is a part of, finer than its label (the renderer's materials): the label's
# own part (wall, roof, detail, clutter, ground) unless a detail or clutter object says more.
(PART_WALL, PART_ROOF, PART_DETAIL, PART_CLUTTER, PART_GROUND, PART_WINDOW, PART_REVEAL,
 PART_DOOR, PART_GARAGE, PART_PILASTER, PART_BALCONY, PART_OVERHANG, PART_PARAPET,
 PART_CHIMNEY, PART_CROWN, PART_TRUNK, PART_CAR, PART_FURNITURE) = range(18)
PART_NAMES = ("wall", "roof", "detail", "clutter", "ground", "window", "reveal", "door",
              "garage", "pilaster", "balcony", "overhang", "parapet", "chimney", "crown",
              "trunk", "car", "furniture")

# Random streams: each stage draws from its own generator np.random.default_rng([seed, stage,
# ...]), so changing one stage's options never changes another stage's random numbers.
STAGE_PROCEDURAL, STAGE_DETAILS, STAGE_ERRORS, STAGE_CLUTTER = 11, 12, 13, 14
STAGE_FURNITURE, STAGE_DORMERS = 15, 16


@dataclass
class ProceduralOptions:
    """A row of buildings along a street (x axis); street facades face -y."""

    num_buildings: int = 14
    width_range: tuple[float, float] = (9.0, 22.0)  # along the street (m)
    depth_range: tuple[float, float] = (10.0, 15.0)
    eave_height_range: tuple[float, float] = (7.0, 17.0)
    roof_pitch_range_deg: tuple[float, float] = (25.0, 40.0)
    roof_types: tuple[str, ...] = ("gable", "gable_street", "hip", "flat")
    gap_probability: float = 0.3  # chance of a gap (side walls visible) before a building
    gap_range: tuple[float, float] = (3.0, 9.0)
    setback_range: tuple[float, float] = (0.0, 2.0)  # front facade behind the street line
    # an ETRS89/UTM 32N origin so CRS coordinates have 6-7 digits like real data
    crs: str = "EPSG:25832"
    origin: tuple[float, float, float] = (691000.0, 5336000.0, 515.0)


@dataclass
class DetailOptions:
    """Generalisation effects of the true scene (magnitudes from Unger 5.2.2 / Fig. 10)."""

    bay_width: float = 3.6  # window axis spacing along facades (m)
    storey_height: float = 3.0
    window_size: tuple[float, float] = (1.2, 1.5)  # width, height
    window_depth: float = 0.12  # recess of windows behind the wall plane
    pilaster_width: float = 0.5
    pilaster_depth: float = 0.1  # prongs in front of the wall plane
    pilaster_every: int = 2  # a pilaster every n bays (0: none)
    entrance_probability: float = 0.12  # per ground-floor bay
    garage_probability: float = 0.08
    entrance_depth_range: tuple[float, float] = (0.5, 1.0)  # recessed entrances/garage doors
    balcony_probability: float = 0.12  # per upper-storey bay (walls with >= 3 storeys)
    balcony_depth: float = 1.0
    balustrade_height: float = 1.0
    roof_overhang: float = 0.5  # horizontal eave/verge overhang of sloped roofs
    parapet_height: float = 0.8  # on flat roofs
    parapet_thickness: float = 0.25
    roof_furniture_per_100m2: float = 1.5  # chimneys, vents, boxes
    tree_spacing: float = 14.0  # mean spacing of trees in front of facades (0: none)
    car_spacing: float = 18.0  # mean spacing of parked cars (0: none)
    camera_clearance: float = 3.0  # no clutter closer than this to a camera
    ground_cell: float = 4.0  # terrain grid cell (m)
    # The street's shape beside the buildings' feet (GroundModel): pavements sidewalk_width
    # wide along the footprints stand kerb_height above the road, and the road falls by
    # road_cross_slope per metre from the kerb (up to ROAD_CAMBER_WIDTH m out). 0: flat.
    kerb_height: float = 0.0
    sidewalk_width: float = 3.0
    road_cross_slope: float = 0.0
    min_wall_length: float = 2.0  # smaller walls stay plain
    # Street furniture (lamp posts, bollards, benches, sign posts) in front of decorated
    # facades: one per furniture_spacing metres of facade on average (0: none, the default,
    # which keeps the scenes of earlier sequences unchanged). Drawn from its own random stream.
    furniture_spacing: float = 0.0
    # Dormers: the chance that a sloped roof face near the flight (at least DORMER_MIN_AREA m^2)
    # carries a row of one to three dormers with a window each (0: none, the default).
    dormer_probability: float = 0.0


@dataclass
class ModelErrorOptions:
    """Systematic errors of the "original" model and imperfections of the "detailed" one."""

    shift_sigma: float = 0.2  # per face, along its normal (m)
    rotation_sigma_deg: float = 0.5  # per face, tilt about an in-plane axis through its centroid
    detailed_shift_sigma: float = 0.02  # per polygon of the detailed model
    detailed_rotation_sigma_deg: float = 0.1
    detailed_min_area: float = 0.5  # smaller true polygons are left out of the detailed model
    # Whole buildings the given model (every variant) gets wrong, as an outdated or
    # incomplete city model does (simulate.buildings): `missing_buildings` of the true
    # buildings near the flight (footprint within the observations' max_distance of a camera)
    # left out of it, at least one near building kept; `extra_buildings` flat-roofed boxes in
    # it where the true scene has none (a demolished building), in front of the cameras, each
    # side drawn from extra_size_range (m) and its height from extra_height_range (m). 0: none.
    missing_buildings: int = 0
    extra_buildings: int = 0
    extra_size_range: tuple[float, float] = (8.0, 16.0)
    extra_height_range: tuple[float, float] = (5.0, 14.0)


@dataclass
class TrueScene:
    triangles: np.ndarray  # (T,3,3) local coordinates
    labels: np.ndarray  # (T,) int8 LABEL_*
    polygons: list[RawPolygon]  # building polygons of the true scene, LOCAL coordinates
    num_clutter_objects: int = 0
    # per triangle: PART_* (what it is a part of), the object it belongs to (a building or one
    # clutter object, numbered from 0; -1: the terrain) and the planar face it was cut from (a
    # polygon, a quad or the triangle itself), numbered from 0
    parts: np.ndarray | None = None
    objects: np.ndarray | None = None
    faces: np.ndarray | None = None

    @property
    def normals(self) -> np.ndarray:
        n = np.cross(self.triangles[:, 1] - self.triangles[:, 0],
                     self.triangles[:, 2] - self.triangles[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-15)

    @property
    def areas(self) -> np.ndarray:
        n = np.cross(self.triangles[:, 1] - self.triangles[:, 0],
                     self.triangles[:, 2] - self.triangles[:, 0])
        return 0.5 * np.linalg.norm(n, axis=1)

    def to_trimesh(self):
        import trimesh

        v = self.triangles.reshape(-1, 3)
        f = np.arange(len(v)).reshape(-1, 3)
        return trimesh.Trimesh(vertices=v, faces=f, process=False)

    def raycasting_scene(self):
        """An open3d RaycastingScene of the true mesh (float32, local coordinates)."""
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        v = self.triangles.reshape(-1, 3).astype(np.float32)
        f = np.arange(len(v), dtype=np.uint32).reshape(-1, 3)
        scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(f))
        return scene


# ----------------------------------------------------------------------------------------------
# polygon helpers


def newell_normal(ring: np.ndarray) -> np.ndarray:
    """Unit normal of a planar ring by Newell's method (sign from the ring's orientation)."""
    r = np.asarray(ring, dtype=np.float64)
    c = r - r.mean(0)
    nxt = np.roll(c, -1, axis=0)
    n = np.array(
        [
            np.sum((c[:, 1] - nxt[:, 1]) * (c[:, 2] + nxt[:, 2])),
            np.sum((c[:, 2] - nxt[:, 2]) * (c[:, 0] + nxt[:, 0])),
            np.sum((c[:, 0] - nxt[:, 0]) * (c[:, 1] + nxt[:, 1])),
        ]
    )
    norm = np.linalg.norm(n)
    return n / norm if norm > 0 else n


def plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(u, v) orthonormal in-plane axes: u horizontal where possible, v = n x u."""
    n = normal / np.linalg.norm(normal)
    u = np.cross([0.0, 0.0, 1.0], n)
    if np.linalg.norm(u) < 1e-6:  # horizontal plane: u along x
        u = np.array([1.0, 0.0, 0.0]) - n[0] * n
    u /= np.linalg.norm(u)
    return u, np.cross(n, u)


def triangulate_rings(exterior: np.ndarray, holes=()) -> np.ndarray:
    """(K,3,3) triangles of a planar 3D polygon with holes (earcut in the polygon's plane)."""
    rings = [np.asarray(exterior, dtype=np.float64)] + [np.asarray(h, dtype=np.float64)
                                                        for h in holes]
    pts = np.concatenate(rings)
    n = newell_normal(rings[0])
    if not np.any(n):
        return np.zeros((0, 3, 3))
    u, v = plane_basis(n)
    c = pts - pts.mean(0)
    xy = np.stack([c @ u, c @ v], axis=1)
    ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
    idx = mapbox_earcut.triangulate_float64(xy, ends)
    return pts[np.asarray(idx, dtype=np.int64).reshape(-1, 3)]


def semantic_from_normal(normal: np.ndarray) -> str:
    if normal[2] >= 0.7:
        return "RoofSurface"
    if normal[2] <= -0.7:
        return "OuterCeilingSurface"
    return "WallSurface"


_LABEL_PART = {LABEL_WALL: PART_WALL, LABEL_ROOF: PART_ROOF, LABEL_DETAIL: PART_DETAIL,
               LABEL_CLUTTER: PART_CLUTTER, LABEL_GROUND: PART_GROUND}


class MeshBuilder:
    """Accumulates labelled triangles and the building polygons they come from; per triangle
    also its part, object and face (TrueScene)."""

    def __init__(self):
        self._tris: list[np.ndarray] = []
        self._labels: list[np.ndarray] = []
        self._parts: list[np.ndarray] = []
        self._objects: list[np.ndarray] = []
        self._faces: list[np.ndarray] = []
        self._num_faces = 0
        self._num_objects = 0
        self._building_objects: dict[str, int] = {}
        self.polygons: list[RawPolygon] = []

    def new_object(self) -> int:
        """A fresh object number (a clutter object: a tree, a car, a lamp post)."""
        self._num_objects += 1
        return self._num_objects - 1

    def _object(self, building_id: str, obj: int | None) -> int:
        """`obj` when given, else the building's number (-1 without a building)."""
        if obj is not None:
            return obj
        if not building_id:
            return -1
        if building_id not in self._building_objects:
            self._building_objects[building_id] = self.new_object()
        return self._building_objects[building_id]

    def _append(self, tris: np.ndarray, label: int, part: int | None, obj: int,
                faces: np.ndarray) -> None:
        n = len(tris)
        self._tris.append(tris)
        self._labels.append(np.full(n, label, dtype=np.int8))
        self._parts.append(np.full(n, _LABEL_PART[label] if part is None else part, np.int8))
        self._objects.append(np.full(n, obj, dtype=np.int32))
        self._faces.append(self._num_faces + faces.astype(np.int32))
        self._num_faces += int(faces.max()) + 1 if n else 0

    def add(self, exterior, holes=(), *, label: int, building_id: str = "",
            semantic: str | None = None, polygon: bool = True, part: int | None = None,
            obj: int | None = None) -> None:
        exterior = np.asarray(exterior, dtype=np.float64)
        holes = [np.asarray(h, dtype=np.float64) for h in holes]
        tris = triangulate_rings(exterior, holes)
        if len(tris) == 0:
            return
        self._append(tris, label, part, self._object(building_id, obj),
                     np.zeros(len(tris), np.int32))
        if polygon and label != LABEL_CLUTTER and label != LABEL_GROUND:
            self.polygons.append(
                RawPolygon(
                    exterior=exterior,
                    holes=holes,
                    semantic=semantic or semantic_from_normal(newell_normal(exterior)),
                    building_id=building_id,
                    gml_id="",
                )
            )

    def add_quads(self, quads: np.ndarray, *, label: int, building_id: str = "",
                  polygon: bool = True, part: int | None = None,
                  obj: int | None = None) -> None:
        """Planar convex quads (K,4,3), already oriented: two triangles each, no earcut."""
        quads = np.asarray(quads, dtype=np.float64).reshape(-1, 4, 3)
        if len(quads) == 0:
            return
        tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
        self._append(tris, label, part, self._object(building_id, obj),
                     np.tile(np.arange(len(quads), dtype=np.int32), 2))
        if polygon and label != LABEL_CLUTTER and label != LABEL_GROUND:
            nrm = np.cross(quads[:, 1] - quads[:, 0], quads[:, 2] - quads[:, 0])
            nz = nrm[:, 2] / np.maximum(np.linalg.norm(nrm, axis=1), 1e-15)
            for q, z in zip(quads, nz):
                sem = "RoofSurface" if z >= 0.7 else (
                    "OuterCeilingSurface" if z <= -0.7 else "WallSurface")
                self.polygons.append(RawPolygon(exterior=q, semantic=sem,
                                                building_id=building_id))

    def add_triangles(self, tris: np.ndarray, label: int, *, parts=None,
                      obj: int = -1) -> None:
        """Loose triangles, each its own face; `parts`: one PART_* or one per triangle."""
        tris = np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)
        if len(tris) == 0:
            return
        self._append(tris, label, None, obj, np.arange(len(tris), dtype=np.int32))
        if parts is not None:
            self._parts[-1][:] = parts

    def merge(self, other: MeshBuilder, *, obj: int) -> None:
        """Another builder's triangles (its parts and faces kept), all as object `obj`."""
        for tris, label, part, face in zip(other._tris, other._labels, other._parts,
                                           other._faces):
            self._append(tris, int(label[0]), None, obj, face - face.min())
            self._parts[-1][:] = part
        self.polygons += other.polygons

    @property
    def triangles(self) -> np.ndarray:
        """(T,3,3) all triangles so far."""
        return np.concatenate(self._tris) if self._tris else np.zeros((0, 3, 3))

    def scene(self, num_clutter_objects: int = 0) -> TrueScene:
        tris = self.triangles
        labels = np.concatenate(self._labels) if self._labels else np.zeros(0, np.int8)

        def joined(parts, dtype):
            return np.concatenate(parts) if parts else np.zeros(0, dtype)

        return TrueScene(tris, labels, self.polygons, num_clutter_objects,
                         parts=joined(self._parts, np.int8),
                         objects=joined(self._objects, np.int32),
                         faces=joined(self._faces, np.int32))


@dataclass
class _Frame:
    """A facade frame: origin, u (horizontal along the wall), v (up the wall), n (outward)."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    n: np.ndarray

    def to3d(self, xy: np.ndarray, depth: float = 0.0) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        return self.origin + xy[:, :1] * self.u + xy[:, 1:2] * self.v + depth * self.n

    def to2d(self, pts: np.ndarray) -> np.ndarray:
        c = np.asarray(pts, dtype=np.float64) - self.origin
        return np.stack([c @ self.u, c @ self.v], axis=1)


def _rings2d(poly: Polygon) -> list[np.ndarray]:
    poly = orient(poly, 1.0)  # exterior counter-clockwise, holes clockwise
    return [np.asarray(poly.exterior.coords)[:-1]] + [
        np.asarray(r.coords)[:-1] for r in poly.interiors
    ]


def _polygons_of(geom) -> list[Polygon]:
    if geom.is_empty:
        return []
    if isinstance(geom, Polygon):
        return [geom]
    return [g for g in getattr(geom, "geoms", []) if isinstance(g, Polygon) and g.area > 1e-6]


def _cap(mb: MeshBuilder, fr: _Frame, region: Polygon, depth: float, facing: float,
         label: int, bid: str, part: int | None = None) -> None:
    """A planar face of `region` at `depth`; facing=+1 looks along n, -1 against it."""
    rings = _rings2d(region)
    if len(rings) == 1 and len(rings[0]) == 4:  # rectangles (most details): no earcut
        quad = fr.to3d(rings[0], depth)  # counter-clockwise in (u, v): faces +n
        mb.add_quads((quad if facing > 0 else quad[::-1])[None], label=label, building_id=bid,
                     part=part)
        return
    ext3 = fr.to3d(rings[0], depth)
    holes3 = [fr.to3d(r, depth) for r in rings[1:]]
    if facing < 0:
        ext3 = ext3[::-1]
        holes3 = [h[::-1] for h in holes3]
    mb.add(ext3, holes3, label=label, building_id=bid,
           semantic="WallSurface" if abs(fr.n[2]) < 0.7 else None, part=part)


def _extrude(mb: MeshBuilder, fr: _Frame, region: Polygon, d0: float, d1: float, *,
             cap0: bool, cap1: bool, label: int, bid: str, part: int | None = None,
             side_part: int | None = None) -> None:
    """A prism of the 2D `region` between depths d0 and d1 along the facade normal; its caps
    are `part`, its sides `side_part` (default: `part`)."""
    if region.is_empty or region.area < 1e-4:
        return
    if cap1:
        _cap(mb, fr, region, d1, 1.0 if d1 >= d0 else -1.0, label, bid, part)
    if cap0:
        _cap(mb, fr, region, d0, -1.0 if d1 >= d0 else 1.0, label, bid, part)
    for ring in _rings2d(region):
        nxt = np.roll(ring, -1, axis=0)
        keep = np.linalg.norm(nxt - ring, axis=1) > 1e-6
        a, b = ring[keep], nxt[keep]
        if len(a) == 0:
            continue
        quads = np.stack([fr.to3d(a, d0), fr.to3d(b, d0), fr.to3d(b, d1), fr.to3d(a, d1)],
                         axis=1)
        # orient outward: the 2D outward normal of a CCW ring edge a->b is (dy, -dx)
        out3 = (b[:, 1] - a[:, 1])[:, None] * fr.u - (b[:, 0] - a[:, 0])[:, None] * fr.v
        nrm = np.cross(quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0])
        flip = np.einsum("ij,ij->i", nrm, out3) < 0
        quads[flip] = quads[flip][:, ::-1]
        mb.add_quads(quads, label=label, building_id=bid,
                     part=part if side_part is None else side_part)


# ----------------------------------------------------------------------------------------------
# the given model


def procedural_street(options: ProceduralOptions, seed: int):
    """The LOD2 model of a procedural street: polygons (CRS coordinates), semantics, building
    ids. Buildings stand side by side along +x, street facades at y = setback facing -y."""
    rng = np.random.default_rng([seed, STAGE_PROCEDURAL])
    o = np.asarray(options.origin, dtype=np.float64)
    polygons, semantics, bids = [], [], []
    x = 0.0
    for i in range(options.num_buildings):
        if i > 0 and rng.random() < options.gap_probability:
            x += rng.uniform(*options.gap_range)
        w = rng.uniform(*options.width_range)
        d = rng.uniform(*options.depth_range)
        y0 = rng.uniform(*options.setback_range)
        h = rng.uniform(*options.eave_height_range)
        pitch = math.radians(rng.uniform(*options.roof_pitch_range_deg))
        kind = options.roof_types[rng.integers(len(options.roof_types))]
        if kind == "hip" and w < d + 2.0:
            kind = "gable"
        bid = f"BLDG_{i:04d}"
        for ring, sem in _box_building(x, x + w, y0, y0 + d, h, pitch, kind):
            polygons.append(ring + o)
            semantics.append(sem)
            bids.append(bid)
        x += w
    return polygons, semantics, bids


def _box_building(x0, x1, y0, y1, h, pitch, kind):
    """Rings (local, outward counter-clockwise) of one building on z = 0."""
    c = np.array([(x0 + x1) / 2, (y0 + y1) / 2, h / 2])
    out = []

    def add(pts, sem):
        ring = np.asarray(pts, dtype=np.float64)
        nrm = newell_normal(ring)
        centre = ring.mean(0)
        ref = centre - c
        if sem == "GroundSurface":
            ref = np.array([0.0, 0.0, -1.0])
        if np.dot(nrm, ref) < 0:
            ring = ring[::-1]
        out.append((ring, sem))

    add([[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]], "GroundSurface")
    ym, xm = (y0 + y1) / 2, (x0 + x1) / 2
    if kind == "flat":
        for a, b in [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)),
                     ((x0, y1), (x0, y0))]:
            add([[*a, 0], [*b, 0], [*b, h], [*a, h]], "WallSurface")
        add([[x0, y0, h], [x1, y0, h], [x1, y1, h], [x0, y1, h]], "RoofSurface")
    elif kind == "gable":  # ridge along x (eaves to the street)
        H = h + (y1 - y0) / 2 * math.tan(pitch)
        add([[x0, y0, 0], [x1, y0, 0], [x1, y0, h], [x0, y0, h]], "WallSurface")
        add([[x0, y1, 0], [x1, y1, 0], [x1, y1, h], [x0, y1, h]], "WallSurface")
        add([[x0, y0, 0], [x0, y1, 0], [x0, y1, h], [x0, ym, H], [x0, y0, h]], "WallSurface")
        add([[x1, y0, 0], [x1, y1, 0], [x1, y1, h], [x1, ym, H], [x1, y0, h]], "WallSurface")
        add([[x0, y0, h], [x1, y0, h], [x1, ym, H], [x0, ym, H]], "RoofSurface")
        add([[x0, y1, h], [x1, y1, h], [x1, ym, H], [x0, ym, H]], "RoofSurface")
    elif kind == "gable_street":  # ridge along y (gable facing the street)
        H = h + (x1 - x0) / 2 * math.tan(pitch)
        add([[x0, y0, 0], [x1, y0, 0], [x1, y0, h], [xm, y0, H], [x0, y0, h]], "WallSurface")
        add([[x0, y1, 0], [x1, y1, 0], [x1, y1, h], [xm, y1, H], [x0, y1, h]], "WallSurface")
        add([[x0, y0, 0], [x0, y1, 0], [x0, y1, h], [x0, y0, h]], "WallSurface")
        add([[x1, y0, 0], [x1, y1, 0], [x1, y1, h], [x1, y0, h]], "WallSurface")
        add([[x0, y0, h], [x0, y1, h], [xm, y1, H], [xm, y0, H]], "RoofSurface")
        add([[x1, y0, h], [x1, y1, h], [xm, y1, H], [xm, y0, H]], "RoofSurface")
    elif kind == "hip":
        r = (y1 - y0) / 2
        H = h + r * math.tan(pitch)
        for a, b in [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)),
                     ((x0, y1), (x0, y0))]:
            add([[*a, 0], [*b, 0], [*b, h], [*a, h]], "WallSurface")
        add([[x0, y0, h], [x1, y0, h], [x1 - r, ym, H], [x0 + r, ym, H]], "RoofSurface")
        add([[x0, y1, h], [x1, y1, h], [x1 - r, ym, H], [x0 + r, ym, H]], "RoofSurface")
        add([[x0, y0, h], [x0, y1, h], [x0 + r, ym, H]], "RoofSurface")
        add([[x1, y0, h], [x1, y1, h], [x1 - r, ym, H]], "RoofSurface")
    else:
        raise ValueError(f"unknown roof type {kind!r}")
    return out


def procedural_store(options: ProceduralOptions, seed: int) -> PlaneStore:
    from ..citymodel.crs import user_crs

    polygons, semantics, bids = procedural_street(options, seed)
    return store_from_polygons(polygons, semantics=semantics, building_ids=bids,
                               crs=user_crs(options.crs))


def building_footprints(store: PlaneStore) -> dict[str, Polygon]:
    """Horizontal footprint per building: union of its ground/roof faces projected to xy (walls
    alone when a building has neither)."""
    groups: dict[str, list] = {}
    for f, face in enumerate(store.faces):
        groups.setdefault(face.building_id, []).append(f)
    out = {}
    for bid, faces in groups.items():
        areal = [f for f in faces if store.faces[f].semantic in ("GroundSurface", "RoofSurface")]
        geoms = []
        for f in areal or faces:
            xy = store.vertices[store.faces[f].exterior][:, :2]
            p = Polygon(xy)
            if not p.is_valid:
                p = p.buffer(0)
            if p.area > 1e-3:
                geoms.append(p)
        if not geoms:  # only vertical faces: hull of their vertices
            pts = np.concatenate([store.vertices[store.faces[f].exterior][:, :2] for f in faces])
            geoms = [shapely.MultiPoint(pts).convex_hull]
        out[bid] = shapely.unary_union(geoms).buffer(0)
    return out


#: Metres from the kerb over which a road's cross slope falls (half a carriageway).
ROAD_CAMBER_WIDTH = 6.0


class GroundModel:
    """Terrain height: linear interpolation of the buildings' lowest vertices (nearest outside
    their hull). Real LOD2 models put GroundSurfaces at the terrain; this is the street level.
    With `details` (DetailOptions) kerbs, pavements and the road's cross slope are added."""

    def __init__(self, store: PlaneStore, details: DetailOptions | None = None):
        self._shape = None
        if details is not None and (details.kerb_height or details.road_cross_slope):
            self._shape = (details, _footprint_edges(store))
        self._feet(store)

    def _feet(self, store: PlaneStore) -> None:
        from scipy.interpolate import LinearNDInterpolator, NearestNDInterpolator

        pts = []
        groups: dict[str, list[int]] = {}
        for f, face in enumerate(store.faces):
            groups.setdefault(face.building_id, []).append(f)
        for faces in groups.values():
            ids = np.unique(np.concatenate([store.faces[f].exterior for f in faces]))
            v = store.vertices[ids]
            zmin = v[:, 2].min()
            low = v[v[:, 2] < zmin + 0.5]
            pts.append(np.c_[low[:, :2], np.full(len(low), zmin)])
        pts = np.concatenate(pts)
        self._nearest = NearestNDInterpolator(pts[:, :2], pts[:, 2])
        self._linear = None
        if len(pts) >= 4 and np.ptp(pts[:, 0]) > 1 and np.ptp(pts[:, 1]) > 1:
            try:
                self._linear = LinearNDInterpolator(pts[:, :2], pts[:, 2])
            except Exception:  # degenerate (collinear) input: nearest only
                self._linear = None

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        z = np.full(len(xy), np.nan)
        if self._linear is not None:
            z = self._linear(xy)
        bad = ~np.isfinite(z)
        if bad.any():
            z[bad] = self._nearest(xy[bad])
        if self._shape is not None:
            details, (edges, footprints) = self._shape
            d = edges.query(xy)[0]
            d[shapely.contains_xy(footprints, xy[:, 0], xy[:, 1])] = 0.0
            road = d > details.sidewalk_width
            z = z - details.kerb_height * road - details.road_cross_slope * np.clip(
                d - details.sidewalk_width, 0.0, ROAD_CAMBER_WIDTH)
        return z


def _footprint_edges(store: PlaneStore, step: float = 0.25):
    """A KD-tree of points every `step` m along the buildings' footprint outlines, and the
    footprints (shapely, local xy)."""
    from scipy.spatial import cKDTree

    union = shapely.unary_union(list(building_footprints(store).values()))
    points = []
    for poly in _polygons_of(union):
        for ring in [poly.exterior, *poly.interiors]:
            n = max(int(ring.length / step), 4)
            points.append(np.array([ring.interpolate(t, normalized=True).coords[0]
                                    for t in np.linspace(0, 1, n, endpoint=False)]))
    shapely.prepare(union)
    return cKDTree(np.concatenate(points)[:, :2]), union


# ----------------------------------------------------------------------------------------------
# model variants


def perturb_planes(store: PlaneStore, options: ModelErrorOptions, seed: int) -> PlaneStore:
    """Unger's "original" model: systematic plane errors with shared vertices moved consistently.

    Per face f: the plane turns by N(0, rotation_sigma) about a random in-plane axis through its
    centroid and shifts by N(0, shift_sigma) along its normal. Each vertex then moves to
    argmin_x sum_f (n_f' x + d_f')^2 + lam |x - x0 - s|^2 over its faces f (s: the mean normal
    shift of those faces; lam = 1e-4 only fixes the directions no plane constrains, e.g. along
    the ridge line of a vertex on two planes). Faces whose vertices lie on more than three planes
    become slightly non-planar; the store refits their planes (eq. 2-4).
    """
    rng = np.random.default_rng([seed, STAGE_ERRORS])
    nf = store.num_faces
    normals = store.normals.copy()
    cents = store.centroids
    shifts = rng.normal(0.0, options.shift_sigma, nf)
    angles = np.radians(rng.normal(0.0, options.rotation_sigma_deg, nf))
    phis = rng.uniform(0.0, 2 * np.pi, nf)
    new_n = np.empty_like(normals)
    for f in range(nf):
        a = store.rotations[f, :, 0] * math.cos(phis[f]) + store.rotations[f, :, 1] * math.sin(
            phis[f])
        # Rodrigues rotation of the normal about the in-plane axis a
        n = normals[f]
        new_n[f] = n * math.cos(angles[f]) + np.cross(a, n) * math.sin(angles[f])
    new_p0 = cents + shifts[:, None] * normals
    new_d = -np.einsum("fi,fi->f", new_n, new_p0)
    indptr, owners = store.vertex_faces
    lam = 1e-4
    out = store.vertices.copy()
    for vi in range(len(store.vertices)):
        fs = owners[indptr[vi]:indptr[vi + 1]]
        if len(fs) == 0:
            continue
        x0 = store.vertices[vi] + np.mean(shifts[fs][:, None] * normals[fs], axis=0)
        N = new_n[fs]
        A = N.T @ N + lam * np.eye(3)
        b = -N.T @ new_d[fs] + lam * x0
        out[vi] = np.linalg.solve(A, b)
    return store.with_vertices(out)


def perturb_polygons(polygons: list[RawPolygon], shift_sigma: float, rotation_sigma_deg: float,
                     seed: int, stage: int) -> list[RawPolygon]:
    """Independent small plane errors per polygon (the detailed model's own imperfections)."""
    rng = np.random.default_rng([seed, stage])
    out = []
    for p in polygons:
        n = newell_normal(p.exterior)
        c = p.exterior.mean(0)
        u, v = plane_basis(n)
        phi = rng.uniform(0, 2 * np.pi)
        axis = u * math.cos(phi) + v * math.sin(phi)
        ang = math.radians(rng.normal(0.0, rotation_sigma_deg))
        shift = rng.normal(0.0, shift_sigma)
        K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        R = np.eye(3) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K

        def move(r):
            return (r - c) @ R.T + c + shift * n

        out.append(RawPolygon(exterior=move(p.exterior), holes=[move(h) for h in p.holes],
                              semantic=p.semantic, building_id=p.building_id,
                              part_id=p.part_id, gml_id=p.gml_id, lod=p.lod))
    return out


# ----------------------------------------------------------------------------------------------
# the true scene


def _wall_frame(store: PlaneStore, f: int, building_centre: np.ndarray) -> _Frame:
    n = store.normals[f].copy()
    c = store.centroids[f]
    horiz = np.array([n[0], n[1], 0.0])
    # outward: away from the building's centre (the store's orientation is not trusted for
    # multisurface-only buildings)
    if np.dot(horiz, c - building_centre) < 0:
        n = -n
    u, v = plane_basis(n)
    return _Frame(c, u, v, n)


def _plan_openings(poly: Polygon, nbays: int, bay: float, opt: DetailOptions,
                   rng: np.random.Generator):
    """Per bay and storey of a wall (2D, facade frame): a garage door or an entrance on the
    ground floor, else a window; balconies under some upper windows. Returns the openings
    (rectangle, depth behind the wall, PART_*) and the balconies (u0, u1, floor v)."""
    umin, vmin, _, vmax = poly.bounds
    inner = poly.buffer(-0.3)
    nstoreys = max(int((vmax - vmin) // opt.storey_height), 1)
    openings: list[tuple[Polygon, float, int]] = []
    balconies: list[tuple[float, float, float]] = []
    ww, wh = opt.window_size
    for b in range(nbays):
        uc = umin + (b + 0.5) * bay
        for s in range(nstoreys):
            base = vmin + s * opt.storey_height
            if s == 0:
                r = rng.random()
                size = None
                if r < opt.garage_probability and bay >= 3.0:
                    size, kind = (1.3, 2.3), PART_GARAGE  # garage door: half width, height
                elif r < opt.garage_probability + opt.entrance_probability:
                    size, kind = (0.7, 2.4), PART_DOOR  # entrance
                if size is not None:
                    half, top = size
                    depth = rng.uniform(*opt.entrance_depth_range)
                    # doors reach the ground: test containment above the bottom margin
                    if inner.contains(box(uc - half, vmin + 0.3, uc + half, vmin + top)):
                        openings.append((box(uc - half, vmin, uc + half, vmin + top), depth,
                                         kind))
                        continue
            sill = base + 0.9
            rect = box(uc - ww / 2, sill, uc + ww / 2, sill + wh)
            if inner.contains(rect):
                openings.append((rect, opt.window_depth, PART_WINDOW))
                if s >= 1 and nstoreys >= 3 and rng.random() < opt.balcony_probability:
                    u0, u1 = uc - min(1.3, bay / 2 - 0.3), uc + min(1.3, bay / 2 - 0.3)
                    if inner.contains(box(u0, base - 0.15, u1, base + 1.0)):
                        balconies.append((u0, u1, base))
    return openings, balconies


def _decorate_wall(mb: MeshBuilder, store: PlaneStore, f: int, fr: _Frame, opt: DetailOptions,
                   rng: np.random.Generator, bid: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """Windows, entrances, pilasters and balconies on one wall. Returns clutter anchor points
    (bottom centre of the facade, outward normal) for trees/cars."""
    face = store.faces[f]
    ext = fr.to2d(store.vertices[face.exterior])
    holes = [fr.to2d(store.vertices[h]) for h in face.holes]
    poly = Polygon(ext, holes)
    if not poly.is_valid:
        poly = poly.buffer(0)
    polys = _polygons_of(poly)
    if not polys:
        return []
    poly = max(polys, key=lambda p: p.area) if len(polys) > 1 else polys[0]
    umin, vmin, umax, vmax = poly.bounds
    length, height = umax - umin, vmax - vmin
    if length < opt.min_wall_length or height < 2.5 or abs(fr.n[2]) > 0.3:
        _cap(mb, fr, poly, 0.0, 1.0, LABEL_WALL, bid)
        return []
    nbays = max(int(length // opt.bay_width), 1)
    bay = length / nbays
    openings, balconies = _plan_openings(poly, nbays, bay, opt, rng)
    holes_union = shapely.unary_union([r for r, _, _ in openings]) if openings else None
    wall = poly.difference(holes_union) if holes_union is not None else poly
    for part in _polygons_of(wall):
        _cap(mb, fr, part, 0.0, 1.0, LABEL_WALL, bid)
    for rect, depth, kind in openings:
        _extrude(mb, fr, rect, 0.0, -depth, cap0=False, cap1=True, label=LABEL_DETAIL, bid=bid,
                 part=kind, side_part=PART_REVEAL)
    if opt.pilaster_every > 0 and opt.pilaster_depth > 0:
        for k in range(0, nbays + 1, opt.pilaster_every):
            uc = umin + k * bay
            strip = box(uc - opt.pilaster_width / 2, vmin - 1, uc + opt.pilaster_width / 2,
                        vmax + 1)
            region = poly.intersection(strip)
            if holes_union is not None:
                region = region.difference(holes_union.buffer(0.05))
            for part in _polygons_of(region):
                if part.area > 0.2:
                    _extrude(mb, fr, part, 0.0, opt.pilaster_depth, cap0=False, cap1=True,
                             label=LABEL_DETAIL, bid=bid, part=PART_PILASTER)
    for u0, u1, floor in balconies:
        slab = box(u0, floor - 0.15, u1, floor)
        _extrude(mb, fr, slab, 0.0, opt.balcony_depth, cap0=False, cap1=True,
                 label=LABEL_DETAIL, bid=bid, part=PART_BALCONY)
        rail = box(u0, floor, u1, floor + opt.balustrade_height)
        _extrude(mb, fr, rail, opt.balcony_depth - 0.05, opt.balcony_depth, cap0=True,
                 cap1=True, label=LABEL_DETAIL, bid=bid, part=PART_BALCONY)
    # clutter anchors every metre along the bottom edge
    anchors = []
    for uu in np.arange(umin + 1.0, umax - 1.0, 1.0):
        anchors.append((fr.to3d([uu, vmin])[0], fr.n.copy()))
    return anchors


def _roof_edges(store: PlaneStore) -> dict[tuple[int, int], list[int]]:
    edges: dict[tuple[int, int], list[int]] = {}
    for f, face in enumerate(store.faces):
        for ring in [face.exterior] + list(face.holes):
            for a, b in zip(ring, np.roll(ring, -1)):
                edges.setdefault((min(a, b), max(a, b)), []).append(f)
    return edges


def _decorate_roof(mb: MeshBuilder, store: PlaneStore, f: int, edges, opt: DetailOptions,
                   rng: np.random.Generator, bid: str) -> None:
    face = store.faces[f]
    V = store.vertices
    ext = V[face.exterior]
    mb.add(ext, [V[h] for h in face.holes], label=LABEL_ROOF, building_id=bid,
           semantic="RoofSurface")
    n = store.normals[f].copy()
    if n[2] < 0:
        n = -n
    centre = store.centroids[f]
    flat = n[2] > 0.97
    ring = face.exterior
    for a, b in zip(ring, np.roll(ring, -1)):
        others = [g for g in edges.get((min(a, b), max(a, b)), []) if g != f]
        if not any(store.faces[g].semantic == "WallSurface" for g in others):
            continue
        pa, pb = V[a], V[b]
        e = pb - pa
        le = np.linalg.norm(e)
        if le < 0.5:
            continue
        e /= le
        o = np.cross(e, n)  # in the roof plane, perpendicular to the edge
        if np.dot(o, (pa + pb) / 2 - centre) < 0:
            o = -o
        if flat:
            if opt.parapet_height <= 0:
                continue
            oh = o - o[2] * np.array([0, 0, 1.0])
            oh /= np.linalg.norm(oh)
            up = np.array([0, 0, opt.parapet_height])
            t = -oh * opt.parapet_thickness
            for ring in ([pa, pb, pb + up, pa + up],
                         [pa + t, pb + t, pb + t + up, pa + t + up][::-1],
                         [pa + up, pb + up, pb + up + t, pa + up + t]):
                mb.add(ring, label=LABEL_DETAIL, building_id=bid, part=PART_PARAPET)
        elif opt.roof_overhang > 0:
            horiz = math.hypot(o[0], o[1])
            if horiz < 0.2:
                continue
            off = o * (opt.roof_overhang / horiz)
            mb.add([pa, pb, pb + off, pa + off], label=LABEL_DETAIL, building_id=bid,
                   part=PART_OVERHANG)
    # roof furniture: boxes standing on the roof plane
    area = store.areas[f]
    k = rng.poisson(area * opt.roof_furniture_per_100m2 / 100.0) if area > 10 else 0
    if k == 0:
        return
    u, v = plane_basis(n)
    xy = np.stack([(ext - centre) @ u, (ext - centre) @ v], axis=1)
    poly2 = Polygon(xy)
    if not poly2.is_valid:
        poly2 = poly2.buffer(0)
    inner = poly2.buffer(-1.0)
    if inner.is_empty:
        return
    minx, miny, maxx, maxy = inner.bounds
    d = -np.dot(n, centre)
    for _ in range(k):
        for _try in range(20):
            p2 = np.array([rng.uniform(minx, maxx), rng.uniform(miny, maxy)])
            if inner.contains(shapely.Point(p2)):
                break
        else:
            continue
        q = centre + p2[0] * u + p2[1] * v
        sx, sy = rng.uniform(0.5, 2.0, 2)
        hgt = rng.uniform(0.6, 1.8)
        yaw = math.atan2(u[1], u[0])
        corners = np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]]) / 2
        rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        cxy = corners @ rot.T + q[:2]
        zr = -(n[0] * cxy[:, 0] + n[1] * cxy[:, 1] + d) / n[2]
        _add_box(mb, cxy, zr.min() - 0.1, zr.max() + hgt, LABEL_DETAIL, bid, bottom=False,
                 part=PART_CHIMNEY)


def _add_box(mb: MeshBuilder, cxy: np.ndarray, z0: float, z1: float, label: int, bid: str,
             bottom: bool = False, part: int | None = None, obj: int | None = None) -> None:
    """A vertical prism over the counter-clockwise footprint `cxy` (4,2) from z0 to z1."""
    if Polygon(cxy).exterior.is_ccw is False:
        cxy = cxy[::-1]
    top = np.c_[cxy, np.full(len(cxy), z1)]
    kw = dict(label=label, building_id=bid, part=part, obj=obj)
    mb.add(top, **kw)
    if bottom:
        mb.add(np.c_[cxy, np.full(len(cxy), z0)][::-1], **kw)
    for i in range(len(cxy)):
        a, b = cxy[i], cxy[(i + 1) % len(cxy)]
        mb.add([[*a, z0], [*b, z0], [*b, z1], [*a, z1]], **kw)


def _tree(base: np.ndarray, rng: np.random.Generator) -> MeshBuilder:
    """A tree standing at `base`: an irregular icosphere crown on a square trunk."""
    import trimesh

    trunk_h = rng.uniform(2.0, 3.5)
    r = rng.uniform(1.5, 2.8)
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=r)
    v = sphere.vertices * np.array([1.0, 1.0, rng.uniform(0.8, 1.2)])
    # an irregular crown: radial noise per vertex
    v = v * (1 + rng.uniform(-0.15, 0.15, (len(v), 1)))
    v = v + base + np.array([0, 0, trunk_h + r])
    crown = v[sphere.faces]
    t = 0.15
    cxy = np.array([[-t, -t], [t, -t], [t, t], [-t, t]]) + base[:2]
    mb = MeshBuilder()
    mb.add_triangles(crown, LABEL_CLUTTER, parts=PART_CROWN)
    _add_box(mb, cxy, base[2], base[2] + trunk_h + 0.5, LABEL_CLUTTER, "", bottom=False,
             part=PART_TRUNK)
    return mb


def build_true_scene(store: PlaneStore, options: DetailOptions, seed: int, *,
                     roi_centres: np.ndarray, roi_radius: float,
                     ground: GroundModel | None = None,
                     avoid_points: np.ndarray | None = None) -> TrueScene:
    """The true scene around the flight: faces within `roi_radius` of a camera centre
    (`roi_centres`, local) get generalisation effects, all others stay plain LOD2; clutter
    (trees, cars, street furniture) stands in front of decorated facades, away from
    `avoid_points` (cameras); terrain covers the cameras' surroundings."""
    from scipy.spatial import cKDTree

    ground = ground or GroundModel(store)
    tree = cKDTree(roi_centres)
    groups: dict[str, list[int]] = {}
    for f, face in enumerate(store.faces):
        groups.setdefault(face.building_id, []).append(f)
    # faces near the flight get generalisation effects (vertices, centroid and triangle
    # centroids within roi_radius of a camera); far ones stay plain LOD2
    near = np.zeros(store.num_faces, dtype=bool)
    for f, face in enumerate(store.faces):
        pts = [store.vertices[face.exterior], store.centroids[f][None]]
        tris = triangulate_rings(store.vertices[face.exterior],
                                 [store.vertices[h] for h in face.holes])
        if len(tris):
            pts.append(tris.mean(1))
        near[f] = np.min(tree.query(np.concatenate(pts))[0]) < roi_radius
    edges = _roof_edges(store)
    mb = MeshBuilder()
    anchors: list[tuple[np.ndarray, np.ndarray]] = []
    for bid in sorted(groups):
        faces = groups[bid]
        ids = np.unique(np.concatenate([store.faces[f].exterior for f in faces]))
        centre = store.vertices[ids].mean(0)
        for f in faces:
            face = store.faces[f]
            if face.semantic in ("GroundSurface", "ClosureSurface"):
                continue  # invisible from outside; not part of the visible scene
            rng = np.random.default_rng([seed, STAGE_DETAILS, f])
            if not near[f]:
                label = LABEL_ROOF if face.semantic == "RoofSurface" else LABEL_WALL
                mb.add(store.vertices[face.exterior], [store.vertices[h] for h in face.holes],
                       label=label, building_id=bid, semantic=face.semantic)
            elif face.semantic == "RoofSurface" or (
                    face.semantic != "WallSurface" and abs(store.normals[f][2]) > 0.7):
                _decorate_roof(mb, store, f, edges, options, rng, bid)
                if options.dormer_probability > 0:
                    _add_dormers(mb, store, f, options,
                                 np.random.default_rng([seed, STAGE_DORMERS, f]), bid)
            else:
                fr = _wall_frame(store, f, centre)
                anchors += _decorate_wall(mb, store, f, fr, options, rng, bid)
    # terrain around the cameras
    lo = roi_centres[:, :2].min(0) - roi_radius
    hi = roi_centres[:, :2].max(0) + roi_radius
    cell = options.ground_cell
    xs = np.arange(lo[0], hi[0] + cell, cell)
    ys = np.arange(lo[1], hi[1] + cell, cell)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    gz = ground(np.c_[gx.ravel(), gy.ravel()]).reshape(gx.shape)
    P = np.stack([gx, gy, gz], axis=-1)
    a, b, c, d = P[:-1, :-1], P[:-1, 1:], P[1:, 1:], P[1:, :-1]
    tris = np.concatenate([np.stack([a, b, c], -2).reshape(-1, 3, 3),
                           np.stack([a, c, d], -2).reshape(-1, 3, 3)])
    cen = tris.mean(1)
    keep = tree.query(cen)[0] < roi_radius
    mb.add_triangles(tris[keep], LABEL_GROUND)
    # clutter in front of facades
    n_clutter, placed = _add_clutter(mb, store, anchors, options, seed, avoid_points)
    n_clutter += _add_furniture(mb, store, anchors, options, seed, avoid_points, placed)
    return mb.scene(num_clutter_objects=n_clutter)


def _add_clutter(mb: MeshBuilder, store: PlaneStore, anchors, opt: DetailOptions, seed: int,
                 avoid_points: np.ndarray | None) -> int:
    from scipy.spatial import cKDTree

    if not anchors or (opt.tree_spacing <= 0 and opt.car_spacing <= 0):
        return 0, []
    rng = np.random.default_rng([seed, STAGE_CLUTTER])
    footprints = shapely.unary_union(list(building_footprints(store).values())).buffer(0.5)
    shapely.prepare(footprints)
    cams = cKDTree(avoid_points) if avoid_points is not None and len(avoid_points) else None
    placed: list[np.ndarray] = []
    count = 0
    p_tree = 1.0 / opt.tree_spacing if opt.tree_spacing > 0 else 0.0
    p_car = 1.0 / opt.car_spacing if opt.car_spacing > 0 else 0.0
    for base, n in anchors:  # one anchor per metre of facade
        r = rng.random()
        kind = "tree" if r < p_tree else ("car" if r < p_tree + p_car else None)
        if kind is None:
            continue
        nh = np.array([n[0], n[1], 0.0])
        if np.linalg.norm(nh) < 1e-6:
            continue
        nh /= np.linalg.norm(nh)
        dist = rng.uniform(3.0, 5.5) if kind == "tree" else rng.uniform(2.5, 4.0)
        pos = base + dist * nh
        if footprints.contains(shapely.Point(pos[:2])):
            continue
        if any(np.linalg.norm(pos[:2] - q[:2]) < 3.0 for q in placed[-50:]):
            continue
        if kind == "tree":
            tmp = _tree(pos, rng)
        else:
            along = np.array([-nh[1], nh[0]])
            acr = nh[:2]
            L, W, H = rng.uniform(3.8, 4.8), rng.uniform(1.7, 1.9), rng.uniform(1.4, 1.7)
            cxy = np.array([pos[:2] + s1 * L / 2 * along + s2 * W / 2 * acr
                            for s1, s2 in [(-1, -1), (1, -1), (1, 1), (-1, 1)]])
            tmp = MeshBuilder()
            _add_box(tmp, cxy, pos[2] + 0.2, pos[2] + H, LABEL_CLUTTER, "", part=PART_CAR)
        if cams is not None:
            pts = tmp.triangles.reshape(-1, 3)
            if np.min(cams.query(pts)[0]) < opt.camera_clearance:
                continue
        mb.merge(tmp, obj=mb.new_object())
        placed.append(pos)
        count += 1
    return count, placed


#: The smallest sloped roof face (m^2) that may carry dormers.
DORMER_MIN_AREA = 20.0


def _add_dormers(mb: MeshBuilder, store: PlaneStore, f: int, opt: DetailOptions,
                 rng: np.random.Generator, bid: str) -> None:
    """With probability opt.dormer_probability, one to three dormers in a row on the sloped
    roof face f: a vertical front wall with a window, facing down the slope, two triangular
    cheeks and a flat top that runs back into the roof plane."""
    n = store.normals[f].copy()
    n = -n if n[2] < 0 else n
    if not 0.3 < n[2] < 0.97 or store.areas[f] < DORMER_MIN_AREA:
        return
    if rng.random() >= opt.dormer_probability:
        return
    centre = store.centroids[f]
    u, v = plane_basis(n)  # u horizontal, v up the slope in the roof plane
    ext = store.vertices[store.faces[f].exterior]
    poly = Polygon(np.stack([(ext - centre) @ u, (ext - centre) @ v], axis=1)).buffer(0)
    inner = poly.buffer(-0.8)
    if inner.is_empty:
        return
    sin_a = math.sqrt(max(1.0 - n[2] ** 2, 1e-12))
    count = int(rng.integers(1, 4))
    width, front = rng.uniform(1.6, 2.4), rng.uniform(1.3, 1.7)
    u_lo, v_lo, u_hi, _ = inner.bounds
    v_front = v_lo + rng.uniform(1.0, 1.8)
    depth = front / sin_a  # in-plane distance up the slope to where the top meets the roof
    for i in range(count):
        uc = u_lo + (i + 0.5) * (u_hi - u_lo) / count
        if not inner.contains(box(uc - width / 2, v_front, uc + width / 2, v_front + depth)):
            continue
        a = centre + (uc - width / 2) * u + v_front * v
        b = centre + (uc + width / 2) * u + v_front * v
        _dormer(mb, a, b, front, depth * (v - (v @ [0, 0, 1.0]) * np.array([0, 0, 1.0])),
                bid)


def _dormer(mb: MeshBuilder, a: np.ndarray, b: np.ndarray, front: float, back: np.ndarray,
            bid: str) -> None:
    """A dormer whose front wall stands on the roof between a and b, `front` m high; its top
    reaches back by the horizontal vector `back` to the roof plane."""
    up = np.array([0.0, 0.0, front])
    out = -back / np.linalg.norm(back)  # the front wall's outward normal (down the slope)
    fu, _ = plane_basis(out)
    if np.dot(b - a, fu) < 0:
        a, b = b, a
    width = float(np.linalg.norm(b - a))
    fr = _Frame(a, fu, np.array([0.0, 0.0, 1.0]), out)
    window = box(0.3, 0.25, width - 0.3, front - 0.2)
    for part in _polygons_of(box(0.0, 0.0, width, front).difference(window)):
        _cap(mb, fr, part, 0.0, 1.0, LABEL_DETAIL, bid, PART_WALL)
    _extrude(mb, fr, window, 0.0, -0.08, cap0=False, cap1=True, label=LABEL_DETAIL, bid=bid,
             part=PART_WINDOW, side_part=PART_REVEAL)
    for p, side in ((a, -fu), (b, fu)):
        ring = np.array([p, p + back + up, p + up])
        if np.dot(newell_normal(ring), side) < 0:
            ring = ring[::-1]
        mb.add(ring, label=LABEL_DETAIL, building_id=bid, part=PART_WALL)
    top = np.array([a + up, b + up, b + up + back, a + up + back])
    if newell_normal(top)[2] < 0:
        top = top[::-1]
    mb.add(top, label=LABEL_DETAIL, building_id=bid, part=PART_ROOF)


#: Street furniture: (kind, probability, distance range from the facade in m).
FURNITURE = (("lamp", 0.35, (2.4, 3.0)), ("bollard", 0.3, (2.0, 2.8)),
             ("bench", 0.2, (0.9, 1.6)), ("sign", 0.15, (2.2, 2.9)))


def _add_furniture(mb: MeshBuilder, store: PlaneStore, anchors, opt: DetailOptions, seed: int,
                   avoid_points: np.ndarray | None, placed: list[np.ndarray]) -> int:
    """Lamp posts, bollards, benches and sign posts in front of decorated facades (see
    DetailOptions.furniture_spacing), at least 1.5 m from each other and from trees and cars,
    outside the footprints and camera_clearance from every camera. Returns their number."""
    from scipy.spatial import cKDTree

    if not anchors or opt.furniture_spacing <= 0:
        return 0
    rng = np.random.default_rng([seed, STAGE_FURNITURE])
    footprints = shapely.unary_union(list(building_footprints(store).values())).buffer(0.3)
    shapely.prepare(footprints)
    cams = cKDTree(avoid_points) if avoid_points is not None and len(avoid_points) else None
    taken = [p[:2] for p in placed]
    count = 0
    kinds = [k for k, _, _ in FURNITURE]
    weights = np.array([w for _, w, _ in FURNITURE])
    for base, n in anchors:
        if rng.random() >= 1.0 / opt.furniture_spacing:
            continue
        kind = kinds[int(rng.choice(len(kinds), p=weights / weights.sum()))]
        nh = np.array([n[0], n[1], 0.0])
        if np.linalg.norm(nh) < 1e-6:
            continue
        nh /= np.linalg.norm(nh)
        pos = base + rng.uniform(*dict((k, r) for k, _, r in FURNITURE)[kind]) * nh
        if footprints.contains(shapely.Point(pos[:2])) or any(
                np.linalg.norm(pos[:2] - q) < 1.5 for q in taken[-80:]):
            continue
        tmp = MeshBuilder()
        _furniture(tmp, kind, pos, nh, rng)
        if cams is not None and np.min(cams.query(tmp.triangles.reshape(-1, 3))[0]) < \
                opt.camera_clearance:
            continue
        mb.merge(tmp, obj=mb.new_object())
        taken.append(pos[:2])
        count += 1
    return count


def _furniture(mb: MeshBuilder, kind: str, pos: np.ndarray, out: np.ndarray,
               rng: np.random.Generator) -> None:
    """One piece of street furniture of `kind` standing at `pos`; `out` (horizontal, unit)
    points away from the facade."""
    along = np.array([-out[1], out[0]])

    def prism(centre, half_along, half_out, z0, z1):
        c = pos[:2] + centre[0] * along + centre[1] * out[:2]
        cxy = np.array([c + sa * half_along * along + so * half_out * out[:2]
                        for sa, so in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
        _add_box(mb, cxy, pos[2] + z0, pos[2] + z1, LABEL_CLUTTER, "", part=PART_FURNITURE)

    if kind == "lamp":
        h = rng.uniform(5.0, 6.5)
        prism((0.0, 0.0), 0.07, 0.07, 0.0, h)
        prism((0.0, 0.6), 0.05, 0.6, h - 0.1, h)  # the arm over the road
        prism((0.0, 1.15), 0.15, 0.25, h - 0.28, h - 0.1)  # the lamp head
    elif kind == "bollard":
        prism((0.0, 0.0), 0.08, 0.08, 0.0, rng.uniform(0.8, 1.0))
    elif kind == "bench":
        prism((0.0, 0.0), 0.8, 0.22, 0.42, 0.48)  # seat
        for s in (-0.7, 0.7):
            prism((s, 0.0), 0.04, 0.2, 0.0, 0.42)  # legs
        prism((0.0, -0.2), 0.8, 0.03, 0.5, 0.95)  # backrest, on the facade side
    else:  # a sign post with its plate
        prism((0.0, 0.0), 0.035, 0.035, 0.0, 2.6)
        prism((0.0, 0.05), 0.3, 0.015, 2.0, 2.6)


def detailed_polygons(scene: TrueScene, min_area: float) -> list[RawPolygon]:
    """The true scene's building polygons of at least `min_area` (the detailed model)."""
    out = []
    for p in scene.polygons:
        tris = triangulate_rings(p.exterior, p.holes)
        area = 0.5 * np.linalg.norm(
            np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1).sum()
        if area >= min_area:
            out.append(p)
    return out
