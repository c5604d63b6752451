"""Ground marks: points surveyed on the ground and measured in the images, as control (in the
adjustment, adjust.marks) or as check points (only compared with the block, precision.accuracy).

File format: OpenDroneMap's ``gcp_list.txt`` (the format OpenSfM reads):

    <CRS>                                  first line: EPSG:32632, EPSG:25832+7837, a PROJ
                                           string (+proj=utm +zone=32 ...) or WGS84 UTM 32N
    geo_x geo_y geo_z im_x im_y image_name [gcp_name] [sigma_h sigma_v]

- geo_x, geo_y: easting and northing (longitude and latitude for a geographic CRS, in that
  order whatever the CRS's own axis order), geo_z the height in the CRS's height system;
- im_x, im_y: the mark in the image, pixels from the image's top-left corner with the centre
  of the top-left pixel at (0, 0), as OpenSfM reads them (COLMAP puts that centre at
  (0.5, 0.5): 0.5 is added);
- geo_z NaN: no surveyed height (OpenDroneMap's convention): a control mark then holds the
  block horizontally only (its height sigma NO_HEIGHT_SIGMA), a check mark is left out of the
  check statistics;
- gcp_name (optional): lines of one mark share it; without names, lines with the same
  coordinates are one mark (OpenSfM's rule);
- sigma_h sigma_v (optional, this package's extension; OpenDroneMap ignores extra columns):
  the surveyed position's sigmas in metres; else the defaults (`MarkOptions`,
  `--gcp_sigma H V`). Other extra columns are ignored.

Blank lines and ``#`` comments are skipped. Coordinates are converted into the city model's
CRS and height system as GNSS positions are (block.gnss.reproject_with_report: the national
geoid grid, else EGM96 with a warning); a CRS that names no height system (EPSG:32632) keeps
the heights as given, taken as the model's (a note says so): name it (EPSG:25832+7837, or
EPSG:4979 for ellipsoidal heights) to have them converted.
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap

from ..citymodel.raw_model import CRSInfo
from ..errors import InputError
from ..files import content_lines

logger = logging.getLogger(__name__)

#: What COLMAP's pixel coordinates add to gcp_list's: COLMAP puts the centre of the top-left
#: pixel at (0.5, 0.5), OpenSfM (and so gcp_list.txt) at (0, 0).
PIXEL_CENTRE = 0.5
#: Two lines of one named mark whose coordinates differ by more than this (m, in the file's
#: units) name two different points: the file is refused.
SAME_POSITION = 1e-3
#: Sigma (m) of the height of a mark surveyed without one (geo_z NaN): so large that the height
#: holds nothing, small enough to keep the adjustment's normal equations well scaled.
NO_HEIGHT_SIGMA = 1e4
#: Gauss-Newton steps of a mark's triangulation (converges in 2-3 from the linear solution).
TRIANGULATION_STEPS = 10

_UTM = re.compile(r"WGS\s*84\s+UTM\s+(\d{1,2})\s*([NS])", re.IGNORECASE)


@dataclass
class GroundMark:
    """One surveyed mark: its position (model CRS: easting, northing, height in the model's
    height system), the sigmas of that position (m, E N U) and where it was measured in the
    images (image name, x, y in COLMAP's pixel convention)."""

    name: str
    position: np.ndarray
    sigma: np.ndarray
    observations: list[tuple[str, float, float]] = field(default_factory=list)
    line: int = 0  # the mark's first line in its file
    has_height: bool = True  # False: surveyed without a height (geo_z NaN)


@dataclass
class GroundMarks:
    """The marks of one file, in the city model's CRS (`crs`)."""

    marks: list[GroundMark]
    crs: CRSInfo
    source_crs: str  # the file's header as read
    path: str | None = None
    notes: list[str] = field(default_factory=list)
    geoid: dict | None = None  # the fallback geoid that converted the heights, if one did

    def __len__(self) -> int:
        return len(self.marks)

    @property
    def names(self) -> list[str]:
        return [m.name for m in self.marks]

    def checkpoints(self) -> tuple[dict[str, np.ndarray], list[tuple[str, str, float, float]]]:
        """The marks as precision.checkpoints takes check points: {name: XYZ} (model CRS) and
        [(image_name, name, x, y)] (COLMAP pixels)."""
        known = {m.name: np.asarray(m.position, float) for m in self.marks if m.has_height}
        observations = [(image, m.name, x, y) for m in self.marks if m.has_height
                        for image, x, y in m.observations]
        return known, observations


# -- reading ----------------------------------------------------------------------------------

def header_crs(text: str) -> str:
    """The CRS of a gcp_list header as pyproj takes it: "WGS84 UTM 32N" becomes EPSG:32632,
    anything else (EPSG:N, a PROJ string, WKT) is passed on."""
    match = _UTM.fullmatch(text.strip())
    if match:
        zone = int(match.group(1))
        if not 1 <= zone <= 60:
            raise InputError(f"UTM zone {zone} out of 1-60 in the header {text!r}")
        return f"EPSG:{(32600 if match.group(2).upper() == 'N' else 32700) + zone}"
    return text.strip()


def _sigma_columns(parts: list[str]) -> np.ndarray | None:
    """(sigma_h, sigma_h, sigma_v) from the two columns after the name, when both are positive
    finite numbers; None otherwise (no such columns, or other extras)."""
    if len(parts) < 9:
        return None
    try:
        h, v = float(parts[7]), float(parts[8])
    except ValueError:
        return None
    if not (math.isfinite(h) and math.isfinite(v) and h > 0 and v > 0):
        return None
    return np.array([h, h, v])


def _parse_line(number: int, content: str, path: Path):
    """(x, y, z, im_x, im_y, image, name or None, sigma or None) of one data line."""
    parts = content.split()
    if len(parts) < 6:
        raise InputError(f"line {number}: expected 'geo_x geo_y geo_z im_x im_y image_name "
                         f"[gcp_name]', got {len(parts)} fields", path)
    try:
        values = [float(v) for v in parts[:5]]
    except ValueError:
        raise InputError(f"line {number}: not a number in {' '.join(parts[:5])!r}",
                         path) from None
    if not all(math.isfinite(v) for v in values[:2] + values[3:]) or math.isinf(values[2]):
        raise InputError(f"line {number}: a coordinate or pixel is not finite (only geo_z may "
                         "be NaN: no surveyed height)", path)
    name = parts[6] if len(parts) > 6 else None
    return (*values, parts[5], name, _sigma_columns(parts))


def _same(a: float, b: float) -> bool:
    """One coordinate of one mark on two lines (both NaN: no height on either)."""
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= SAME_POSITION


def _group(rows: list, default_sigma: np.ndarray, path: Path) -> list[dict]:
    """Lines grouped into marks: by name, else by identical coordinates."""
    marks: dict[str, dict] = {}
    for number, (x, y, z, u, v, image, name, sigma) in rows:
        key = name if name is not None else f"{x!r} {y!r} {z!r}"
        mark = marks.get(key)
        if mark is None:
            mark = marks[key] = {"name": name or f"unnamed-{len(marks) + 1}",
                                 "xyz": (x, y, z), "line": number, "images": {},
                                 "sigma": sigma if sigma is not None else default_sigma}
        elif not all(_same(a, b) for a, b in zip(mark["xyz"], (x, y, z))):
            raise InputError(f"line {number}: mark {name!r} has other coordinates than on line "
                             f"{mark['line']} (one name, two points)", path)
        if image in mark["images"]:
            raise InputError(f"line {number}: mark {mark['name']!r} measured twice in image "
                             f"{image!r} (also line {mark['images'][image][0]})", path)
        mark["images"][image] = (number, u + PIXEL_CENTRE, v + PIXEL_CENTRE)
    return list(marks.values())


def read_gcp_list(path, target_crs: CRSInfo, default_sigma=(0.02, 0.03)) -> GroundMarks:
    """The marks of a gcp_list.txt in `target_crs` (the city model's). `default_sigma`: (H, V)
    metres for lines that state none."""
    from .gnss import _crs_info

    path = Path(path)
    lines = list(content_lines(path, "the marks file"))
    if not lines:
        raise InputError("the marks file is empty (a first line with the CRS, then one line "
                         "per mark and image)", path)
    header = lines[0][1]
    if len(header.split()) >= 6 and _looks_numeric(header.split()[:5]):
        raise InputError("line 1 must name the CRS (EPSG:N, a PROJ string or WGS84 UTM 32N); "
                         "it holds a mark", path)
    source = _crs_info(header_crs(header), path)
    h, v = (float(s) for s in default_sigma)
    rows = [(number, _parse_line(number, content, path)) for number, content in lines[1:]]
    if not rows:
        raise InputError("no marks in the file (only its CRS line)", path)
    grouped = _group(rows, np.array([h, h, v]), path)
    given = np.array([g["xyz"] for g in grouped])
    heights = ~np.isnan(given[:, 2])
    xyz, notes, geoid = _to_model_crs(np.where(np.isnan(given), 0.0, given), source, target_crs,
                                      path)
    marks = [GroundMark(g["name"], xyz[k], np.asarray(g["sigma"], float)
                        if heights[k] else np.append(np.asarray(g["sigma"], float)[:2],
                                                     NO_HEIGHT_SIGMA),
                        [(image, x, y) for image, (_, x, y) in g["images"].items()], g["line"],
                        bool(heights[k]))
             for k, g in enumerate(grouped)]
    logger.info("read %d marks (%d image measurements) from %s (%s -> %s)", len(marks),
                sum(len(m.observations) for m in marks), path, source.label, target_crs.label)
    return GroundMarks(marks, target_crs, header, str(path), notes, geoid)


def _looks_numeric(values: list[str]) -> bool:
    try:
        [float(v) for v in values]
    except ValueError:
        return False
    return True


def _to_model_crs(xyz: np.ndarray, source: CRSInfo, target: CRSInfo, path: Path):
    """(N, 3) easting/longitude, northing/latitude, height from `source` into `target`:
    (positions, notes, fallback geoid record)."""
    from .gnss import _first_axis_is_north, _has_vertical, _pyproj_crs, reproject_with_report

    crs = _pyproj_crs(source)
    ordered = xyz.copy()
    if _first_axis_is_north(crs):  # the file is always x = east / longitude first
        ordered[:, [0, 1]] = ordered[:, [1, 0]]
    out, report = reproject_with_report(ordered, source, target, what=f"marks {path.name}",
                                        path=path)
    notes = list(report.notes)
    if not _has_vertical(crs) and len(crs.axis_info) < 3 and not crs.is_geocentric:
        notes.append(f"marks {path.name}: {crs.name} names no height system: the heights are "
                     "taken as the city model's (name one, e.g. EPSG:25832+7837, or EPSG:4979 "
                     "for ellipsoidal heights, to have them converted)")
        logger.info(notes[-1])
    return out, notes, report.geoid


# -- writing ----------------------------------------------------------------------------------

def write_gcp_list(path, crs_label: str, rows) -> None:
    """A gcp_list.txt: `rows` of (xyz in the CRS, image name, x, y in COLMAP pixels, mark name);
    the header `crs_label` (EPSG:N or a PROJ string)."""
    lines = [crs_label]
    for xyz, image, x, y, name in rows:
        lines.append(f"{xyz[0]:.4f} {xyz[1]:.4f} {xyz[2]:.4f} {x - PIXEL_CENTRE:.3f} "
                     f"{y - PIXEL_CENTRE:.3f} {image} {name}")
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


# -- geometry in a reconstruction --------------------------------------------------------------

def measurements_in(rec: pycolmap.Reconstruction, mark: GroundMark
                    ) -> tuple[list[tuple[int, np.ndarray]], list[str]]:
    """The mark's measurements in `rec`'s registered images as (image id, xy), and the names
    of the images it was measured in that `rec` does not hold or has not registered."""
    ids = {image.name: image for image in rec.images.values()}
    found, missing = [], []
    for name, x, y in mark.observations:
        image = ids.get(name)
        if image is None or not image.has_pose:
            missing.append(name)
            continue
        found.append((int(image.image_id), np.array([x, y], float)))
    return found, missing


def _view(rec: pycolmap.Reconstruction, image_id: int, xy: np.ndarray):
    """(cam_from_world rotation, translation, normalised measurement, focal) of one
    measurement."""
    image = rec.image(image_id)
    pose = image.cam_from_world()
    ray = np.asarray(image.camera.cam_ray_from_img(np.asarray(xy, float).reshape(1, 2)),
                     float).reshape(-1)
    return (np.asarray(pose.rotation.matrix()), np.asarray(pose.translation),
            ray[:2] / ray[2], float(image.camera.mean_focal_length()))


def triangulate_mark(rec: pycolmap.Reconstruction, measurements: list[tuple[int, np.ndarray]],
                     sigma_pixel: float = 1.0
                     ) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The point where the mark's rays meet in `rec`'s frame (linear, then Gauss-Newton on the
    image residuals): (X, its covariance from the rays alone with `sigma_pixel`, RMS residual
    px), or None with fewer than two measurements, parallel rays or a point behind a camera."""
    if len(measurements) < 2:
        return None
    views = [_view(rec, i, xy) for i, xy in measurements]
    rows = []
    for rotation, translation, m, _ in views:
        ray = np.array([m[0], m[1], 1.0])
        skew = np.array([[0, -ray[2], ray[1]], [ray[2], 0, -ray[0]], [-ray[1], ray[0], 0]])
        rows.append(skew @ np.column_stack([rotation, translation]))
    homogeneous = np.linalg.svd(np.vstack(rows))[2][-1]
    if abs(homogeneous[3]) < 1e-12 * np.linalg.norm(homogeneous):
        return None
    x = homogeneous[:3] / homogeneous[3]
    for _ in range(TRIANGULATION_STEPS):
        residual, jacobian = _ray_residuals(views, x)
        if residual is None:
            return None
        step = np.linalg.lstsq(jacobian, -residual, rcond=None)[0]
        x = x + step
        if np.linalg.norm(step) < 1e-9 * max(1.0, np.linalg.norm(x)):
            break
    residual, jacobian = _ray_residuals(views, x)
    if residual is None:
        return None
    normal = jacobian.T @ jacobian
    if np.linalg.cond(normal) > 1e12:
        return None
    return x, sigma_pixel ** 2 * np.linalg.inv(normal), float(np.sqrt(np.mean(residual ** 2)))


def _ray_residuals(views, x: np.ndarray):
    """Pixel residuals (2 per view) of point `x` and their Jacobian; (None, None) where it lies
    behind a camera."""
    residuals, rows = [], []
    for rotation, translation, m, focal in views:
        p = rotation @ x + translation
        if p[2] <= 0:
            return None, None
        residuals.append(focal * (p[:2] / p[2] - m))
        d = np.array([[1.0 / p[2], 0.0, -p[0] / p[2] ** 2], [0.0, 1.0 / p[2], -p[1] / p[2] ** 2]])
        rows.append(focal * d @ rotation)
    return np.concatenate(residuals), np.vstack(rows)


def similarity(source: np.ndarray, target: np.ndarray) -> pycolmap.Sim3d | None:
    """The 7-parameter similarity taking `source` onto `target` ((N, 3), N >= 3 not on a line),
    least squares; None where the points do not fix it."""
    source = np.asarray(source, float).reshape(-1, 3)
    target = np.asarray(target, float).reshape(-1, 3)
    if len(source) < 3 or np.linalg.matrix_rank(source - source.mean(0), tol=1e-6) < 2:
        return None
    return pycolmap.estimate_sim3d(source, target)


def similarity_design(points: np.ndarray, centre: np.ndarray | None = None) -> np.ndarray:
    """(3N, 7) derivative of a small similarity X + t + s (X - c) + w x (X - c) at `points`
    with respect to (t, s, w), c = `centre` (default their centroid): what a 7-parameter fit
    can absorb."""
    q = np.asarray(points, float).reshape(-1, 3)
    q = q - (q.mean(axis=0) if centre is None else np.asarray(centre, float))
    a = np.zeros((3 * len(q), 7))
    for i, (x, y, z) in enumerate(q):
        rows = slice(3 * i, 3 * i + 3)
        a[rows, :3] = np.eye(3)
        a[rows, 3] = (x, y, z)
        a[rows, 4:] = [[0.0, z, -y], [-z, 0.0, x], [y, -x, 0.0]]
    return a
