"""A tile index of city model files: each file's bounding box and CRS, so that a block reads
only the tiles near it instead of a whole city.

One streaming pass per file: CityGML through `lxml.etree.iterparse` over the coordinate
elements (`posList`, `pos`, `coordinates`; `srsDimension` from the element, its `count` or an
ancestor), one city object in memory at a time; CityJSON / CityJSONSeq from the vertex array
(with `transform`). The box covers every coordinate in the file (terrain intersections and
other city objects too), so it contains every building the readers keep. The CRS is the
first `srsName` (CityGML) or `metadata.referenceSystem` (CityJSON), resolved when the index is
queried; files that name none take the CRS the user gives (`assumed`).

The index is cached in `.colmap_citymodel_tiles.cache` (JSON) next to the data, one entry per file
name, and an entry is re-read when the file's size or modification time changed. Where the
data directory is not writable, the cache goes to `cache_dir` (a batch uses its output
directory). Boxes are stored in the file's own coordinates (latitude first for PLATEAU's
EPSG:6697, as the file writes them); `TileIndex.select` reprojects a tile's box (a 5 x 5 grid
over it) when the query's CRS differs.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import stat
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..errors import CityModelError, CRSError
from . import crs as crs_mod
from .raw_model import CRSInfo
from .archives import open_model
from .read import _kind, city_model_files

logger = logging.getLogger(__name__)

#: The cache file (JSON; named so that no reader takes it for a tile of the directory).
INDEX_NAME = ".colmap_citymodel_tiles.cache"
#: Bump when the scan changes what it records (old caches are then re-read).
INDEX_VERSION = 1
_FLUSH_TOKENS = 300_000  # coordinate tokens buffered before one numpy conversion


@dataclass
class TileInfo:
    """What the index knows of one city model file."""

    path: Path
    size: int
    mtime_ns: int
    kind: str  # "citygml" | "cityjson"
    srs_name: str | None  # the first srsName / referenceSystem in the file; None: it names none
    bbox: list[float] | None  # [x_min, y_min, x_max, y_max] in the file's CRS and axis order
    error: str | None = None  # why the file could not be scanned (it is then never selected)

    def entry(self) -> dict:
        d = asdict(self)
        del d["path"]
        return d

    @classmethod
    def from_entry(cls, path: Path, entry: dict) -> TileInfo:
        return cls(path=path, **{k: entry.get(k) for k in
                                 ("size", "mtime_ns", "kind", "srs_name", "bbox", "error")})


# -- scanning one file ---------------------------------------------------------------------------

class _Box:
    """Running xy bounds of coordinate tokens, converted in large batches."""

    def __init__(self):
        self.lo = np.full(2, np.inf)
        self.hi = np.full(2, -np.inf)
        self.tokens: dict[int, list[str]] = {2: [], 3: []}

    def add(self, tokens: list[str], dim: int) -> None:
        if len(tokens) % dim:
            dim = 5 - dim  # the stated dimension does not divide the count: the other one
            if len(tokens) % dim:
                return
        buffer = self.tokens[dim]
        buffer.extend(tokens)
        if len(buffer) > _FLUSH_TOKENS:
            self.flush()

    def add_points(self, xy: np.ndarray) -> None:
        if len(xy):
            self.lo = np.minimum(self.lo, xy[:, :2].min(0))
            self.hi = np.maximum(self.hi, xy[:, :2].max(0))

    def flush(self) -> None:
        for dim, buffer in self.tokens.items():
            if buffer:
                self.add_points(np.array(buffer, dtype=np.float64).reshape(-1, dim))
                buffer.clear()

    def result(self) -> list[float] | None:
        self.flush()
        if not np.all(np.isfinite(self.lo)):
            return None
        return [float(self.lo[0]), float(self.lo[1]), float(self.hi[0]), float(self.hi[1])]


def _context(el) -> tuple[str | None, str | None]:
    """(srsName, srsDimension) in force at a coordinate element: its own or its nearest
    ancestor's."""
    srs, dim = el.get("srsName"), el.get("srsDimension")
    for anc in el.iterancestors():
        if srs is not None and dim is not None:
            break
        if srs is None:
            srs = anc.get("srsName")
        if dim is None:
            dim = anc.get("srsDimension")
    return srs, dim


