"""Exterior orientation of multi-head aerial cameras: GNSS/IMU exposures and a rig of heads,
turned into COLMAP camera poses (Mulder 4.2.1, eq. 4.3-4.5, with the conventions stated here).

Frames
------
- **World**: the model CRS's grid axes, x east, y north, z up (heights of the CRS), shifted by an
  origin (`local` frame) so that no coordinate has 6-7 digits.
- **Body**: the frame whose attitude the EO file gives.
  * attitude ``opk`` (photogrammetric omega, phi, kappa): the body frame is a photogrammetric
    camera frame, x right, y up (towards the top of the image), z backwards (the camera looks
    along -z); R_world_from_body = Rx(omega) Ry(phi) Rz(kappa) (rotations about the fixed world
    axes x, then y, then z applied to the body: X_world = C + R x_body). omega = phi = kappa = 0
    is a camera looking straight down with the top of its image to grid north.
  * attitude ``rpy`` (navigation roll, pitch, yaw / heading of an IMU): the body frame is x
    forward, y right, z down; R_world_from_body = T Rz(yaw) Ry(pitch) Rx(roll) with
    T = [[0, 1, 0], [1, 0, 0], [0, 0, -1]] (north-east-down to east-north-up). Yaw is the
    heading clockwise from north, pitch positive nose up, roll positive right side down.
- **Head**: each camera of the rig in photogrammetric axes (x right, y up, z backwards).
  ``lever_arm`` is the head's projection centre in the body frame (metres) and ``boresight``
  its omega, phi, kappa in degrees in the body frame: R_body_from_head = Rx(o) Ry(p) Rz(k).
  A head with zero lever arm and boresight is the body itself (the usual nadir head with
  ``opk``). With ``rpy`` a nadir head with the top of its image forward has boresight
  (180, 0, -90).
- **COLMAP camera**: x right, y down, z forward: R_cam_from_world = F R_world_from_head^T with
  F = diag(1, -1, -1), t = -R_cam_from_world C.

Positions. The EO position of an exposure is that of the GNSS antenna unless the rig's
``gnss_lever_arm`` is zero (the default: the position is the body origin itself, e.g. a
post-processed trajectory already reduced to the IMU or the reference camera). The antenna is at
``gnss_lever_arm`` in the body frame: body origin O = P - R_world_from_body a; head centre
C = O + R_world_from_body l (Mulder eq. 4.5).

Map projection. When the EO positions are geographic or in another projected CRS than the
model's, the positions are reprojected and the attitude is turned about the vertical by the
difference of the grid convergences (the angle between true and grid north of each CRS at the
exposure), so that the angles keep describing the same directions on the ground.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError

ATTITUDES = ("opk", "rpy")
#: COLMAP camera axes (x right, y down, z forward) from photogrammetric ones (x right, y up,
#: z backwards) and back (its own inverse).
FLIP = np.diag([1.0, -1.0, -1.0])
#: East-north-up from north-east-down.
ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: Default sigma (m) of EO positions without sigma columns: post-processed GNSS/IMU.
DEFAULT_EO_SIGMA = (0.05, 0.05, 0.10)


def _rx(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_opk(omega: float, phi: float, kappa: float) -> np.ndarray:
    """R_world_from_body = Rx(omega) Ry(phi) Rz(kappa), angles in degrees."""
    o, p, k = np.radians([omega, phi, kappa])
    return _rx(o) @ _ry(p) @ _rz(k)


def angles_opk(rotation: np.ndarray) -> np.ndarray:
    """(omega, phi, kappa) in degrees of R = Rx(omega) Ry(phi) Rz(kappa); phi in [-90, 90]."""
    r = np.asarray(rotation, float)
    phi = math.asin(max(-1.0, min(1.0, r[0, 2])))
    omega = math.atan2(-r[1, 2], r[2, 2])
    kappa = math.atan2(-r[0, 1], r[0, 0])
    return np.degrees([omega, phi, kappa])


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R_world(ENU)_from_body(x forward, y right, z down) = T Rz(yaw) Ry(pitch) Rx(roll)."""
    r, p, y = np.radians([roll, pitch, yaw])
    return ENU_FROM_NED @ _rz(y) @ _ry(p) @ _rx(r)


