"""What the rendered JPEGs carry besides their pixels, as a drone writes it: EXIF (make, focal
length, time, GPS position from the simulated GNSS) and DJI's XMP (drone-dji: position,
absolute and relative altitude, gimbal and flight attitude, RTK flag and standard deviations,
calibrated focal length); and the check-point targets' image positions as OpenDroneMap's
`gcp_list.txt`.

Conventions (those of DJI's XMP): angles in degrees; yaw clockwise from true north (-180..180],
pitch 0 at the horizon and -90 looking straight down, roll about the viewing direction; the
gimbal angles are the camera's attitude, Z-Y-X (yaw, pitch, roll) Euler angles of the camera
(x forward along the optical axis, y to the image's right, z to its bottom) in north-east-down.
Altitudes are heights in the city model's height system (EXIF's "above sea level");
RelativeAltitude is above the ground under the first key frame (the take-off point).
"""

from __future__ import annotations

import datetime as dt
import math
from dataclasses import dataclass

import numpy as np

from ...errors import InputError

#: Sensor width (mm) assumed for the EXIF focal length in millimetres: a 1" sensor.
SENSOR_WIDTH_MM = 13.2
#: Diagonal of a 35 mm film frame (36 x 24 mm), for FocalLengthIn35mmFilm.
FILM_DIAGONAL_MM = math.hypot(36.0, 24.0)
#: Time of the first exposure (EXIF DateTimeOriginal) and the interval between key frames.
START_TIME = dt.datetime(2024, 6, 15, 9, 0, 0)
INTERVAL_S = 2.0
#: DJI's RtkFlag values: 50 a fixed RTK solution, 0 none (a single-point GNSS fix).
RTK_FIXED, RTK_NONE = 50, 0


@dataclass
class RenderedTags:
    """What the renderer writes into one image's EXIF and XMP (block.image_metadata reads it)."""

    name: str
    index: int
    latitude: float  # degrees
    longitude: float
    altitude: float  # m, the model's height system
    relative_altitude: float  # m above the take-off point
    gimbal: tuple[float, float, float]  # yaw, pitch, roll (deg)
    flight: tuple[float, float, float]
    sigma: tuple[float, float, float]  # stated GNSS sigma E, N, U (m)
    rtk: bool


