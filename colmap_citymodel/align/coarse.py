"""Coarse alignment: bring a GNSS-registered block within reach of direct assignment.

After the GNSS-only adjustment the block is off the model by the GNSS error: metres, often a
bias common to the whole flight, which no assignment with a 2 m threshold can bridge. Two
searches close that gap before any tie point is assigned:

- `search_roll`: for a nearly straight flight line GNSS cannot fix the rotation about that line.
  The planes found in the tie points (RANSAC) must have the orientations of model faces, which
  does not depend on where the block is: the roll that best matches the two sets of normals,
  with the cameras kept upright (their image "up" above the horizon), is searched on a 1 deg grid.
- `search_heading`: GNSS fixes the block's heading only to its sigma over the block's extent:
  degrees over a short block or a street drive (3 m over 40 images spread along 90 m: about
  1 deg), which puts its ends metres off across the street. The tie points' walls must have
  the azimuths of model walls wherever the block is: the rotation about the vertical that
  matches them, within a window of GNSS's heading sigmas, is a candidate like the roll.
- `search_translation`: the translation that puts the most tie points near a model surface,
  within a box that covers the GNSS uncertainty (+- 8 sigma by default), coarse to fine
  (kernel radius 2 m -> 1 m -> 0.4 m), with a mild, heavy-tailed penalty in units of the GNSS
  sigma so that a direction the model leaves free stays where GNSS put it. When the GNSS
  heights carry an unknown offset (`--gnss_height_offset auto`: another height system, heights
  above take-off) the height is searched over the whole range where the tie points meet the
  model's heights (`height_search_range`), without penalty: roofs and eaves put the block at
  its height.
- `level_roll`: `search_roll` without the model, for the georegistration of a straight line
  of cameras looking sideways: walls vertical, ground and flat roofs level.

Both use `SurfaceDistance`, the unsigned distance from a point to the model's surfaces that can
carry tie points (walls, roofs, ...; not ground or closure surfaces) up to the radius a caller
counts points within (the extension's `TriangleDistance`: a grid of the triangles near each
cell, exact in double precision below that radius).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from .._ext import load_core
from ..citymodel.store import PlaneStore
from ..errormodel.score import REACH_SIGMAS

logger = logging.getLogger(__name__)

#: Grid steps (m) of the translation search's coarse-to-fine levels; each level anneals the
#: tie points' distances with its step (errormodel.score.SurfaceErrorModel.level_sigma).
TRANSLATION_STEPS = (1.5, 0.5, 0.2)
#: How closely the coarse placement puts a block (m): twice the finest grid step. Along an
#: axis whose GNSS sigma is below it (RTK or PPK positions of an aerial block) GNSS places the
#: block better: the search leaves that axis where GNSS put it, and so does the height the
#: adjustment holds (adjust.scale.level_prior); one step of the search's grid would move the
#: block off there by several GNSS sigmas.
PLACEMENT_RESOLUTION = 2 * TRANSLATION_STEPS[-1]
#: Tie points used by the searches (a random subset of a larger block).
MAX_SEARCH_POINTS = 2000
#: Cameras of a street or UAV block do not look up at the sky: a roll that would make their
#: mean viewing direction rise above this elevation (deg) is not considered.
MAX_VIEW_ELEVATION_DEG = 20.0
#: Cells of the coarse distance grid at most (its spacing grows for large blocks).
MAX_GRID_CELLS = 4_000_000


class SurfaceDistance:
    """Unsigned distance (m) from points to the model surfaces that tie points can lie on (the
    faces not excluded by class, without what lies inside the city's volume), up to
    a radius: exact below `within`, `within` itself where no face is closer. Every caller
    counts points within a radius of the model, so no distance beyond it is ever computed."""

    def __init__(self, store: PlaneStore, excluded_classes=("GroundSurface", "ClosureSurface"),
                 threads: int = 0):
        """`threads`: of each query (0 or less: every core)."""
        from ..citymodel.visibility import visible_triangles

        vertices, triangles, faces = visible_triangles(store, excluded_classes)
        if not len(triangles):  # nothing a camera sees: every face rather than none
            vertices, triangles, faces = visible_triangles(store, ())
        self.vertices = np.ascontiguousarray(vertices, np.float64)
        self.triangles = np.ascontiguousarray(triangles, np.int64)
        self.triangle_faces, self.face_classes = faces, store.faces.semantic  # face, classes
        self.threads = max(int(threads), 0)
        self._grids: dict[float, object] = {}  # one triangle grid per radius asked for

    def __call__(self, points: np.ndarray, within: float) -> np.ndarray:
        if len(points) == 0:
            return np.zeros(0)
        grid = self._grids.get(within)
        if grid is None:
            grid = self._grids[within] = load_core().TriangleDistance(
                self.vertices, self.triangles, float(within))
        return grid(np.ascontiguousarray(points, np.float64).reshape(-1, 3), self.threads)


def near_weights(distances: np.ndarray, radius: float) -> np.ndarray:
    """Each point's smooth nearness to a surface: (1 - (d/r)^2)^2 for d < r, 0 beyond."""
    u = np.clip(np.asarray(distances) / radius, 0.0, 1.0)
    return (1.0 - u * u) ** 2


def near_share(distances: np.ndarray, radius: float) -> float:
    """Smooth share of points within `radius` of a surface: the mean of `near_weights`."""
    return float(np.mean(near_weights(distances, radius))) if len(distances) else 0.0


def subsample(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    if len(points) <= n:
        return points
    return points[np.random.default_rng(seed).choice(len(points), n, replace=False)]


@dataclass
class TranslationSearch:
    """Result of `search_translation`."""

    shift: np.ndarray  # (3,) metres, to add to the block
    value: float  # the search objective at `shift` (finest level)
    share_before: float  # near_share at the finest radius without / with the shift
    share_after: float
    shift_sigmas: np.ndarray  # (3,) |shift| per axis in GNSS sigmas
    seconds: float = 0.0

    def todict(self) -> dict:
        return {"shift_m": self.shift.tolist(), "shift_sigmas": self.shift_sigmas.tolist(),
                "near_share_before": self.share_before, "near_share_after": self.share_after}


def _grid_scores_builder(points: np.ndarray, weights: np.ndarray, surface: SurfaceDistance,
                         low: np.ndarray, high: np.ndarray, spacing: float, within: float,
                         terms_of):
    """The weighted sum of `terms_of(distance)` over `points` moved by each of a set of shifts
    within `low`..`high`, for the coarse level: distances (up to `within`) on a regular grid
    around the points (nearest-cell lookups), one distance query per cell instead of one per
    (point, shift)."""
    lower = points.min(0) + low - 2 * spacing
    upper = points.max(0) + high + 2 * spacing
    cells = np.prod((upper - lower) / spacing)
    if cells > MAX_GRID_CELLS:
        spacing *= float((cells / MAX_GRID_CELLS) ** (1 / 3))
    shape = np.ceil((upper - lower) / spacing).astype(int) + 1
    axes = [lower[k] + spacing * np.arange(shape[k]) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    values = surface(grid, within).reshape(shape).astype(np.float32)
    terms = terms_of(values).ravel()  # each cell's term, as a point there would add it
    strides = np.array([shape[1] * shape[2], shape[2], 1], np.int64)
    cells_of_points = (points - lower) / spacing  # fractional cell coordinates

    def scores(shifts: np.ndarray) -> np.ndarray:
        out = np.empty(len(shifts))
        # A shift of whole cells w plus a fraction f puts a point at cell rint(c + f) + w:
        # the shifts of a regular grid have few fractions, so one flat cell index per point
        # and fraction plus one per shift replaces rounding every (shift, point).
        steps = shifts / spacing
        whole = np.floor(steps)
        fraction = np.round(steps - whole, 9)
        kinds, kind_of_shift = np.unique(fraction, axis=0, return_inverse=True)
        kind_of_shift = kind_of_shift.reshape(-1)
        if len(kinds) <= 8:
            bases = [np.rint(cells_of_points + f).astype(np.int64) for f in kinds]
            lowest = np.min([b.min(0) for b in bases], axis=0) + whole.min(0)
            highest = np.max([b.max(0) for b in bases], axis=0) + whole.max(0)
            if np.all(lowest >= 0) and np.all(highest <= shape - 1):
                offsets = whole.astype(np.int64) @ strides
                for kind, base in enumerate(bases):
                    rows = np.flatnonzero(kind_of_shift == kind)
                    flat = base @ strides
                    for start in range(0, len(rows), 256):
                        chunk = rows[start:start + 256]
                        out[chunk] = terms[offsets[chunk, None] + flat[None, :]] @ weights
                return out
        for start in range(0, len(shifts), 256):  # any shifts: round each (shift, point)
            xyz = points[None, :, :] + shifts[start:start + 256, None, :]
            index = np.rint((xyz - lower) / spacing).astype(np.int64)
            np.clip(index, 0, shape - 1, out=index)
            out[start:start + 256] = terms[index @ strides] @ weights
        return out

    return scores


def search_translation(score, sigmas: np.ndarray, search_sigmas: float = 8.0,
                       candidates: int = 3, steps=TRANSLATION_STEPS, height_range=None,
                       points: np.ndarray | None = None, antennas: np.ndarray | None = None
                       ) -> TranslationSearch:
    """The shift of the block that maximises its placement score (errormodel.score.
    PlacementScore `score`: its tie points on faces and terrain, GNSS with its bias), or of
    `points` and `antennas` (the score's, the block turned).

    `sigmas` (3,) is the uncertainty of the block's position (GNSS sigma per axis); the search
    covers +- `search_sigmas` of it, except along axes whose sigma is below
    PLACEMENT_RESOLUTION (not searched: GNSS places the block better than the search can).
    `height_range` (lowest, highest): the vertical shifts searched instead (the GNSS heights'
    level is unknown, which the score's GNSS model knows). The coarse level scores every grid
    shift with a distance grid; the best `candidates` separate maxima are refined on the finer
    levels, each with its grid step and the sigma it anneals the distances with.
    """
    import time

    t0 = time.perf_counter()
    sigmas = np.maximum(np.asarray(sigmas, float), 1e-3)
    pts = score.points if points is None else points
    held = sigmas < PLACEMENT_RESOLUTION
    if height_range is not None:
        held[2] = False
    high = np.where(held, 0.0, search_sigmas * sigmas)
    low = -high
    if height_range is not None:
        low[2], high[2] = float(min(height_range)), float(max(height_range))
    model = score.model

    # Coarse level on a distance grid.
    step = steps[0]
    sigma = model.level_sigma(step)
    grid_scores = _grid_scores_builder(pts, score.weights, score.surface, low, high, step / 1.5,
                                       REACH_SIGMAS * sigma,
                                       lambda d: model.terms(d, sigma))
    axes = [np.arange(np.ceil(lo / step), np.floor(hi / step) + 1) * step
            for lo, hi in zip(low, high)]
    shifts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    values = grid_scores(shifts) + score.gnss_shift_terms(shifts, antennas)
    order = np.argsort(-values)
    seeds: list[np.ndarray] = []
    for k in order:  # the best maxima at least two steps apart
        if all(np.max(np.abs(shifts[k] - s)) > 1.5 * step for s in seeds):
            seeds.append(shifts[k])
        if len(seeds) == candidates:
            break

    def refine(centre: np.ndarray, step: float, reach: float):
        offsets = np.arange(-np.floor(reach / step), np.floor(reach / step) + 1) * step
        local = np.stack(np.meshgrid(offsets, offsets, offsets, indexing="ij"), -1).reshape(-1, 3)
        local = centre + local
        local = local[np.all((local >= low - step) & (local <= high + step), axis=1)
                      & np.all(local[:, held] == 0.0, axis=1)]
        s = score.shift_scores(local, model.level_sigma(step), pts, antennas)
        best = int(np.argmax(s))
        return local[best], float(s[best])

    best_shift, best_score = np.zeros(3), -np.inf
    for seed in seeds:
        shift, value = seed, -np.inf
        for reach, step_k in zip(steps[:-1], steps[1:]):
            # Each level searches +- the previous level's step around its best shift.
            shift, value = refine(shift, step_k, reach)
        if value > best_score:
            best_shift, best_score = shift, value
    finest = PLACEMENT_RESOLUTION
    sample = subsample(pts, 20000)
    result = TranslationSearch(best_shift, best_score,
                               near_share(score.surface(sample, finest), finest),
                               near_share(score.surface(sample + best_shift, finest), finest),
                               np.abs(best_shift) / sigmas, time.perf_counter() - t0)
    logger.info("translation search (%s m): shift %s m (%s GNSS sigma), tie points near the "
                "model %.0f %% -> %.0f %%, %.1f s",
                ", ".join(f"{lo:+.1f}..{hi:+.1f}" for lo, hi in zip(low, high)),
                np.round(best_shift, 2).tolist(),
                np.round(result.shift_sigmas, 1).tolist(), 100 * result.share_before,
                100 * result.share_after, result.seconds)
    return result


# -- roll about a straight flight line -------------------------------------------------------


def rotation_about(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def point_cloud_planes(points: np.ndarray, distance: float = 0.3, max_planes: int = 12,
                       min_points: int = 40, with_inliers: bool = False, threads: int = 0):
    """Dominant planes of a tie point cloud by sequential RANSAC (the extension's
    `segment_plane`, 500 hypotheses at most, seeded: the same planes on every run, on any
    number of `threads`, 0: all cores): (normals (K,3), inlier counts (K,)), and with
    `with_inliers` the inlier points of each."""
    core = load_core()
    rest = subsample(points, 20000)
    normals, counts, members = [], [], []
    for k in range(max_planes):
        if len(rest) < min_points:
            break
        plane, inliers = core.segment_plane(rest, distance, 500, seed=k,
                                             threads=max(int(threads), 0))
        if len(inliers) < min_points:
            break
        normals.append(np.asarray(plane[:3], float))
        counts.append(len(inliers))
        members.append(rest[inliers])
        rest = np.delete(rest, inliers, axis=0)
    result = np.array(normals).reshape(-1, 3), np.array(counts, float)
    return (*result, members) if with_inliers else result


#: Planes of the tie point cloud within this angle of the vertical direction count as walls.
WALL_TILT_DEG = 15.0


def wall_points(points: np.ndarray, threads: int = 0) -> np.ndarray:
    """Tie points on the dominant vertical planes of the cloud (walls): in a city they are
    where a LoD2 model is surely right, unlike the ground (not modelled), trees or cars."""
    normals, _, members = point_cloud_planes(points, with_inliers=True, threads=threads)
    walls = [m for n, m in zip(normals, members)
             if abs(n[2]) < np.sin(np.radians(WALL_TILT_DEG))]
    return np.vstack(walls) if walls else np.zeros((0, 3))


@dataclass
class RollSearch:
    angle: float  # radians about `axis` through `centre`
    axis: np.ndarray
    centre: np.ndarray
    score: float
    score_at_zero: float
    num_planes: int

    @property
    def rotation(self) -> np.ndarray:
        return rotation_about(self.axis, self.angle)


def search_roll(points: np.ndarray, axis: np.ndarray, centre: np.ndarray, store: PlaneStore,
                camera_up: np.ndarray, camera_view: np.ndarray, tolerance_deg: float = 4.0,
                step_deg: float = 1.0, max_view_elevation_deg: float = MAX_VIEW_ELEVATION_DEG,
                window_deg: float = 180.0,
                excluded_classes=("GroundSurface", "ClosureSurface"),
                threads: int = 0, planes=None) -> RollSearch | None:
    """The rotation about `axis` (through `centre`) that makes the tie point planes' normals
    model normals, keeping the cameras upright: `camera_up` (N,3) are the cameras' image "up"
    directions (-y axis), `camera_view` their viewing directions (z axis), in the current
    frame. The mean image up must point above the horizon and the mean view must not rise
    above `max_view_elevation_deg`: walls and flat roofs are both planes of model
    orientations, so a block turned by 90 deg (walls on roofs, cameras looking at the sky)
    would match as well. Only rolls within +- `window_deg` are searched; the tie point planes
    on `threads` (0: all cores), or `planes` (normals, counts) of `point_cloud_planes` found
    before. None when the tie points hold no plane."""
    faces = [i for i, f in enumerate(store.faces) if f.semantic not in excluded_classes]
    model = store.normals[faces] if faces else store.normals

    def closeness(normals: np.ndarray) -> np.ndarray:
        return np.abs(normals @ model.T).max(axis=1)

    return _search_roll(points, axis, centre, closeness, camera_up, camera_view,
                        tolerance_deg, step_deg, max_view_elevation_deg, window_deg, threads,
                        planes)


def level_roll(points: np.ndarray, axis: np.ndarray, centre: np.ndarray,
               camera_up: np.ndarray, camera_view: np.ndarray, window_deg: float = 90.0,
               threads: int = 0) -> RollSearch | None:
    """`search_roll` without a model: the rotation about `axis` that makes the tie point
    planes walls (vertical) or level (ground, flat roofs), as a city's planes are, with the
    same upright cameras. Walls parallel to the line and the ground fix the roll about a
    straight line wherever the block is, which GNSS cannot and the cameras' image "up" can
    only to their unknown tilt when they look sideways. A block turned by 90 deg has level
    and vertical planes too: the cameras' constraints rule it out, and `window_deg` keeps the
    search within a quarter turn of the roll the block has."""

    def closeness(normals: np.ndarray) -> np.ndarray:
        vertical = np.abs(normals[:, 2])
        return np.maximum(vertical, np.sqrt(np.clip(1.0 - vertical ** 2, 0.0, 1.0)))

    return _search_roll(points, axis, centre, closeness, camera_up, camera_view,
                        window_deg=window_deg, threads=threads)


def _search_roll(points: np.ndarray, axis: np.ndarray, centre: np.ndarray, closeness,
                 camera_up: np.ndarray, camera_view: np.ndarray, tolerance_deg: float = 4.0,
                 step_deg: float = 1.0,
                 max_view_elevation_deg: float = MAX_VIEW_ELEVATION_DEG,
                 window_deg: float = 180.0, threads: int = 0, planes=None) -> RollSearch | None:
    """The roll search of `search_roll` and `level_roll`: `closeness(normals)` (K,) is the
    cosine of the angle between each rotated tie point plane normal and the nearest
    orientation it should have."""
    normals, counts = (point_cloud_planes(points, threads=threads) if planes is None
                       else planes)
    if not len(normals):
        return None
    cos_tol = np.cos(np.radians(tolerance_deg))
    up_mean = np.mean(camera_up, axis=0)
    view_mean = np.mean(camera_view, axis=0)
    view_mean /= max(np.linalg.norm(view_mean), 1e-12)
    max_rise = np.sin(np.radians(max_view_elevation_deg))

    def score(angle: float) -> float:
        rotation = rotation_about(axis, angle)
        if (rotation @ up_mean)[2] <= 0.0 or (rotation @ view_mean)[2] > max_rise:
            return -1.0
        u = np.clip((1.0 - closeness(normals @ rotation.T)) / (1.0 - cos_tol), 0.0, 1.0)
        return float(np.sum(counts * (1.0 - u) ** 2) / counts.sum())

    window = min(float(window_deg), 180.0)
    coarse = np.radians(np.arange(-window, window + 1e-9, step_deg))
    values = np.array([score(a) for a in coarse])
    best = coarse[int(np.argmax(values))]
    fine = best + np.radians(np.linspace(-step_deg, step_deg, 21))
    fine_values = np.array([score(a) for a in fine])
    angle = float(fine[int(np.argmax(fine_values))])
    return RollSearch(angle, axis, centre, float(fine_values.max()), score(0.0), len(normals))


#: Metres added on both sides of the vertical search range of `height_search_range`.
HEIGHT_SEARCH_MARGIN = 5.0


def height_search_range(points: np.ndarray, store: PlaneStore,
                        excluded_classes=("GroundSurface", "ClosureSurface")
                        ) -> tuple[float, float]:
    """Vertical shifts (lowest, highest) that put some of the tie points (2nd-98th height
    percentile) within the height range of the model's surfaces: where the block must be when
    its GNSS heights are in an unknown height system."""
    faces = [i for i, f in enumerate(store.faces) if f.semantic not in excluded_classes]
    ids = (np.unique(np.concatenate([store.face_vertex_ids(f) for f in faces])) if faces
           else np.arange(len(store.vertices)))
    z_model = store.vertices[ids, 2]
    z_low, z_high = np.percentile(points[:, 2], [2.0, 98.0])
    return (float(z_model.min() - z_high - HEIGHT_SEARCH_MARGIN),
            float(z_model.max() - z_low + HEIGHT_SEARCH_MARGIN))


@dataclass
class CoarseAlignment:
    """The similarity (rotation about the vertical and about the flight line, then a shift)
    that coarse alignment applies, and what decided it."""

    sim3: "pycolmap.Sim3d"  # noqa: F821
    translation: TranslationSearch
    roll_deg: float | None  # None: no roll search (the flight line is not straight)
    roll_candidates: list[dict]
    heading_deg: float | None = None  # None: the heading GNSS gave was kept
    heading_candidates: list[dict] = field(default_factory=list)
    moved: bool = False  # whether the block was moved by it (workflow.coarse_start)

    def todict(self) -> dict:
        return {"translation": self.translation.todict(), "roll_deg": self.roll_deg,
                "roll_candidates": self.roll_candidates, "heading_deg": self.heading_deg,
                "heading_candidates": self.heading_candidates,
                "seconds": self.translation.seconds}


#: The heading search's window is this many of GNSS's heading sigmas on either side, at
#: most HEADING_WINDOW_MAX_DEG: walls of a city stand mostly at right angles to each other, so
#: a window of 45 deg or more would let a block turn onto the perpendicular walls.
HEADING_WINDOW_SIGMAS = 8.0
HEADING_WINDOW_MAX_DEG = 30.0
#: Below this window (deg) GNSS fixes the heading better than the normals' 1 deg grid can.
HEADING_WINDOW_MIN_DEG = 1.0
#: A turn is tried only where it makes most of the tie point planes (this share of their
#: points) parallel to model faces: where fewer match, the planes are not the model's walls
#: (trees, cars, buildings the model lacks), and some turn within the window matches a few of
#: them to some model face by chance.
HEADING_MIN_SCORE = 0.5


def heading_sigma_deg(centres: np.ndarray, sigmas: np.ndarray) -> float:
    """GNSS's sigma (deg) of a block's heading: its horizontal position sigma (the mean of
    the E and N of `sigmas`, (3,)) over the root of the cameras' summed squared horizontal
    distances from their centre (`centres`, (N, 3)), as for the scale
    (block.priors.scale_sigma_from_gnss). A bias common to all positions turns nothing."""
    spread = centres[:, :2] - centres[:, :2].mean(0)
    sigma = float(np.mean(np.asarray(sigmas, float)[:2]))
    return float(np.degrees(sigma / np.sqrt(max(float(np.sum(spread ** 2)), 1e-12))))


def search_heading(points: np.ndarray, centre: np.ndarray, store: PlaneStore,
                   camera_up: np.ndarray, camera_view: np.ndarray, window_deg: float,
                   threads: int = 0, planes=None) -> RollSearch | None:
    """The rotation about the vertical through `centre`, within +- `window_deg`, that makes
    the tie point planes' normals model normals (search_roll about the vertical axis; cameras
    stay upright under it; `planes` as there). None when the tie points hold no plane."""
    return search_roll(points, np.array([0.0, 0.0, 1.0]), centre, store, camera_up,
                       camera_view, window_deg=window_deg, threads=threads, planes=planes)


#: Cameras that look along a straight flight line fix the roll about it to about their
#: mounting's roll (a vehicle, a gimbal): the planes may change it by this much (deg) at most.
ROLL_WINDOW_DEG = 3.0
#: A roll about the flight line is tried when the tie point planes match the model normals
#: better by this much (share of plane points) than without it.
MIN_ROLL_GAIN = 0.05


def coarse_alignment(points: np.ndarray, centres: np.ndarray, camera_up: np.ndarray,
                     camera_view: np.ndarray, store: PlaneStore, score, sigmas: np.ndarray,
                     straight: bool, search_sigmas: float = 8.0, free_height: bool = False,
                     heading_sigma: float | None = None) -> CoarseAlignment:
    """Heading, roll about a straight flight line (when `straight`) and shift of the whole
    block, all scored by its placement score `score` (errormodel.score.PlacementScore: its tie
    points on the model's faces and terrain, GNSS with its bias).

    Each rotation candidate (none; the heading `search_heading` prefers within
    HEADING_WINDOW_SIGMAS of `heading_sigma`, GNSS's heading sigma in deg, when given; and on
    each of these the roll `search_roll` prefers) gets its own translation search; the one
    with the best score wins, so a rotation is kept only where the tie points and GNSS together
    are likelier turned. `points`: the block's tie points (their planes give the rotation
    candidates). `free_height`: the GNSS heights' level is unknown, the height is searched over
    `height_search_range`.
    """
    import pycolmap

    if not len(points):
        from ..errors import GeoregistrationError

        raise GeoregistrationError(
            "no tie points are left after the bundle adjustment with the GNSS positions (step "
            "2) eliminated their observations: are some GNSS positions far off the flight (see "
            "the outlier warning of the georegistration)?")
    centre = centres.mean(0)
    surface = score.surface
    # The tie points' planes, found once: a turn about the cameras' centre turns them along.
    window = heading_window(heading_sigma)
    planes = (point_cloud_planes(points, threads=surface.threads)
              if straight or window is not None else None)
    headings, heading_found = _heading_candidates(points, centre, store, camera_up, camera_view,
                                                  window, surface.threads, planes)
    candidates, found = list(headings), []
    if straight:
        for _, heading_deg, turn, _ in headings:
            roll = _roll_candidate(points, centres, camera_up, camera_view, store, surface,
                                   turn, found, heading_deg, planes)
            if roll is not None:
                candidates.append(roll)
    best = None
    for roll_deg, heading_deg, rotation, record in candidates:
        offset = centre - rotation @ centre
        moved = score.points @ rotation.T + offset
        antennas = None if score.antennas is None else score.antennas @ rotation.T + offset
        height_range = height_search_range(moved, store) if free_height else None
        search = search_translation(score, sigmas, search_sigmas,
                                    candidates=5 if free_height else 3,
                                    height_range=height_range, points=moved, antennas=antennas)
        if record is not None:
            record["search_value"] = search.value
        if roll_deg is None and heading_deg is None and (found or heading_found):
            found.append({"roll_deg": 0.0, "heading_deg": 0.0, "search_value": search.value})
        if best is None or search.value > best[4].value:
            best = (roll_deg, heading_deg, rotation, offset, search)
    roll_deg, heading_deg, rotation, offset, search = best
    if heading_deg is not None:
        logger.info("turned the block by %.1f deg about the vertical (its walls parallel to "
                    "model walls; GNSS's heading sigma %.1f deg)", heading_deg, heading_sigma)
    if roll_deg is not None:
        logger.info("flight line nearly straight: rotated the block by %.1f deg about it (tie "
                    "point planes parallel to model faces)", roll_deg)
    sim3 = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(rotation), offset + search.shift)
    return CoarseAlignment(sim3, search, roll_deg, found, heading_deg, heading_found)


def heading_window(heading_sigma: float | None) -> float | None:
    """The heading search's window (deg, on either side) for GNSS's heading sigma (deg):
    HEADING_WINDOW_SIGMAS of it, at most HEADING_WINDOW_MAX_DEG; None (no search) without a
    sigma or below HEADING_WINDOW_MIN_DEG."""
    if heading_sigma is None:
        return None
    window = min(HEADING_WINDOW_SIGMAS * heading_sigma, HEADING_WINDOW_MAX_DEG)
    return window if window >= HEADING_WINDOW_MIN_DEG else None


def _heading_candidates(points, centre, store, camera_up, camera_view, window,
                        threads, planes) -> tuple[list[tuple], list[dict]]:
    """The heading candidates of coarse_alignment as (roll deg, heading deg, rotation, its
    record): (None, None, identity, None) and, where the walls match the model's better
    turned (by MIN_ROLL_GAIN, and mostly: HEADING_MIN_SCORE), (None, heading deg, its
    rotation, its record), searched within +- `window` deg (None: not searched); and the
    records of the search."""
    out = [(None, None, np.eye(3), None)]
    if window is None:
        return out, []
    heading = search_heading(points, centre, store, camera_up, camera_view, window, threads,
                             planes)
    if heading is None:
        return out, []
    degrees = float(np.degrees(heading.angle))
    logger.info("heading search (+- %.1f deg): the tie points' planes match the model's "
                "normals %.2f turned by %.1f deg, %.2f as they are (%d planes)", window,
                heading.score, degrees, heading.score_at_zero, heading.num_planes)
    found = [{"heading_deg": degrees, "window_deg": window, "normal_score": heading.score,
              "normal_score_unrotated": heading.score_at_zero,
              "tie_point_planes": heading.num_planes}]
    if heading.score > max(heading.score_at_zero + MIN_ROLL_GAIN, HEADING_MIN_SCORE):
        out.append((None, degrees, heading.rotation, found[0]))
    return out, found


def _roll_candidate(points, centres, camera_up, camera_view, store, surface, turn, found,
                    heading_deg, planes) -> tuple | None:
    """The roll about the straight flight line of the block turned by `turn` (3x3, about the
    cameras' centre; `planes` the unturned block's), its record appended to `found`: (roll
    deg, heading deg, rotation, record) where it matches the model's normals better (by
    MIN_ROLL_GAIN), else None."""
    centre = centres.mean(0)
    axis = turn @ np.linalg.svd(centres - centre)[2][0]
    moved = (points - centre) @ turn.T + centre
    up, view = camera_up @ turn.T, camera_view @ turn.T
    # Cameras looking along the line (a vehicle) hold the roll with their horizontal image
    # x axis (georegistration used it): the planes may only fine-tune it. Cameras looking
    # sideways give no such cue: the whole circle is searched.
    right = np.cross(up, view)
    cue = float(np.mean(np.linalg.norm(np.cross(right, axis), axis=1)))
    window = ROLL_WINDOW_DEG / cue if cue > 0.5 else 180.0
    roll = search_roll(moved, axis, centre, store, up, view, window_deg=window,
                       threads=surface.threads, planes=(planes[0] @ turn.T, planes[1]))
    if roll is None:
        return None
    degrees = float(np.degrees(roll.angle))
    found.append({"roll_deg": degrees, "heading_deg": heading_deg or 0.0,
                  "normal_score": roll.score, "normal_score_unrotated": roll.score_at_zero,
                  "tie_point_planes": roll.num_planes})
    if roll.score <= roll.score_at_zero + MIN_ROLL_GAIN:
        return None
    return degrees, heading_deg, roll.rotation @ turn, found[-1]
