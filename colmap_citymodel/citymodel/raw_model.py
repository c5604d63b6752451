"""Plain data that every city model reader returns, before vertices are merged into a store.

Readers (read_citygml.py, read_cityjson.py) produce a `RawCityModel` whose polygons are a flat
`RawPolygonTable` (grown with a `RawPolygonBuilder`); citymodel.store.build_store() turns it into a
`PlaneStore`. A plain list of `RawPolygon` is accepted as well (synthetic scenes, tests). Coordinates here are still in the file's CRS (or the target CRS
when the reader reprojected), float64, never shifted.
"""

from __future__ import annotations

import operator
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np


def row_index(i, n: int, what: str) -> int:
    """A sequence index (negative counts from the end) checked against length n."""
    i = operator.index(i)
    if i < 0:
        i += n
    if not 0 <= i < n:
        raise IndexError(f"{what} index out of range")
    return i


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


class _Lookup(dict):
    """str -> code, a new code for a new string (insertion order = code order)."""

    __slots__ = ()

    def __missing__(self, key: str) -> int:
        code = self[key] = len(self)
        return code


_ROWS = 1 << 16  # rows per chunk when a column is iterated or gathered


class CodedStrings(Sequence):
    """A column of strings with few distinct values (semantic class, building and part id),
    behaving like a list of str: int32 codes into a list of categories.

    codes (N,) int32; categories: list of str (a string may appear twice after concatenation
    or assignment; compare strings, not codes, across columns). `column[i] = value` is
    supported (a few rows: readers completing a semantic class)."""

    __slots__ = ("codes", "categories", "_lookup")

    def __init__(self, codes, categories):
        self.codes = np.asarray(codes, dtype=np.int32)
        self.categories = list(categories)
        self._lookup = None

    @classmethod
    def from_values(cls, values) -> CodedStrings:
        if isinstance(values, CodedStrings):
            return values
        lookup = _Lookup()
        codes = np.fromiter(map(lookup.__getitem__, values), np.int32)
        return cls(codes, list(lookup))

    @classmethod
    def concatenate(cls, columns: list) -> CodedStrings:
        columns = [cls.from_values(c) for c in columns]
        if len(columns) == 1:
            return columns[0]
        lookup = _Lookup()
        parts = []
        for c in columns:
            remap = np.fromiter(map(lookup.__getitem__, c.categories), np.int32, len(c.categories))
            parts.append(remap[c.codes] if len(c.codes) else c.codes)
        codes = np.concatenate(parts) if parts else np.zeros(0, np.int32)
        return cls(codes, list(lookup))

    def code(self, value: str) -> int:
        """The code of `value` (a new category when it has none)."""
        if self._lookup is None:  # first occurrence of each value
            self._lookup = {c: i for i, c in reversed(list(enumerate(self.categories)))}
        code = self._lookup.get(value)
        if code is None:
            code = self._lookup[value] = len(self.categories)
            self.categories.append(value)
        return code

    def __len__(self) -> int:
        return len(self.codes)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return list(map(self.categories.__getitem__, self.codes[i].tolist()))
        return self.categories[self.codes[i]]

    def __setitem__(self, i, value: str) -> None:
        self.codes[operator.index(i)] = self.code(value)

    def __iter__(self):
        cats = self.categories.__getitem__
        for a in range(0, len(self.codes), _ROWS):
            yield from map(cats, self.codes[a:a + _ROWS].tolist())

    def __repr__(self) -> str:
        return f"CodedStrings({len(self)} rows, {len(self.categories)} categories)"

    def tolist(self) -> list[str]:
        return list(self)

    def take(self, sel) -> CodedStrings:
        """Rows `sel` (indices or a bool mask)."""
        return CodedStrings(self.codes[sel], list(self.categories))

    def mask(self, value: str) -> np.ndarray:
        """(N,) bool: rows equal to `value`."""
        hits = [k for k, c in enumerate(self.categories) if c == value]
        if not hits:
            return np.zeros(len(self.codes), dtype=bool)
        if len(hits) == 1:
            return self.codes == hits[0]
        return np.isin(self.codes, hits)

    def counts(self) -> dict[str, int]:
        """{value: number of rows} over the values that occur."""
        out: dict[str, int] = {}
        for k, n in enumerate(np.bincount(self.codes, minlength=len(self.categories)).tolist()):
            if n:
                out[self.categories[k]] = out.get(self.categories[k], 0) + n
        return out

    def unique(self) -> set[str]:
        """The distinct values that occur."""
        return set(self.counts())

    def normalized(self, mapping: dict[str, str]) -> CodedStrings:
        """A copy with values renamed by `mapping` (others kept) and equal values merged."""
        lookup = _Lookup()
        remap = np.fromiter((lookup[mapping.get(c, c)] for c in self.categories), np.int32,
                            len(self.categories))
        codes = remap[self.codes] if len(self.codes) else self.codes.copy()
        return CodedStrings(codes, list(lookup))

    def nbytes(self) -> int:
        return self.codes.nbytes


