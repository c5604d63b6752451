"""Georegistration from the city model alone: no GNSS, a location hint and a search radius.

A block without GNSS (frames cut from a video, photos without EXIF, a drone whose GNSS failed)
still carries the city's signature: walls at right angles and known distances, roofs, street
widths. The search finds the similarity (scale, rotation, translation) that puts the most tie
points on the model within `radius` of the hint:

1. vertical: the tie points' planes are walls (vertical) or level (ground, flat roofs), the
   cameras are upright (their image x axes horizontal, their image "up" above the horizon);
2. yaw: the normals of the tie points' walls, turned towards the cameras that see them, must
   be outward normals of model walls near the hint (a histogram of matching angles);
3. scale and horizontal position: for each yaw and each scale of a logarithmic grid (the SfM
   scale is arbitrary; plausible viewing distances bound it) the tie points' walls and roofs,
   seen from above, are correlated (FFT) with the model's walls and roofs around the hint:
   the best shifts within the radius are hypotheses;
4. height, then 3D: each of the best hypotheses gets its height by the share of tie points
   near the model's surfaces (align.coarse's objective), is refined by a few rounds of
   tie points to their nearest faces and a similarity to those planes, and is scored again;
5. the best placement and the best *distinct* one (another place or heading) are compared:
   a block that fits two places about equally well is ambiguous and fails
   (`AmbiguousLocationError`), as does one that fits nowhere well.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..citymodel.store import PlaneStore
from ..errors import GeoregistrationError

logger = logging.getLogger(__name__)


class ModelOnlyFailure(GeoregistrationError):
    """A block registered from the model alone that the model cannot hold: the verdict is
    "failed" (exit 3, report.json only); `report` holds what the search found."""

    exit_code = 3

    def __init__(self, message: str, report: dict, path=None):
        super().__init__(message, path)
        self.report = report


class AmbiguousLocationError(ModelOnlyFailure):
    """Two distinct placements of the block fit the model about equally well."""


@dataclass
class LocateOptions:
    """Tolerances of the search (one place)."""

    radius: float = 100.0
    """Metres around the hint within which the block's centre is searched (--location_radius)."""
    cell: float = 2.0
    """Metres per cell of the 2D correlation of the block's walls and roofs with the model."""
    scale_step: float = 0.04
    """Relative step of the scale grid (4 %: 1.6 m at the ends of an 80 m block)."""
    viewing_distance: tuple[float, float] = (5.0, 250.0)
    """Plausible median distance (m) from a tie point to the nearest camera: bounds the scale
    (below 5 m a block shrunk into a corner of the model fits as well as the true one)."""
    yaw_candidates: int = 12
    """Headings (peaks of the wall-normal histogram) searched."""
    hypotheses: int = 60
    """Placements (the best distinct ones after the height search) refined in 3D."""
    distinct_m: float = 5.0
    """A runner-up placement counts as distinct when its block centre (the cameras' mean) lies
    this far from the best one's..."""
    distinct_deg: float = 10.0
    """...or its heading differs by this much."""
    max_ratio: float = 0.85
    """Runner-up over best score above this: the block fits two places (ambiguous, failed)."""
    min_share: float = 0.2
    """Best score (smooth share of tie points within 0.5 m of the model) below this: the block
    fits nowhere near the hint (failed)."""
    max_points: int = 4000
    """Tie points of the 2D correlation and of the 3D scores (a random subset)."""
    seed: int = 0
    """Of the random subsets and the plane segmentation."""


@dataclass
class Location:
    """Result: `sim3` maps the input reconstruction's frame to the store's local frame."""

    sim3: pycolmap.Sim3d
    score: float
    runner_up: float
    report: dict = field(default_factory=dict)


#: Planes within this angle of the vertical are walls, within it of the horizontal level.
WALL_DEG = 10.0
#: Weight of the cameras' upright orientation beside the planes' in the vertical's score.
CAMERA_WEIGHT = 0.5
#: Roll of the cameras (deg) up to which their image x axes count as horizontal.
CAMERA_ROLL_DEG = 10.0
#: The cameras' image x axes lie within this angle (RMS, deg) of the horizontal.
MAX_ROLL_DEG = 20.0
#: Kernel radii (m) of the 3D scores: height search, refinement rounds, final score.
HEIGHT_RADIUS, FIT_RADIUS, FINAL_RADIUS = 2.0, 1.0, 0.5
#: Metres below a roof from which a camera or a line of sight is inside the building.
SOLID_MARGIN = 1.0
#: Weight of the share of camera rays inside buildings against the share of tie points near
#: the model: a placement whose cameras look through walls is not the block's.
RAY_WEIGHT = 1.0
#: Weight of the share of the block's ground points under a roof (streets are not inside
#: buildings) or off the height of the buildings' feet, against the share of tie points near
#: the model.
GROUND_WEIGHT = 0.5
#: Metres the ground's median height may lie from that of the nearest building feet (a
#: street's slope and kerbs, the model's generalised feet) ...
GROUND_TOLERANCE = 1.5
#: ... within this distance (m) of it; further, only "not under a roof" is asked.
GROUND_REACH = 30.0
#: A tie point of a plane counts near a model face whose normal is within this angle (deg).
ORIENTED_DEG = 20.0
#: Tie points of the 3D refinement of each placement.
FIT_POINTS = 2000
#: Tie points of the height search of each 2D placement.
HEIGHT_POINTS = 300
#: A round of the 3D refinement may change the scale by about this much (relative; bounded at
#: 3 times it): planes alone would pull a block with partly wrong nearest faces smaller.
SCALE_SIGMA = 0.02
#: The 3D refinement changes a placement's scale by at most this (log): a placement shrinking
#: round after round is not the block's.
MAX_FIT_SCALE = 0.08
#: 2D placements per scale (over all headings) that are given a height and a 3D score.
PER_SCALE = 6


