"""The plane and vertex store: one building model as shared vertices plus planar faces.

Everything downstream (assignment, hybrid adjustment, model correction, mesh export) works on
this representation (method.md section 1; Unger 2020, 3.1 and 3.2.1, eq. 2-4):

- a vertex array in a LOCAL frame (float64 `origin` subtracted once, so nothing downstream
  handles 6-7 digit coordinates), merged within a tolerance so that faces meeting at a corner or
  an edge share vertex indices (the vertex-to-plane relations f_dVT come from this);
- faces as vertex-index rings (exterior + holes) with semantic class, building/part id, gml:id;
- per face a plane with its local frame: P0 = centroid of the face's vertices, R = eigenvectors
  of the vertices' 3x3 covariance sorted by eigenvalue (descending), third column = normal,
  oriented outward by the ring orientation (CityGML/CityJSON rings run counter-clockwise seen
  from outside), right-handed;
- a uniform-grid spatial index answering "closest face whose polygon contains the projection of
  this point" for 1e5 points against 1e4 faces in a fraction of a second.

All tolerances live in `Tolerances` below. Stores are built by build.py (`build_store` from a
reader's raw polygons, `store_from_polygons` for tests and the simulator); the packed faces and
their planes are in faces.py.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace

import numpy as np

from .faces import FaceList, compute_planes, face_unique_vertices
from .raw_model import CRSInfo

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Tolerances:
    """Every geometric tolerance of the store, in metres (areas in m^2).

    merge: vertices closer than this become one vertex (single linkage, so chains merge).
        Official models round to 1 mm and tum2twin walls/roofs disagree by exactly one unit of
        that rounding at shared corners; two such coordinates are 1 mm apart only up to float
        noise (e.g. 1.0000000000331966 mm), so the merge radius is `merge + merge_slack`,
        i.e. "within 1 mm" includes "exactly 1 mm" but not 1.01 mm.
    nonplanar: faces whose RMS out-of-plane residual exceeds this are kept but flagged.
    min_area: faces smaller than this are dropped as degenerate.
    collinear: faces whose vertices spread less than this across their main direction
        (sqrt of the middle covariance eigenvalue) are dropped as degenerate.
    chain_warning: a merged cluster wider than this says the merge chained too far (warned).
    """

    merge: float = 0.001
    merge_slack: float = 1e-6
    nonplanar: float = 0.05
    min_area: float = 1e-4
    collinear: float = 1e-4
    chain_warning: float = 0.005


DEFAULT_TOLERANCES = Tolerances()

THEMATIC_CLASSES = (
    "WallSurface",
    "RoofSurface",
    "GroundSurface",
    "ClosureSurface",
    "OuterCeilingSurface",
    "OuterFloorSurface",
)


# ----------------------------------------------------------------------------------------------
# geometry kernels (vectorised over all faces)
# ----------------------------------------------------------------------------------------------


# ----------------------------------------------------------------------------------------------
# the store
# ----------------------------------------------------------------------------------------------


@dataclass
class VertexProvenance:
    """Which coordinates of the files each store vertex was merged from.

    Every distinct coordinate triple the reader returned (file CRS, or the target CRS after a
    reprojection, minus the store's origin: bit for bit what build_store merged), in
    lexicographic order, and the store vertex it became (-1: only in faces that were dropped,
    or outside a cropped store). A writer finds a file coordinate's vertex by its value
    (`vertex_of`), so every raw coordinate of a merged vertex (up to the merge tolerance apart)
    can be moved by that vertex's shift: the file stays consistent where it was before."""

    points: np.ndarray  # (U, 3) float64, lexicographic order
    vertex: np.ndarray  # (U,) int64

    def __len__(self) -> int:
        return len(self.vertex)

    def vertex_of(self, points_local: np.ndarray) -> np.ndarray:
        """(N,) the store vertex of each point, found by exact value; -1 for a point the
        store was not built from (or whose faces it dropped)."""
        q = np.asarray(points_local, dtype=np.float64).reshape(-1, 3) + 0.0  # -0.0 == 0.0
        out = np.full(len(q), -1, dtype=np.int64)
        if not len(q) or not len(self.vertex):
            return out
        n = len(self.points)
        both = np.concatenate([self.points + 0.0, q])
        # among equal values the store's own row (there is at most one) sorts first
        source = np.concatenate([np.zeros(n, np.int8), np.ones(len(q), np.int8)])
        order = np.lexsort((source, both[:, 2], both[:, 1], both[:, 0]))
        b = both[order]
        starts = np.r_[True, np.any(b[1:] != b[:-1], axis=1)]
        group = np.cumsum(starts) - 1
        first = order[starts]  # the first row of each group of equal values
        group_vertex = np.where(first < n, self.vertex[np.minimum(first, max(n - 1, 0))], -1)
        queries = order >= n
        out[order[queries] - n] = group_vertex[group[queries]]
        return out

    def remapped(self, remap: np.ndarray) -> VertexProvenance:
        """The provenance after the vertices were renumbered by `remap` (old -> new, -1:
        gone); rows of gone vertices are dropped."""
        new = np.where(self.vertex >= 0, remap[np.maximum(self.vertex, 0)], -1)
        keep = new >= 0
        return VertexProvenance(self.points[keep], new[keep])


#: Two faces whose normals agree to this cosine (about 5 deg) and whose planes pass a point
#: within SAME_PLANE_DISTANCE (m) of each other continue one surface.
SAME_PLANE_COS = 0.996
SAME_PLANE_DISTANCE = 0.05
#: Faces whose normals agree to this cosine (30 deg) are parallel surfaces: a point between
#: two of them could lie on either.
PARALLEL_COS = 0.866


@dataclass
class PlaneStore:
    origin: np.ndarray
    crs: CRSInfo
    vertices: np.ndarray
    faces: FaceList  # a Sequence of Face (flat ring arrays inside); a list[Face] is converted
    centroids: np.ndarray
    rotations: np.ndarray
    areas: np.ndarray
    rms_out_of_plane: np.ndarray
    nonplanar: np.ndarray
    source: str = ""
    format: str = ""
    version: str = ""
    num_buildings: int = 0
    num_parts: int = 0
    num_dropped_degenerate: int = 0
    warnings: list[str] = field(default_factory=list)
    tolerances: Tolerances = DEFAULT_TOLERANCES
    provenance: VertexProvenance | None = field(default=None, repr=False, compare=False)
    """Where the vertices came from in the files (build_store); None for stores made
    otherwise. Kept by with_vertices (same vertices), renumbered by subset_bbox."""
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.faces, FaceList):
            self.faces = FaceList.from_faces(self.faces)

    # -- derived ---------------------------------------------------------------------------
    @property
    def num_faces(self) -> int:
        return len(self.faces)

    @property
    def normals(self) -> np.ndarray:
        return self.rotations[:, :, 2]

    @property
    def offsets(self) -> np.ndarray:
        """d = -n . P0, so the signed distance of X is n . X + d."""
        return -np.einsum("fi,fi->f", self.normals, self.centroids)

    def _face_vertex_csr(self) -> tuple[np.ndarray, np.ndarray]:
        if "fv" not in self._cache:
            self._cache["fv"] = face_unique_vertices(self.faces)
        return self._cache["fv"]

    def face_vertex_ids(self, f: int) -> np.ndarray:
        """Unique vertex ids of face f (exterior + holes), sorted."""
        ptr, ids = self._face_vertex_csr()
        return ids[ptr[f] : ptr[f + 1]]

    @property
    def vertex_faces(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR (indptr (V+1,), indices): the faces each vertex belongs to (for f_dVT)."""
        if "vf" not in self._cache:
            ptr, ids = self._face_vertex_csr()
            owner = np.repeat(np.arange(self.num_faces, dtype=np.int64), np.diff(ptr))
            order = np.lexsort((owner, ids))
            counts = np.bincount(ids, minlength=len(self.vertices))
            indptr = np.zeros(len(self.vertices) + 1, dtype=np.int64)
            np.cumsum(counts, out=indptr[1:])
            self._cache["vf"] = (indptr, owner[order])
        return self._cache["vf"]

    @property
    def bbox_local(self) -> np.ndarray:
        if len(self.vertices) == 0:
            return np.zeros((2, 3))
        return np.stack([self.vertices.min(0), self.vertices.max(0)])

    @property
    def bbox_crs(self) -> np.ndarray:
        return self.bbox_local + self.origin

    def to_local(self, xyz_crs: np.ndarray) -> np.ndarray:
        return np.asarray(xyz_crs, dtype=np.float64) - self.origin

    def to_crs(self, xyz_local: np.ndarray) -> np.ndarray:
        return np.asarray(xyz_local, dtype=np.float64) + self.origin

    # -- 2D face frames and edges ------------------------------------------------------------
    def _edges2d(self) -> dict[str, np.ndarray]:
        """All ring edges of all faces in each face's 2D frame (R columns 0, 1), grouped by face."""
        if "edges" not in self._cache:
            rings = self.faces.rings()
            nxt = rings.next_index()
            face_of = rings.face[rings.ring_of_entry()]  # sorted by face (rings are in order)
            R = self.rotations[face_of]
            A = self.vertices[rings.vertex] - self.centroids[face_of]
            B = self.vertices[rings.vertex[nxt]] - self.centroids[face_of]
            au, av = np.einsum("ki,ki->k", A, R[:, :, 0]), np.einsum("ki,ki->k", A, R[:, :, 1])
            bu, bv = np.einsum("ki,ki->k", B, R[:, :, 0]), np.einsum("ki,ki->k", B, R[:, :, 1])
            counts = np.bincount(face_of, minlength=self.num_faces)
            ptr = np.zeros(self.num_faces + 1, dtype=np.int64)
            np.cumsum(counts, out=ptr[1:])
            lo_u = np.full(self.num_faces, np.inf)
            hi_u = np.full(self.num_faces, -np.inf)
            lo_v, hi_v = lo_u.copy(), hi_u.copy()
            np.minimum.at(lo_u, face_of, au)
            np.maximum.at(hi_u, face_of, au)
            np.minimum.at(lo_v, face_of, av)
            np.maximum.at(hi_v, face_of, av)
            self._cache["edges"] = dict(
                au=au, av=av, bu=bu, bv=bv, ptr=ptr, lo_u=lo_u, hi_u=hi_u, lo_v=lo_v, hi_v=hi_v
            )
        return self._cache["edges"]

    def _to_face_2d(self, faces: np.ndarray, points: np.ndarray):
        D = points - self.centroids[faces]
        R = self.rotations[faces]
        return np.einsum("ki,ki->k", D, R[:, :, 0]), np.einsum("ki,ki->k", D, R[:, :, 1])

    def _inside_pairs(
        self, faces: np.ndarray, u: np.ndarray, v: np.ndarray, margin: float,
        chunk_edges: int = 4_000_000,
    ) -> np.ndarray:
        """Point-in-polygon (with holes) for (face, 2D point) pairs, polygon grown by `margin`.

        Crossing-number parity over all rings of the face (holes flip parity), OR distance to
        any ring edge <= margin. Vectorised over pairs x edges, in chunks to bound memory.
        """
        E = self._edges2d()
        out = np.zeros(len(faces), dtype=bool)
        if len(faces) == 0:
            return out
        n_edges = E["ptr"][faces + 1] - E["ptr"][faces]
        ends = np.cumsum(n_edges)
        start = 0
        while start < len(faces):
            stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + chunk_edges))
            stop = max(stop, start + 1)
            stop = min(stop, len(faces))
            cnt = n_edges[start:stop]
            pair = np.repeat(np.arange(stop - start), cnt)
            first = np.cumsum(cnt) - cnt
            edge = np.arange(len(pair)) - np.repeat(first, cnt) + np.repeat(
                E["ptr"][faces[start:stop]], cnt
            )
            x, y = u[start:stop][pair], v[start:stop][pair]
            au, av, bu, bv = E["au"][edge], E["av"][edge], E["bu"][edge], E["bv"][edge]
            straddle = (av > y) != (bv > y)
            with np.errstate(divide="ignore", invalid="ignore"):
                xint = au + (bu - au) * (y - av) / (bv - av)
            cross = straddle & (x < xint)
            parity = np.bincount(pair, cross, stop - start).astype(np.int64) % 2 == 1
            inside = parity
            if margin > 0:
                du, dv = bu - au, bv - av
                L2 = du * du + dv * dv
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = np.where(L2 > 0, ((x - au) * du + (y - av) * dv) / L2, 0.0)
                t = np.clip(t, 0.0, 1.0)
                d2 = (x - au - t * du) ** 2 + (y - av - t * dv) ** 2
                dmin = np.minimum.reduceat(d2, first) if len(d2) else d2
                inside = inside | (dmin <= margin * margin)
            out[start:stop] = inside
            start = stop
        return out

    def contains_projection(
        self, face: int, points_local: np.ndarray, margin: float = 0.0
    ) -> np.ndarray:
        """(P,) bool: does face `face` (with holes, grown by `margin` m) contain the orthogonal
        projection of each point onto its plane?"""
        pts = np.asarray(points_local, dtype=np.float64).reshape(-1, 3)
        faces = np.full(len(pts), int(face), dtype=np.int64)
        u, v = self._to_face_2d(faces, pts)
        return self._inside_pairs(faces, u, v, margin)

    # -- spatial index ---------------------------------------------------------------------
    def _grid(self, reach: float, max_registrations: int = 20_000_000) -> dict:
        """Uniform 3D grid: each face registered in the cells its AABB (grown by `reach`)
        overlaps AND whose centre lies within reach + half a cell diagonal of the face plane."""
        key = round(float(reach), 6)
        grids = self._cache.setdefault("grids", {})
        if key in grids:
            return grids[key]
        F = self.num_faces
        ptr, ids = self._face_vertex_csr()
        owner = np.repeat(np.arange(F), np.diff(ptr))
        lo = np.full((F, 3), np.inf)
        hi = np.full((F, 3), -np.inf)
        np.minimum.at(lo, owner, self.vertices[ids])
        np.maximum.at(hi, owner, self.vertices[ids])
        lo -= reach
        hi += reach
        gmin = lo.min(0) if F else np.zeros(3)
        extent = np.max(hi - lo, axis=1) if F else np.ones(1)
        h = float(np.clip(np.median(extent) / 2.0, 0.25, 50.0))
        while True:
            i0 = np.floor((lo - gmin) / h).astype(np.int64)
            i1 = np.floor((hi - gmin) / h).astype(np.int64)
            n = i1 - i0 + 1
            per_face = n.prod(1)
            if per_face.sum() <= max_registrations:
                break
            h *= 1.5
        dims = (np.floor((hi.max(0) - gmin) / h).astype(np.int64) + 1) if F else np.ones(3, int)
        total = int(per_face.sum())
        face = np.repeat(np.arange(F), per_face)
        local = np.arange(total) - np.repeat(np.cumsum(per_face) - per_face, per_face)
        nf = n[face]
        ix = local % nf[:, 0]
        iy = (local // nf[:, 0]) % nf[:, 1]
        iz = local // (nf[:, 0] * nf[:, 1])
        cell = np.stack([ix, iy, iz], 1) + i0[face]
        centre = gmin + (cell + 0.5) * h
        dist = np.abs(np.einsum("ki,ki->k", centre, self.normals[face]) + self.offsets[face])
        keep = dist <= reach + h * math.sqrt(3) / 2 + 1e-9
        face, cell = face[keep], cell[keep]
        keys = cell[:, 0] + dims[0] * (cell[:, 1] + dims[1] * cell[:, 2])
        order = np.argsort(keys, kind="stable")
        keys, face = keys[order], face[order]
        ukeys, starts = np.unique(keys, return_index=True)
        ends = np.append(starts[1:], len(keys))
        grid = dict(gmin=gmin, h=h, dims=dims, ukeys=ukeys, starts=starts, ends=ends, faces=face)
        grids[key] = grid
        logger.debug("grid reach %.3f: cell %.2f m, %d registrations", reach, h, len(face))
        return grid

    def _candidate_pairs(self, pts: np.ndarray, reach: float) -> tuple[np.ndarray, np.ndarray]:
        if self.num_faces == 0 or len(pts) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        g = self._grid(reach)
        c = np.floor((pts - g["gmin"]) / g["h"]).astype(np.int64)
        ok = np.all((c >= 0) & (c < g["dims"]), axis=1)
        keys = c[:, 0] + g["dims"][0] * (c[:, 1] + g["dims"][1] * c[:, 2])
        pos = np.searchsorted(g["ukeys"], keys)
        pos = np.minimum(pos, len(g["ukeys"]) - 1)
        ok &= g["ukeys"][pos] == keys
        pidx = np.flatnonzero(ok)
        s, e = g["starts"][pos[pidx]], g["ends"][pos[pidx]]
        cnt = e - s
        point = np.repeat(pidx, cnt)
        idx = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt) + np.repeat(s, cnt)
        return point, g["faces"][idx]

    def closest_faces(
        self,
        points_local: np.ndarray,
        max_distance: float,
        margin: float = 0.1,
        candidates: int | None = 8,
        allowed: np.ndarray | None = None,
        hidden=None,
        runner_up: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """For each point: the face with the smallest |distance to plane| among faces whose
        polygon (with holes, grown by `margin` m) contains the point's orthogonal projection,
        only if |d| <= max_distance. `allowed` ((F,) bool): the faces that may be chosen (None:
        all); `hidden(feet, faces)` ((K,) bool): the candidate pairs whose face is hidden where
        the point's projection meets it (citymodel.visibility), which are not chosen either.
        `runner_up` ((P,) float, filled in): |distance| to the nearest other candidate face
        parallel to the chosen one (PARALLEL_COS) but not on its plane (inf: none).

        Returns (face_index int64, -1 for none; signed_distance float64, nan for none).
        `candidates` caps how many planes (nearest first) per point are tested for containment
        after the plane-distance and 2D-bbox filters (None: all); only points near more than
        that many overlapping faces can be affected.
        """
        pts = np.asarray(points_local, dtype=np.float64).reshape(-1, 3)
        P = len(pts)
        best = np.full(P, -1, dtype=np.int64)
        dist = np.full(P, np.nan)
        point, face = self._candidate_pairs(pts, max_distance + margin)
        if len(point) == 0:
            return best, dist
        d = np.einsum("ki,ki->k", pts[point], self.normals[face]) + self.offsets[face]
        keep = np.abs(d) <= max_distance
        if allowed is not None:
            keep &= allowed[face]
        point, face, d = point[keep], face[keep], d[keep]
        u, v = self._to_face_2d(face, pts[point])
        E = self._edges2d()
        keep = (
            (u >= E["lo_u"][face] - margin) & (u <= E["hi_u"][face] + margin)
            & (v >= E["lo_v"][face] - margin) & (v <= E["hi_v"][face] + margin)
        )
        point, face, d, u, v = point[keep], face[keep], d[keep], u[keep], v[keep]
        order = np.lexsort((face, np.abs(d), point))
        point, face, d, u, v = point[order], face[order], d[order], u[order], v[order]
        if candidates is not None and len(point):
            first = np.r_[True, point[1:] != point[:-1]]
            start = np.maximum.accumulate(np.where(first, np.arange(len(point)), 0))
            keep = (np.arange(len(point)) - start) < candidates
            point, face, d, u, v = point[keep], face[keep], d[keep], u[keep], v[keep]
        inside = self._inside_pairs(face, u, v, margin)
        point, face, d = point[inside], face[inside], d[inside]
        if hidden is not None and len(point):
            seen = ~hidden(pts[point] - d[:, None] * self.normals[face], face)
            point, face, d = point[seen], face[seen], d[seen]
        first = np.r_[True, point[1:] != point[:-1]] if len(point) else np.zeros(0, bool)
        best[point[first]] = face[first]
        dist[point[first]] = d[first]
        if runner_up is not None:
            # The next face of each point parallel to its best face but not on its plane: a
            # surface the point could as well lie on (faces that continue one plane are one
            # surface; a face at an angle meets the best one at an edge, where either is near).
            runner_up[:] = np.inf
            lead = np.maximum.accumulate(np.where(first, np.arange(len(point)), 0))
            cos = np.abs(np.einsum("ki,ki->k", self.normals[face], self.normals[face[lead]]))
            same = (cos > SAME_PLANE_COS) & (np.abs(d - d[lead]) < SAME_PLANE_DISTANCE)
            other = ~first & ~same & (cos > PARALLEL_COS)
            np.minimum.at(runner_up, point[other], np.abs(d[other]))
        return best, dist

    # -- derived stores ---------------------------------------------------------------------
    def with_vertices(self, vertices_local: np.ndarray) -> PlaneStore:
        """Same topology with new vertex coordinates; planes recomputed (model correction)."""
        V = np.asarray(vertices_local, dtype=np.float64)
        if V.shape != self.vertices.shape:
            raise ValueError(f"vertices must have shape {self.vertices.shape}, got {V.shape}")
        planes = compute_planes(V, self.faces, extras=False)
        return replace(
            self,
            vertices=V.copy(),
            centroids=planes["centroids"],
            rotations=planes["rotations"],
            areas=planes["areas"],
            rms_out_of_plane=planes["rms"],
            nonplanar=planes["rms"] > self.tolerances.nonplanar,
            warnings=list(self.warnings),
            # What lies inside the city's volume does not change when vertices move by a
            # model's corrections (decimetres): the same faces stay hidden.
            _cache={k: v for k, v in self._cache.items() if k == "visibility"},
        )

    def with_plane_shifts(self, shifts: np.ndarray) -> PlaneStore:
        """Same faces with each plane moved along its normal so that the signed distance of a
        point X becomes n . X + d + shifts[f] ((F,) m): the surface a face's tie points lie on
        when it stands `-shifts[f]` off the face. Outlines in the plane, and so every
        containment and visibility test, stay the face's own."""
        shifts = np.asarray(shifts, dtype=np.float64)
        if shifts.shape != (self.num_faces,):
            raise ValueError(f"shifts must have shape ({self.num_faces},), got {shifts.shape}")
        return replace(
            self,
            centroids=self.centroids - shifts[:, None] * self.normals,
            warnings=list(self.warnings),
            # Edges and grids are in each face's own 2D frame, which a move along the normal
            # keeps, as it keeps what is hidden.
            _cache={k: v for k, v in self._cache.items() if k in ("visibility", "edges", "fv",
                                                                 "vf")},
        )

    def subset_bbox(self, bbox_local_min, bbox_local_max) -> PlaneStore:
        """Faces whose vertex AABB touches the box, with only their vertices (re-indexed)."""
        bmin = np.asarray(bbox_local_min, dtype=np.float64)
        bmax = np.asarray(bbox_local_max, dtype=np.float64)
        dim = len(bmin)  # 2 (x, y) or 3
        ptr, ids = self._face_vertex_csr()
        owner = np.repeat(np.arange(self.num_faces), np.diff(ptr))
        lo = np.full((self.num_faces, 3), np.inf)
        hi = np.full((self.num_faces, 3), -np.inf)
        np.minimum.at(lo, owner, self.vertices[ids])
        np.maximum.at(hi, owner, self.vertices[ids])
        keep = np.all((hi[:, :dim] >= bmin) & (lo[:, :dim] <= bmax), axis=1)
        sel = np.flatnonzero(keep)
        faces = self.faces.take(sel)
        used = np.unique(faces.ring_vertex)
        remap = np.full(len(self.vertices), -1, dtype=np.int64)
        remap[used] = np.arange(len(used))
        faces = faces.with_ring_vertex(remap[faces.ring_vertex])
        buildings = faces.building_id.unique()
        parts = {(b, p) for b, p in zip(faces.building_id, faces.part_id) if p}
        return replace(
            self,
            vertices=self.vertices[used].copy(),
            faces=faces,
            centroids=self.centroids[sel],
            rotations=self.rotations[sel],
            areas=self.areas[sel],
            rms_out_of_plane=self.rms_out_of_plane[sel],
            nonplanar=self.nonplanar[sel],
            num_buildings=len(buildings),
            num_parts=len(parts),
            warnings=list(self.warnings),
            provenance=None if self.provenance is None else self.provenance.remapped(remap),
            _cache={},
        )

    def summary(self) -> dict:
        """Plain-data summary for `model-info` (JSON-serialisable)."""
        by_class = self.faces.semantic.counts()
        num_holes = self.faces.num_holes
        return {
            "format": self.format,
            "version": self.version,
            "source": self.source,
            "crs": {
                "label": self.crs.label,
                "srs_name": self.crs.srs_name,
                "horizontal_epsg": self.crs.horizontal_epsg,
                "vertical_epsg": self.crs.vertical_epsg,
                "wkt": self.crs.wkt,
            },
            "num_buildings": int(self.num_buildings),
            "num_parts": int(self.num_parts),
            "num_faces": int(self.num_faces),
            "num_vertices": int(len(self.vertices)),
            "faces_by_class": dict(sorted(by_class.items())),
            "faces_with_holes": int(np.count_nonzero(num_holes)),
            "num_holes": int(num_holes.sum()),
            "bbox": self.bbox_crs.tolist(),
            "origin": self.origin.tolist(),
            "num_dropped_degenerate": int(self.num_dropped_degenerate),
            "num_nonplanar": int(np.count_nonzero(self.nonplanar)),
            "max_rms_out_of_plane": float(self.rms_out_of_plane.max()) if self.num_faces else 0.0,
            "warnings": list(self.warnings),
        }


# ----------------------------------------------------------------------------------------------
# construction
# ----------------------------------------------------------------------------------------------


