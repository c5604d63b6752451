"""Quality of dense points: each point's covariance from the precision of the cameras that see
it, and weighted RANSAC plane extraction with those sigmas (Mulder 4.3-4.4, method.md 9).

Propagation. A dense point X seen by cameras i in V is taken as the forward intersection of
its image observations x_i = pi_i(X) (pixels). With A_i = d pi_i / dX (2 x 3) and
B_i = d pi_i / d p_i (2 x 6) for the camera's projection centre and omega, phi, kappa
(p_i = X0, Y0, Z0, omega, phi, kappa as in image_precision.csv; R = Rx(omega) Ry(phi) Rz(kappa)
from photogrammetric camera axes to the model frame), least squares gives

    N = sum_i A_i^T A_i
    Sigma_X = sigma_image^2 N^-1 + N^-1 (sum_i A_i^T B_i Sigma_i B_i^T A_i) N^-1

the first term the point's own matching noise (`sigma_image` pixels per observation), the
second the cameras' a posteriori covariances Sigma_i carried through the intersection. The
cameras' covariances are taken as independent of each other (refine's per-image 6 x 6 blocks;
their cross covariances are not written), which makes the camera part a little optimistic
where cameras share errors (same rig frame, same strip). The Jacobians use the pinhole part of
each camera (focal lengths; the lens distortion's own derivative is left out: it changes
A and B by far less than a percent at aerial distortions).

Visibility. A camera sees a dense point when the point lies in front of it and projects into
its image, and the camera observes one of the point's `visibility_neighbours` nearest tie
points within `visibility_radius` (the tie points' tracks are where the camera really saw that
surface, so cameras looking at the back of a wall or through a building do not count). A dense
point without tie points that near is seen by every camera it projects into (marked in the
`visibility_tie_points` field, 0).

Mulder's own propagation (4.4.1: a polynomial through the median tie point sigma per number of
observations, evaluated at the dense point's number of views) is `count_sigma` when tie point
sigmas (refine's point_precision.ply) are given.

Planes. `extract_planes` finds planes one after another with the MSAC of assign/msac.py
(weighted sampling proportional to the weight, weighted least-squares refits, Mulder's point
normal test) and removes each plane's inliers; weights 1 / sigma_3d^2 or none.
"""

from __future__ import annotations

import csv
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pycolmap
import scipy.sparse as sp
from scipy.spatial import cKDTree

from ..assign.msac import msac_plane, point_normals
from ..errors import InputError
from ..options import AssignmentOptions

logger = logging.getLogger(__name__)

PHOTO = np.diag([1.0, -1.0, -1.0])


@dataclass
class DenseOptions:
    sigma_image: float = 1.0
    """Pixels: sigma of a dense point's image observation (its matching noise); 0 gives the
    cameras' part alone."""
    visibility_neighbours: int = 8
    """Nearest tie points whose tracks decide which cameras see a dense point."""
    visibility_radius: float = 5.0
    """Model units (m): tie points further away do not count."""
    min_views: int = 2
    """Points seen by fewer cameras get NaN sigmas."""
    polynomial_degree: int = 2
    """Degree of Mulder's polynomial of the median tie point sigma per number of views."""


# -- cameras --------------------------------------------------------------------------------------

@dataclass
class CameraSet:
    """Per camera: centre (3), R_world_from_photo (3,3), focal lengths, pycolmap camera and image,
    and the 6 x 6 covariance of X0, Y0, Z0 (m), omega, phi, kappa (rad)."""

    names: list[str]
    centres: np.ndarray
    rotations: np.ndarray
    angles: np.ndarray
    covariances: np.ndarray
    cameras: list
    images: list


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], float)


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], float)


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], float)


def _skew(axis: int) -> np.ndarray:
    e = np.zeros(3)
    e[axis] = 1.0
    return np.array([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]])


def photo_rotation(angles: np.ndarray) -> np.ndarray:
    return _rx(angles[0]) @ _ry(angles[1]) @ _rz(angles[2])


def _rotation_derivatives(angles: np.ndarray) -> list[np.ndarray]:
    """d R / d omega, d phi, d kappa of R = Rx Ry Rz."""
    rx, ry, rz = _rx(angles[0]), _ry(angles[1]), _rz(angles[2])
    return [rx @ _skew(0) @ ry @ rz, rx @ ry @ _skew(1) @ rz, rx @ ry @ rz @ _skew(2)]