def _dimension(el, stated: str | None) -> int:
    """The dimension of a posList: stated, else from its point count; GML's default 3."""
    if not stated:
        count = el.get("count")
        if count and count.isdigit() and int(count) > 0:
            n = len(el.text.split())
            if n % int(count) == 0 and n // int(count) in (2, 3):
                return n // int(count)
        return 3
    return 2 if stated.strip() == "2" else 3


def _scan_citygml(path: Path) -> tuple[str | None, list[float] | None]:
    """The first srsName and the xy box of the coordinates in that CRS (geometries in another
    CRS, such as an address's EPSG:4326 point, are not building geometry and are left out)."""
    from lxml import etree

    with open_model(path) as source:
        return _scan_citygml_stream(source, etree)


def _scan_citygml_stream(source, etree) -> tuple[str | None, list[float] | None]:
    box = _Box()
    srs_name = None
    local: dict[str, str] = {}
    same: dict[str, bool] = {}  # srsName -> names the file's CRS
    for _event, el in etree.iterparse(source, events=("end",), huge_tree=True,
                                      remove_comments=True, remove_pis=True):
        tag = el.tag
        name = local.get(tag)
        if name is None:
            name = local[tag] = tag.rpartition("}")[2]
        if name in ("posList", "pos", "coordinates") and el.text:
            srs, dim = _context(el)
            if srs_name is None:
                srs_name = srs
            if srs is not None and srs not in same:
                same[srs] = _same_srs(srs, srs_name)
            if srs is None or same[srs]:
                if name == "posList":
                    box.add(el.text.split(), _dimension(el, dim))
                elif name == "pos":
                    tokens = el.text.split()
                    box.add(tokens, 3 if len(tokens) >= 3 else 2)
                else:
                    _add_coordinates(box, el)
        elif srs_name is None and name == "Envelope":
            srs_name = el.get("srsName")
        parent = el.getparent()
        if parent is not None and parent.getparent() is None:
            # a top-level member is done: free it and everything before it
            el.clear()
            while el.getprevious() is not None:
                del parent[0]
    return srs_name, box.result()


def _same_srs(a: str, b: str) -> bool:
    """Whether two srsNames name one CRS (equal strings, or resolved and same_crs())."""
    if a == b:
        return True
    try:
        return crs_mod.same_crs(crs_mod.resolve_crs(a), crs_mod.resolve_crs(b))
    except CRSError:
        return False


def _add_coordinates(box: _Box, el) -> None:
    """GML 2 `coordinates`: tuples separated by `ts`, values by `cs`."""
    cs, ts, decimal = el.get("cs", ","), el.get("ts", " "), el.get("decimal", ".")
    text = el.text.replace(decimal, ".") if decimal != "." else el.text
    for point in (text.split() if ts.isspace() else text.split(ts)):
        values = point.replace(cs, " ").split()
        if len(values) in (2, 3):
            box.add(values, len(values))


def _scan_cityjson(path: Path) -> tuple[str | None, list[float] | None]:
    from .read_cityjson import _load

    doc, features = _load(path)
    meta = doc.get("metadata") or {}
    srs_name = meta.get("referenceSystem") or meta.get("referencesystem")
    transform = doc.get("transform") or {}
    scale = np.asarray(transform.get("scale", [1.0, 1.0, 1.0]), np.float64)[:2]
    translate = np.asarray(transform.get("translate", [0.0, 0.0, 0.0]), np.float64)[:2]
    box = _Box()
    for d in (features or [doc]):
        vertices = np.asarray(d.get("vertices") or np.zeros((0, 3)), np.float64).reshape(-1, 3)
        box.add_points(vertices[:, :2] * scale + translate)
    return (str(srs_name) if srs_name else None), box.result()