def angles_rpy(rotation: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) in degrees of `rotation_rpy`; pitch in [-90, 90], yaw in [0, 360)."""
    m = ENU_FROM_NED.T @ np.asarray(rotation, float)  # Rz(y) Ry(p) Rx(r)
    pitch = math.asin(max(-1.0, min(1.0, -m[2, 0])))
    roll = math.atan2(m[2, 1], m[2, 2])
    yaw = math.atan2(m[1, 0], m[0, 0])
    out = np.degrees([roll, pitch, yaw])
    out[2] %= 360.0
    return out


def body_rotation(angles: np.ndarray, attitude: str) -> np.ndarray:
    if attitude == "opk":
        return rotation_opk(*angles)
    if attitude == "rpy":
        return rotation_rpy(*angles)
    raise InputError(f"attitude must be one of {', '.join(ATTITUDES)}, not {attitude!r}")


def body_angles(rotation: np.ndarray, attitude: str) -> np.ndarray:
    return angles_opk(rotation) if attitude == "opk" else angles_rpy(rotation)


# -- the rig --------------------------------------------------------------------------------------

@dataclass
class Head:
    """One camera of a multi-head rig (see the module docstring for the frames)."""

    name: str
    image_name: str
    """Image name template; ``{exposure}`` is replaced by the exposure id of the EO file."""
    lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    boresight: np.ndarray = field(default_factory=lambda: np.zeros(3))
    camera: dict | None = None
    """COLMAP camera: {"model", "width", "height", "params"}; None: the camera the database
    already has for this head's images."""

    @property
    def body_from_head(self) -> np.ndarray:
        return rotation_opk(*self.boresight)

    def image(self, exposure: str) -> str:
        return self.image_name.replace("{exposure}", exposure)