def locate(rec: pycolmap.Reconstruction, store: PlaneStore, hint_local: np.ndarray,
           options: LocateOptions | None = None) -> Location:
    """The similarity that puts `rec` onto `store` with its centre within `options.radius`
    of `hint_local` (x, y in the store's local frame). Raises GeoregistrationError when no
    placement fits, AmbiguousLocationError when two distinct ones fit about equally well."""
    from ..block.reconstruction import tie_points

    options = options or LocateOptions()
    t0 = time.perf_counter()
    hint = np.asarray(hint_local, float).reshape(-1)[:2]
    near = _model_near(store, hint, options.radius)
    _, points = tie_points(rec)
    if len(points) < 50:
        raise GeoregistrationError(f"only {len(points)} tie points: too few to find the block "
                                   "on the city model")
    block = _block(rec, points, options)
    logger.info("model-only georegistration: vertical from %d tie point planes and %d cameras "
                "(%s)", len(block.plane_counts), len(block.centres), block.vertical_cue)
    hypotheses = _search_2d(block, near, hint, options)
    if not hypotheses:
        raise GeoregistrationError(
            f"no placement of the block within {options.radius:g} m of the location hint "
            "matches the model's walls (are there walls in the tie points, is the hint right?)")
    placements = _refine_3d(block, near, hypotheses, options)
    return _decide(placements, hypotheses, block, near, hint, options,
                   time.perf_counter() - t0)


# -- the model near the hint -------------------------------------------------------------------


