"""Plain data that every city model reader returns, before vertices are merged into a store.

Readers (read_citygml.py, read_cityjson.py) produce a `RawCityModel` whose polygons are a flat
`RawPolygonTable` (grown with a `RawPolygonBuilder`); plane_store.build_store() turns it into a
`PlaneStore`. A plain list of `RawPolygon` is accepted as well (synthetic scenes, tests). Coordinates here are still in the file's CRS (or the target CRS
when the reader reprojected), float64, never shifted.
"""

from __future__ import annotations

import operator
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np


@dataclass
class CRSInfo:
    """A resolved coordinate reference system of a city model."""

    srs_name: str | None  # as written in the file (or given by the user)
    horizontal_epsg: int | None  # e.g. 25832
    vertical_epsg: int | None  # e.g. 7837 (DHHN2016 height); None when unknown/absent
    wkt: str  # WKT2 of the (compound) CRS
    is_projected: bool
    units: str = "metre"

    @property
    def label(self) -> str:
        if self.horizontal_epsg and self.vertical_epsg:
            return f"EPSG:{self.horizontal_epsg}+{self.vertical_epsg}"
        if self.horizontal_epsg:
            return f"EPSG:{self.horizontal_epsg}"
        return self.srs_name or "unknown"


@dataclass(slots=True)
class RawPolygon:
    """One planar surface polygon as read from a file (slots: a city has 1e5-1e6 of them)."""

    exterior: np.ndarray  # (N, 3) float64, ring without the repeated closing point
    holes: list[np.ndarray] = field(default_factory=list)  # each (M, 3) float64
    semantic: str = "Unknown"  # WallSurface, RoofSurface, GroundSurface, ClosureSurface, ...
    building_id: str = ""
    part_id: str = ""  # BuildingPart id, "" when the polygon belongs to the building itself
    gml_id: str = ""  # the polygon's own id ("" when it has none)
    lod: int = 2
    from_solid: bool = False  # True when the polygon is a face of a closed solid (outward order)


@dataclass
class RawCityModel:
    source: str  # file path(s) it was read from
    format: str  # "CityGML" or "CityJSON"
    version: str  # "1.0", "2.0", "3.0", "1.1", ...
    crs: CRSInfo
    polygons: Sequence[RawPolygon]  # a RawPolygonTable from the readers, or a list
    building_ids: list[str]
    part_ids: list[str]
    warnings: list[str] = field(default_factory=list)

    def polygon_table(self) -> RawPolygonTable:
        """The polygons as a RawPolygonTable (the table itself, or a new one from a list)."""
        return RawPolygonTable.from_polygons(self.polygons)


def _ptr(counts: np.ndarray) -> np.ndarray:
    ptr = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(counts, out=ptr[1:])
    return ptr


_NO_POINTS = np.zeros((0, 3))


