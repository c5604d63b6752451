"""The blocks of the generalisation benchmark (bench_generalisation.py): real tiles, geometry
families, and the seeded drawing of blocks with their model errors, GNSS and wrong models.

A block is a simulator scenario (colmap_citymodel.simulate) plus what refine is given: the
tile and the family fix its flight, the rest is drawn per block. Candidates are drawn one after
the other from `np.random.default_rng([seed, i])`; each goes to the split its simulation seed
hashes to ("dev" or "held_out", `split_of`), until each split has its share. Within a split the
family, the tile, the GNSS model, the model level, the DTM and the wrong models run through
seeded random permutations (`cycled`), so that both splits hold the same mix and any prefix
covers all families. Drawing reads the tiles only (no simulation): it is fast and
deterministic, and a longer run's first blocks are a shorter run's blocks.
"""

from __future__ import annotations

import hashlib
import math
import zlib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import Point, Polygon

ROOT = Path(__file__).resolve().parents[1]
#: The tiles, relative to the repository (a block's description is the same in any checkout).
DATA_REL = Path("tests") / "data"

FAMILIES = ("drive_forward", "drive_side", "orbit_building", "orbit_block", "nadir_grid",
            "oblique_ring", "video")
GNSS_MODELS = ("white", "constant_bias", "slow_bias", "jumps", "rtk", "none")
MODEL_LEVELS = ("detailed", "corrected", "original", "harsh")
WRONG_KINDS = ("shifted", "shifted", "rotated", "neighbour")
SPLITS = ("dev", "held_out")
#: Of every 9 blocks with GNSS in a split, 2 get a wrong model (22 %; with the blocks without
#: GNSS, which never get one, about 18 % of all blocks).
WRONG_CYCLE = (True, True, False, False, False, False, False, False, False)
#: Chance of a block's given model lacking one building near the flight, and of it holding
#: one box building the true scene lacks (independent).
MISSING_CHANCE, EXTRA_CHANCE = 0.2, 0.2
#: Stated GNSS sigma (m, E N U) of every GNSS model but RTK.
GNSS_SIGMA = [3.0, 3.0, 5.0]
#: Draws of a family's geometry tried on a tile before the drawing stops with an error.
FAMILY_TRIES = 10
#: The location hint of a block without GNSS: this far (m) from the true block centre.
HINT_RANGE = (10.0, 50.0)


@dataclass
class Tile:
    """A real tile of tests/data (or the procedural street): where it is, how the simulator
    reads it, and the families it can hold (the others with the reason they are left out)."""

    name: str
    city: str
    format: str
    scene: dict
    families: tuple[str, ...]
    skipped: dict[str, str] = field(default_factory=dict)


_ALL = FAMILIES
_STREET = ("drive_forward", "drive_side")
TILES = {
    "berlin_block": Tile("berlin_block", "Berlin", "CityGML",
                         {"source": str(DATA_REL / "citygml/berlin/3910_5819.gml")}, _ALL),
    "berlin_corner": Tile("berlin_corner", "Berlin", "CityGML",
                          {"source": str(DATA_REL / "citygml/berlin/3920_5820.gml")},
                          tuple(f for f in FAMILIES if f != "orbit_block"),
                          {"orbit_block": "the corner building has one neighbour of 40 m2 or "
                                          "more within 60 m"}),
    "nrw": Tile("nrw", "NRW", "CityGML",
                {"source": str(DATA_REL / "citygml/nrw/LoD2_32_328_5725_1_NW.gml")},
                ("orbit_building", "video"),
                {f: "two buildings (108 and 10 m2, 2.4 m high) 700 m apart: no street front, "
                    "no block, a grid or ring would see one low roof"
                 for f in (*_STREET, "orbit_block", "nadir_grid", "oblique_ring")}),
    "munich": Tile("munich", "Munich", "CityGML",
                   {"source": str(DATA_REL / "citygml/tum2twin")}, _ALL),
    "tokyo": Tile("tokyo", "Tokyo", "CityGML",
                  {"source": str(DATA_REL / "citygml/plateau/53394517_bldg_6697_op_CityGML2.gml"),
                   "target_crs": "EPSG:6677"},
                  tuple(f for f in FAMILIES if f != "orbit_block"),
                  {"orbit_block": "one building in the tile"}),
    "delft_3dbag": Tile("delft_3dbag", "Delft", "CityJSON",
                        {"source": str(DATA_REL / "cityjson/3dbag_b2.city.json")},
                        ("orbit_building", "oblique_ring", "video"),
                        {**{f: "two semi-detached houses (28 x 27 m): no street front long "
                               "enough" for f in _STREET},
                         "orbit_block": "two buildings only",
                         "nadir_grid": "two small roofs: a grid of 30 images sees ground"}),
    "den_haag": Tile("den_haag", "The Hague", "CityJSON",
                     {"source": str(DATA_REL / "cityjson/DH_01_subs.city.json"),
                      "crs": "EPSG:7415"},
                     ("orbit_building", "video"),
                     {f: "four small buildings (47-81 m2) 80-240 m apart: no street front, no "
                         "block, a grid or ring would see one roof"
                      for f in (*_STREET, "orbit_block", "nadir_grid", "oblique_ring")}),
    "rotterdam": Tile("rotterdam", "Rotterdam", "CityJSON",
                      {"source": str(DATA_REL / "cityjson/rotterdam_subset.json"),
                       "crs": "EPSG:7415"}, _ALL),
    "street": Tile("street", "procedural street", "procedural", {"source": "procedural"}, _ALL),
}


