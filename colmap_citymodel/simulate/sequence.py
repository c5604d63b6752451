"""Simulated UAV flights through city models, mapped by COLMAP (Unger chapter 5).

`colmap-citymodel simulate SCENARIO.toml --output_path WORKSPACE [--seed N]` builds a COLMAP
workspace whose drift is COLMAP's own:

1. Scene (simulate/scene.py): the given LOD2 model (a real CityGML/CityJSON file or a procedural
   street) and the true scene = model + generalisation effects (facade relief, recessed doors,
   balconies, roof overhangs, roof furniture, trees, cars, terrain) as a triangle mesh.
2. Flight: key frames >= 1 m apart along a loop around the buildings (their footprints buffered
   by the facade distance), 5-15 m from the facades with a height profile, the camera looking
   sideways at the facades and tilted down (DJI Zenmuse X3 class: 4096 x 2160 px, f = 2400 px);
   or looking forward along the path; or along a given polyline of waypoints (a vehicle drive,
   a straight strip); or an orbit: one full circle around a centre, looking inward and down.
3. Observations: points sampled on the true surfaces, visibility by ray casting (open3d) against
   the true mesh with distance and incidence limits, tracks broken by large viewpoint changes,
   detection losses and gaps, tracks of >= 3 views, 1 px image noise, unmatched keypoints and a
   few percent wrong matches. Optionally an unmodelled systematic image error: the true lens has
   radial distortion `flight.radial_k1` while the database camera states
   `flight.calibrated_radial_k1` (fixed in COLMAP). Without it, COLMAP's block is nearly perfect
   (2 mm camera-centre RMS after a similarity fit over 100 m); with k1 = 0.0007-0.001 (1.5-2 px
   in the image corners) it bends like Unger's real blocks (cm over 100 m, decimetres to a metre
   over 400 m after a Helmert fit). Check points: targets on facades and roofs, observed with 1 px
   noise, kept out of the SfM data.
4. GNSS: true projection centres + white noise (default 3, 3, 5 m, the stated a priori sigma)
   + a slowly varying bias (Gaussian-filtered noise along the path) + optionally a constant bias
   of a given magnitude in a direction drawn from the seed. The benchmark sequences use
   Unger-like filtered GNSS instead: 0.3-0.5 m white noise, a 1 m bias, stated sigma 3, 3, 5 m.
5. COLMAP: database (camera, rig, frames, images, keypoints, matches, pose priors), geometric
   verification by COLMAP itself (`pycolmap.verify_matches`), then COLMAP's incremental mapper ->
   `sparse/0`. The interior orientation is known and kept fixed (as in Unger 5.3).

Frames. `truth/` and everything "local" use the model CRS minus `truth/origin.txt` (the store's
origin: the model's lower bbox corner rounded down to metres). `checkpoints.txt`, `gnss.txt` and
the database pose priors (coordinate system CARTESIAN) are in the model CRS itself, full
coordinates: COLMAP stores prior positions as float64, so UTM-sized numbers lose nothing there,
but consumers should subtract the origin before adjusting.

Sequences and scenarios. Everything that defines the images and their observations (scene,
flight, noise, seed, mapping) is a *sequence*; a scenario only chooses the given model variant
and the GNSS availability (Unger Table 6). With `cache_path`, a sequence is built and mapped once
(directory `<cache_path>/<name>-<hash>`) and every scenario of it is derived by copying, so all
scenarios of a sequence share the same images, observations, GNSS noise and `sparse/0`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import math
import os
import shutil
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from .scene import (
    LABEL_ROOF,
    LABEL_WALL,
    DetailOptions,
    GroundModel,
    ModelErrorOptions,
    ProceduralOptions,
    TrueScene,
    build_true_scene,
    building_footprints,
    detailed_polygons,
    perturb_planes,
    perturb_polygons,
    procedural_store,
)

logger = logging.getLogger(__name__)

# Bump when the simulation changes in a way that makes cached sequences stale.
SIMULATOR_VERSION = 1
STAGE_FLIGHT, STAGE_POINTS, STAGE_OBS, STAGE_CHECK, STAGE_GNSS, STAGE_DETAILED = 21, 22, 23, 24, \
    25, 26
MODEL_VARIANTS = ("detailed", "corrected", "original", "none")
FLIGHT_MODES = ("sideways", "forward", "orbit")
# Options added after sequences were first cached: left out of the sequence key while they hold
# these defaults, so that existing sequences keep their keys.
_KEY_NEUTRAL = {"flight": {"yaw_offset_deg": 0.0, "orbit_centre": None, "orbit_radius": 35.0},
                "gnss": {"bias_magnitude": 0.0}}


# ----------------------------------------------------------------------------------------------
# options


@dataclass
class SceneOptions:
    source: str = "procedural"  # "procedural" or a CityGML/CityJSON file/directory
    lod: int = 2
    crs: str | None = None  # CRS to assume when the file names none
    bbox_crs: list[float] | None = None  # [xmin, ymin, xmax, ymax] (model CRS) to read a part
    procedural: ProceduralOptions = field(default_factory=ProceduralOptions)


@dataclass
class FlightOptions:
    # "sideways": looking at the facades; "forward": along the path; "orbit": one full circle
    # of radius orbit_radius around orbit_centre, looking at the centre
    mode: str = "sideways"
    num_key_frames: int = 90
    spacing: float = 1.0  # minimum distance between key frames (m) (Unger 5.3: base >= 1 m)
    spacing_jitter: float = 0.3  # plus U(0, jitter) m
    facade_distance: float = 10.0  # the path follows the footprints buffered by this (m)
    distance_amplitude: float = 3.0  # +- variation of that distance (-> 7..13 m)
    distance_period: float = 70.0  # m of path per period
    closing: float = 12.0  # gaps between buildings narrower than 2x this are bridged by the path
    flight_height: float = 12.0  # mean height above ground (m)
    height_amplitude: float = 5.0  # height profile +-
    height_period: float = 110.0
    pitch_deg: float = 20.0  # camera tilted down
    attitude_sigma_deg: tuple[float, float, float] = (2.0, 1.5, 1.0)  # yaw, pitch, roll jitter
    turn_smoothing: float = 5.0  # heading: path tangent averaged over +-this (m)
    start_xy: list[float] | None = None  # local; default: the footprints' lower-left corner
    waypoints: list[list[float]] | None = None  # local xy polyline instead of the loop
    look: str = "left"  # for waypoints: which side the facades are on
    # the camera's heading turned from the mode's (towards the facades, the path tangent or the
    # orbit centre) by this angle, counter-clockwise seen from above (deg)
    yaw_offset_deg: float = 0.0
    # orbit: centre (local xy; default: the centre of the model's bounding box) and radius (m);
    # num_key_frames evenly spaced over the circle (spacing is then 2 pi r / n), counter-clockwise
    orbit_centre: list[float] | None = None
    orbit_radius: float = 35.0
    image_width: int = 4096
    image_height: int = 2160
    focal_length: float = 2400.0
    # lens distortion (COLMAP SIMPLE_RADIAL k1) of the true camera, and the k1 the database
    # camera states (its calibration); a difference is an unmodelled systematic image error
    radial_k1: float = 0.0
    calibrated_radial_k1: float = 0.0


@dataclass
class ObservationOptions:
    points_per_m2: float = 2.0  # candidate features on true surfaces near the flight
    max_distance: float = 40.0  # no features further from the camera (m)
    min_distance: float = 1.0
    max_incidence_deg: float = 75.0  # between viewing ray and surface normal
    detection_probability: float = 0.8  # a visible candidate gives a matched keypoint
    max_track_view_angle_deg: float = 40.0  # viewpoint change that breaks a track (descriptors)
    min_track_length: int = 3
    pixel_noise: float = 1.0  # sigma (px) of image coordinates
    outlier_ratio: float = 0.03  # wrong matches per image pair, relative to its correct ones
    unmatched_ratio: float = 0.3  # keypoints without a match, relative to matched ones per image
    match_window: int = 10  # sequential matching: each key frame with the next N
    min_matches: int = 15  # pairs with fewer matches are not written
    image_margin: float = 2.0  # px


@dataclass
class CheckPointOptions:
    count: int = 30
    roof_fraction: float = 0.3
    min_views: int = 4
    candidates: int = 20000
    pixel_noise: float = 1.0


@dataclass
class GNSSOptions:
    sigma: tuple[float, float, float] = (3.0, 3.0, 5.0)  # stated a priori sigma (priors, gnss.txt)
    # actual white noise per key frame; None: the stated sigma. Unger's DJI positions were
    # filtered (5.2.1: "a smoothed trajectory"): small white noise, a bias of metres
    white_sigma: tuple[float, float, float] | None = None
    bias_sigma: tuple[float, float, float] = (1.0, 1.0, 1.5)  # slowly varying bias (m)
    bias_length: float = 100.0  # correlation length of the bias along the path (m)
    # a constant bias of this length (m) over the whole block, its direction uniform on the
    # sphere and drawn from the seed alone (the same direction for every magnitude)
    bias_magnitude: float = 0.0


@dataclass
class MappingOptions:
    run: bool = True
    two_view_geometry: str = "verify"  # "verify": COLMAP's RANSAC; "truth": E from true poses
    refine_intrinsics: bool = False  # interior orientation known and fixed (Unger 5.3)
    num_threads: int = -1
    random_seed: int | None = None  # None: the simulation seed
    incremental: dict[str, Any] = field(default_factory=dict)  # IncrementalPipelineOptions


@dataclass
class ScenarioOptions:
    """What a scenario adds to its sequence (Unger Table 6)."""

    name: str = ""
    model: str = "corrected"  # detailed | corrected | original | none
    gnss: str = "all"  # all | first | none
    gnss_first_n: int = 50


@dataclass
class SimulationOptions:
    name: str = "sequence"
    seed: int = 0
    scene: SceneOptions = field(default_factory=SceneOptions)
    details: DetailOptions = field(default_factory=DetailOptions)
    model_errors: ModelErrorOptions = field(default_factory=ModelErrorOptions)
    flight: FlightOptions = field(default_factory=FlightOptions)
    observations: ObservationOptions = field(default_factory=ObservationOptions)
    checkpoints: CheckPointOptions = field(default_factory=CheckPointOptions)
    gnss: GNSSOptions = field(default_factory=GNSSOptions)
    mapping: MappingOptions = field(default_factory=MappingOptions)
    scenario: ScenarioOptions = field(default_factory=ScenarioOptions)
    # files the options came from (copied into the workspace)
    source_files: list[str] = field(default_factory=list)

    def sequence_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("scenario")
        d.pop("source_files")
        return d


def _merge_into(obj, values: dict, path: Path, where: str) -> None:
    """Set dataclass fields from a TOML table; unknown keys are an error naming the file."""
    names = {f.name: f for f in dataclasses.fields(obj)}
    for key, value in values.items():
        if key not in names:
            raise InputError(f"unknown option '{where}{key}' (known: {', '.join(names)})", path)
        current = getattr(obj, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise InputError(f"'{where}{key}' must be a table", path)
            _merge_into(current, value, path, f"{where}{key}.")
        elif isinstance(current, dict):
            if not isinstance(value, dict):
                raise InputError(f"'{where}{key}' must be a table", path)
            setattr(obj, key, dict(value))
        else:
            if isinstance(current, tuple):
                if not isinstance(value, list) or len(value) != len(current):
                    raise InputError(f"'{where}{key}' must be a list of {len(current)}", path)
                value = tuple(value)
            elif isinstance(current, bool) and not isinstance(value, bool):
                raise InputError(f"'{where}{key}' must be true or false", path)
            elif isinstance(current, float) and isinstance(value, int) and not isinstance(
                    value, bool):
                value = float(value)
            setattr(obj, key, value)


def _read_toml(path: Path) -> dict:
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise InputError("scenario file not found", path) from None
    except (OSError, tomllib.TOMLDecodeError) as error:
        raise InputError(f"cannot read scenario TOML: {error}", path) from None


def load_scenario(path: str | Path) -> SimulationOptions:
    """Read a scenario TOML. `sequence = "file.toml"` (relative path) pulls in a shared sequence
    definition first; the scenario file's own keys override it. `scene.source` paths are
    resolved relative to the file that names them."""
    path = Path(path).resolve()
    data = _read_toml(path)
    options = SimulationOptions()
    sources = [str(path)]
    seq = data.pop("sequence", None)
    if seq is not None:
        if not isinstance(seq, str):
            raise InputError("'sequence' must be the path of a sequence TOML file", path)
        seq_path = (path.parent / seq).resolve()
        seq_data = _read_toml(seq_path)
        if "sequence" in seq_data:
            raise InputError("a sequence file cannot name another sequence", seq_path)
        _resolve_source(seq_data, seq_path)
        _merge_into(options, seq_data, seq_path, "")
        sources.insert(0, str(seq_path))
    _resolve_source(data, path)
    _merge_into(options, data, path, "")
    options.source_files = sources
    _validate(options, path)
    return options


def _resolve_source(data: dict, path: Path) -> None:
    scene = data.get("scene")
    if isinstance(scene, dict) and isinstance(scene.get("source"), str):
        if scene["source"] != "procedural":
            scene["source"] = str((path.parent / scene["source"]).resolve())


def _validate(o: SimulationOptions, path: Path) -> None:
    def bad(msg):
        raise InputError(msg, path)

    if o.scenario.model not in MODEL_VARIANTS:
        bad(f"scenario.model must be one of {MODEL_VARIANTS}, got {o.scenario.model!r}")
    if o.scenario.gnss not in ("all", "first", "none"):
        bad(f"scenario.gnss must be all, first or none, got {o.scenario.gnss!r}")
    if o.flight.mode not in FLIGHT_MODES:
        bad(f"flight.mode must be one of {FLIGHT_MODES}, got {o.flight.mode!r}")
    if o.flight.mode == "orbit" and o.flight.waypoints:
        bad("flight.waypoints and flight.mode = orbit exclude each other")
    if o.flight.orbit_radius <= 0:
        bad("flight.orbit_radius must be positive (metres)")
    if o.gnss.bias_magnitude < 0:
        bad("gnss.bias_magnitude must not be negative (metres)")
    if o.flight.num_key_frames < 3:
        bad("flight.num_key_frames must be at least 3")
    if o.flight.spacing < 0.05:
        bad("flight.spacing must be positive (metres)")
    if o.mapping.two_view_geometry not in ("verify", "truth"):
        bad("mapping.two_view_geometry must be verify or truth")
    if o.observations.min_track_length < 2:
        bad("observations.min_track_length must be at least 2")
    if o.scene.source != "procedural" and not Path(o.scene.source).exists():
        bad(f"scene.source {o.scene.source} does not exist")


def sequence_key(options: SimulationOptions) -> str:
    """Hash of everything that defines a sequence (not the scenario), incl. the model file."""
    d = options.sequence_dict()
    for group, defaults in _KEY_NEUTRAL.items():
        for name, default in defaults.items():
            if d[group][name] == default:
                del d[group][name]
    src = options.scene.source
    if src != "procedural":
        h = hashlib.sha256()
        p = Path(src)
        files = sorted(p.rglob("*")) if p.is_dir() else [p]
        for f in files:
            if f.is_file():
                h.update(f.name.encode())
                h.update(f.read_bytes())
        d["scene"]["source"] = h.hexdigest()
    d["version"] = SIMULATOR_VERSION
    text = json.dumps(d, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:12]


# ----------------------------------------------------------------------------------------------
# flight


@dataclass
class Flight:
    names: list[str]
    centres: np.ndarray  # (N,3) local
    rotations: np.ndarray  # (N,3,3) cam_from_world
    arc: np.ndarray  # (N,) arc length along the path (m)
    width: int
    height: int
    focal: float
    k1: float = 0.0  # true radial distortion
    k1_calibrated: float = 0.0  # the database camera's

    @property
    def translations(self) -> np.ndarray:
        return -np.einsum("nij,nj->ni", self.rotations, self.centres)

    def project(self, k: int, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (COLMAP convention) and depth of local points in key frame k."""
        Xc = (X - self.centres[k]) @ self.rotations[k].T
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            n = Xc[:, :2] / z[:, None]
            if self.k1:
                n = n * (1.0 + self.k1 * np.sum(n * n, axis=1, keepdims=True))
            uv = self.focal * n + np.array([self.width / 2, self.height / 2])
        return uv, z