def camera_set(rec: pycolmap.Reconstruction, covariances: dict[str, np.ndarray]) -> CameraSet:
    """The registered images of `rec` that have a covariance."""
    from scipy.spatial.transform import Rotation

    names, centres, rotations, angles, covs, cams, images = [], [], [], [], [], [], []
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        if image.name not in covariances:
            continue
        pose = image.cam_from_world()
        r_photo = np.asarray(pose.rotation.matrix()).T @ PHOTO
        names.append(image.name)
        centres.append(np.asarray(image.projection_center()))
        rotations.append(r_photo)
        angles.append(Rotation.from_matrix(r_photo).as_euler("XYZ"))
        covs.append(covariances[image.name])
        cams.append(rec.camera(image.camera_id))
        images.append(image)
    if not names:
        raise InputError("no registered image of the model has a covariance")
    return CameraSet(names, np.asarray(centres), np.asarray(rotations), np.asarray(angles),
                     np.asarray(covs), cams, images)


def _focal(camera) -> tuple[float, float]:
    return float(camera.focal_length_x), float(camera.focal_length_y)


# -- visibility ----------------------------------------------------------------------------------

def in_image(cams: CameraSet, k: int, points: np.ndarray) -> np.ndarray:
    """Points in front of camera k that project into its image."""
    cam = cams.cameras[k]
    xc = (points - cams.centres[k]) @ cams.rotations[k] @ PHOTO  # COLMAP camera frame
    front = xc[:, 2] > 0
    out = np.zeros(len(points), bool)
    if not np.any(front):
        return out
    pixels = np.asarray(cam.img_from_cam(xc[front]))
    inside = ((pixels[:, 0] >= 0) & (pixels[:, 0] <= cam.width) & (pixels[:, 1] >= 0)
              & (pixels[:, 1] <= cam.height))
    out[np.flatnonzero(front)[inside]] = True
    return out


def visibility(rec: pycolmap.Reconstruction, cams: CameraSet, points: np.ndarray,
               options: DenseOptions) -> tuple[sp.csr_matrix, np.ndarray]:
    """(points x cameras boolean CSR: who sees each point, per point whether tie points decided
    it). See the module docstring."""
    index = {name: k for k, name in enumerate(cams.names)}
    tie_xyz, rows, cols = [], [], []
    for p, point in enumerate(rec.points3D.values()):
        tie_xyz.append(point.xyz)
        for element in point.track.elements:
            k = index.get(rec.image(element.image_id).name)
            if k is not None:
                rows.append(p)
                cols.append(k)
    num_cams = len(cams.names)
    decided = np.zeros(len(points), bool)
    seen_by_ties = sp.csr_matrix((len(points), num_cams), dtype=bool)
    if tie_xyz:
        tracks = sp.csr_matrix((np.ones(len(rows), bool), (rows, cols)),
                               shape=(len(tie_xyz), num_cams))
        tree = cKDTree(np.asarray(tie_xyz))
        k = min(options.visibility_neighbours, len(tie_xyz))
        dist, idx = tree.query(points, k=k, distance_upper_bound=options.visibility_radius)
        dist, idx = dist.reshape(len(points), -1), idx.reshape(len(points), -1)
        ok = np.isfinite(dist)
        r = np.repeat(np.arange(len(points)), ok.sum(1))
        near = sp.csr_matrix((np.ones(len(r), bool), (r, idx[ok])),
                             shape=(len(points), len(tie_xyz)))
        seen_by_ties = (near.astype(np.int32) @ tracks.astype(np.int32)) > 0
        decided = np.asarray(ok.any(1)).ravel()
    by_camera = sp.csc_matrix(seen_by_ties)
    rows, cols = [], []
    for j in range(num_cams):
        allowed = ~decided
        allowed[by_camera.indices[by_camera.indptr[j]:by_camera.indptr[j + 1]]] = True
        hit = np.flatnonzero(in_image(cams, j, points) & allowed)
        rows.append(hit)
        cols.append(np.full(len(hit), j))
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    seen = sp.csr_matrix((np.ones(len(rows), bool), (rows, cols)),
                         shape=(len(points), num_cams))
    return seen, decided


# -- propagation ---------------------------------------------------------------------------------

