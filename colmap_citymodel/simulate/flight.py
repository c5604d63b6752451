"""Flights of the simulator: camera centres and orientations along a street (sideways or
forward looking), along waypoints (a mapping flight's strips, pitch 90 deg: a nadir camera)
or on an orbit around one building."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .scenario import STAGE_FLIGHT, FlightOptions
from .scene import GroundModel, building_footprints


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
        """Pixel coordinates (COLMAP convention) and depth of local points in key frame k.

        A barrel-distorting lens (k1 < 0) maps radius r to r (1 + k1 r^2), which turns back
        beyond r^2 = 1 / (3 |k1|): points that far off the axis (76 deg for k1 = -0.02) would
        fold back into the image although no pixel sees them; their pixel coordinates are
        NaN."""
        Xc = (X - self.centres[k]) @ self.rotations[k].T
        z = Xc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            n = Xc[:, :2] / z[:, None]
            if self.k1:
                r2 = np.sum(n * n, axis=1, keepdims=True)
                n = n * (1.0 + self.k1 * r2)
                if self.k1 < 0:
                    n[r2[:, 0] >= 1.0 / (3.0 * -self.k1)] = np.nan
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
    jitter[1] and rolled by jitter[2] (rad). The image's x axis is the heading's right, also
    for a nadir camera (pitch 90 deg: the image's top points along the heading)."""
    pitch = math.radians(pitch_deg) + jitter[1]
    fwd = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch),
                    -math.sin(pitch)])
    x = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    y = np.cross(fwd, x)
    roll = jitter[2]
    if roll:
        x, y = math.cos(roll) * x + math.sin(roll) * y, -math.sin(roll) * x + math.cos(roll) * y
    return np.stack([x, y, fwd])


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
