"""Scenario files of the simulator: the options of scene, flight, observations, check points,
GNSS and mapping as dataclasses, read from TOML and checked."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import InputError
from .render.options import RenderOptions
from .scene import DetailOptions, ModelErrorOptions, ProceduralOptions

# Bump when the simulation changes in a way that makes cached sequences stale.
SIMULATOR_VERSION = 1


MODEL_VARIANTS = ("detailed", "corrected", "original", "none")


FLIGHT_MODES = ("sideways", "forward", "orbit")


# Options left out of the sequence key while they hold these defaults, so that sequences
# cached without them keep their keys.
_KEY_NEUTRAL = {"flight": {"yaw_offset_deg": 0.0, "orbit_centre": None, "orbit_radius": 35.0},
                "gnss": {"bias_magnitude": 0.0, "outliers": 0, "outlier_range": (10.0, 30.0),
                         "step_magnitude": 0.0, "step_range": (0.3, 0.7)},
                "scene": {"target_crs": None},
                # which marks are written as control changes no simulated value
                "checkpoints": {"control": 5},
                "model_errors": {"missing_buildings": 0, "extra_buildings": 0,
                                 "extra_size_range": (8.0, 16.0),
                                 "extra_height_range": (5.0, 14.0)},
                "observations": {"ground_points_per_m2": None,
                                 "ground_max_incidence_deg": None},
                "details": {"kerb_height": 0.0, "sidewalk_width": 3.0,
                            "road_cross_slope": 0.0, "furniture_spacing": 0.0,
                            "dormer_probability": 0.0}}


@dataclass
class SceneOptions:
    source: str = "procedural"  # "procedural" or a CityGML/CityJSON file/directory
    lod: int = 2
    crs: str | None = None  # CRS to assume when the file names none
    # projected CRS to reproject the model to (a geographic model such as PLATEAU's EPSG:6697
    # needs one: the simulation works in metres); None: the model's own CRS
    target_crs: str | None = None
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
    pitch_deg: float = 20.0  # camera tilted down (deg; 90: a nadir camera)
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
    # The ground's features (road markings, kerbs, paving): their density (None: as the
    # other surfaces') and the steepest incidence at which they are still matched (None: as
    # the others'); a street camera sees the road at grazing angles.
    ground_points_per_m2: float | None = None
    ground_max_incidence_deg: float | None = None


@dataclass
class CheckPointOptions:
    count: int = 30
    roof_fraction: float = 0.3
    min_views: int = 4
    candidates: int = 20000
    pixel_noise: float = 1.0
    # How many of the targets are written as control marks (gcp_list.txt), spread along the
    # flight; the others are check marks (checkpoints_gcp_list.txt).
    control: int = 5


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
    # Gross errors (a wrong fix, a change of satellites or of correction service), drawn from
    # their own random stream so that the noise above stays as it is: `outliers` key frames
    # (never the first or last) each off by a length drawn from outlier_range (m), and from a
    # point along the path drawn from step_range (share of the path length) on, every position
    # moved by step_magnitude (m); each in a direction uniform on the sphere. 0: none.
    outliers: int = 0
    outlier_range: tuple[float, float] = (10.0, 30.0)
    step_magnitude: float = 0.0
    step_range: tuple[float, float] = (0.3, 0.7)


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
    # A DTM beside the model (dtm/dtm_<k>.tif, from truth/ground.tif): dtm_tiles tiles along
    # x, each with its own height offset ~ N(0, dtm_offset_sigma^2), white noise dtm_noise (m)
    # per 1 m post.
    dtm: bool = False
    dtm_tiles: int = 2
    dtm_offset_sigma: float = 0.10
    dtm_noise: float = 0.15
    # A wrong given model (its datum, not its shape): turned by model_turn_deg (counter-
    # clockwise seen from above) about the vertical through model_turn_centre (local xy, the
    # truth's frame; None: the centre of the true camera centres), then moved by model_shift
    # (m, x y z). The truth, the DTM and the other models/ variants stay where they are.
    model_shift: tuple[float, float, float] = (0.0, 0.0, 0.0)
    model_turn_deg: float = 0.0
    model_turn_centre: list[float] | None = None


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
    # rendered images of the key frames (simulate --render); part of the sequence when enabled
    render: RenderOptions = field(default_factory=RenderOptions)
    scenario: ScenarioOptions = field(default_factory=ScenarioOptions)
    # files the options came from (copied into the workspace)
    source_files: list[str] = field(default_factory=list)

    def sequence_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("scenario")
        d.pop("source_files")
        if not self.render.enabled:  # sequences without images keep their keys
            d.pop("render")
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
    if o.gnss.outliers < 0 or o.gnss.step_magnitude < 0:
        bad("gnss.outliers and gnss.step_magnitude must not be negative")
    if not 0.0 <= o.gnss.step_range[0] <= o.gnss.step_range[1] <= 1.0:
        bad("gnss.step_range must be [a, b] with 0 <= a <= b <= 1 (shares of the path)")
    if o.model_errors.missing_buildings < 0 or o.model_errors.extra_buildings < 0:
        bad("model_errors.missing_buildings and extra_buildings must not be negative")
    if o.scenario.model == "none" and (any(o.scenario.model_shift)
                                       or o.scenario.model_turn_deg):
        bad("scenario.model_shift / model_turn_deg need a given model (scenario.model)")
    if o.scenario.model_turn_centre is not None and len(o.scenario.model_turn_centre) != 2:
        bad("scenario.model_turn_centre must be [x, y] (local metres)")
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
    for problem in o.render.validate():
        bad(problem)


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


#: Random streams: each stage of a sequence draws from its own seed (seed, stage), so that
#: changing one stage's options leaves the others' draws as they were.
STAGE_FLIGHT, STAGE_POINTS, STAGE_OBS, STAGE_CHECK, STAGE_GNSS, STAGE_DETAILED = 21, 22, 23, 24, \
    25, 26
STAGE_GNSS_GROSS, STAGE_BUILDINGS = 27, 28
