"""Faces of the plane store packed in flat arrays (rings as vertex-id runs), and the planes
fitted to them."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .raw_model import CodedStrings, PackedStrings, row_index


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


def compress_rows(a: np.ndarray, mask: np.ndarray) -> np.ndarray:
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


def gather_segments(values: np.ndarray, starts: np.ndarray, lengths: np.ndarray,
                     step: int = 1 << 16) -> np.ndarray:
    """values[concatenated segments [starts[i], starts[i] + lengths[i])], in chunks of
    segments (no index array of the full result)."""
    ptr = offsets_from_counts(lengths)
    out = np.empty(int(ptr[-1]), dtype=values.dtype)
    for a in range(0, len(starts), step):
        b = min(len(starts), a + step)
        out[ptr[a]:ptr[b]] = values[segment_gather(starts[a:b], lengths[a:b])]
    return out


def segment_gather(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Indices of the concatenated segments [starts[i], starts[i] + lengths[i])."""
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offs = np.cumsum(lengths) - lengths
    return np.arange(total, dtype=np.int64) + np.repeat(starts - offs, lengths)


def offsets_from_counts(counts: np.ndarray) -> np.ndarray:
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
            offsets_from_counts(np.array([len(r) for r in rings], dtype=np.int64)),
            offsets_from_counts(np.array([1 + len(f.holes) for f in faces], dtype=np.int64)),
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
        rings = segment_gather(self.face_ring[sel], nr)
        rlen = np.diff(self.ring_ptr)[rings]
        entries = segment_gather(self.ring_ptr[rings], rlen)
        return FaceList(
            self.ring_vertex[entries], offsets_from_counts(rlen), offsets_from_counts(nr),
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
        ring_vertex = compress_rows(self.ring_vertex, entry_keep)  # self's rings are gone after
        del entry_keep
        return FaceList._own(
            ring_vertex, offsets_from_counts(rlen[ring_keep]), offsets_from_counts(nr[keep]),
            CodedStrings(compress_rows(self.semantic.codes, keep), self.semantic.categories),
            CodedStrings(compress_rows(self.building_id.codes, keep), self.building_id.categories),
            CodedStrings(compress_rows(self.part_id.codes, keep), self.part_id.categories),
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
    return offsets_from_counts(np.bincount(fo, minlength=num_groups)), ids


def face_unique_vertices(faces) -> tuple[np.ndarray, np.ndarray]:
    """CSR (ptr, ids) of the unique vertex ids of each face (exterior + holes), ids sorted."""
    fl = FaceList.from_faces(faces)
    F = len(fl)
    if F == 0:
        return np.zeros(1, np.int64), np.zeros(0, np.int64)
    ids = fl.ring_vertex
    n = int(ids.max()) + 1 if len(ids) else 1
    return _unique_per_group(fl.entry_face(), ids, F, n)


def compute_planes(vertices: np.ndarray, faces, chunk_faces: int = 8192,
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