def geographic(crs, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Latitude, longitude (deg) and the grid azimuth of true north (deg, clockwise from the
    grid's north) at model-CRS points `xy` (N,2)."""
    import pyproj

    if not crs.horizontal_epsg:
        raise InputError("rendering writes EXIF GPS: the city model's CRS needs an EPSG code "
                         f"(it is {crs.label})")
    to_geo = pyproj.Transformer.from_crs(f"EPSG:{crs.horizontal_epsg}", "EPSG:4326",
                                         always_xy=True)
    to_grid = pyproj.Transformer.from_crs("EPSG:4326", f"EPSG:{crs.horizontal_epsg}",
                                          always_xy=True)
    lon, lat = to_geo.transform(xy[:, 0], xy[:, 1])
    step = 1e-5  # deg of latitude (about 1 m)
    x1, y1 = to_grid.transform(lon, lat + step)
    north = np.degrees(np.arctan2(x1 - xy[:, 0], y1 - xy[:, 1]))
    return np.asarray(lat), np.asarray(lon), north


def dji_angles(cam_from_world: np.ndarray, north_azimuth: float) -> tuple[float, float, float]:
    """Gimbal yaw, pitch, roll (deg) of a camera (COLMAP cam_from_world rotation in the local
    east-north-up grid) whose grid's true north lies at `north_azimuth` (deg clockwise from
    grid north). Beyond the nadir (pitch below -90) the yaw stays the camera's heading and the
    pitch continues past -90, as a gimbal tilted over writes it."""
    x_cam, y_cam, z_cam = np.asarray(cam_from_world, dtype=np.float64)
    enu_to_ned = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    # columns: the gimbal's forward, right, down axes in north-east-down
    m = enu_to_ned @ np.stack([z_cam, x_cam, y_cam], axis=1)
    yaw = math.atan2(m[1, 0], m[0, 0])
    pitch = math.asin(max(-1.0, min(1.0, -m[2, 0])))
    roll = math.atan2(m[2, 1], m[2, 2])
    if abs(roll) > math.pi / 2:  # the equivalent angles with |roll| < 90 deg
        yaw += math.pi
        pitch = -math.pi - pitch
        roll -= math.copysign(math.pi, roll)
    yaw = math.degrees(yaw) - north_azimuth
    yaw = (yaw + 180.0) % 360.0 - 180.0
    return yaw, math.degrees(pitch), math.degrees(roll)


def _dms(value: float) -> tuple[float, float, float]:
    value = abs(value)
    degrees = math.floor(value)
    minutes = math.floor((value - degrees) * 60.0)
    seconds = (value - degrees - minutes / 60.0) * 3600.0
    return float(degrees), float(minutes), round(seconds, 6)


def exif_bytes(meta: RenderedTags, width: int, height: int, focal_px: float) -> bytes:
    """The EXIF block of one image (Pillow): make, model, time, focal length, GPS."""
    from fractions import Fraction

    from PIL import Image
    from PIL.TiffImagePlugin import IFDRational

    def rational(value: float, denominator: int = 10**6) -> IFDRational:
        f = Fraction(value).limit_denominator(denominator)
        return IFDRational(f.numerator, f.denominator)

    exif = Image.Exif()
    exif[0x010F] = "DJI"  # Make: DJI XMP readers look at it
    exif[0x0110] = "SIMULATED"  # Model
    exif[0x0131] = "colmap-citymodel simulate --render"  # Software
    sub = exif.get_ifd(0x8769)
    taken = START_TIME + dt.timedelta(seconds=INTERVAL_S * meta.index)
    sub[0x9003] = taken.strftime("%Y:%m:%d %H:%M:%S")  # DateTimeOriginal
    sub[0x920A] = rational(focal_px * SENSOR_WIDTH_MM / width, 1000)
    # 35 mm equivalent: the same angle of view over the diagonal (43.27 mm on 35 mm film)
    sub[0xA405] = int(round(focal_px * FILM_DIAGONAL_MM / math.hypot(width, height)))
    sub[0xA002], sub[0xA003] = width, height
    gps = exif.get_ifd(0x8825)
    gps[0x0000] = b"\x02\x03\x00\x00"  # GPSVersionID 2.3
    gps[0x0001] = "N" if meta.latitude >= 0 else "S"
    gps[0x0002] = tuple(rational(v) for v in _dms(meta.latitude))
    gps[0x0003] = "E" if meta.longitude >= 0 else "W"
    gps[0x0004] = tuple(rational(v) for v in _dms(meta.longitude))
    gps[0x0005] = 0 if meta.altitude >= 0 else 1  # above / below sea level
    gps[0x0006] = rational(abs(meta.altitude), 1000)
    return exif.tobytes()


def xmp_bytes(meta: RenderedTags, width: int, height: int, focal_px: float) -> bytes:
    """DJI's XMP packet (attributes of one rdf:Description, as DJI's cameras write it)."""
    gy, gp, gr = meta.gimbal
    fy, fp, fr = meta.flight
    fields = {
        "GpsStatus": "RTK" if meta.rtk else "Normal",
        "AltitudeType": "RtkAlt" if meta.rtk else "GpsFusionAlt",
        "GpsLatitude": f"{meta.latitude:+.9f}", "GpsLongitude": f"{meta.longitude:+.9f}",
        "AbsoluteAltitude": f"{meta.altitude:+.3f}",
        "RelativeAltitude": f"{meta.relative_altitude:+.3f}",
        "GimbalRollDegree": f"{gr:+.2f}", "GimbalYawDegree": f"{gy:+.2f}",
        "GimbalPitchDegree": f"{gp:+.2f}", "FlightRollDegree": f"{fr:+.2f}",
        "FlightYawDegree": f"{fy:+.2f}", "FlightPitchDegree": f"{fp:+.2f}",
        "RtkFlag": str(RTK_FIXED if meta.rtk else RTK_NONE),
    }
    if meta.rtk:
        fields.update(RtkStdLon=f"{meta.sigma[0]:.5f}", RtkStdLat=f"{meta.sigma[1]:.5f}",
                      RtkStdHgt=f"{meta.sigma[2]:.5f}")
    fields.update(CalibratedFocalLength=f"{focal_px:.6f}",
                  CalibratedOpticalCenterX=f"{width / 2:.6f}",
                  CalibratedOpticalCenterY=f"{height / 2:.6f}")
    taken = START_TIME + dt.timedelta(seconds=INTERVAL_S * meta.index)
    attributes = "\n".join(f'   drone-dji:{k}="{v}"' for k, v in fields.items())
    text = (
        '<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n'
        '<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
        ' <rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
        '  <rdf:Description rdf:about="DJI Meta Data"\n'
        '    xmlns:tiff="http://ns.adobe.com/tiff/1.0/"\n'
        '    xmlns:xmp="http://ns.adobe.com/xap/1.0/"\n'
        '    xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"\n'
        f'   xmp:CreateDate="{taken.isoformat()}"\n'
        '   tiff:Make="DJI"\n'
        '   tiff:Model="SIMULATED"\n'
        f"{attributes}>\n"
        "  </rdf:Description>\n"
        " </rdf:RDF>\n"
        "</x:xmpmeta>\n"
        '<?xpacket end="w"?>')
    return text.encode("utf-8")


def write_gcp_list(path, crs, origin: np.ndarray, targets, observations, names) -> int:
    """OpenDroneMap's gcp_list.txt: the CRS on the first line, then per target seen in an
    image `geo_x geo_y geo_z im_x im_y image_name gcp_name`: model-CRS coordinates and pixel
    coordinates as OpenSfM reads them (the top-left pixel's centre is 0, 0; COLMAP's
    convention minus half a pixel). Returns the number of lines written."""
    by_id = {int(i): c for i, c in zip(targets.ids, targets.centres)}
    header = f"EPSG:{crs.horizontal_epsg}" if crs.horizontal_epsg else crs.wkt.replace("\n", " ")
    lines = [header]
    for frame, tid, uv in observations:
        x, y, z = by_id[tid] + origin
        lines.append(f"{x:.4f} {y:.4f} {z:.4f} {uv[0] - 0.5:.3f} {uv[1] - 0.5:.3f} "
                     f"{names[frame]} cp{tid}")
    path.write_text("\n".join(lines) + "\n")
    return len(lines) - 1