@dataclass
class _ModelNearHint:
    store: PlaneStore
    surface: object  # align.coarse.SurfaceDistance
    wall_angles: np.ndarray  # (F,) outward normal headings of the walls (rad)
    wall_areas: np.ndarray
    samples_wall: np.ndarray  # (K, 2) points on the walls, seen from above
    samples_roof: np.ndarray  # (K, 2) points on roofs and other faces seen from above
    z_range: tuple[float, float]  # heights of the faces tie points can lie on
    roofs: tuple  # (lower corner (2,), cell, (I, J) lowest roof height per cell, nan: none)
    feet: np.ndarray  # (K, 3) lowest corners of the walls: the ground at the buildings

    def ground_height(self, xy: np.ndarray) -> np.ndarray:
        """(N,) the height of the nearest building foot within GROUND_REACH m (nan: none)."""
        from scipy.spatial import cKDTree

        if not len(self.feet):
            return np.full(len(xy), np.nan)
        if not hasattr(self, "_feet_tree"):
            self._feet_tree = cKDTree(self.feet[:, :2])
        distance, index = self._feet_tree.query(xy[:, :2])
        return np.where(distance <= GROUND_REACH, self.feet[np.minimum(index, len(self.feet) - 1),
                                                            2], np.nan)

    def roof_above(self, xy: np.ndarray) -> np.ndarray:
        """(N,) the lowest roof height above each of the points `xy` (nan: none)."""
        lower, cell, low = self.roofs
        idx = np.floor((xy[:, :2] - lower) / cell).astype(int)
        ok = np.all((idx >= 0) & (idx < low.shape), axis=1)
        out = np.full(len(xy), np.nan)
        out[ok] = low[idx[ok, 0], idx[ok, 1]]
        return out

    def inside(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool: under a roof by more than SOLID_MARGIN, i.e. inside a building."""
        return points[:, 2] < self.roof_above(points) - SOLID_MARGIN  # nan compares False


def _model_near(store: PlaneStore, hint: np.ndarray, radius: float) -> _ModelNearHint:
    from ..citymodel.visibility import visible_triangles
    from .coarse import SurfaceDistance

    reach = 2.0 * radius + 60.0
    lower = np.array([hint[0] - reach, hint[1] - reach, -1e9])
    upper = np.array([hint[0] + reach, hint[1] + reach, 1e9])
    near = store.subset_bbox(lower, upper)
    excluded = ("GroundSurface", "ClosureSurface")
    vertices, triangles, _ = visible_triangles(near, excluded) if len(near.faces) else (
        np.zeros((0, 3)), np.zeros((0, 3), int), None)
    inside = np.zeros(0, bool)
    if len(triangles):
        centres = vertices[triangles].mean(axis=1)
        inside = np.linalg.norm(centres[:, :2] - hint, axis=1) <= radius + 20.0
    if not np.any(inside):
        origin = store.origin
        raise GeoregistrationError(
            f"the city model has no building surface within {radius:g} m of the location hint "
            f"({hint[0] + origin[0]:.1f}, {hint[1] + origin[1]:.1f}; model bbox "
            + ", ".join(f"{v:.1f}" for v in store.bbox_crs.ravel()[[0, 1, 3, 4]])
            + "): check the hint's coordinates (model CRS) and the radius", store.source)
    corners = vertices[triangles]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    areas = 0.5 * np.linalg.norm(normals, axis=1)
    normals = normals / np.maximum(2.0 * areas, 1e-12)[:, None]
    wall = np.abs(normals[:, 2]) < np.sin(np.radians(30.0))
    rng = np.random.default_rng(0)
    samples = _sample_triangles(corners, areas, 0.5, rng)
    is_wall = wall[samples[1]]
    keep_w = wall & inside & (areas > 0.5)
    up = normals[samples[1], 2] > 0.3
    return _ModelNearHint(near, SurfaceDistance(near, excluded),
                          np.arctan2(normals[keep_w, 1], normals[keep_w, 0]), areas[keep_w],
                          samples[0][is_wall, :2], samples[0][~is_wall, :2],
                          (float(corners[:, :, 2].min()), float(corners[:, :, 2].max())),
                          _roof_raster(samples[0][up]), _feet(corners[wall]))


def _feet(walls: np.ndarray) -> np.ndarray:
    """(K, 3) the lowest corners of the wall triangles: where the buildings meet the ground."""
    if not len(walls):
        return np.zeros((0, 3))
    corners = walls.reshape(-1, 3, 3)
    low = np.argmin(corners[:, :, 2], axis=1)
    return corners[np.arange(len(corners)), low]


def _roof_raster(samples: np.ndarray, cell: float = 1.0) -> tuple:
    """The lowest roof height per cell of a grid over the roof samples (nan: no roof)."""
    if not len(samples):
        return np.zeros(2), cell, np.full((1, 1), np.nan)
    lower = samples[:, :2].min(axis=0) - cell
    idx = np.floor((samples[:, :2] - lower) / cell).astype(int)
    low = np.full(idx.max(axis=0) + 2, np.inf)
    np.minimum.at(low, (idx[:, 0], idx[:, 1]), samples[:, 2])
    low[np.isinf(low)] = np.nan
    return lower, cell, low


def _sample_triangles(corners: np.ndarray, areas: np.ndarray, spacing: float, rng):
    """Points on the triangles, about one per spacing^2 (at least one each), and their
    triangle."""
    counts = np.maximum(np.rint(areas / spacing ** 2).astype(int), 1)
    owner = np.repeat(np.arange(len(corners)), counts)
    u, v = rng.random(len(owner)), rng.random(len(owner))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    a, b, c = corners[owner, 0], corners[owner, 1], corners[owner, 2]
    return a + u[:, None] * (b - a) + v[:, None] * (c - a), owner


# -- the block: vertical, planes, walls --------------------------------------------------------


@dataclass
class _LevelledBlock:
    points: np.ndarray  # (N, 3) levelled, normalised (block centre at 0, unit `unit`)
    level: np.ndarray  # (3, 3) rotation of the SfM frame that makes the vertical +z
    centre: np.ndarray  # SfM coordinates of the normalised frame's origin
    unit: float  # SfM units per normalised unit
    centres: np.ndarray  # camera centres, levelled and normalised
    wall_angles: np.ndarray  # headings of the tie point walls' normals towards the cameras
    wall_counts: np.ndarray
    channel_wall: np.ndarray  # (K, 2) wall points seen from above
    channel_roof: np.ndarray  # (K, 2) points of the other (non-ground) planes
    plane_counts: np.ndarray
    depth: float  # median distance (normalised units) from a tie point to the nearest camera
    vertical_cue: str
    rays: np.ndarray  # (M, 3) points on lines of sight from cameras to their tie points
    ground: np.ndarray  # (G, 3) tie points on the ground (level planes at the walls' feet)
    plane_points: np.ndarray  # (P, 3) tie points of the other planes
    plane_normals: np.ndarray  # (P, 3) their planes' normals
    plane_weights: np.ndarray  # (P,) summing to 1, a plane as the root of its points


def _block(rec: pycolmap.Reconstruction, points: np.ndarray, options: LocateOptions) -> _LevelledBlock:
    from scipy.spatial import cKDTree

    from ..block.reconstruction import camera_up_and_view
    from .coarse import point_cloud_planes, subsample

    ids = rec.reg_image_ids()
    centres = np.array([rec.image(i).projection_center() for i in ids])
    up, view = camera_up_and_view(rec, ids)
    right = np.cross(up, view)  # image x = (-y) x z ... x right, y down, z view: x = y cross z
    right = -right
    pts = subsample(points, 20000, options.seed)
    centre = centres.mean(axis=0)  # the block centre: the cameras' mean
    unit = float(np.sqrt(np.sum(np.var(pts, axis=0))))
    if not unit > 0:
        raise GeoregistrationError("the tie points coincide: no block to locate")
    q = (pts - centre) / unit
    normals, counts, members = point_cloud_planes(q, distance=0.006, max_planes=20,
                                                  min_points=30, with_inliers=True)
    vertical, cue = _vertical(normals, counts, right, up, view)
    level = _rotation_to_z(vertical)
    q = q @ level.T
    cams = ((centres - centre) / unit) @ level.T
    normals = normals @ level.T
    members = [m @ level.T for m in members]
    depth = float(np.median(cKDTree(cams).query(q)[0]))
    walls, roofs, angles, wall_counts, ground = _classify_planes(normals, members, cams)
    oriented = _oriented_points(normals, members, ground, options)
    if len(ground):  # the ground is scored by lying outside buildings, not near a surface
        q = q[cKDTree(ground).query(q)[0] > 1e-12]
        ground = subsample(ground, 500, options.seed)
    rays = (_ray_samples(rec, ids, options.seed) - centre) / unit @ level.T
    return _LevelledBlock(q, level, centre, unit, cams, angles, wall_counts, walls, roofs,
                          counts, depth, cue, rays, ground, *oriented)


def _oriented_points(normals, members, ground, options: LocateOptions):
    """The tie points of the planes but the ground, each with its plane's normal (a random
    subset of `options.max_points`)."""
    keep = [k for k, m in enumerate(members)
            if not (len(ground) and np.any(np.all(m[:1] == ground, axis=1)))]
    if not keep:
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    points = np.vstack([members[k] for k in keep])
    point_normals = np.vstack([np.tile(normals[k], (len(members[k]), 1)) for k in keep])
    plane = np.concatenate([np.full(len(members[k]), j) for j, k in enumerate(keep)])
    rng = np.random.default_rng(options.seed + 2)
    pick = (np.arange(len(points)) if len(points) <= options.max_points else
            rng.choice(len(points), options.max_points, replace=False))
    # A plane weighs as the square root of its points: the walls' heights fix the scale that
    # roofs of many points, shrunk onto one flat roof, would not; small planes (eaves,
    # balconies the model lacks) do not outweigh the facades.
    weights = 1.0 / np.sqrt(np.bincount(plane[pick]))[plane[pick]]
    return points[pick], point_normals[pick], weights / weights.sum()


def _ray_samples(rec: pycolmap.Reconstruction, ids, seed: int, images: int = 150,
                 per_image: int = 12) -> np.ndarray:
    """Points on the lines of sight from cameras to tie points they see (the camera itself
    and 30, 60, 85 % of the way): free space, outside every building."""
    rng = np.random.default_rng(seed)
    chosen = ids if len(ids) <= images else rng.choice(ids, images, replace=False)
    out = []
    for image_id in chosen:
        image = rec.image(int(image_id))
        seen = [p.point3D_id for p in image.points2D if p.has_point3D()]
        if not seen:
            continue
        pick = rng.choice(seen, min(per_image, len(seen)), replace=False)
        xyz = np.array([rec.point3D(int(i)).xyz for i in pick])
        centre = image.projection_center()
        out += [centre[None, :]] + [centre + f * (xyz - centre) for f in (0.3, 0.6, 0.85)]
    return np.vstack(out) if out else np.zeros((0, 3))


def _vertical(normals: np.ndarray, counts: np.ndarray, right: np.ndarray, up: np.ndarray,
              view: np.ndarray) -> tuple[np.ndarray, str]:
    """The up direction in the SfM frame: tie point planes vertical or level, camera x axes
    horizontal, image "up" above the horizon, the mean view not rising above 20 deg."""
    candidates = _fibonacci_sphere(20000)
    mean_up, mean_view = up.mean(axis=0), view.mean(axis=0)
    mean_view /= max(np.linalg.norm(mean_view), 1e-12)
    allowed = (candidates @ mean_up > 0) & (candidates @ mean_view < np.sin(np.radians(20)))
    # Cameras held about upright: the image x axes lie within MAX_ROLL_DEG of the horizontal
    # (RMS). Sloped roofs of one pitch can make a block on its side fit the planes better.
    upright = np.mean((right @ candidates.T) ** 2, axis=0) < np.sin(np.radians(MAX_ROLL_DEG)) ** 2
    if np.any(allowed & upright):
        allowed &= upright
    candidates = candidates[allowed] if np.any(allowed) else candidates

    def score(v: np.ndarray) -> np.ndarray:
        s = np.zeros(len(v))
        if len(normals):
            c = np.abs(normals @ v.T)  # (K, M)
            close = np.maximum(c, np.sqrt(np.clip(1 - c ** 2, 0, 1)))
            u = np.clip((1 - close) / (1 - np.cos(np.radians(4.0))), 0, 1)
            s += (counts @ (1 - u) ** 2) / counts.sum()
        roll = (right @ v.T) ** 2 / np.sin(np.radians(CAMERA_ROLL_DEG)) ** 2
        return s + CAMERA_WEIGHT * np.mean(np.clip(1 - roll, 0, 1), axis=0)

    best = candidates[int(np.argmax(score(candidates)))]
    for reach in (3.0, 0.6):  # local refinement on finer grids
        a, b = _tangent_basis(best)
        steps = np.radians(np.linspace(-reach, reach, 21))
        da, db = np.meshgrid(steps, steps)
        local = best + da.reshape(-1, 1) * a + db.reshape(-1, 1) * b
        local /= np.linalg.norm(local, axis=1, keepdims=True)
        best = local[int(np.argmax(score(local)))]
    eig = np.linalg.eigvalsh(right.T @ right / len(right))
    cue = ("cameras upright and tie point planes" if eig[1] > 0.05 else
           "tie point planes about the cameras' common x axis")
    return best, cue


def _fibonacci_sphere(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    r = np.sqrt(1 - z ** 2)
    phi = np.pi * (1 + 5 ** 0.5) * k
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _tangent_basis(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a = np.cross(v, [1.0, 0, 0] if abs(v[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    return a, np.cross(v, a)


def _rotation_to_z(v: np.ndarray) -> np.ndarray:
    """A rotation taking the unit vector `v` to +z."""
    a, b = _tangent_basis(v)
    return np.vstack([a, b, v])


def _classify_planes(normals, members, cams):
    """Wall points, points of level and sloped planes above the ground, and the walls' normal
    headings turned towards the cameras nearest to each wall."""
    sin_wall = np.sin(np.radians(WALL_DEG))
    is_wall = np.abs(normals[:, 2]) < sin_wall if len(normals) else np.zeros(0, bool)
    walls, others, angles, counts, ground = [], [], [], [], []
    foot = (np.median([np.percentile(m[:, 2], 10) for m, w in zip(members, is_wall) if w])
            if np.any(is_wall) else -np.inf)
    for normal, m, wall in zip(normals, members, is_wall):
        if wall:
            centroid = m.mean(axis=0)
            nearest = np.argsort(np.linalg.norm(cams - centroid, axis=1))[:max(3, len(cams) // 4)]
            n = normal * np.sign((cams[nearest].mean(axis=0) - centroid) @ normal or 1.0)
            angles.append(np.arctan2(n[1], n[0]))
            counts.append(len(m))
            walls.append(m[:, :2])
        elif abs(normal[2]) > np.cos(np.radians(WALL_DEG)) and np.median(m[:, 2]) <= foot:
            ground.append(m)  # the ground: not in the model, not under a roof
        else:
            others.append(m[:, :2])
    stack = (lambda parts, d=2: np.vstack(parts) if parts else np.zeros((0, d)))
    return (stack(walls), stack(others), np.array(angles), np.array(counts, float),
            stack(ground, 3))


# -- 2D search: heading, scale, horizontal position -------------------------------------------


@dataclass
class _Hypothesis:
    score: float
    yaw: float  # rad
    scale: float  # metres per normalised unit
    shift: np.ndarray  # (2,) local frame position of the block's normalised origin
    z: float = 0.0
    sim3: pycolmap.Sim3d | None = None  # levelled-normalised block -> local, after 3D
    share: float = 0.0


def _yaws(block: _LevelledBlock, model: _ModelNearHint, options: LocateOptions) -> np.ndarray:
    """Headings that turn the tie point walls' normals onto model wall normals (histogram
    peaks); all of a circle's grid when the block shows no wall."""
    grid = np.radians(np.arange(0.0, 360.0, 0.5))
    if not len(block.wall_angles) or not len(model.wall_angles):
        return np.radians(np.arange(0.0, 360.0, 10.0))
    sigma = np.radians(3.0)
    diff = (grid[:, None, None] + block.wall_angles[None, :, None]
            - model.wall_angles[None, None, :])
    diff = (diff + np.pi) % (2 * np.pi) - np.pi
    weights = block.wall_counts[None, :, None] * np.sqrt(model.wall_areas)[None, None, :]
    hist = np.sum(weights * np.exp(-0.5 * (diff / sigma) ** 2), axis=(1, 2))
    peaks = [k for k in range(len(grid))
             if hist[k] >= hist[k - 1] and hist[k] >= hist[(k + 1) % len(grid)]]
    peaks.sort(key=lambda k: -hist[k])
    chosen: list[float] = []
    for k in peaks:
        if all(abs((grid[k] - c + np.pi) % (2 * np.pi) - np.pi) > np.radians(5) for c in chosen):
            chosen.append(grid[k])
        if len(chosen) == options.yaw_candidates:
            break
    return np.array(chosen)