class RawPolygonTable(Sequence):
    """All polygons of a model in flat arrays, behaving like a read-only list of `RawPolygon`.

    A city of 2.5e5 polygons held as RawPolygon objects costs ~500 bytes per polygon beyond its
    coordinates; here it is one float64 coordinate array (kept as a list of chunks until someone
    needs it whole, so readers and tile merging never copy it), ring lengths, rings per polygon
    and per-polygon attribute lists (the strings are shared with the readers) and arrays.

    coords: (P, 3) float64, all rings one after the other: per polygon its exterior, then its
        holes (rings without the repeated closing point);
    ring_len: (R,) int64 points per ring; poly_nring: (N,) int64 rings per polygon (>= 1);
    semantic, building_id, part_id, gml_id: lists of N str; lod: (N,) int16;
    from_solid: (N,) bool.

    `table[i]` builds a RawPolygon whose arrays are views into `coords`: changing the returned
    object does not change the table (use the arrays/lists here for that).
    """

    __slots__ = ("_chunks", "ring_len", "poly_nring", "semantic", "building_id", "part_id",
                 "gml_id", "lod", "from_solid", "_ring_ptr", "_poly_ptr")

    def __init__(self, coords, ring_len, poly_nring, semantic, building_id, part_id, gml_id, lod,
                 from_solid):
        chunks = coords if isinstance(coords, list) else [coords]
        self._chunks = [np.asarray(c, dtype=np.float64).reshape(-1, 3) for c in chunks]
        self.ring_len = np.asarray(ring_len, dtype=np.int64)
        self.poly_nring = np.asarray(poly_nring, dtype=np.int64)
        self.semantic = semantic
        self.building_id = building_id
        self.part_id = part_id
        self.gml_id = gml_id
        self.lod = np.asarray(lod, dtype=np.int16)
        self.from_solid = np.asarray(from_solid, dtype=bool)
        self._ring_ptr = None
        self._poly_ptr = None

    @classmethod
    def empty(cls) -> RawPolygonTable:
        return cls([], np.zeros(0, np.int64), np.zeros(0, np.int64), [], [], [], [],
                   np.zeros(0, np.int16), np.zeros(0, bool))

    @classmethod
    def from_polygons(cls, polygons) -> RawPolygonTable:
        """A table from RawPolygon objects (or anything with their attributes)."""
        if isinstance(polygons, RawPolygonTable):
            return polygons
        b = RawPolygonBuilder()
        for p in polygons:
            b.add(p.exterior, p.holes, p.semantic, p.building_id, p.part_id, p.gml_id, p.lod,
                  p.from_solid)
        return b.finish()

    @classmethod
    def concatenate(cls, tables: list[RawPolygonTable]) -> RawPolygonTable:
        """One table from several (the coordinate chunks are shared, not copied)."""
        if len(tables) == 1:
            return tables[0]
        cat = lambda name: [x for t in tables for x in getattr(t, name)]  # noqa: E731
        arr = lambda name, dt: (np.concatenate([getattr(t, name) for t in tables])  # noqa: E731
                                if tables else np.zeros(0, dt))
        return cls(
            [c for t in tables for c in t._chunks], arr("ring_len", np.int64),
            arr("poly_nring", np.int64), cat("semantic"), cat("building_id"), cat("part_id"),
            cat("gml_id"), arr("lod", np.int16), arr("from_solid", bool),
        )

    # -- coordinates ------------------------------------------------------------------------
    @property
    def coords(self) -> np.ndarray:
        """(P, 3) float64 coordinates of all rings (the chunks joined on first use)."""
        if len(self._chunks) != 1:
            self._chunks = [np.concatenate(self._chunks) if self._chunks else _NO_POINTS.copy()]
        return self._chunks[0]

    @coords.setter
    def coords(self, value: np.ndarray) -> None:
        value = np.asarray(value, dtype=np.float64).reshape(-1, 3)
        if len(value) != self.num_points:
            raise ValueError(f"{len(value)} coordinates for {self.num_points} points")
        self._chunks = [value]

    @property
    def num_points(self) -> int:
        return sum(len(c) for c in self._chunks)

    def coords_min(self) -> np.ndarray:
        """(3,) lower corner of all coordinates (without joining the chunks)."""
        mins = [c.min(0) for c in self._chunks if len(c)]
        return np.min(mins, axis=0) if mins else np.zeros(3)

    def pop_coords(self, shift: np.ndarray | None = None) -> np.ndarray:
        """All coordinates minus `shift` as one new array, releasing the table's own copy chunk
        by chunk (peak: the result plus one chunk). The table has no coordinates afterwards:
        only for a caller that owns the table (plane_store.build_store(release_raw=True))."""
        chunks, self._chunks = self._chunks, []
        if len(chunks) == 1:
            out = chunks.pop()
            return out if shift is None else _shift_owned(out, shift)
        out = np.empty((sum(len(c) for c in chunks), 3))
        k = 0
        chunks.reverse()
        while chunks:
            c = chunks.pop()
            if shift is None:
                out[k:k + len(c)] = c
            else:
                np.subtract(c, shift, out=out[k:k + len(c)])
            k += len(c)
            del c
        return out

    def points_exteriors_first(self, shift: np.ndarray, release: bool = False) -> np.ndarray:
        """(P, 3) new array: coordinates minus `shift`, the points of all exteriors first (in
        polygon order), then those of all holes (the ring order of plane_store.build_store).
        release: drop the table's coordinates chunk by chunk while copying (peak: the result
        plus one chunk); the table has no coordinates afterwards (for an owner only)."""
        is_ext = np.zeros(self.num_rings, dtype=bool)
        is_ext[self.poly_ptr[:-1]] = True
        if is_ext.all():
            return self.pop_coords(shift) if release else self.coords - shift
        mask = np.repeat(is_ext, self.ring_len)
        out = np.empty((len(mask), 3))
        e, h = 0, int(np.count_nonzero(mask))  # next exterior / hole point
        chunks = self._chunks
        if release:
            self._chunks = []
            chunks.reverse()
        k, step = 0, 1 << 16
        for c in (chunks.pop() for _ in range(len(chunks))) if release else chunks:
            for a in range(0, len(c), step):
                piece = c[a:a + step]
                m = mask[k + a:k + a + len(piece)]
                ext = piece[m]
                np.subtract(ext, shift, out=out[e:e + len(ext)])
                e += len(ext)
                hole = piece[~m]
                np.subtract(hole, shift, out=out[h:h + len(hole)])
                h += len(hole)
            k += len(c)
            del c
        return out

    # -- structure ---------------------------------------------------------------------------
    @property
    def ring_ptr(self) -> np.ndarray:
        """(R+1,) ring r is coords[ring_ptr[r]:ring_ptr[r+1]]."""
        if self._ring_ptr is None or len(self._ring_ptr) != len(self.ring_len) + 1:
            self._ring_ptr = _ptr(self.ring_len)
        return self._ring_ptr

    @property
    def poly_ptr(self) -> np.ndarray:
        """(N+1,) polygon i owns rings poly_ptr[i]:poly_ptr[i+1]; the first is its exterior."""
        if self._poly_ptr is None or len(self._poly_ptr) != len(self.poly_nring) + 1:
            self._poly_ptr = _ptr(self.poly_nring)
        return self._poly_ptr

    @property
    def num_rings(self) -> int:
        return len(self.ring_len)

    def __len__(self) -> int:
        return len(self.poly_nring)

    def _polygon(self, i: int, coords, rp, pp) -> RawPolygon:
        a, b = pp[i], pp[i + 1]
        return RawPolygon(
            exterior=coords[rp[a]:rp[a + 1]],
            holes=[coords[rp[r]:rp[r + 1]] for r in range(a + 1, b)],
            semantic=self.semantic[i],
            building_id=self.building_id[i],
            part_id=self.part_id[i],
            gml_id=self.gml_id[i],
            lod=int(self.lod[i]),
            from_solid=bool(self.from_solid[i]),
        )

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        i = operator.index(i)
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError("polygon index out of range")
        return self._polygon(i, self.coords, self.ring_ptr, self.poly_ptr)

    def __iter__(self):
        coords = self.coords
        rp, pp = self.ring_ptr.tolist(), self.poly_ptr.tolist()
        for i in range(len(self)):
            yield self._polygon(i, coords, rp, pp)

    def __repr__(self) -> str:
        return f"RawPolygonTable({len(self)} polygons, {self.num_rings} rings, {self.num_points} points)"

    def take(self, sel) -> RawPolygonTable:
        """The polygons `sel` (int indices or a bool mask), in that order."""
        sel = np.asarray(sel)
        if sel.dtype == bool:
            sel = np.flatnonzero(sel)
        sel = sel.astype(np.int64, copy=False)
        pp, rp = self.poly_ptr, self.ring_ptr
        nr = self.poly_nring[sel]
        rings = _segment_gather(pp[sel], nr)
        rl = self.ring_len[rings]
        pts = _segment_gather(rp[rings], rl)
        pick = lambda values: [values[i] for i in sel.tolist()]  # noqa: E731
        return RawPolygonTable(
            self.coords[pts], rl, nr, pick(self.semantic), pick(self.building_id),
            pick(self.part_id), pick(self.gml_id), self.lod[sel], self.from_solid[sel],
        )

    def nbytes(self) -> int:
        return (sum(c.nbytes for c in self._chunks) + self.ring_len.nbytes + self.poly_nring.nbytes
                + self.lod.nbytes + self.from_solid.nbytes + 8 * 4 * len(self))