# ----------------------------------------------------------------------------------------------
# tiles as the simulator reads them

@dataclass
class Building:
    id: str
    footprint: Polygon  # local xy (the simulator's frame: the model CRS minus its origin)
    height: float  # highest minus lowest vertex (m)

    @property
    def centre(self) -> np.ndarray:
        return np.array([self.footprint.centroid.x, self.footprint.centroid.y])

    @property
    def radius(self) -> float:
        """Largest distance of the footprint's outline from its centre (m)."""
        return _reach(self.footprint, self.centre)


def _reach(footprint, centre: np.ndarray) -> float:
    """Largest distance of a footprint's outline (its convex hull) from `centre` (m)."""
    xy = np.asarray(footprint.convex_hull.exterior.coords)
    return float(np.max(np.linalg.norm(xy - centre, axis=1)))


@dataclass
class TileModel:
    store: object  # PlaneStore, local frame as in the simulator
    buildings: list[Building]


def tile_model(tile: Tile, num_buildings: int = 0, seed: int = 0) -> TileModel:
    """The tile's store and buildings as the simulator reads them (the procedural street: its
    `num_buildings` houses for a scene `seed`)."""
    if tile.scene["source"] == "procedural":
        return _procedural_model(num_buildings, seed)
    return _real_model(tile.name)


@lru_cache(maxsize=None)
def _real_model(name: str) -> TileModel:
    from colmap_citymodel.citymodel.read import read_city_model

    scene = TILES[name].scene
    store = read_city_model(ROOT / scene["source"], crs=scene.get("crs"),
                            target_crs=scene.get("target_crs"))
    return TileModel(store, _buildings(store))


@lru_cache(maxsize=64)
def _procedural_model(num_buildings: int, seed: int) -> TileModel:
    from colmap_citymodel.simulate.scene import ProceduralOptions, procedural_store

    store = procedural_store(ProceduralOptions(num_buildings=num_buildings), seed)
    return TileModel(store, _buildings(store))


def _buildings(store) -> list[Building]:
    from colmap_citymodel.simulate.scene import building_footprints

    heights: dict[str, list[float]] = {}
    for face in store.faces:
        z = store.vertices[face.exterior][:, 2]
        heights.setdefault(face.building_id, []).extend([z.min(), z.max()])
    return [Building(b, fp, float(np.ptp(heights[b])))
            for b, fp in sorted(building_footprints(store).items()) if fp.area > 1.0]


# ----------------------------------------------------------------------------------------------
# geometry families: each returns (flight, observations, details, region) in local metres;
# region: the ground the block covers (for placing wrong models and checking their overlap)

def _u(rng, lo, hi, digits=1) -> float:
    return round(float(rng.uniform(lo, hi)), digits)


def _street_details(rng) -> dict:
    """Kerbs, pavements and a cambered road beside the footprints (street-level families)."""
    return {"ground_cell": 1.0, "kerb_height": _u(rng, 0.10, 0.18, 2), "sidewalk_width": 3.0,
            "road_cross_slope": _u(rng, 0.01, 0.03, 3)}