def _look_rotation(forward: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """cam_from_world for a camera looking along `forward` (x right, y down, z forward)."""
    f = forward / np.linalg.norm(forward)
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(f, x)
    if roll:
        x, y = math.cos(roll) * x + math.sin(roll) * y, -math.sin(roll) * x + math.cos(roll) * y
    return np.stack([x, y, f])


def flight_path(store, options: FlightOptions):
    """The xy path (shapely LineString/LinearRing, counter-clockwise around the buildings when a
    loop) and the side the facades are on (+1 left, -1 right)."""
    import shapely
    from shapely.geometry import LineString, Polygon
    from shapely.geometry.polygon import orient

    if options.waypoints:
        line = LineString(np.asarray(options.waypoints, dtype=np.float64)[:, :2])
        return line, (1.0 if options.look == "left" else -1.0)
    union = shapely.unary_union(list(building_footprints(store).values()))
    d, c = options.facade_distance, options.closing
    area = union.buffer(d + c, quad_segs=16).buffer(-c, quad_segs=16)
    polys = [area] if isinstance(area, Polygon) else list(area.geoms)
    poly = orient(max(polys, key=lambda p: p.area), 1.0)
    return poly.exterior, 1.0


def plan_flight(store, options: FlightOptions, seed: int, ground: GroundModel) -> Flight:
    """Key frames along the path (see FlightOptions), deterministic for a seed."""
    from shapely.geometry import Point

    if options.mode == "orbit":
        return plan_orbit(store, options, seed, ground)
    rng = np.random.default_rng([seed, STAGE_FLIGHT])
    line, side = flight_path(store, options)
    L = line.length
    closed = line.is_ring
    if options.start_xy is not None:
        s0 = line.project(Point(options.start_xy[:2]))
    elif options.waypoints:
        s0 = 0.0
    else:
        lo = store.bbox_local[0]
        s0 = line.project(Point(lo[0], lo[1]))
    n = options.num_key_frames
    steps = options.spacing + rng.uniform(0.0, options.spacing_jitter, n - 1)
    arc = s0 + np.concatenate([[0.0], np.cumsum(steps)])
    if arc[-1] - s0 > (L if closed else L - s0):
        raise InputError(
            f"the flight needs {arc[-1] - s0:.0f} m of path but the path is {L:.0f} m long "
            "(fewer key frames, smaller spacing or a larger scene)")

    def xy_at(s):
        s = np.mod(s, L) if closed else np.clip(s, 0, L)
        return np.array([line.interpolate(float(v)).coords[0][:2] for v in np.atleast_1d(s)])

    def tangent(s):
        t = xy_at(s + 0.5) - xy_at(s - 0.5)
        return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)

    offsets = np.linspace(-options.turn_smoothing, options.turn_smoothing, 21)
    weights = np.exp(-0.5 * (offsets / max(options.turn_smoothing / 2, 1e-6)) ** 2)
    phase_d, phase_h = rng.uniform(0, 2 * np.pi, 2)
    jitter = np.radians(np.asarray(options.attitude_sigma_deg))[None, :] * rng.standard_normal(
        (n, 3))
    centres = np.zeros((n, 3))
    rotations = np.zeros((n, 3, 3))
    for k, s in enumerate(arc):
        p = xy_at(s)[0]
        t = (weights[:, None] * tangent(s + offsets)).sum(0)
        t /= np.linalg.norm(t)
        left = np.array([-t[1], t[0]])
        towards = side * left  # horizontal direction to the facades
        dd = options.distance_amplitude * math.sin(2 * math.pi * (s - s0) /
                                                   options.distance_period + phase_d)
        p = p - dd * towards
        h = options.flight_height + options.height_amplitude * math.sin(
            2 * math.pi * (s - s0) / options.height_period + phase_h)
        z = ground(p[None])[0] + h
        centres[k] = [p[0], p[1], z]
        heading = towards if options.mode == "sideways" else t
        yaw = math.atan2(heading[1], heading[0]) + jitter[k, 0]
        if options.yaw_offset_deg:
            yaw += math.radians(options.yaw_offset_deg)
        rotations[k] = _camera_rotation(yaw, options.pitch_deg, jitter[k])
    return _flight(options, centres, rotations, arc - s0)