def _shift_owned(a: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """a - shift, in place when `a` owns writeable memory."""
    if a.base is None and a.flags.writeable and a.flags.c_contiguous:
        a -= shift
        return a
    return a - shift


def _segment_gather(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Indices of the concatenated segments [starts[i], starts[i] + lengths[i])."""
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    offs = np.cumsum(lengths) - lengths
    return np.arange(total, dtype=np.int64) + np.repeat(starts - offs, lengths)


class RawPolygonBuilder:
    """Grows a RawPolygonTable: readers append polygons one by one (`add`) or a city object's
    polygons at once (`add_block`); small coordinate blocks are joined into chunks of about
    `chunk_points` points so that a city becomes a few dozen arrays, not 1e5."""

    def __init__(self, chunk_points: int = 1 << 16):
        self.chunk_points = chunk_points
        self._chunks: list[np.ndarray] = []
        self._blocks: list[np.ndarray] = []
        self._block_points = 0
        self._ring_len: list[np.ndarray] = []
        self._poly_nring: list[np.ndarray] = []
        self._lod: list[np.ndarray] = []
        self._from_solid: list[np.ndarray] = []
        self._pending_rl: list[int] = []  # ring lengths / rings of single `add` calls
        self._pending_nr: list[int] = []
        self._pending_lod: list[int] = []
        self._pending_solid: list[bool] = []
        self.semantic: list[str] = []
        self.building_id: list[str] = []
        self.part_id: list[str] = []
        self.gml_id: list[str] = []

    def __len__(self) -> int:
        return len(self.semantic)

    def _push_coords(self, block: np.ndarray) -> None:
        if len(block) == 0:
            return
        self._blocks.append(block)
        self._block_points += len(block)
        if self._block_points >= self.chunk_points:
            self._flush_blocks()

    def _flush_blocks(self) -> None:
        if self._blocks:
            self._chunks.append(
                np.concatenate(self._blocks) if len(self._blocks) > 1
                else self._blocks[0] if self._blocks[0].base is None else self._blocks[0].copy()
            )
            self._blocks = []
            self._block_points = 0

    def _flush_pending(self) -> None:
        if self._pending_nr:
            self._ring_len.append(np.array(self._pending_rl, dtype=np.int64))
            self._poly_nring.append(np.array(self._pending_nr, dtype=np.int64))
            self._lod.append(np.array(self._pending_lod, dtype=np.int16))
            self._from_solid.append(np.array(self._pending_solid, dtype=bool))
            self._pending_rl, self._pending_nr = [], []
            self._pending_lod, self._pending_solid = [], []

    def add(self, exterior, holes=(), semantic="Unknown", building_id="", part_id="", gml_id="",
            lod=2, from_solid=False) -> int:
        """Append one polygon (rings (N,3) float64); returns its index."""
        rings = [np.asarray(exterior, dtype=np.float64).reshape(-1, 3)]
        rings += [np.asarray(h, dtype=np.float64).reshape(-1, 3) for h in holes]
        for r in rings:
            self._push_coords(r)
        self._pending_rl.extend(len(r) for r in rings)
        self._pending_nr.append(len(rings))
        self._pending_lod.append(int(lod))
        self._pending_solid.append(bool(from_solid))
        self.semantic.append(semantic)
        self.building_id.append(building_id)
        self.part_id.append(part_id)
        self.gml_id.append(gml_id)
        if len(self._pending_nr) >= 4096:
            self._flush_pending()
        return len(self.semantic) - 1

    def add_block(self, coords: np.ndarray, ring_len, poly_nring, semantic: list[str],
                  building_id: list[str], part_id: list[str], gml_id: list[str], lod,
                  from_solid) -> None:
        """Append several polygons given in flat form (as in RawPolygonTable)."""
        self._flush_pending()
        n = len(semantic)
        self._push_coords(np.asarray(coords, dtype=np.float64).reshape(-1, 3))
        self._ring_len.append(np.asarray(ring_len, dtype=np.int64))
        self._poly_nring.append(np.asarray(poly_nring, dtype=np.int64))
        self._lod.append(np.broadcast_to(np.asarray(lod, dtype=np.int16), (n,)))
        self._from_solid.append(np.broadcast_to(np.asarray(from_solid, dtype=bool), (n,)))
        self.semantic.extend(semantic)
        self.building_id.extend(building_id)
        self.part_id.extend(part_id)
        self.gml_id.extend(gml_id)

    def finish(self) -> RawPolygonTable:
        self._flush_pending()
        self._flush_blocks()
        cat = lambda parts, dt: np.concatenate(parts) if parts else np.zeros(0, dt)  # noqa: E731
        table = RawPolygonTable(
            self._chunks, cat(self._ring_len, np.int64), cat(self._poly_nring, np.int64),
            self.semantic, self.building_id, self.part_id, self.gml_id,
            cat(self._lod, np.int16), cat(self._from_solid, bool),
        )
        self.__init__(self.chunk_points)
        return table