def _scales(block: _LevelledBlock, options: LocateOptions) -> np.ndarray:
    """Metres per normalised unit: viewing distances within `viewing_distance`, the block no
    wider than the search area."""
    low, high = options.viewing_distance
    lo, hi = low / block.depth, high / block.depth
    extent = float(np.max(np.linalg.norm(block.points[:, :2], axis=1)))
    hi = min(hi, (options.radius + 60.0) / max(extent, 1e-9))
    if hi <= lo:
        hi = lo * 1.5
    n = int(np.ceil(np.log(hi / lo) / np.log1p(options.scale_step))) + 1
    return lo * (1 + options.scale_step) ** np.arange(n)


def _search_2d(block: _LevelledBlock, model: _ModelNearHint, hint: np.ndarray, options: LocateOptions
               ) -> list[_Hypothesis]:
    """Correlate the block's walls and roofs seen from above with the model's for each
    heading and scale; the best distinct shifts within the radius."""
    from scipy import fft, ndimage

    cell = options.cell
    rng = np.random.default_rng(options.seed)
    walls = _subset(block.channel_wall, options.max_points, rng)
    roofs = _subset(block.channel_roof, options.max_points // 2, rng)
    if not len(walls) and not len(roofs):
        return []
    total = len(walls) + 0.5 * len(roofs)
    scales = _scales(block, options)
    extent = float(np.max(np.linalg.norm(np.vstack([walls, roofs]), axis=1)))
    half = int(np.ceil(scales[-1] * extent / cell)) + 2
    lower = hint - options.radius - scales[-1] * extent - 4 * cell
    size_map = int(np.ceil((2 * (options.radius + scales[-1] * extent) + 8 * cell) / cell))
    n = fft.next_fast_len(size_map + half + 2, real=True)
    maps = []
    for samples in (model.samples_wall, model.samples_roof):
        image = np.zeros((n, n))
        idx = np.floor((samples - lower) / cell).astype(int)
        ok = np.all((idx >= 0) & (idx < size_map), axis=1)
        np.add.at(image, (idx[ok, 0], idx[ok, 1]), 1.0)
        image = ndimage.gaussian_filter(np.minimum(image, 1.0), 0.7)
        maps.append(fft.rfft2(image / max(image.max(), 1e-12)))
    # Shifts of the block's origin allowed: within the radius of the hint.
    ax = lower[0] + cell * (np.arange(n) + 0.5)
    ay = lower[1] + cell * (np.arange(n) + 0.5)
    allowed = ((ax[:, None] - hint[0]) ** 2 + (ay[None, :] - hint[1]) ** 2
               <= options.radius ** 2)
    found: list[_Hypothesis] = []
    yaws = _yaws(block, model, options)
    for yaw in yaws:
        c, s = np.cos(yaw), np.sin(yaw)
        turn = np.array([[c, -s], [s, c]])
        for scale in scales:
            spectrum = 0
            for points, channel, weight in ((walls, maps[0], 1.0), (roofs, maps[1], 0.5)):
                if not len(points):
                    continue
                xy = scale * points @ turn.T
                idx = np.floor(xy / cell + 0.5).astype(int) % n
                image = np.zeros((n, n))
                np.add.at(image, (idx[:, 0], idx[:, 1]), weight / total)
                spectrum = spectrum + np.conj(fft.rfft2(image)) * channel
            corr = fft.irfft2(spectrum, s=(n, n))
            corr[~allowed] = -1.0
            found += _peaks(corr, ax, ay, yaw, scale, PER_SCALE)
    logger.info("model-only georegistration: %d headings x %d scales (%.3g-%.3g m per unit) "
                "correlated, best 2D score %.2f", len(yaws), len(scales), scales[0],
                scales[-1], max((h.score for h in found), default=float("nan")))
    # Seen from above, a block shrunk onto one building fits as well as the true one: the
    # best of every scale go on to the 3D score, not the best overall.
    chosen = []
    for scale in scales:
        of_scale = sorted((h for h in found if h.scale == scale), key=lambda h: -h.score)
        chosen += of_scale[:PER_SCALE]
    return chosen


def _subset(points: np.ndarray, n: int, rng) -> np.ndarray:
    return points if len(points) <= n else points[rng.choice(len(points), n, replace=False)]


def _peaks(corr: np.ndarray, ax, ay, yaw: float, scale: float, count: int):
    from scipy import ndimage

    local = (corr == ndimage.maximum_filter(corr, size=5)) & (corr > 0)
    idx = np.flatnonzero(local)
    idx = idx[np.argsort(-corr.ravel()[idx])[:count]]
    i, j = np.unravel_index(idx, corr.shape)
    return [_Hypothesis(float(corr[a, b]), float(yaw), float(scale), np.array([ax[a], ay[b]]))
            for a, b in zip(i, j)]


def _distinct(found: list[_Hypothesis], count: int, metres: float, radians: float,
              log_scale: float) -> list[_Hypothesis]:
    kept: list[_Hypothesis] = []
    for h in found:
        if all(np.linalg.norm(h.shift - k.shift) > metres
               or abs((h.yaw - k.yaw + np.pi) % (2 * np.pi) - np.pi) > radians
               or abs(np.log(h.scale / k.scale)) > log_scale for k in kept):
            kept.append(h)
        if len(kept) == count:
            break
    return kept


# -- 3D: height, refinement, score -------------------------------------------------------------


def _as_sim3(yaw: float, scale: float, shift: np.ndarray) -> pycolmap.Sim3d:
    c, s = np.cos(yaw), np.sin(yaw)
    rotation = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), np.asarray(shift, float))


