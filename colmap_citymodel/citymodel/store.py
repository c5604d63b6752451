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

All tolerances live in `Tolerances` below.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import math
import platform
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .raw_model import CodedStrings, CRSInfo, PackedStrings, RawCityModel, RawPolygon, RawPolygonTable, row_index

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


def local_engineering_crs() -> CRSInfo:
    """The CRS of synthetic scenes: a metric engineering frame without geodetic meaning."""
    wkt = (
        'ENGCRS["local engineering",EDATUM["local"],CS[Cartesian,3],'
        'AXIS["x",east,LENGTHUNIT["metre",1]],AXIS["y",north,LENGTHUNIT["metre",1]],'
        'AXIS["z",up,LENGTHUNIT["metre",1]]]'
    )
    return CRSInfo(
        srs_name="local", horizontal_epsg=None, vertical_epsg=None, wkt=wkt, is_projected=True
    )


@dataclass(slots=True)
class Face:
    """One face as the public API sees it; `store.faces[i]` builds it on access from the
    store's flat ring arrays (exterior/holes are views into them: read, do not write)."""

    exterior: np.ndarray  # (N,) int64 vertex indices, ring order, not closed
    holes: list[np.ndarray]  # each (M,) int64
    semantic: str  # "WallSurface", "RoofSurface", "GroundSurface", "ClosureSurface", ...
    building_id: str
    part_id: str
    gml_id: str
    lod: int


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    """glibc's malloc_trim(pad) (None on other platforms and C libraries)."""
    if sys.platform != "linux" or platform.libc_ver()[0] != "glibc":
        return None
    try:
        trim = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):
        return None
    trim.argtypes = [ctypes.c_size_t]
    trim.restype = ctypes.c_int
    return trim


def release_free_memory() -> None:
    """Hand memory that was freed but is still held by the C allocator back to the system.

    glibc keeps freed heap memory (and, after freeing a large array, serves later arrays from
    the heap instead of fresh mappings), so a big read's resident memory would keep the sum of
    its phases' high-water marks; build_store calls this between its phases (a few ms each)."""
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