@dataclass
class DenseSigmas:
    covariances: np.ndarray
    """(P, 3, 3) total covariance (NaN where fewer than min_views cameras see the point)."""
    camera_part: np.ndarray
    """(P, 3, 3) the cameras' share alone."""
    num_views: np.ndarray

    @property
    def sigmas(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(self.covariances, axis1=1, axis2=2), 0.0))

    @property
    def sigma_3d(self) -> np.ndarray:
        return np.sqrt(np.trace(self.covariances, axis1=1, axis2=2).clip(min=0))


def jacobians(cams: CameraSet, k: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A (P,2,3), B (P,2,6)): pixel derivatives w.r.t. the point and camera k's X0, Y0, Z0,
    omega, phi, kappa (pinhole part)."""
    fx, fy = _focal(cams.cameras[k])
    cam_from_world = PHOTO @ cams.rotations[k].T
    d = points - cams.centres[k]
    xc = d @ cam_from_world.T
    z = xc[:, 2]
    j = np.zeros((len(points), 2, 3))
    j[:, 0, 0] = fx / z
    j[:, 0, 2] = -fx * xc[:, 0] / z ** 2
    j[:, 1, 1] = fy / z
    j[:, 1, 2] = -fy * xc[:, 1] / z ** 2
    a = j @ cam_from_world
    b = np.empty((len(points), 2, 6))
    b[:, :, :3] = -a
    for m, dr in enumerate(_rotation_derivatives(cams.angles[k])):
        dxc = d @ (PHOTO @ dr.T).T  # d(xc)/d(angle m)
        b[:, :, 3 + m] = np.einsum("pij,pj->pi", j, dxc)
    return a, b


def propagate(cams: CameraSet, points: np.ndarray, seen: sp.csr_matrix,
              options: DenseOptions) -> DenseSigmas:
    """Sigma_X of every point from the cameras `seen` marks (module docstring)."""
    num = len(points)
    normal = np.zeros((num, 3, 3))
    middle = np.zeros((num, 3, 3))
    seen = sp.csc_matrix(seen)
    for k in range(len(cams.names)):
        rows = seen.indices[seen.indptr[k]:seen.indptr[k + 1]]
        if not len(rows):
            continue
        a, b = jacobians(cams, k, points[rows])
        normal[rows] += np.einsum("pji,pjk->pik", a, a)
        atb = np.einsum("pji,pjk->pik", a, b)  # A^T B (P,3,6)
        middle[rows] += atb @ cams.covariances[k] @ np.transpose(atb, (0, 2, 1))
    views = np.asarray(seen.sum(axis=1)).ravel().astype(np.int64)
    cov = np.full((num, 3, 3), np.nan)
    cam_part = np.full((num, 3, 3), np.nan)
    ok = views >= options.min_views
    if np.any(ok):
        inverse = np.linalg.inv(normal[ok])
        cam_part[ok] = inverse @ middle[ok] @ inverse
        cov[ok] = options.sigma_image ** 2 * inverse + cam_part[ok]
    return DenseSigmas(cov, cam_part, views)


def count_sigma(tie_sigma_3d: np.ndarray, tie_views: np.ndarray, dense_views: np.ndarray,
                degree: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Mulder 4.4.1: a polynomial through the median tie point sigma_3d per number of views,
    evaluated at each dense point's number of views (clamped to the tie points' range). Returns
    (sigma per dense point, polynomial coefficients, highest power first)."""
    counts = np.unique(tie_views)
    medians = np.array([np.median(tie_sigma_3d[tie_views == c]) for c in counts])
    degree = min(degree, len(counts) - 1)
    coefficients = np.polyfit(counts.astype(float), medians, degree)
    x = np.clip(dense_views, counts.min(), counts.max()).astype(float)
    return np.polyval(coefficients, x), coefficients


# -- planes --------------------------------------------------------------------------------------

@dataclass
class PlaneOptions:
    inlier_distance: float = 0.1
    """Model units (m): inlier distance of a point to a plane."""
    normal_angle: float = 20.0
    """Degrees: a point's normal (from its `normal_neighbours` nearest points) must be this
    close to the plane's (Mulder: 6 neighbours)."""
    normal_neighbours: int = 7
    min_inliers: int = 50
    """Planes with fewer inliers end the extraction."""
    max_planes: int = 20
    max_trials: int = 2000
    confidence: float = 0.999