def _camera_rotation(yaw: float, pitch_deg: float, jitter: np.ndarray) -> np.ndarray:
    """cam_from_world for a heading `yaw` (rad, jitter included), tilted down by pitch_deg plus
    jitter[1] and rolled by jitter[2] (rad)."""
    pitch = math.radians(pitch_deg) + jitter[1]
    fwd = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch),
                    -math.sin(pitch)])
    return _look_rotation(fwd, jitter[2])


def _flight(options: FlightOptions, centres: np.ndarray, rotations: np.ndarray,
            arc: np.ndarray) -> Flight:
    names = [f"frame_{k + 1:05d}.jpg" for k in range(len(centres))]
    return Flight(names, centres, rotations, arc, options.image_width, options.image_height,
                  options.focal_length, options.radial_k1, options.calibrated_radial_k1)


def plan_orbit(store, options: FlightOptions, seed: int, ground: GroundModel) -> Flight:
    """One counter-clockwise circle of key frames around `orbit_centre` at `orbit_radius`,
    evenly spaced in angle (starting at a seed-drawn angle), each camera heading for the centre
    (plus yaw_offset_deg) and tilted down by pitch_deg; height above ground as for the other
    modes (flight_height + height_amplitude profile along the circle)."""
    rng = np.random.default_rng([seed, STAGE_FLIGHT])
    n, r = options.num_key_frames, options.orbit_radius
    if options.orbit_centre is not None:
        c = np.asarray(options.orbit_centre, dtype=np.float64)[:2]
    else:
        c = store.bbox_local.mean(axis=0)[:2]
    theta0, phase_h = rng.uniform(0, 2 * np.pi, 2)
    jitter = np.radians(np.asarray(options.attitude_sigma_deg))[None, :] * rng.standard_normal(
        (n, 3))
    theta = theta0 + 2 * np.pi * np.arange(n) / n
    arc = r * (theta - theta0)
    xy = c + r * np.c_[np.cos(theta), np.sin(theta)]
    h = options.flight_height + options.height_amplitude * np.sin(
        2 * np.pi * arc / options.height_period + phase_h)
    centres = np.c_[xy, ground(xy) + h]
    rotations = np.zeros((n, 3, 3))
    for k in range(n):
        yaw = theta[k] + np.pi + jitter[k, 0] + math.radians(options.yaw_offset_deg)
        rotations[k] = _camera_rotation(yaw, options.pitch_deg, jitter[k])
    return _flight(options, centres, rotations, arc)


