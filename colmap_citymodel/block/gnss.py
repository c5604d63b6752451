"""Read GNSS projection-centre positions of images and bring them into the city model's CRS.

Three sources (method.md section 2, group f_pos):
- a text file ``image_name X Y Z [sX sY sZ]`` in a user-given CRS (``--gnss_crs``),
- the EXIF GPS tags of the images (Pillow),
- the pose priors of a COLMAP 4 database (``pycolmap.Database.read_all_pose_priors``).

Positions are returned in the *target* CRS (the city model's CRS), easting, northing, height,
float64 and NOT shifted; ``GNSSObservations.to_local(origin)`` gives the store's local frame.

Heights. GNSS delivers ellipsoidal heights; city models use physical (orthometric/normal)
heights, which differ by the geoid undulation N (tens of metres: ~35-50 m in Central and
Northern Europe). PROJ converts between them only with the grid of the model's height system;
without network access and without that grid it falls back to a "ballpark vertical
transformation" that leaves the height unchanged. We detect that from the operation PROJ
actually used; the heights are then converted with the worldwide EGM96 geoid
(`citymodel.crs.fallback_geoid`, Debian's proj-data) and a warning names the grid used, its
accuracy (metre-level) and the missing national grid. Only without EGM96 do the heights stay
ellipsoidal (`vertical_applied` False), which refine refuses unless the offset is given or
estimated (`--gnss_height_offset METRES|auto`).
"""

from __future__ import annotations

import logging
import math
import shutil
import tempfile
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np
import pycolmap

from ..citymodel.raw_model import MAX_PROJECTED_COORDINATE, CRSInfo, coordinate_problem
from ..errors import CRSError, GNSSError
from .image_metadata import ImageMetadata, read_folder_metadata

logger = logging.getLogger(__name__)

DEFAULT_SIGMA = (3.0, 3.0, 5.0)  # metres, X Y Z (method.md section 2, Unger 5.3)
#: Largest GNSS sigma (m): beyond it a position says nothing, and its square overflows nothing.
MAX_SIGMA = 1e6
# Typical magnitude of the geoid undulation, quoted when PROJ lacks the grid to apply it.
TYPICAL_UNDULATION = "typically 20-50 m in Europe, -106 to +85 m worldwide"


@dataclass
class GNSSObservations:
    """GNSS projection centres of images in the target (city model) CRS."""

    image_names: list[str]
    positions: np.ndarray  # (N,3) float64 in the target CRS, not shifted
    sigmas: np.ndarray  # (N,3) metres
    crs: CRSInfo
    source: str  # "database", "exif", "text"
    # Antenna offset in the camera frame (metres), applied by apply_lever_arm once poses are known.
    lever_arm: np.ndarray | None = None
    # True: heights converted to the model's height system; False: they are still ellipsoidal
    # (or in another vertical datum) because PROJ lacked a grid; None: nothing to convert.
    vertical_applied: bool | None = None
    notes: list[str] = field(default_factory=list)
    # The fallback geoid that converted the heights in place of the model height system's own
    # grid (citymodel.crs.Geoid.todict() plus the mean undulation and the missing grid), or None.
    geoid: dict | None = None
    path: str | None = None  # the file or directory read (None for other sources)

    def __post_init__(self):
        self.positions = np.asarray(self.positions, dtype=np.float64).reshape(-1, 3)
        self.sigmas = np.asarray(self.sigmas, dtype=np.float64).reshape(-1, 3)
        if len(self.image_names) != len(self.positions) or len(self.positions) != len(self.sigmas):
            raise ValueError("image_names, positions and sigmas must have the same length")

    def __len__(self) -> int:
        return len(self.image_names)

    def to_local(self, origin) -> np.ndarray:
        """Positions in the store's local frame (CRS minus origin)."""
        return self.positions - np.asarray(origin, dtype=np.float64).reshape(1, 3)

    def subset(self, names: Iterable[str]) -> "GNSSObservations":
        """Observations of the given image names, in the given order (unknown names -> GNSSError)."""
        index = {name: i for i, name in enumerate(self.image_names)}
        names = list(names)
        missing = [n for n in names if n not in index]
        if missing:
            raise GNSSError(f"no GNSS position for {len(missing)} image(s), e.g. {missing[:5]}")
        idx = np.array([index[n] for n in names], dtype=np.int64)
        return replace(
            self,
            image_names=names,
            positions=self.positions[idx],
            sigmas=self.sigmas[idx],
            notes=list(self.notes),
        )


# --------------------------------------------------------------------------------------------
# CRS handling (pyproj; colmap_citymodel.crs is used for parsing user strings when present)


def _pyproj_crs(crs):
    import pyproj

    if isinstance(crs, pyproj.CRS):
        return crs
    if isinstance(crs, CRSInfo):
        if crs.wkt:
            return pyproj.CRS.from_wkt(crs.wkt)
        return pyproj.CRS.from_user_input(crs.label)
    return pyproj.CRS.from_user_input(crs)