def _compress_rows(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """a[mask] (bool mask) written over `a` itself (which must own its memory and have no
    views) and shrunk in place, in chunks of ~2 MB: no index array, no second full array."""
    if not (a.flags.owndata and a.flags.c_contiguous and a.flags.writeable):
        return a[mask]
    step = max(1024, (1 << 21) // max(1, a[:1].nbytes))
    w = 0
    for r in range(0, len(a), step):
        piece = a[r:r + step][mask[r:r + step]]  # a copy: safe to write at w <= r
        a[w:w + len(piece)] = piece
        w += len(piece)
    a.resize((w,) + a.shape[1:], refcheck=False)
    return a


def _gather_segments(values: np.ndarray, starts: np.ndarray, lengths: np.ndarray,
                     step: int = 1 << 16) -> np.ndarray:
    """values[concatenated segments [starts[i], starts[i] + lengths[i])], in chunks of
    segments (no index array of the full result)."""
    ptr = _ptr(lengths)
    out = np.empty(int(ptr[-1]), dtype=values.dtype)
    for a in range(0, len(starts), step):
        b = min(len(starts), a + step)
        out[ptr[a]:ptr[b]] = values[_segment_gather(starts[a:b], lengths[a:b])]
    return out


def _segment_gather(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Indices of the concatenated segments [starts[i], starts[i] + lengths[i])."""
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offs = np.cumsum(lengths) - lengths
    return np.arange(total, dtype=np.int64) + np.repeat(starts - offs, lengths)


def _ptr(counts: np.ndarray) -> np.ndarray:
    ptr = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    return ptr


class FaceList(Sequence):
    """All faces of a store in flat arrays (CSR), behaving like a list of `Face`.

    ring_vertex (K,) int64 vertex ids of all rings; ring_ptr (R+1,) ring r is
    ring_vertex[ring_ptr[r]:ring_ptr[r+1]]; face_ring (F+1,) face f owns rings
    face_ring[f]:face_ring[f+1], the first is its exterior, the others its holes. Per-face
    attributes read like lists of str: semantic, building_id, part_id are CodedStrings (int32
    codes + the distinct strings), gml_id is PackedStrings (UTF-8 bytes + int64 offsets); lists
    given to the constructor are converted; lod is an int16 array. A 250k-face city costs
    ~60 bytes per face here instead of ~600 for Face objects.
    """

    __slots__ = ("ring_vertex", "ring_ptr", "face_ring", "semantic", "building_id", "part_id",
                 "gml_id", "lod")

    def __init__(self, ring_vertex, ring_ptr, face_ring, semantic, building_id, part_id, gml_id,
                 lod):
        self.ring_vertex = np.asarray(ring_vertex, dtype=np.int64)
        self.ring_ptr = np.asarray(ring_ptr, dtype=np.int64)
        self.face_ring = np.asarray(face_ring, dtype=np.int64)
        self.semantic = CodedStrings.from_values(semantic)
        self.building_id = CodedStrings.from_values(building_id)
        self.part_id = CodedStrings.from_values(part_id)
        self.gml_id = PackedStrings.from_values(gml_id)
        self.lod = np.asarray(lod, dtype=np.int16)

    @classmethod
    def _own(cls, ring_vertex, ring_ptr, face_ring, semantic, building_id, part_id, gml_id,
             lod) -> FaceList:
        """A FaceList that takes the given arrays and columns as they are, without copies."""
        fl = cls.__new__(cls)
        fl.ring_vertex, fl.ring_ptr, fl.face_ring = ring_vertex, ring_ptr, face_ring
        fl.semantic, fl.building_id, fl.part_id, fl.gml_id = semantic, building_id, part_id, gml_id
        fl.lod = lod
        return fl

    @classmethod
    def from_faces(cls, faces) -> FaceList:
        if isinstance(faces, FaceList):
            return faces
        faces = list(faces)
        rings = [np.asarray(r, dtype=np.int64).ravel() for f in faces for r in (f.exterior, *f.holes)]
        return cls(
            np.concatenate(rings) if rings else np.zeros(0, np.int64),
            _ptr(np.array([len(r) for r in rings], dtype=np.int64)),
            _ptr(np.array([1 + len(f.holes) for f in faces], dtype=np.int64)),
            [f.semantic for f in faces], [f.building_id for f in faces],
            [f.part_id for f in faces], [f.gml_id for f in faces], [int(f.lod) for f in faces],
        )

    def __len__(self) -> int:
        return len(self.face_ring) - 1

    def _face(self, f: int, fr, rp) -> Face:
        a, b = fr[f], fr[f + 1]
        rv = self.ring_vertex
        return Face(
            exterior=rv[rp[a]:rp[a + 1]],
            holes=[rv[rp[r]:rp[r + 1]] for r in range(a + 1, b)],
            semantic=self.semantic[f],
            building_id=self.building_id[f],
            part_id=self.part_id[f],
            gml_id=self.gml_id[f],
            lod=int(self.lod[f]),
        )

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        f = row_index(i, len(self), "face")
        return self._face(f, self.face_ring, self.ring_ptr)

    def __iter__(self):
        fr, rp = self.face_ring.tolist(), self.ring_ptr.tolist()
        for f in range(len(self)):
            yield self._face(f, fr, rp)

    def __repr__(self) -> str:
        return f"FaceList({len(self)} faces, {len(self.ring_ptr) - 1} rings)"

    @property
    def num_holes(self) -> np.ndarray:
        return np.diff(self.face_ring) - 1

    def rings(self) -> _Rings:
        F = len(self)
        nr = np.diff(self.face_ring)
        face = np.repeat(np.arange(F, dtype=np.int64), nr)
        is_hole = np.ones(len(face), dtype=bool)
        is_hole[self.face_ring[:-1]] = False
        return _Rings(self.ring_vertex, self.ring_ptr, face, is_hole)

    def entry_face(self) -> np.ndarray:
        """(K,) the face of each entry of ring_vertex."""
        nr = np.diff(self.face_ring)
        return np.repeat(np.repeat(np.arange(len(self), dtype=np.int64), nr), np.diff(self.ring_ptr))

    def take(self, sel: np.ndarray) -> FaceList:
        """The faces `sel` (int indices, in that order), with their rings gathered."""
        sel = np.asarray(sel, dtype=np.int64)
        nr = np.diff(self.face_ring)[sel]
        rings = _segment_gather(self.face_ring[sel], nr)
        rlen = np.diff(self.ring_ptr)[rings]
        entries = _segment_gather(self.ring_ptr[rings], rlen)
        return FaceList(
            self.ring_vertex[entries], _ptr(rlen), _ptr(nr),
            self.semantic.take(sel), self.building_id.take(sel),
            self.part_id.take(sel), self.gml_id.take(sel), self.lod[sel],
        )

    def compress(self, keep: np.ndarray) -> FaceList:
        """The faces where `keep` (bool (F,)) is True, in order, reusing (overwriting) this
        list's ring array: only for a FaceList about to be dropped (build_store)."""
        nr = np.diff(self.face_ring)
        ring_keep = np.repeat(keep, nr)
        rlen = np.diff(self.ring_ptr)
        entry_keep = np.repeat(ring_keep, rlen)
        ring_vertex = _compress_rows(self.ring_vertex, entry_keep)  # self's rings are gone after
        del entry_keep
        return FaceList._own(
            ring_vertex, _ptr(rlen[ring_keep]), _ptr(nr[keep]),
            CodedStrings(_compress_rows(self.semantic.codes, keep), self.semantic.categories),
            CodedStrings(_compress_rows(self.building_id.codes, keep), self.building_id.categories),
            CodedStrings(_compress_rows(self.part_id.codes, keep), self.part_id.categories),
            self.gml_id.compress_owned(keep), self.lod[keep],
        )

    def with_ring_vertex(self, ring_vertex: np.ndarray) -> FaceList:
        return FaceList(ring_vertex, self.ring_ptr, self.face_ring, self.semantic,
                        self.building_id, self.part_id, self.gml_id, self.lod)

    def nbytes(self) -> int:
        """Bytes of all arrays (rings, string columns' codes/bytes/offsets, lod)."""
        return (self.ring_vertex.nbytes + self.ring_ptr.nbytes + self.face_ring.nbytes
                + self.lod.nbytes + self.semantic.nbytes() + self.building_id.nbytes()
                + self.part_id.nbytes() + self.gml_id.nbytes())


# ----------------------------------------------------------------------------------------------
# geometry kernels (vectorised over all faces)
# ----------------------------------------------------------------------------------------------


@dataclass
class _Rings:
    """All rings of all faces flattened: vertex ids, CSR pointers, owning face, hole flag."""

    vertex: np.ndarray  # (K,) int64
    ptr: np.ndarray  # (R+1,) int64
    face: np.ndarray  # (R,) int64
    is_hole: np.ndarray  # (R,) bool

    @classmethod
    def from_faces(cls, faces) -> _Rings:
        return FaceList.from_faces(faces).rings()

    def next_index(self) -> np.ndarray:
        """Index (into `vertex`) of the next vertex along each ring, wrapping at the ring end."""
        nxt = np.arange(1, len(self.vertex) + 1, dtype=np.int64)
        nonempty = self.ptr[1:] > self.ptr[:-1]
        nxt[self.ptr[1:][nonempty] - 1] = self.ptr[:-1][nonempty]
        return nxt

    def ring_of_entry(self) -> np.ndarray:
        return np.repeat(np.arange(len(self.ptr) - 1), np.diff(self.ptr))


def _unique_per_group(owner: np.ndarray, ids: np.ndarray, num_groups: int, n: int):
    """CSR (ptr, ids) of the distinct ids of each group, ids sorted; owner must be sorted."""
    # keys are sorted by owner already, so a stable (merge) sort has short runs to fix only
    key = np.sort(owner * n + ids, kind="stable")
    key = key[np.r_[True, key[1:] != key[:-1]]] if len(key) else key
    fo, ids = np.divmod(key, n)
    return _ptr(np.bincount(fo, minlength=num_groups)), ids


def _face_unique_vertices(faces) -> tuple[np.ndarray, np.ndarray]:
    """CSR (ptr, ids) of the unique vertex ids of each face (exterior + holes), ids sorted."""
    fl = FaceList.from_faces(faces)
    F = len(fl)
    if F == 0:
        return np.zeros(1, np.int64), np.zeros(0, np.int64)
    ids = fl.ring_vertex
    n = int(ids.max()) + 1 if len(ids) else 1
    return _unique_per_group(fl.entry_face(), ids, F, n)


def _compute_planes(vertices: np.ndarray, faces, chunk_faces: int = 8192,
                    extras: bool = True) -> dict[str, np.ndarray]:
    """Planes of all faces (eq. 2-4), vectorised, in chunks of faces to bound temporaries.

    P0 = centroid of the face's distinct vertices (Unger: "all vertices that belong to a
    plane", so holes count too), M = their covariance (eq. 2-3), R = eigenvectors of M sorted
    by eigenvalue descending (eq. 4), column 2 = normal. The normal sign follows the Newell
    vector of the exterior ring (outward for counter-clockwise-from-outside rings); column 1 is
    flipped if needed so that det(R) = +1.

    Returns centroids, rotations, areas, rms and eigval1 (F,) the middle eigenvalue (>= 0, the
    collinearity test); with extras also eigvals (F,3), newell_area and num_distinct (not needed
    by build_store: less memory without them).
    """
    fl = FaceList.from_faces(faces)
    F = len(fl)
    out = dict(
        centroids=np.zeros((F, 3)), rotations=np.zeros((F, 3, 3)), areas=np.zeros(F),
        rms=np.zeros(F), eigval1=np.zeros(F),
    )
    if extras:
        out.update(eigvals=np.zeros((F, 3)), newell_area=np.zeros(F),
                   num_distinct=np.zeros(F, np.int64))
    n = len(vertices) or 1
    for f0 in range(0, F, chunk_faces):
        f1 = min(F, f0 + chunk_faces)
        r0, r1 = int(fl.face_ring[f0]), int(fl.face_ring[f1])
        e0, e1 = int(fl.ring_ptr[r0]), int(fl.ring_ptr[r1])
        face_ring = fl.face_ring[f0:f1 + 1] - r0
        ring_ptr = fl.ring_ptr[r0:r1 + 1] - e0
        rings = _Rings(
            fl.ring_vertex[e0:e1], ring_ptr,
            np.repeat(np.arange(f1 - f0, dtype=np.int64), np.diff(face_ring)),
            np.ones(r1 - r0, dtype=bool),
        )
        rings.is_hole[face_ring[:-1]] = False
        _planes_chunk(vertices, rings, f1 - f0, n, out, slice(f0, f1))
    return out


def _planes_chunk(vertices, rings: _Rings, F: int, n: int, out: dict, sl: slice) -> None:
    ring_of = rings.ring_of_entry()
    face_of_entry = rings.face[ring_of]
    ptr, ids = _unique_per_group(face_of_entry, rings.vertex, F, n)
    counts = np.diff(ptr)
    owner = np.repeat(np.arange(F), counts)
    X = vertices[ids]
    del ids
    centroids = np.stack([np.bincount(owner, X[:, k], F) for k in range(3)], 1) / np.maximum(
        counts, 1
    )[:, None]
    D = X - centroids[owner]
    del X
    M = np.zeros((F, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            M[:, a, b] = M[:, b, a] = np.bincount(owner, D[:, a] * D[:, b], F)
    M /= np.maximum(counts - 1, 1)[:, None, None]
    eigvals, eigvecs = np.linalg.eigh(M)  # ascending
    del M
    eigvals = eigvals[:, ::-1]
    R = eigvecs[:, :, ::-1].copy()
    del eigvecs

    # Newell area vectors per ring (relative to the face centroid for precision)
    nxt = rings.next_index()
    P = vertices[rings.vertex] - centroids[face_of_entry]
    C = np.cross(P, P[nxt])
    C *= 0.5
    del P, nxt
    nring = len(rings.ptr) - 1
    ring_area_vec = np.stack([np.bincount(ring_of, C[:, k], nring) for k in range(3)], 1)
    del C, ring_of, face_of_entry
    ext = np.flatnonzero(~rings.is_hole)  # exactly one exterior per face, in face order
    ext_vec = ring_area_vec[ext]

    normals = R[:, :, 2]
    sign = np.where(np.einsum("fi,fi->f", normals, ext_vec) < 0, -1.0, 1.0)
    R[:, :, 2] *= sign[:, None]
    det = np.linalg.det(R)
    R[:, :, 1] *= np.where(det < 0, -1.0, 1.0)[:, None]
    normals = R[:, :, 2]

    proj = np.abs(np.einsum("ri,ri->r", ring_area_vec, normals[rings.face]))
    area = np.where(rings.is_hole, -proj, proj)
    areas = np.bincount(rings.face, area, F)

    resid = np.einsum("ki,ki->k", D, normals[owner])
    rms = np.sqrt(np.bincount(owner, resid**2, F) / np.maximum(counts, 1))
    out["centroids"][sl] = centroids
    out["rotations"][sl] = R
    out["areas"][sl] = areas
    out["rms"][sl] = rms
    out["eigval1"][sl] = np.clip(eigvals[:, 1], 0.0, None)
    if "eigvals" in out:
        out["eigvals"][sl] = np.clip(eigvals, 0.0, None)
        out["newell_area"][sl] = np.linalg.norm(ext_vec, axis=1)
        out["num_distinct"][sl] = counts


def _exact_duplicates(owned: list) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distinct points in lexicographic order: (uniq (U,3), inverse (N,) into uniq, first (U,)
    the smallest input index of each). The points come in a one-element list and are dropped
    from it (freed, when the caller holds no other reference) once the distinct ones are copied.

    Equal points are found by sorting a 64-bit hash of their coordinates (one key, one int64
    order array: less memory and time than a 3-key lexsort of all points); only the distinct
    points are sorted lexicographically. A hash collision between different points falls back
    to the lexsort."""
    points = owned[0]
    N = len(points)
    step = 1 << 16
    h = np.empty(N, dtype=np.uint64)
    with np.errstate(over="ignore"):
        for a in range(0, N, step):
            bits = (points[a:a + step] + 0.0).view(np.uint64)  # + 0.0: -0.0 hashes as 0.0
            h[a:a + step] = _splitmix(bits[:, 0] ^ _splitmix(bits[:, 1] ^ _splitmix(bits[:, 2])))
    order = np.argsort(h)
    new = np.empty(N, dtype=bool)
    new[0] = True
    P = None
    for a in range(1, N, step):  # new[i]: sorted point i differs from i - 1
        o = order[a - 1:a + step]
        P = points[o]
        np.any(P[1:] != P[:-1], axis=1, out=new[a:a + step])
        hs = h[o]
        if np.any(new[a:a + step] & (hs[1:] == hs[:-1])):  # collision (or NaN): be exact
            del h, order, new, P
            return _exact_duplicates_lexsort(points)
    del h, P
    starts = np.flatnonzero(new)
    first = np.minimum.reduceat(order, starts)  # equal points are in any order: take the min
    del starts
    inverse = np.empty(N, dtype=np.int64)
    g0 = -1
    for a in range(0, N, step):  # inverse[order] = cumsum(new) - 1, in chunks
        g = np.cumsum(new[a:a + step], dtype=np.int64)
        g += g0
        inverse[order[a:a + step]] = g
        g0 = int(g[-1])
    del order, new
    # number the distinct points in lexicographic order (ties: input order), as the lexsort did
    uniq = points[first]
    owned.clear()
    del points
    perm = np.lexsort((first, uniq[:, 2], uniq[:, 1], uniq[:, 0]))
    uniq, first = uniq[perm], first[perm]
    label = np.empty(len(perm), dtype=np.int64)
    label[perm] = np.arange(len(perm))
    del perm
    for a in range(0, N, 1 << 16):
        inverse[a:a + (1 << 16)] = label[inverse[a:a + (1 << 16)]]
    return uniq, inverse, first


def _exact_duplicates_lexsort(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """_exact_duplicates by a lexsort of all points (exact whatever the hashes do)."""
    N = len(points)
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))  # stable
    new = np.empty(N, dtype=bool)
    new[0] = True
    step, P = 1 << 18, None
    for a in range(1, N, step):
        P = points[order[a - 1:a + step]]
        np.any(P[1:] != P[:-1], axis=1, out=new[a:a + step])
    del P
    first = order[new]  # the stable sort puts the smallest input index first
    uniq = points[first]
    group = np.cumsum(new, dtype=np.int64)
    del new
    group -= 1
    inverse = np.empty(N, dtype=np.int64)
    inverse[order] = group
    return uniq, inverse, first


def merge_vertices(
    points: np.ndarray, tolerance: float, slack: float = DEFAULT_TOLERANCES.merge_slack
) -> tuple[np.ndarray, np.ndarray, float]:
    """Merge points closer than `tolerance + slack` (single linkage over a cKDTree).

    Returns (merged (V,3) = mean of each cluster, index (N,) into merged, widest cluster extent).
    Clusters are numbered in order of first appearance so the result is deterministic.
    """
    return _merge_vertices([points], tolerance, slack)


def _merge_vertices(owned: list, tolerance: float, slack: float):
    """merge_vertices on [points] handed over in a list: the points are dropped from it (and
    freed, when the caller kept no reference) as soon as the exact duplicates are known."""
    owned[0] = np.ascontiguousarray(owned[0], dtype=np.float64)
    N = len(owned[0])
    if N == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64), 0.0
    # exact duplicates first (most points are corners shared by several rings); the points are
    # released in there as soon as the distinct ones are known
    uniq, inverse, first = _exact_duplicates(owned)
    owned.clear()
    if tolerance > 0 and len(uniq) > 1:
        pairs = cKDTree(uniq).query_pairs(tolerance + slack, output_type="ndarray")
    else:
        pairs = np.zeros((0, 2), np.int64)
    n = len(uniq)
    if len(pairs):
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        nlab, labels = connected_components(graph, directed=False)
    else:
        nlab, labels = n, np.arange(n)
    # renumber clusters by first appearance in the input
    first_c = np.full(nlab, N, dtype=np.int64)
    np.minimum.at(first_c, labels, first)
    order = np.argsort(first_c)
    renum = np.empty_like(order)
    renum[order] = np.arange(len(order))
    cluster = renum[labels]
    counts = np.bincount(cluster)
    merged = np.stack([np.bincount(cluster, uniq[:, k]) for k in range(3)], 1) / counts[:, None]
    extent = 0.0
    if len(pairs):
        # only clusters with more than one point can be wider than 0
        members = np.unique(pairs)
        lo = np.full((len(counts), 3), np.inf)
        hi = np.full((len(counts), 3), -np.inf)
        np.minimum.at(lo, cluster[members], uniq[members])
        np.maximum.at(hi, cluster[members], uniq[members])
        wide = counts > 1
        extent = float(np.linalg.norm(hi[wide] - lo[wide], axis=1).max())
    cluster = cluster.astype(np.int64, copy=False)
    for a in range(0, N, 1 << 16):  # index = cluster[inverse], in place, in chunks
        inverse[a:a + (1 << 16)] = cluster[inverse[a:a + (1 << 16)]]
    return merged, inverse, extent


def _ring_key(ids: list[int]) -> tuple:
    """Same ring up to the starting vertex (orientation kept: reversed rings are other faces)."""
    if not ids:
        return ()
    k = ids.index(min(ids))
    return tuple(ids[k:] + ids[:k])


# ----------------------------------------------------------------------------------------------
# the store
# ----------------------------------------------------------------------------------------------


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
            self._cache["fv"] = _face_unique_vertices(self.faces)
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
    ) -> tuple[np.ndarray, np.ndarray]:
        """For each point: the face with the smallest |distance to plane| among faces whose
        polygon (with holes, grown by `margin` m) contains the point's orthogonal projection,
        only if |d| <= max_distance.

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
        first = np.r_[True, point[1:] != point[:-1]] if len(point) else np.zeros(0, bool)
        best[point[first]] = face[first]
        dist[point[first]] = d[first]
        return best, dist

    # -- derived stores ---------------------------------------------------------------------
    def with_vertices(self, vertices_local: np.ndarray) -> PlaneStore:
        """Same topology with new vertex coordinates; planes recomputed (model correction)."""
        V = np.asarray(vertices_local, dtype=np.float64)
        if V.shape != self.vertices.shape:
            raise ValueError(f"vertices must have shape {self.vertices.shape}, got {V.shape}")
        planes = _compute_planes(V, self.faces, extras=False)
        return replace(
            self,
            vertices=V.copy(),
            centroids=planes["centroids"],
            rotations=planes["rotations"],
            areas=planes["areas"],
            rms_out_of_plane=planes["rms"],
            nonplanar=planes["rms"] > self.tolerances.nonplanar,
            warnings=list(self.warnings),
            _cache={},
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


def default_origin(points_crs: np.ndarray) -> np.ndarray:
    """Lower bbox corner rounded down to whole metres (float64)."""
    if len(points_crs) == 0:
        return np.zeros(3)
    return np.floor(np.asarray(points_crs, dtype=np.float64).min(0))


def _splitmix(x: np.ndarray) -> np.ndarray:
    """64-bit mixing (splitmix64 finaliser), wrapping uint64 arithmetic."""
    x = x.astype(np.uint64, copy=True)
    x += np.uint64(0x9E3779B97F4A7C15)
    x ^= x >> np.uint64(30)
    x *= np.uint64(0xBF58476D1CE4E5B9)
    x ^= x >> np.uint64(27)
    x *= np.uint64(0x94D049BB133111EB)
    x ^= x >> np.uint64(31)
    return x


def _ring_hashes(ids: np.ndarray, ptr: np.ndarray, chunk_rings: int = 65536) -> np.ndarray:
    """(R,) uint64 hash of each ring up to its starting vertex (rotation to the smallest id,
    orientation kept), i.e. equal for rings with equal `_ring_key`. Rings must be non-empty.
    In chunks of rings to bound the temporaries."""
    R = len(ptr) - 1
    out = np.zeros(R, np.uint64)
    for r0 in range(0, R, chunk_rings):
        r1 = min(R, r0 + chunk_rings)
        out[r0:r1] = _ring_hashes_chunk(ids[ptr[r0]:ptr[r1]], ptr[r0:r1 + 1] - ptr[r0])
    return out


def _ring_hashes_chunk(ids: np.ndarray, ptr: np.ndarray) -> np.ndarray:
    R = len(ptr) - 1
    starts, lengths = ptr[:-1], np.diff(ptr)
    ring = np.repeat(np.arange(R), lengths)
    pos = np.arange(len(ids), dtype=np.int64) - starts[ring]
    ring_min = np.minimum.reduceat(ids, starts)
    first_min = np.minimum.reduceat(np.where(ids == ring_min[ring], pos, len(ids)), starts)
    rot = pos - first_min[ring]
    rot[rot < 0] += lengths[ring][rot < 0]
    # polynomial hash of the rotated sequence: sum mix(id) * B^rot (mod 2^64)
    powers = np.cumprod(np.full(int(lengths.max()), 0x100000001B3, dtype=np.uint64))
    with np.errstate(over="ignore"):
        terms = _splitmix(ids) * powers[rot]
        h = np.add.reduceat(terms, starts)
    return _splitmix(h ^ lengths.astype(np.uint64))


def _dedupe_faces(
    raw_semantic: CodedStrings, valid: np.ndarray, ext_hash: np.ndarray,
    hole_hash_sum: np.ndarray, gml_ids: PackedStrings, semantic: CodedStrings, ring_lists,
) -> tuple[np.ndarray, int, dict[int, str]]:
    """Which valid polygons become faces: a polygon whose gml:id or rings (up to the starting
    vertex; holes as a set) equal an earlier face's is merged into it (semantic class and id
    completed from the duplicate). Candidates come from hashes; the exact comparison (the
    original tuple keys) runs only on the few polygons that share a hash or an id.
    Returns (is_face bool (n,), number of duplicates, {row: gml id completed from a
    duplicate}); `semantic` is updated in place."""
    n = len(raw_semantic)
    is_face = valid.copy()
    key = _splitmix(ext_hash) + hole_hash_sum  # wraps
    cand = np.zeros(n, dtype=bool)
    vidx = np.flatnonzero(valid)
    if len(vidx) > 1:
        k = key[vidx]
        order = np.argsort(k, kind="stable")
        ks = k[order]
        same = ks[1:] == ks[:-1]
        hit = np.zeros(len(vidx), dtype=bool)
        hit[1:] |= same
        hit[:-1] |= same
        cand[vidx[order[hit]]] = True
    cand |= gml_ids.repeated_candidates()  # a superset of the rows whose id repeats
    cand &= valid
    filled: dict[int, str] = {}
    duplicates = 0
    seen: dict = {}
    for i in np.flatnonzero(cand).tolist():
        gid = gml_ids[i]
        ext, holes = ring_lists(i)
        key_ring = (_ring_key(ext), tuple(sorted(_ring_key(h) for h in holes)) if holes else ())
        prev = seen.get(("id", gid)) if gid else None
        if prev is None:
            prev = seen.get(key_ring)
        if prev is not None:
            duplicates += 1
            is_face[i] = False
            sem = raw_semantic[i]
            # the thematic surface knows the class; the solid only references the polygon
            if semantic[prev] in ("", "Unknown") and sem not in ("", "Unknown"):
                semantic[prev] = sem
            if gid and not filled.get(prev, gml_ids[prev]):
                filled[prev] = gid
            if gid:
                seen[("id", gid)] = prev
            continue
        seen[key_ring] = i
        if gid:
            seen[("id", gid)] = i
    return is_face, duplicates, filled


def build_store(
    raw: RawCityModel,
    merge_tolerance: float = DEFAULT_TOLERANCES.merge,
    origin: np.ndarray | None = None,
    nonplanar_tolerance: float = DEFAULT_TOLERANCES.nonplanar,
    tolerances: Tolerances | None = None,
    release_raw: bool = False,
) -> PlaneStore:
    """Turn reader output into a PlaneStore: local frame, merged vertices, de-duplicated faces,
    planes; degenerate faces dropped (counted), non-planar faces flagged (counted).

    Vectorised over all polygons (a 250k-polygon city in about a second), straight from the
    flat RawPolygonTable. release_raw: the caller hands the raw model over; its coordinates are
    released as soon as they are copied into the local frame (raw.polygons is unusable after)."""
    tol = replace(
        tolerances or DEFAULT_TOLERANCES, merge=merge_tolerance, nonplanar=nonplanar_tolerance
    )
    warnings = list(raw.warnings)
    table = raw.polygon_table()
    if release_raw:  # nothing but this function holds the polygons from here on
        raw.polygons = RawPolygonTable.empty()
    n = len(table)
    R = table.num_rings
    num_holes = table.poly_nring - 1
    # rings in the order: all exteriors, then all holes (polygon order); vertex numbering
    # follows first appearance in this order (the table keeps each polygon's rings together)
    if num_holes.any():
        is_ext = np.zeros(R, dtype=bool)
        is_ext[table.poly_ptr[:-1]] = True
        lengths = np.concatenate([table.ring_len[is_ext], table.ring_len[~is_ext]])
        del is_ext
    else:
        lengths = table.ring_len
    if origin is None:
        origin = np.floor(table.coords_min()) if table.num_points else np.zeros(3)
    else:
        origin = np.asarray(origin, dtype=np.float64)
    # release_raw: the raw coordinates are gone once they are copied to the local frame
    owned = [table.points_exteriors_first(origin, release=release_raw)]
    table.drop_cached_pointers()
    large = len(owned[0]) >= 1 << 17  # worth returning freed memory between the phases
    if large:
        release_free_memory()  # the parser's and the raw coordinates' memory
    merged, index, extent = _merge_vertices(owned, tol.merge, tol.merge_slack)
    if large:
        release_free_memory()
    if extent > tol.chain_warning:
        warnings.append(
            f"vertex merging (tolerance {tol.merge * 1000:.1f} mm) chained points up to "
            f"{extent * 1000:.1f} mm apart into one vertex"
        )

    # ring vertex ids, consecutive repeats (and the closing point) removed: an id is kept when
    # it differs from the previous one of its ring (cyclically)
    starts = np.cumsum(lengths) - lengths
    nonempty = lengths > 0
    s0 = starts[nonempty]
    keep = np.empty(len(index), dtype=bool)
    rlen = np.zeros(R, np.int64)
    if len(index):
        np.not_equal(index[1:], index[:-1], out=keep[1:])
        keep[s0] = index[s0] != index[(starts + lengths - 1)[nonempty]]
        rlen[nonempty] = np.add.reduceat(keep, s0, dtype=np.int64)
    del s0, starts, nonempty
    ids = _compress_rows(index, keep)  # in place: index is gone
    del index, keep
    rptr = _ptr(rlen)
    # >= 3 distinct ids: (no consecutive repeats left) some id differs from the first two
    first = ids[np.minimum(rptr[:-1], max(len(ids) - 1, 0))] if len(ids) else np.zeros(R, np.int64)
    second = ids[np.minimum(rptr[:-1] + 1, max(len(ids) - 1, 0))] if len(ids) else first
    ring_of = np.repeat(np.arange(R, dtype=np.int32 if R < 2**31 else np.int64), rlen)
    other = np.empty(len(ids), dtype=bool)
    for a in range(0, len(ids), 1 << 18):  # in chunks: no (K,) int64 temporaries
        r, v = ring_of[a:a + (1 << 18)], ids[a:a + (1 << 18)]
        np.logical_and(v != first[r], v != second[r], out=other[a:a + (1 << 18)])
        del r, v  # views: would keep ids alive after its del below
    ring_ok = (rlen >= 3) & (np.bincount(ring_of, other, R) > 0)
    del other, ring_of, first, second
    rs, rl = rptr[:-1], rlen  # ring r is ids[rs[r]:rs[r] + rl[r]]
    valid = ring_ok[:n].copy()
    hole_owner = np.repeat(np.arange(n), num_holes)
    hole_ok = ring_ok[n:]
    dropped_holes = int(np.count_nonzero(~hole_ok))
    dropped = int(np.count_nonzero(~valid))

    # duplicate detection on hashes of the valid rings
    ring_hash = np.zeros(R, np.uint64)
    sel = np.flatnonzero(ring_ok)
    if len(sel):
        sub = ids[_segment_gather(rs[sel], rl[sel])]
        ring_hash[sel] = _ring_hashes(sub, _ptr(rl[sel]))
        del sub
    hole_sum = np.zeros(n, np.uint64)
    if len(hole_owner):
        hh = np.where(hole_ok, _splitmix(ring_hash[n:] ^ np.uint64(0x5BD1E995)), np.uint64(0))
        np.add.at(hole_sum, hole_owner, hh)
    gml_ids = table.gml_id
    building_ids, part_ids = table.building_id, table.part_id
    raw_semantic = table.semantic
    semantic = raw_semantic.normalized({"": "Unknown"})  # completed by the de-duplication
    hole_first = np.cumsum(num_holes) - num_holes + n

    def ring_lists(i: int):
        ext = ids[rs[i]:rs[i] + rl[i]].tolist()
        hs = [ids[rs[r]:rs[r] + rl[r]].tolist()
              for r in range(hole_first[i], hole_first[i] + num_holes[i]) if ring_ok[r]]
        return ext, hs

    is_face, duplicates, filled = _dedupe_faces(
        raw_semantic, valid, ring_hash[:n], hole_sum, gml_ids, semantic, ring_lists
    )
    if duplicates:
        logger.debug("%d polygons referenced twice became one face each", duplicates)
    if dropped_holes:
        warnings.append(f"{dropped_holes} degenerate interior rings dropped")

    # the faces in flat arrays: per face its exterior, then its valid holes
    src = np.flatnonzero(is_face)
    hole_rings = n + np.flatnonzero(hole_ok & is_face[hole_owner])
    face_rings = np.concatenate([src, hole_rings])
    owner = np.concatenate([src, hole_owner[hole_rings - n]])
    face_rings = face_rings[np.argsort(owner, kind="stable")]
    del owner
    if len(face_rings) == R and np.array_equal(face_rings, np.arange(R)):
        ring_vertex = ids  # every ring in place (no holes, nothing dropped)
    else:
        ring_vertex = _gather_segments(ids, rs[face_rings], rl[face_rings])
    del ids, ring_lists
    face_ptr = _ptr(1 + np.bincount(hole_owner[hole_rings - n], minlength=n)[src])
    faces = FaceList._own(
        ring_vertex,
        _ptr(rl[face_rings]),
        face_ptr,
        semantic.take(is_face),
        building_ids.take(is_face),
        part_ids.take(is_face),
        gml_ids.take(is_face).replaced(
            {int(np.searchsorted(src, row)): gid for row, gid in filled.items()}
        ),
        table.lod[src],
    )
    del ring_vertex, semantic, gml_ids, building_ids, part_ids, table, raw_semantic
    del rs, rl, ring_ok, ring_hash, hole_sum, valid, is_face, src, hole_rings, face_rings

    if large:
        release_free_memory()
    planes = _compute_planes(merged, faces, extras=False)
    if large:
        release_free_memory()  # the plane chunks' temporaries
    degenerate = (planes["areas"] < tol.min_area) | (
        np.sqrt(planes["eigval1"]) < tol.collinear
    )
    del planes["eigval1"]  # not kept: free before copying
    if degenerate.any():
        dropped += int(degenerate.sum())
        keep = ~degenerate
        faces = faces.compress(keep)
        for k in list(planes):  # compacted in place: no second copy of the plane arrays
            planes[k] = _compress_rows(planes[k], keep)
    if dropped:
        warnings.append(f"{dropped} degenerate faces dropped (< 3 vertices, tiny area, collinear)")

    if large:
        release_free_memory()
    # drop vertices no face uses any more and re-index
    used = np.bincount(faces.ring_vertex, minlength=len(merged)) > 0
    remap = np.cumsum(used)
    remap -= 1  # new index of each used vertex
    rv = faces.ring_vertex
    for a in range(0, len(rv), 1 << 16):  # rv = remap[rv], in place, in chunks
        rv[a:a + (1 << 16)] = remap[rv[a:a + (1 << 16)]]
    del remap, rv
    vertices = _compress_rows(merged, used)  # in place
    del merged, used

    _orient_by_semantics(planes, faces, warnings)
    nonplanar = planes["rms"] > tol.nonplanar
    if nonplanar.any():
        warnings.append(
            f"{int(nonplanar.sum())} non-planar faces (RMS out-of-plane > {tol.nonplanar} m) kept"
        )
    parts = set(raw.part_ids) | faces.part_id.unique()
    buildings = set(raw.building_ids) | faces.building_id.take(faces.part_id.mask("")).unique()
    store = PlaneStore(
        origin=origin,
        crs=raw.crs,
        vertices=vertices,
        faces=faces,
        centroids=planes["centroids"],
        rotations=planes["rotations"],
        areas=planes["areas"],
        rms_out_of_plane=planes["rms"],
        nonplanar=nonplanar,
        source=raw.source,
        format=raw.format,
        version=raw.version,
        num_buildings=len(buildings - {""}),
        num_parts=len(parts - {""}),
        num_dropped_degenerate=dropped,
        warnings=warnings,
        tolerances=tol,
    )
    logger.debug(
        "store: %d faces, %d vertices, %d dropped, %d non-planar",
        store.num_faces, len(vertices), dropped, int(nonplanar.sum()),
    )
    return store


def _orient_by_semantics(planes: dict, faces: FaceList, warnings: list[str]) -> None:
    """Rings give the orientation; a roof whose ring says "facing down" or a ground surface
    "facing up" has a reversed ring (seen in real data), so the semantics win there."""
    F = len(faces)
    if not F:
        return
    nz = planes["rotations"][:, 2, 2]
    roof = faces.semantic.mask("RoofSurface")
    ground = faces.semantic.mask("GroundSurface")
    flip = (roof & (nz < -0.1)) | (ground & (nz > 0.1))
    if flip.any():
        R = planes["rotations"]
        R[flip, :, 2] *= -1
        R[flip, :, 1] *= -1  # keep det(R) = +1
        # reverse every ring of the flipped faces in place
        fsel = np.flatnonzero(flip)
        rsel = _segment_gather(faces.face_ring[fsel], np.diff(faces.face_ring)[fsel])
        s, L = faces.ring_ptr[rsel], np.diff(faces.ring_ptr)[rsel]
        src = _segment_gather(s, L)
        ring = np.repeat(np.arange(len(rsel)), L)
        dst = 2 * s[ring] + L[ring] - 1 - src  # s + (L - 1 - (src - s))
        rv = faces.ring_vertex
        rv[dst] = rv[src].copy()
        warnings.append(
            f"{int(flip.sum())} roof/ground faces had reversed rings; oriented by their class"
        )


def store_from_polygons(
    polygons: list[np.ndarray],
    *,
    semantics: list[str] | None = None,
    origin: np.ndarray | None = None,
    crs: CRSInfo | None = None,
    holes: list[list[np.ndarray]] | None = None,
    building_ids: list[str] | None = None,
    merge_tolerance: float = DEFAULT_TOLERANCES.merge,
) -> PlaneStore:
    """A store from plain (N,3) rings (synthetic scenes, tests, the simulator).

    Rings run counter-clockwise seen from outside (that orientation gives the normal sign).
    Coordinates are taken as CRS coordinates; pass origin=np.zeros(3) to keep them as they are.
    """
    n = len(polygons)
    semantics = semantics or ["Unknown"] * n
    holes = holes or [[] for _ in range(n)]
    building_ids = building_ids or ["b0"] * n
    raw = RawCityModel(
        source="<polygons>",
        format="synthetic",
        version="",
        crs=crs or local_engineering_crs(),
        polygons=[
            RawPolygon(
                exterior=np.asarray(p, dtype=np.float64).reshape(-1, 3),
                holes=[np.asarray(h, dtype=np.float64).reshape(-1, 3) for h in holes[i]],
                semantic=semantics[i],
                building_id=building_ids[i],
                gml_id=f"poly_{i}",
            )
            for i, p in enumerate(polygons)
        ],
        building_ids=sorted(set(building_ids)),
        part_ids=[],
    )
    return build_store(raw, merge_tolerance=merge_tolerance, origin=origin)