# ----------------------------------------------------------------------------------------------
# observations


def sample_surface_points(scene: TrueScene, density: float, rng: np.random.Generator,
                          near: np.ndarray | None = None, radius: float = np.inf,
                          labels: tuple[int, ...] | None = None):
    """Area-weighted random points on the true triangles (optionally only triangles within
    `radius` of a point in `near`, and/or with given labels). Returns points, triangle index."""
    from scipy.spatial import cKDTree

    tri = scene.triangles
    keep = np.ones(len(tri), dtype=bool)
    if labels is not None:
        keep &= np.isin(scene.labels, labels)
    if near is not None:
        # distance of the closest vertex or the centroid (triangles are small or near)
        tree = cKDTree(near)
        d = np.minimum.reduce([tree.query(tri[:, i])[0] for i in range(3)] +
                              [tree.query(tri.mean(1))[0]])
        keep &= d < radius
    idx = np.flatnonzero(keep)
    areas = scene.areas[idx]
    total = areas.sum()
    n = int(rng.poisson(density * total)) if density > 0 else 0
    if n == 0 or total <= 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    which = idx[rng.choice(len(idx), size=n, p=areas / total)]
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = tri[which, 0], tri[which, 1], tri[which, 2]
    pts = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
    return pts, which


def visibility(flight: Flight, points: np.ndarray, normals: np.ndarray, raycaster,
               opt: ObservationOptions, progress: bool = True):
    """All (point, frame) pairs where the point projects into the image, lies within the
    distance limits, is seen at an incidence below the limit and is not occluded (the first ray
    hit from the camera is the point itself, +-2 cm). Returns point index, frame index, pixel
    coordinates (no noise) and unit viewing rays."""
    import open3d as o3d
    from scipy.spatial import cKDTree
    from tqdm import tqdm

    tree = cKDTree(points)
    cos_max = math.cos(math.radians(opt.max_incidence_deg))
    P, F, UV, RAY = [], [], [], []
    m = opt.image_margin
    frames = range(len(flight.names))
    for k in tqdm(frames, desc="visibility", disable=None if progress else True, leave=False):
        C = flight.centres[k]
        idx = np.asarray(tree.query_ball_point(C, opt.max_distance), dtype=np.int64)
        if len(idx) == 0:
            continue
        idx.sort()
        uv, z = flight.project(k, points[idx])
        ok = (z > opt.min_distance) & (uv[:, 0] >= m) & (uv[:, 0] < flight.width - m) & (
            uv[:, 1] >= m) & (uv[:, 1] < flight.height - m)
        idx, uv = idx[ok], uv[ok]
        ray = points[idx] - C
        dist = np.linalg.norm(ray, axis=1)
        ray /= dist[:, None]
        inc = np.abs(np.einsum("ij,ij->i", ray, normals[idx])) >= cos_max
        idx, uv, ray, dist = idx[inc], uv[inc], ray[inc], dist[inc]
        if len(idx) == 0:
            continue
        rays = np.concatenate([np.repeat(C[None], len(idx), 0), ray], axis=1).astype(np.float32)
        hit = raycaster.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        vis = hit >= dist - 0.02
        P.append(idx[vis])
        F.append(np.full(vis.sum(), k, dtype=np.int64))
        UV.append(uv[vis])
        RAY.append(ray[vis])
    if not P:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 3)))
    return np.concatenate(P), np.concatenate(F), np.concatenate(UV), np.concatenate(RAY)


@dataclass
class Observations:
    """Tie point tracks and the keypoints of every image."""

    track_xyz: np.ndarray  # (T,3) true local coordinates of each track's point
    obs_track: np.ndarray  # (M,) track index of each observation
    obs_frame: np.ndarray  # (M,) frame index
    obs_kp: np.ndarray  # (M,) keypoint index in its image
    obs_uv_true: np.ndarray  # (M,2)
    keypoints: list[np.ndarray]  # per image (K_i,2) float64, with noise, shuffled
    pairs: dict[tuple[int, int], np.ndarray]  # (frame_i, frame_j) -> (m,2) keypoint indices
    num_outlier_matches: int = 0
    num_candidates: int = 0
    num_visible: int = 0