@dataclass
class DensePlane:
    normal: np.ndarray
    offset: float
    inliers: np.ndarray
    """Indices into the input points."""


def extract_planes(points: np.ndarray, weights: np.ndarray | None, options: PlaneOptions,
                   rng: np.random.Generator) -> list[DensePlane]:
    """Planes one after another; each plane's inliers leave the cloud."""
    msac = replace(AssignmentOptions(), msac_max_trials=options.max_trials,
                   msac_confidence=options.confidence, msac_sample_points=20000,
                   msac_point_normal_angle=options.normal_angle)
    normals = point_normals(points, options.normal_neighbours) if len(points) > 3 else None
    remaining = np.arange(len(points))
    planes: list[DensePlane] = []
    while len(planes) < options.max_planes and len(remaining) >= options.min_inliers:
        found = msac_plane(points[remaining], options.inlier_distance, msac, rng,
                           weights=None if weights is None else weights[remaining],
                           normals_of_points=None if normals is None else normals[remaining])
        if found is None:
            break
        normal, offset, inliers = found
        if np.count_nonzero(inliers) < options.min_inliers:
            break
        planes.append(DensePlane(normal, offset, remaining[inliers]))
        remaining = remaining[~inliers]
    return planes


# -- files ---------------------------------------------------------------------------------------

_PLY_TYPES = {"char": "i1", "uchar": "u1", "int8": "i1", "uint8": "u1", "short": "i2",
              "ushort": "u2", "int16": "i2", "uint16": "u2", "int": "i4", "uint": "u4",
              "int32": "i4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}


def read_ply_vertices(path) -> np.ndarray:
    """The vertex element of a PLY file (ascii or binary) as a structured array (COLMAP's
    fused.ply: x y z nx ny nz red green blue)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise InputError("PLY file does not exist", path) from None
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file", path)
    header = raw[:end].decode("ascii", "replace").splitlines()
    body = raw[raw.index(b"\n", end) + 1:]
    fmt, count, fields, element = None, 0, [], None
    for line in header:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            element = parts[1]
            if element == "vertex":
                count = int(parts[2])
            elif not fields:
                raise InputError("PLY: the vertex element must come first", path)
        elif parts[0] == "property" and element == "vertex":
            if parts[1] == "list" or parts[1] not in _PLY_TYPES:
                raise InputError(f"PLY: unsupported vertex property {line!r}", path)
            fields.append((parts[2], _PLY_TYPES[parts[1]]))
    if not {"x", "y", "z"} <= {name for name, _ in fields}:
        raise InputError("PLY vertices need x, y, z", path)
    if fmt == "ascii":
        text = body.decode("ascii", "replace").split("\n")[:count]
        values = np.loadtxt(text, ndmin=2) if count else np.zeros((0, len(fields)))
        out = np.empty(count, [(n, t) for n, t in fields])
        for k, (name, _) in enumerate(fields):
            out[name] = values[:, k]
        return out
    order = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
    if order is None:
        raise InputError(f"PLY: unknown format {fmt!r}", path)
    dtype = np.dtype([(n, order + t) for n, t in fields])
    if len(body) < count * dtype.itemsize:
        raise InputError("PLY file is shorter than its header says", path)
    return np.frombuffer(body, dtype, count).copy()


def read_image_covariances(path) -> dict[str, np.ndarray]:
    """Per image name the 6 x 6 covariance of X0, Y0, Z0 (m), omega, phi, kappa (rad):
    refine's image_covariance.csv (21 upper-triangle entries) or image_precision.csv (sigmas
    only: a diagonal covariance)."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except FileNotFoundError:
        raise InputError("image covariance file does not exist", path) from None
    out = {}
    upper = np.triu_indices(6)
    try:
        for row in rows:
            if "c00" in row:
                cov = np.zeros((6, 6))
                cov[upper] = [float(row[f"c{i}{j}"]) for i, j in zip(*upper)]
                cov = cov + np.triu(cov, 1).T
            else:
                sigma = np.array([float(row[k]) for k in ("sigma_X0_m", "sigma_Y0_m",
                                                         "sigma_Z0_m")]
                                 + [math.radians(float(row[k])) for k in (
                                     "sigma_omega_deg", "sigma_phi_deg", "sigma_kappa_deg")])
                cov = np.diag(sigma ** 2)
            out[row["name"]] = cov
    except (KeyError, ValueError) as error:
        raise InputError(f"not an image_covariance.csv / image_precision.csv: {error}",
                         path) from None
    if not out:
        raise InputError("no image in the covariance file", path)
    return out