def scan_tile(path: str | Path) -> TileInfo:
    """Read one file's bounding box and CRS name (never raises for a bad file: `error` says)."""
    path = Path(path)
    st = path.stat()
    kind = "citygml"
    try:
        kind = _kind(path)
        srs_name, bbox = (_scan_citygml if kind == "citygml" else _scan_cityjson)(path)
        error = None if bbox is not None else "no coordinates in the file"
    except CityModelError as err:
        srs_name, bbox, error = None, None, err.message
    except Exception as err:  # lxml's syntax errors, bad numbers, unreadable files
        srs_name, bbox, error = None, None, f"{type(err).__name__}: {err}"
    return TileInfo(path=path, size=st.st_size, mtime_ns=st.st_mtime_ns, kind=kind,
                    srs_name=srs_name, bbox=bbox, error=error)


# -- the cache ------------------------------------------------------------------------------------

def _cache_files(directory: Path, cache_dir: Path | None) -> list[Path]:
    """Where the cache of `directory` may live: next to the data, else under `cache_dir`."""
    places = [directory / INDEX_NAME]
    if cache_dir is not None:
        key = hashlib.sha1(str(directory.resolve()).encode()).hexdigest()[:12]
        places.append(Path(cache_dir) / f"tile_index-{directory.name}-{key}.json")
    return places