def _crs_info(text: str, path=None) -> CRSInfo:
    """A CRSInfo from a user string such as "EPSG:4979" or "EPSG:25832+7837"."""
    try:
        from ..citymodel.crs import user_crs  # written by the CRS helper; optional here
    except ImportError:
        user_crs = None
    if user_crs is not None:
        try:
            return user_crs(text)
        except CRSError as error:
            raise CRSError(f"GNSS CRS {text!r}: {error.message}", path) from None
    import pyproj

    try:
        crs = pyproj.CRS.from_user_input(text)
    except pyproj.exceptions.CRSError as error:
        raise CRSError(f"unknown CRS {text!r}: {error}", path) from None
    horizontal, vertical = crs, None
    if crs.is_compound:
        horizontal, vertical = crs.sub_crs_list[0], crs.sub_crs_list[1]
    return CRSInfo(
        srs_name=text,
        horizontal_epsg=horizontal.to_epsg(),
        vertical_epsg=None if vertical is None else vertical.to_epsg(),
        wkt=crs.to_wkt(),
        is_projected=horizontal.is_projected,
    )


def _first_axis_is_north(crs) -> bool:
    axes = crs.axis_info
    return bool(axes) and axes[0].direction.lower() in ("north", "south")


def _has_vertical(crs) -> bool:
    """True when the CRS carries a physical (gravity-related) height datum."""
    if crs.is_compound:
        return any(sub.is_vertical for sub in crs.sub_crs_list)
    return crs.is_vertical


def _is_ellipsoidal_3d(crs) -> bool:
    """True for 3D geographic/projected/geocentric CRSs whose third axis is ellipsoidal height."""
    return (not _has_vertical(crs)) and (crs.is_geocentric or len(crs.axis_info) == 3)


@dataclass
class _Transform:
    description: str
    vertical_applied: bool | None
    notes: list[str]
    geoid: dict | None = None  # the fallback geoid used for the heights (see GNSSObservations)


def _fallback_heights(xyz: np.ndarray, src_crs, what: str, missing: list[str], target: str
                      ) -> tuple[np.ndarray, dict, str] | None:
    """Physical heights from the ellipsoidal heights of `xyz` (x/y in always_xy order of
    `src_crs`) with the fallback geoid: (heights, geoid record, note), or None without it."""
    from pyproj.transformer import Transformer

    from ..citymodel.crs import fallback_geoid, geoid_undulation

    geoid = fallback_geoid()
    if geoid is None:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        to_wgs84 = Transformer.from_crs(src_crs, "EPSG:4979", always_xy=True)
        lon, lat, h = to_wgs84.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
    undulation = geoid_undulation(lon, lat, geoid)
    record = {**geoid.todict(), "mean_undulation_m": float(np.mean(undulation)),
              "missing_grids": missing}
    note = (f"{what}: ellipsoidal heights converted to {target} with the worldwide geoid "
            f"{geoid.name} ({geoid.grid}, mean undulation {np.mean(undulation):.2f} m; typically "
            f"within {geoid.accuracy_m:g} m of a national height system, more in mountains)"
            + (f" because PROJ lacks {', '.join(missing)}" if missing else "")
            + ". For centimetres install the national grid (projsync --file NAME, or PROJ_DATA); "
            "refine --gnss_height_offset auto estimates the remaining offset from the model.")
    return np.asarray(h, dtype=np.float64) - undulation, record, note