def simulate_observations(flight: Flight, scene: TrueScene, raycaster,
                          opt: ObservationOptions, seed: int,
                          progress: bool = True) -> Observations:
    rng_pts = np.random.default_rng([seed, STAGE_POINTS])
    rng = np.random.default_rng([seed, STAGE_OBS])
    pts, tri = sample_surface_points(scene, opt.points_per_m2, rng_pts, near=flight.centres,
                                     radius=opt.max_distance)
    normals = scene.normals[tri]
    logger.info("%d candidate feature points on the true surfaces", len(pts))
    p_idx, f_idx, uv, ray = visibility(flight, pts, normals, raycaster, opt, progress)
    num_visible = len(p_idx)
    # detection losses
    det = rng.random(len(p_idx)) < opt.detection_probability
    p_idx, f_idx, uv, ray = p_idx[det], f_idx[det], uv[det], ray[det]
    order = np.lexsort((f_idx, p_idx))
    p_idx, f_idx, uv, ray = p_idx[order], f_idx[order], uv[order], ray[order]
    # tracks: break at frame gaps longer than the matching window and when the viewing
    # direction has turned by more than max_track_view_angle from the track's first view
    new_point = np.r_[True, p_idx[1:] != p_idx[:-1]]
    gap = np.r_[False, np.diff(f_idx) > opt.match_window] & ~new_point
    seg_gap = np.cumsum(new_point | gap)
    first = np.flatnonzero(np.r_[True, seg_gap[1:] != seg_gap[:-1]])
    first_of = first[np.searchsorted(first, np.arange(len(seg_gap)), side="right") - 1]
    cosang = np.clip(np.einsum("ij,ij->i", ray, ray[first_of]), -1, 1)
    seg_ang = np.floor(np.degrees(np.arccos(cosang)) / opt.max_track_view_angle_deg).astype(
        np.int64)
    brk = np.r_[True, (seg_gap[1:] != seg_gap[:-1]) | (seg_ang[1:] != seg_ang[:-1])]
    track_raw = np.cumsum(brk) - 1
    counts = np.bincount(track_raw)
    good = counts[track_raw] >= opt.min_track_length
    track_raw, p_idx, f_idx, uv = track_raw[good], p_idx[good], f_idx[good], uv[good]
    uniq, track = np.unique(track_raw, return_inverse=True)
    track_xyz = pts[p_idx[np.r_[True, track[1:] != track[:-1]]]]
    # noisy keypoints + unmatched ones, shuffled per image
    n_frames = len(flight.names)
    uv_noisy = uv + rng.normal(0.0, opt.pixel_noise, uv.shape)
    uv_noisy[:, 0] = np.clip(uv_noisy[:, 0], 0.0, flight.width - 1e-3)
    uv_noisy[:, 1] = np.clip(uv_noisy[:, 1], 0.0, flight.height - 1e-3)
    kp_index = np.zeros(len(track), dtype=np.int64)
    keypoints = []
    by_frame = np.argsort(f_idx, kind="stable")
    starts = np.searchsorted(f_idx[by_frame], np.arange(n_frames + 1))
    for k in range(n_frames):
        mine = by_frame[starts[k]:starts[k + 1]]
        n_un = int(round(opt.unmatched_ratio * len(mine)))
        extra = np.c_[rng.uniform(0, flight.width, n_un), rng.uniform(0, flight.height, n_un)]
        allkp = np.concatenate([uv_noisy[mine], extra])
        perm = rng.permutation(len(allkp))
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(perm))
        kp_index[mine] = inv[: len(mine)]
        keypoints.append(allkp[perm])
    # matches: every pair of observations of one track within the matching window
    order = np.lexsort((f_idx, track))
    t_s, f_s, k_s = track[order], f_idx[order], kp_index[order]
    I, J, KI, KJ = [], [], [], []
    for off in range(1, opt.match_window + 1):
        a = np.arange(len(t_s) - off)
        b = a + off
        ok = (t_s[a] == t_s[b]) & (f_s[b] - f_s[a] <= opt.match_window)
        if not ok.any():
            break
        I.append(f_s[a[ok]]), J.append(f_s[b[ok]]), KI.append(k_s[a[ok]]), KJ.append(
            k_s[b[ok]])
    I, J = np.concatenate(I), np.concatenate(J)
    KI, KJ = np.concatenate(KI), np.concatenate(KJ)
    order = np.lexsort((J, I))
    I, J, KI, KJ = I[order], J[order], KI[order], KJ[order]
    cut = np.flatnonzero(np.r_[True, (I[1:] != I[:-1]) | (J[1:] != J[:-1]), True])
    pairs: dict[tuple[int, int], np.ndarray] = {}
    n_out_total = 0
    for s, e in zip(cut[:-1], cut[1:]):
        i, j = int(I[s]), int(J[s])
        m = np.stack([KI[s:e], KJ[s:e]], axis=1)
        n_out = rng.binomial(len(m), opt.outlier_ratio) if opt.outlier_ratio > 0 else 0
        if n_out and len(m) + n_out >= opt.min_matches:
            free_i = np.setdiff1d(np.arange(len(keypoints[i])), m[:, 0])
            free_j = np.setdiff1d(np.arange(len(keypoints[j])), m[:, 1])
            n_out = min(n_out, len(free_i), len(free_j))
            out = np.stack([rng.choice(free_i, n_out, replace=False),
                            rng.choice(free_j, n_out, replace=False)], axis=1)
            m = np.concatenate([m, out])
            m = m[rng.permutation(len(m))]
        if len(m) >= opt.min_matches:
            pairs[(i, j)] = m.astype(np.uint32)
            n_out_total += len(m) - (e - s)
    return Observations(track_xyz, track, f_idx, kp_index, uv, keypoints, pairs, n_out_total,
                        len(pts), num_visible)


# ----------------------------------------------------------------------------------------------
# check points and GNSS


@dataclass
class CheckPoints:
    ids: np.ndarray  # (C,) int
    xyz: np.ndarray  # (C,3) local
    obs_frame: np.ndarray
    obs_id: np.ndarray
    obs_uv: np.ndarray  # with noise


def simulate_checkpoints(flight: Flight, scene: TrueScene, raycaster, obs_opt: ObservationOptions,
                         opt: CheckPointOptions, seed: int) -> CheckPoints:
    """Targets on the main wall and roof planes of the true scene, spread out by farthest-point
    sampling among candidates seen in >= min_views key frames."""
    rng = np.random.default_rng([seed, STAGE_CHECK])
    empty = CheckPoints(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64),
                        np.zeros(0, np.int64), np.zeros((0, 2)))
    if opt.count <= 0:
        return empty
    chosen_all = []
    # candidates: a fixed number on walls and on roofs near the flight
    for labels, n_want in ((LABEL_WALL,), opt.count - round(opt.count * opt.roof_fraction)), \
            ((LABEL_ROOF,), round(opt.count * opt.roof_fraction)):
        if n_want <= 0:
            continue
        area = scene.areas[np.isin(scene.labels, labels)].sum()
        density = opt.candidates / 2 / max(area, 1e-9)
        pts, tri = sample_surface_points(scene, density, rng, near=flight.centres,
                                         radius=obs_opt.max_distance, labels=labels)
        if len(pts) == 0:
            continue
        normals = scene.normals[tri]
        p, f, uv, _ = visibility(flight, pts, normals, raycaster, obs_opt, progress=False)
        views = np.bincount(p, minlength=len(pts))
        cand = np.flatnonzero(views >= opt.min_views)
        if len(cand) == 0:
            continue
        # farthest point sampling
        sel = [cand[rng.integers(len(cand))]]
        d = np.linalg.norm(pts[cand] - pts[sel[0]], axis=1)
        while len(sel) < min(n_want, len(cand)):
            nxt = int(np.argmax(d))
            sel.append(cand[nxt])
            d = np.minimum(d, np.linalg.norm(pts[cand] - pts[cand[nxt]], axis=1))
        for s in sel:
            mask = p == s
            chosen_all.append((pts[s], f[mask], uv[mask]))
    if not chosen_all:
        return empty
    # order along the flight (mean frame index), ids from 1
    chosen_all.sort(key=lambda c: float(np.mean(c[1])))
    ids = np.arange(1, len(chosen_all) + 1)
    xyz = np.array([c[0] for c in chosen_all])
    of = np.concatenate([c[1] for c in chosen_all])
    oi = np.concatenate([np.full(len(c[1]), i) for i, c in zip(ids, chosen_all)])
    ouv = np.concatenate([c[2] for c in chosen_all])
    ouv = ouv + rng.normal(0.0, opt.pixel_noise, ouv.shape)
    order = np.lexsort((oi, of))
    return CheckPoints(ids, xyz, of[order], oi[order], ouv[order])


def simulate_gnss(flight: Flight, opt: GNSSOptions, seed: int) -> np.ndarray:
    """Local GNSS positions: truth + white noise + a smooth bias (Gaussian-filtered noise along
    the path with std `bias_sigma` and correlation length `bias_length`) + a constant bias of
    length `bias_magnitude` in a direction uniform on the sphere (drawn from the seed only, so
    the same direction for every magnitude and independent of the other noise)."""
    rng = np.random.default_rng([seed, STAGE_GNSS])
    n = len(flight.centres)
    white_sigma = opt.sigma if opt.white_sigma is None else opt.white_sigma
    white = rng.standard_normal((n, 3)) * np.asarray(white_sigma)
    s = flight.arc
    grid = np.arange(s.min() - 3 * opt.bias_length, s.max() + 3 * opt.bias_length + 1.0, 1.0)
    raw = rng.standard_normal((len(grid), 3))
    sig = max(opt.bias_length / 2.0, 1e-6)
    kx = np.arange(-int(3 * sig), int(3 * sig) + 1)
    kernel = np.exp(-0.5 * (kx / sig) ** 2)
    kernel /= np.sqrt(np.sum(kernel ** 2))  # unit variance after filtering
    smooth = np.stack([np.convolve(raw[:, i], kernel, mode="same") for i in range(3)], axis=1)
    bias = np.stack([np.interp(s, grid, smooth[:, i]) for i in range(3)], axis=1)
    bias *= np.asarray(opt.bias_sigma)
    if opt.bias_magnitude:
        bias = bias + opt.bias_magnitude * constant_bias_direction(seed)
    return flight.centres + white + bias


