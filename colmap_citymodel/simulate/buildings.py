"""Whole-building errors of the given model (ModelErrorOptions.missing_buildings and
extra_buildings): an outdated or incomplete city model lacks a building the true scene has
(built after the survey) or has one the true scene lacks (demolished since). The true scene,
its terrain and the truth are made from the full model; only the given model's variants
(detailed, corrected, original) change."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import Polygon

from ..citymodel.build import build_store
from ..citymodel.raw_model import RawCityModel, RawPolygon
from ..citymodel.store import PlaneStore
from ..citymodel.write_citygml import raw_from_store
from .scenario import STAGE_BUILDINGS
from .scene import GroundModel, ModelErrorOptions, _box_building, building_footprints

logger = logging.getLogger(__name__)

#: Metres an extra box keeps from the true buildings' footprints (a street or a yard between).
EXTRA_CLEARANCE = 2.0
#: Metres an extra box keeps from every camera's ground position (no camera inside it).
EXTRA_CAMERA_CLEARANCE = 4.0
#: Placements tried per extra box before it is given up (logged).
EXTRA_TRIES = 300


@dataclass
class BuildingChanges:
    """What the given model lacks and adds: building ids, and the extra boxes' polygons
    (CRS coordinates, LOD2 surfaces with their semantics)."""

    missing: list[str] = field(default_factory=list)
    extra: list[str] = field(default_factory=list)
    extra_polygons: list[RawPolygon] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def __bool__(self) -> bool:
        return bool(self.missing or self.extra)

    def todict(self) -> dict:
        return {"missing": self.missing, "extra": self.extra, "notes": self.notes}


def building_changes(store: PlaneStore, centres: np.ndarray, view_dirs: np.ndarray,
                     max_distance: float, options: ModelErrorOptions, seed: int,
                     ground: GroundModel) -> BuildingChanges:
    """The buildings the given model lacks and the boxes it adds, drawn from the seed. `centres`
    (N, 3) and `view_dirs` (N, 3): the cameras (local) and their viewing directions."""
    rng = np.random.default_rng([seed, STAGE_BUILDINGS])
    changes = BuildingChanges()
    footprints = building_footprints(store)
    if options.missing_buildings:
        changes.missing = _missing(footprints, centres, max_distance, options.missing_buildings,
                                   rng, changes.notes)
    for k in range(options.extra_buildings):
        ring = _extra_footprint(footprints, centres, view_dirs, max_distance, options, rng,
                                [p for p in changes.extra_polygons])
        if ring is None:
            changes.notes.append(f"extra building {k}: no free place in view of the cameras")
            logger.warning("simulate: %s", changes.notes[-1])
            continue
        bid = f"EXTRA_{k}"
        height = float(rng.uniform(*options.extra_height_range))
        changes.extra.append(bid)
        changes.extra_polygons += _box_polygons(ring, height, ground, store.origin, bid)
    return changes


def _missing(footprints: dict[str, Polygon], centres: np.ndarray, max_distance: float,
             count: int, rng: np.random.Generator, notes: list[str]) -> list[str]:
    """`count` of the buildings whose footprint lies within max_distance of a camera (their
    order sorted, the draw from rng), at least one of them left in the model."""
    cameras = shapely.MultiPoint(centres[:, :2])
    near = sorted(b for b, fp in footprints.items() if fp.distance(cameras) < max_distance)
    take = min(count, len(near) - 1)
    if take < count:
        notes.append(f"{count} missing building(s) asked for, {max(take, 0)} left out: "
                     f"{len(near)} building(s) near the cameras and one must stay")
    if take <= 0:
        return []
    return sorted(near[i] for i in rng.choice(len(near), size=take, replace=False))


def _extra_footprint(footprints: dict[str, Polygon], centres: np.ndarray, view_dirs: np.ndarray,
                     max_distance: float, options: ModelErrorOptions, rng: np.random.Generator,
                     placed: list[RawPolygon]) -> np.ndarray | None:
    """A rectangle (4, 2) local xy on free ground in front of a camera (within 30 deg of its
    horizontal viewing direction, 8 m to 0.6 max_distance away; any direction for a camera
    looking straight down), clear of the buildings and of every camera; None when none fits."""
    taken = list(footprints.values()) + [Polygon(p.exterior[:, :2]) for p in placed
                                         if p.semantic == "GroundSurface"]
    blocked = shapely.unary_union(taken).buffer(EXTRA_CLEARANCE)
    cameras = shapely.MultiPoint(centres[:, :2])
    far = max(10.0, 0.6 * max_distance)
    for _ in range(EXTRA_TRIES):
        k = int(rng.integers(len(centres)))
        d = view_dirs[k, :2]
        heading = (math.atan2(d[1], d[0]) + rng.uniform(-0.5, 0.5) if np.hypot(*d) > 0.2
                   else rng.uniform(0, 2 * math.pi))
        r = rng.uniform(8.0, far)
        centre = centres[k, :2] + r * np.array([math.cos(heading), math.sin(heading)])
        w, l = rng.uniform(*options.extra_size_range, 2)
        yaw = rng.uniform(0.0, math.pi)
        rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        ring = np.array([[-w, -l], [w, -l], [w, l], [-w, l]]) / 2 @ rot.T + centre
        box = Polygon(ring)
        if box.intersects(blocked) or box.distance(cameras) < EXTRA_CAMERA_CLEARANCE:
            continue
        return ring
    return None


def _box_polygons(ring: np.ndarray, height: float, ground: GroundModel, origin: np.ndarray,
                  bid: str) -> list[RawPolygon]:
    """A flat-roofed box over the rectangle `ring` (local xy), standing on the lowest ground
    under its corners: its ground, wall and roof surfaces in CRS coordinates."""
    z0 = float(np.nanmin(ground(ring)))
    # the box built axis-aligned in the rectangle's own frame, then turned onto it
    u = (ring[1] - ring[0]) / np.linalg.norm(ring[1] - ring[0])
    v = np.array([-u[1], u[0]])
    w, l = np.linalg.norm(ring[1] - ring[0]), np.linalg.norm(ring[3] - ring[0])
    out = []
    for i, (rr, semantic) in enumerate(_box_building(0.0, w, 0.0, l, height, 0.0, "flat")):
        xy = ring[0] + rr[:, :1] * u + rr[:, 1:2] * v
        xyz = np.c_[xy, rr[:, 2] + z0] + origin
        out.append(RawPolygon(exterior=xyz, semantic=semantic, building_id=bid,
                              gml_id=f"{bid}_{i}"))
    return out


def given_store(store: PlaneStore, changes: BuildingChanges) -> PlaneStore:
    """The model with the missing buildings left out and the extra boxes added, in the same
    local frame (origin) as `store`; `store` itself when nothing changes."""
    if not changes:
        return store
    raw = raw_from_store(store)
    polygons = [p for p in raw.polygons if p.building_id not in set(changes.missing)]
    polygons += changes.extra_polygons
    return build_store(RawCityModel(raw.source, raw.format, raw.version, raw.crs, polygons,
                                    sorted({p.building_id for p in polygons}), raw.part_ids),
                       origin=store.origin)


def given_polygons(polygons: list[RawPolygon], changes: BuildingChanges,
                   origin: np.ndarray) -> list[RawPolygon]:
    """The detailed model's polygons (local) without the missing buildings and with the extra
    boxes (local)."""
    kept = [p for p in polygons if p.building_id not in set(changes.missing)]
    extra = [RawPolygon(exterior=p.exterior - origin, semantic=p.semantic,
                        building_id=p.building_id, gml_id=p.gml_id)
             for p in changes.extra_polygons]
    return kept + extra