def reproject_with_report(xyz, src, dst, *, what: str = "GNSS", path=None):
    """Reproject (N,3) points from `src` to `dst` (CRSInfo, pyproj.CRS or user string).

    Input columns follow the source CRS's axis order (EPSG:4979: latitude, longitude, height);
    output is easting/x, northing/y, height. Returns (xyz_out, _Transform) where the report tells
    whether the vertical part was really applied. Warnings are logged.
    """
    import pyproj
    from pyproj.transformer import Transformer, TransformerGroup

    src_crs, dst_crs = _pyproj_crs(src), _pyproj_crs(dst)
    xyz = np.array(xyz, dtype=np.float64, copy=True).reshape(-1, 3)
    if _first_axis_is_north(src_crs):
        xyz[:, [0, 1]] = xyz[:, [1, 0]]
    if src_crs.is_geographic:
        if np.any(np.abs(xyz[:, 1]) > 90.0) or np.any(np.abs(xyz[:, 0]) > 360.0):
            raise GNSSError(
                f"{what}: latitude/longitude out of range for {src_crs.name}; columns must follow "
                "the CRS axis order (latitude longitude height for EPSG:4979/4326)",
                path,
            )
        area = dst_crs.area_of_use or (
            dst_crs.sub_crs_list[0].area_of_use if dst_crs.is_compound else None
        )
        if area is not None:
            margin = 2.0  # degrees; GNSS near the edge of a CRS's area is still fine
            inside = ((xyz[:, 0] >= area.west - margin) & (xyz[:, 0] <= area.east + margin)
                      & (xyz[:, 1] >= area.south - margin) & (xyz[:, 1] <= area.north + margin))
            if not np.any(inside):
                raise GNSSError(
                    f"{what}: no position lies in the area of the model CRS {dst_crs.name} "
                    f"({area.name}); are the columns in the CRS axis order (latitude longitude "
                    "height for EPSG:4979/4326)?",
                    path,
                )
    elif not src_crs.is_geocentric:
        _check_projected_area(xyz, src_crs, dst_crs, what, path)
    notes: list[str] = []
    if src_crs == dst_crs:
        return xyz, _Transform("no transformation (same CRS)", None, notes)

    with warnings.catch_warnings():
        # pyproj warns about missing grids; we report that ourselves, in words, below.
        warnings.simplefilter("ignore", UserWarning)
        group = TransformerGroup(src_crs, dst_crs, always_xy=True)
        transformer = (
            Transformer.from_crs(src_crs, dst_crs, always_xy=True) if group.transformers else None
        )
    if transformer is None:
        # No complete operation at all (e.g. EGM96 -> DHHN2016 without either grid): transform
        # horizontally and keep the heights.
        src2d = src_crs.sub_crs_list[0] if src_crs.is_compound else src_crs
        dst2d = dst_crs.sub_crs_list[0] if dst_crs.is_compound else dst_crs
        transformer = Transformer.from_crs(src2d, dst2d, always_xy=True)
        grids = sorted(
            {g.short_name for op in group.unavailable_operations for g in op.grids if not g.available}
        )
        notes.append(
            f"{what}: PROJ has no transformation from {src_crs.name} to {dst_crs.name} without "
            f"the grid(s) {', '.join(grids) or '?'}; heights were kept unchanged"
        )
    x, y, z = transformer.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2], errcheck=False)
    out = np.column_stack([x, y, z]).astype(np.float64)
    if not np.all(np.isfinite(out)):
        bad = int(np.sum(~np.all(np.isfinite(out), axis=1)))
        raise GNSSError(
            f"{what}: {bad} position(s) could not be transformed from {src_crs.name} to "
            f"{dst_crs.name}",
            path,
        )
    try:
        used = transformer.get_last_used_operation()
        description = used.description or transformer.description
    except Exception:  # pyproj < 3.4 or no operation recorded
        description = transformer.description
    lower = description.lower()

    missing = sorted(
        {g.short_name for op in group.unavailable_operations for g in op.grids if not g.available}
    )
    missing_text = f" (missing PROJ grid: {', '.join(missing)})" if missing else ""
    network = pyproj.network.is_network_enabled()
    vertical_applied: bool | None = None
    geoid = None
    src_ell, dst_vert = _is_ellipsoidal_3d(src_crs), _has_vertical(dst_crs)
    src_vert = _has_vertical(src_crs)
    if "ballpark geographic offset" in lower:
        notes.append(
            f"{what}: the horizontal datum shift {src_crs.name} -> {dst_crs.name} is a ballpark "
            f"offset (PROJ lacks a better operation){missing_text}; positions may be off by metres"
        )
    if src_ell and dst_vert:
        if "ballpark vertical" in lower or not group.transformers:
            dst_v = ([s for s in dst_crs.sub_crs_list if s.is_vertical] if dst_crs.is_compound
                     else [dst_crs])
            fallback = _fallback_heights(xyz, src_crs, what, missing,
                                         f"{dst_v[0].name if dst_v else dst_crs.name}")
            if fallback is not None:
                out[:, 2], geoid, note = fallback
                vertical_applied = True
                notes.append(note)
            else:
                vertical_applied = False
                notes.append(
                    f"{what}: heights stay ELLIPSOIDAL: PROJ could not apply the geoid model to "
                    f"reach the model's height system ({dst_crs.name}){missing_text}, and the "
                    "worldwide geoid EGM96 (Debian package proj-data) is not installed either; "
                    f"they differ from the model heights by the geoid undulation N "
                    f"({TYPICAL_UNDULATION}). Install the grid (projsync --file NAME, or "
                    f"PROJ_DATA) {'' if network else '(PROJ network is off) '}or proj-data, "
                    "give GNSS in the model's height system, or let refine estimate the offset "
                    "(--gnss_height_offset auto)."
                )
        else:
            vertical_applied = True
            shift = float(np.mean(xyz[:, 2] - out[:, 2]))
            notes.append(
                f"{what}: ellipsoidal heights converted to {dst_crs.name} heights "
                f"(mean geoid undulation {shift:.2f} m) via: {description}"
            )
    elif src_ell and not dst_vert and not dst_crs.is_geocentric:
        # City models hold physical heights even where their CRS names no height system.
        fallback = _fallback_heights(xyz, src_crs, what, [],
                                     "heights above the geoid (the model CRS "
                                     f"{dst_crs.name} names no height system)")
        if fallback is not None:
            out[:, 2], geoid, note = fallback
            vertical_applied = True
            notes.append(note)
        else:
            vertical_applied = False
            notes.append(
                f"{what}: the model CRS {dst_crs.name} has no vertical datum, so GNSS heights "
                f"stay ELLIPSOIDAL; if the model's heights are orthometric they differ by the "
                f"geoid undulation ({TYPICAL_UNDULATION})"
            )
    elif src_vert and dst_vert:
        src_v = [s for s in src_crs.sub_crs_list if s.is_vertical] if src_crs.is_compound else []
        dst_v = [s for s in dst_crs.sub_crs_list if s.is_vertical] if dst_crs.is_compound else []
        same = bool(src_v and dst_v and src_v[0] == dst_v[0])
        if not same and ("ballpark vertical" in lower or not group.transformers):
            vertical_applied = False
            notes.append(
                f"{what}: heights were NOT converted between the vertical datums of "
                f"{src_crs.name} and {dst_crs.name}{missing_text} (differences are usually < 1 m)"
            )
        elif not same:
            vertical_applied = True
    for note in notes:
        alarming = any(k in note for k in ("NOT", "ELLIPSOIDAL", "ballpark", "kept unchanged",
                                           "worldwide geoid"))
        logger.log(logging.WARNING if alarming else logging.INFO, note)
    logger.debug("%s: %s -> %s via %s", what, src_crs.name, dst_crs.name, description)
    return out, _Transform(description, vertical_applied, notes, geoid)