def _read_cache(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(doc, dict) or doc.get("version") != INDEX_VERSION:
        return {}
    tiles = doc.get("tiles")
    return tiles if isinstance(tiles, dict) else {}


def _write_json_atomic(path: Path, doc: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(doc, f, indent=1)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _writable(directory: Path) -> bool:
    """Whether to write into `directory`: the process may, and its mode bits allow it (a
    directory marked read-only stays untouched even for root, who could write anyway)."""
    try:
        mode = directory.stat().st_mode
    except OSError:
        return False
    return os.access(directory, os.W_OK) and bool(mode & (stat.S_IWUSR | stat.S_IWGRP
                                                          | stat.S_IWOTH))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _write_cache(directory: Path, entries: dict, cache_dir: Path | None) -> Path | None:
    doc = {"version": INDEX_VERSION, "directory": str(directory.resolve()), "tiles": entries}
    for place in _cache_files(directory, cache_dir):
        if place.parent == directory and not _writable(directory):
            continue
        try:
            _write_json_atomic(place, doc)
            return place
        except OSError:
            continue
    return None


# -- the index ------------------------------------------------------------------------------------

@dataclass
class TileIndex:
    """The tiles of a city model and where they lie."""

    tiles: list[TileInfo]
    scanned: int = 0  # files read by this build (the others came from the cache)

    @property
    def errors(self) -> list[TileInfo]:
        return [t for t in self.tiles if t.error]

    def tile_crs(self, tile: TileInfo, assumed: CRSInfo | None = None) -> CRSInfo | None:
        """The tile's CRS (its own, else `assumed`); None when neither is known or resolvable."""
        if tile.srs_name:
            try:
                return crs_mod.resolve_crs(tile.srs_name, path=tile.path)
            except CRSError:
                return None
        return assumed

    def crs_groups(self, assumed: CRSInfo | None = None) -> list[CRSInfo]:
        """The distinct CRSs of the usable tiles (same_crs() ones once)."""
        groups: list[CRSInfo] = []
        for tile in self.tiles:
            crs = self.tile_crs(tile, assumed) if not tile.error else None
            if crs is None:
                continue
            for k, g in enumerate(groups):
                if crs_mod.same_crs(g, crs):
                    groups[k] = crs_mod.more_complete(g, crs)
                    break
            else:
                groups.append(crs)
        return groups

    def box_in(self, tile: TileInfo, crs: CRSInfo, assumed: CRSInfo | None = None
               ) -> np.ndarray | None:
        """The tile's xy box [[x_min, y_min], [x_max, y_max]] in `crs` (projected), or None when
        it cannot be placed there."""
        own = self.tile_crs(tile, assumed)
        if tile.error or tile.bbox is None or own is None:
            return None
        box = np.array(tile.bbox, dtype=np.float64).reshape(2, 2)
        if own.is_projected and crs_mod.same_crs(own, crs):
            return box
        u = np.linspace(0.0, 1.0, 5)
        grid = np.stack(np.meshgrid(u, u), -1).reshape(-1, 2)
        points = box[0] + grid * (box[1] - box[0])
        try:
            xy = crs_mod.reproject_points(points, own, crs)
        except CRSError:
            return None
        return np.array([xy.min(0), xy.max(0)])

    def select(self, box_xy, crs: CRSInfo, *, assumed: CRSInfo | None = None
               ) -> list[TileInfo]:
        """The tiles whose box overlaps `box_xy` ([[x_min, y_min], [x_max, y_max]] in `crs`,
        a projected CRS), in index order."""
        query = np.asarray(box_xy, dtype=np.float64).reshape(2, -1)[:, :2]
        chosen = []
        for tile in self.tiles:
            box = self.box_in(tile, crs, assumed)
            if box is not None and np.all(box[0] <= query[1]) and np.all(box[1] >= query[0]):
                chosen.append(tile)
        return chosen

    def todict(self) -> dict:
        return {"version": INDEX_VERSION,
                "tiles": [{"path": str(t.path), **t.entry()} for t in self.tiles]}


def build_tile_index(paths, *, cache_dir: str | Path | None = None) -> TileIndex:
    """Index the city model files named by `paths` (files and directories of tiles, as
    `read_city_model` takes them), reading only files that are new or changed since the
    cache was written (see the module docstring for where the cache lives)."""
    files = city_model_files(paths)
    cache_dir = Path(cache_dir) if cache_dir is not None else None
    by_dir: dict[Path, list[Path]] = {}
    for f in files:
        by_dir.setdefault(f.parent, []).append(f)
    known: dict[Path, TileInfo] = {}
    scanned = 0
    for directory, members in by_dir.items():
        entries: dict = {}
        for place in _cache_files(directory, cache_dir):
            entries = _read_cache(place)
            if entries:
                break
        changed = False
        for f in members:
            st = f.stat()
            entry = entries.get(f.name)
            if entry is not None and entry.get("size") == st.st_size \
                    and entry.get("mtime_ns") == st.st_mtime_ns:
                known[f] = TileInfo.from_entry(f, entry)
                continue
            tile = scan_tile(f)
            scanned += 1
            known[f] = tile
            entries[f.name] = tile.entry()
            changed = True
        if changed:
            # entries of files that are gone are dropped; those of unlisted siblings kept
            entries = {name: e for name, e in entries.items() if (directory / name).is_file()}
            if _write_cache(directory, entries, cache_dir) is None:
                logger.debug("tile index of %s not cached (no writable place)", directory)
    index = TileIndex([known[f] for f in files], scanned=scanned)
    logger.info("tile index: %d file(s), %d read, %d from the cache%s", len(files), scanned,
                len(files) - scanned,
                f"; {len(index.errors)} unreadable" if index.errors else "")
    return index


def files_near(paths, box_xy, crs: CRSInfo, *, assumed: CRSInfo | None = None) -> list[Path]:
    """The city model files of `paths` a block inside `box_xy` (in `crs`) needs: the tiles
    that overlap it, found through the tile index, plus every file the index cannot place
    (unreadable, no CRS known), so that the reader reports those as it would have. One file,
    or no tile overlapping, gives the files as they are (the reader then says what is wrong)."""
    files = city_model_files(paths)
    if len(files) < 2:
        return files
    index = build_tile_index(files)
    near = [t.path for t in index.select(box_xy, crs, assumed=assumed)]
    if not near:
        return files
    unplaced = [t.path for t in index.tiles if t.error or (
        t.bbox is not None and index.tile_crs(t, assumed) is None)]
    chosen = set(near) | set(unplaced)
    logger.info("%d of %d city model file(s) lie near the GNSS positions", len(near), len(files))
    return [f for f in files if f in chosen]