def constant_bias_direction(seed: int) -> np.ndarray:
    """The unit direction of GNSSOptions.bias_magnitude's bias for a seed (uniform on the
    sphere)."""
    v = np.random.default_rng([seed, STAGE_GNSS, 1]).standard_normal(3)
    return v / np.linalg.norm(v)


# ----------------------------------------------------------------------------------------------
# COLMAP


@contextlib.contextmanager
def quiet_colmap(log_path: Path):
    """Send COLMAP's glog output (and anything else on fds 1/2) to `log_path`."""
    import sys

    sys.stdout.flush()
    sys.stderr.flush()
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "ab") as log:
        saved = os.dup(1), os.dup(2)
        try:
            os.dup2(log.fileno(), 1)
            os.dup2(log.fileno(), 2)
            yield
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])


def make_camera(flight: Flight, true: bool = False):
    """The camera as calibrated (database, COLMAP) or, with true=True, as it really is."""
    import pycolmap

    k1 = flight.k1 if true else flight.k1_calibrated
    cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=flight.width, height=flight.height,
                          params=[flight.focal, flight.width / 2, flight.height / 2, k1])
    cam.camera_id = 1
    cam.has_prior_focal_length = True
    return cam


def write_database(path: Path, flight: Flight, obs: Observations, gnss_crs: np.ndarray | None,
                   gnss_sigma, available: np.ndarray | None = None) -> None:
    """Camera, one rig, one frame per image, images, keypoints, raw matches and pose priors
    (positions in the model CRS, covariance diag(sigma^2), CARTESIAN)."""
    import pycolmap

    db = pycolmap.Database.open(str(path))
    try:
        cam = make_camera(flight)
        cam_id = db.write_camera(cam, use_camera_id=True)
        cam = db.read_camera(cam_id)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(cam.sensor_id)
        rig_id = db.write_rig(rig)
        for k, name in enumerate(flight.names):
            image = pycolmap.Image(name=name, camera_id=cam_id, image_id=k + 1)
            image_id = db.write_image(image, use_image_id=True)
            image = db.read_image(image_id)
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(image.data_id)
            db.write_frame(frame)
            db.write_keypoints(image_id, obs.keypoints[k].astype(np.float32))
        for (i, j), m in obs.pairs.items():
            db.write_matches(i + 1, j + 1, m)
        if gnss_crs is not None:
            write_pose_priors(db, gnss_crs, gnss_sigma, available)
    finally:
        db.close()


def write_pose_priors(db, gnss_crs: np.ndarray, sigma, available: np.ndarray | None) -> None:
    import pycolmap

    cov = np.diag(np.asarray(sigma, dtype=np.float64) ** 2)
    db.clear_pose_priors()
    for k, pos in enumerate(gnss_crs):
        if available is not None and not available[k]:
            continue
        image = db.read_image(k + 1)
        prior = pycolmap.PosePrior(
            position=np.asarray(pos, dtype=np.float64), position_covariance=cov,
            coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN)
        prior.corr_data_id = image.data_id
        db.write_pose_prior(prior)


def truth_two_view_geometries(db_path: Path, flight: Flight, obs: Observations,
                              max_error: float = 4.0) -> None:
    """Two-view geometries from the true relative poses: E, F, inliers with Sampson error below
    `max_error` px (what COLMAP's verification finds without its RANSAC)."""
    import pycolmap

    K = np.array([[flight.focal, 0, flight.width / 2], [0, flight.focal, flight.height / 2],
                  [0, 0, 1]])
    Kinv = np.linalg.inv(K)
    db = pycolmap.Database.open(str(db_path))
    try:
        for (i, j), m in obs.pairs.items():
            R = flight.rotations[j] @ flight.rotations[i].T
            t = flight.translations[j] - R @ flight.translations[i]
            tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
            E = tx @ R
            F = Kinv.T @ E @ Kinv
            x1 = np.c_[obs.keypoints[i][m[:, 0]], np.ones(len(m))]
            x2 = np.c_[obs.keypoints[j][m[:, 1]], np.ones(len(m))]
            Fx1 = x1 @ F.T
            Ftx2 = x2 @ F
            num = np.einsum("ij,ij->i", x2, Fx1) ** 2
            den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
            inl = num / den < max_error ** 2
            tvg = pycolmap.TwoViewGeometry()
            tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            tvg.E = E / np.linalg.norm(E)
            tvg.F = F / np.linalg.norm(F)
            tvg.inlier_matches = m[inl]
            db.write_two_view_geometry(i + 1, j + 1, tvg)
    finally:
        db.close()


def incremental_options(opt: MappingOptions, seed: int):
    import pycolmap

    o = pycolmap.IncrementalPipelineOptions()
    o.extract_colors = False  # there are no image files
    o.num_threads = opt.num_threads
    o.random_seed = seed if opt.random_seed is None else opt.random_seed
    if not opt.refine_intrinsics:
        o.ba_refine_focal_length = False
        o.ba_refine_principal_point = False
        o.ba_refine_extra_params = False
        o.mapper.abs_pose_refine_focal_length = False
        o.mapper.abs_pose_refine_extra_params = False
    if opt.incremental:
        try:
            o.mergedict(dict(opt.incremental))
        except Exception as error:  # pycolmap rejects unknown keys
            raise InputError(f"mapping.incremental: {error}") from None
    return o


def run_mapping(workspace: Path, flight: Flight, obs: Observations, opt: MappingOptions,
                seed: int) -> dict:
    """Geometric verification and COLMAP's incremental mapper; the largest model -> sparse/0.
    Returns statistics (times, models, registered images)."""
    import pycolmap

    db_path = workspace / "database.db"
    log = workspace / "colmap.log"
    stats: dict[str, Any] = {}
    t0 = time.perf_counter()
    if opt.two_view_geometry == "verify":
        pairs_txt = workspace / "pairs.txt"
        pairs_txt.write_text("".join(f"{flight.names[i]} {flight.names[j]}\n"
                                     for i, j in obs.pairs))
        with quiet_colmap(log):
            pycolmap.verify_matches(str(db_path), str(pairs_txt),
                                    pycolmap.TwoViewGeometryOptions())
        pairs_txt.unlink()
    else:
        truth_two_view_geometries(db_path, flight, obs)
    stats["verification_seconds"] = time.perf_counter() - t0
    db = pycolmap.Database.open(str(db_path))
    stats["num_verified_pairs"] = int(db.num_verified_image_pairs())
    stats["num_inlier_matches"] = int(db.num_inlier_matches())
    db.close()
    if not opt.run:
        return stats
    images = workspace / "images"
    images.mkdir(exist_ok=True)  # must exist; COLMAP maps from the database alone
    raw = workspace / "sparse_raw"
    raw.mkdir()
    t0 = time.perf_counter()
    with quiet_colmap(log):
        models = pycolmap.incremental_mapping(str(db_path), str(images), str(raw),
                                              incremental_options(opt, seed))
    stats["mapping_seconds"] = time.perf_counter() - t0
    ordered = sorted(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()),
                     reverse=True)
    sparse = workspace / "sparse"
    sparse.mkdir()
    for i, rec in enumerate(ordered):
        (sparse / str(i)).mkdir()
        rec.write(str(sparse / str(i)))
    shutil.rmtree(raw)
    shutil.rmtree(images)
    stats["num_models"] = len(ordered)
    stats["model_sizes"] = [int(r.num_reg_images()) for r in ordered]
    if ordered:
        best = ordered[0]
        stats["num_registered_images"] = int(best.num_reg_images())
        stats["registered_fraction"] = best.num_reg_images() / len(flight.names)
        stats["num_points3D"] = int(best.num_points3D())
        stats["num_observations"] = int(best.compute_num_observations())
        stats["mean_reprojection_error"] = float(best.compute_mean_reprojection_error())
        stats["mean_track_length"] = float(best.compute_mean_track_length())
    else:
        stats["num_registered_images"] = 0
        stats["registered_fraction"] = 0.0
    if len(ordered) != 1:
        logger.warning("COLMAP produced %d models (sizes %s); sparse/0 is the largest",
                       len(ordered), stats["model_sizes"])
    return stats