# --------------------------------------------------------------------------------------------
# Text files


def _parse_sigma(default_sigma) -> np.ndarray:
    sigma = np.asarray(default_sigma, dtype=np.float64).reshape(-1)
    if sigma.size == 1:
        sigma = np.repeat(sigma, 3)
    if sigma.size != 3 or not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        raise GNSSError(f"default sigma must be three positive numbers, got {default_sigma!r}")
    return sigma


def read_gnss_text(
    path,
    gnss_crs: str,
    target_crs: CRSInfo,
    default_sigma=DEFAULT_SIGMA,
    lever_arm=None,
) -> GNSSObservations:
    """Read ``image_name X Y Z [sX sY sZ]`` lines (``#`` comments, blank lines ignored).

    X Y Z follow the axis order of `gnss_crs` (EPSG:4979: latitude longitude ellipsoidal
    height; EPSG:25832+7837: easting northing DHHN2016 height). Image names must not contain
    whitespace. `lever_arm` (3,) in the camera frame is stored for apply_lever_arm.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise GNSSError(f"cannot read GNSS file: {error}", path) from None
    sigma_default = _parse_sigma(default_sigma)
    names, xyz, sigmas, numbers = [], [], [], []
    seen: dict[str, int] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].strip()
        if not content:
            continue
        parts = content.split()
        if len(parts) not in (4, 7):
            raise GNSSError(
                f"line {number}: expected 'image_name X Y Z [sX sY sZ]', got {len(parts)} fields",
                path,
            )
        try:
            values = [float(v) for v in parts[1:]]
        except ValueError:
            raise GNSSError(f"line {number}: not a number in {content!r}", path) from None
        if not all(math.isfinite(v) for v in values):
            raise GNSSError(f"line {number}: non-finite value in {content!r}", path)
        if parts[0] in seen:
            raise GNSSError(
                f"line {number}: image {parts[0]!r} already given on line {seen[parts[0]]}", path
            )
        seen[parts[0]] = number
        sigma = values[3:] if len(values) == 6 else sigma_default
        if np.any(np.asarray(sigma) <= 0):
            raise GNSSError(f"line {number}: sigmas must be positive", path)
        if np.any(np.asarray(sigma) > MAX_SIGMA):
            raise GNSSError(f"line {number}: a sigma beyond {MAX_SIGMA:.0e} m", path)
        numbers.append(number)
        names.append(parts[0])
        xyz.append(values[:3])
        sigmas.append(sigma)
    if not names:
        raise GNSSError("no GNSS positions in file", path)
    src = _crs_info(gnss_crs, path)
    problem = _position_problem(np.array(xyz), src)
    if problem is not None:
        row, why = problem
        raise GNSSError(f"line {numbers[row]}: {why} in {src.label}", path)
    positions, report = reproject_with_report(
        np.array(xyz), src, target_crs, what=f"GNSS {path.name}", path=path
    )
    logger.info("Read %d GNSS positions from %s (%s -> %s)", len(names), path, src.label,
                target_crs.label)
    return GNSSObservations(
        image_names=names,
        positions=positions,
        sigmas=np.array(sigmas, dtype=np.float64),
        crs=target_crs,
        source="text",
        lever_arm=None if lever_arm is None else np.asarray(lever_arm, dtype=np.float64),
        vertical_applied=report.vertical_applied,
        notes=report.notes,
        geoid=report.geoid,
        path=str(path),
    )


def _check_projected_area(xyz: np.ndarray, src_crs, dst_crs, what: str, path) -> None:
    """Projected positions none of which lies in the area of use of their CRS or of the model's
    CRS (2 degrees margin) were given in another CRS: a GNSSError says so."""
    from pyproj import CRS, Transformer

    src2d = src_crs.sub_crs_list[0] if src_crs.is_compound else src_crs
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        to_geo = Transformer.from_crs(src2d, CRS.from_epsg(4326), always_xy=True)
        lon, lat = to_geo.transform(xyz[:, 0], xyz[:, 1], errcheck=False)
    lon, lat = np.asarray(lon, dtype=np.float64), np.asarray(lat, dtype=np.float64)
    margin = 2.0
    for crs, whose in ((src2d, "the GNSS CRS"), (dst_crs, "the model CRS")):
        area = crs.area_of_use or (
            crs.sub_crs_list[0].area_of_use if crs.is_compound else None)
        if area is None:
            continue
        west, east = area.west - margin, area.east + margin
        in_lon = (lon >= west) & (lon <= east) if west <= east else (lon >= west) | (lon <= east)
        inside = np.isfinite(lon) & np.isfinite(lat) & in_lon \
            & (lat >= area.south - margin) & (lat <= area.north + margin)
        if not np.any(inside):
            raise GNSSError(
                f"{what}: no position lies in the area of {whose} {crs.name} ({area.name}); "
                f"are the positions really in {src_crs.name}? (check --gnss_crs)",
                path,
            )


def _position_problem(xyz: np.ndarray, crs: CRSInfo) -> tuple[int, str] | None:
    """The first position no CRS of its kind can hold (raw_model.coordinate_problem; geocentric
    coordinates only within MAX_PROJECTED_COORDINATE on every axis), or None."""
    pcrs = _pyproj_crs(crs)
    horizontal = pcrs.sub_crs_list[0] if pcrs.is_compound else pcrs
    if horizontal.is_geocentric:
        bad = np.flatnonzero(np.abs(xyz).max(axis=1) > MAX_PROJECTED_COORDINATE)
        if len(bad):
            return int(bad[0]), f"position {xyz[bad[0]].tolist()} lies beyond the Earth"
        return None
    problem = coordinate_problem(xyz, geographic=horizontal.is_geographic,
                                 lat_first=_first_axis_is_north(horizontal))
    if problem is not None and horizontal.is_geographic and "latitude" in problem[1]:
        problem = (problem[0], problem[1] + "; columns must follow the CRS axis order (latitude "
                   "longitude height for EPSG:4979/4326)")
    return problem


# --------------------------------------------------------------------------------------------
# EXIF


def read_gnss_exif(
    image_dir,
    target_crs: CRSInfo,
    default_sigma=DEFAULT_SIGMA,
    *,
    altitude: str = "sea_level",
    dop_scale: float = 1.0,
    metadata: list[ImageMetadata] | None = None,
) -> GNSSObservations:
    """GNSS positions from the EXIF GPS tags and a drone's XMP of all images below `image_dir`
    (block.image_metadata: DJI's XMP position and absolute altitude win over EXIF GPS).

    Names are paths relative to `image_dir` (as COLMAP names images). Sigmas
    (ImageMetadata.sigma): an RTK solution's standard deviations (DJI RtkStdLon/Lat/Hgt), else
    GPSHPositioningError (metres) as sigma_h, else the Pix4D camera's GPSXYAccuracy and
    GPSZAccuracy, else GPSDOP * dop_scale as sigma_h; sigma_z = sigma_h * 5/3 (the ratio of the
    default sigmas). dop_scale defaults to 1 m because phones and mapping apps (e.g. the Lund
    photos, written by Mapillary) store their accuracy estimate in metres in GPSDOP; for a
    receiver's true DOP pass its range error (UERE, ~3-5 m). Without any: `default_sigma`.

    `altitude`: "sea_level" (the EXIF definition, written by phones and DJI drones) keeps the
    altitude as a height in the model's system (national height datums differ from mean sea
    level by < ~1 m); "ellipsoidal" treats it as WGS84 ellipsoidal height (EPSG:4979) and
    converts it with PROJ where the geoid grid is available. `metadata`: the images' metadata
    when already read (block.image_metadata.read_folder_metadata).
    """
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise GNSSError("image directory does not exist", image_dir)
    if altitude not in ("sea_level", "ellipsoidal"):
        raise ValueError("altitude must be 'sea_level' or 'ellipsoidal'")
    if metadata is None:
        metadata = read_folder_metadata(image_dir)
    names, lla, sigmas, sources = _metadata_positions(metadata, _parse_sigma(default_sigma),
                                                      dop_scale, image_dir)
    positions, vertical_applied, notes, geoid = _exif_to_crs(lla, altitude, target_crs,
                                                             image_dir)
    counts = {s: sources.count(s) for s in dict.fromkeys(sources)}
    notes.append("EXIF/XMP GPS sigmas: " + ", ".join(f"{n} from {SIGMA_SOURCES[s]}"
                                                     for s, n in counts.items()))
    logger.info("Read %d EXIF/XMP GPS positions from %s (%s)", len(names), image_dir,
                notes[-1].split(": ", 1)[1])
    return GNSSObservations(
        image_names=names,
        positions=positions,
        sigmas=np.array(sigmas, dtype=np.float64),
        crs=target_crs,
        source="exif",
        vertical_applied=vertical_applied,
        notes=notes,
        geoid=geoid,
        path=str(image_dir),
    )


#: What each ImageMetadata.sigma source is called in the notes.
SIGMA_SOURCES = {"rtk": "RTK standard deviations", "exif_error": "GPSHPositioningError",
                 "xmp_accuracy": "the XMP GPS accuracy", "dop": "GPSDOP",
                 "default": "the default sigma"}


def _metadata_positions(metadata, sigma_default: np.ndarray, dop_scale: float, image_dir):
    """(names, (N, 3) latitude longitude altitude, (N, 3) sigmas, sigma sources) of the images
    that have a position; GNSSError when none has."""
    names, lla, sigmas, sources, without = [], [], [], [], []
    for meta in metadata:
        if not meta.has_position:
            without.append(meta.name)
            continue
        sigma, source = meta.sigma(dop_scale)
        names.append(meta.name)
        lla.append([meta.latitude, meta.longitude, meta.altitude])
        sigmas.append(sigma_default if sigma is None else sigma)
        sources.append(source or "default")
    if without:
        logger.warning(
            "%d of %d images have no usable EXIF/XMP GPS position (latitude, longitude and "
            "altitude), e.g. %s", len(without), len(metadata), without[:3],
        )
    if not names:
        raise GNSSError(f"none of the {len(metadata)} images has an EXIF/XMP GPS position",
                        image_dir)
    return names, np.array(lla, dtype=np.float64), sigmas, sources


def _exif_to_crs(lla: np.ndarray, altitude: str, target_crs, image_dir):
    """(positions in `target_crs`, vertical_applied, notes, geoid) of EXIF latitude,
    longitude, altitude (read_gnss_exif's `altitude`)."""
    if altitude == "ellipsoidal":
        positions, report = reproject_with_report(
            lla, "EPSG:4979", target_crs, what="EXIF GPS", path=image_dir
        )
        return positions, report.vertical_applied, list(report.notes), report.geoid
    import pyproj

    dst = _pyproj_crs(target_crs)
    dst2d = dst.sub_crs_list[0] if dst.is_compound else dst
    horizontal, report = reproject_with_report(
        np.column_stack([lla[:, :2], np.zeros(len(lla))]),
        pyproj.CRS.from_epsg(4326),
        dst2d,
        what="EXIF GPS",
        path=image_dir,
    )
    positions = np.column_stack([horizontal[:, :2], lla[:, 2]])
    notes = report.notes + [
        "EXIF GPS: altitude taken as height above sea level (EXIF definition) and used as a "
        "model height without a datum change (national height datums differ from mean sea "
        "level by < ~1 m)"
    ]
    logger.info(notes[-1])
    return positions, None, notes, None


# --------------------------------------------------------------------------------------------
# COLMAP database pose priors


def _sigmas_from_covariance(cov, sigma_default: np.ndarray) -> np.ndarray:
    cov = np.asarray(cov, dtype=np.float64).reshape(3, 3)
    if not np.all(np.isfinite(cov)):
        return sigma_default.copy()
    diag = np.diag(cov)
    if np.any(diag <= 0):
        return sigma_default.copy()
    return np.sqrt(diag)


def read_gnss_database(
    database_path,
    target_crs: CRSInfo,
    default_sigma=DEFAULT_SIGMA,
) -> GNSSObservations:
    """GNSS positions from the pose priors of a COLMAP 4 database.

    pycolmap 4.2.1: ``Database.read_all_pose_priors()`` returns PosePrior objects with
    ``position`` (3,), ``position_covariance`` (3,3, NaN when unknown), ``coordinate_system``
    (WGS84 / CARTESIAN / UNDEFINED) and ``corr_data_id`` (a data_t: sensor_id + id). COLMAP links
    a prior to an image through the image's ``data_id`` (sensor type CAMERA, sensor id = camera
    id, id = image id); priors of other sensors (e.g. IMU) are attached to every image of the
    frame that holds that data id.

    WGS84 priors are (latitude, longitude, altitude) as COLMAP writes them; the altitude is
    treated as ellipsoidal height (EPSG:4979), as COLMAP's own GPS conversion does.
    CARTESIAN priors are taken to be in the target (model) CRS already, unshifted.
    UNDEFINED priors are taken as CARTESIAN with a warning. Sigmas are the square roots of the
    covariance diagonal; a NaN or non-positive covariance gives `default_sigma`.
    """

    database_path = Path(database_path)
    if not database_path.is_file():
        raise GNSSError("COLMAP database does not exist", database_path)
    sigma_default = _parse_sigma(default_sigma)
    # pycolmap opens a database read-write and rewrites it (schema upgrade, pragmas): read a
    # private copy so that the user's database stays byte-identical.
    scratch = tempfile.TemporaryDirectory(prefix="colmap_citymodel_db_")
    copy = Path(scratch.name) / "database.db"
    try:
        shutil.copyfile(database_path, copy)
        database = pycolmap.Database.open(str(copy))
    except Exception as error:  # pycolmap raises plain RuntimeError/ValueError
        scratch.cleanup()
        raise GNSSError(f"cannot open COLMAP database: {error}", database_path) from None
    try:
        try:
            images = database.read_all_images()
            priors = database.read_all_pose_priors()
            frames = database.read_all_frames()
        except Exception as error:
            raise GNSSError(f"cannot read pose priors: {error}", database_path) from None
        names_by_data = {_data_key(image.data_id): image.name for image in images}
        frame_images: dict[tuple, list[str]] = {}
        for frame in frames:
            frame_names = [names_by_data[k] for k in map(_data_key, frame.image_ids)
                           if k in names_by_data]
            for data_id in frame.data_ids:
                frame_images[_data_key(data_id)] = frame_names
    finally:
        database.close()
        scratch.cleanup()

    CS = pycolmap.PosePriorCoordinateSystem
    rows: dict[str, tuple[np.ndarray, np.ndarray, str]] = {}
    unlinked = 0
    for prior in priors:
        position = np.asarray(prior.position, dtype=np.float64)
        if not np.all(np.isfinite(position)):
            continue
        key = _data_key(prior.corr_data_id)
        if key in names_by_data:
            targets = [names_by_data[key]]
        else:
            targets = frame_images.get(key, [])
        if not targets:
            unlinked += 1
            continue
        system = {CS.WGS84: "WGS84", CS.CARTESIAN: "CARTESIAN"}.get(prior.coordinate_system,
                                                                   "UNDEFINED")
        sigma = _sigmas_from_covariance(prior.position_covariance, sigma_default)
        for name in targets:
            rows[name] = (position, sigma, system)
    if unlinked:
        logger.warning("%d pose prior(s) in %s are linked to no image; ignored", unlinked,
                       database_path)
    if not rows:
        raise GNSSError("the database has no pose priors with a position", database_path)
    names = sorted(rows)
    raw = np.array([rows[n][0] for n in names])
    sigmas = np.array([rows[n][1] for n in names])
    systems = np.array([rows[n][2] for n in names])
    positions = raw.copy()
    notes: list[str] = []
    vertical_applied = geoid = None
    wgs = systems == "WGS84"
    if np.any(wgs):
        positions[wgs], report = reproject_with_report(
            raw[wgs], "EPSG:4979", target_crs, what="pose priors (WGS84)", path=database_path
        )
        vertical_applied, notes = report.vertical_applied, list(report.notes)
        geoid = report.geoid
    if np.any(systems == "UNDEFINED"):
        note = (f"{int(np.sum(systems == 'UNDEFINED'))} pose prior(s) have an UNDEFINED "
                "coordinate system; taken as coordinates in the model CRS")
        logger.warning(note)
        notes.append(note)
    if np.any(~wgs):
        notes.append("CARTESIAN pose priors taken as unshifted coordinates in the model CRS "
                     f"({target_crs.label})")
    logger.info("Read %d pose priors from %s", len(names), database_path)
    return GNSSObservations(
        image_names=names,
        positions=positions,
        sigmas=sigmas,
        crs=target_crs,
        source="database",
        vertical_applied=vertical_applied,
        notes=notes,
        geoid=geoid,
        path=str(database_path),
    )


def _data_key(data_id) -> tuple:
    sensor = data_id.sensor_id
    return (int(sensor.type.value), int(sensor.id), int(data_id.id))


# --------------------------------------------------------------------------------------------
# Lever arm and matching to a reconstruction


def apply_lever_arm(
    gnss: GNSSObservations,
    cam_from_world_rotations: Mapping[str, np.ndarray],
    lever_arm=None,
) -> GNSSObservations:
    """Projection centres from antenna positions: C = antenna - R^T lever.

    `lever_arm` (default: gnss.lever_arm) is the vector from the projection centre to the GNSS
    antenna in the camera frame (COLMAP: x right, y down, z viewing direction), metres.
    `cam_from_world_rotations` maps image names to the 3x3 rotation R of cam_from_world *in the
    target CRS orientation*, so this is applied after georegistration (a lever arm of decimetres
    does not matter for the initial Sim3 with metre-level GNSS noise). Images without a rotation
    keep the antenna position (logged). Returns a new object with lever_arm cleared.
    """
    lever = gnss.lever_arm if lever_arm is None else np.asarray(lever_arm, dtype=np.float64)
    if lever is None:
        return gnss
    lever = np.asarray(lever, dtype=np.float64).reshape(3)
    positions = gnss.positions.copy()
    missing = 0
    for i, name in enumerate(gnss.image_names):
        rotation = cam_from_world_rotations.get(name)
        if rotation is None:
            missing += 1
            continue
        positions[i] -= np.asarray(rotation, dtype=np.float64).reshape(3, 3).T @ lever
    if missing:
        logger.warning("lever arm not applied to %d image(s) without a pose", missing)
    return replace(gnss, positions=positions, lever_arm=None, notes=list(gnss.notes))


def rotations_from_reconstruction(reconstruction) -> dict[str, np.ndarray]:
    """cam_from_world rotation matrices of all registered images, by name."""
    out = {}
    for image in reconstruction.images.values():
        if image.has_pose:
            out[image.name] = image.cam_from_world().rotation.matrix()
    return out


def match_to_reconstruction(gnss: GNSSObservations, reconstruction, origin=None, *,
                            min_positions: int = 3):
    """Pair GNSS positions with the registered images of a pycolmap.Reconstruction.

    Returns (image_ids (K,) int64, positions_local (K,3), sigmas (K,3)) for the GNSS positions
    whose image is registered in the reconstruction, in GNSS order; positions_local are
    gnss.to_local(origin) (origin None: zeros).

    GNSS positions of images that are not in the reconstruction, or are in it without a pose, are
    normal (a COLMAP database holds priors for every image, while the mapper often registers a
    subset or splits the block into sparse/0, sparse/1, ...): they are dropped and their number is
    logged. Only fewer than `min_positions` usable positions raise GNSSError; the message then
    shows a few GNSS names and a few reconstruction image names, so a naming mismatch (folder
    prefixes, extensions) is visible.
    """
    by_name = {image.name: image for image in reconstruction.images.values()}
    origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64)
    local = gnss.to_local(origin)
    ids, keep = [], []
    not_in_model = not_registered = 0
    for i, name in enumerate(gnss.image_names):
        image = by_name.get(name)
        if image is None:
            not_in_model += 1
        elif not image.has_pose:
            not_registered += 1
        else:
            ids.append(image.image_id)
            keep.append(i)
    if not_in_model:
        logger.info(
            "%d of %d GNSS position(s) (%s) name images that are not in the reconstruction; "
            "they are not used", not_in_model, len(gnss), gnss.source,
        )
    if not_registered:
        logger.info(
            "%d GNSS position(s) belong to images of the reconstruction without a pose; "
            "they are not used", not_registered,
        )
    if len(keep) < min_positions:
        gnss_names = list(gnss.image_names[:5])
        model_names = sorted(by_name)[:5]
        if not keep:
            what = "none of the"
        else:
            what = f"only {len(keep)} of the"
        raise GNSSError(
            f"{what} {len(gnss)} GNSS ({gnss.source}) image name(s) match a registered image of "
            f"the reconstruction (at least {min_positions} needed; {not_in_model} name(s) not in "
            f"the reconstruction, {not_registered} without a pose); GNSS names e.g. "
            f"{gnss_names}, reconstruction image names e.g. {model_names}",
            gnss.path,
        )
    keep = np.array(keep, dtype=np.int64)
    return np.array(ids, dtype=np.int64), local[keep], gnss.sigmas[keep]


def read_gnss(*, database=None, gnss=None, gnss_crs=None, exif=None, target_crs,
              default_sigma=(3.0, 3.0, 5.0)):
    """GNSS from exactly one source: COLMAP database pose priors, a text file or EXIF."""
    from ..errors import InputError

    given = [name for name, value in (("--database", database), ("--gnss", gnss),
                                      ("--exif", exif)) if value]
    if len(given) > 1:
        raise InputError(f"give one GNSS source, not {' and '.join(given)}")
    if database:
        return read_gnss_database(database, target_crs, default_sigma)
    if gnss:
        if not gnss_crs:
            raise InputError("--gnss needs --gnss_crs (e.g. EPSG:4979 or EPSG:25832+7837)", gnss)
        return read_gnss_text(gnss, gnss_crs, target_crs, default_sigma)
    if exif:
        return read_gnss_exif(exif, target_crs, default_sigma)
    return None