def _apply(sim3: pycolmap.Sim3d, points: np.ndarray) -> np.ndarray:
    matrix = np.asarray(sim3.matrix())
    return points @ matrix[:, :3].T + matrix[:, 3]


def _share(model: _ModelNearHint, points: np.ndarray, radius: float) -> float:
    from .coarse import near_share

    return near_share(model.surface(points, radius), radius)


def _score(model: _ModelNearHint, block: _LevelledBlock, sim3: pycolmap.Sim3d,
           points: np.ndarray, radius: float) -> float:
    """Share of tie points near the model less RAY_WEIGHT x the share of ray samples inside
    buildings."""
    inside = model.inside(_apply(sim3, block.rays)).mean() if len(block.rays) else 0.0
    share = (_oriented_share(model, block, sim3, radius) if len(block.plane_points)
             else _share(model, _apply(sim3, points), radius))
    return (share - RAY_WEIGHT * float(inside)
            - GROUND_WEIGHT * _ground_under_roofs(model, block, sim3))


def _oriented_share(model: _ModelNearHint, block: _LevelledBlock, sim3, radius: float
                    ) -> float:
    """Smooth share of the tie points of planes that lie within `radius` of a model face
    whose normal is within ORIENTED_DEG of their plane's: scale-fair, where the share near any
    surface favours a block shrunk into a corner of the model."""
    moved = _apply(sim3, block.plane_points)
    normals = block.plane_normals @ np.asarray(sim3.rotation.matrix()).T
    faces, distance = model.store.closest_faces(moved, radius)
    ok = faces >= 0
    agree = np.zeros(len(moved), bool)
    agree[ok] = np.abs(np.einsum("ij,ij->i", normals[ok], model.store.normals[faces[ok]])) \
        > np.cos(np.radians(ORIENTED_DEG))
    u = np.clip(np.abs(np.nan_to_num(distance, nan=radius)) / radius, 0, 1)
    return float(np.sum(((1 - u * u) ** 2 * block.plane_weights)[agree]))