def truth_reconstruction(flight: Flight, obs: Observations):
    """The true poses and tie points as a pycolmap Reconstruction (local frame)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(make_camera(flight, true=True))
    for k, name in enumerate(flight.names):
        image = pycolmap.Image(name=name, keypoints=obs.keypoints[k], camera_id=1,
                               image_id=k + 1)
        pose = pycolmap.Rigid3d(np.c_[flight.rotations[k], flight.translations[k]])
        rec.add_image_with_trivial_frame(image, pose)
    order = np.lexsort((obs.obs_frame, obs.obs_track))
    t, f, kp = obs.obs_track[order], obs.obs_frame[order], obs.obs_kp[order]
    cut = np.flatnonzero(np.r_[True, t[1:] != t[:-1], True])
    for s, e in zip(cut[:-1], cut[1:]):
        track = pycolmap.Track()
        for ff, kk in zip(f[s:e], kp[s:e]):
            track.add_element(int(ff) + 1, int(kk))
        rec.add_point3D(obs.track_xyz[t[s]], track)
    return rec


# ----------------------------------------------------------------------------------------------
# the sequence and the scenario workspace


def _fmt(x: float) -> str:
    return repr(float(x))


def _write_lines(path: Path, header: str, lines) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(header)
        for line in lines:
            fh.write(line)
            fh.write("\n")


def _load_store(options: SimulationOptions):
    if options.scene.source == "procedural":
        return procedural_store(options.scene.procedural, options.seed)
    from ..citymodel.read import read_city_model

    bbox = None
    if options.scene.bbox_crs is not None:
        b = np.asarray(options.scene.bbox_crs, dtype=np.float64)
        bbox = b.reshape(2, -1)
    return read_city_model(options.scene.source, lod=options.scene.lod, crs=options.scene.crs,
                           bbox_crs=bbox)


def build_sequence(options: SimulationOptions, out: Path, *, progress: bool = True) -> dict:
    """Everything shared by the scenarios of a sequence, written into `out` (a new directory):
    models/, truth/, database.db with all GNSS priors, gnss_all.txt, check points, sparse/."""
    from ..citymodel.write_citygml import raw_from_store, write_citygml

    t_start = time.perf_counter()
    seed = options.seed
    out.mkdir(parents=True)
    store = _load_store(options)
    ground = GroundModel(store)
    flight = plan_flight(store, options.flight, seed, ground)
    logger.info("%d key frames along %.0f m of path", len(flight.names), flight.arc[-1])
    roi = options.observations.max_distance + 5.0
    scene = build_true_scene(store, options.details, seed, roi_centres=flight.centres,
                             roi_radius=roi, ground=ground, avoid_points=flight.centres)
    logger.info("true scene: %d triangles, %d clutter objects", len(scene.triangles),
                scene.num_clutter_objects)
    raycaster = scene.raycasting_scene()
    obs = simulate_observations(flight, scene, raycaster, options.observations, seed, progress)
    cps = simulate_checkpoints(flight, scene, raycaster, options.observations,
                               options.checkpoints, seed)
    gnss_local = simulate_gnss(flight, options.gnss, seed)
    origin = store.origin
    gnss_crs = gnss_local + origin
    t_built = time.perf_counter()

    # models
    models = out / "models"
    models.mkdir()
    write_citygml(models / "corrected.gml", raw_from_store(store), name="corrected (as given)")
    original = perturb_planes(store, options.model_errors, seed)
    write_citygml(models / "original.gml", raw_from_store(original),
                  name="original (systematic plane errors)")
    det = detailed_polygons(scene, options.model_errors.detailed_min_area)
    det = perturb_polygons(det, options.model_errors.detailed_shift_sigma,
                           options.model_errors.detailed_rotation_sigma_deg, seed, STAGE_DETAILED)
    for i, p in enumerate(det):
        p.exterior = p.exterior + origin
        p.holes = [h + origin for h in p.holes]
        p.gml_id = f"detailed_{i}"
    srs = raw_from_store(store).crs
    from ..citymodel.raw_model import RawCityModel

    write_citygml(models / "detailed.gml",
                  RawCityModel("simulate", "CityGML", "2.0", srs, det,
                               sorted({p.building_id for p in det}), []),
                  name="detailed (true scene planes)")

    # truth
    truth = out / "truth"
    truth.mkdir()
    truth_reconstruction(flight, obs).write_text(str(truth))
    (truth / "origin.txt").write_text(
        "# origin X Y Z: local = model CRS - origin\n"
        f"{_fmt(origin[0])} {_fmt(origin[1])} {_fmt(origin[2])}\n"
        f"# crs: {store.crs.label}\n")
    scene.to_trimesh().export(truth / "true_scene.ply")
    np.save(truth / "true_scene_labels.npy", scene.labels)

    # check points, GNSS
    cp_crs = cps.xyz + origin
    _write_lines(out / "checkpoints.txt", f"# id X Y Z ({store.crs.label})\n",
                 (f"{i} {_fmt(x)} {_fmt(y)} {_fmt(z)}" for i, (x, y, z) in zip(cps.ids, cp_crs)))
    _write_lines(out / "checkpoint_observations.txt",
                 "# image_name id x y (pixels, COLMAP convention)\n",
                 (f"{flight.names[f]} {i} {_fmt(u)} {_fmt(v)}"
                  for f, i, (u, v) in zip(cps.obs_frame, cps.obs_id, cps.obs_uv)))
    sig = options.gnss.sigma
    _write_lines(out / "gnss_all.txt", f"# image_name X Y Z sX sY sZ ({store.crs.label})\n",
                 (f"{n} {_fmt(p[0])} {_fmt(p[1])} {_fmt(p[2])} {sig[0]} {sig[1]} {sig[2]}"
                  for n, p in zip(flight.names, gnss_crs)))

    # COLMAP
    write_database(out / "database.db", flight, obs, gnss_crs, sig)
    stats: dict[str, Any] = {
        "sequence": options.name,
        "seed": seed,
        "sequence_key": sequence_key(options),
        "crs": store.crs.label,
        "origin": [float(v) for v in origin],
        "num_key_frames": len(flight.names),
        "path_length_m": float(flight.arc[-1]),
        "image_size": [flight.width, flight.height],
        "focal_length_px": flight.focal,
        "num_model_faces": store.num_faces,
        "num_buildings": store.num_buildings,
        "num_true_triangles": int(len(scene.triangles)),
        "num_clutter_objects": scene.num_clutter_objects,
        "num_detailed_polygons": len(det),
        "num_candidate_points": obs.num_candidates,
        "num_visible_observations": obs.num_visible,
        "num_tie_points": int(len(obs.track_xyz)),
        "num_image_observations": int(len(obs.obs_track)),
        "mean_track_length_true": float(len(obs.obs_track) / max(len(obs.track_xyz), 1)),
        "num_keypoints": int(sum(len(k) for k in obs.keypoints)),
        "num_matched_pairs": len(obs.pairs),
        "num_matches": int(sum(len(m) for m in obs.pairs.values())),
        "num_outlier_matches": int(obs.num_outlier_matches),
        "num_checkpoints": int(len(cps.ids)),
        "num_checkpoint_observations": int(len(cps.obs_id)),
        "build_seconds": t_built - t_start,
    }
    stats.update(run_mapping(out, flight, obs, options.mapping, seed))
    stats["total_seconds"] = time.perf_counter() - t_start
    stats["options"] = options.sequence_dict()
    (out / "simulation.json").write_text(json.dumps(stats, indent=2, default=str))
    logger.info(
        "sequence %s: %d key frames, %d tie points, %d observations; COLMAP registered %s/%d "
        "images in %s model(s), %.0f s in total", options.name, stats["num_key_frames"],
        stats["num_tie_points"], stats["num_image_observations"],
        stats.get("num_registered_images"), stats["num_key_frames"], stats.get("num_models"),
        stats["total_seconds"])
    return stats


README = """# Simulated COLMAP workspace: {name}