class PackedStrings(Sequence):
    """A column of (mostly distinct) strings, the gml:ids, behaving like a read-only list of
    str: all UTF-8 bytes in one uint8 array and (N+1,) int64 offsets. A 250k-row column of
    20-character ids costs ~7 MB here instead of ~22 MB as str objects in a list."""

    __slots__ = ("data", "offsets")

    def __init__(self, data, offsets):
        self.data = np.asarray(data, dtype=np.uint8)
        self.offsets = np.asarray(offsets, dtype=np.int64)

    @staticmethod
    def _encode(values: list[str]) -> tuple[bytes, np.ndarray]:
        joined = "".join(values).encode("utf-8")
        n = len(values)
        lengths = np.fromiter(map(len, values), np.int64, n)
        if len(joined) != int(lengths.sum()):  # not all ASCII: byte lengths per string
            lengths = np.fromiter((len(v.encode("utf-8")) for v in values), np.int64, n)
        return joined, lengths

    @classmethod
    def from_values(cls, values) -> PackedStrings:
        if isinstance(values, PackedStrings):
            return values
        values = list(values)
        joined, lengths = cls._encode(values)
        return cls(np.frombuffer(joined, np.uint8).copy(), _ptr(lengths))

    @classmethod
    def concatenate(cls, columns: list) -> PackedStrings:
        columns = [cls.from_values(c) for c in columns]
        if len(columns) == 1:
            return columns[0]
        lengths = [np.diff(c.offsets) for c in columns]
        return cls(
            np.concatenate([c.data for c in columns]) if columns else np.zeros(0, np.uint8),
            _ptr(np.concatenate(lengths) if lengths else np.zeros(0, np.int64)),
        )

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        i = row_index(i, len(self), "string")
        return self.data[self.offsets[i]:self.offsets[i + 1]].tobytes().decode("utf-8")

    def __iter__(self):
        o = self.offsets
        for a in range(0, len(self), _ROWS):
            b = min(len(self), a + _ROWS)
            buf = self.data[o[a]:o[b]].tobytes()
            offs = (o[a:b + 1] - o[a]).tolist()
            for k in range(b - a):
                yield buf[offs[k]:offs[k + 1]].decode("utf-8")

    def __repr__(self) -> str:
        return f"PackedStrings({len(self)} rows, {len(self.data)} bytes)"

    def tolist(self) -> list[str]:
        return list(self)

    def take(self, sel) -> PackedStrings:
        """Rows `sel` (indices or a bool mask), in that order."""
        sel = np.asarray(sel)
        lengths = np.diff(self.offsets)
        if sel.dtype == bool:
            ptr = _ptr(lengths[sel])
            data = np.empty(int(ptr[-1]), np.uint8)
            o, k = self.offsets, 0
            for a in range(0, len(self), _ROWS):  # byte masks of a chunk of rows at a time
                b = min(len(self), a + _ROWS)
                piece = self.data[o[a]:o[b]][np.repeat(sel[a:b], lengths[a:b])]
                data[k:k + len(piece)] = piece
                k += len(piece)
            return PackedStrings(data, ptr)
        sel = sel.astype(np.int64, copy=False)
        if len(sel) and np.all(sel[1:] > sel[:-1]):  # increasing: a byte mask, no index array
            mask = np.zeros(len(self), dtype=bool)
            mask[sel] = True
            return self.take(mask)
        new_len = lengths[sel]
        ptr = _ptr(new_len)
        data = np.empty(int(ptr[-1]), np.uint8)
        for a in range(0, len(sel), _ROWS // 4):  # bounded index temporaries
            b = min(len(sel), a + _ROWS // 4)
            data[ptr[a]:ptr[b]] = self.data[_segment_gather(self.offsets[sel[a:b]], new_len[a:b])]
        return PackedStrings(data, ptr)

    def compress_owned(self, keep: np.ndarray) -> PackedStrings:
        """The rows where `keep` (bool) is True, written over this column's own arrays (for
        an owner about to drop this column: it is unusable afterwards)."""
        data, offsets = self.data, self.offsets
        if not (data.flags.owndata and offsets.flags.owndata and data.flags.writeable
                and offsets.flags.writeable):
            return self.take(keep)
        w = 0
        for a in range(0, len(self), _ROWS):  # bytes: w never passes the read position
            b = min(len(self), a + _ROWS)
            lengths = offsets[a + 1:b + 1] - offsets[a:b]
            piece = data[offsets[a]:offsets[b]][np.repeat(keep[a:b], lengths)]
            data[w:w + len(piece)] = piece
            w += len(piece)
        lengths = np.diff(offsets)[keep]
        offsets[0] = 0
        np.cumsum(lengths, out=offsets[1:len(lengths) + 1])
        del lengths
        offsets.resize(int(np.count_nonzero(keep)) + 1, refcheck=False)
        data.resize(w, refcheck=False)
        self.data = self.offsets = np.zeros(0, np.uint8)
        return PackedStrings(data, offsets)

    def replaced(self, values: dict[int, str]) -> PackedStrings:
        """A copy with the rows in `values` set to new strings."""
        if not values:
            return self
        rows = self.tolist()
        for i, v in values.items():
            rows[i] = v
        return PackedStrings.from_values(rows)

    def repeated_candidates(self) -> np.ndarray:
        """(N,) bool: non-empty strings whose 64-bit hash another non-empty row shares (every
        string that occurs twice is among them; a hash collision adds a false candidate)."""
        n = len(self)
        lengths = np.diff(self.offsets)
        out = np.zeros(n, dtype=bool)
        nonempty = np.flatnonzero(lengths > 0)
        if len(nonempty) < 2:
            return out
        # Python's bytes hash (salted per process: only which rows share one matters), one
        # short-lived bytes object at a time, in chunks of rows
        h = np.empty(len(nonempty), dtype=np.int64)
        for a in range(0, len(nonempty), _ROWS):
            sel = nonempty[a:a + _ROWS]
            o0 = int(self.offsets[sel[0]])
            buf = self.data[o0:int(self.offsets[sel[-1] + 1])].tobytes()
            starts = (self.offsets[sel] - o0).tolist()
            ends = (self.offsets[sel + 1] - o0).tolist()
            pieces = map(buf.__getitem__, map(slice, starts, ends))
            h[a:a + len(sel)] = np.fromiter(map(hash, pieces), np.int64, len(sel))
        order = np.argsort(h)
        hs = h[order]
        same = hs[1:] == hs[:-1]
        hit = np.zeros(len(h), dtype=bool)
        hit[1:] |= same
        hit[:-1] |= same
        out[nonempty[order[hit]]] = True
        return out

    def nbytes(self) -> int:
        return self.data.nbytes + self.offsets.nbytes


def _mix64(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 (wrapping)."""
    x = x.astype(np.uint64, copy=True)
    with np.errstate(over="ignore"):
        x += np.uint64(0x9E3779B97F4A7C15)
        x ^= x >> np.uint64(30)
        x *= np.uint64(0xBF58476D1CE4E5B9)
        x ^= x >> np.uint64(27)
        x *= np.uint64(0x94D049BB133111EB)
        x ^= x >> np.uint64(31)
    return x


_NO_POINTS = np.zeros((0, 3))


class RawPolygonTable(Sequence):
    """All polygons of a model in flat arrays, behaving like a read-only list of `RawPolygon`.

    A city of 2.5e5 polygons held as RawPolygon objects costs ~500 bytes per polygon beyond its
    coordinates; here it is one float64 coordinate array (kept as a list of chunks until someone
    needs it whole, so readers and tile merging never copy it), ring lengths, rings per polygon
    and per-polygon string columns (codes, packed UTF-8 ids) and arrays.

    coords: (P, 3) float64, all rings one after the other: per polygon its exterior, then its
        holes (rings without the repeated closing point);
    ring_len: (R,) int64 points per ring; poly_nring: (N,) int64 rings per polygon (>= 1);
    semantic, building_id, part_id: CodedStrings (N rows: int32 codes + the distinct strings);
    gml_id: PackedStrings (N rows: UTF-8 bytes + offsets); both read like lists of str (lists
    given to the constructor are converted); lod: (N,) int16; from_solid: (N,) bool.

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
        self.semantic = CodedStrings.from_values(semantic)
        self.building_id = CodedStrings.from_values(building_id)
        self.part_id = CodedStrings.from_values(part_id)
        self.gml_id = PackedStrings.from_values(gml_id)
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
        coded = lambda name: CodedStrings.concatenate(  # noqa: E731
            [getattr(t, name) for t in tables])
        arr = lambda name, dt: (np.concatenate([getattr(t, name) for t in tables])  # noqa: E731
                                if tables else np.zeros(0, dt))
        return cls(
            [c for t in tables for c in t._chunks], arr("ring_len", np.int64),
            arr("poly_nring", np.int64), coded("semantic"), coded("building_id"), coded("part_id"),
            PackedStrings.concatenate([t.gml_id for t in tables]), arr("lod", np.int16),
            arr("from_solid", bool),
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
        only for a caller that owns the table (citymodel.store.build_store(release_raw=True))."""
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
        polygon order), then those of all holes (the ring order of citymodel.store.build_store).
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

    def drop_cached_pointers(self) -> None:
        """Free the cached ring_ptr / poly_ptr (recomputed on the next use)."""
        self._ring_ptr = None
        self._poly_ptr = None

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
        i = row_index(i, len(self), "polygon")
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
        return RawPolygonTable(
            self.coords[pts], rl, nr, self.semantic.take(sel), self.building_id.take(sel),
            self.part_id.take(sel), self.gml_id.take(sel), self.lod[sel], self.from_solid[sel],
        )

    def nbytes(self) -> int:
        return (sum(c.nbytes for c in self._chunks) + self.ring_len.nbytes + self.poly_nring.nbytes
                + self.lod.nbytes + self.from_solid.nbytes + self.semantic.nbytes()
                + self.building_id.nbytes() + self.part_id.nbytes() + self.gml_id.nbytes())


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
        self._pending_gml_single: list[str] = []
        # string columns: codes per distinct string; gml ids packed in blocks of bytes
        self._lookups = (_Lookup(), _Lookup(), _Lookup())  # semantic, building_id, part_id
        self._codes: tuple[list, list, list] = ([], [], [])  # int32 arrays per block
        self._pending_str_codes: tuple[list, list, list] = ([], [], [])  # ints, not yet packed
        self._pending_codes: tuple[list, list, list] = ([], [], [])
        self._gml_data: list[np.ndarray] = []
        self._gml_len: list[np.ndarray] = []
        self._pending_gml: list[str] = []
        self._n = 0

    def __len__(self) -> int:
        return self._n + len(self._pending_nr)

    def _push_strings(self, semantic, building_id, part_id, gml_id) -> None:
        """Append the string columns of n polygons (lists of str); codes and ids are kept as
        plain lists for a few thousand rows, then packed into arrays."""
        for lookup, codes, values in zip(self._lookups, self._pending_str_codes,
                                         (semantic, building_id, part_id)):
            codes.extend(map(lookup.__getitem__, values))
        self._pending_gml.extend(gml_id)
        self._n += len(gml_id)
        if len(self._pending_gml) >= 8192:
            self._flush_gml()

    def _flush_gml(self) -> None:
        if self._pending_gml:
            for codes, pending in zip(self._codes, self._pending_str_codes):
                codes.append(np.array(pending, dtype=np.int32))
                pending.clear()
            joined, lengths = PackedStrings._encode(self._pending_gml)
            self._gml_data.append(np.frombuffer(joined, np.uint8))
            self._gml_len.append(lengths)
            self._pending_gml = []

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
            self._push_strings(*self._pending_codes, self._pending_gml_single)
            self._pending_codes = ([], [], [])
            self._pending_gml_single = []
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
        for values, v in zip(self._pending_codes, (semantic, building_id, part_id)):
            values.append(v)
        self._pending_gml_single.append(gml_id)
        row = self._n + len(self._pending_nr) - 1
        if len(self._pending_nr) >= 4096:
            self._flush_pending()
        return row

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
        self._push_strings(semantic, building_id, part_id, gml_id)

    def finish(self) -> RawPolygonTable:
        self._flush_pending()
        self._flush_blocks()
        self._flush_gml()
        cat = lambda parts, dt: np.concatenate(parts) if parts else np.zeros(0, dt)  # noqa: E731
        coded = [CodedStrings(cat(codes, np.int32), list(lookup))
                 for codes, lookup in zip(self._codes, self._lookups)]
        table = RawPolygonTable(
            self._chunks, cat(self._ring_len, np.int64), cat(self._poly_nring, np.int64),
            *coded,
            PackedStrings(cat(self._gml_data, np.uint8), _ptr(cat(self._gml_len, np.int64))),
            cat(self._lod, np.int16), cat(self._from_solid, bool),
        )
        self.__init__(self.chunk_points)
        return table


#: Largest easting or northing (m) a projected CRS can hold: UTM northings stay below 1e7, false
#: eastings and national grids far below 1e8. Larger values are damaged numbers, not places.
MAX_PROJECTED_COORDINATE = 1e8
#: Largest height (m) above or below any vertical datum a building surface can have.
MAX_HEIGHT = 1e5


def coordinate_problem(xyz, *, geographic: bool = False, lat_first: bool = True
                       ) -> tuple[int, str] | None:
    """The first point of (N, 3) coordinates that no CRS can hold and why, or None.

    A value that is not finite, an easting/northing beyond `MAX_PROJECTED_COORDINATE`, a height
    beyond `MAX_HEIGHT` or, for `geographic` coordinates (latitude first when `lat_first`), a
    latitude outside [-90, 90] or a longitude outside [-180, 360] is a damaged number."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if not len(xyz):
        return None
    with np.errstate(invalid="ignore"):
        absolute = np.abs(xyz)
        if geographic:
            lat, lon = (absolute[:, 0], xyz[:, 1]) if lat_first else (absolute[:, 1], xyz[:, 0])
            horizontal_bad = (lat > 90.0) | (lon < -180.0) | (lon > 360.0)
        else:
            horizontal_bad = (absolute[:, 0] > MAX_PROJECTED_COORDINATE) | \
                (absolute[:, 1] > MAX_PROJECTED_COORDINATE)
        bad = ~np.isfinite(xyz).all(axis=1) | horizontal_bad | (absolute[:, 2] > MAX_HEIGHT)
    if not bad.any():
        return None
    i = int(np.argmax(bad))
    p = xyz[i]
    text = "(" + ", ".join(f"{v:.10g}" for v in p) + ")"
    if not np.isfinite(p).all():
        why = "is not finite"
    elif geographic and horizontal_bad[i]:
        why = ("is not a latitude/longitude (latitude outside [-90, 90] or longitude outside "
               "[-180, 360])")
    elif horizontal_bad[i]:
        why = (f"lies beyond {MAX_PROJECTED_COORDINATE:.0e} m from the CRS origin, outside any "
               "projected CRS")
    else:
        why = f"has a height beyond +-{MAX_HEIGHT:.0e} m"
    return i, f"coordinate {text} {why}"