def _loop_section(model: TileModel, rng, facade_distance: float, length: float):
    """A start point on the path around the tile's buildings (the simulator's loop at this
    facade distance) and the section of the path a flight of `length` m covers; None when the
    loop is shorter."""
    from shapely.ops import substring

    from colmap_citymodel.simulate.flight import flight_path
    from colmap_citymodel.simulate.scenario import FlightOptions

    line, _ = flight_path(model.store, FlightOptions(facade_distance=facade_distance))
    if line.length < length + 5.0:
        return None
    s0 = float(rng.uniform(0.0, line.length))
    start = line.interpolate(s0)
    s1 = s0 + length
    parts = [substring(line, s0, min(s1, line.length))]
    if s1 > line.length:
        parts.append(substring(line, 0.0, s1 - line.length))
    return [round(start.x, 2), round(start.y, 2)], shapely.unary_union(parts)


def drive_forward(model: TileModel, rng):
    """A vehicle camera 2 m above the road looking along it, turned 15-30 deg towards the
    facades (a mobile-mapping car's front camera)."""
    d, frames = _u(rng, 7.0, 11.0), int(rng.integers(30, 61))
    section = _loop_section(model, rng, d, frames * 2.2)
    if section is None:
        return None
    start, path = section
    flight = {"mode": "forward", "facade_distance": d, "distance_amplitude": 0.0,
              "start_xy": start, "num_key_frames": frames, "spacing": 2.0,
              "spacing_jitter": 0.4, "flight_height": 2.0, "height_amplitude": 0.0,
              "pitch_deg": 2.0, "yaw_offset_deg": _u(rng, 15.0, 30.0),
              "attitude_sigma_deg": [0.5, 0.3, 0.3], "image_width": 2464, "image_height": 2056,
              "focal_length": _u(rng, 1800.0, 2600.0, 0)}
    obs = {"points_per_m2": _u(rng, 3.0, 5.0), "ground_points_per_m2": _u(rng, 1.5, 2.5),
           "ground_max_incidence_deg": 86.0, "max_distance": 40.0}
    return flight, obs, _street_details(rng), path.buffer(d + 15.0)


def drive_side(model: TileModel, rng):
    """A vehicle camera 2 m above the road looking sideways at the facades, a little up."""
    d, frames = _u(rng, 8.0, 15.0), int(rng.integers(35, 71))
    spacing = _u(rng, 1.0, 1.5, 2)
    section = _loop_section(model, rng, d, frames * (spacing + 0.15))
    if section is None:
        return None
    start, path = section
    flight = {"mode": "sideways", "facade_distance": d, "distance_amplitude": 0.0,
              "start_xy": start, "num_key_frames": frames, "spacing": spacing,
              "spacing_jitter": 0.3, "flight_height": _u(rng, 1.8, 2.5, 2),
              "height_amplitude": 0.0, "pitch_deg": _u(rng, -12.0, -3.0),
              "attitude_sigma_deg": [0.5, 0.3, 0.3], "image_width": 1936, "image_height": 1216,
              "focal_length": _u(rng, 1100.0, 1500.0, 0)}
    obs = {"points_per_m2": _u(rng, 2.5, 4.0), "ground_points_per_m2": _u(rng, 1.0, 2.0),
           "ground_max_incidence_deg": 86.0, "max_distance": 35.0}
    return flight, obs, _street_details(rng), path.buffer(d + 10.0)


def video(model: TileModel, rng):
    """A short hand-held video: a walker 1.5-1.8 m above the pavement filming the facades
    5-12 m away, a frame every 0.5-0.9 m, shaky."""
    d, frames = _u(rng, 5.0, 12.0), int(rng.integers(20, 41))
    spacing = _u(rng, 0.5, 0.8, 2)
    section = _loop_section(model, rng, d, frames * (spacing + 0.05))
    if section is None:
        return None
    start, path = section
    flight = {"mode": "sideways", "facade_distance": d, "distance_amplitude": _u(rng, 0.0, 1.0),
              "distance_period": 30.0, "start_xy": start, "num_key_frames": frames,
              "spacing": spacing, "spacing_jitter": 0.1, "flight_height": _u(rng, 1.5, 1.8, 2),
              "height_amplitude": 0.1, "height_period": 10.0, "pitch_deg": _u(rng, -15.0, 0.0),
              "attitude_sigma_deg": [2.0, 1.5, 1.5], "image_width": 1920, "image_height": 1080,
              "focal_length": _u(rng, 1300.0, 1700.0, 0)}
    obs = {"points_per_m2": _u(rng, 4.0, 6.0), "ground_points_per_m2": _u(rng, 1.5, 3.0),
           "ground_max_incidence_deg": 86.0, "max_distance": 30.0}
    return flight, obs, _street_details(rng), path.buffer(d + 10.0)