Made by `colmap-citymodel simulate` (colmap_citymodel/simulate/), seed {seed},
sequence {sequence} (key {key}). Scenario: given model `{model}`, GNSS `{gnss}`.

| file | content |
|---|---|
| `database.db` | COLMAP database: camera (SIMPLE_PINHOLE, fixed), rig, frames, images, keypoints, matches incl. wrong ones, two-view geometries (COLMAP's own verification), pose priors (GNSS, model CRS, CARTESIAN, covariance diag(sigma^2)) for the images with GNSS in this scenario |
| `sparse/0` | COLMAP's incremental mapper result (arbitrary frame); `sparse/1..` only if COLMAP split the block |
| `truth/` | true poses and tie points (COLMAP text model) in the LOCAL frame = model CRS - `truth/origin.txt`; `true_scene.ply` the true mesh (same frame), `true_scene_labels.npy` its triangle labels (0 wall, 1 roof, 2 detail, 3 clutter, 4 ground) |
| `given_model.gml` | the building model of this scenario (CityGML 2.0, model CRS); absent when the scenario has none |
| `models/` | all variants: `corrected.gml` (the LOD2 model as given: only generalisation effects), `original.gml` (plus systematic plane errors), `detailed.gml` (the true building planes, LOD3-like, stored as LOD2 surfaces) |
| `checkpoints.txt` | `id X Y Z` true check point coordinates (model CRS) |
| `checkpoint_observations.txt` | `image_name id x y` image observations of check points (1 px noise); not in the database |
| `gnss.txt` | `image_name X Y Z sX sY sZ` GNSS available in this scenario (model CRS) |
| `gnss_all.txt` | GNSS of every key frame (same noise realisation) |
| `scenario.toml` | the scenario file (`sequence.toml`: the sequence file it names) |
| `simulation.json` | options, sizes, timings |
| `colmap.log` | COLMAP's log |

Sizes: {frames} key frames, {tps} tie points, {obs} image observations, {cps} check points;
COLMAP registered {reg} of {frames} images ({models} model(s)).
"""


def derive_scenario(seq_dir: Path, options: SimulationOptions, out: Path) -> dict:
    """A scenario workspace from a built sequence: copies, then restricts GNSS priors and picks
    the given model."""
    import pycolmap

    shutil.copytree(seq_dir, out)
    stats = json.loads((out / "simulation.json").read_text())
    sc = options.scenario
    names, lines = [], []
    for line in (out / "gnss_all.txt").read_text().splitlines():
        if line.startswith("#") or not line.strip():
            continue
        names.append(line.split()[0])
        lines.append(line)
    n = len(names)
    available = np.zeros(n, dtype=bool)
    if sc.gnss == "all":
        available[:] = True
    elif sc.gnss == "first":
        available[: max(sc.gnss_first_n, 0)] = True
    if sc.gnss != "none":
        hdr = (out / "gnss_all.txt").read_text().splitlines()[0] + "\n"
        _write_lines(out / "gnss.txt", hdr, (l for l, a in zip(lines, available) if a))
    db = pycolmap.Database.open(str(out / "database.db"))
    try:
        priors = db.read_all_pose_priors()
        keep_ids = {k + 1 for k in np.flatnonzero(available)}
        db.clear_pose_priors()
        for p in priors:
            if p.corr_data_id.id in keep_ids:
                p.pose_prior_id = pycolmap.INVALID_POSE_PRIOR_ID
                db.write_pose_prior(p)
    finally:
        db.close()
    if sc.model != "none":
        shutil.copy2(out / "models" / f"{sc.model}.gml", out / "given_model.gml")
    for i, src in enumerate(options.source_files):
        dst = "scenario.toml" if i == len(options.source_files) - 1 else "sequence.toml"
        shutil.copy2(src, out / dst)
    stats["scenario"] = dataclasses.asdict(sc)
    stats["num_gnss"] = int(available.sum())
    (out / "simulation.json").write_text(json.dumps(stats, indent=2, default=str))
    (out / "README.md").write_text(README.format(
        name=sc.name or options.name, seed=options.seed, sequence=options.name,
        key=stats["sequence_key"], model=sc.model, gnss=sc.gnss if sc.gnss != "first" else
        f"first {sc.gnss_first_n} key frames", frames=stats["num_key_frames"],
        tps=stats["num_tie_points"], obs=stats["num_image_observations"],
        cps=stats["num_checkpoints"], reg=stats.get("num_registered_images", "-"),
        models=stats.get("num_models", "-")))
    return stats


def main(scenario_path: str | Path, output_path: str | Path, *, seed: int | None = None,
         cache_path: str | Path | None = None, overwrite: bool = False,
         progress: bool = True) -> Path:
    """Build the scenario's workspace at `output_path` (see the module docstring); returns it.

    cache_path: directory of built sequences (`<name>-<hash>`), reused by later scenarios of the
    same sequence; None builds the sequence afresh. The workspace appears atomically."""
    options = load_scenario(scenario_path)
    if seed is not None:
        options.seed = int(seed)
    out = Path(output_path).resolve()
    if out.exists():
        if not overwrite:
            raise InputError("output workspace exists (use --overwrite to replace it)", out)
    out.parent.mkdir(parents=True, exist_ok=True)
    key = sequence_key(options)
    tmp_root = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        if cache_path is not None:
            cache = Path(cache_path).resolve()
            cache.mkdir(parents=True, exist_ok=True)
            seq_dir = cache / f"{options.name}-{key}"
            if not (seq_dir / "simulation.json").exists():
                seq_tmp = Path(tempfile.mkdtemp(prefix=f".{seq_dir.name}.", dir=cache))
                try:
                    build_sequence(options, seq_tmp / "seq", progress=progress)
                    if seq_dir.exists():
                        shutil.rmtree(seq_dir)
                    os.replace(seq_tmp / "seq", seq_dir)
                finally:
                    shutil.rmtree(seq_tmp, ignore_errors=True)
            else:
                logger.info("reusing sequence %s", seq_dir)
        else:
            seq_dir = tmp_root / "sequence"
            build_sequence(options, seq_dir, progress=progress)
        derive_scenario(seq_dir, options, tmp_root / "workspace")
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp_root / "workspace", out)
    finally:
        shutil.rmtree(tmp_root, ignore_errors=True)
    logger.info("wrote %s", out)
    return out
