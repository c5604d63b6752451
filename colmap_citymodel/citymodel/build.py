"""Building a plane store from raw polygons: vertices merged within the tolerance, duplicate
faces removed, planes fitted and oriented by their semantics."""

from __future__ import annotations

import ctypes
import functools
import logging
import platform
import sys
from dataclasses import replace

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .faces import FaceList, compress_rows, compute_planes, gather_segments, offsets_from_counts, segment_gather
from .raw_model import CodedStrings, CRSInfo, PackedStrings, RawCityModel, RawPolygon, RawPolygonTable
from .store import DEFAULT_TOLERANCES, PlaneStore, Tolerances, VertexProvenance

logger = logging.getLogger(__name__)


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


def _merge_vertices(owned: list, tolerance: float, slack: float,
                    provenance: list | None = None):
    """merge_vertices on [points] handed over in a list: the points are dropped from it (and
    freed, when the caller kept no reference) as soon as the exact duplicates are known.
    `provenance`, when given a list, receives (distinct points (U,3) in lexicographic order,
    their cluster (U,)): which merged vertex each distinct input coordinate became."""
    owned[0] = np.ascontiguousarray(owned[0], dtype=np.float64)
    N = len(owned[0])
    if N == 0:
        if provenance is not None:
            provenance.append((np.zeros((0, 3)), np.zeros(0, np.int64)))
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
    if provenance is not None:
        provenance.append((uniq, cluster))
    for a in range(0, N, 1 << 16):  # index = cluster[inverse], in place, in chunks
        inverse[a:a + (1 << 16)] = cluster[inverse[a:a + (1 << 16)]]
    return merged, inverse, extent


def _ring_key(ids: list[int]) -> tuple:
    """Same ring up to the starting vertex (orientation kept: reversed rings are other faces)."""
    if not ids:
        return ()
    k = ids.index(min(ids))
    return tuple(ids[k:] + ids[:k])


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
    keep_provenance: bool = True,
) -> PlaneStore:
    """Turn reader output into a PlaneStore: local frame, merged vertices, de-duplicated faces,
    planes; degenerate faces dropped (counted), non-planar faces flagged (counted).

    Vectorised over all polygons (a 250k-polygon city in about a second), straight from the
    flat RawPolygonTable. release_raw: the caller hands the raw model over; its coordinates are
    released as soon as they are copied into the local frame (raw.polygons is unusable after).
    keep_provenance: the store keeps, for every distinct coordinate read, the vertex it was
    merged into (`PlaneStore.provenance`: what a corrected model is written back through;
    32 bytes per distinct coordinate)."""
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
    merged_from: list | None = [] if keep_provenance else None
    merged, index, extent = _merge_vertices(owned, tol.merge, tol.merge_slack, merged_from)
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
    ids = compress_rows(index, keep)  # in place: index is gone
    del index, keep
    rptr = offsets_from_counts(rlen)
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
        sub = ids[segment_gather(rs[sel], rl[sel])]
        ring_hash[sel] = _ring_hashes(sub, offsets_from_counts(rl[sel]))
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
        ring_vertex = gather_segments(ids, rs[face_rings], rl[face_rings])
    del ids, ring_lists
    face_ptr = offsets_from_counts(1 + np.bincount(hole_owner[hole_rings - n], minlength=n)[src])
    faces = FaceList._own(
        ring_vertex,
        offsets_from_counts(rl[face_rings]),
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
    planes = compute_planes(merged, faces, extras=False)
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
            planes[k] = compress_rows(planes[k], keep)
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
    provenance = None
    if merged_from:
        points, cluster = merged_from.pop()
        provenance = VertexProvenance(points, np.where(used[cluster], remap[cluster], -1))
        del points, cluster
    del remap, rv
    vertices = compress_rows(merged, used)  # in place
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
        provenance=provenance,
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
        rsel = segment_gather(faces.face_ring[fsel], np.diff(faces.face_ring)[fsel])
        s, L = faces.ring_ptr[rsel], np.diff(faces.ring_ptr)[rsel]
        src = segment_gather(s, L)
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