def _uav_camera(rng) -> dict:
    return {"image_width": 4000, "image_height": 3000, "focal_length": _u(rng, 2600, 3200, 0),
            "attitude_sigma_deg": [1.0, 0.8, 0.8]}


def _orbit(centre, radius, height, aim, frames, rng) -> dict:
    """An orbit whose camera looks at height `aim` above the ground at the centre."""
    pitch = math.degrees(math.atan2(height - aim, radius)) + rng.uniform(-5.0, 5.0)
    return {"mode": "orbit", "orbit_centre": [round(float(c), 2) for c in centre],
            "orbit_radius": round(radius, 1), "num_key_frames": frames,
            "flight_height": round(height, 1), "height_amplitude": _u(rng, 0.0, 2.0),
            "pitch_deg": round(float(np.clip(pitch, 15.0, 65.0)), 1)}


def orbit_building(model: TileModel, rng):
    """A UAV orbit round one building, 12-30 m outside its outline, 5-25 m above its roof."""
    candidates = [b for b in model.buildings if b.footprint.area >= 40.0 and b.height >= 2.0]
    b = candidates[int(rng.integers(len(candidates)))]
    radius = min(b.radius + rng.uniform(12.0, 30.0), 120.0)
    height = b.height + rng.uniform(5.0, 25.0)
    flight = {**_orbit(b.centre, radius, height, 0.5 * b.height, int(rng.integers(36, 73)), rng),
              **_uav_camera(rng)}
    reach = math.hypot(radius + b.radius, height) + 10.0
    obs = {"points_per_m2": _u(rng, 0.4, 0.8, 2), "ground_points_per_m2": _u(rng, 0.15, 0.3, 2),
           "max_distance": round(reach, 1)}
    return flight, obs, {}, Point(*b.centre).buffer(radius)


def _clusters(model: TileModel, radius: float, size: int) -> list[list[Building]]:
    """Groups of at least `size` buildings (40 m2 or more) whose centres lie within `radius`
    of one of them."""
    big = [b for b in model.buildings if b.footprint.area >= 40.0]
    out = []
    for b in big:
        members = [o for o in big if np.linalg.norm(o.centre - b.centre) <= radius]
        if len(members) >= size:
            out.append(members)
    return out


def orbit_block(model: TileModel, rng):
    """A UAV orbit round a group of three or more buildings."""
    clusters = _clusters(model, 60.0, 3)
    if not clusters:
        return None
    members = clusters[int(rng.integers(len(clusters)))]
    union = shapely.unary_union([m.footprint for m in members])
    centre = np.array([union.centroid.x, union.centroid.y])
    extent = max(_reach(m.footprint, centre) for m in members)
    top = max(m.height for m in members)
    radius = min(extent + rng.uniform(10.0, 25.0), 110.0)
    height = top + rng.uniform(10.0, 35.0)
    flight = {**_orbit(centre, radius, height, 0.3 * top, int(rng.integers(40, 73)), rng),
              **_uav_camera(rng)}
    reach = math.hypot(radius + extent, height) + 10.0
    obs = {"points_per_m2": _u(rng, 0.25, 0.5, 2), "ground_points_per_m2": _u(rng, 0.1, 0.2, 2),
           "max_distance": round(reach, 1)}
    return flight, obs, {}, Point(*centre).buffer(radius)


def _block_centre(model: TileModel, rng) -> np.ndarray:
    """A random building's centre, or the centre of a group of buildings around it."""
    big = [b for b in model.buildings if b.footprint.area >= 40.0]
    b = big[int(rng.integers(len(big)))]
    near = [o.centre for o in big if np.linalg.norm(o.centre - b.centre) <= 50.0]
    return np.mean(near, axis=0)