def _ground_under_roofs(model: _ModelNearHint, block: _LevelledBlock, sim3) -> float:
    """`_off_ground` of the placement `sim3`."""
    if not len(block.ground):
        return 0.0
    return float(_off_ground(model, _apply(sim3, block.ground), np.zeros(1))[0])


def _off_ground(model: _ModelNearHint, ground: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """(Z,) for the ground points shifted up by each of `zs`: the share of them under a roof
    (in plan), plus up to 1 as the ground's median height leaves that of the nearest
    building feet by GROUND_TOLERANCE to twice it (a street on a roof, or in the air)."""
    under = float(np.mean(np.isfinite(model.roof_above(ground))))
    foot = model.ground_height(ground)
    known = np.isfinite(foot)
    if not np.any(known):
        return np.full(len(zs), under)
    offset = float(np.median(ground[known, 2] - foot[known])) + zs
    return under + np.clip((np.abs(offset) - GROUND_TOLERANCE) / GROUND_TOLERANCE, 0.0, 1.0)


def _refine_3d(block: _LevelledBlock, model: _ModelNearHint, hypotheses: list[_Hypothesis],
               options: LocateOptions) -> list[_Hypothesis]:
    """Height by the share of tie points near the model, then rounds of nearest faces and a
    similarity to their planes; each scored by the share within FINAL_RADIUS."""
    rng = np.random.default_rng(options.seed + 1)
    points = _subset(block.points, options.max_points, rng)
    few = points[:HEIGHT_POINTS]
    for h in hypotheses:
        moved = _apply(_as_sim3(h.yaw, h.scale, np.r_[h.shift, 0.0]), few)
        zs = np.arange(model.z_range[0] - moved[:, 2].max() - 5.0,
                       model.z_range[1] - moved[:, 2].min() + 5.0, 1.0)
        if not len(zs):
            continue
        stack = (moved[None, :, :] + zs[:, None, None] * [0, 0, 1.0]).reshape(-1, 3)
        u = np.clip(model.surface(stack, HEIGHT_RADIUS).reshape(len(zs), -1) / HEIGHT_RADIUS,
                    0, 1)
        shares = np.mean((1 - u * u) ** 2, axis=1)
        if len(block.rays):
            rays = _apply(_as_sim3(h.yaw, h.scale, np.r_[h.shift, 0.0]), block.rays)
            limit = model.roof_above(rays) - SOLID_MARGIN
            inside = rays[None, :, 2] + zs[:, None] < limit[None, :]
            shares = shares - RAY_WEIGHT * inside.mean(axis=1)
        if len(block.ground):
            ground = _apply(_as_sim3(h.yaw, h.scale, np.r_[h.shift, 0.0]), block.ground)
            shares = shares - GROUND_WEIGHT * _off_ground(model, ground, zs)
        h.z, h.share = float(zs[int(np.argmax(shares))]), float(shares.max())
    ranked = sorted(hypotheses, key=lambda h: -h.share)
    ranked = _distinct(ranked, options.hypotheses, 3.0, np.radians(5.0), 0.06)
    out = []
    for h in ranked:
        sim3 = _fit_to_planes(_as_sim3(h.yaw, h.scale, np.r_[h.shift, h.z]),
                              points[:FIT_POINTS], model)
        out.append(_Hypothesis(h.score, h.yaw, h.scale, h.shift, h.z, sim3,
                               _score(model, block, sim3, points, FINAL_RADIUS)))
    out.sort(key=lambda h: -h.share)
    return out


def _fit_to_planes(sim3: pycolmap.Sim3d, points: np.ndarray, model: _ModelNearHint,
                   thresholds=(3.0, 2.0, 1.0, 1.0, 0.6), max_scale: float | None = None
                   ) -> pycolmap.Sim3d:
    """A few rounds: each tie point to its nearest face (within `thresholds`, m), a
    similarity to those planes (robust); kept only while the share near the model grows and
    the scale stays within `max_scale` (log; default MAX_FIT_SCALE) of the start."""
    from .initial_alignment import similarity_to_planes

    max_scale = MAX_FIT_SCALE if max_scale is None else max_scale
    store = model.store
    best, best_share = sim3, _share(model, _apply(sim3, points), FIT_RADIUS)
    for threshold in thresholds:
        moved = _apply(best, points)
        faces, _ = store.closest_faces(moved, threshold)
        ok = faces >= 0
        if ok.sum() < 20:
            break
        fit = similarity_to_planes(moved[ok], store.normals[faces[ok]],
                                   store.offsets[faces[ok]], 0.3, max_iterations=20,
                                   scale_sigma=SCALE_SIGMA)
        candidate = fit.sim3 * best
        if abs(np.log(candidate.scale / sim3.scale)) > max_scale:  # the scale grid's job
            break
        share = _share(model, _apply(candidate, points), FIT_RADIUS)
        if share <= best_share:
            break
        best, best_share = candidate, share
    return best


# -- decision ----------------------------------------------------------------------------------


def _apart(sim3: pycolmap.Sim3d, centre: np.ndarray, heading: float, cameras: np.ndarray
           ) -> tuple[float, float]:
    """How far (m, in plan) and how much turned (deg) the placement `sim3` puts the mean
    of `cameras` from `centre`, and its heading from `heading`."""
    other = _apply(sim3, cameras).mean(axis=0)
    turn = abs((_heading(sim3) - heading + 180.0) % 360.0 - 180.0)
    return float(np.linalg.norm(other[:2] - centre[:2])), float(turn)


def _decide(placements: list[_Hypothesis], hypotheses: list[_Hypothesis],
            block: _LevelledBlock, model: _ModelNearHint, hint: np.ndarray,
            options: LocateOptions, seconds: float) -> Location:
    if not placements:
        raise GeoregistrationError("no placement of the block near the location hint could be "
                                   "given a height on the model")
    best = placements[0]
    points = block.points[:FIT_POINTS]
    cameras = block.centres
    centre = _apply(best.sim3, cameras).mean(axis=0)  # the block's centre: its cameras' mean
    heading = _heading(best.sim3)
    runner = None
    for h in placements[1:]:
        offset, turn = _apart(h.sim3, centre, heading, cameras)
        if offset <= options.distinct_m and turn <= options.distinct_deg:
            continue
        # A placement the best one's own, half-way there (scale or shift not settled), is no
        # alternative: refitted with the scale free it joins the best.
        refit = _fit_to_planes(h.sim3, points, model, (4.0, 3.0, 2.0, 2.0, 1.0, 1.0, 0.6),
                               max_scale=0.5)
        if all(a <= b for a, b in zip(_apart(refit, centre, heading, cameras),
                                      (options.distinct_m, options.distinct_deg))):
            continue
        runner = (h, offset, turn)
        break
    runner_share = max(runner[0].share, 0.0) if runner else 0.0
    ratio = runner_share / best.share if best.share > 0 else 1.0
    # The normalised levelled frame -> the input frame is undone: input -> local.
    to_block = pycolmap.Sim3d(1.0 / block.unit, pycolmap.Rotation3d(block.level),
                              -block.level @ block.centre / block.unit)
    sim3 = best.sim3 * to_block
    report = {
        "method": "model only",
        "hypotheses_2d": len(hypotheses), "hypotheses_3d": len(placements),
        "best_score": float(best.share), "runner_up_score": float(runner_share),
        "score_ratio": float(ratio),
        "runner_up_offset_m": None if runner is None else runner[1],
        "runner_up_turn_deg": None if runner is None else runner[2],
        "scale": float(sim3.scale), "heading_deg": float(heading),
        "hint_distance_m": float(np.linalg.norm(centre[:2] - hint)),
        "radius_m": float(options.radius), "vertical_cue": block.vertical_cue,
        "seconds": float(seconds),
    }
    logger.info("model-only georegistration: best share %.2f, distinct runner-up %.2f (ratio "
                "%.2f), %.1f m from the hint, scale %.4g, %.1f s", best.share, runner_share,
                ratio, report["hint_distance_m"], sim3.scale, seconds)
    if best.share < options.min_share:  # a verdict on the block, not a refusal of the input
        raise ModelOnlyFailure(
            f"the block fits nowhere within {options.radius:g} m of the location hint: at best "
            f"{100 * max(best.share, 0.0):.0f} % of its tie points lie near the model (at least "
            f"{100 * options.min_share:.0f} % needed, less where its rays would pass through "
            "roofs or its ground would lie under them); check the hint and the radius",
            {**report, "verdict": "failed"})
    if ratio > options.max_ratio:
        raise AmbiguousLocationError(
            f"the block fits two places about equally well ({100 * best.share:.0f} % and "
            f"{100 * runner_share:.0f} % of its tie points near the model, "
            f"{report['runner_up_offset_m']:.1f} m and {report['runner_up_turn_deg']:.0f} deg "
            "apart): the model alone cannot tell where it is; give a closer hint or GNSS",
            {**report, "verdict": "failed"})
    return Location(sim3, best.share, runner_share, report)


def _heading(sim3: pycolmap.Sim3d) -> float:
    rotation = np.asarray(sim3.rotation.matrix())
    return float(np.degrees(np.arctan2(rotation[1, 0], rotation[0, 0])))


# -- entry from refine -------------------------------------------------------------------------

#: GNSS whose stated horizontal sigma (median, m) exceeds this cannot put the block on the
#: model: the model-only search is used instead, around the GNSS positions' mean.
USELESS_GNSS_SIGMA = 20.0


def start_from_model(rec: pycolmap.Reconstruction, store: PlaneStore, gnss, location,
                     radius: float = 100.0):
    """Refine's start without (usable) GNSS: `location` (x, y, model CRS) or, for GNSS whose
    stated sigma exceeds USELESS_GNSS_SIGMA, the GNSS mean is the hint. GNSS whose positions
    spread too little for a similarity (a short video, a hovering drone: GNSS then fixes the
    block's position, not its heading) gives the hint too, and stays as the adjustment's priors
    (`short_baseline`). Returns (the similarity input -> model CRS, the GNSS refine is to use,
    report.json's georegistration entries), or (None, gnss, None) when GNSS registers the
    block."""
    sigma = (float(np.median(np.asarray(gnss.sigmas)[:, :2])) if gnss is not None
             and len(gnss.positions) else None)
    useless = sigma is not None and sigma > USELESS_GNSS_SIGMA
    short = False
    if gnss is not None and not useless:
        from ..block.gnss import match_to_reconstruction

        # only positions of registered images count (a naming mismatch is an error here)
        _, positions, sigmas = match_to_reconstruction(gnss, rec)
        short = short_baseline(positions, sigmas)
    if gnss is not None and not useless and not short:
        if location is not None:
            logger.warning("GNSS is given: it registers the block, the location hint is not "
                           "used")
        return None, gnss, None
    if location is None or short:
        if gnss is None:
            return None, None, None
        location = np.mean(np.asarray(gnss.positions)[:, :2], axis=0)
        radius = max(radius, 2.0 * sigma) if useless else min(radius, SHORT_RADIUS_SIGMAS * sigma)
    if useless:
        logger.warning("the GNSS positions' stated sigma (%.0f m) exceeds %.0f m: the block is "
                       "registered from the model alone around %s (radius %.0f m), without GNSS",
                       sigma, USELESS_GNSS_SIGMA, np.round(np.asarray(location)[:2], 1).tolist(),
                       radius)
    elif short:
        logger.warning("the GNSS positions spread too little to turn the block: it is found on "
                       "the model around their mean %s (radius %.0f m), GNSS kept as its priors",
                       np.round(np.asarray(location)[:2], 1).tolist(), radius)
    hint = np.asarray(location, float).reshape(-1)[:2] - store.origin[:2]
    found = locate(rec, store, hint, LocateOptions(radius=float(radius)))
    to_crs = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), np.asarray(store.origin, float))
    report = {**found.report, "location_hint": [float(v) for v in np.asarray(location)[:2]],
              "gnss_ignored": bool(useless), "short_baseline": bool(short)}
    return to_crs * found.sim3, (gnss if short else None), report


#: With GNSS too short to turn the block, its centre is searched within this many of GNSS's
#: horizontal sigmas of the positions' mean (a bias of that many sigmas is as far as GNSS's
#: error model reaches).
SHORT_RADIUS_SIGMAS = 5.0


def short_baseline(positions: np.ndarray, sigmas: np.ndarray) -> bool:
    """Whether GNSS positions spread too little along their main axis for a similarity
    (align.georegister's own rule: GeoregistrationOptions.min_baseline_sigmas of the
    horizontal sigma)."""
    from .georegister import GeoregistrationOptions, _principal_std

    positions = np.asarray(positions, float)
    if len(positions) < 3:
        return True
    horizontal = float(np.median(np.asarray(sigmas, float), axis=0)[:2].max())
    return bool(_principal_std(positions)[0]
                < GeoregistrationOptions().min_baseline_sigmas * horizontal)
