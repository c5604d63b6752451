"""Coordinate reference systems of city models: parse the many ways a CityGML `srsName` names a CRS,
split it into horizontal and vertical EPSG codes with pyproj, and reproject coordinates.

Accepted spellings (case-insensitive where it makes sense):
- `EPSG:25832`, `EPSG::25832`, `EPSG:25832+7837` (horizontal + vertical), a bare `25832`
- OGC URNs `urn:ogc:def:crs:EPSG::25832`, versioned `urn:ogc:def:crs:EPSG:6.12:25833`,
  `urn:x-ogc:def:crs:EPSG:25832`, compound `urn:ogc:def:crs,crs:EPSG:6.12:25833,crs:EPSG:6.12:5783`
- OGC URLs `http://www.opengis.net/def/crs/EPSG/0/25832` and compound
  `http://www.opengis.net/def/crs-compound?1=...EPSG/0/25832&2=...EPSG/0/7837`
- German AdV URNs `urn:adv:crs:ETRS89_UTM32*DE_DHHN2016_NH[*GCG2016]` (see `ADV_CRS` below)
- anything else pyproj understands (WKT, `OGC:CRS84`, ...) as a last resort.

Axis order: CityGML writes coordinates in the axis order of the CRS definition, but producers of
projected data write easting first even for CRSs that EPSG defines northing-first (German
Gauss-Krueger EPSG:31468, Japanese EPSG:6677). We therefore always treat projected coordinates as
(easting, northing, height). Geographic coordinates follow EPSG (latitude, longitude, height;
PLATEAU EPSG:6697 files do this); `reproject_points` swaps them for pyproj's always_xy mode, and
detects files that nevertheless write longitude first (a first value outside [-90, 90]).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import pyproj
from pyproj.crs import CompoundCRS

from ..errors import CRSError
from .raw_model import CRSInfo

# AdV (German surveying authorities) CRS names used in `urn:adv:crs:<horizontal>*<vertical>[*<geoid>]`
# (AdV "CRS-Registry", GeoInfoDok). Horizontal names map to EPSG projected/geographic CRSs, vertical
# names to EPSG height systems. "NH" = normal heights, "NOH" = normal-orthometric heights. The third
# part (quasigeoid model, e.g. GCG2016) does not change the CRS and is ignored.
ADV_CRS: dict[str, int] = {
    # horizontal
    "ETRS89_UTM31": 25831,
    "ETRS89_UTM32": 25832,
    "ETRS89_UTM33": 25833,
    "ETRS89_LAT-LON": 4258,
    "ETRS89_LAT-LON-H": 4937,
    "ETRS89_X_Y_Z": 4936,
    "DE_DHDN_LAT-LON": 4314,
    "DE_DHDN_3GK2": 31466,
    "DE_DHDN_3GK3": 31467,
    "DE_DHDN_3GK4": 31468,
    "DE_DHDN_3GK5": 31469,
    "DE_42/83_3GK3": 2397,
    "DE_42/83_3GK4": 2398,
    "DE_42/83_3GK5": 2399,
    # vertical
    "DE_DHHN2016_NH": 7837,
    "DE_DHHN92_NH": 5783,
    "DE_DHHN85_NOH": 5784,
    "DE_SNN76_NH": 5785,
}

_EPSG_PLUS = re.compile(r"^(?:EPSG:+)?(\d+)(?:\s*\+\s*(?:EPSG:+)?(\d+))?$", re.IGNORECASE)
# `EPSG:<optional version>:<code>` inside URNs, and `EPSG/<version>/<code>` inside URLs
_URN_EPSG = re.compile(r"EPSG:[\d.]*:(\d+)\b|EPSG:(\d+)\b", re.IGNORECASE)
_URL_EPSG = re.compile(r"/EPSG/[\d.]+/(\d+)\b", re.IGNORECASE)


def _fail(message: str, path) -> CRSError:
    return CRSError(message, path)


def _epsg_codes(text: str, path) -> list[int] | None:
    """EPSG codes named by `text` (1 or 2: horizontal[, vertical]); None if it is no EPSG spelling."""
    s = text.strip()
    if s.lower().startswith("urn:adv:crs:"):
        names = [p.strip().upper() for p in s[len("urn:adv:crs:"):].split("*") if p.strip()]
        codes = []
        for k, name in enumerate(names[:2]):
            if name not in ADV_CRS:
                if k == 0:
                    raise _fail(
                        f"unknown AdV CRS name {name!r} in srsName {text!r} "
                        f"(known: {', '.join(sorted(ADV_CRS))}); pass --crs EPSG:N", path
                    )
                continue  # unknown height system: keep the horizontal part
            codes.append(ADV_CRS[name])
        return codes
    m = _EPSG_PLUS.match(s)
    if m:
        return [int(c) for c in m.groups() if c]
    low = s.lower()
    if low.startswith(("urn:ogc:def:crs", "urn:x-ogc:def:crs", "urn:epsg")):
        codes = [int(a or b) for a, b in _URN_EPSG.findall(s)]
        return codes or None
    if low.startswith(("http://", "https://")) and "opengis.net/def/crs" in low:
        codes = [int(c) for c in _URL_EPSG.findall(s)]
        return codes or None
    return None


@lru_cache(maxsize=256)
def _crs_from_epsg(code: int) -> pyproj.CRS:
    return pyproj.CRS.from_epsg(code)


def _split(crs: pyproj.CRS) -> tuple[pyproj.CRS | None, pyproj.CRS | None]:
    """(horizontal, vertical) parts of a pyproj CRS."""
    if crs.is_compound:
        horizontal = vertical = None
        for sub in crs.sub_crs_list:
            if sub.is_vertical:
                vertical = sub
            elif horizontal is None:
                horizontal = sub
        return horizontal, vertical
    if crs.is_vertical:
        return None, crs
    return crs, None


def _info(srs_name: str, horizontal: pyproj.CRS, vertical: pyproj.CRS | None) -> CRSInfo:
    h_epsg = horizontal.to_epsg(min_confidence=90)
    v_epsg = vertical.to_epsg(min_confidence=90) if vertical is not None else None
    if vertical is not None:
        full = CompoundCRS(name=f"{horizontal.name} + {vertical.name}", components=[horizontal, vertical])
    else:
        full = horizontal
    units = horizontal.axis_info[0].unit_name if horizontal.axis_info else "unknown"
    return CRSInfo(
        srs_name=srs_name,
        horizontal_epsg=h_epsg,
        vertical_epsg=v_epsg,
        wkt=full.to_wkt(),
        is_projected=bool(horizontal.is_projected),
        units=units,
    )


@lru_cache(maxsize=256)
def _resolve_cached(srs_name: str) -> CRSInfo | str:
    """CRSInfo, or an error message string (cached either way; the path is added by the caller)."""
    try:
        codes = _epsg_codes(srs_name, None)
    except CRSError as error:
        return error.message
    try:
        if codes:
            parts = [_crs_from_epsg(c) for c in codes]
        else:
            parts = [pyproj.CRS.from_user_input(srs_name)]
    except pyproj.exceptions.CRSError:
        if codes:
            return f"unknown EPSG code in srsName {srs_name!r}; pass --crs EPSG:N"
        return f"cannot interpret srsName {srs_name!r} as a coordinate reference system; pass --crs EPSG:N"
    horizontal = vertical = None
    for part in parts:
        h, v = _split(part)
        if h is not None:
            if horizontal is not None:
                return f"srsName {srs_name!r} names two horizontal CRSs"
            horizontal = h
        if v is not None:
            if vertical is not None:
                return f"srsName {srs_name!r} names two vertical CRSs"
            vertical = v
    if horizontal is None:
        return f"srsName {srs_name!r} names only a vertical CRS"
    if horizontal.is_geocentric:
        return f"srsName {srs_name!r} is a geocentric (X, Y, Z) CRS, not usable for a city model"
    return _info(srs_name, horizontal, vertical)


def resolve_crs(srs_name: str, *, path: str | Path | None = None) -> CRSInfo:
    """Resolve an `srsName` (EPSG code, OGC URN/URL, compound/versioned URN, AdV URN) to a CRSInfo.

    Raises CRSError naming `path` and the string when it names no known CRS.
    """
    if srs_name is None or not str(srs_name).strip():
        raise _fail("empty srsName", path)
    result = _resolve_cached(str(srs_name).strip())
    if isinstance(result, str):
        raise _fail(result, path)
    # a copy, so callers may not alter the cached object
    return CRSInfo(**result.__dict__)


def user_crs(text: str) -> CRSInfo:
    """A CRS given on the command line: "EPSG:3946", "EPSG:25832+7837", a URN, WKT, ..."""
    return resolve_crs(text, path="--crs")


def same_crs(a: CRSInfo, b: CRSInfo) -> bool:
    """True when a and b describe the same CRS; a missing vertical part matches any."""
    if a.horizontal_epsg is not None and b.horizontal_epsg is not None:
        if a.horizontal_epsg != b.horizontal_epsg:
            return False
    elif not _horizontal(a).equals(_horizontal(b), ignore_axis_order=True):
        return False
    if a.vertical_epsg is not None and b.vertical_epsg is not None:
        return a.vertical_epsg == b.vertical_epsg
    return True


def more_complete(a: CRSInfo, b: CRSInfo) -> CRSInfo:
    """Of two same_crs() CRSs, the one that also names a height system."""
    return b if (a.vertical_epsg is None and b.vertical_epsg is not None) else a


@lru_cache(maxsize=128)
def _parts_of_wkt(wkt: str) -> tuple[pyproj.CRS | None, pyproj.CRS | None]:
    return _split(pyproj.CRS(wkt))


def _horizontal(info: CRSInfo) -> pyproj.CRS:
    return _parts_of_wkt(info.wkt)[0]


def _vertical(info: CRSInfo) -> pyproj.CRS | None:
    return _parts_of_wkt(info.wkt)[1]


def output_crs(src: CRSInfo, dst: CRSInfo) -> CRSInfo:
    """The CRS of points reprojected from src to dst: dst, keeping src's height system when dst
    names none (heights then pass through unchanged)."""
    if dst.vertical_epsg is None and src.vertical_epsg is not None and _vertical(dst) is None:
        out = _info(dst.srs_name or dst.label, _horizontal(dst), _vertical(src))
        return out
    return dst


@lru_cache(maxsize=64)
def _transformer(src_wkt: str, dst_wkt: str) -> pyproj.Transformer:
    return pyproj.Transformer.from_crs(pyproj.CRS(src_wkt), pyproj.CRS(dst_wkt), always_xy=True)


def lat_first(xyz: np.ndarray, crs: CRSInfo) -> bool:
    """Whether geographic coordinates are stored latitude first (EPSG order).

    Files that write longitude first are recognised by a first value outside [-90, 90]."""
    if crs.is_projected:
        return False
    axes = _horizontal(crs).axis_info
    epsg_lat_first = bool(axes) and axes[0].direction.lower() == "north"
    if epsg_lat_first and len(xyz) and np.any(np.abs(xyz[:, 0]) > 90.0):
        return False
    return epsg_lat_first


def reproject_points(xyz: np.ndarray, src: CRSInfo, dst: CRSInfo, *, swap_lat_lon: bool | None = None) -> np.ndarray:
    """Reproject (N,3) points from src to dst (pyproj, always_xy=True).

    Geographic input is taken in the file's axis order (latitude, longitude, height per EPSG, see
    module doc; `swap_lat_lon` overrides the detection); projected input and the output are
    (easting, northing, height). When dst names no height system, only the horizontal position is
    transformed and heights are kept (the output CRS is `output_crs(src, dst)`); otherwise the full
    compound transformation is used.
    """
    xyz = np.asarray(xyz, dtype=np.float64)
    if xyz.ndim != 2 or xyz.shape[1] not in (2, 3):
        raise ValueError(f"reproject_points expects (N,2) or (N,3) points, got {xyz.shape}")
    out = xyz.copy()
    if len(xyz) == 0:
        return out
    swap = lat_first(xyz, src) if swap_lat_lon is None else swap_lat_lon
    x, y = (xyz[:, 1], xyz[:, 0]) if swap else (xyz[:, 0], xyz[:, 1])
    three_d = xyz.shape[1] == 3 and _vertical(dst) is not None and src.vertical_epsg != dst.vertical_epsg
    if three_d:
        t = _transformer(src.wkt, dst.wkt)
        ox, oy, oz = t.transform(x, y, xyz[:, 2])
        out[:, 2] = oz
    else:
        t = _transformer(_horizontal(src).to_wkt(), _horizontal(dst).to_wkt())
        ox, oy = t.transform(x, y)
    out[:, 0] = ox
    out[:, 1] = oy
    if not np.all(np.isfinite(out)):
        raise CRSError(f"reprojection from {src.label} to {dst.label} failed for some points (outside the CRS area?)")
    return out


# -- the fallback geoid ---------------------------------------------------------------------------
#
# GNSS gives ellipsoidal heights h; city models use physical heights H = h - N, with N the geoid
# (or quasigeoid) undulation of the model's height system. PROJ applies N only with the national
# grid of that system (Germany: de_bkg_gcg2016.tif for DHHN2016), which neither the pyproj wheel
# nor a PROJ without network access has. EGM96, a worldwide geoid, is always at hand on a machine
# with Debian's proj-data (egm96_15.gtx, a 15' grid; PROJ's own name us_nga_egm96_15.tif): it is
# used instead of a missing national grid, and the log and report say so.

#: File names of the EGM96 15' grid: PROJ's current name first, then Debian proj-data's.
FALLBACK_GEOID_FILES = ("us_nga_egm96_15.tif", "egm96_15.gtx")
#: Directories searched for it besides PROJ's own (PROJ_DATA, pyproj's data and user dirs).
FALLBACK_GEOID_DIRS = ("/usr/share/proj", "/usr/local/share/proj")
#: What EGM96 heights typically differ from a national height system's (m): metre-level where
#: gravity data are dense (Europe, North America), several metres in mountains and elsewhere.
FALLBACK_GEOID_ACCURACY = 2.0


@dataclass(frozen=True)
class Geoid:
    """A geoid grid used to turn ellipsoidal heights into physical heights."""

    name: str  # "EGM96"
    path: str  # the grid file
    accuracy_m: float  # how far its heights typically are from the national system's

    @property
    def grid(self) -> str:
        return Path(self.path).name

    def todict(self) -> dict:
        return {"name": self.name, "grid": self.grid, "path": self.path,
                "accuracy_m": self.accuracy_m}


def proj_search_dirs() -> list[Path]:
    """Where PROJ (as pyproj runs it) and Debian keep grids, in search order."""
    import os

    dirs: list[str] = []
    for variable in ("PROJ_DATA", "PROJ_LIB"):
        dirs += [d for d in os.environ.get(variable, "").split(os.pathsep) if d]
    try:
        dirs += [d for d in pyproj.datadir.get_data_dir().split(os.pathsep) if d]
    except pyproj.exceptions.DataDirError:
        pass
    dirs.append(pyproj.datadir.get_user_data_dir())
    dirs += list(FALLBACK_GEOID_DIRS)
    out: list[Path] = []
    for d in dirs:
        path = Path(d)
        if path not in out:
            out.append(path)
    return out


def fallback_geoid() -> Geoid | None:
    """The worldwide EGM96 grid if this machine has it (None otherwise; `scripts/bootstrap.sh`
    installs Debian's proj-data, which ships it)."""
    for directory in proj_search_dirs():
        for name in FALLBACK_GEOID_FILES:
            path = directory / name
            if path.is_file():
                return Geoid("EGM96", str(path), FALLBACK_GEOID_ACCURACY)
    return None


@lru_cache(maxsize=8)
def _undulation_transformer(path: str) -> pyproj.Transformer:
    return pyproj.Transformer.from_pipeline(
        "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
        f"+step +proj=vgridshift +grids={path} +multiplier=1 "
        "+step +proj=unitconvert +xy_in=rad +xy_out=deg")


def geoid_undulation(longitude, latitude, geoid: Geoid) -> np.ndarray:
    """Undulation N (m) of `geoid` at WGS84 longitudes and latitudes (degrees): physical
    height = ellipsoidal height - N."""
    lon = np.atleast_1d(np.asarray(longitude, dtype=np.float64))
    lat = np.atleast_1d(np.asarray(latitude, dtype=np.float64))
    if " " in geoid.path:
        raise CRSError(f"the geoid grid path must not contain spaces: {geoid.path!r}")
    try:
        _, _, n = _undulation_transformer(geoid.path).transform(lon, lat, np.zeros_like(lon))
    except pyproj.exceptions.ProjError as error:
        raise CRSError(f"cannot read the geoid grid {geoid.path}: {error}") from None
    n = np.asarray(n, dtype=np.float64)
    if not np.all(np.isfinite(n)):
        raise CRSError(f"the geoid grid {geoid.grid} has no value at some positions")
    return n