def nadir_grid(model: TileModel, rng):
    """A UAV mapping flight: a nadir camera 50-80 m up on 3-5 strips (75 % forward, 45-60 %
    side overlap) over a random part of the tile, the strips turned by a random heading."""
    height = _u(rng, 50.0, 80.0)
    spacing = round(0.21 * height - 0.5, 1)  # plus half the 1 m jitter: 75 % forward overlap
    gap = round((1.0 - rng.uniform(0.45, 0.6)) * height * 2464 / 2400, 1)
    strips = int(rng.integers(3, 6))
    per_strip = int(np.clip(rng.integers(8, 15), math.ceil(34 / strips), 70 // strips))
    length = (per_strip - 1) * (spacing + 0.5)
    centre, yaw = _block_centre(model, rng), rng.uniform(0.0, math.pi)
    rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    points = []
    for k in range(strips):
        y = (k - (strips - 1) / 2) * gap
        ends = [[-length / 2, y], [length / 2, y]]
        points += ends if k % 2 == 0 else ends[::-1]
    waypoints = (np.asarray(points) @ rot.T + centre).round(2)
    path = length * strips + gap * (strips - 1)
    flight = {"mode": "forward", "waypoints": waypoints.tolist(),
              "num_key_frames": int(path / (spacing + 0.5)) - 1, "spacing": spacing,
              "spacing_jitter": 1.0, "distance_amplitude": 0.0, "flight_height": height,
              "height_amplitude": 0.0, "pitch_deg": 90.0, "turn_smoothing": 2.0,
              "attitude_sigma_deg": [1.0, 0.5, 0.5], "image_width": 2464,
              "image_height": 2056, "focal_length": 2400.0}
    obs = {"points_per_m2": _u(rng, 1.0, 1.5), "ground_points_per_m2": _u(rng, 0.3, 0.5),
           "max_distance": round(1.6 * height, 1), "match_window": 2 * per_strip + 4}
    details = {"ground_cell": 2.0, "kerb_height": _u(rng, 0.10, 0.18, 2),
               "road_cross_slope": _u(rng, 0.01, 0.03, 3)}
    return flight, obs, details, shapely.MultiPoint(waypoints).convex_hull.buffer(10.0)


def oblique_ring(model: TileModel, rng):
    """A UAV ring 60-120 m from the centre of a part of the tile, looking down 35-50 deg at
    it with a longer lens (an oblique survey of a quarter)."""
    centre = _block_centre(model, rng)
    radius, pitch = _u(rng, 60.0, 120.0), _u(rng, 35.0, 50.0)
    height = radius * math.tan(math.radians(pitch)) * rng.uniform(0.9, 1.05)
    flight = {"mode": "orbit", "orbit_centre": centre.round(2).tolist(), "orbit_radius": radius,
              "num_key_frames": int(rng.integers(36, 61)), "flight_height": round(height, 1),
              "height_amplitude": _u(rng, 0.0, 3.0), "pitch_deg": pitch,
              "image_width": 4000, "image_height": 3000,
              "focal_length": _u(rng, 3500.0, 4500.0, 0), "attitude_sigma_deg": [1.0, 0.8, 0.8]}
    reach = math.hypot(radius, height) + 50.0
    obs = {"points_per_m2": _u(rng, 0.15, 0.3, 2), "ground_points_per_m2": _u(rng, 0.05, 0.1, 2),
           "max_distance": round(reach, 1)}
    return flight, obs, {}, Point(*centre).buffer(radius)


FAMILY_BUILDERS = {"drive_forward": drive_forward, "drive_side": drive_side,
                   "orbit_building": orbit_building, "orbit_block": orbit_block,
                   "nadir_grid": nadir_grid, "oblique_ring": oblique_ring, "video": video}


# ----------------------------------------------------------------------------------------------
# what refine is given: model level and details, GNSS, wrong models

def details_of(rng) -> dict:
    """The true scene's generalisation effects, drawn per block (simulate DetailOptions)."""
    return {"parapet_height": _u(rng, 0.3, 1.2, 2), "roof_overhang": _u(rng, 0.2, 0.8, 2),
            "roof_furniture_per_100m2": _u(rng, 0.5, 3.0, 2),
            "balcony_probability": _u(rng, 0.0, 0.25, 2), "window_depth": _u(rng, 0.05, 0.2, 2),
            "pilaster_depth": _u(rng, 0.0, 0.15, 2), "tree_spacing": _u(rng, 8.0, 30.0),
            "car_spacing": _u(rng, 10.0, 40.0)}


def model_errors_of(level: str, rng) -> dict:
    """ModelErrorOptions of a model level: "harsh" is "original" with larger face errors."""
    out = {}
    if level == "harsh":
        out = {"shift_sigma": _u(rng, 0.4, 0.7, 2), "rotation_sigma_deg": _u(rng, 1.0, 2.0, 2)}
    if rng.random() < MISSING_CHANCE:
        out["missing_buildings"] = 1
    if rng.random() < EXTRA_CHANCE:
        out["extra_buildings"] = 1
    return out


def gnss_of(model: str, rng) -> dict:
    """The simulator's [gnss] table of a GNSS model ("none": positions simulated but not given
    to refine)."""
    quiet = {"bias_sigma": [0.0, 0.0, 0.0], "bias_magnitude": 0.0}

    def white(lo, hi):
        w = _u(rng, lo, hi, 3)
        return [w, w, round(1.5 * w, 3)]

    if model == "white":
        return {"sigma": GNSS_SIGMA, "white_sigma": white(1.0, 3.0), **quiet}
    if model == "constant_bias":
        return {"sigma": GNSS_SIGMA, "white_sigma": white(0.3, 1.5), **quiet,
                "bias_magnitude": _u(rng, 1.0, 8.0, 2)}
    if model == "slow_bias":
        b = _u(rng, 2.0, 4.0, 2)
        return {"sigma": GNSS_SIGMA, "white_sigma": white(0.3, 1.0), "bias_sigma": [b, b, b],
                "bias_length": _u(rng, 100.0, 300.0, 0), "bias_magnitude": 0.0}
    if model == "jumps":
        return {"sigma": GNSS_SIGMA, "white_sigma": white(0.5, 2.0), **quiet,
                "outliers": int(rng.integers(2, 5)), "outlier_range": [10.0, 30.0],
                "step_magnitude": _u(rng, 2.0, 5.0, 2)}
    if model == "rtk":
        w = white(0.02, 0.05)
        return {"sigma": w, "white_sigma": w, **quiet}
    return {"sigma": GNSS_SIGMA, "white_sigma": white(1.0, 3.0), **quiet}  # "none"


def wrong_model_of(kind: str, model: TileModel, region, rng) -> dict:
    """The scenario options of a wrong model that still overlaps the block: "shifted" 10-40 m
    horizontally, "rotated" 3-20 deg about a point within 20 m of the block's centre,
    "neighbour" moved so that another part of the tile (a building 40-300 m away) lies where
    the block's buildings are (falls back to "shifted" when the tile has none)."""
    centre = np.array([region.centroid.x, region.centroid.y])
    if kind == "neighbour":
        shift = _neighbour_shift(model, region, centre, rng)
        if shift is not None:
            return {"kind": "neighbour", "model_shift": shift,
                    "size_m": round(float(np.hypot(*shift[:2])), 1)}
        kind = "shifted"
    if kind == "rotated":
        angle = float(rng.uniform(3.0, 20.0)) * (1 if rng.random() < 0.5 else -1)
        at = centre + rng.uniform(0.0, 20.0) * _direction(rng)
        return {"kind": "rotated", "model_turn_deg": round(angle, 2),
                "model_turn_centre": at.round(2).tolist(), "size_m": round(abs(angle), 2)}
    union = shapely.unary_union([b.footprint for b in model.buildings])
    for _ in range(50):  # a direction in which the moved buildings still meet the block
        size = float(rng.uniform(10.0, 40.0))
        shift = size * _direction(rng)
        if shapely.affinity.translate(union, *shift).intersects(region):
            break
    return {"kind": "shifted",
            "model_shift": [round(float(shift[0]), 2), round(float(shift[1]), 2), 0.0],
            "size_m": round(size, 1)}


def _direction(rng) -> np.ndarray:
    a = rng.uniform(0.0, 2.0 * math.pi)
    return np.array([math.cos(a), math.sin(a)])


def _neighbour_shift(model: TileModel, region, centre, rng) -> list[float] | None:
    here = min(model.buildings, key=lambda b: np.linalg.norm(b.centre - centre))
    others = [b for b in model.buildings if b.footprint.area >= 40.0
              and 40.0 <= np.linalg.norm(b.centre - here.centre) <= 300.0
              and not b.footprint.intersects(region)]
    if not others:
        return None
    other = others[int(rng.integers(len(others)))]
    shift = here.centre - other.centre
    return [round(float(shift[0]), 2), round(float(shift[1]), 2), 0.0]


# ----------------------------------------------------------------------------------------------
# drawing

def split_of(sim_seed: int) -> str:
    """The block's split: a hash of its simulation seed, never of anything it gives."""
    return SPLITS[hashlib.sha256(str(sim_seed).encode()).digest()[0] & 1]


def cycled(items, seed: int, split: str, what: str, k: int):
    """The k-th of `items` in a seeded random order that runs through all of them once per
    round: in any len(items) consecutive draws of a split, each item once."""
    r = k // len(items)
    order = np.random.default_rng([seed, zlib.crc32(f"{split}/{what}".encode()), r]).permutation(
        len(items))
    return items[int(order[k % len(items)])]


def draw_blocks(count: int, seed: int) -> list[dict]:
    """`count` blocks, count // 2 per split (dev first in each pair of the order they were
    drawn), deterministic for the seed."""
    want = {s: count // 2 + (count % 2 if s == "dev" else 0) for s in SPLITS}
    made: dict[str, list[dict]] = {s: [] for s in SPLITS}
    counters: dict[str, dict[str, int]] = {s: {} for s in SPLITS}
    i = 0
    while any(len(made[s]) < want[s] for s in SPLITS):
        rng = np.random.default_rng([seed, i])
        sim_seed = int(rng.integers(1, 2 ** 31 - 1))
        split = split_of(sim_seed)
        if len(made[split]) < want[split]:
            block = _draw_block(seed, i, sim_seed, split, counters[split], rng)
            made[split].append(block)
        i += 1
    return made["dev"] + made["held_out"]


def _next(counters: dict, key: str) -> int:
    counters[key] = counters.get(key, 0) + 1
    return counters[key] - 1


def _draw_block(seed: int, i: int, sim_seed: int, split: str, counters: dict, rng) -> dict:
    """One block of a split; its family, tile, GNSS model, model level, DTM and wrong model
    from the split's cycles, the rest from its own random stream."""
    family = cycled(FAMILIES, seed, split, "family", _next(counters, "family"))
    tiles = [t for t in TILES.values() if family in t.families]
    tile = cycled(tiles, seed, split, f"tile/{family}", _next(counters, f"tile/{family}"))
    num_buildings = int(rng.integers(6, 15))
    model = tile_model(tile, num_buildings, sim_seed)
    for _ in range(FAMILY_TRIES):  # e.g. a loop too short for the frames drawn
        drawn = FAMILY_BUILDERS[family](model, rng)
        if drawn is not None:
            break
    else:
        raise RuntimeError(f"{family} cannot be drawn on {tile.name}")
    flight, observations, street, region = drawn
    gnss_model = cycled(GNSS_MODELS, seed, split, "gnss", _next(counters, "gnss"))
    level = cycled(MODEL_LEVELS, seed, split, "level", _next(counters, "level"))
    terrain = cycled((True, False), seed, split, "terrain", _next(counters, "terrain"))
    wrong = None
    if gnss_model != "none" and cycled(WRONG_CYCLE, seed, split, "wrong",
                                       _next(counters, "wrong")):
        kind = cycled(WRONG_KINDS, seed, split, "wrong_kind", _next(counters, "wrong_kind"))
        wrong = wrong_model_of(kind, model, region, rng)
    hint = None
    if gnss_model == "none":
        hint = {"distance_m": _u(rng, *HINT_RANGE), "angle_deg": _u(rng, 0.0, 360.0)}
    scene = {k: v for k, v in tile.scene.items()}
    if tile.scene["source"] == "procedural":
        scene["procedural"] = {"num_buildings": num_buildings}
    return {"name": f"g{seed}-{i:03d}-{family}-{tile.name}", "index": i, "split": split,
            "family": family, "tile": tile.name, "city": tile.city, "format": tile.format,
            "gnss_model": gnss_model, "model": level, "terrain": terrain,
            "wrong_model": wrong is not None, "wrong": wrong, "hint": hint,
            "sim_seed": sim_seed,
            "toml": {"scene": scene, "flight": flight, "observations": observations,
                     "details": {**details_of(rng), **street},
                     "model_errors": model_errors_of(level, rng),
                     "gnss": gnss_of(gnss_model, rng)}}


def skipped_combinations() -> list[dict]:
    """Family and tile combinations left out, with the reason."""
    return [{"tile": t.name, "family": f, "why": why} for t in TILES.values()
            for f, why in t.skipped.items()]