@dataclass
class RigSpec:
    heads: list[Head]
    reference: int = 0
    """Index of the head that is COLMAP's reference sensor (its frame is the rig frame)."""
    gnss_lever_arm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """GNSS antenna in the body frame (m); zero: the EO positions are the body origin."""

    def cam_from_body(self, h: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of head h's COLMAP camera from the body frame."""
        head = self.heads[h]
        rotation = FLIP @ head.body_from_head.T
        return rotation, -rotation @ head.lever_arm

    def sensor_from_rig(self, h: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of head h from the reference head (COLMAP's rig frame)."""
        r_h, t_h = self.cam_from_body(h)
        r_r, t_r = self.cam_from_body(self.reference)
        rotation = r_h @ r_r.T
        return rotation, t_h - rotation @ t_r


def _vector(value, what: str, path) -> np.ndarray:
    try:
        out = np.asarray(value, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be three numbers, not {value!r}", path) from None
    if not np.all(np.isfinite(out)):
        raise InputError(f"{what} must be finite, not {value!r}", path)
    return out


def rig_from_dict(data: dict, path=None) -> RigSpec:
    """The rig from its JSON form::

        {"gnss_lever_arm": [x, y, z],                       (optional, m, body frame)
         "heads": [{"name": "nadir", "image_name": "{exposure}_N.jpg",
                    "lever_arm": [x, y, z], "boresight": [omega, phi, kappa],
                    "camera": {"model": "PINHOLE", "width": W, "height": H,
                               "params": [fx, fy, cx, cy]},      (optional)
                    "reference": true}, ...]}              (at most one; default: the first)
    """
    if not isinstance(data, dict) or not isinstance(data.get("heads"), list) or not data["heads"]:
        raise InputError("rig file needs a non-empty list 'heads'", path)
    unknown = set(data) - {"heads", "gnss_lever_arm"}
    if unknown:
        raise InputError(f"rig file: unknown key(s) {sorted(unknown)}", path)
    heads, reference = [], []
    for k, item in enumerate(data["heads"]):
        if not isinstance(item, dict):
            raise InputError(f"rig head {k} must be an object", path)
        unknown = set(item) - {"name", "image_name", "lever_arm", "boresight", "camera",
                               "reference"}
        if unknown:
            raise InputError(f"rig head {k}: unknown key(s) {sorted(unknown)}", path)
        name = str(item.get("name", f"head{k}"))
        template = item.get("image_name")
        if not isinstance(template, str) or "{exposure}" not in template:
            raise InputError(f"rig head {name!r}: 'image_name' must be a template containing "
                             "{exposure}", path)
        camera = item.get("camera")
        if camera is not None:
            if not isinstance(camera, dict) or not {"model", "width", "height",
                                                    "params"} <= set(camera):
                raise InputError(f"rig head {name!r}: 'camera' needs model, width, height, "
                                 "params", path)
        heads.append(Head(name, template,
                          _vector(item.get("lever_arm", [0, 0, 0]), f"{name} lever_arm", path),
                          _vector(item.get("boresight", [0, 0, 0]), f"{name} boresight", path),
                          camera))
        if item.get("reference"):
            reference.append(k)
    if len(reference) > 1:
        raise InputError("rig file: more than one head is the reference", path)
    names = [h.name for h in heads]
    if len(set(names)) != len(names):
        raise InputError("rig file: head names must be unique", path)
    templates = [h.image_name for h in heads]
    if len(set(templates)) != len(templates):
        raise InputError("rig file: image_name templates must differ between heads", path)
    return RigSpec(heads, reference[0] if reference else 0,
                   _vector(data.get("gnss_lever_arm", [0, 0, 0]), "gnss_lever_arm", path))


def read_rig(path) -> RigSpec:
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError("rig file does not exist", path) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(f"cannot read rig JSON: {error}", path) from None
    return rig_from_dict(data, path)


# -- exposures ------------------------------------------------------------------------------------

@dataclass
class Exposures:
    """One row per exposure of the EO file, in the EO file's CRS and attitude convention."""

    ids: list[str]
    positions: np.ndarray
    """(N, 3) in the EO CRS's axis order (geographic CRSs: latitude, longitude, height)."""
    angles: np.ndarray
    """(N, 3) degrees: omega, phi, kappa or roll, pitch, yaw."""
    sigmas: np.ndarray
    """(N, 3) metres, position sigmas."""
    attitude: str


_SPLIT = re.compile(r"[,;\s]+")


def read_eo(path, attitude: str = "opk", default_sigma=DEFAULT_EO_SIGMA) -> Exposures:
    """An EO text file: one exposure a line, ``exposure X Y Z A1 A2 A3 [sX sY sZ]``, separated
    by whitespace, commas or semicolons; angles in degrees (omega phi kappa or roll pitch yaw);
    lines starting with # and a header line (a non-numeric X) are skipped."""
    if attitude not in ATTITUDES:
        raise InputError(f"attitude must be one of {', '.join(ATTITUDES)}, not {attitude!r}")
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise InputError("EO file does not exist", path) from None
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"cannot read EO file: {error}", path) from None
    ids, rows, sigmas = [], [], []
    default = np.asarray(default_sigma, float).reshape(3)
    for number, line in enumerate(lines, 1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = [p for p in _SPLIT.split(text) if p]
        try:
            values = [float(v) for v in parts[1:]]
        except ValueError:
            if not rows and not ids:
                continue  # header
            raise InputError(f"line {number}: expected exposure X Y Z A1 A2 A3 [sX sY sZ]",
                             path) from None
        if len(values) not in (6, 9):
            raise InputError(f"line {number}: expected 7 or 10 columns, found {len(parts)}",
                             path)
        if not all(math.isfinite(v) for v in values):
            raise InputError(f"line {number}: values must be finite", path)
        sigma = np.asarray(values[6:9], float) if len(values) == 9 else default
        if np.any(sigma <= 0):
            raise InputError(f"line {number}: sigmas must be positive", path)
        ids.append(parts[0])
        rows.append(values[:6])
        sigmas.append(sigma)
    if not rows:
        raise InputError("EO file holds no exposure", path)
    if len(set(ids)) != len(ids):
        raise InputError("EO file: exposure ids must be unique", path)
    rows = np.asarray(rows, float)
    return Exposures(ids, rows[:, :3], rows[:, 3:], np.asarray(sigmas, float), attitude)


# -- poses ---------------------------------------------------------------------------------------

@dataclass
class BlockPoses:
    """Camera poses of every (exposure, head) in the local frame of the model CRS."""

    exposure_ids: list[str]
    body_rotations: np.ndarray
    """(E, 3, 3) R_world_from_body (model CRS grid axes)."""
    antenna: np.ndarray
    """(E, 3) EO positions in the local frame."""
    cam_rotations: np.ndarray
    """(E, H, 3, 3) COLMAP R_cam_from_world per exposure and head."""
    centres: np.ndarray
    """(E, H, 3) projection centres in the local frame."""


def block_poses(rig: RigSpec, exposure_ids: list[str], antenna_local: np.ndarray,
                body_rotations: np.ndarray) -> BlockPoses:
    """Projection centres and COLMAP rotations of every head at every exposure."""
    antenna_local = np.asarray(antenna_local, float).reshape(-1, 3)
    body_rotations = np.asarray(body_rotations, float).reshape(-1, 3, 3)
    origin = antenna_local - np.einsum("eij,j->ei", body_rotations, rig.gnss_lever_arm)
    num_heads = len(rig.heads)
    centres = np.empty((len(origin), num_heads, 3))
    rotations = np.empty((len(origin), num_heads, 3, 3))
    for h, head in enumerate(rig.heads):
        centres[:, h] = origin + np.einsum("eij,j->ei", body_rotations, head.lever_arm)
        world_from_head = body_rotations @ head.body_from_head
        rotations[:, h] = FLIP @ np.transpose(world_from_head, (0, 2, 1))
    return BlockPoses(list(exposure_ids), body_rotations, antenna_local, rotations, centres)


def exposure_from_reference(rig: RigSpec, cam_rotation: np.ndarray, centre: np.ndarray
                            ) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of `block_poses` for one exposure: (R_world_from_body, antenna position) from the
    reference head's COLMAP rotation (cam_from_world) and projection centre."""
    head = rig.heads[rig.reference]
    world_from_head = (FLIP @ np.asarray(cam_rotation, float)).T
    world_from_body = world_from_head @ head.body_from_head.T
    origin = np.asarray(centre, float) - world_from_body @ head.lever_arm
    return world_from_body, origin + world_from_body @ rig.gnss_lever_arm


def grid_north_azimuth(crs, easting: np.ndarray, northing: np.ndarray) -> np.ndarray:
    """Degrees, clockwise from grid north, of true north at each point of a projected CRS (its
    grid convergence; 0 for a geographic CRS), by projecting a 1 m step north."""
    import pyproj

    crs = pyproj.CRS.from_user_input(crs)
    horizontal = crs.sub_crs_list[0] if crs.is_compound else crs
    if not horizontal.is_projected:
        return np.zeros(len(np.atleast_1d(easting)))
    geographic = horizontal.geodetic_crs
    forward = pyproj.Transformer.from_crs(geographic, horizontal, always_xy=True)
    inverse = pyproj.Transformer.from_crs(horizontal, geographic, always_xy=True)
    lon, lat = inverse.transform(np.atleast_1d(easting), np.atleast_1d(northing))
    step = 1.0 / 111_000.0
    e1, n1 = forward.transform(lon, lat)
    e2, n2 = forward.transform(lon, np.asarray(lat) + step)
    return np.degrees(np.arctan2(np.asarray(e2) - e1, np.asarray(n2) - n1))