# -- the command ---------------------------------------------------------------------------------

@dataclass
class DenseQualityResult:
    output: Path
    num_points: int
    num_with_sigma: int
    median_sigma: np.ndarray
    median_views: float
    planes: dict = field(default_factory=dict)

    def summary(self) -> str:
        s = self.median_sigma
        return (f"dense quality: {self.num_with_sigma} of {self.num_points} point(s) with a "
                f"sigma (median views {self.median_views:.0f}); median sigma X {s[0]:.4f}, "
                f"Y {s[1]:.4f}, Z {s[2]:.4f}; written to {self.output}"
                + "".join(f"; {name}: {p['planes']} plane(s), {100 * p['inlier_share']:.1f} % "
                          "of the points on them" for name, p in self.planes.items()))


def main(input_path, ply, image_covariance, output, *, tie_point_precision=None,
         options: DenseOptions | None = None, planes: PlaneOptions | None = None,
         seed: int = 0) -> DenseQualityResult:
    """Sigma of every point of the dense cloud `ply` (same frame as the model `input_path`)
    from the cameras' covariances; written as PLY scalar fields to `output`. With `planes`,
    planes are extracted twice, weighted by 1 / sigma_3d^2 and unweighted (points without a
    sigma left out), and each point's plane number (-1: none) written too."""
    from ..files import write_point_ply
    from .report import sigma_colours

    options = options or DenseOptions()
    try:
        rec = pycolmap.Reconstruction(str(input_path))
    except Exception as error:
        raise InputError(f"cannot read COLMAP model: {error}", input_path) from None
    cams = camera_set(rec, read_image_covariances(image_covariance))
    vertices = read_ply_vertices(ply)
    points = np.c_[vertices["x"], vertices["y"], vertices["z"]].astype(np.float64)
    seen, decided = visibility(rec, cams, points, options)
    result = propagate(cams, points, seen, options)
    sigma = result.sigmas
    scalars = {"sigma_x": sigma[:, 0], "sigma_y": sigma[:, 1], "sigma_z": sigma[:, 2],
               "sigma_3d": result.sigma_3d,
               "sigma_3d_cameras": np.sqrt(np.trace(result.camera_part, axis1=1, axis2=2)),
               "num_views": result.num_views.astype(np.float32),
               "visibility_tie_points": decided.astype(np.float32)}
    if tie_point_precision is not None:
        ties = read_ply_vertices(tie_point_precision)
        scalars["sigma_3d_count"], _ = count_sigma(
            np.asarray(ties["sigma_3d"], float), np.asarray(ties["num_images"]).astype(int),
            result.num_views, options.polynomial_degree)
    plane_summary = {}
    if planes is not None:
        usable = np.flatnonzero(np.isfinite(result.sigma_3d))
        centre = points[usable].mean(0) if len(usable) else np.zeros(3)
        for name, weights in (("weighted", 1.0 / result.sigma_3d[usable] ** 2),
                              ("unweighted", None)):
            found = extract_planes(points[usable] - centre, weights, planes,
                                   np.random.default_rng(seed))
            label = np.full(len(points), -1.0, np.float32)
            for k, plane in enumerate(found):
                label[usable[plane.inliers]] = k
            scalars[f"plane_{name}"] = label
            plane_summary[name] = {"planes": len(found),
                                   "inlier_share": float(np.mean(label[usable] >= 0))
                                   if len(usable) else 0.0}
    if all(n in vertices.dtype.names for n in ("red", "green", "blue")):
        rgb = np.c_[vertices["red"], vertices["green"], vertices["blue"]].astype(np.uint8)
    else:
        finite = np.where(np.isfinite(result.sigma_3d), result.sigma_3d, 0.0)
        rgb = sigma_colours(finite)
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_point_ply(output, points, rgb, {k: np.asarray(v, np.float32)
                                          for k, v in scalars.items()})
    ok = np.isfinite(result.sigma_3d)
    median = np.nanmedian(sigma[ok], axis=0) if np.any(ok) else np.full(3, np.nan)
    return DenseQualityResult(output, len(points), int(ok.sum()), median,
                              float(np.median(result.num_views)) if len(points) else 0.0,
                              plane_summary)
